//! Placements judged against the simulator's truth, shared by the merge tests.

use cloud::se3::pose_error;
use nalgebra::Isometry3;
use station::merge::MergeReport;

/// The true transform mapping map `b`'s frame into map `a`'s, from each map's frame in the world.
pub fn truth(frames: &[Isometry3<f64>], a: usize, b: usize) -> Isometry3<f64> {
    frames[a].inverse() * frames[b]
}

/// The worst error of any merged map's placement against the truth in the reference's frame,
/// metres and degrees; `frames[id]` is map `id`'s frame in the world.
pub fn worst_error(report: &MergeReport, frames: &[Isometry3<f64>]) -> (f64, f64) {
    let Some(reference) = report.reference else { return (0.0, 0.0) };
    let root = report.maps[reference].id;
    report.maps.iter().filter(|m| m.is_merged()).fold((0.0, 0.0), |(t, r), m| {
        let e = pose_error(&m.transform(), &truth(frames, root, m.id));
        (t.max(e.translation_m), r.max(e.rotation_deg))
    })
}
