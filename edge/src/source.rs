//! Where scans come from: the built-in simulator (`sim:SCENARIO:ROBOT`), a recording (a directory
//! of scans, a ROS 1 bag, an MCAP file, a packet capture), a live sensor (`udp:ADDRESS:PORT`) or a
//! ROS 2 driver's PointCloud2 topic over rmw_zenoh (`ros2:/TOPIC`), behind one iterator.

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::RecvTimeoutError;
use std::time::Duration;

use cloud::PointCloud;
use nalgebra::Isometry3;
use serde::Serialize;
use sim::{Scenario, SimConfig, SimError, Simulator, UnknownScenario};

use bus::Network;
use proto::ros2::keys::TopicName;

use crate::live_sensor::LiveSensor;
use crate::recording::pointcloud2::MessageError;
use crate::recording::{self, ChannelDeriver, RecordingError, RecordingOptions};
use crate::ros2_topic::{Link, Ros2Topic, Ros2TopicError};

/// A scan source named on the command line.
#[derive(Clone, Debug, PartialEq)]
pub enum SourceSpec {
    /// `sim:SCENARIO:ROBOT` (robot ids start at 1; `sim:SCENARIO` is robot 1).
    Sim {
        /// Scenario name.
        scenario: String,
        /// Robot id, 1-based.
        robot: u32,
    },
    /// A directory of scans, a `.bag`, `.mcap` or packet capture (`pcap:FILE` names a capture
    /// whatever its extension).
    Recording(PathBuf),
    /// `udp:ADDR:PORT`: a live sensor's packets, received on that local address.
    Udp(std::net::SocketAddr),
    /// `ros2:/TOPIC`: a sensor_msgs/PointCloud2 topic published over rmw_zenoh.
    Ros2 {
        /// The topic.
        topic: TopicName,
        /// Its ROS domain (0 unless set with [`SourceSpec::on_network`]).
        domain: u32,
        /// How a source of its own reaches the publisher (a peer connecting to the default port of
        /// 127.0.0.1 unless set with [`SourceSpec::on_network`]); a robot's node reads the topic
        /// on its own session instead.
        network: Network,
    },
}

impl SourceSpec {
    /// A `ros2:` source in ROS domain `domain`, reached through `network`; other sources as they are.
    pub fn on_network(self, network: Network, domain: u32) -> Self {
        match self {
            SourceSpec::Ros2 { topic, .. } => SourceSpec::Ros2 { topic, domain, network },
            other => other,
        }
    }
}

/// A source specification that cannot be understood.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[error("invalid source {input:?}: {reason}")]
pub struct InvalidSource {
    /// What was given.
    pub input: String,
    /// Why it is not a source.
    pub reason: String,
}

impl std::fmt::Display for SourceSpec {
    /// As it is written on the command line.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SourceSpec::Sim { scenario, robot } => write!(f, "sim:{scenario}:{robot}"),
            SourceSpec::Recording(path) => write!(f, "{}", path.display()),
            SourceSpec::Udp(address) => write!(f, "udp:{address}"),
            SourceSpec::Ros2 { topic, .. } => write!(f, "ros2:{topic}"),
        }
    }
}

impl FromStr for SourceSpec {
    type Err = InvalidSource;

