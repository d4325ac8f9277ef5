//! Which keyframes to ask a robot for, and when. Pure: the caller brings the state and the clock.
//!
//! One request per robot is outstanding at a time, so a burst of gaps cannot spawn a query storm;
//! wants that arrive meanwhile are kept and served when it completes. A robot that no longer holds
//! a missing keyframe is not asked for the same gaps again before `retry` has passed.
//!
//! A request that did not complete (it timed out on a slow or lossy link: whatever arrived is
//! kept) is made again, for what is still missing, once `retry` has passed; and gaps that nothing
//! new will reveal (the robot's source has ended) are asked for again by [`Backfill::recheck`].
//!
//! Wants are per robot session ([`Member`]); one request per robot is outstanding, whichever session
//! it asks for. A robot that (re)appears is asked which session it is in now ([`Target::Current`]:
//! its lowest keyframes held, no session named): a station that has not heard of that session yet
//! learns it from the replies and then asks for the rest of it.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use proto::KeyframeRequest;

use super::fleet_state::{FleetState, Member};

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

/// Why the station wants keyframes from a robot session.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Want {
    /// A keyframe arrived past a gap: ask for the gaps.
    Gaps,
    /// The session (re)appeared: ask for the gaps and everything after the newest keyframe held.
    Everything,
}

/// Which of a robot's sessions a request is for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Target {
    /// A session the station holds keyframes of.
    Session(u64),
    /// Whichever session the robot is in now: asked for its lowest keyframe held, which names it.
    Current,
}

/// The backfill planner of one fleet.
#[derive(Clone, Debug)]
pub struct Backfill {
    retry: Duration,
    /// Per robot with a request outstanding, what it asks for.
    in_flight: BTreeMap<u32, Target>,
    wanted: BTreeMap<(u32, Target), Want>,
    /// The gaps last asked for per robot session, and when.
    last_gaps: BTreeMap<Member, (Vec<u64>, Instant)>,
    /// Requests that did not complete, and when to make them again.
    again_at: BTreeMap<(u32, Target), Instant>,
}

impl Backfill {
    /// A planner that repeats a request for the same gaps at most every `retry`.
    pub fn new(retry: Duration) -> Self {
        Self {
            retry,
            in_flight: BTreeMap::new(),
            wanted: BTreeMap::new(),
            last_gaps: BTreeMap::new(),
            again_at: BTreeMap::new(),
        }
    }

    /// Notes that keyframes are wanted from a robot session (a bare robot id: its session 0).
    pub fn want(&mut self, member: impl Into<Member>, want: Want) {
        let member = member.into();
        self.want_target(member.robot, Target::Session(member.session), want);
    }

    /// Notes that `robot` (re)appeared: everything of its newest session held, and which session it
    /// is in now.
    pub fn appeared(&mut self, robot: u32, state: &FleetState) {
        if let Some(newest) = state.newest_session(robot) {
            self.want(newest, Want::Everything);
        }
        self.want_target(robot, Target::Current, Want::Everything);
    }

    fn want_target(&mut self, robot: u32, target: Target, want: Want) {
        let w = self.wanted.entry((robot, target)).or_insert(want);
        *w = (*w).max(want);
    }

    /// The requests to send now: per robot without a request outstanding, the first of its wants
    /// that asks for something.
    pub fn requests(&mut self, state: &FleetState, now: Instant) -> Vec<(u32, KeyframeRequest)> {
        let due: Vec<(u32, Target)> = self.again_at.iter().filter(|(_, at)| **at <= now).map(|(&k, _)| k).collect();
        for (robot, target) in due {
            self.again_at.remove(&(robot, target));
            self.want_target(robot, target, Want::Everything);
        }
        let ready: Vec<((u32, Target), Want)> =
            self.wanted.iter().filter(|((r, _), _)| !self.in_flight.contains_key(r)).map(|(&k, &w)| (k, w)).collect();
        let mut out = Vec::new();
        for ((robot, target), want) in ready {
            if self.in_flight.contains_key(&robot) {
                continue;
            }
            self.wanted.remove(&(robot, target));
            if let Some(request) = self.request(state, robot, target, want, now) {
                self.in_flight.insert(robot, target);
                out.push((robot, request));
            }
        }
        out
    }

    /// The request for a session of `robot`, or `None` when there is nothing (new) to ask for.
    fn request(
        &mut self,
        state: &FleetState,
        robot: u32,
        target: Target,
        want: Want,
        now: Instant,
    ) -> Option<KeyframeRequest> {
        let Target::Session(session) = target else {
            // Of a robot never heard of, the first piece of everything; of one whose sessions are
            // held, one keyframe is enough to tell whether it is in a new one.
            let limit = if state.newest_session(robot).is_some() { 1 } else { MAX_KEYFRAMES_PER_REQUEST };
            return Some(KeyframeRequest { seqs: vec![], from_seq: Some(0), limit: Some(limit), session: None });
        };
        let member = Member::new(robot, session);
        let mut seqs = state.missing(member);
        seqs.truncate(MAX_SEQS_PER_REQUEST);
        let from_seq = match want {
            Want::Everything => Some(state.robot(member).and_then(|r| r.max_seq()).map_or(0, |s| s.saturating_add(1))),
            Want::Gaps => None,
        };
        let asked_lately =
            self.last_gaps.get(&member).is_some_and(|(gaps, at)| *gaps == seqs && now.duration_since(*at) < self.retry);
        if from_seq.is_none() && (seqs.is_empty() || asked_lately) {
            return None;
        }
        self.last_gaps.insert(member, (seqs.clone(), now));
        Some(KeyframeRequest { seqs, from_seq, limit: Some(MAX_KEYFRAMES_PER_REQUEST), session: Some(session) })
    }

    /// The request to `robot` has ended, at `now`.
    pub fn done(&mut self, robot: u32, ended: Ended, now: Instant) {
        let Some(target) = self.in_flight.remove(&robot) else { return };
        match (ended, target) {
            (Ended::Complete, _) => {}
            // The next piece: the gaps left, and everything after the newest keyframe now held.
            (Ended::Full, Target::Session(_)) => self.want_target(robot, target, Want::Everything),
            // Its replies named the session; one not held before is asked for in full when its
            // first keyframe is inserted, a held one by the want of [`Backfill::appeared`].
            (Ended::Full, Target::Current) => {}
            (Ended::TimedOut, _) => {
                self.again_at.insert((robot, target), now + self.retry);
            }
        }
    }

    /// Wants the gaps of every robot session that has some: called periodically, so that gaps no
    /// new keyframe reveals are still asked for (each set of gaps at most every `retry`).
    pub fn recheck(&mut self, state: &FleetState) {
        for (&member, held) in state.robots() {
            if held.missing_count() > 0 {
                self.want(member, Want::Gaps);
            }
        }
    }

    /// Requests outstanding.
    pub fn in_flight(&self) -> usize {
        self.in_flight.len()
    }
}
