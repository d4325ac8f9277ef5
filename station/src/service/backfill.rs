//! Which keyframes to ask a robot for, and when. Pure: the caller brings the state and the clock.
//!
//! One request per robot is outstanding at a time, so a burst of gaps cannot spawn a query storm;
//! wants that arrive meanwhile are kept and served when it completes. A robot that no longer holds
//! a missing keyframe is not asked for the same gaps again before `retry` has passed.
//!
//! A request that did not complete (it timed out on a slow or lossy link: whatever arrived is
//! kept) is made again, for what is still missing, once `retry` has passed; and gaps that nothing
//! new will reveal (the robot's source has ended) are asked for again by [`Backfill::recheck`].

use std::collections::{BTreeMap, BTreeSet};
use std::time::{Duration, Instant};

use proto::KeyframeRequest;

use super::fleet_state::FleetState;

/// Most sequence numbers listed in one request (the rest follow in the next one).
pub const MAX_SEQS_PER_REQUEST: usize = 4096;

/// Most keyframes one request asks for (its `limit`), the rest in the next one. A keyframe is
/// 40-60 kB: on a link that drops a fifth of its packets TCP carries 25-40 kB/s, so a request for
/// everything a robot made while the station was away did not arrive within the query's 30 s; the
/// replies after that were dropped on the way and asked for, and sent, again. Eight arrive in 10-20
/// s there, and in milliseconds on a sound link.
pub const MAX_KEYFRAMES_PER_REQUEST: u32 = 8;

/// How a request to a robot ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ended {
    /// Every reply came in, fewer than the request's limit: the robot sent all it holds of it.
    Complete,
    /// Every reply came in, as many as the limit: the robot may hold more, asked for at once.
    Full,
    /// It timed out (whatever arrived is kept): made again `retry` later.
    TimedOut,
}

/// Why the station wants keyframes from a robot.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Want {
    /// A keyframe arrived past a gap: ask for the gaps.
    Gaps,
    /// The robot (re)appeared: ask for the gaps and everything after the newest keyframe held.
    Everything,
}

/// The backfill planner of one fleet.
#[derive(Clone, Debug)]
pub struct Backfill {
    retry: Duration,
    in_flight: BTreeSet<u32>,
    wanted: BTreeMap<u32, Want>,
    /// The gaps last asked for per robot, and when.
    last_gaps: BTreeMap<u32, (Vec<u64>, Instant)>,
    /// Robots whose last request did not complete, and when to ask them again.
    again_at: BTreeMap<u32, Instant>,
}

impl Backfill {
    /// A planner that repeats a request for the same gaps at most every `retry`.
    pub fn new(retry: Duration) -> Self {
        Self {
            retry,
            in_flight: BTreeSet::new(),
            wanted: BTreeMap::new(),
            last_gaps: BTreeMap::new(),
            again_at: BTreeMap::new(),
        }
    }

    /// Notes that keyframes are wanted from `robot`.
    pub fn want(&mut self, robot: u32, want: Want) {
        let w = self.wanted.entry(robot).or_insert(want);
        *w = (*w).max(want);
    }

    /// The requests to send now: one per robot with a want and no request outstanding.
    pub fn requests(&mut self, state: &FleetState, now: Instant) -> Vec<(u32, KeyframeRequest)> {
        let due: Vec<u32> = self.again_at.iter().filter(|(_, at)| **at <= now).map(|(&r, _)| r).collect();
        for robot in due {
            self.again_at.remove(&robot);
            self.want(robot, Want::Everything);
        }
        let ready: Vec<(u32, Want)> =
            self.wanted.iter().filter(|(r, _)| !self.in_flight.contains(r)).map(|(&r, &w)| (r, w)).collect();
        let mut out = Vec::new();
        for (robot, want) in ready {
            self.wanted.remove(&robot);
            if let Some(request) = self.request(state, robot, want, now) {
                self.in_flight.insert(robot);
                out.push((robot, request));
            }
        }
        out
    }

    /// The request for `robot`, or `None` when there is nothing (new) to ask for.
    fn request(&mut self, state: &FleetState, robot: u32, want: Want, now: Instant) -> Option<KeyframeRequest> {
        let mut seqs = state.missing(robot);
        seqs.truncate(MAX_SEQS_PER_REQUEST);
        let from_seq = match want {
            Want::Everything => Some(state.robot(robot).and_then(|r| r.max_seq()).map_or(0, |s| s.saturating_add(1))),
            Want::Gaps => None,
        };
        let asked_lately =
            self.last_gaps.get(&robot).is_some_and(|(gaps, at)| *gaps == seqs && now.duration_since(*at) < self.retry);
        if from_seq.is_none() && (seqs.is_empty() || asked_lately) {
            return None;
        }
        self.last_gaps.insert(robot, (seqs.clone(), now));
        Some(KeyframeRequest { seqs, from_seq, limit: Some(MAX_KEYFRAMES_PER_REQUEST) })
    }

    /// The request to `robot` has ended, at `now`.
    pub fn done(&mut self, robot: u32, ended: Ended, now: Instant) {
        self.in_flight.remove(&robot);
        match ended {
            Ended::Complete => {}
            // The next piece: the gaps left, and everything after the newest keyframe now held.
            Ended::Full => self.want(robot, Want::Everything),
            Ended::TimedOut => {
                self.again_at.insert(robot, now + self.retry);
            }
        }
    }

    /// Wants the gaps of every robot that has some: called periodically, so that gaps no new
    /// keyframe reveals are still asked for (each set of gaps at most every `retry`).
    pub fn recheck(&mut self, state: &FleetState) {
        for (&robot, held) in state.robots() {
            if held.missing_count() > 0 {
                self.want(robot, Want::Gaps);
            }
        }
    }

    /// Requests outstanding.
    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }
}
