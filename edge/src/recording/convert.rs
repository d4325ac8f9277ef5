//! Converting a recording to the KITTI layout the rest of the project reads.
//!
//! `DIR/velodyne/NNNNNN.bin` holds scan N (numbered from 0 in the order written) as little-endian
//! f32 `x y z intensity` (intensity 0 where the recording has none). A scan that carries rings or
//! per-point times (decoded packets, most driver clouds) is written as `NNNNNN.pcd` (binary)
//! instead, which keeps them: the motion compensation needs the times. `DIR/times.txt` holds one
//! stamp per scan, in seconds relative to the first scan (as the simulator writes it), with
//! microsecond resolution.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use cloud::formats::{FileFormat, FormatError, PcdEncoding, write_cloud};

use super::{RecordingError, Scan};

/// What [`convert`] wrote.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ConvertSummary {
    /// Scans written.
    pub scans: usize,
    /// Points written, over all scans.
    pub points: usize,
    /// Invalid points dropped, over all scans.
    pub dropped: usize,
    /// Scans covering only part of a rotation (a packet capture's first and last).
    pub partial: usize,
    /// Packets or columns missing within scans.
    pub gaps: usize,
    /// Stamp of the first scan, seconds (the zero of `times.txt`).
    pub first_stamp: Option<f64>,
}

/// Why a conversion stopped.
#[derive(Debug, thiserror::Error)]
pub enum ConvertError {
    /// The output directory or `times.txt` could not be created or written.
    #[error("{}: {source}", path.display())]
    Output {
        /// The path concerned.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The output already holds scans, which this conversion would mix with its own.
    #[error("{}: already holds scans; convert into an empty directory", path.display())]
    NotEmpty {
        /// The `velodyne/` directory.
        path: PathBuf,
    },
    /// A scan file could not be written.
    #[error(transparent)]
    Write(#[from] FormatError),
    /// The recording failed; the scans before the failure are written, `times.txt` matches them.
    #[error("stopped after {} scans (those are written): {source}", summary.scans)]
    Recording {
        /// What was written before the failure.
        summary: ConvertSummary,
        /// The recording's error (boxed: it is large and this path is rare).
        source: Box<RecordingError>,
    },
}

/// Writes every scan of `scans` to `out_dir` in the KITTI layout, calling `progress` after each.
///
/// Stops at the first error of the recording, keeping what was written (see
/// [`ConvertError::Recording`]).
pub fn convert(
    scans: impl IntoIterator<Item = Result<Scan, RecordingError>>,
    out_dir: &Path,
    mut progress: impl FnMut(&Scan),
) -> Result<ConvertSummary, ConvertError> {
    let velodyne = out_dir.join("velodyne");
    prepare(&velodyne)?;
    let times_path = out_dir.join("times.txt");
    let output = |source| ConvertError::Output { path: times_path.clone(), source };
    let mut times = BufWriter::new(File::create(&times_path).map_err(output)?);
    let mut summary = ConvertSummary::default();
    for item in scans {
        let scan = match item {
            Ok(scan) => scan,
            Err(source) => {
                times.flush().map_err(output)?;
                return Err(ConvertError::Recording { summary, source: Box::new(source) });
            }
        };
        let format = if scan.cloud.ring.is_some() || scan.cloud.time.is_some() {
            FileFormat::Pcd(PcdEncoding::Binary)
        } else {
            FileFormat::KittiBin
        };
        let name = format!("{:06}.{}", summary.scans, format.extension());
        write_cloud(&velodyne.join(name), &scan.cloud, format)?;
        let first = *summary.first_stamp.get_or_insert(scan.stamp);
        writeln!(times, "{:.6}", scan.stamp - first).map_err(output)?;
        summary.scans += 1;
        summary.points += scan.cloud.len();
        summary.dropped += scan.dropped;
        summary.partial += usize::from(scan.partial);
        summary.gaps += scan.gaps;
        progress(&scan);
    }
    times.flush().map_err(output)?;
    Ok(summary)
}

/// Creates `velodyne/` and checks it holds no scans yet.
fn prepare(velodyne: &Path) -> Result<(), ConvertError> {
    let output = |source| ConvertError::Output { path: velodyne.to_owned(), source };
    std::fs::create_dir_all(velodyne).map_err(output)?;
    for entry in std::fs::read_dir(velodyne).map_err(output)? {
        if entry.map_err(output)?.path().extension().is_some_and(|e| e == "bin" || e == "pcd") {
            return Err(ConvertError::NotEmpty { path: velodyne.to_owned() });
        }
    }
    Ok(())
}