    fn from_str(s: &str) -> Result<Self, InvalidSource> {
        let invalid = |reason: &str| InvalidSource { input: s.to_owned(), reason: reason.to_owned() };
        if let Some(file) = s.strip_prefix("pcap:") {
            return Ok(SourceSpec::Recording(PathBuf::from(file)));
        }
        if let Some(address) = s.strip_prefix("udp:") {
            return address.parse().map(SourceSpec::Udp).map_err(|_| {
                invalid(
                    "expected udp:ADDRESS:PORT, e.g. udp:192.168.1.100:2368 (the local address the sensor sends to)",
                )
            });
        }
        if let Some(topic) = s.strip_prefix("ros2:") {
            let topic = TopicName::new(topic).map_err(|e| invalid(&format!("expected ros2:/TOPIC; {e}")))?;
            let network = Network::loopback_ports(&[], &[bus::DEFAULT_PORT]);
            return Ok(SourceSpec::Ros2 { topic, domain: 0, network });
        }
        let Some(rest) = s.strip_prefix("sim:") else { return Ok(SourceSpec::Recording(PathBuf::from(s))) };
        let (scenario, robot) = match rest.split_once(':') {
            Some((name, id)) => {
                (name, id.parse::<u32>().ok().filter(|r| *r >= 1).ok_or_else(|| invalid("robot ids are 1, 2, ..."))?)
            }
            None => (rest, 1),
        };
        if scenario.is_empty() {
            return Err(invalid("expected sim:SCENARIO:ROBOT, e.g. sim:warehouse-small:1"));
        }
        Ok(SourceSpec::Sim { scenario: scenario.to_owned(), robot })
    }
}

/// One sweep from any source.
#[derive(Clone, Debug)]
pub struct SourceScan {
    /// Points with whatever channels the source has (the simulator: intensity, ring, time).
    pub cloud: PointCloud,
    /// Sweep start, seconds.
    pub stamp: f64,
    /// Position in the source, 0-based.
    pub index: usize,
    /// Ground-truth sensor pose at the sweep end, in the world frame, when the source knows it.
    pub ground_truth: Option<Isometry3<f64>>,
    /// Packets or columns of the rotation lost before decoding (packet sources; 0 elsewhere).
    pub gaps: usize,
    /// Only part of a rotation: a packet capture's first or last.
    pub partial: bool,
    /// Whole scans a live sensor sent since the previous one that were dropped because the
    /// consumer was busy (0 for files, which wait).
    pub dropped_before: usize,
}

impl From<sim::Scan> for SourceScan {
    /// A simulated sweep, with its ground truth; nothing lost.
    fn from(s: sim::Scan) -> Self {
        SourceScan {
            cloud: s.cloud,
            stamp: s.stamp,
            index: s.frame,
            ground_truth: Some(s.ground_truth),
            gaps: 0,
            partial: false,
            dropped_before: 0,
        }
    }
}

/// What a packet source lost before the odometry saw its scans: each is counted in `stats.json`
/// and warned about, since a scan with a hole or a missing scan is less than the sensor saw.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct SourceLosses {
    /// Scans covering only part of a rotation (a capture's first and last).
    pub partial_scans: usize,
    /// Packets (Velodyne) or columns (Ouster) missing within the scans.
    pub packet_gaps: usize,
    /// Whole scans of a live sensor dropped because the odometry was busy.
    pub dropped_scans: usize,
}

impl SourceLosses {
    /// Adds what `scan` lost.
    pub fn count(&mut self, scan: &SourceScan) {
        self.partial_scans += usize::from(scan.partial);
        self.packet_gaps += scan.gaps;
        self.dropped_scans += scan.dropped_before;
    }

    /// Adds another count.
    pub fn add(&mut self, other: &SourceLosses) {
        self.partial_scans += other.partial_scans;
        self.packet_gaps += other.packet_gaps;
        self.dropped_scans += other.dropped_scans;
    }

    /// A line per kind of loss, for the log.
    pub fn warnings(&self) -> Vec<String> {
        let mut warnings = Vec::new();
        if self.partial_scans > 0 {
            warnings.push(format!("{} scans cover only part of a rotation", self.partial_scans));
        }
        if self.packet_gaps > 0 {
            warnings.push(format!("{} packets or columns were missing within scans", self.packet_gaps));
        }
        if self.dropped_scans > 0 {
            warnings.push(format!("{} whole scans were dropped: the odometry did not keep up", self.dropped_scans));
        }
        warnings
    }
}

