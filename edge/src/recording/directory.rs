//! A directory of scan files (KITTI `.bin`, `.pcd`, `.ply`), read in file-name order.
//!
//! Stamps come from `times.txt` (one number of seconds per line, as KITTI ships it) in the
//! directory, or in its parent when the directory is a KITTI `velodyne/` folder. Without one, scan
//! `i` is stamped `i * period` ([`super::RecordingOptions::directory_period_s`]). A `times.txt`
//! with more lines than there are scans is the usual cut of a KITTI snippet (the sequence's stamps,
//! a few of its scans): KITTI names a scan by its index, so scan `000123.bin` takes line 123.

use std::path::{Path, PathBuf};

use super::{RawScan, RecordingErrorKind};

/// Scan files and their stamps, read one file at a time.
pub(super) struct DirectorySource {
    files: Vec<PathBuf>,
    stamps: Vec<f64>,
    next: usize,
}

impl DirectorySource {
    /// Lists the scans of `dir` (or of `dir/velodyne` when `dir` holds none) and their stamps.
    pub(super) fn open(dir: &Path, period_s: f64) -> Result<Self, RecordingErrorKind> {
        let mut scan_dir = dir.to_path_buf();
        let mut files = scan_files(&scan_dir)?;
        if files.is_empty() && dir.join("velodyne").is_dir() {
            scan_dir = dir.join("velodyne");
            files = scan_files(&scan_dir)?;
        }
        if files.is_empty() {
            return Err(RecordingErrorKind::NoScans);
        }
        let stamps = match times_file(&scan_dir) {
            Some(path) => stamps_of(&files, &read_times(&path)?, &path)?,
            None => (0..files.len()).map(|i| i as f64 * period_s).collect(),
        };
        Ok(DirectorySource { files, stamps, next: 0 })
    }

    /// Reads the next file; a file that fails to parse is an error for that scan only.
    pub(super) fn next_scan(&mut self) -> Option<Result<RawScan, RecordingErrorKind>> {
        let index = self.next;
        let file = self.files.get(index)?;
        self.next += 1;
        let loaded = match cloud::formats::read_cloud(file) {
            Ok(loaded) => loaded,
            Err(e) => return Some(Err(RecordingErrorKind::ScanFile { index, source: e })),
        };
        let stamp = self.stamps.get(index).copied().unwrap_or(0.0);
        Some(Ok(RawScan {
            cloud: loaded.cloud,
            stamp,
            index,
            dropped: loaded.dropped_non_finite,
            gaps: 0,
            partial: false,
        }))
    }
}

/// The `.bin`, `.pcd` and `.ply` files of `dir` (extension case-insensitive), sorted by name.
fn scan_files(dir: &Path) -> Result<Vec<PathBuf>, RecordingErrorKind> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).map_err(RecordingErrorKind::Io)? {
        let path = entry.map_err(RecordingErrorKind::Io)?.path();
        let extension = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase());
        if path.is_file() && matches!(extension.as_deref(), Some("bin" | "pcd" | "ply")) {
            files.push(path);
        }
    }
    files.sort_by(|a, b| a.file_name().cmp(&b.file_name()));
    Ok(files)
}

/// `times.txt` beside the scans, or beside a KITTI `velodyne/` folder.
fn times_file(scan_dir: &Path) -> Option<PathBuf> {
    let beside = scan_dir.join("times.txt");
    if beside.is_file() {
        return Some(beside);
    }
    let parent = scan_dir.parent().filter(|_| scan_dir.file_name().is_some_and(|n| n == "velodyne"))?;
    Some(parent.join("times.txt")).filter(|p| p.is_file())
}

/// The stamps in `path`, one per non-blank line.
fn read_times(path: &Path) -> Result<Vec<f64>, RecordingErrorKind> {
    let text = std::fs::read_to_string(path).map_err(RecordingErrorKind::Io)?;
    let mut stamps = Vec::new();
    for (i, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let stamp = line.trim().parse::<f64>().ok().filter(|s| s.is_finite());
        let syntax = || RecordingErrorKind::TimesSyntax { file: path.to_owned(), line: i + 1, text: line.to_owned() };
        stamps.push(stamp.ok_or_else(syntax)?);
    }
    Ok(stamps)
}

/// Each file's stamp: line `i` for the `i`-th file when there is one line per file; otherwise, when
/// every file is named by a sequence index (`000123.bin`) within the list, the line of that index.
fn stamps_of(files: &[PathBuf], times: &[f64], path: &Path) -> Result<Vec<f64>, RecordingErrorKind> {
    if times.len() == files.len() {
        return Ok(times.to_vec());
    }
    let by_index: Option<Vec<f64>> = files.iter().map(|f| times.get(sequence_index(f)?).copied()).collect();
    by_index.ok_or_else(|| RecordingErrorKind::TimesCount {
        file: path.to_owned(),
        stamps: times.len(),
        scans: files.len(),
    })
}

/// The index a KITTI scan file is named by: its stem, all decimal digits.
fn sequence_index(file: &Path) -> Option<usize> {
    let stem = file.file_stem()?.to_str()?;
    stem.bytes().all(|b| b.is_ascii_digit()).then(|| stem.parse().ok()).flatten()
}
