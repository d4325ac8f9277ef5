//! `emr-eval codec`: the point-cloud codec's sizes, times and errors on real scans.

use std::fmt;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use cloud::PointCloud;
use cloud::stopwatch::Stopwatch;
use proto::codec::{self, CodecConfig};

use super::median;

/// Codec figures over a directory of scans: one row per scan and mode, then totals, also for
/// keyframes made from the scans.
pub struct CodecReport {
    /// Quantisation step, metres.
    pub step: f64,
    /// Timed repetitions per scan and variant.
    pub repeat: usize,
    /// Figures per scan, in file-name order.
    pub scans: Vec<ScanFigures>,
    /// Figures per keyframe: the scan downsampled to [`KEYFRAME_VOXEL`] centroids.
    pub keyframes: Vec<ScanFigures>,
    /// The same keyframes shuffled, like voxels out of a hash map.
    pub shuffled: Vec<ScanFigures>,
}

/// Voxel edge of the keyframes, metres.
pub const KEYFRAME_VOXEL: f32 = 0.2;

/// One scan in both modes.
pub struct ScanFigures {
    /// File name.
    pub name: String,
    /// Number of points.
    pub points: usize,
    /// Points kept in scan order.
    pub ordered: ModeFigures,
    /// Points sorted in Z-order by the encoder.
    pub reordered: ModeFigures,
}

/// Sizes and median times of one scan in one mode.
#[derive(Clone, Copy)]
pub struct ModeFigures {
    /// Encoded size of xyz alone, bytes.
    pub xyz_bytes: usize,
    /// Encoded size of xyz plus intensity, bytes.
    pub intensity_bytes: usize,
    /// Median encode / decode time of xyz alone, milliseconds.
    pub xyz_ms: (f64, f64),
    /// Median encode / decode time of xyz plus intensity, milliseconds.
    pub intensity_ms: (f64, f64),
    /// Largest coordinate error after decoding, millimetres.
    pub max_error_mm: f64,
    /// Largest intensity error after decoding, sensor units.
    pub max_intensity_error: f64,
}

/// Runs the codec benchmark on every KITTI `.bin` scan in `dir` (or `dir/velodyne`), encoding and
/// decoding each `repeat` times on the calling thread (the codec's zstd contexts never spawn
/// worker threads).
pub fn codec(dir: &Path, step: f64, repeat: usize) -> Result<CodecReport> {
    let repeat = repeat.max(1);
    let (mut scans, mut keyframes, mut shuffled) = (Vec::new(), Vec::new(), Vec::new());
    for path in kitti_scans(dir)? {
        let scan = read_kitti(&path)?;
        let name = path.file_name().map_or_else(String::new, |n| n.to_string_lossy().into_owned());
        let keyframe = cloud::voxel::downsample(&scan, KEYFRAME_VOXEL)?;
        let mixed = shuffle(&keyframe);
        scans.push(figures(&name, &scan, step, repeat)?);
        keyframes.push(figures(&name, &keyframe, step, repeat)?);
        shuffled.push(figures(&name, &mixed, step, repeat)?);
        tracing::info!(scan = %name, "measured");
    }
    Ok(CodecReport { step, repeat, scans, keyframes, shuffled })
}

/// `cloud` measured in both modes.
fn figures(name: &str, cloud: &PointCloud, step: f64, repeat: usize) -> Result<ScanFigures> {
    let config = |reorder| CodecConfig { step, reorder, ..CodecConfig::default() };
    Ok(ScanFigures {
        name: name.to_owned(),
        points: cloud.len(),
        ordered: measure(cloud, &config(false), repeat)?,
        reordered: measure(cloud, &config(true), repeat)?,
    })
}

/// `cloud` in a fixed pseudo-random order (Fisher-Yates with a xorshift generator).
fn shuffle(cloud: &PointCloud) -> PointCloud {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut order: Vec<usize> = (0..cloud.len()).collect();
    for i in (1..order.len()).rev() {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        order.swap(i, (state % (i as u64 + 1)) as usize);
    }
    cloud.select(&order)
}