/// Why a source could not be opened or read.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// The scenario name is unknown (the message lists the valid ones).
    #[error(transparent)]
    Scenario(#[from] UnknownScenario),
    /// The simulator refused its settings or robot.
    #[error(transparent)]
    Sim(#[from] SimError),
    /// A recording could not be opened or read.
    #[error(transparent)]
    Recording(#[from] RecordingError),
    /// A live sensor's address cannot be listened on, or its decoder set up.
    #[error("udp:{address}: {reason}")]
    Live {
        /// The address asked for.
        address: std::net::SocketAddr,
        /// Why.
        reason: String,
    },
    /// A ROS 2 topic could not be subscribed to.
    #[error(transparent)]
    Ros2(#[from] Ros2TopicError),
    /// A message of a ROS 2 topic is not a PointCloud2 the odometry can read (skipped).
    #[error("ros2:{topic}: message {index}: {reason}")]
    Ros2Message {
        /// The topic.
        topic: String,
        /// Its rank among the topic's messages.
        index: usize,
        /// Why.
        reason: MessageError,
    },
}

impl SourceError {
    /// True when reading cannot go on after this error (a bad message is not fatal, a cut file is).
    pub fn is_fatal(&self) -> bool {
        match self {
            SourceError::Recording(e) => e.is_fatal(),
            SourceError::Ros2Message { .. } => false,
            _ => true,
        }
    }
}

/// An open source: an iterator of scans.
pub struct Source {
    inner: Inner,
    /// How many scans the source will give, when known in advance.
    pub len: Option<usize>,
    limit: Option<usize>,
    given: usize,
    /// Set when the source must end early (Ctrl-C, a node shutting down).
    interrupt: Option<Arc<AtomicBool>>,
}

enum Inner {
    Sim { sim: Box<Simulator>, next: usize },
    Recording(Box<recording::Recording>),
    Live { sensor: LiveSensor, next: usize },
    Ros2(Box<Ros2Scans>),
}

/// A ROS 2 topic's messages made scans as a recording's are.
struct Ros2Scans {
    topic: Ros2Topic,
    next: usize,
    options: RecordingOptions,
    channels: ChannelDeriver,
}

/// How long a live sensor may be silent before it is warned about (it is waited for still: a
/// sensor that restarts comes back).
const SILENCE_WARNING: Duration = Duration::from_secs(5);

/// How often a wait for a live scan looks whether the source was interrupted.
const POLL: Duration = Duration::from_millis(200);

/// Waits for the next item of a live source through `poll` (which waits up to the given time),
/// warning about `what` every [`SILENCE_WARNING`] of silence; `None` when `poll` says the source
/// ended, `done` says no more is to come, or `interrupt` is set.
fn wait_live<T>(
    what: &str,
    interrupt: Option<&AtomicBool>,
    mut poll: impl FnMut(Duration) -> Result<T, RecvTimeoutError>,
    done: impl Fn() -> bool,
) -> Option<T> {
    let mut silent = Duration::ZERO;
    loop {
        if interrupt.is_some_and(|i| i.load(Ordering::Relaxed)) {
            return None;
        }
        match poll(POLL) {
            Ok(item) => return Some(item),
            Err(RecvTimeoutError::Timeout) if done() => return None,
            Err(RecvTimeoutError::Timeout) => {
                silent += POLL;
                if silent.as_millis().is_multiple_of(SILENCE_WARNING.as_millis()) {
                    tracing::warn!("no scan from {what} for {} s", silent.as_secs());
                }
            }
            Err(RecvTimeoutError::Disconnected) => return None,
        }
    }
}

impl Source {
    /// Opens a source; `frames` caps the number of scans, `sim` configures simulated sensors and
    /// `options` recordings (rings and times are derived there when a recording lacks them).
    pub fn open(
        spec: &SourceSpec,
        frames: Option<usize>,
        sim: &SimConfig,
        options: &RecordingOptions,
    ) -> Result<Self, SourceError> {
        match spec {
            SourceSpec::Sim { scenario, robot } => {
                let scenario = Scenario::by_name(scenario)?;
                let sim = Simulator::new(scenario, *robot as usize - 1, sim.clone())?;
                let len = frames.unwrap_or(sim.frames());
                Ok(Source {
                    inner: Inner::Sim { sim: Box::new(sim), next: 0 },
                    len: Some(len),
                    limit: Some(len),
                    given: 0,
                    interrupt: None,
                })
            }
            SourceSpec::Recording(path) => {
                let rec = recording::open(path, options)?;
                let len = match (frames, directory_len(path)) {
                    (Some(f), Some(n)) => Some(f.min(n)),
                    (f, n) => f.or(n),
                };
                Ok(Source { inner: Inner::Recording(Box::new(rec)), len, limit: frames, given: 0, interrupt: None })
            }
            SourceSpec::Udp(address) => {
                let fail = |e: std::io::Error| SourceError::Live { address: *address, reason: e.to_string() };
                let assembler = recording::assembler_for(None, &options.packets)
                    .map_err(|e| SourceError::Live { address: *address, reason: e.to_string() })?;
                let sensor = LiveSensor::start(*address, assembler).map_err(fail)?;
                Ok(Source {
                    inner: Inner::Live { sensor, next: 0 },
                    len: frames,
                    limit: frames,
                    given: 0,
                    interrupt: None,
                })
            }
            SourceSpec::Ros2 { topic, domain, network } => {
                Source::ros2(Link::Join(network.clone()), *domain, topic, frames, options)
            }
        }
    }
}

impl Source {
    /// Opens `ros2:TOPIC` of ROS domain `domain` on `link`'s session (a node's own session, where
    /// [`Source::open`] joins the spec's network); `frames` caps the number of scans.
    pub fn ros2(
        link: Link,
        domain: u32,
        topic: &TopicName,
        frames: Option<usize>,
        options: &RecordingOptions,
    ) -> Result<Self, SourceError> {
        let topic = Ros2Topic::start(link, domain, topic)?;
        let channels = ChannelDeriver::new(options.clone());
        let scans = Ros2Scans { topic, next: 0, options: options.clone(), channels };
        Ok(Source { inner: Inner::Ros2(Box::new(scans)), len: frames, limit: frames, given: 0, interrupt: None })
    }

    /// Ends the source as soon as `interrupt` is set: before the next scan, or while waiting for a
    /// live one.
    pub fn until(mut self, interrupt: Arc<AtomicBool>) -> Self {
        self.interrupt = Some(interrupt);
        self
    }

    /// Leaves out the first `scans` scans (a run that starts where another stopped): the
    /// simulator starts at that sweep, a recording is read past them, a live sensor's are dropped
    /// as they come. `len` and the limit count from there.
    pub fn starting_at(mut self, scans: usize) -> Self {
        match &mut self.inner {
            Inner::Sim { sim, next } => {
                *next = scans;
                // Counted from there, and no further than the simulated run goes.
                let left = sim.frames().saturating_sub(scans);
                self.limit = self.limit.map(|l| l.min(left));
                self.len = self.len.map(|l| l.min(left));
                return self;
            }
            Inner::Recording(rec) => rec.by_ref().take(scans).for_each(drop),
            Inner::Live { sensor, next } => {
                for _ in 0..scans {
                    if live_scan(sensor, next, None, self.interrupt.as_deref()).is_none() {
                        break;
                    }
                }
            }
            Inner::Ros2(ros2) => {
                for _ in 0..scans {
                    if ros2.next_scan(None, self.interrupt.as_deref()).is_none() {
                        break;
                    }
                }
            }
        }
        self.len = self.len.map(|len| len.saturating_sub(if self.limit.is_some() { 0 } else { scans }));
        self
    }
}

/// Scans in a directory source (known up front, for progress bars).
fn directory_len(path: &Path) -> Option<usize> {
    let dir = if path.join("velodyne").is_dir() { path.join("velodyne") } else { path.to_owned() };
    let n = std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| e.ok())
        .filter(|e| {
            e.path()
                .extension()
                .and_then(|x| x.to_str())
                .is_some_and(|x| ["bin", "pcd", "ply"].contains(&x.to_ascii_lowercase().as_str()))
        })
        .count();
    (n > 0).then_some(n)
}

impl Iterator for Source {
    type Item = Result<SourceScan, SourceError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.limit.is_some_and(|l| self.given >= l)
            || self.interrupt.as_ref().is_some_and(|i| i.load(Ordering::Relaxed))
        {
            return None;
        }
        let item = match &mut self.inner {
            Inner::Sim { sim, next } => {
                let s = sim.scan(*next);
                *next += 1;
                Ok(SourceScan::from(s))
            }
            Inner::Recording(rec) => rec
                .next()?
                .map(|s| SourceScan {
                    cloud: s.cloud,
                    stamp: s.stamp,
                    index: s.index,
                    ground_truth: None,
                    gaps: s.gaps,
                    partial: s.partial,
                    dropped_before: 0,
                })
                .map_err(SourceError::from),
            Inner::Live { sensor, next } => Ok(live_scan(sensor, next, self.limit, self.interrupt.as_deref())?),
            Inner::Ros2(ros2) => ros2.next_scan(self.limit, self.interrupt.as_deref())?,
        };
        // A live sensor's dropped scans count towards the limit: it is the sensor's scans.
        self.given += item.as_ref().map_or(0, |scan| 1 + scan.dropped_before);
        Some(item)
    }
}

/// The next scan of a live sensor, waiting for it; `None` when its receiving thread ended, when
/// the sensor went silent after sending `limit` scans (the last of which were dropped), or when
/// interrupted.
fn live_scan(
    sensor: &LiveSensor,
    next: &mut usize,
    limit: Option<usize>,
    interrupt: Option<&AtomicBool>,
) -> Option<SourceScan> {
    let what = format!("udp:{}", sensor.address());
    let done = || limit.is_some_and(|l| sensor.counts().rotations >= l);
    let live = wait_live(&what, interrupt, |t| sensor.next_rotation(t), done)?;
    let index = *next;
    *next += 1;
    let scan = SourceScan {
        cloud: recording::rotation_cloud(&live.rotation),
        stamp: live.rotation.stamp,
        index,
        ground_truth: None,
        gaps: live.rotation.gaps,
        partial: live.rotation.partial,
        dropped_before: live.dropped_before,
    };
    sensor.recycle(live.rotation.returns);
    Some(scan)
}

impl Ros2Scans {
    /// The next message made a scan, waiting for it; `None` when the subscription ended, when the
    /// topic went silent after sending `limit` scans (the last of which were dropped), or when
    /// interrupted.
    fn next_scan(
        &mut self,
        limit: Option<usize>,
        interrupt: Option<&AtomicBool>,
    ) -> Option<Result<SourceScan, SourceError>> {
        let what = format!("ros2:{}", self.topic.topic());
        let topic = &self.topic;
        let done = || limit.is_some_and(|l| topic.counts().received >= l);
        let message = wait_live(&what, interrupt, |t| topic.next_message(t), done)?;
        // The dropped scans had their places on the topic.
        self.next += message.dropped_before;
        let index = self.next;
        self.next += 1;
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(0.0, |d| d.as_secs_f64());
        let scan = recording::cdr_scan(&message.payload, index, now, &self.options, &mut self.channels);
        Some(match scan {
            Ok(scan) => Ok(SourceScan {
                cloud: scan.cloud,
                stamp: scan.stamp,
                index,
                ground_truth: None,
                gaps: 0,
                partial: false,
                dropped_before: message.dropped_before,
            }),
            Err(reason) => Err(SourceError::Ros2Message { topic: self.topic.topic().to_string(), index, reason }),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_sim_and_recording_specs() {
        assert_eq!("sim:campus:3".parse(), Ok(SourceSpec::Sim { scenario: "campus".into(), robot: 3 }));
        assert_eq!("sim:aisles".parse(), Ok(SourceSpec::Sim { scenario: "aisles".into(), robot: 1 }));
        assert_eq!("data/run.bag".parse(), Ok(SourceSpec::Recording("data/run.bag".into())));
        assert!("sim:campus:0".parse::<SourceSpec>().is_err());
        assert!("sim:campus:x".parse::<SourceSpec>().is_err());
        assert!("sim:".parse::<SourceSpec>().is_err());
    }

    #[test]
    fn parses_capture_and_live_sensor_specs() {
        assert_eq!("pcap:run/lidar.cap".parse(), Ok(SourceSpec::Recording("run/lidar.cap".into())));
        assert_eq!("udp:127.0.0.1:2368".parse(), Ok(SourceSpec::Udp("127.0.0.1:2368".parse().unwrap())));
        assert_eq!("udp:[::1]:7502".parse(), Ok(SourceSpec::Udp("[::1]:7502".parse().unwrap())));
        let err = "udp:2368".parse::<SourceSpec>().unwrap_err();
        assert!(err.to_string().contains("udp:ADDRESS:PORT"), "{err}");
        let spec: SourceSpec = "udp:127.0.0.1:2368".parse().unwrap();
        assert_eq!(spec.to_string(), "udp:127.0.0.1:2368");
    }

    #[test]
    fn sim_source_gives_ground_truth_and_stops() {
        let spec: SourceSpec = "sim:aisles:2".parse().unwrap();
        let scans: Vec<_> = Source::open(&spec, Some(3), &SimConfig::default(), &RecordingOptions::default())
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(scans.len(), 3);
        assert!(scans.iter().all(|s| s.ground_truth.is_some() && s.cloud.ring.is_some()));
        let err =
            Source::open(&"sim:aisles:3".parse().unwrap(), None, &SimConfig::default(), &RecordingOptions::default());
        assert!(err.err().unwrap().to_string().contains("has 2 robots"));
    }

    #[test]
    fn a_source_started_later_gives_the_same_scans_from_there() {
        let spec: SourceSpec = "sim:aisles:1".parse().unwrap();
        let open = || Source::open(&spec, Some(5), &SimConfig::default(), &RecordingOptions::default()).unwrap();
        let all: Vec<_> = open().map(Result::unwrap).collect();
        let later: Vec<_> = open().starting_at(3).map(Result::unwrap).take(2).collect();
        assert_eq!(later.iter().map(|s| s.index).collect::<Vec<_>>(), [3, 4]);
        for (a, b) in later.iter().zip(&all[3..]) {
            assert_eq!((a.stamp, &a.cloud.points, a.ground_truth), (b.stamp, &b.cloud.points, b.ground_truth));
        }
        let kitti = testkit::shared_data("kitti00");
        let recording = Source::open(&SourceSpec::Recording(kitti), None, &SimConfig::default(), &Default::default());
        let first = recording.unwrap().starting_at(14).map(Result::unwrap).next().unwrap();
        assert_eq!(first.index, 14);
    }

    #[test]
    fn a_simulated_run_started_later_ends_where_the_run_ends() {
        let spec: SourceSpec = "sim:aisles:1".parse().unwrap();
        let sim = Simulator::new(Scenario::by_name("aisles").unwrap(), 0, SimConfig::default()).unwrap();
        let frames = sim.frames();
        let open = |limit| Source::open(&spec, limit, &SimConfig::default(), &RecordingOptions::default()).unwrap();
        let late = open(None).starting_at(frames - 2);
        assert_eq!(late.len, Some(2));
        assert_eq!(late.map(|s| s.unwrap().index).collect::<Vec<_>>(), [frames - 2, frames - 1]);
        // A limit counts from the start, and still stops at the run's end.
        assert_eq!(open(Some(5)).starting_at(frames - 3).count(), 3);
        assert_eq!(open(Some(2)).starting_at(3).count(), 2);
    }
}
