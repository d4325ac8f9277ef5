//! The keyframes a robot keeps for backfill: encoded messages by sequence number, oldest evicted first
//! once their total size passes a budget.

use std::collections::BTreeMap;
use std::ops::RangeInclusive;

use proto::KeyframeRequest;
use zenoh::bytes::ZBytes;

/// Encoded keyframes by sequence number, within a byte budget.
#[derive(Debug)]
pub(crate) struct Store {
    held: BTreeMap<u64, ZBytes>,
    bytes: usize,
    budget: usize,
}

impl Store {
    /// An empty store that keeps at most `budget` bytes of payloads (and always the newest one).
    pub(crate) fn new(budget: usize) -> Self {
        Store { held: BTreeMap::new(), bytes: 0, budget }
    }

    /// Adds a keyframe; returns the sequence numbers evicted to make room, if any.
    pub(crate) fn insert(&mut self, seq: u64, payload: ZBytes) -> Option<RangeInclusive<u64>> {
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
    /// them when it sets one.
    pub(crate) fn select(&self, request: &KeyframeRequest) -> Vec<(u64, ZBytes)> {
        let mut wanted: BTreeMap<u64, ZBytes> = BTreeMap::new();
        for seq in &request.seqs {
            if let Some(p) = self.held.get(seq) {
                wanted.insert(*seq, p.clone());
            }
        }
        if let Some(from) = request.from_seq {
            wanted.extend(self.held.range(from..).map(|(s, p)| (*s, p.clone())));
        }
        let limit = request.limit.map_or(usize::MAX, |l| l as usize);
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
        let mut store = Store::new(1000);
        (0..10).for_each(|s| assert_eq!(store.insert(s, payload(10)), None));
        let request = KeyframeRequest { seqs: vec![7, 2], from_seq: Some(5), limit: Some(3) };
        assert_eq!(seqs(&store, request), vec![2, 5, 6]);
    }

    #[test]
    fn requests_get_listed_and_trailing_seqs_once() {
        let mut store = Store::new(1000);
        (0..6).for_each(|s| assert_eq!(store.insert(s, payload(10)), None));
        let request = KeyframeRequest { seqs: vec![4, 1, 3, 99, 1], from_seq: Some(4), limit: None };
        assert_eq!(seqs(&store, request), vec![1, 3, 4, 5]);
        assert_eq!(seqs(&store, KeyframeRequest::default()), Vec::<u64>::new());
        assert_eq!(seqs(&store, KeyframeRequest { seqs: vec![], from_seq: Some(6), limit: None }), Vec::<u64>::new());
    }

    #[test]
    fn the_oldest_go_first_and_the_newest_stays() {
        let mut store = Store::new(25);
        assert_eq!(store.insert(0, payload(10)), None);
        assert_eq!(store.insert(1, payload(10)), None);
        assert_eq!(store.insert(2, payload(10)), Some(0..=0));
        assert_eq!(store.insert(3, payload(20)), Some(1..=2));
        assert_eq!(store.insert(4, payload(40)), Some(3..=3));
        assert_eq!(store.bytes(), 40);
        assert_eq!(seqs(&store, KeyframeRequest { seqs: vec![0, 1, 2, 3], from_seq: Some(0), limit: None }), vec![4]);
    }
}
