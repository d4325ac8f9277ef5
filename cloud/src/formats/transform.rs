//! Rigid transforms in text files, as the reference poses of registration pairs come: 16 numbers
//! (a 4x4 matrix, row-major) or 12 (a KITTI `[R | t]` row), whitespace separated.

use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Matrix4};

use crate::se3::from_matrix;

/// A transform file that could not be read, and why.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {reason}")]
pub struct TransformError {
    /// The file.
    pub path: PathBuf,
    /// What was wrong with it.
    pub reason: String,
}

/// Parses a transform from its text; the reason when it is not one.
pub fn parse_transform(text: &str) -> Result<Isometry3<f64>, String> {
    let values: Vec<f64> =
        text.split_whitespace().map(str::parse).collect::<Result<_, _>>().map_err(|e| format!("{e}"))?;
    if values.len() != 16 && values.len() != 12 {
        return Err(format!("{} numbers, expected 16 (4x4) or 12 (3x4)", values.len()));
    }
    let mut m = Matrix4::identity();
    for (i, v) in values.iter().take(12).enumerate() {
        m[(i / 4, i % 4)] = *v;
    }
    from_matrix(&m).ok_or_else(|| "not a rigid transform".into())
}

/// Reads a transform file ([`parse_transform`]).
pub fn read_transform(path: &Path) -> Result<Isometry3<f64>, TransformError> {
    let fail = |reason: String| TransformError { path: path.to_owned(), reason };
    let text = std::fs::read_to_string(path).map_err(|e| fail(e.to_string()))?;
    parse_transform(&text).map_err(fail)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn four_by_four_and_kitti_rows_read_alike_and_the_rest_is_refused() {
        let row = "0 -1 0 1.5  1 0 0 -2  0 0 1 0.25";
        let kitti = parse_transform(row).unwrap();
        let full = parse_transform(&format!("{row}  0 0 0 1")).unwrap();
        assert_eq!(kitti, full);
        assert!((kitti.translation.vector - nalgebra::Vector3::new(1.5, -2.0, 0.25)).norm() < 1e-12);
        assert!((kitti.rotation.angle() - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert!(parse_transform("1 0 0").unwrap_err().contains("3 numbers"));
        assert!(parse_transform(&"2 ".repeat(12)).unwrap_err().contains("not a rigid transform"));
        assert!(parse_transform("1 0 0 x 0 1 0 0 0 0 1 0").is_err());
        let err = read_transform(Path::new("/nonexistent/T.txt")).unwrap_err();
        assert!(err.to_string().starts_with("/nonexistent/T.txt: "), "{err}");
    }
}
