//! `emr-demo bench load`: a station under a simulated fleet's load.
//!
//! N robots publish one keyframe per scan at the sensor rate (10 Hz: ten times what a robot driving
//! 1.5 m/s with 1 m keyframe spacing sends, the worst case) to an in-process station, each robot on
//! its own zenoh session, peers on loopback. The keyframes are simulated scans at their true poses,
//! made before the clock starts so that only the station is measured. Robots beyond the scenario's
//! own replay its robots from later in their runs.

use std::sync::Arc;
use std::time::{Duration, Instant};

use edge::odometry::Keyframe;
use edge::wire::keyframe_message;
use prost::Message;
use proto::codec::CodecConfig;
use proto::{Fleet, keyexpr};
use rayon::prelude::*;
use serde::Serialize;
use sim::{Scenario, SimConfig, Simulator};
use station::service::{Station, StationConfig, StationError, StationProgress};
use tokio::sync::watch;

/// What the benchmark does.
#[derive(Clone, Debug)]
pub struct LoadConfig {
    /// Scenario the robots come from (default `campus`, 4 robots).
    pub scenario: String,
    /// Robots publishing (default 8).
    pub robots: usize,
    /// Keyframes per second per robot (default 10).
    pub rate_hz: f64,
    /// How long they publish (default 20 s).
    pub seconds: f64,
    /// Keyframe voxel, metres (default 0.2, the outdoor odometry preset's).
    pub voxel: f32,
    /// The station's settings.
    pub station: StationConfig,
}

impl LoadConfig {
    /// The defaults above, with the station's defaults and a 1 s debounce.
    pub fn new() -> Self {
        let fleet = Fleet::new("load").expect("valid fleet name");
        LoadConfig {
            scenario: "campus".into(),
            robots: 8,
            rate_hz: 10.0,
            seconds: 20.0,
            voxel: 0.2,
            station: StationConfig { debounce: Duration::from_secs(1), ..StationConfig::new(fleet) },
        }
    }
}

impl Default for LoadConfig {
    fn default() -> Self {
        Self::new()
    }
}

/// What was measured.
#[derive(Clone, Debug, Serialize)]
pub struct LoadReport {
    /// Robots.
    pub robots: usize,
    /// Keyframes published over all robots.
    pub published: u64,
    /// Mean keyframe payload, bytes.
    pub mean_payload_bytes: f64,
    /// Keyframes the station received per second while the robots published.
    pub received_per_s: f64,
    /// Most keyframes published but not yet taken in by the station at any sample (every 50 ms).
    pub max_backlog: u64,
    /// Merge jobs waiting at most (coalesced: never above 1).
    pub max_queue_depth: u32,
    /// Merges run while publishing and until caught up.
    pub merges: usize,
    /// Merge wall time, milliseconds: median and max.
    pub merge_ms_median: f64,
    /// Longest merge.
    pub merge_ms_max: f64,
    /// From the last keyframe published to a published global map holding every keyframe, seconds.
    pub catch_up_s: f64,
    /// Robots merged in the final map.
    pub merged: usize,
}

