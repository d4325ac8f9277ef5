//! Ring (beam) indices for clouds recorded without them, derived from elevation angles.
//!
//! Elevation is `atan2(z - h, hypot(x, y))`, where `h` is the height of the beams' origin above
//! the cloud's origin. On a Velodyne HDL-64 as published by KITTI, `h` is about 0.2 m: taken from
//! the cloud origin instead, a beam's apparent elevation drifts by over a degree between 5 m and
//! 50 m, more than the 0.3-0.5 degree beam spacing. [`ClusterOptions::fit_beam_origin`] finds `h`
//! as the value that makes the elevation histogram sharpest.
//!
//! Elevation alone cannot separate every beam of a motion-compensated cloud: KITTI's scans were
//! de-skewed, which moves short-range points (the ground hits of the lower beams) by up to a
//! degree in elevation depending on azimuth, more than the beam spacing. On KITTI sequence 00,
//! frames 0-15, with `beams: Some(64)`: rings never invert the order of the scan lines, 59-62
//! distinct rings are the majority ring of a line, and on average 73-79% of a line's points lie on
//! its majority ring (most upper-block lines 100%, lower-block lines 40-80%). Without a beam count
//! 69-74 rings are found. Sensors whose drivers publish a `ring` field should keep it.
//!
//! Ring indices are per scan: ring 0 is the lowest beam found in that scan. A beam that returns
//! nothing in a scan (sky beams in open space) shifts the indices above it.

use cloud::PointCloud;
use nalgebra::Point3;
use std::sync::LazyLock;

/// How to fill the ring channel of a scan that has none.
#[derive(Clone, Debug, Default, PartialEq)]
pub enum RingModel {
    /// Leave the ring channel absent (the default: nothing is invented).
    #[default]
    None,
    /// Beams evenly spaced in elevation (VLP-16: 16 beams from -15 to +15 degrees); points outside
    /// the range go to the nearest end beam.
    Uniform {
        /// Number of beams (at least 1).
        beams: u16,
        /// Elevation of beam 0, degrees.
        min_elevation_deg: f32,
        /// Elevation of the top beam, degrees.
        max_elevation_deg: f32,
    },
    /// Beams found as peaks of the elevation histogram; for unevenly spaced beams (HDL-64, VLP-32C).
    Clustered(ClusterOptions),
    /// Rings from the point order of a ring-major cloud (one full revolution per beam, beam after
    /// beam, as KITTI stores its scans): a new ring starts where the azimuth wraps past the start.
    /// Exact where it applies; see [`scan_order_rings`].
    ScanOrder,
    /// [`RingModel::ScanOrder`] when the cloud is ring-major, else [`RingModel::Clustered`] with
    /// default options: the choice for recordings of unknown layout.
    Auto,
}

/// Settings of [`cluster_rings`].
#[derive(Clone, Debug, PartialEq)]
pub struct ClusterOptions {
    /// Number of beams, if known: the strongest this many peaks become rings. Default `None`: every
    /// peak passing `min_prominence` and `min_separation_deg` is a ring.
    pub beams: Option<u16>,
    /// Histogram bin width, degrees. Default 0.02 (a tenth of the closest beam spacing in common
    /// sensors).
    pub bin_deg: f32,
    /// Standard deviation of the Gaussian smoothing of the histogram, degrees. Default 0.04.
    pub smoothing_deg: f32,
    /// Two peaks closer than this are one beam, degrees. Default 0.2 (HDL-64 beams are >= 0.27 apart).
    pub min_separation_deg: f32,
    /// A peak counts only if it rises this fraction of its height above the valleys either side.
    /// Default 0.3.
    pub min_prominence: f32,
    /// Fit the beams' origin height before clustering (see the module doc). Default `true`.
    pub fit_beam_origin: bool,
    /// The fit searches heights in `[-max, max]`, metres. Default 0.5.
    pub max_beam_origin_m: f32,
}

