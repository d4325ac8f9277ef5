//! Writes a simulated sequence in the KITTI odometry layout.
//!
//! `DIR/velodyne/NNNNNN.bin` holds the raw (motion-distorted) sweeps as little-endian f32
//! `x y z intensity` records; `DIR/poses.txt` holds one ground-truth pose per sweep as the 12
//! numbers of the row-major 3 × 4 matrix, re-based so the first pose is the identity
//! (`T_0⁻¹ · T_k`, the sensor frame at the end of sweep 0 is the origin); `DIR/times.txt` holds
//! each sweep's start time in seconds, the first at 0.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use cloud::formats::{FileFormat, FormatError, write_cloud};

use crate::simulator::Simulator;

/// Why a sequence could not be written.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// A directory or text file could not be created or written.
    #[error("cannot write {}: {source}", path.display())]
    Io {
        /// The path concerned.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A scan file could not be written.
    #[error(transparent)]
    Scan(#[from] FormatError),
}

/// What was written.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Written {
    /// Sweeps written.
    pub frames: usize,
    /// Points over all sweeps.
    pub points: usize,
}

/// Writes sweeps `0..frames` of `sim` under `dir`; `progress` is called with the number of sweeps
/// done after each one.
pub fn write_kitti(
    sim: &Simulator,
    dir: &Path,
    frames: usize,
    progress: impl FnMut(usize),
) -> Result<Written, ExportError> {
    write_kitti_from(sim, dir, 0, frames, progress)
}

/// Writes sweeps `start..start + frames` of `sim` under `dir`, numbered from 0 with the poses and
/// times re-based on sweep `start` (a robot that starts there); `progress` as [`write_kitti`]'s.
pub fn write_kitti_from(
    sim: &Simulator,
    dir: &Path,
    start: usize,
    frames: usize,
    mut progress: impl FnMut(usize),
) -> Result<Written, ExportError> {
    let velodyne = dir.join("velodyne");
    std::fs::create_dir_all(&velodyne).map_err(|source| ExportError::Io { path: velodyne.clone(), source })?;
    let mut poses = String::new();
    let mut times = String::new();
    let mut points = 0;
    let first = sim.ground_truth(start).inverse();
    let start_stamp = sim.stamp(start);
    for frame in 0..frames {
        let scan = sim.scan(start + frame);
        write_cloud(&velodyne.join(format!("{frame:06}.bin")), &scan.cloud, FileFormat::KittiBin)?;
        points += scan.cloud.len();
        let row = cloud::se3::to_kitti_row(&(first * scan.ground_truth));
        let line: Vec<String> = row.iter().map(|v| format!("{v:.9}")).collect();
        let _ = writeln!(poses, "{}", line.join(" "));
        let _ = writeln!(times, "{:.6}", scan.stamp - start_stamp);
        progress(frame + 1);
    }
    for (name, text) in [("poses.txt", poses), ("times.txt", times)] {
        let path = dir.join(name);
        std::fs::write(&path, text).map_err(|source| ExportError::Io { path, source })?;
    }
    Ok(Written { frames, points })
}
