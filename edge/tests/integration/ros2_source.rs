//! `ros2:/TOPIC` against a publisher on loopback: what the subscription announces, the scans it
//! gives, and what it does with samples that are not PointCloud2 messages. (The independent peer's
//! check of the wire is tests/tests/ros2.rs.)

use std::sync::mpsc;
use std::time::{Duration, Instant};

use bus::Network;
use bus::ros2::Ros2Node;
use edge::recording::RecordingOptions;
use edge::source::{Source, SourceError, SourceScan, SourceSpec};
use proto::ros2::keys::{Qos, TopicName, topic_key};
use proto::ros2::messages::{Header, PointCloud2, StringMessage, Time, xyzi_cloud};
use proto::ros2::{POINT_CLOUD2, STRING};
use sim::SimConfig;

/// A source read on a thread of its own, one item per call: a scan that never comes fails the
/// test after a while instead of hanging it.
struct Reader {
    ask: mpsc::Sender<()>,
    items: mpsc::Receiver<Option<Result<SourceScan, SourceError>>>,
}

impl Reader {
    fn new(mut source: Source) -> Reader {
        let (ask, asked) = mpsc::channel::<()>();
        let (give, items) = mpsc::channel();
        std::thread::spawn(move || {
            while asked.recv().is_ok() {
                if give.send(source.next()).is_err() {
                    break;
                }
            }
        });
        Reader { ask, items }
    }

    fn next(&mut self) -> Option<Result<SourceScan, SourceError>> {
        self.ask.send(()).unwrap();
        self.items.recv_timeout(Duration::from_secs(30)).expect("no item from the source within 30 s")
    }
}

fn cloud(scan: usize) -> PointCloud2 {
    let rows = (0..500).map(move |i| {
        let a = i as f32 * 0.0125;
        ([10.0 * a.cos(), 10.0 * a.sin(), scan as f32 * 0.1, i as f32], Vec::new())
    });
    xyzi_cloud(Header { stamp: Time { sec: 100 + scan as i32, nanosec: 0 }, frame_id: "lidar".into() }, &[], rows)
}

#[test]
fn a_ros2_topic_gives_its_clouds_as_scans_and_skips_what_is_not_one() {
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
    let port = bus::free_port().unwrap();
    let session = runtime.block_on(Network::loopback_ports(&[port], &[]).open()).unwrap();
    let topic = TopicName::new("/lidar/points").unwrap();
    let node = runtime.block_on(Ros2Node::new(&session, 7, "/", "driver")).unwrap();
    let points = runtime.block_on(node.publisher::<PointCloud2>(&topic, POINT_CLOUD2, Qos::DEFAULT)).unwrap();
    let strings = runtime.block_on(node.publisher::<StringMessage>(&topic, STRING, Qos::DEFAULT)).unwrap();

    let spec: SourceSpec = "ros2:/lidar/points".parse().unwrap();
    assert_eq!(spec.to_string(), "ros2:/lidar/points");
    let spec = spec.on_network(Network::loopback_ports(&[], &[port]), 7);
    let source = Source::open(&spec, Some(7), &SimConfig::default(), &RecordingOptions::default()).unwrap();
    let mut source = Reader::new(source);

    // The subscription is announced as rmw_zenoh announces one, in domain 7.
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let tokens = runtime.block_on(async {
            let replies = session.liveliness().get("@ros2_lv/7/**").await.unwrap();
            let mut keys = Vec::new();
            while let Ok(reply) = replies.recv_async().await {
                if let Ok(sample) = reply.result() {
                    keys.push(sample.key_expr().to_string());
                }
            }
            keys
        });
        let wanted = format!("/MS/%/%/emr_edge_source/%lidar%points/{}/{}/", POINT_CLOUD2.dds, POINT_CLOUD2.hash);
        if tokens.iter().any(|t| t.contains(&wanted)) {
            break;
        }
        assert!(Instant::now() < deadline, "no subscription token among {tokens:?}");
        std::thread::sleep(Duration::from_millis(100));
    }

    let put = |message: &PointCloud2| runtime.block_on(points.put(message)).unwrap();
    put(&cloud(0));
    let first = source.next().unwrap().unwrap();
    assert_eq!((first.index, first.stamp, first.cloud.len()), (0, 100.0, 500));
    assert_eq!(first.cloud.intensity.as_ref().unwrap()[499], 499.0);

    // Another type on the same topic is not a scan; a payload that is not CDR is a scan that
    // could not be read (skipped, the source goes on).
    runtime.block_on(async {
        strings.put(&StringMessage { data: "not a cloud".into() }).await.unwrap();
        session.put(topic_key(7, &topic, &POINT_CLOUD2), vec![0u8, 1, 0, 0, 42]).await.unwrap();
    });
    let damaged = source.next().unwrap();
    assert!(matches!(&damaged, Err(e @ SourceError::Ros2Message { index: 1, .. }) if !e.is_fatal()), "{damaged:?}");

    // Four scans while the odometry is busy: two wait in the queue, two are dropped whole and
    // counted with the next scan taken, which keeps its place on the topic.
    for scan in 2..6 {
        put(&cloud(scan));
    }
    std::thread::sleep(Duration::from_millis(500));
    let queued: Vec<_> = (0..2).map(|_| source.next().unwrap().unwrap()).collect();
    assert_eq!(queued.iter().map(|s| (s.index, s.dropped_before)).collect::<Vec<_>>(), [(2, 0), (3, 0)]);
    put(&cloud(6));
    let after = source.next().unwrap().unwrap();
    assert_eq!((after.index, after.dropped_before, after.stamp, after.cloud.points[0].z), (6, 2, 106.0, 0.6));
    // The limit counts the topic's scans, dropped ones too.
    assert!(source.next().is_none(), "the limit of 7 scans ends the source");
}
