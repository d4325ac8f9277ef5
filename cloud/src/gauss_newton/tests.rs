//! The kit against brute force: numerical Jacobians of `e(T · exp(δ))`, and sums across thread counts.

use nalgebra::{Isometry3, Matrix3, Matrix6, Point3, Vector3, Vector6};

use super::*;
use crate::se3::{exp, update};

/// A fixed sequence in [-1, 1): deterministic without a random crate.
fn wave(i: usize, k: usize) -> f64 {
    ((i * 7 + k * 13) as f64 * 0.37).sin()
}

fn pose() -> Isometry3<f64> {
    exp(&Vector6::new(3.0, -1.5, 0.4, 0.2, -0.1, 0.7))
}

fn distances(n: usize) -> Vec<SignedDistance> {
    (0..n)
        .map(|i| SignedDistance {
            source: Point3::new(5.0 * wave(i, 0), 5.0 * wave(i, 1), wave(i, 2)),
            anchor: Point3::new(4.0 * wave(i, 3), 4.0 * wave(i, 4), wave(i, 5)),
            normal: Vector3::new(wave(i, 6), wave(i, 7), 1.0 + wave(i, 8)).normalize(),
            weight: 0.5 + 0.5 * wave(i, 9).abs(),
        })
        .collect()
}

/// The 1x6 or 3x6 Jacobian of `residual(T · exp(δ))` at δ = 0 by central differences.
fn numerical_jacobian<const R: usize>(
    t: &Isometry3<f64>,
    residual: impl Fn(&Isometry3<f64>) -> nalgebra::SVector<f64, R>,
) -> nalgebra::SMatrix<f64, R, 6> {
    let step = 1e-6;
    let mut j = nalgebra::SMatrix::<f64, R, 6>::zeros();
    for k in 0..6 {
        let d = Vector6::ith(k, step);
        j.set_column(k, &((residual(&update(t, &d)) - residual(&update(t, &-d))) / (2.0 * step)));
    }
    j
}

fn assert_close(got: &NormalEquations<impl Sums>, h: &Matrix6<f64>, b: &Vector6<f64>, cost: f64) {
    assert!((got.h - h).norm() <= 1e-6 * h.norm(), "H\n{}\nvs brute force\n{}", got.h, h);
    assert!((got.b - b).norm() <= 1e-6 * b.norm(), "b {} vs {}", got.b, b);
    assert!((got.cost - cost).abs() <= 1e-12 * cost, "cost {} vs {}", got.cost, cost);
}

#[test]
fn signed_distances_sum_to_the_brute_force_normal_equations() {
    let t = pose();
    let terms = distances(1000);
    // A Huber threshold that some residuals exceed: their weight is cut to δ_H / |e|.
    let huber = 0.5;
    let eq = sum_terms(&SignedDistanceFactor::new(&t, huber), &terms);
    let (mut h, mut b, mut cost, mut cut) = (Matrix6::zeros(), Vector6::zeros(), 0.0, 0);
    for r in &terms {
        let residual = |t: &Isometry3<f64>| nalgebra::SVector::<f64, 1>::new(r.normal.dot(&(t * r.source - r.anchor)));
        let e = residual(&t)[0];
        let k = r.weight * if e.abs() <= huber { 1.0 } else { huber / e.abs() };
        cut += usize::from(e.abs() > huber);
        let j = numerical_jacobian(&t, residual);
        h += j.transpose() * k * j;
        b += j.transpose() * (k * e);
        cost += k * e * e;
    }
    assert!(cut > 100 && cut < 900, "{cut} residuals beyond the Huber threshold");
    assert_close(&eq, &h, &b, cost);
    assert_eq!(eq.count, terms.len());
    let weights: f64 = terms.iter().map(|r| r.weight).sum();
    assert!((eq.sums.weight_sum - weights).abs() < 1e-9 * weights);
}

#[test]
fn point_residuals_sum_to_the_brute_force_normal_equations() {
    let t = pose();
    let r = t.rotation.to_rotation_matrix().into_inner();
    let (mut eq, mut h, mut b, mut cost) = (NormalEquations::<()>::zero(), Matrix6::zeros(), Vector6::zeros(), 0.0);
    for i in 0..200 {
        let p = Vector3::new(5.0 * wave(i, 0), 5.0 * wave(i, 1), wave(i, 2));
        let mu = Vector3::new(4.0 * wave(i, 3), 4.0 * wave(i, 4), wave(i, 5));
        // A symmetric positive definite weight, as GICP's fused inverse covariance.
        let l = Matrix3::new(1.0, 0.0, 0.0, wave(i, 6), 0.5, 0.0, wave(i, 7), wave(i, 8), 0.2);
        let w = l * l.transpose();
        let residual = |t: &Isometry3<f64>| mu - (t * Point3::from(p)).coords;
        let e = residual(&t);
        eq.add_point(&p, &e, &w, &r);
        let j = numerical_jacobian(&t, residual);
        h += j.transpose() * w * j;
        b += j.transpose() * w * e;
        cost += e.dot(&(w * e));
    }
    assert_close(&eq, &h, &b, cost);
}

