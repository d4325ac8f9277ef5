//! What the station holds for each robot of its fleet: keyframes by sequence number (the bytes as
//! received and the pose they carry) and the latest optimised poses. Pure: no I/O.
//!
//! A robot is held per session ([`Member`]): an edge that restarts begins a new odometry frame and
//! numbers its keyframes from 0 again, so each session is a map of its own, and the merge places it
//! like any other robot's.
//!
//! The decoded clouds are not kept: a 0.2 m keyframe's points take three to four times its encoded
//! bytes (144 kB against 41 kB on the campus), and the merge needs them only when a keyframe first
//! enters its robot's map or the map is rebuilt at new poses; it decodes them then.
//!
//! Every insertion is idempotent, so live samples, backfill replies and a reload from the database
//! all go through the same path in any order.

use std::collections::BTreeMap;
use std::sync::Arc;

use cloud::PointCloud;
use nalgebra::Isometry3;

/// Most gaps [`RobotState::missing`] lists (the backfill asks for at most 4096 at a time).
pub const MAX_LISTED_GAPS: usize = 4096;

/// One session of one robot: what an edge sent between one start and the next, a map of its own.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Member {
    /// Robot id.
    pub robot: u32,
    /// The robot's session (higher is newer; 0 for a robot that sends none).
    pub session: u64,
}

impl Member {
    /// Session `session` of `robot`.
    pub fn new(robot: u32, session: u64) -> Self {
        Member { robot, session }
    }

    /// Its name in frames, logs and status: `robotN` for session 0, so that a fleet without
    /// restarts keeps the names it always had, `robotN/sK` for a later session.
    pub fn name(&self) -> String {
        match self.session {
            0 => format!("robot{}", self.robot),
            s => format!("robot{}/s{s}", self.robot),
        }
    }
}

/// A bare robot id is its session 0: what a message without a session says.
impl From<u32> for Member {
    fn from(robot: u32) -> Self {
        Member { robot, session: 0 }
    }
}

impl std::fmt::Display for Member {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.name())
    }
}

/// A keyframe checked and decoded by [`super::ingest`].
#[derive(Clone, Debug)]
pub struct ReceivedKeyframe {
    /// Robot id (the key expression's and the message's, which agree).
    pub robot: u32,
    /// The robot's session, from the message.
    pub session: u64,
    /// Sequence number.
    pub seq: u64,
    /// The protobuf `Keyframe` exactly as received: what is persisted and what a conflict compares.
    pub bytes: Arc<[u8]>,
    /// The odometry pose the robot sent with it.
    pub odom_pose: Isometry3<f64>,
    /// The decoded cloud, positions only, in the keyframe's sensor frame.
    pub cloud: Arc<PointCloud>,
}

impl ReceivedKeyframe {
    /// The robot session it belongs to.
    pub fn member(&self) -> Member {
        Member::new(self.robot, self.session)
    }

    /// What the station holds of it.
    fn held(&self) -> HeldKeyframe {
        HeldKeyframe { bytes: Arc::clone(&self.bytes), odom_pose: self.odom_pose }
    }
}

/// A keyframe as the station holds it: its bytes, and the pose decoded from them.
#[derive(Clone, Debug)]
pub struct HeldKeyframe {
    /// The protobuf `Keyframe` exactly as received.
    pub bytes: Arc<[u8]>,
    /// The odometry pose the robot sent with it.
    pub odom_pose: Isometry3<f64>,
}

/// What became of an inserted keyframe.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Inserted {
    /// A sequence number not held before.
    New,
    /// The same bytes again: nothing changed.
    Duplicate,
    /// Different bytes for a held sequence number of the same session: the first ones were kept.
    Conflict,
}

/// What a robot's map was built from: enough to tell whether a persisted global map is current.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Basis {
    /// Keyframes held.
    pub keyframes: u64,
    /// Revision of the pose-graph update whose poses are in effect, if any.
    pub pose_revision: Option<u64>,
}

/// One robot session's keyframes and poses.
#[derive(Clone, Debug, Default)]
pub struct RobotState {
    keyframes: BTreeMap<u64, HeldKeyframe>,
    /// Bytes of `keyframes`, kept as they are inserted: the station reports it after every sample.
    keyframe_bytes: u64,
    /// Optimised poses of the latest pose-graph revision, by sequence number.
    poses: BTreeMap<u64, Isometry3<f64>>,
    /// Newest pose-graph revision accepted.
    pose_revision: Option<u64>,
    /// The revision whose poses are in effect: a newer update with the same poses leaves it, so
    /// the basis (and with it the need to re-merge after a restart) follows the map's content.
    poses_from: Option<u64>,
    /// Bumped whenever the robot's map changes (a new keyframe or different poses).
    revision: u64,
    conflicts: u64,
}

impl RobotState {
    /// Keyframes held, by sequence number.
    pub fn keyframes(&self) -> &BTreeMap<u64, HeldKeyframe> {
        &self.keyframes
    }

    /// The newest pose-graph revision accepted, if any.
    pub fn pose_revision(&self) -> Option<u64> {
        self.pose_revision
    }

    /// The best pose of keyframe `seq`: the optimised one if any, else the odometry pose.
    pub fn pose(&self, seq: u64) -> Option<Isometry3<f64>> {
        self.poses.get(&seq).copied().or_else(|| self.keyframes.get(&seq).map(|k| k.odom_pose))
    }

    /// The map revision: changes whenever keyframes or poses change.
    pub fn revision(&self) -> u64 {
        self.revision
    }