/// Why the benchmark failed.
#[derive(Debug, thiserror::Error)]
pub enum LoadError {
    /// Simulation or encoding.
    #[error("preparing keyframes: {0}")]
    Prepare(String),
    /// Zenoh.
    #[error("network: {0}")]
    Network(String),
    /// The station.
    #[error(transparent)]
    Station(#[from] StationError),
}

/// Runs the benchmark.
pub async fn run(config: LoadConfig) -> Result<LoadReport, LoadError> {
    let per_robot = (config.seconds * config.rate_hz).round() as usize;
    let payloads = tokio::task::spawn_blocking({
        let config = config.clone();
        move || prepare(&config, per_robot)
    })
    .await
    .map_err(|e| LoadError::Prepare(e.to_string()))??;
    let port = bus::free_port().map_err(|e| LoadError::Network(e.to_string()))?;
    let station_session = open(&bus::Network::loopback_ports(&[port], &[])).await?;
    let station = Station::start(station_session, config.station.clone()).await?;
    let mut sessions = Vec::new();
    for _ in 0..config.robots {
        sessions.push(open(&bus::Network::loopback_ports(&[], &[port])).await?);
    }
    let published = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let stop_sampling = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let sampler = tokio::spawn(sample(station.progress(), Arc::clone(&published), Arc::clone(&stop_sampling)));
    let started = Instant::now();
    let mut robots = Vec::new();
    for (i, (session, robot_payloads)) in sessions.into_iter().zip(payloads.clone()).enumerate() {
        let key = keyexpr::keyframe(&config.station.fleet, i as u32 + 1);
        robots.push(tokio::spawn(publish(session, key, robot_payloads, config.rate_hz, Arc::clone(&published))));
    }
    for r in robots {
        r.await.map_err(|e| LoadError::Network(e.to_string()))??;
    }
    let publishing = started.elapsed();
    let total = published.load(std::sync::atomic::Ordering::Relaxed);
    let mut progress = station.progress();
    let received_during = progress.borrow().total_keyframes() as f64;
    let caught_up = Instant::now();
    let _ = progress.wait_for(|p| p.total_keyframes() as u64 == total && p.up_to_date()).await;
    let catch_up = caught_up.elapsed();
    stop_sampling.store(true, std::sync::atomic::Ordering::Relaxed);
    let (max_backlog, max_queue_depth) = sampler.await.unwrap_or_default();
    let summary = station.stop().await?;
    let mut ms = summary.merge_ms.clone();
    ms.sort_by(f64::total_cmp);
    let merged = summary
        .global_map
        .as_ref()
        .map_or(0, |m| m.robots.iter().filter(|r| r.status() == proto::MergeStatus::Merged).count());
    let bytes: usize = payloads.iter().flatten().map(Vec::len).sum();
    Ok(LoadReport {
        robots: config.robots,
        published: total,
        mean_payload_bytes: bytes as f64 / total.max(1) as f64,
        received_per_s: received_during / publishing.as_secs_f64(),
        max_backlog,
        max_queue_depth,
        merges: ms.len(),
        merge_ms_median: ms.get(ms.len() / 2).copied().unwrap_or(0.0),
        merge_ms_max: ms.last().copied().unwrap_or(0.0),
        catch_up_s: catch_up.as_secs_f64(),
        merged,
    })
}

async fn open(network: &bus::Network) -> Result<zenoh::Session, LoadError> {
    network.open().await.map_err(|e| LoadError::Network(e.to_string()))
}

/// Every robot's keyframe payloads, in order: simulated scans at their true poses (relative to
/// the robot's first), voxelised and encoded. Robot `i` beyond the scenario's own replays robot
/// `i mod n` from `i / n` half-runs later.
fn prepare(config: &LoadConfig, per_robot: usize) -> Result<Vec<Vec<Vec<u8>>>, LoadError> {
    let scenario = Scenario::by_name(&config.scenario).map_err(|e| LoadError::Prepare(e.to_string()))?;
    let own = scenario.robots().len();
    let fleet = &config.station.fleet;
    (0..config.robots)
        .into_par_iter()
        .map(|i| {
            let sim = Simulator::new(scenario.clone(), i % own, SimConfig::default())
                .map_err(|e| LoadError::Prepare(e.to_string()))?;
            let offset = (i / own) * sim.frames() / 2;
            let origin = sim.ground_truth(offset).inverse();
            (0..per_robot)
                .map(|k| {
                    let scan = sim.scan(offset + k);
                    let cloud = cloud::voxel::downsample(&scan.cloud, config.voxel)
                        .map_err(|e| LoadError::Prepare(e.to_string()))?;
                    let kf = Keyframe { seq: k as u64, frame: k, pose: origin * scan.ground_truth, cloud };
                    keyframe_message(fleet, i as u32 + 1, &kf, scan.stamp, None, &CodecConfig::default())
                        .map(|m| m.encode_to_vec())
                        .map_err(|e| LoadError::Prepare(e.to_string()))
                })
                .collect()
        })
        .collect()
}

/// Publishes one robot's keyframes at `rate_hz`, blocking under congestion as the edges do.
async fn publish(
    session: zenoh::Session,
    key: String,
    payloads: Vec<Vec<u8>>,
    rate_hz: f64,
    published: Arc<std::sync::atomic::AtomicU64>,
) -> Result<(), LoadError> {
    let publisher = session
        .declare_publisher(key)
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .await
        .map_err(|e| LoadError::Network(e.to_string()))?;
    let deadline = Instant::now() + Duration::from_secs(5);
    while !publisher.matching_status().await.is_ok_and(|s| s.matching()) && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / rate_hz));
    for p in payloads {
        tick.tick().await;
        publisher.put(p).await.map_err(|e| LoadError::Network(e.to_string()))?;
        published.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    }
    Ok(())
}

/// Samples the backlog (published minus received) and the merge queue every 50 ms.
async fn sample(
    progress: watch::Receiver<StationProgress>,
    published: Arc<std::sync::atomic::AtomicU64>,
    stop: Arc<std::sync::atomic::AtomicBool>,
) -> (u64, u32) {
    let (mut backlog, mut depth) = (0u64, 0u32);
    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
        {
            let p = progress.borrow();
            let sent = published.load(std::sync::atomic::Ordering::Relaxed);
            backlog = backlog.max(sent.saturating_sub(p.total_keyframes() as u64));
            depth = depth.max(u32::from(p.merge_pending));
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    (backlog, depth)
}
