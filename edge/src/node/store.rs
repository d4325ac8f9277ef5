//! The keyframes a robot keeps for backfill: encoded messages by sequence number, oldest evicted first
//! once their total size passes a budget; with a state directory also on disk, every session's,
//! served from there when memory no longer holds them.

use std::collections::BTreeMap;
use std::ops::RangeInclusive;
use std::sync::{Arc, Mutex, PoisonError};

use tracing::warn;

use proto::KeyframeRequest;
use zenoh::bytes::ZBytes;

use super::state_dir::StateDir;

/// Encoded keyframes of the node's session by sequence number, within a byte budget.
#[derive(Debug)]
pub(crate) struct Store {
    session: u64,
    held: BTreeMap<u64, ZBytes>,
    bytes: usize,
    budget: usize,
    disk: Option<Arc<Mutex<StateDir>>>,
}

impl Store {
    /// An empty store of `session` that keeps at most `budget` bytes of payloads (and always the
    /// newest one).
    pub(crate) fn new(session: u64, budget: usize) -> Self {
        Store { session, held: BTreeMap::new(), bytes: 0, budget, disk: None }
    }

    /// The same, writing every keyframe to `disk` too and serving from it what memory does not hold.
    pub(crate) fn with_disk(self, disk: Option<Arc<Mutex<StateDir>>>) -> Self {
        Store { disk, ..self }
    }

    /// Adds a keyframe; returns the sequence numbers evicted to make room, if any.
    pub(crate) fn insert(&mut self, seq: u64, payload: ZBytes) -> Option<RangeInclusive<u64>> {
        if let Some(disk) = &self.disk {
            let written =
                disk.lock().unwrap_or_else(PoisonError::into_inner).write(self.session, seq, &payload.to_bytes());
            if let Err(e) = written {
                // Still published and held in memory: the disk only matters after a crash.
                warn!("keyframe {seq} not kept on disk: {e}");
            }
        }
        self.bytes += payload.len();
        if let Some(old) = self.held.insert(seq, payload) {
            self.bytes -= old.len();
        }
        let mut evicted: Option<RangeInclusive<u64>> = None;
        // Keep the newest even when it alone is over budget: an asker can still catch up on it.
        while self.bytes > self.budget && self.held.len() > 1 {
            let Some((oldest, payload)) = self.held.pop_first() else { break };
            self.bytes -= payload.len();
            evicted = Some(evicted.map_or(oldest..=oldest, |r| *r.start()..=oldest));
        }
        evicted
    }

    /// Bytes of the payloads held.
    pub(crate) fn bytes(&self) -> usize {
        self.bytes
    }

    /// The held keyframes a request asks for, in sequence order, each once; the first `limit` of
    /// them when it sets one. None for a request naming another session.
    pub(crate) fn select(&self, request: &KeyframeRequest) -> Vec<(u64, ZBytes)> {
        let session = request.session.unwrap_or(self.session);
        let limit = request.limit.map_or(usize::MAX, |l| l as usize);
        let mut wanted: BTreeMap<u64, ZBytes> = BTreeMap::new();
        // From disk first: memory's copy of the same keyframe replaces it below.
        if let Some(disk) = &self.disk {
            let disk = disk.lock().unwrap_or_else(PoisonError::into_inner);
            wanted.extend(disk.select(session, request).into_iter().map(|(seq, bytes)| (seq, ZBytes::from(bytes))));
        }
        if session != self.session {
            return wanted.into_iter().take(limit).collect();
        }
        for seq in &request.seqs {
            if let Some(p) = self.held.get(seq) {
                wanted.insert(*seq, p.clone());
            }
        }
        if let Some(from) = request.from_seq {
            wanted.extend(self.held.range(from..).map(|(s, p)| (*s, p.clone())));
        }
        wanted.into_iter().take(limit).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn payload(n: usize) -> ZBytes {
        ZBytes::from(vec![7u8; n])
    }

    fn seqs(store: &Store, request: KeyframeRequest) -> Vec<u64> {
        store.select(&request).into_iter().map(|(s, _)| s).collect()
    }

    #[test]
    fn a_limit_keeps_the_lowest_sequence_numbers() {
        let mut store = Store::new(0, 1000);
        (0..10).for_each(|s| assert_eq!(store.insert(s, payload(10)), None));
        let request = KeyframeRequest { seqs: vec![7, 2], from_seq: Some(5), limit: Some(3), session: None };
        assert_eq!(seqs(&store, request), vec![2, 5, 6]);
    }

    #[test]
    fn requests_get_listed_and_trailing_seqs_once() {
        let mut store = Store::new(0, 1000);
        (0..6).for_each(|s| assert_eq!(store.insert(s, payload(10)), None));
        let request = KeyframeRequest { seqs: vec![4, 1, 3, 99, 1], from_seq: Some(4), limit: None, session: None };
        assert_eq!(seqs(&store, request), vec![1, 3, 4, 5]);
        assert_eq!(seqs(&store, KeyframeRequest::default()), Vec::<u64>::new());
        let after = KeyframeRequest { from_seq: Some(6), ..KeyframeRequest::default() };
        assert_eq!(seqs(&store, after), Vec::<u64>::new());
    }

    #[test]
    fn the_oldest_go_first_and_the_newest_stays() {
        let mut store = Store::new(0, 25);
        assert_eq!(store.insert(0, payload(10)), None);
        assert_eq!(store.insert(1, payload(10)), None);
        assert_eq!(store.insert(2, payload(10)), Some(0..=0));
        assert_eq!(store.insert(3, payload(20)), Some(1..=2));
        assert_eq!(store.insert(4, payload(40)), Some(3..=3));
        assert_eq!(store.bytes(), 40);
        let all = KeyframeRequest { seqs: vec![0, 1, 2, 3], from_seq: Some(0), ..KeyframeRequest::default() };
        assert_eq!(seqs(&store, all), vec![4]);
    }

    #[test]
    fn a_request_for_another_session_gets_nothing_and_one_naming_none_the_current() {
        let mut store = Store::new(7, 1000);
        (0..3).for_each(|s| assert_eq!(store.insert(s, payload(10)), None));
        let from = |session| KeyframeRequest { from_seq: Some(0), session, ..KeyframeRequest::default() };
        assert_eq!(seqs(&store, from(Some(6))), Vec::<u64>::new());
        assert_eq!(seqs(&store, from(Some(7))), vec![0, 1, 2]);
        assert_eq!(seqs(&store, from(None)), vec![0, 1, 2]);
    }
}
