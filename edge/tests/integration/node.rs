//! `edge::node` on loopback: a node on robot 1 of the simulated warehouse, a second session as the
//! station (subscriber and backfill asker), and `emr-edge run` as a process.

use std::collections::BTreeMap;
use std::time::Duration;

use bus::Network;
use edge::node::{self, NodeConfig, NodeError, NodeSummary, Rate};
use edge::wire;
use prost::Message;
use proto::{Fleet, KeyframeRequest, keyexpr};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use zenoh::Session;
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::query::ConsolidationMode;
use zenoh::sample::Sample;

/// How long the keyframe stream must be silent before a lingering node's source counts as done.
/// Only a guess: every test that relies on it checks the final summary against what it saw.
const QUIET: Duration = Duration::from_secs(2);

/// A node running in the background, and the station-side session watching it.
struct Running {
    fleet: Fleet,
    client: Session,
    keyframes: Subscriber<FifoChannelHandler<Sample>>,
    stop: Option<oneshot::Sender<()>>,
    node: JoinHandle<Result<NodeSummary, NodeError>>,
}

fn config(fleet: &str, frames: Option<usize>) -> NodeConfig {
    let source = "sim:warehouse-small:1".parse().unwrap();
    NodeConfig { max_frames: frames, rate: Rate::Max, ..NodeConfig::new(Fleet::new(fleet).unwrap(), 1, source) }
}

/// Starts `config`'s node on its own loopback port, with a subscriber already declared.
async fn start(config: NodeConfig) -> Running {
    let port = bus::free_port().unwrap();
    let session = Network::loopback_ports(&[port], &[]).open().await.unwrap();
    let client = Network::loopback_ports(&[], &[port]).open().await.unwrap();
    let fleet = config.fleet.clone();
    let keyframes = client.declare_subscriber(keyexpr::keyframe(&fleet, 1)).await.unwrap();
    let (stop, stopped) = oneshot::channel::<()>();
    let node = tokio::spawn(async move {
        node::run(&session, config, async {
            let _ = stopped.await;
        })
        .await
    });
    Running { fleet, client, keyframes, stop: Some(stop), node }
}

impl Running {
    /// The next published keyframe's payload, or `None` after `wait` without one.
    async fn next(&self, wait: Duration) -> Option<Vec<u8>> {
        let sample = tokio::time::timeout(wait, self.keyframes.recv_async()).await.ok()?.ok()?;
        Some(sample.payload().to_bytes().to_vec())
    }

    /// Published payloads by seq, until none came for `quiet`.
    async fn collect(&self, quiet: Duration, into: &mut BTreeMap<u64, Vec<u8>>) {
        while let Some(payload) = self.next(quiet).await {
            let seq = proto::Keyframe::decode(payload.as_slice()).unwrap().seq;
            assert!(into.insert(seq, payload).is_none(), "keyframe {seq} published twice");
        }
    }

    /// Sends a raw request to the keyframe store: the replied payloads, and the error replies.
    async fn ask(&self, payload: Vec<u8>) -> (Vec<Vec<u8>>, Vec<String>) {
        let replies = self
            .client
            .get(keyexpr::keyframe_store(&self.fleet, 1))
            .payload(payload)
            // Every reply carries the store's key: the default consolidation would keep only one.
            .consolidation(ConsolidationMode::None)
            .timeout(Duration::from_secs(10))
            .await
            .unwrap();
        let (mut ok, mut err) = (vec![], vec![]);
        while let Ok(reply) = replies.recv_async().await {
            match reply.result() {
                Ok(sample) => ok.push(sample.payload().to_bytes().to_vec()),
                Err(e) => err.push(String::from_utf8_lossy(&e.payload().to_bytes()).into_owned()),
            }
        }
        (ok, err)
    }

    /// The seqs and payloads a request gets back.
    async fn request(&self, seqs: &[u64], from_seq: Option<u64>) -> BTreeMap<u64, Vec<u8>> {
        let request = KeyframeRequest { seqs: seqs.to_vec(), from_seq, limit: None, session: None };
        let (ok, err) = self.ask(request.encode_to_vec()).await;
        assert!(err.is_empty(), "{err:?}");
        let decoded = ok.into_iter().map(|p| (proto::Keyframe::decode(p.as_slice()).unwrap().seq, p));
        decoded.collect()
    }

