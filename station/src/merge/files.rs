//! File-level entry points behind `emr-station merge` and `emr-station align`: read clouds, run the
//! library, write `global_map.ply`, `transforms.json` and `top_down.png`.

use std::path::{Path, PathBuf};

use cloud::PointCloud;
use cloud::formats::{FileFormat, FormatError, PcdEncoding, PlyEncoding, read_cloud, write_cloud};
use cloud::kdtree::KdTree;
use cloud::registration::{Method, RegistrationError, align};
use cloud::voxel::downsample;
use nalgebra::Isometry3;
use pictures::{PictureError, RobotLayer, TopDown, TopDownConfig};
use serde_json::{Value, json};

use super::PairRejection;
use super::{MergeConfig, MergeError, MergeReport, PairVerdict, PreparedMap, estimate_pair};
use crate::pairwise::{FeatureError, confidence};

/// Why a file-level command failed.
#[derive(Debug, thiserror::Error)]
pub enum FilesError {
    /// A cloud could not be read or written.
    #[error(transparent)]
    Cloud(#[from] FormatError),
    /// A file other than a cloud could not be written.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The merge refused its input or configuration.
    #[error(transparent)]
    Merge(#[from] MergeError),
    /// Fine registration refused its input.
    #[error(transparent)]
    Registration(#[from] RegistrationError),
    /// A map of the pair cannot be registered at all.
    #[error("{which} map is unusable: {reason}")]
    Unusable {
        /// "source" or "target".
        which: &'static str,
        /// Why its features failed.
        reason: FeatureError,
    },
    /// Global registration found no reliable transform.
    #[error("not aligned: {0}")]
    NotAligned(PairRejection),
    /// The top-down picture could not be drawn.
    #[error("top_down.png: {0}")]
    Picture(#[from] PictureError),
}

/// Reads every map (.pcd, .ply, .bin); non-finite points are dropped by the readers.
pub fn read_maps(paths: &[PathBuf]) -> Result<Vec<PointCloud>, FilesError> {
    paths.iter().map(|p| Ok(read_cloud(p)?.cloud)).collect()
}

/// A transform as 4 rows of 4 numbers.
pub fn matrix_rows(t: &Isometry3<f64>) -> [[f64; 4]; 4] {
    let m = t.to_homogeneous();
    std::array::from_fn(|r| std::array::from_fn(|c| m[(r, c)]))
}

/// The `transforms.json` document: per map its global transform, per accepted edge the transform
/// mapping map `b` into map `a`, and the stage timings.
pub fn transforms_json(inputs: &[PathBuf], report: &MergeReport) -> Value {
    let maps: Vec<Value> = report
        .maps
        .iter()
        .zip(inputs)
        .map(|(m, path)| {
            json!({
                "input": path.display().to_string(),
                "transform": matrix_rows(&m.transform()),
                "confidence": m.confidence(),
                "status": if m.is_merged() { "merged" } else { "unmerged" },
            })
        })
        .collect();
    let edges: Vec<Value> = report
        .edges()
        .map(|e| {
            json!({
                "a": e.a,
                "b": e.b,
                "transform": matrix_rows(&e.transform),
                "confidence": e.confidence.score,
                "inliers": e.inliers,
            })
        })
        .collect();
    let ms = cloud::stopwatch::millis;
    let t = &report.timing;
    json!({
        "maps": maps,
        "edges": edges,
        "timing_ms": {
            "features": ms(t.features),
            "pairs": ms(t.pairs),
            "graph": ms(t.graph),
            "assemble": ms(t.assemble),
            "total": ms(t.total),
        },
    })
}

/// Merges the files and writes `dir/global_map.ply` (binary little endian) and
/// `dir/transforms.json`.
pub fn merge_files(inputs: &[PathBuf], dir: &Path, config: &MergeConfig) -> Result<MergeReport, FilesError> {
    let maps = read_maps(inputs)?;
    let report = super::merge(&maps, config)?;
    std::fs::create_dir_all(dir).map_err(|source| FilesError::Io { path: dir.to_owned(), source })?;
    write_cloud(&dir.join("global_map.ply"), &report.global_map, FileFormat::Ply(PlyEncoding::BinaryLittleEndian))?;
    let json_path = dir.join("transforms.json");
    let text = serde_json::to_string_pretty(&transforms_json(inputs, &report)).expect("JSON values always serialise");
    std::fs::write(&json_path, text + "\n").map_err(|source| FilesError::Io { path: json_path, source })?;
    let png_path = dir.join("top_down.png");
    let png = top_down_png(inputs, &maps, &report, &TopDownConfig::default())?;
    std::fs::write(&png_path, png).map_err(|source| FilesError::Io { path: png_path, source })?;
    Ok(report)
}

/// The merged maps seen from above in the global frame, each input in its own colour (PNG
/// bytes). Unmerged maps are listed in the legend and not drawn: they have no place there.
pub fn top_down_png(
    inputs: &[PathBuf],
    maps: &[PointCloud],
    report: &MergeReport,
    config: &TopDownConfig,
) -> Result<Vec<u8>, FilesError> {
    let robots = report.maps.iter().zip(inputs).zip(maps).map(|((m, path), map)| {
        let name = path.file_name().map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned());
        if !m.is_merged() {
            return RobotLayer { label: format!("{name}: unmerged"), ..RobotLayer::default() };
        }
        let t = m.transform().cast::<f32>();
        let points = map.points.iter().map(|p| (t * p).coords.into()).collect();
        RobotLayer { label: name, points, ..RobotLayer::default() }
    });
    let title = format!("emr-station merge: {} of {} maps merged, top view", report.merged(), report.maps.len());
    let scene = TopDown { title, robots: robots.collect() };
    Ok(pictures::top_down(&scene, config)?.png)
}

/// How `emr-station align` registers a pair.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AlignMethod {
    /// The merge's pairwise estimate: global registration, VGICP refinement, confidence.
    Global,
    /// VGICP alone, from the initial guess.
    Vgicp,
    /// GICP alone, from the initial guess.
    Gicp,
}

/// The result of one registration of SOURCE onto TARGET.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Alignment {
    /// Maps SOURCE points into the TARGET frame.
    pub transform: Isometry3<f64>,
    /// The overlap-aware score (global only: it needs the RANSAC inlier ratio).
    pub score: Option<f64>,
    /// Share of source points with a target point within the overlap distance.
    pub overlap: f64,
    /// map_merge_3d's fitness `1 / mean(d²)`, 1/m².
    pub fitness: f64,
    /// RANSAC inliers (global only).
    pub inliers: Option<usize>,
}

/// Registers `source` onto `target` with `method` (`init` is ignored by [`AlignMethod::Global`]).
pub fn align_pair(
    source: &PointCloud,
    target: &PointCloud,
    init: &Isometry3<f64>,
    method: AlignMethod,
    config: &MergeConfig,
) -> Result<Alignment, FilesError> {
    match method {
        AlignMethod::Global => align_global(source, target, config),
        AlignMethod::Vgicp => align_fine(source, target, init, Method::Vgicp, config),
        AlignMethod::Gicp => align_fine(source, target, init, Method::Gicp, config),
    }
}

fn align_global(source: &PointCloud, target: &PointCloud, config: &MergeConfig) -> Result<Alignment, FilesError> {
    let (s, t) = rayon::join(
        || PreparedMap::new(source.clone(), None, config),
        || PreparedMap::new(target.clone(), None, config),
    );
    for (map, which) in [(&s, "source"), (&t, "target")] {
        if let Err(reason) = &map.features {
            return Err(FilesError::Unusable { which, reason: reason.clone() });
        }
    }
    match estimate_pair((0, &t), (1, &s), config, None) {
        PairVerdict::Edge(e) => Ok(Alignment {
            transform: e.transform,
            score: Some(e.confidence.score),
            overlap: e.confidence.overlap,
            fitness: e.confidence.fitness,
            inliers: Some(e.inliers),
        }),
        PairVerdict::Rejected { reason, .. } => Err(FilesError::NotAligned(reason)),
    }
}

/// Fine registration on both clouds at the refinement voxel; overlap and fitness at the result.
fn align_fine(
    source: &PointCloud,
    target: &PointCloud,
    init: &Isometry3<f64>,
    method: Method,
    config: &MergeConfig,
) -> Result<Alignment, FilesError> {
    let down = |c: &PointCloud| downsample(c, config.refine_voxel).expect("refine_voxel is validated positive");
    let (s, t) = (down(source), down(target));
    let result = align(&s, &t, init, method, &config.refine)?;
    let tree = KdTree::from_points(&t.points);
    let scores = confidence::confidence(&s.points, &tree, &result.transform, 1.0, &config.pairwise.confidence);
    Ok(Alignment {
        transform: result.transform,
        score: None,
        overlap: scores.overlap,
        fitness: scores.fitness,
        inliers: None,
    })
}

/// Writes `cloud` in the format its extension names (.ply binary little endian, .pcd binary, .bin).
pub fn write_by_extension(path: &Path, cloud: &PointCloud) -> Result<(), FilesError> {
    let ext = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase()).unwrap_or_default();
    let format = match ext.as_str() {
        "pcd" => FileFormat::Pcd(PcdEncoding::Binary),
        "bin" => FileFormat::KittiBin,
        _ => FileFormat::Ply(PlyEncoding::BinaryLittleEndian),
    };
    Ok(write_cloud(path, cloud, format)?)
}
