//! When to merge: changes mark the fleet dirty; a job starts once the changes have settled for
//! `debounce` (or `max_delay` after the first one, so a steady stream of keyframes still gets merged),
//! one job at a time. Changes during a job leave exactly one job pending. Pure: the caller brings the
//! clock.

use std::time::{Duration, Instant};

/// The merge queue of one fleet.
#[derive(Clone, Debug)]
pub struct MergeQueue {
    debounce: Duration,
    max_delay: Duration,
    /// First and last change not yet picked up by a job.
    dirty: Option<(Instant, Instant)>,
    running: bool,
}

impl MergeQueue {
    /// An idle queue.
    pub fn new(debounce: Duration, max_delay: Duration) -> Self {
        Self { debounce, max_delay, dirty: None, running: false }
    }

    /// Records a change of the fleet's maps at `now`.
    pub fn changed(&mut self, now: Instant) {
        let first = self.dirty.map_or(now, |(first, _)| first);
        self.dirty = Some((first, now));
    }

    /// When the pending job may start, if one is pending and none is running.
    pub fn deadline(&self) -> Option<Instant> {
        let (first, last) = self.dirty.filter(|_| !self.running)?;
        Some((last + self.debounce).min(first + self.max_delay))
    }

    /// True when the pending changes have settled at `now` (the last one is `debounce` old), as
    /// opposed to a job forced by `max_delay` under a steady stream of changes.
    pub fn quiet(&self, now: Instant) -> bool {
        self.dirty.is_some_and(|(_, last)| now >= last + self.debounce)
    }

    /// Starts the pending job if it is due at `now`; true when it did.
    pub fn start(&mut self, now: Instant) -> bool {
        if self.deadline().is_none_or(|d| now < d) {
            return false;
        }
        self.dirty = None;
        self.running = true;
        true
    }

    /// The running job has finished.
    pub fn finished(&mut self) {
        self.running = false;
    }

    /// Jobs waiting: 0 or 1.
    pub fn depth(&self) -> u32 {
        u32::from(self.dirty.is_some())
    }

    /// True while a job runs.
    pub fn running(&self) -> bool {
        self.running
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S: Duration = Duration::from_secs(1);

    #[test]
    fn waits_for_changes_to_settle_but_not_forever() {
        let t0 = Instant::now();
        let mut q = MergeQueue::new(2 * S, 10 * S);
        assert_eq!(q.deadline(), None);
        q.changed(t0);
        assert_eq!(q.deadline(), Some(t0 + 2 * S));
        q.changed(t0 + S);
        assert_eq!(q.deadline(), Some(t0 + 3 * S));
        q.changed(t0 + 9 * S);
        assert_eq!(q.deadline(), Some(t0 + 10 * S), "max_delay after the first change");
        assert!(!q.start(t0 + 9 * S));
        assert!(!q.quiet(t0 + 10 * S), "forced by max_delay while changes go on");
        assert!(q.quiet(t0 + 11 * S));
        assert!(q.start(t0 + 10 * S));
        assert_eq!(q.depth(), 0);
    }

    #[test]
    fn changes_during_a_job_leave_one_pending() {
        let t0 = Instant::now();
        let mut q = MergeQueue::new(S, 10 * S);
        q.changed(t0);
        assert!(q.start(t0 + S));
        for i in 0..5 {
            q.changed(t0 + S + i * S / 10);
        }
        assert_eq!(q.depth(), 1);
        assert_eq!(q.deadline(), None, "one job at a time");
        assert!(!q.start(t0 + 100 * S));
        q.finished();
        assert!(q.start(t0 + 100 * S));
        assert!(q.running());
    }
}
