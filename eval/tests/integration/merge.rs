//! The station's pairwise merge on the KITTI revisit thinned to about 50k points per scan, for the
//! Open3D comparison (scripts/compare_open3d.py): a benchmark, run by hand with
//! `cargo test --release -p eval --test merge -- --ignored --nocapture`.

use cloud::PointCloud;
use cloud::formats::read_transform;
use cloud::se3::pose_error;
use eval::merge::bench_pairwise;
use station::pairwise::{PairwiseConfig, register};
use testkit::shared_data;

const KITTI: &str = "kitti08_revisit";

/// Benchmark (run with `--release --ignored --nocapture`): the KITTI revisit pair thinned to about
/// 50k points per scan (voxel 0.12 m), written to /tmp for the Open3D comparison, registered 5 times.
#[test]
#[ignore]
fn bench_kitti_revisit_50k() {
    let read = |name: &str| cloud::formats::read_cloud(&shared_data(KITTI).join(name)).unwrap().cloud;
    let truth = read_transform(&shared_data(KITTI).join("T_000720_001500.txt")).unwrap();
    let thin = |c: PointCloud| cloud::voxel::downsample(&c, 0.12).unwrap();
    let (source, target) = (thin(read("001500.bin")), thin(read("000720.bin")));
    for (c, name) in [(&source, "source"), (&target, "target")] {
        let path = std::env::temp_dir().join(format!("kitti08_{name}_50k.bin"));
        cloud::formats::write_cloud(&path, c, cloud::formats::FileFormat::KittiBin).unwrap();
    }
    let bench = bench_pairwise(&source, &target, &PairwiseConfig::outdoor(), 5, Some(&truth)).unwrap();
    println!("{bench}");
    let mut runs: Vec<f64> = bench.runs.iter().map(|d| d.as_secs_f64() * 1e3).collect();
    runs.sort_by(f64::total_cmp);
    println!("all runs (ms): {runs:.1?}");
    // Reliability: the same pair under ten RANSAC seeds.
    let ok = (0..10u64)
        .filter(|&seed| {
            let mut config = PairwiseConfig::outdoor();
            config.global.ransac.seed = seed;
            let outcome = register(&source, &target, &config).unwrap();
            outcome.aligned().is_some_and(|r| {
                let e = pose_error(&r.transform, &truth);
                e.translation_m < 0.2 && e.rotation_deg < 1.0
            })
        })
        .count();
    println!("seeds within 0.2 m / 1 deg: {ok}/10");
}