#[test]
fn the_sum_is_bit_identical_across_thread_counts() {
    let t = pose();
    let terms = distances(5000);
    let sum = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| sum_terms(&SignedDistanceFactor::new(&t, 0.5), &terms))
    };
    let one = sum(1);
    assert_eq!(one, sum(2));
    assert_eq!(one, sum(3));
}

#[test]
fn a_remapped_solve_keeps_unconstrained_directions_at_zero() {
    // Points at y = 0 against normals without a y part: rows [n_x, 0, n_z, 0, p_z n_x − p_x n_z, 0]
    // constrain x, z and the rotation about y only.
    let t = Isometry3::identity();
    let terms: Vec<SignedDistance> = distances(600)
        .into_iter()
        .map(|mut r| {
            r.normal = Vector3::new(r.normal.x, 0.0, r.normal.z).normalize();
            r.source.y = 0.0;
            r
        })
        .collect();
    let eq = sum_terms(&SignedDistanceFactor::new(&t, f64::INFINITY), &terms);
    let step = solve_remapped(&eq, 1e-3, RotationScale::Common);
    assert_eq!(step.degenerate, 3, "{step:?}");
    for k in [1, 3, 5] {
        assert!(step.delta[k].abs() < 1e-12, "{}", step.delta);
    }
    assert!(step.delta.norm() > 1e-3, "the constrained directions move: {}", step.delta);
}

/// Plane terms of an aisle seen from its middle (x along it): the floor 0.7 m below across
/// its 3 m width, the two side walls 1.6 m away up to 0.5 m above the sensor, and the aisle's end
/// 30 m ahead, placed so that `truth` puts every term on its plane.
fn aisle(truth: &Isometry3<f64>) -> Vec<SignedDistance> {
    let mut planes: Vec<(Point3<f64>, Vector3<f64>)> = Vec::new();
    for i in 0..40 {
        for j in 0..7 {
            let (x, y) = (-3.0 + 33.0 * i as f64 / 39.0, -1.5 + 0.5 * j as f64);
            planes.push((Point3::new(x, y, -0.7), Vector3::z()));
        }
        for (j, side) in [-1.6, 1.6].iter().enumerate() {
            let z = -0.7 + 1.2 * ((i + 3 * j) % 5) as f64 / 4.0;
            planes.push((Point3::new(-3.0 + 33.0 * i as f64 / 39.0, *side, z), Vector3::new(0.0, -side.signum(), 0.0)));
        }
    }
    for j in 0..20 {
        planes.push((
            Point3::new(30.0, -1.5 + 3.0 * (j % 5) as f64 / 4.0, -0.7 + 1.2 * (j / 5) as f64 / 3.0),
            -Vector3::x(),
        ));
    }
    // The world point is `truth * source`; the term's plane passes through it.
    planes
        .into_iter()
        .map(|(source, normal)| SignedDistance {
            source,
            anchor: truth * source,
            normal: truth.rotation * normal,
            weight: 1.0,
        })
        .collect()
}

#[test]
fn a_roll_measured_by_near_surfaces_is_not_left_to_the_prior_along_an_aisle() {
    // Looking down a 30 m aisle, the far points set a ~12 m RMS lever arm, while a roll moves the
    // points by their ~1 m offsets from the aisle's axis: measured in the common lever arm the roll
    // looks unconstrained and would keep its prior (here 0.5 degrees off). Each axis's own lever
    // arm finds it constrained and solves it.
    let truth = Isometry3::new(Vector3::new(0.02, -0.01, 0.005), Vector3::new(0.5f64.to_radians(), 0.0, 0.0));
    let terms = aisle(&truth);
    let t = Isometry3::identity();
    let eq = sum_terms(&SignedDistanceFactor::new(&t, f64::INFINITY), &terms);
    let step = solve_remapped(&eq, 0.01, RotationScale::PerAxis);
    assert_eq!(step.degenerate, 0, "{step:?}");
    let solved = update(&t, &step.delta);
    let error = solved.inverse() * truth;
    assert!(error.rotation.angle().to_degrees() < 0.01 && error.translation.vector.norm() < 1e-3, "{error:?}");
    // With the common lever arm the roll is flagged and stays where it started.
    let common = solve_remapped(&eq, 0.01, RotationScale::Common);
    assert_eq!(common.degenerate, 1, "{common:?}");
    let left = (update(&t, &common.delta).inverse() * truth).rotation.angle().to_degrees();
    assert!((left - 0.5).abs() < 0.01, "{left} deg of roll left");
    // The scene is what the test says: overall the lever arm is long, about the aisle's axis short.
    let overall = eq.sums.from_origin();
    let axes = eq.sums.about_axes();
    assert!(overall > 10.0 && axes.x < 2.0 && axes.y > 10.0 && axes.z > 10.0, "{overall} {axes}");
}
