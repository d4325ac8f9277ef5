//! Mean and covariance of a point set, the input of every local line or plane fit.

use nalgebra::{Matrix3, Vector3};

/// Mean and (population) covariance of `points`, in two passes: one-pass sums of squares cancel
/// badly for points far from the origin. Empty input gives NaNs.
pub fn mean_covariance<I>(points: I) -> (Vector3<f64>, Matrix3<f64>)
where
    I: IntoIterator<Item = Vector3<f64>>,
    I::IntoIter: Clone,
{
    let points = points.into_iter();
    let (sum, n) = points.clone().fold((Vector3::zeros(), 0usize), |(s, n), p| (s + p, n + 1));
    let mean = sum / n as f64;
    let cov = points.fold(Matrix3::zeros(), |acc, p| {
        let d = p - mean;
        acc + d * d.transpose()
    }) / n as f64;
    (mean, cov)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn by_hand() {
        // x in {0, 2}, y in {0, 4}: mean (1, 2, 0), var x 1, var y 4, no covariance.
        let pts = [
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(2.0, 0.0, 0.0),
            Vector3::new(0.0, 4.0, 0.0),
            Vector3::new(2.0, 4.0, 0.0),
        ];
        let (mean, cov) = mean_covariance(pts);
        assert_eq!(mean, Vector3::new(1.0, 2.0, 0.0));
        assert_eq!(cov, Matrix3::from_diagonal(&Vector3::new(1.0, 4.0, 0.0)));
    }
}