    /// Highest sequence number held.
    pub fn max_seq(&self) -> Option<u64> {
        self.keyframes.keys().next_back().copied()
    }

    /// Sequence numbers below the highest one held that are not held, lowest first, at most
    /// [`MAX_LISTED_GAPS`]: a single keyframe with an absurd sequence number must not make the
    /// station list (or allocate) trillions of gaps.
    pub fn missing(&self) -> Vec<u64> {
        let mut missing = Vec::new();
        let mut expected = 0u64;
        for &seq in self.keyframes.keys() {
            let room = MAX_LISTED_GAPS - missing.len();
            missing.extend((expected..seq).take(room));
            if missing.len() == MAX_LISTED_GAPS {
                break;
            }
            expected = seq.saturating_add(1);
        }
        missing
    }

    /// How many sequence numbers below the highest one held are not held (up to `u64::MAX`).
    pub fn missing_count(&self) -> u64 {
        let span = self.max_seq().map_or(0, |max| u128::from(max) + 1);
        u64::try_from(span - self.keyframes.len() as u128).unwrap_or(u64::MAX)
    }

    /// Bytes of the keyframes held, as received.
    pub fn keyframe_bytes(&self) -> u64 {
        self.keyframe_bytes
    }

    /// Conflicting keyframes seen (same sequence number, different bytes).
    pub fn conflicts(&self) -> u64 {
        self.conflicts
    }

    /// What the robot's map is built from now.
    pub fn basis(&self) -> Basis {
        Basis { keyframes: self.keyframes.len() as u64, pose_revision: self.poses_from }
    }
}

/// Every robot session of the fleet.
#[derive(Clone, Debug, Default)]
pub struct FleetState {
    robots: BTreeMap<Member, RobotState>,
}

impl FleetState {
    /// Adds a keyframe unless its session's sequence number is already held.
    pub fn insert_keyframe(&mut self, keyframe: &ReceivedKeyframe) -> Inserted {
        let robot = self.robots.entry(keyframe.member()).or_default();
        match robot.keyframes.get(&keyframe.seq) {
            Some(held) if held.bytes == keyframe.bytes => Inserted::Duplicate,
            Some(_) => {
                robot.conflicts += 1;
                Inserted::Conflict
            }
            None => {
                robot.keyframes.insert(keyframe.seq, keyframe.held());
                robot.keyframe_bytes += keyframe.bytes.len() as u64;
                robot.revision += 1;
                Inserted::New
            }
        }
    }

    /// Applies a pose-graph update of a robot session; returns true when it changed its poses.
    /// Revisions older than the one held are ignored.
    pub fn apply_poses(
        &mut self,
        member: impl Into<Member>,
        revision: u64,
        poses: BTreeMap<u64, Isometry3<f64>>,
    ) -> bool {
        let state = self.robots.entry(member.into()).or_default();
        if state.pose_revision.is_some_and(|held| revision <= held) {
            return false;
        }
        state.pose_revision = Some(revision);
        if state.poses == poses {
            return false;
        }
        state.poses = poses;
        state.poses_from = Some(revision);
        state.revision += 1;
        true
    }

    /// One robot session (a bare robot id: its session 0), if seen.
    pub fn robot(&self, member: impl Into<Member>) -> Option<&RobotState> {
        self.robots.get(&member.into())
    }

    /// Every robot session seen, by robot and session.
    pub fn robots(&self) -> &BTreeMap<Member, RobotState> {
        &self.robots
    }

    /// The sessions seen of `robot`, oldest first.
    pub fn sessions(&self, robot: u32) -> impl DoubleEndedIterator<Item = (&Member, &RobotState)> {
        self.robots.range(Member::new(robot, 0)..=Member::new(robot, u64::MAX))
    }

    /// The newest session seen of `robot`.
    pub fn newest_session(&self, robot: u32) -> Option<Member> {
        self.sessions(robot).next_back().map(|(m, _)| *m)
    }

    /// The session of `member`'s robot just before it, if one was seen.
    pub fn previous_session(&self, member: Member) -> Option<Member> {
        self.robots.range(Member::new(member.robot, 0)..member).next_back().map(|(m, _)| *m)
    }

    /// Gaps of one robot session (empty for an unknown one).
    pub fn missing(&self, member: impl Into<Member>) -> Vec<u64> {
        self.robots.get(&member.into()).map(RobotState::missing).unwrap_or_default()
    }

    /// Keyframes held over all robots.
    pub fn total_keyframes(&self) -> usize {
        self.robots.values().map(|r| r.keyframes.len()).sum()
    }

    /// Conflicts seen over all robots.
    pub fn total_conflicts(&self) -> u64 {
        self.robots.values().map(|r| r.conflicts).sum()
    }

    /// Keyframes held per robot, over its sessions.
    pub fn keyframe_counts(&self) -> BTreeMap<u32, usize> {
        let mut counts = BTreeMap::new();
        for (member, r) in &self.robots {
            *counts.entry(member.robot).or_default() += r.keyframes.len();
        }
        counts
    }

    /// Keyframes held per robot session.
    pub fn session_counts(&self) -> BTreeMap<Member, usize> {
        self.robots.iter().map(|(&id, r)| (id, r.keyframes.len())).collect()
    }

    /// Every robot session's current basis.
    pub fn basis(&self) -> BTreeMap<Member, Basis> {
        self.robots.iter().map(|(&id, r)| (id, r.basis())).collect()
    }
}
