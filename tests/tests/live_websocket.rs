//! A Foxglove WebSocket client watches a running station (`--foxglove` on 127.0.0.1): it speaks the
//! protocol as the Foxglove app does (subprotocol `foxglove.sdk.v1`, advertise, subscribe, binary
//! message frames), decodes the `/map` channel's `foxglove.PointCloud` and finds the station's
//! published global map in it, point for point, each point labelled with a merged robot.

use std::collections::BTreeSet;
use std::net::{SocketAddr, TcpStream};
use std::sync::Arc;
use std::time::Duration;

use cloud::kdtree::KdTree;
use foxglove::messages::PointCloud as FoxgloveCloud;
use live::Live;
use nalgebra::Point3;
use prost::Message;
use proto::codec::CodecConfig;
use proto::{Fleet, MergeStatus, keyexpr};
use serde_json::{Value, json};
use sim::{Scenario, SimConfig, Simulator};
use station::service::{Station, StationConfig, client};
use tungstenite::client::IntoClientRequest;

/// Keyframes per robot: a few metres of driving.
const KEYFRAMES: usize = 8;
/// The codec's quantisation (1 mm) bounds how far a published point is from the merged one.
const CODEC_TOLERANCE_M: f32 = 1e-3;

/// Robot `robot`'s first keyframes: simulated scans at their true poses, voxelised and encoded as
/// an edge sends them.
fn keyframes(fleet: &Fleet, scenario: &Scenario, robot: u32) -> Vec<Vec<u8>> {
    let sim = Simulator::new(scenario.clone(), robot as usize - 1, SimConfig::default()).unwrap();
    let origin = sim.ground_truth(0).inverse();
    (0..KEYFRAMES)
        .map(|k| {
            let scan = sim.scan(k * 5);
            let cloud = cloud::voxel::downsample(&scan.cloud, 0.2).unwrap();
            let kf = edge::odometry::Keyframe { seq: k as u64, frame: k * 5, pose: origin * scan.ground_truth, cloud };
            edge::wire::keyframe_message(fleet, robot, &kf, scan.stamp, None, &CodecConfig::default())
                .unwrap()
                .encode_to_vec()
        })
        .collect()
}

/// Connects as the Foxglove app does.
fn connect(addr: SocketAddr) -> tungstenite::WebSocket<TcpStream> {
    let stream = TcpStream::connect(addr).unwrap();
    stream.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let mut request = format!("ws://{addr}").into_client_request().unwrap();
    request.headers_mut().insert("Sec-WebSocket-Protocol", "foxglove.sdk.v1".parse().unwrap());
    let (socket, response) = tungstenite::client(request, stream).expect("WebSocket handshake");
    assert_eq!(response.headers()["Sec-WebSocket-Protocol"], "foxglove.sdk.v1");
    socket
}

/// Reads text messages until a channel on `topic` is advertised; returns it.
fn advertised(socket: &mut tungstenite::WebSocket<TcpStream>, topic: &str) -> Value {
    loop {
        let tungstenite::Message::Text(text) = socket.read().expect("a server message") else { continue };
        let msg: Value = serde_json::from_str(&text).unwrap();
        if msg["op"] == "advertise"
            && let Some(c) = msg["channels"].as_array().unwrap().iter().find(|c| c["topic"] == topic)
        {
            return c.clone();
        }
    }
}

/// Reads until a binary message-data frame (opcode 1) of subscription `id`; returns its payload.
fn message_data(socket: &mut tungstenite::WebSocket<TcpStream>, id: u32) -> Vec<u8> {
    loop {
        let tungstenite::Message::Binary(frame) = socket.read().expect("a server message") else { continue };
        // opcode u8, subscription id u32 LE, log time u64 LE, payload.
        if frame[0] == 1 && u32::from_le_bytes(frame[1..5].try_into().unwrap()) == id {
            return frame[13..].to_vec();
        }
    }
}

