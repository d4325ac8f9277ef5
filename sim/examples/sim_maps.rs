//! Robot maps of a simulated scenario with their exact relative transforms, for comparing global
//! registration methods on clouds whose ground truth is known to the last bit.
//!
//! ```text
//! cargo run --release -p sim --example sim_maps -- SCENARIO OUT_DIR [--stride 10] [--voxel 0.1]
//! ```
//!
//! For each robot `r` of the scenario, `OUT_DIR/map{r}.ply` (binary PLY, x y z) holds every
//! `stride`-th sweep, each point placed by the exact pose at its own firing time, expressed in the
//! robot's pose at t = 0 and voxel-downsampled (`RobotMaps`, as station/tests/merge.rs merges them). For each
//! ordered pair of robots `a != b`, `OUT_DIR/truth_{a}_{b}.txt` holds the 4x4 row-major matrix
//! `T0_a⁻¹ T0_b` mapping map `b`'s points into map `a`'s frame: the `--reference` of
//! `emr-station bench merge OUT_DIR/map{b}.ply OUT_DIR/map{a}.ply`.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Parser;
use cloud::formats::{FileFormat, PlyEncoding, write_cloud};
use nalgebra::Isometry3;
use sim::{RobotMaps, Scenario};

#[derive(Parser)]
struct Args {
    /// Built-in scenario (warehouse-small, warehouse-large, campus, aisles).
    scenario: String,
    /// Directory for map{r}.ply and truth_{a}_{b}.txt (created if missing).
    out_dir: PathBuf,
    /// Use every `stride`-th sweep.
    #[arg(long, default_value_t = 10)]
    stride: usize,
    /// Voxel size of each sweep and of the map (m).
    #[arg(long, default_value_t = 0.1)]
    voxel: f32,
}

/// Writes `m` as four lines of four numbers.
fn write_matrix(path: &Path, m: &Isometry3<f64>) -> anyhow::Result<()> {
    let h = m.to_homogeneous();
    let text: String =
        h.row_iter().map(|row| row.iter().map(|v| format!("{v:.15e}")).collect::<Vec<_>>().join(" ") + "\n").collect();
    std::fs::write(path, text).with_context(|| path.display().to_string())
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let scenario = Scenario::by_name(&args.scenario)?;
    std::fs::create_dir_all(&args.out_dir).with_context(|| args.out_dir.display().to_string())?;
    let robots = RobotMaps::build(&scenario, args.stride, args.voxel)?;
    for (r, map) in robots.maps.iter().enumerate() {
        let path = args.out_dir.join(format!("map{r}.ply"));
        write_cloud(&path, map, FileFormat::Ply(PlyEncoding::BinaryLittleEndian))?;
        println!("{}: {} points", path.display(), map.len());
    }
    for a in 0..robots.maps.len() {
        for b in (0..robots.maps.len()).filter(|&b| b != a) {
            write_matrix(&args.out_dir.join(format!("truth_{a}_{b}.txt")), &robots.truth(a, b))?;
        }
    }
    Ok(())
}