impl Default for ClusterOptions {
    fn default() -> Self {
        Self {
            beams: None,
            bin_deg: 0.02,
            smoothing_deg: 0.04,
            min_separation_deg: 0.2,
            min_prominence: 0.3,
            fit_beam_origin: true,
            max_beam_origin_m: 0.5,
        }
    }
}

/// The outcome of [`cluster_rings`].
#[derive(Clone, Debug, PartialEq)]
pub struct RingClusters {
    /// Ring index per point, 0 = lowest beam.
    pub ring: Vec<u16>,
    /// Mean elevation of each ring, degrees, ascending.
    pub elevations_deg: Vec<f32>,
    /// The beam origin height used, metres (0 when not fitted).
    pub beam_origin_m: f32,
}

/// At most this many points feed the origin fit and the peak search; more add time, not accuracy.
const SAMPLE_POINTS: usize = 30_000;
/// Rounds of 1-D k-means that move each peak to the mean of its points.
const REFINE_ROUNDS: usize = 5;

/// Rings for `cloud` under `model`, or `None` for [`RingModel::None`].
pub fn derive_rings(cloud: &PointCloud, model: &RingModel) -> Option<Vec<u16>> {
    match model {
        RingModel::None => None,
        RingModel::Uniform { beams, min_elevation_deg, max_elevation_deg } => {
            Some(uniform_rings(&cloud.points, *beams, *min_elevation_deg, *max_elevation_deg))
        }
        RingModel::Clustered(options) => Some(cluster_rings(&cloud.points, options).ring),
        RingModel::ScanOrder => scan_order_rings(&cloud.points),
        RingModel::Auto => scan_order_rings(&cloud.points)
            .or_else(|| Some(cluster_rings(&cloud.points, &ClusterOptions::default()).ring)),
    }
}

/// Fewest points a ring of a ring-major cloud may have; fewer means the order is not ring-major.
const MIN_SCAN_ORDER_RING: usize = 100;
/// Most rings a ring-major cloud may have (the largest sensors have 128 beams).
const MAX_SCAN_ORDER_RINGS: usize = 256;

