//! The CPU-bound half of a node: reads the source, runs the odometry and encodes keyframes on a
//! blocking thread, handing each registered scan to the async half through a bounded channel (a slow
//! network slows the odometry down instead of filling memory).

use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use cloud::PointCloud;
use cloud::stopwatch::Stopwatch;
use nalgebra::Isometry3;
use prost::Message;
use proto::Fleet;
use proto::codec::CodecConfig;
use tokio::sync::mpsc;
use tracing::{error, warn};

use super::{NodeError, Rate};
use crate::loops::LoopCloser;
use crate::odometry::{Keyframe, Odometry};
use crate::source::{Source, SourceLosses, SourceScan};
use crate::wire;
use cloud::memory::release_periodically;
use cloud::scan_context::{ScanContext, ScanContextConfig};

/// One registered scan, as the async half needs it.
#[derive(Debug)]
pub(crate) struct Registered {
    /// Sensor pose at the sweep end, odometry frame.
    pub pose: Isometry3<f64>,
    /// Sweep start, seconds.
    pub stamp: f64,
    /// Ground-truth pose, when the source knows it.
    pub ground_truth: Option<Isometry3<f64>>,
    /// The keyframe the scan made, encoded for the wire.
    pub keyframe: Option<EncodedKeyframe>,
    /// The pose graph, when the keyframe's loop re-optimised it.
    pub posegraph: Option<EncodedPoseGraph>,
    /// Wall time of the odometry on this scan, milliseconds.
    pub odometry_ms: f64,
    /// What the source lost of this scan, or before it.
    pub losses: SourceLosses,
}

/// A `emr.v1.PoseGraphUpdate` protobuf encoding.
#[derive(Debug)]
pub(crate) struct EncodedPoseGraph {
    /// Its revision.
    pub revision: u64,
    /// The optimised keyframe poses it holds, by keyframe index.
    pub poses: Vec<Isometry3<f64>>,
    /// The loops in the graph (they change only when it is optimised).
    pub loops: usize,
    /// The message bytes.
    pub payload: Vec<u8>,
}

/// A keyframe's `emr.v1.Keyframe` protobuf encoding.
#[derive(Debug)]
pub(crate) struct EncodedKeyframe {
    /// Sequence number.
    pub seq: u64,
    /// The message bytes.
    pub payload: Vec<u8>,
    /// The keyframe's cloud, kept for the ROS 2 topics (only when they are on: it is not counted
    /// among what the node holds).
    pub cloud: Option<PointCloud>,
}

/// The worker's side of what a node holds ([`super::Held`]), shared with the publisher, which
/// takes each keyframe's bytes off `in_flight` as it stores it.
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct Made {
    /// Keyframes made and encoded.
    pub keyframes: u64,
    /// Bytes of encoded keyframes handed to the channel and not yet taken.
    pub in_flight: u64,
    /// What the loop closure keeps of its keyframes, bytes.
    pub loops: u64,
}

/// Everything the blocking thread owns.
pub(crate) struct Worker {
    /// Where scans come from.
    pub source: Source,
    /// The robot's odometry.
    pub odometry: Odometry,
    /// Fleet named in the messages.
    pub fleet: Fleet,
    /// Robot id named in the messages.
    pub robot: u32,
    /// The session named in the messages (see [`super::NodeConfig::session`]).
    pub session: u64,
    /// How keyframe clouds are compressed.
    pub codec: CodecConfig,
    /// How fast scans are read.
    pub rate: Rate,
    /// The loop closure, unless off (the paper's MR mode).
    pub loops: Option<LoopCloser>,
    /// How descriptors are made when the loop closure is off (they still go on the wire).
    pub scan_context: ScanContextConfig,
    /// What it has made, for the count of what the node holds.
    pub made: Arc<Mutex<Made>>,
    /// Hand each keyframe's cloud on beside its message (for the ROS 2 topics).
    pub keep_clouds: bool,
}

impl Worker {
    /// Runs until the source ends or the receiver is closed (shutdown) or dropped.
    pub(crate) fn run(mut self, tx: mpsc::Sender<Registered>) -> Result<(), NodeError> {
        let mut pacer = Pacer::new(self.rate);
        let mut scans = 0;
        while let Some(scan) = self.next_scan() {
            if !pacer.wait_for(scan.stamp, &tx) {
                break;
            }
            let registered = self.register(scan)?;
            scans += 1;
            release_periodically(scans);
            if tx.blocking_send(registered).is_err() {
                break;
            }
        }
        Ok(())
    }

