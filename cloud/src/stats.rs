//! Nearest-rank summaries of a series: the one percentile helper of the workspace (the odometry's
//! `stats.json` and every benchmark in `eval` use it).

use serde::Serialize;

fn sorted(values: &[f64]) -> Vec<f64> {
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    v
}

/// The nearest-rank `q` quantile of a sorted, non-empty series.
fn nearest_rank(sorted: &[f64], q: f64) -> f64 {
    sorted[((q * sorted.len() as f64).ceil() as usize).clamp(1, sorted.len()) - 1]
}

/// Median, 95th percentile and maximum of a series.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Spread {
    /// Median.
    pub median: f64,
    /// 95th percentile (nearest rank).
    pub p95: f64,
    /// Maximum.
    pub max: f64,
}

impl Spread {
    /// The spread of `values` (all zero when empty).
    pub fn of(values: &[f64]) -> Self {
        if values.is_empty() {
            return Spread::default();
        }
        let v = sorted(values);
        Spread { median: nearest_rank(&v, 0.5), p95: nearest_rank(&v, 0.95), max: v[v.len() - 1] }
    }

    /// The spread of `values`, or `None` when there are none (where a zero would read as a figure).
    pub fn of_some(values: &[f64]) -> Option<Self> {
        (!values.is_empty()).then(|| Spread::of(values))
    }
}

/// Minimum, 5th percentile and median of a series (for figures where the low end matters).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct Low {
    /// Minimum.
    pub min: f64,
    /// 5th percentile (nearest rank).
    pub p5: f64,
    /// Median.
    pub median: f64,
}

impl Low {
    /// The low end of `values` (all zero when empty).
    pub fn of(values: &[f64]) -> Self {
        if values.is_empty() {
            return Low::default();
        }
        let v = sorted(values);
        Low { min: v[0], p5: nearest_rank(&v, 0.05), median: nearest_rank(&v, 0.5) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spread_by_hand() {
        let v: Vec<f64> = (1..=20).map(f64::from).collect();
        // Nearest rank: median = 10th of 20, p95 = 19th.
        assert_eq!(Spread::of(&v), Spread { median: 10.0, p95: 19.0, max: 20.0 });
        assert_eq!(Spread::of(&[]), Spread::default());
        assert_eq!(Spread::of(&[3.0]), Spread { median: 3.0, p95: 3.0, max: 3.0 });
        assert_eq!(Spread::of_some(&v), Some(Spread::of(&v)));
        assert_eq!(Spread::of_some(&[]), None);
    }
}