/// Rings of a ring-major cloud, or `None` when the order is not ring-major.
///
/// Walking the points in order, the azimuth swept since the first point (in the sensor's spin
/// direction) grows through a revolution, then falls back by nearly a full turn when the next beam
/// starts. Rings are then renumbered by median elevation so that ring 0 is the lowest beam.
/// On KITTI sequence 00 this finds exactly the 64 scan lines, but for the few points per line (at
/// most 8 of ~2000) between the driver's seam (azimuth 0) and the first point's azimuth, which is
/// later than the seam when the first beam has dropouts there.
pub fn scan_order_rings(points: &[Point3<f32>]) -> Option<Vec<u16>> {
    let first = points.first()?;
    let sign = crate::recording::sweep_time::detect_spin(points).sign();
    let start = azimuth(first);
    let turn = std::f64::consts::TAU;
    let mut order = Vec::with_capacity(points.len());
    let (mut ring, mut last) = (0usize, 0.0f64);
    for p in points {
        let swept = (sign * (azimuth(p) - start)).rem_euclid(turn);
        if swept < last - std::f64::consts::PI {
            ring += 1;
        }
        last = swept;
        order.push(ring);
    }
    let rings = ring + 1;
    let mut sizes = vec![0usize; rings];
    order.iter().for_each(|&r| sizes[r] += 1);
    if !(2..=MAX_SCAN_ORDER_RINGS).contains(&rings) || sizes.iter().any(|&n| n < MIN_SCAN_ORDER_RING) {
        return None;
    }
    Some(renumber_by_elevation(points, &order, rings))
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// Maps ring labels in scan order to ring indices ordered by median elevation (0 = lowest).
fn renumber_by_elevation(points: &[Point3<f32>], order: &[usize], rings: usize) -> Vec<u16> {
    let mut elevations: Vec<Vec<f64>> = vec![Vec::new(); rings];
    for (p, &r) in points.iter().zip(order) {
        elevations[r].push(elevation_deg(p, 0.0));
    }
    let medians: Vec<f64> = elevations.iter_mut().map(|v| median(v)).collect();
    let mut by_elevation: Vec<usize> = (0..rings).collect();
    by_elevation.sort_by(|&a, &b| medians[a].total_cmp(&medians[b]));
    let mut index = vec![0u16; rings];
    for (rank, &r) in by_elevation.iter().enumerate() {
        index[r] = rank as u16;
    }
    order.iter().map(|&r| index[r]).collect()
}

fn azimuth(p: &Point3<f32>) -> f64 {
    f64::from(p.y).atan2(f64::from(p.x))
}

/// Rings of evenly spaced beams: the nearest beam to each point's elevation.
pub fn uniform_rings(points: &[Point3<f32>], beams: u16, min_deg: f32, max_deg: f32) -> Vec<u16> {
    let top = f64::from(beams.saturating_sub(1));
    let span = f64::from(max_deg - min_deg);
    points
        .iter()
        .map(|p| {
            let fraction = if span > 0.0 { (elevation_deg(p, 0.0) - f64::from(min_deg)) / span } else { 0.0 };
            (fraction * top).round().clamp(0.0, top) as u16
        })
        .collect()
}

/// Rings by clustering elevations: histogram, peaks, k-means refinement, nearest peak.
pub fn cluster_rings(points: &[Point3<f32>], options: &ClusterOptions) -> RingClusters {
    let step = points.len().div_ceil(SAMPLE_POINTS).max(1);
    let sample: Vec<Point3<f32>> = points.iter().step_by(step).copied().collect();
    let h = if options.fit_beam_origin { fit_beam_origin(&sample, options) } else { 0.0 };
    // Exact elevations, once per point: the sample's feed the peak search, all feed the assignment.
    let elevations: Vec<f64> = points.iter().map(|p| elevation_deg(p, h)).collect();
    let sample_elevations: Vec<f64> = elevations.iter().step_by(step).copied().collect();
    let peaks = find_peaks(&sample_elevations, options);
    let centers = refine(&sample_elevations, peaks);
    let ring = elevations.iter().map(|&e| nearest(&centers, e)).collect();
    RingClusters { ring, elevations_deg: centers.iter().map(|&c| c as f32).collect(), beam_origin_m: h as f32 }
}

/// A sensor's beams as [`cluster_rings`] found them: what every later scan of the same sensor
/// is assigned to, one elevation per point (a few milliseconds where clustering takes ~100).
#[derive(Clone, Debug, PartialEq)]
pub struct Beams {
    /// Beam elevations, degrees, ascending.
    centers: Vec<f64>,
    /// Height of the beams' origin above the cloud's, metres.
    origin: f64,
}

impl Beams {
    /// The beams of a clustering.
    pub fn of(clusters: &RingClusters) -> Self {
        Beams {
            centers: clusters.elevations_deg.iter().map(|&e| f64::from(e)).collect(),
            origin: f64::from(clusters.beam_origin_m),
        }
    }

    /// The ring of each point: its nearest beam in elevation.
    pub fn assign(&self, points: &[Point3<f32>]) -> Vec<u16> {
        points.iter().map(|p| nearest(&self.centers, elevation_deg(p, self.origin))).collect()
    }
}

/// Elevation of `p` in degrees, seen from a point `h` metres above the origin.
fn elevation_deg(p: &Point3<f32>, h: f64) -> f64 {
    let (x, y, z) = (f64::from(p.x), f64::from(p.y), f64::from(p.z));
    (z - h).atan2(x.hypot(y)).to_degrees()
}

/// The beam origin height that makes the elevation histogram sharpest: coarse then fine grid.
fn fit_beam_origin(sample: &[Point3<f32>], options: &ClusterOptions) -> f64 {
    let max = f64::from(options.max_beam_origin_m.abs());
    let polar = Polar::new(sample);
    let mut scratch = Scratch::default();
    let mut sharpest = |candidates: Vec<f64>| {
        candidates
            .into_iter()
            .map(|h| (sharpness(&polar, h, options.bin_deg, &mut scratch), h))
            .max_by(|a, b| a.0.total_cmp(&b.0))
            .map_or(0.0, |(_, h)| h)
    };
    let coarse = sharpest(grid(-max, max, 0.01));
    sharpest(grid(coarse - 0.01, coarse + 0.01, 0.001))
}

/// `from..=to` in steps of `step`.
fn grid(from: f64, to: f64, step: f64) -> Vec<f64> {
    let n = ((to - from) / step).round().max(0.0) as usize;
    (0..=n).map(|i| from + i as f64 * step).collect()
}

/// The sample in cylindrical coordinates, computed once for all candidate heights of the fit.
struct Polar {
    z: Vec<f64>,
    /// `hypot(x, y)`, as [`elevation_deg`] computes it.
    r: Vec<f64>,
    /// Table segments per metre of `z - h`: `(z - h) * scale + HALF_SEGMENTS` is the point's
    /// position in [`ATAN_TABLE`], a multiply-add away from the height.
    scale: Vec<f64>,
}

impl Polar {
    fn new(points: &[Point3<f32>]) -> Self {
        let r: Vec<f64> = points.iter().map(|p| f64::from(p.x).hypot(f64::from(p.y))).collect();
        let scale = r.iter().map(|r| HALF_SEGMENTS / r).collect();
        Polar { z: points.iter().map(|p| f64::from(p.z)).collect(), r, scale }
    }

    /// Exactly [`elevation_deg`] of point `i`.
    fn elevation_deg(&self, i: usize, h: f64) -> f64 {
        (self.z[i] - h).atan2(self.r[i]).to_degrees()
    }

    /// The elevations of all points within [`FAST_ELEVATION_ERROR_DEG`], into `out`, and their
    /// range (inverted if all are NaN). Exact where the table does not apply (beyond 45 degrees,
    /// or not finite).
    fn fast_elevations_deg(&self, h: f64, out: &mut Vec<f64>) -> (f64, f64) {
        let table: &AtanTable = &ATAN_TABLE;
        out.resize(self.z.len(), 0.0);
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for (((&z, &scale), &r), out) in self.z.iter().zip(&self.scale).zip(&self.r).zip(out) {
            let u = (z - h) * scale + HALF_SEGMENTS;
            let e = if (0.0..=2.0 * HALF_SEGMENTS).contains(&u) {
                table_atan_deg(table, u)
            } else {
                (z - h).atan2(r).to_degrees()
            };
            lo = if e < lo { e } else { lo };
            hi = if e > hi { e } else { hi };
            *out = e;
        }
        (lo, hi)
    }
}

/// Bound on the error of [`Polar::fast_elevations_deg`], degrees; the tests measure under a tenth
/// of it. Far below any sensible bin width, so that few points need their exact elevation.
const FAST_ELEVATION_ERROR_DEG: f64 = 1e-8;
/// Half the number of segments of [`ATAN_TABLE`], which spans tangents -1 to 1.
const HALF_SEGMENTS: f64 = 256.0;

/// `atan(t)` in degrees on segments of tangent `1 / HALF_SEGMENTS` wide: per segment, the cubic
/// Taylor expansion about its centre in powers of the table position (see [`table_atan_deg`]).
/// One entry more than segments, for `t = 1` exactly.
type AtanTable = [[f64; 4]; 2 * HALF_SEGMENTS as usize + 1];

static ATAN_TABLE: LazyLock<AtanTable> = LazyLock::new(|| {
    let degrees = 180.0 / std::f64::consts::PI;
    std::array::from_fn(|k| {
        let c = (k as f64 + 0.5) / HALF_SEGMENTS - 1.0;
        let s = 1.0 + c * c;
        let derivatives = [c.atan(), 1.0 / s, -c / (s * s), (3.0 * c * c - 1.0) / (3.0 * s * s * s)];
        // d/du = d/dt / HALF_SEGMENTS
        std::array::from_fn(|n| derivatives[n] * degrees / HALF_SEGMENTS.powi(n as i32))
    })
});

/// `atan(t)` in degrees from the table position `u = (t + 1) * HALF_SEGMENTS` in
/// `[0, 2 * HALF_SEGMENTS]`, within 1e-10 degrees.
fn table_atan_deg(table: &AtanTable, u: f64) -> f64 {
    let k = u as usize;
    let d = u - k as f64 - 0.5;
    let [a0, a1, a2, a3] = table[k];
    // Estrin's scheme: a shorter dependency chain than Horner's.
    (a0 + d * a1) + (d * d) * (a2 + d * a3)
}

/// Buffers reused across the candidate heights of the fit.
#[derive(Default)]
struct Scratch {
    elevations: Vec<f64>,
    counts: Vec<u32>,
}

/// Sum of squared bin probabilities: 1/bins for a flat histogram, 1 when all points share a bin.
///
/// The same histogram as [`Histogram::new`] of the exact elevations, bin for bin: each point is
/// binned from its fast elevation, or from its exact one when the fast one is within its error
/// bound of a bin edge.
fn sharpness(polar: &Polar, h: f64, bin_deg: f32, scratch: &mut Scratch) -> f64 {
    let bin = f64::from(bin_deg);
    let elevations = &mut scratch.elevations;
    let fast_range = polar.fast_elevations_deg(h, elevations);
    let Some((lo, hi)) = exact_range(polar, h, elevations, fast_range) else {
        return 0.0;
    };
    let Some((start, len)) = bin_layout(lo, hi, bin) else {
        return 0.0;
    };
    let counts = &mut scratch.counts;
    counts.clear();
    counts.resize(len, 0);
    // In bins: the error bound, plus the rounding of the bin position (below 1e7) and of 1 / bin.
    let guard = FAST_ELEVATION_ERROR_DEG / bin + 1e-8;
    let inv_bin = 1.0 / bin;
    for (i, &e) in elevations.iter().enumerate() {
        let q = (e - start) * inv_bin;
        if q.is_nan() {
            continue;
        }
        let k = q as u32;
        let fraction = q - f64::from(k);
        let k = if fraction > guard && fraction < 1.0 - guard {
            k as usize
        } else {
            ((polar.elevation_deg(i, h) - start) / bin) as usize
        };
        counts[k.min(len - 1)] += 1;
    }
    let total = elevations.len() as f64;
    counts.iter().map(|&c| (f64::from(c) / total).powi(2)).sum()
}

/// The exact lowest and highest elevations (`None` if all are NaN), given the fast ones: only
/// points within twice the error bound of the fast extremes can hold the exact ones.
fn exact_range(polar: &Polar, h: f64, fast: &[f64], (lo, hi): (f64, f64)) -> Option<(f64, f64)> {
    if lo > hi {
        return None;
    }
    let margin = 2.0 * FAST_ELEVATION_ERROR_DEG;
    let (mut exact_lo, mut exact_hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for (i, &e) in fast.iter().enumerate() {
        if e <= lo + margin {
            exact_lo = exact_lo.min(polar.elevation_deg(i, h));
        }
        if e >= hi - margin {
            exact_hi = exact_hi.max(polar.elevation_deg(i, h));
        }
    }
    Some((exact_lo, exact_hi))
}

/// The first bin's start and the number of bins of a histogram of values in `[lo, hi]`: a margin
/// of a few bins so that edge peaks still have a valley beside them. `None` for an empty range, a
/// bin width that is not positive, or bins so fine that the histogram would not fit in memory.
fn bin_layout(lo: f64, hi: f64, bin: f64) -> Option<(f64, usize)> {
    if !(lo <= hi && bin > 0.0 && (hi - lo) / bin < 1e7) {
        return None;
    }
    let start = lo - 4.0 * bin;
    Some((start, ((hi - start) / bin) as usize + 5))
}

/// Counts of elevations per bin.
struct Histogram {
    start: f64,
    bin: f64,
    counts: Vec<f64>,
}

impl Histogram {
    /// The histogram of `values` (non-finite ones ignored), or `None` if there is none or the bin
    /// width is not positive.
    fn new(values: &[f64], bin: f64) -> Option<Self> {
        let finite = values.iter().copied().filter(|v| v.is_finite());
        let (lo, hi) = finite.clone().fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
        let (start, len) = bin_layout(lo, hi, bin)?;
        let mut counts = vec![0.0; len];
        for v in finite {
            counts[(((v - start) / bin) as usize).min(len - 1)] += 1.0;
        }
        Some(Histogram { start, bin, counts })
    }

    /// The centre of bin `i`.
    fn center(&self, i: usize) -> f64 {
        self.start + (i as f64 + 0.5) * self.bin
    }

    /// The histogram convolved with a Gaussian of standard deviation `sigma` (same units as bins).
    fn smoothed(&self, sigma: f64) -> Vec<f64> {
        let radius = (3.0 * sigma / self.bin).ceil() as isize;
        let kernel: Vec<f64> =
            (-radius..=radius).map(|k| (-0.5 * (k as f64 * self.bin / sigma.max(1e-9)).powi(2)).exp()).collect();
        let norm: f64 = kernel.iter().sum();
        let n = self.counts.len() as isize;
        (0..n)
            .map(|i| {
                let taps = (-radius..=radius).zip(&kernel);
                taps.filter_map(|(k, w)| usize::try_from(i + k).ok().and_then(|j| self.counts.get(j)).map(|c| c * w))
                    .sum::<f64>()
                    / norm
            })
            .collect()
    }
}

/// Peak elevations, ascending: prominent local maxima of the smoothed histogram, strongest first
/// when closer than the minimum separation or beyond the beam count.
fn find_peaks(elevations: &[f64], options: &ClusterOptions) -> Vec<f64> {
    let Some(histogram) = Histogram::new(elevations, f64::from(options.bin_deg)) else {
        return Vec::new();
    };
    let smooth = histogram.smoothed(f64::from(options.smoothing_deg));
    let mut candidates: Vec<usize> = (1..smooth.len().saturating_sub(1))
        .filter(|&i| smooth[i] >= smooth[i - 1] && smooth[i] > smooth[i + 1])
        .filter(|&i| prominence(&smooth, i) >= f64::from(options.min_prominence) * smooth[i])
        .collect();
    candidates.sort_by(|&a, &b| smooth[b].total_cmp(&smooth[a]));
    let separation = f64::from(options.min_separation_deg);
    let mut accepted: Vec<f64> = Vec::new();
    for center in candidates.into_iter().map(|i| histogram.center(i)) {
        if accepted.iter().all(|a| (a - center).abs() >= separation) {
            accepted.push(center);
        }
    }
    if let Some(beams) = options.beams {
        accepted.truncate(usize::from(beams));
    }
    accepted.sort_by(f64::total_cmp);
    accepted
}

/// How far peak `i` rises above the higher of the lowest points between it and a higher bin on
/// either side (or the histogram's end).
fn prominence(values: &[f64], i: usize) -> f64 {
    let peak = values[i];
    let valley =
        |side: &mut dyn Iterator<Item = &f64>| side.take_while(|&&v| v <= peak).fold(peak, |low, &v| low.min(v));
    let left = valley(&mut values[..i].iter().rev());
    let right = valley(&mut values[i + 1..].iter());
    peak - left.max(right)
}

/// Moves each centre to the mean of the elevations nearest to it (1-D k-means).
fn refine(elevations: &[f64], mut centers: Vec<f64>) -> Vec<f64> {
    for _ in 0..REFINE_ROUNDS {
        let mut sums = vec![(0.0, 0usize); centers.len()];
        for &e in elevations {
            if let Some(s) = sums.get_mut(usize::from(nearest(&centers, e))) {
                s.0 += e;
                s.1 += 1;
            }
        }
        for (c, (sum, n)) in centers.iter_mut().zip(sums) {
            if n > 0 {
                *c = sum / n as f64;
            }
        }
        // Means of adjacent clusters cannot cross, but keep the order explicit for the search.
        centers.sort_by(f64::total_cmp);
    }
    centers
}

/// Index of the centre nearest to `e` (`centers` ascending); 0 when there is none.
fn nearest(centers: &[f64], e: f64) -> u16 {
    let above = centers.partition_point(|&c| c < e);
    let best = match (above.checked_sub(1), centers.get(above)) {
        (Some(below), Some(&up)) if up - e < e - centers[below] => above,
        (Some(below), _) => below,
        (None, _) => 0,
    };
    u16::try_from(best).unwrap_or(u16::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Points on `beams` cones at the given elevations (degrees), every 2 degrees of azimuth, at
    /// ranges 5..50 m, seen from a beam origin `h` above the cloud origin.
    fn synthetic(elevations: &[f64], h: f64) -> Vec<Point3<f32>> {
        let mut points = Vec::new();
        for &e in elevations {
            for k in 0..180 {
                let az = f64::from(k) * 2f64.to_radians();
                let range = 5.0 + f64::from(k % 10) * 5.0;
                let (r, z) = (range * e.to_radians().cos(), range * e.to_radians().sin() + h);
                points.push(Point3::new((r * az.cos()) as f32, (r * az.sin()) as f32, z as f32));
            }
        }
        points
    }

    #[test]
    fn clusters_uneven_beams_from_an_offset_origin() {
        let elevations = [-24.0, -20.0, -17.5, -10.0, -9.5, -9.1, -2.0, 1.0, 1.3, 3.0];
        let points = synthetic(&elevations, 0.2);
        let found = cluster_rings(&points, &ClusterOptions::default());
        assert!((found.beam_origin_m - 0.2).abs() < 0.003, "{}", found.beam_origin_m);
        assert_eq!(found.elevations_deg.len(), elevations.len(), "{:?}", found.elevations_deg);
        for (i, ring) in found.ring.iter().enumerate() {
            assert_eq!(usize::from(*ring), i / 180);
        }
    }

    #[test]
    fn uniform_rings_round_to_the_nearest_beam() {
        let points = synthetic(&[-15.0, -13.0, 1.0, 15.0, 40.0], 0.0);
        let rings = uniform_rings(&points, 16, -15.0, 15.0);
        let per_cone: Vec<u16> = rings.chunks(180).map(|c| c[0]).collect();
        assert_eq!(per_cone, vec![0, 1, 8, 15, 15]);
    }

    #[test]
    fn degenerate_inputs_do_not_panic() {
        assert!(cluster_rings(&[], &ClusterOptions::default()).ring.is_empty());
        let one = cluster_rings(&[Point3::new(1.0, 0.0, 0.0)], &ClusterOptions::default());
        assert_eq!(one.ring, vec![0]);
        let zero_bin = ClusterOptions { bin_deg: 0.0, ..ClusterOptions::default() };
        assert_eq!(cluster_rings(&[Point3::new(1.0, 0.0, 0.0)], &zero_bin).ring, vec![0]);
    }

    #[test]
    fn fast_elevations_stay_within_their_error_bound() {
        // Tangents densely across [-1.2, 1.2] (beyond 1 the exact path applies), at short and long
        // ranges, seen from several heights.
        let points: Vec<Point3<f32>> = (0..200_001)
            .flat_map(|i| {
                let t = -1.2 + 2.4 * f64::from(i) / 200_000.0;
                [0.7, 13.0, 90.0].map(|r: f64| Point3::new((r * 0.6) as f32, (r * 0.8) as f32, (r * t) as f32))
            })
            .collect();
        let polar = Polar::new(&points);
        let mut fast = Vec::new();
        for h in [-0.37, 0.0, 0.2] {
            polar.fast_elevations_deg(h, &mut fast);
            let worst = fast.iter().zip(&points).map(|(f, p)| (f - elevation_deg(p, h)).abs()).fold(0.0, f64::max);
            assert!(worst < FAST_ELEVATION_ERROR_DEG / 10.0, "h {h}: {worst:e} degrees");
        }
    }
}