    /// The next good scan; `None` at the end of the source or after a fatal read error.
    fn next_scan(&mut self) -> Option<SourceScan> {
        loop {
            match self.source.next()? {
                Ok(scan) => return Some(scan),
                Err(e) if !e.is_fatal() => warn!("robot {}: skipped a scan: {e}", self.robot),
                Err(e) => {
                    error!("robot {}: {e}; the source ends here", self.robot);
                    return None;
                }
            }
        }
    }

    /// Odometry on one scan, and its keyframe's message if it made one (with the pose graph's when
    /// the keyframe closed a loop that changed it).
    fn register(&mut self, scan: SourceScan) -> Result<Registered, NodeError> {
        let mut losses = SourceLosses::default();
        losses.count(&scan);
        let watch = Stopwatch::start();
        let frame = self
            .odometry
            .register(&scan.cloud, scan.stamp)
            .map_err(|source| NodeError::Odometry { index: scan.index, source })?;
        let odometry_ms = watch.elapsed_ms();
        let (mut keyframe, mut posegraph) = (None, None);
        if let Some(kf) = &frame.keyframe {
            let (context, optimised) = match &mut self.loops {
                Some(loops) => {
                    let step = loops.add(kf).map_err(|source| NodeError::Loops { seq: kf.seq, source })?;
                    (step.context, step.optimised.is_some())
                }
                None => (ScanContext::new(&kf.cloud, &self.scan_context), false),
            };
            let encoded = self.encode(kf, scan.stamp, &context)?;
            let mut made = self.made.lock().unwrap_or_else(PoisonError::into_inner);
            made.keyframes += 1;
            made.in_flight += encoded.payload.len() as u64;
            made.loops = self.loops.as_ref().map_or(0, LoopCloser::held_bytes);
            drop(made);
            keyframe = Some(encoded);
            if optimised && let Some(loops) = &self.loops {
                let msg = proto::PoseGraphUpdate {
                    session: self.session,
                    ..wire::posegraph_message(&self.fleet, self.robot, loops)
                };
                posegraph = Some(EncodedPoseGraph {
                    revision: msg.revision,
                    poses: loops.poses().to_vec(),
                    loops: msg.loops.len(),
                    payload: msg.encode_to_vec(),
                });
            }
        }
        Ok(Registered {
            pose: frame.pose,
            stamp: scan.stamp,
            ground_truth: scan.ground_truth,
            keyframe,
            posegraph,
            odometry_ms,
            losses,
        })
    }

    fn encode(&self, kf: &Keyframe, stamp: f64, context: &ScanContext) -> Result<EncodedKeyframe, NodeError> {
        let mut msg = wire::keyframe_message(&self.fleet, self.robot, kf, stamp, Some(context), &self.codec)
            .map_err(|source| NodeError::Encode { seq: kf.seq, source })?;
        msg.session = self.session;
        let cloud = self.keep_clouds.then(|| kf.cloud.clone());
        Ok(EncodedKeyframe { seq: kf.seq, payload: msg.encode_to_vec(), cloud })
    }
}

/// Paces scans by their stamps (realtime) or not at all.
struct Pacer {
    rate: Rate,
    start: Option<(Instant, f64)>,
}

/// Longest sleep between checks for shutdown.
const PACE_SLICE: Duration = Duration::from_millis(20);

impl Pacer {
    fn new(rate: Rate) -> Self {
        Pacer { rate, start: None }
    }

    /// Waits until the scan stamped `stamp` is due; false when the receiver went away meanwhile.
    fn wait_for<T>(&mut self, stamp: f64, tx: &mpsc::Sender<T>) -> bool {
        if self.rate == Rate::Max {
            return !tx.is_closed();
        }
        let (start, first) = *self.start.get_or_insert((Instant::now(), stamp));
        // Stamps that go backwards or are not finite are played at once rather than waited for.
        let offset = Duration::try_from_secs_f64(stamp - first).unwrap_or_default();
        let due = start + offset;
        loop {
            if tx.is_closed() {
                return false;
            }
            let left = due.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return true;
            }
            std::thread::sleep(left.min(PACE_SLICE));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn realtime_waits_for_the_stamp_and_gives_up_on_shutdown() {
        let (tx, mut rx) = mpsc::channel::<()>(1);
        let mut pacer = Pacer::new(Rate::Realtime);
        let start = Instant::now();
        assert!(pacer.wait_for(100.0, &tx) && pacer.wait_for(100.06, &tx));
        assert!(start.elapsed() >= Duration::from_millis(60), "{:?}", start.elapsed());
        // A stamp 900 s ahead: closing the receiver ends the wait, which returns false (a wait to the
        // stamp would hold the test for 15 minutes).
        rx.close();
        assert!(!pacer.wait_for(1000.0, &tx));
        assert!(!Pacer::new(Rate::Max).wait_for(1000.0, &tx));
    }
}
