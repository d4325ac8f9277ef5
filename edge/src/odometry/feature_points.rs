//! What both feature extractors give: feature points in the sensor frame, each at its own
//! measurement time, sorted into edges and planes.

use nalgebra::Point3;

/// A feature point, still in the sensor frame at its own measurement time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Feature {
    /// Position in the sensor frame at the point's measurement time.
    pub point: Point3<f32>,
    /// Fraction of the sweep at which the point was measured, 0 = sweep start, 1 = sweep end.
    pub phase: f32,
    /// Local smoothness σ (eq. 1).
    pub smoothness: f32,
    /// The ring (beam) that measured it.
    pub ring: u16,
}

/// The features of one scan.
#[derive(Clone, Debug, Default)]
pub struct Features {
    /// Sharp points, matched to lines of the edge map.
    pub edges: Vec<Feature>,
    /// Flat points, matched to planes of the plane map.
    pub planes: Vec<Feature>,
}