/// The `.bin` files of `dir`, or of `dir/velodyne` if `dir` has none, sorted by name.
fn kitti_scans(dir: &Path) -> Result<Vec<PathBuf>> {
    for candidate in [dir.to_path_buf(), dir.join("velodyne")] {
        let Ok(entries) = std::fs::read_dir(&candidate) else {
            continue;
        };
        let mut bins: Vec<PathBuf> = entries
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|e| e == "bin"))
            .collect();
        if !bins.is_empty() {
            bins.sort();
            return Ok(bins);
        }
    }
    bail!("no KITTI .bin scans in {} or its velodyne/ subdirectory", dir.display())
}

/// A KITTI scan: little-endian f32 records of x, y, z, reflectance.
fn read_kitti(path: &Path) -> Result<PointCloud> {
    let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
    if bytes.len() % 16 != 0 {
        bail!("{}: {} bytes is not a whole number of 16-byte records", path.display(), bytes.len());
    }
    let f = |r: &[u8], i: usize| f32::from_le_bytes([r[4 * i], r[4 * i + 1], r[4 * i + 2], r[4 * i + 3]]);
    let records = bytes.chunks_exact(16);
    let mut cloud = PointCloud::from_points(records.clone().map(|r| [f(r, 0), f(r, 1), f(r, 2)].into()).collect());
    cloud.intensity = Some(records.map(|r| f(r, 3)).collect());
    Ok(cloud)
}

/// Sizes, median times and errors of `cloud` under `config`, without and with intensity.
fn measure(cloud: &PointCloud, config: &CodecConfig, repeat: usize) -> Result<ModeFigures> {
    let xyz = PointCloud::from_points(cloud.points.clone());
    let (xyz_bytes, xyz_ms, xyz_decoded) = time_round_trip(&xyz, config, repeat)?;
    let (intensity_bytes, intensity_ms, decoded) = time_round_trip(cloud, config, repeat)?;
    let (max_error_mm, max_intensity_error) = if config.reorder {
        reordered_errors(cloud, &decoded)
    } else {
        (max_error(cloud.xyz(), xyz_decoded.xyz()) * 1e3, max_intensity_error(cloud, &decoded))
    };
    Ok(ModeFigures { xyz_bytes, intensity_bytes, xyz_ms, intensity_ms, max_error_mm, max_intensity_error })
}

/// Encoded size, median encode and decode milliseconds, and the decoded cloud.
fn time_round_trip(cloud: &PointCloud, config: &CodecConfig, repeat: usize) -> Result<(usize, (f64, f64), PointCloud)> {
    let (mut encode_ms, mut decode_ms) = (Vec::with_capacity(repeat), Vec::with_capacity(repeat));
    let mut last = None;
    for _ in 0..repeat {
        let mut watch = Stopwatch::start();
        let bytes = codec::encode(cloud, config)?;
        encode_ms.push(watch.lap_ms());
        let decoded = codec::decode(&bytes)?;
        decode_ms.push(watch.lap_ms());
        last = Some((bytes.len(), decoded));
    }
    let (size, decoded) = last.context("no repetition ran")?;
    if decoded.len() != cloud.len() {
        bail!("decoded {} points out of {}", decoded.len(), cloud.len());
    }
    Ok((size, (median(&encode_ms), median(&decode_ms)), decoded))
}

/// Largest per-coordinate difference, metres.
fn max_error(a: &[[f32; 3]], b: &[[f32; 3]]) -> f64 {
    let coordinate_errors = a.iter().zip(b).flat_map(|(p, q)| (0..3).map(move |k| f64::from((p[k] - q[k]).abs())));
    coordinate_errors.fold(0.0, f64::max)
}

fn max_intensity_error(a: &PointCloud, b: &PointCloud) -> f64 {
    let (Some(a), Some(b)) = (&a.intensity, &b.intensity) else {
        return f64::NAN;
    };
    a.iter().zip(b).map(|(x, y)| f64::from((x - y).abs())).fold(0.0, f64::max)
}

/// Errors of a reordered decode, whose points no longer line up with the input. Quantising is
/// monotonic, so sorting the values of one axis (or channel) on both sides pairs every input
/// value with its own decoded value, or with an equal one.
fn reordered_errors(original: &PointCloud, decoded: &PointCloud) -> (f64, f64) {
    let axis = |cloud: &PointCloud, k: usize| cloud.xyz().iter().map(|p| p[k]).collect();
    let xyz = (0..3).map(|k| sorted_error(axis(original, k), axis(decoded, k)));
    let intensity = match (&original.intensity, &decoded.intensity) {
        (Some(a), Some(b)) => sorted_error(a.clone(), b.clone()),
        _ => f64::NAN,
    };
    (xyz.fold(0.0, f64::max) * 1e3, intensity)
}

