//! Conversions between the wire `Timestamp` and seconds.

use crate::v1::Timestamp;

impl Timestamp {
    /// A timestamp from seconds (since the epoch or the recording's start); negative times clamp to 0.
    pub fn from_secs_f64(secs: f64) -> Self {
        let secs = secs.max(0.0);
        let whole = secs.floor();
        let nanosec = (((secs - whole) * 1e9).round() as u32).min(999_999_999);
        Timestamp { sec: whole as i64, nanosec }
    }

    /// The timestamp in seconds.
    pub fn as_secs_f64(&self) -> f64 {
        self.sec as f64 + f64::from(self.nanosec) * 1e-9
    }

    /// The current wall-clock time.
    pub fn now() -> Self {
        let d = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
        Timestamp { sec: d.as_secs() as i64, nanosec: d.subsec_nanos() }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seconds_round_trip_to_the_nanosecond() {
        let t = Timestamp::from_secs_f64(1_700_000_000.123_456_7);
        assert_eq!(t.sec, 1_700_000_000);
        assert!((i64::from(t.nanosec) - 123_456_700).abs() < 300, "{}", t.nanosec);
        assert!((Timestamp::from_secs_f64(12.5).as_secs_f64() - 12.5).abs() < 1e-12);
    }
}