    /// Receives until `n` keyframes are in.
    async fn collect_into(&self, n: u64, into: &mut BTreeMap<u64, Vec<u8>>) {
        while (into.len() as u64) < n {
            let payload = self.next(Duration::from_secs(60)).await.expect("every keyframe arrives");
            let seq = proto::Keyframe::decode(payload.as_slice()).unwrap().seq;
            into.insert(seq, payload);
        }
    }

    /// Fires the shutdown future.
    fn stop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }

    /// The node's summary, once it returns (within `limit`).
    async fn finish(&mut self, limit: Duration) -> NodeSummary {
        tokio::time::timeout(limit, &mut self.node).await.expect("the node returns in time").unwrap().unwrap()
    }

    /// Fires the shutdown future and returns the node's summary.
    async fn shut_down(mut self) -> NodeSummary {
        self.stop();
        self.finish(Duration::from_secs(20)).await
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_keyframe_arrives_with_the_pose_of_its_scan() {
    let mut running = start(NodeConfig { linger: false, ..config("fleet-a", Some(60)) }).await;
    let summary = running.finish(Duration::from_secs(120)).await;
    let n = summary.keyframes;
    assert_eq!(summary.frames, 60);
    assert!(n >= 3, "only {n} keyframes in 60 scans");
    let mut got = BTreeMap::new();
    running.collect_into(n, &mut got).await;
    assert_eq!(got.keys().copied().collect::<Vec<_>>(), (0..n).collect::<Vec<_>>());
    assert_eq!(got.values().map(|p| p.len() as u64).sum::<u64>(), summary.published_bytes);
    // What the node counts as held: every keyframe it made, in the store, none left on the way.
    let held = summary.held;
    assert_eq!((held.made, held.store, held.in_flight), (n, summary.published_bytes, 0), "{held:?}");
    let mut loop_bound = 0;
    for payload in got.values() {
        let msg = proto::Keyframe::decode(payload.as_slice()).unwrap();
        assert_eq!((msg.fleet.as_str(), msg.robot), ("fleet-a", 1));
        let (pose, cloud) = wire::keyframe_cloud(&msg).unwrap();
        assert!(!cloud.is_empty(), "keyframe {} has no points", msg.seq);
        assert_eq!(msg.cloud.as_ref().unwrap().points, cloud.len() as u64);
        let context = msg.scan_context.as_ref().expect("a descriptor");
        // The loop closure's share: at most the positions and the descriptor (keys, cells and a flag each).
        loop_bound +=
            12 * cloud.len() as u64 + context.cells.len() as u64 * 5 + 4 * u64::from(context.rings + context.sectors);
        let stamp = msg.stamp.unwrap().as_secs_f64();
        let frame = summary.stamps.iter().position(|s| (s - stamp).abs() < 1e-6).expect("a scan with its stamp");
        assert_eq!(pose, summary.poses[frame], "keyframe {} vs scan {frame}", msg.seq);
    }
    assert!(summary.ground_truth.iter().all(Option::is_some));
    assert!(held.loops > 0 && held.loops <= loop_bound, "{held:?}: the loop closure holds more than {loop_bound}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn backfill_replies_with_the_listed_and_the_trailing_keyframes() {
    let running = start(config("fleet-b", Some(60))).await;
    let mut published = BTreeMap::new();
    running.collect(QUIET, &mut published).await;
    let n = published.len() as u64;
    assert!(n >= 5, "only {n} keyframes in 60 scans");
    let replied = running.request(&[1, 3], Some(n - 2)).await;
    assert_eq!(replied.keys().copied().collect::<Vec<_>>(), vec![1, 3, n - 2, n - 1]);
    for (seq, payload) in &replied {
        assert_eq!(payload, &published[seq], "keyframe {seq} replied differs from the published one");
    }
    // Seqs not produced yet are simply not replied.
    assert!(running.request(&[n, n + 5], Some(n + 1)).await.is_empty());
    let summary = running.shut_down().await;
    assert_eq!(summary.keyframes, n, "the stream was silent for {QUIET:?} before the source ended");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_garbage_request_gets_an_error_and_the_node_keeps_serving() {
    let running = start(config("fleet-c", Some(60))).await;
    let first = running.next(Duration::from_secs(60)).await.expect("keyframe 0 is published");
    // A truncated varint: no protobuf message decodes from it.
    let (ok, err) = running.ask(vec![0xff, 0xff, 0xff, 0xff]).await;
    assert!(ok.is_empty());
    assert_eq!(err.len(), 1);
    assert!(err[0].contains("malformed KeyframeRequest"), "{}", err[0]);
    let replied = running.request(&[0], None).await;
    assert_eq!(replied.into_iter().collect::<Vec<_>>(), vec![(0, first)]);
    running.shut_down().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_small_store_evicts_the_oldest_keyframes() {
    let running = start(NodeConfig { store_bytes: 1, ..config("fleet-d", Some(60)) }).await;
    let mut published = BTreeMap::new();
    running.collect(QUIET, &mut published).await;
    let n = published.len() as u64;
    assert!(n >= 3, "only {n} keyframes in 60 scans");
    // One byte holds no keyframe: only the newest is kept.
    assert!(running.request(&[0, 1, n - 2], None).await.is_empty());
    let replied = running.request(&[], Some(0)).await;
    assert_eq!(replied.into_iter().collect::<Vec<_>>(), vec![(n - 1, published[&(n - 1)].clone())]);
    let summary = running.shut_down().await;
    assert_eq!(summary.keyframes, n, "the stream was silent for {QUIET:?} before the source ended");
    // It holds what it keeps: the newest keyframe alone.
    assert_eq!((summary.held.store, summary.held.in_flight), (published[&(n - 1)].len() as u64, 0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_mid_run_flushes_and_returns_promptly() {
    let mut running = start(config("fleet-e", None)).await;
    let mut published = BTreeMap::new();
    running.collect_into(3, &mut published).await;
    let asked = std::time::Instant::now();
    running.stop();
    let summary = running.finish(Duration::from_secs(10)).await;
    let waited = asked.elapsed();
    assert!(waited < Duration::from_secs(3), "took {waited:?} to stop");
    assert!(summary.frames < 1000, "{} scans: the source was not stopped", summary.frames);
    assert_eq!((summary.poses.len(), summary.stamps.len()), (summary.frames, summary.frames));
    // Flushed: every keyframe the summary counts was published.
    running.collect_into(summary.keyframes, &mut published).await;
    assert_eq!(published.keys().copied().collect::<Vec<_>>(), (0..summary.keyframes).collect::<Vec<_>>());
}

#[test]
fn run_on_a_missing_recording_fails_naming_it() {
    let port = bus::free_port().unwrap().to_string();
    let listen = format!("tcp/127.0.0.1:{port}");
    let missing = "/nonexistent/emr-edge-test/scans";
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_emr-edge"))
        .args(["run", "--fleet", "f", "--robot", "1", "--source", missing, "--listen", &listen])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains(missing), "{stderr}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_closed_loop_publishes_the_pose_graph_and_a_late_asker_gets_the_newest() {
    // Robot 1 of the warehouse is back where it started after ~110 m, ~900 scans.
    let running = start(NodeConfig { linger: true, ..config("fleet-loops", Some(950)) }).await;
    let updates = running.client.declare_subscriber(keyexpr::posegraph(&running.fleet, 1)).await.unwrap();
    let mut keyframes = BTreeMap::new();
    running.collect(Duration::from_secs(20), &mut keyframes).await;
    let mut received = Vec::new();
    while let Ok(Ok(sample)) = tokio::time::timeout(Duration::from_millis(200), updates.recv_async()).await {
        received.push(proto::PoseGraphUpdate::decode(sample.payload().to_bytes().as_ref()).unwrap());
    }
    let newest = received.last().expect("a loop closes within 950 scans and the graph is published");
    assert!(received.windows(2).all(|w| w[0].revision < w[1].revision), "revisions increase");
    assert!(newest.loops.len() >= 2, "{} loops", newest.loops.len());
    for l in &newest.loops {
        assert!(l.from_seq < l.to_seq && l.to_seq < keyframes.len() as u64, "{l:?}");
        assert!(l.score > 0.5, "{l:?}");
    }
    // Every keyframe up to the newest one has an optimised pose, in order.
    let seqs: Vec<u64> = newest.poses.iter().map(|p| p.seq).collect();
    assert_eq!(seqs, (0..seqs.len() as u64).collect::<Vec<_>>());
    // Keyframes carry their Scan Context.
    let kf = proto::Keyframe::decode(keyframes[&0].as_slice()).unwrap();
    let context = kf.scan_context.expect("a descriptor on the wire");
    assert_eq!((context.rings, context.sectors, context.cells.len()), (20, 60, 1200));
    // A station that was not listening asks the pose-graph key and gets the newest update.
    let replies =
        running.client.get(keyexpr::posegraph(&running.fleet, 1)).timeout(Duration::from_secs(10)).await.unwrap();
    let reply = replies.recv_async().await.expect("the node answers");
    let late = proto::PoseGraphUpdate::decode(reply.result().unwrap().payload().to_bytes().as_ref()).unwrap();
    assert_eq!(&late, newest);
    let summary = running.shut_down().await;
    assert_eq!(summary.posegraph_revision, newest.revision);
    assert_eq!(summary.loops, newest.loops.len());
}

/// A robot that crashes and restarts with its state directory: the new start is a new session
/// (its keyframes say so, numbered from 0 again) that starts where it is told (`start_at`, checked
/// against the simulator's truth), and it serves the crashed session's keyframes from disk, the
/// bytes it published.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_a_crash_the_restarted_robot_serves_its_earlier_session_from_disk() {
    let state = tempfile::tempdir().unwrap();
    let disk = || {
        let dir = node::state_dir::StateDir::open(state.path(), 1).expect("a usable state directory");
        Some(std::sync::Arc::new(std::sync::Mutex::new(dir)))
    };
    let first = start(NodeConfig { session: 5, state: disk(), ..config("fleet-s", Some(60)) }).await;
    let mut published = BTreeMap::new();
    first.collect_into(4, &mut published).await;
    // The crash: the node is gone wherever it was, nothing shut down.
    first.node.abort();
    drop(first.client);
    let dir = node::state_dir::StateDir::open(state.path(), 1).unwrap();
    assert_eq!(dir.newest_session(), Some(5));
    drop(dir);
    let second = start(NodeConfig { session: 6, start_at: 40, state: disk(), ..config("fleet-s", Some(10)) }).await;
    let newest = second.next(Duration::from_secs(60)).await.expect("the new session publishes");
    let newest = proto::Keyframe::decode(newest.as_slice()).unwrap();
    assert_eq!((newest.session, newest.seq), (6, 0));
    let request = KeyframeRequest { from_seq: Some(0), session: Some(5), ..KeyframeRequest::default() };
    let (replies, errors) = second.ask(request.encode_to_vec()).await;
    assert!(errors.is_empty(), "{errors:?}");
    let served: BTreeMap<u64, Vec<u8>> =
        replies.into_iter().map(|p| (proto::Keyframe::decode(p.as_slice()).unwrap().seq, p)).collect();
    for (seq, payload) in &published {
        assert_eq!(served.get(seq), Some(payload), "keyframe {seq} of session 5 as published");
    }
    let summary = second.shut_down().await;
    let truth = sim::Simulator::new(sim::Scenario::by_name("warehouse-small").unwrap(), 0, Default::default())
        .unwrap()
        .ground_truth(40);
    let started = summary.ground_truth[0].expect("the simulator knows its truth");
    assert!((started.translation.vector - truth.translation.vector).norm() < 1e-9, "started at scan 40");
}