/// Largest difference between the values of `a` and `b` paired in sorted order.
fn sorted_error(mut a: Vec<f32>, mut b: Vec<f32>) -> f64 {
    a.sort_by(f32::total_cmp);
    b.sort_by(f32::total_cmp);
    a.iter().zip(&b).map(|(x, y)| f64::from((x - y).abs())).fold(0.0, f64::max)
}

impl fmt::Display for CodecReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "codec, step {} mm, median of {} runs, one thread; ratio = raw f32 xyz (12 B/point) / encoded",
            self.step * 1e3,
            self.repeat
        )?;
        writeln!(
            f,
            "{:<11} {:<9} {:>7} {:>9} {:>6} {:>6} {:>6} {:>9} {:>6} {:>6} {:>6} {:>7} {:>7}",
            "scan",
            "mode",
            "points",
            "xyz B",
            "ratio",
            "enc ms",
            "dec ms",
            "+int B",
            "ratio",
            "enc ms",
            "dec ms",
            "err mm",
            "int err"
        )?;
        for scan in &self.scans {
            for (mode, m) in [("ordered", &scan.ordered), ("reordered", &scan.reordered)] {
                row(f, &scan.name, mode, scan.points, m)?;
            }
        }
        let sets = [("all", &self.scans), ("keyframes", &self.keyframes), ("shuffled", &self.shuffled)];
        for (name, set) in sets {
            for reordered in [false, true] {
                let figures: Vec<ModeFigures> =
                    set.iter().map(|s| if reordered { s.reordered } else { s.ordered }).collect();
                let mode = if reordered { "reordered" } else { "ordered" };
                if let Some(total) = totals(&figures) {
                    row(f, name, mode, set.iter().map(|s| s.points).sum(), &total)?;
                }
            }
        }
        writeln!(
            f,
            "keyframes: the scans downsampled to {} m voxel centroids; shuffled: the same in random order",
            KEYFRAME_VOXEL
        )?;
        if let Some(total) = totals(&self.scans.iter().map(|s| s.ordered).collect::<Vec<_>>()) {
            let points: usize = self.scans.iter().map(|s| s.points).sum();
            write!(
                f,
                "scans in sensor order, xyz: {:.2}x smaller than f32 xyz, encode + decode {:.2} ms (median scan)",
                12.0 * points as f64 / total.xyz_bytes as f64,
                total.xyz_ms.0 + total.xyz_ms.1
            )?;
        }
        Ok(())
    }
}

fn row(f: &mut fmt::Formatter<'_>, name: &str, mode: &str, points: usize, m: &ModeFigures) -> fmt::Result {
    let ratio = |bytes: usize| 12.0 * points as f64 / bytes as f64;
    writeln!(
        f,
        "{name:<11} {mode:<9} {points:>7} {:>9} {:>6.2} {:>6.2} {:>6.2} {:>9} {:>6.2} {:>6.2} {:>6.2} {:>7.4} {:>7.4}",
        m.xyz_bytes,
        ratio(m.xyz_bytes),
        m.xyz_ms.0,
        m.xyz_ms.1,
        m.intensity_bytes,
        ratio(m.intensity_bytes),
        m.intensity_ms.0,
        m.intensity_ms.1,
        m.max_error_mm,
        m.max_intensity_error
    )
}

/// Summed sizes, median of the per-scan median times, worst errors.
fn totals(modes: &[ModeFigures]) -> Option<ModeFigures> {
    if modes.is_empty() {
        return None;
    }
    let med = |pick: fn(&ModeFigures) -> f64| median(&modes.iter().map(pick).collect::<Vec<_>>());
    Some(ModeFigures {
        xyz_bytes: modes.iter().map(|m| m.xyz_bytes).sum(),
        intensity_bytes: modes.iter().map(|m| m.intensity_bytes).sum(),
        xyz_ms: (med(|m| m.xyz_ms.0), med(|m| m.xyz_ms.1)),
        intensity_ms: (med(|m| m.intensity_ms.0), med(|m| m.intensity_ms.1)),
        max_error_mm: modes.iter().map(|m| m.max_error_mm).fold(0.0, f64::max),
        max_intensity_error: modes.iter().map(|m| m.max_intensity_error).fold(0.0, f64::max),
    })
}