/// The points of a `foxglove.PointCloud` (f32 x, y, z) with their `robot` labels, read by the
/// fields the message declares.
fn points_and_robots(cloud: &FoxgloveCloud) -> (Vec<Point3<f32>>, Vec<u32>) {
    let offset = |name: &str| cloud.fields.iter().find(|f| f.name == name).map(|f| f.offset as usize).unwrap();
    let (x, y, z, r) = (offset("x"), offset("y"), offset("z"), offset("robot"));
    let stride = cloud.point_stride as usize;
    let at = |base: usize, o: usize| cloud.data[base + o..base + o + 4].try_into().unwrap();
    (0..cloud.data.len() / stride)
        .map(|i| {
            let b = i * stride;
            let p =
                Point3::new(f32::from_le_bytes(at(b, x)), f32::from_le_bytes(at(b, y)), f32::from_le_bytes(at(b, z)));
            (p, u32::from_le_bytes(at(b, r)))
        })
        .unzip()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_foxglove_client_receives_the_global_map() {
    let fleet = Fleet::new("livetest").unwrap();
    let scenario = Scenario::by_name("warehouse-large").unwrap();
    let port = bus::free_port().unwrap();
    let station_session = bus::Network::loopback_ports(&[port], &[]).open().await.unwrap();
    let robot_session = bus::Network::loopback_ports(&[], &[port]).open().await.unwrap();
    let live = Arc::new(Live::new());
    let addr = live.serve("127.0.0.1:0".parse().unwrap(), "test").await.expect("serve on loopback");
    let config = StationConfig {
        debounce: Duration::from_millis(200),
        max_delay: Duration::from_secs(2),
        live: Some(Arc::clone(&live)),
        ..StationConfig::new(fleet.clone())
    };
    let station = Station::start(station_session, config).await.unwrap();

    for robot in [1, 2] {
        // Block, as the edges publish: under load zenoh's default (drop) loses keyframes, and this
        // robot has no queryable the station could backfill them from.
        let publisher = robot_session
            .declare_publisher(keyexpr::keyframe(&fleet, robot))
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .await
            .unwrap();
        while !publisher.matching_status().await.unwrap().matching() {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        for payload in keyframes(&fleet, &scenario, robot) {
            publisher.put(payload).await.unwrap();
        }
    }
    let mut progress = station.progress();
    let all = 2 * KEYFRAMES;
    tokio::time::timeout(Duration::from_secs(120), progress.wait_for(|p| p.total_keyframes() == all && p.up_to_date()))
        .await
        .expect("the station merges every keyframe")
        .unwrap();
    let (map, _) = client::fetch_global_map(&robot_session, &fleet, Duration::from_secs(10)).await.unwrap();
    let published = client::global_map_cloud(&map).unwrap();

    // Connected after the merge: the latched map comes on subscription.
    let received = tokio::task::spawn_blocking(move || {
        let mut socket = connect(addr);
        let channel = advertised(&mut socket, "/map");
        assert_eq!((&channel["encoding"], &channel["schemaName"]), (&json!("protobuf"), &json!("foxglove.PointCloud")));
        let subscribe = json!({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": channel["id"]}]});
        socket.send(tungstenite::Message::text(subscribe.to_string())).unwrap();
        let payload = message_data(&mut socket, 7);
        socket.close(None).ok();
        FoxgloveCloud::decode(payload.as_slice()).expect("a foxglove.PointCloud")
    })
    .await
    .unwrap();

    assert_eq!(received.frame_id, "map");
    let (points, robots) = points_and_robots(&received);
    assert!(!published.is_empty());
    assert_eq!(points.len() as u64, map.cloud.as_ref().unwrap().points, "as many points as the published map");
    let tree = KdTree::from_points(&published.points);
    for p in &points {
        let nearest = tree.nearest(&[p.x, p.y, p.z]).unwrap();
        assert!(
            nearest.dist_sq.sqrt() <= CODEC_TOLERANCE_M,
            "{p:?} is {} m from the published map",
            nearest.dist_sq.sqrt()
        );
    }
    let merged: BTreeSet<u32> =
        map.robots.iter().filter(|r| r.status() == MergeStatus::Merged).map(|r| r.robot).collect();
    assert_eq!(robots.iter().copied().collect::<BTreeSet<u32>>(), merged, "labelled with the merged robots");

    station.stop().await.unwrap();
    live.finish().await.unwrap();
}
