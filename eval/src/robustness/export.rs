//! A case's scans on disk in the KITTI layout, so another odometry (KISS-ICP) reads exactly them.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use cloud::formats::{FileFormat, FormatError, write_cloud};
use cloud::trajectory::Trajectory;
use nalgebra::Isometry3;

use super::case::Case;

/// Why a case could not be written.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// A directory or text file could not be written.
    #[error("cannot write {}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
    /// A scan file could not be written.
    #[error(transparent)]
    Scan(#[from] FormatError),
}

/// Writes `poses` (odometry frame) as DIR/poses_kitti.txt, creating DIR.
pub fn write_poses(poses: &[Isometry3<f64>], dir: &Path) -> Result<(), ExportError> {
    std::fs::create_dir_all(dir).map_err(|source| ExportError::Io { path: dir.to_owned(), source })?;
    let path = dir.join("poses_kitti.txt");
    let text = Trajectory { poses: poses.to_vec(), stamps: None }.to_kitti();
    std::fs::write(&path, text).map_err(|source| ExportError::Io { path, source })
}

/// Writes `case` under `dir`: DIR/velodyne/NNNNNN.bin (x y z intensity, float32, the points in the
/// case's order; numbered from 0 in the case's order), DIR/poses.txt (the ground truth relative to
/// the first scan, KITTI layout) and DIR/times.txt (sweep starts relative to the first, seconds).
pub fn write_kitti(case: &Case, dir: &Path) -> Result<(), ExportError> {
    let velodyne = dir.join("velodyne");
    std::fs::create_dir_all(&velodyne).map_err(|source| ExportError::Io { path: velodyne.clone(), source })?;
    for (i, scan) in case.scans.iter().enumerate() {
        write_cloud(&velodyne.join(format!("{i:06}.bin")), &scan.cloud, FileFormat::KittiBin)?;
    }
    let truth = case.truth();
    let first = truth.first().map(|p| p.inverse()).unwrap_or_default();
    let poses = Trajectory { poses: truth.iter().map(|p| first * p).collect(), stamps: None }.to_kitti();
    let start = case.scans.first().map_or(0.0, |s| s.stamp);
    let mut times = String::new();
    for scan in &case.scans {
        let _ = writeln!(times, "{:.6}", scan.stamp - start);
    }
    for (name, text) in [("poses.txt", poses), ("times.txt", times)] {
        let path = dir.join(name);
        std::fs::write(&path, text).map_err(|source| ExportError::Io { path, source })?;
    }
    Ok(())
}
