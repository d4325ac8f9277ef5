//! Stage timing: one clock per pipeline, read once per stage, so the algorithm reads without
//! `Instant` bookkeeping between its steps.

use std::time::{Duration, Instant};

/// Wall time since a start and since the last lap.
#[derive(Clone, Copy, Debug)]
pub struct Stopwatch {
    start: Instant,
    lap: Instant,
}

impl Stopwatch {
    /// A stopwatch running from now.
    pub fn start() -> Self {
        let now = Instant::now();
        Stopwatch { start: now, lap: now }
    }

    /// Time since the previous lap (or the start); the next lap is measured from now.
    pub fn lap(&mut self) -> Duration {
        let now = Instant::now();
        let lap = now - self.lap;
        self.lap = now;
        lap
    }

    /// [`Stopwatch::lap`] in milliseconds.
    pub fn lap_ms(&mut self) -> f64 {
        millis(self.lap())
    }

    /// Time since the start.
    pub fn elapsed(&self) -> Duration {
        self.start.elapsed()
    }

    /// [`Stopwatch::elapsed`] in milliseconds.
    pub fn elapsed_ms(&self) -> f64 {
        millis(self.elapsed())
    }
}

/// `f()` and how long it took: for a stage timed alone, with untimed work around it.
pub fn timed<T>(f: impl FnOnce() -> T) -> (T, Duration) {
    let start = Instant::now();
    let value = f();
    (value, start.elapsed())
}

/// A duration in milliseconds, the unit of every timing report.
pub fn millis(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn laps_add_up_to_the_elapsed_time() {
        let mut watch = Stopwatch::start();
        std::thread::sleep(Duration::from_millis(2));
        let first = watch.lap();
        std::thread::sleep(Duration::from_millis(2));
        let second = watch.lap();
        assert!(first >= Duration::from_millis(2) && second >= Duration::from_millis(2));
        assert!(watch.elapsed() >= first + second);
        assert_eq!(millis(Duration::from_micros(1500)), 1.5);
        let (value, took) = timed(|| {
            std::thread::sleep(Duration::from_millis(2));
            7
        });
        assert!(value == 7 && took >= Duration::from_millis(2));
    }
}
