//! Placements judged against the simulator's truth, shared by the merge tests.

use cloud::se3::pose_error;
use nalgebra::Isometry3;
use station::merge::{MergeReport, Merger};

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

/// Merges until nothing is pending (settling each merge when `settle`), asserting that every
/// placement is within 5 cm / 0.5° of the truth; the last report. `step` names the call in what
/// it prints.
#[allow(dead_code)] // merge_visibility includes this module without it
pub fn merge_until_done(merger: &mut Merger, frames: &[Isometry3<f64>], step: usize, settle: bool) -> MergeReport {
    loop {
        if settle {
            merger.settle();
        }
        let report = merger.merge().unwrap();
        let (t, r) = worst_error(&report, frames);
        println!(
            "step {step}: merged {} of {}, pending {}, worst {t:.3} m {r:.2} deg, {:?}",
            report.merged(),
            report.maps.len(),
            report.pending,
            merger.stats()
        );
        assert!(t < 0.05 && r < 0.5, "step {step}: a placement {t:.3} m / {r:.2} deg off the truth");
        if report.pending == 0 {
            return report;
        }
    }
}
