//! LiDAR models: spinning multi-beam heads and a solid-state rosette.
//!
//! Sensor frame: x forward, y left, z up. A spinning head turns clockwise seen from above, like
//! Velodyne sensors: column `c` of `columns` fires at azimuth `π − 2π·c/columns` (it starts facing
//! backwards, so the seam of the sweep lies behind the robot, as in KITTI) and at time
//! `c/columns · period` after the sweep start. All beams of a column fire together (the real
//! few-microsecond stagger between lasers is below what odometry can see). A rosette sensor fires
//! at the same times but looks forward through a pair of counter-rotating prisms
//! ([`ScanPattern::Rosette`]).

use std::f64::consts::{PI, TAU};
use std::fmt;
use std::str::FromStr;

use nalgebra::Vector3;

/// The geometry and timing of a spinning LiDAR.
#[derive(Clone, Debug, PartialEq)]
pub struct SensorModel {
    /// Short name for reports.
    pub name: String,
    /// Beam elevations, radians, ascending: ring 0 is the lowest beam.
    pub elevations: Vec<f64>,
    /// Firings per revolution.
    pub columns: usize,
    /// Returns closer than this are discarded (the housing's blind zone), metres.
    pub min_range: f64,
    /// No return beyond this, metres.
    pub max_range: f64,
    /// Seconds per revolution.
    pub period: f64,
    /// How the beams sweep the view.
    pub pattern: ScanPattern,
}

/// How a sensor's beams sweep its view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ScanPattern {
    /// A spinning head: beam `b` of column `c` at elevation `elevations[b]` and azimuth
    /// `π − 2π·c/columns`, the same every sweep.
    Spinning,
    /// Two prisms turning at `prism_hz` (opposite signs: opposite senses) deflect each beam by
    /// half the view each, so it draws a rosette whose petals pass through the centre, densest
    /// there, as Livox's solid-state sensors do. The prisms' rates share no short period, so no
    /// two sweeps cover the same directions: the pattern fills the view over time, never within a
    /// sweep. There are no rings: `elevations` (all zero) only count the beams, which start the
    /// first prism's turn `1/beams` apart.
    Rosette {
        /// Half the horizontal field of view, radians.
        half_width: f64,
        /// Half the vertical field of view, radians.
        half_height: f64,
        /// The prisms' turns per second.
        prism_hz: [f64; 2],
    },
}

impl SensorModel {
    /// Velodyne VLP-16: 16 beams from −15° to +15° every 2°, 0.2° azimuth steps (1800 columns),
    /// 100 m range, 0.5 m blind zone, 10 Hz.
    pub fn vlp16() -> Self {
        Self {
            name: "vlp16".into(),
            elevations: (0..16).map(|i| (-15.0 + 2.0 * i as f64).to_radians()).collect(),
            columns: 1800,
            min_range: 0.5,
            max_range: 100.0,
            period: 0.1,
            pattern: ScanPattern::Spinning,
        }
    }

    /// A Velodyne HDL-64E-like model: 32 upper beams evenly from −8.33° to +2°, 32 lower beams evenly
    /// from −24.9° to −8.83° (the two laser blocks), 2083 columns (0.173°), 120 m, 10 Hz.
    pub fn hdl64() -> Self {
        let block = |lo: f64, hi: f64| (0..32).map(move |i| (lo + (hi - lo) * i as f64 / 31.0).to_radians());
        Self {
            name: "hdl64".into(),
            elevations: block(-24.9, -8.83).chain(block(-8.33, 2.0)).collect(),
            columns: 2083,
            min_range: 0.9,
            max_range: 120.0,
            period: 0.1,
            pattern: ScanPattern::Spinning,
        }
    }

    /// An Ouster-like model with `beams` beams evenly from −45° to +45° (the wide field of view of
    /// an OS0), 1024 columns, 100 m range, 0.3 m blind zone, 10 Hz.
    pub fn ouster(beams: usize) -> Self {
        let step = 90.0 / (beams.max(2) - 1) as f64;
        Self {
            name: format!("os{beams}"),
            elevations: (0..beams).map(|i| (-45.0 + step * i as f64).to_radians()).collect(),
            columns: 1024,
            min_range: 0.3,
            max_range: 100.0,
            period: 0.1,
            pattern: ScanPattern::Spinning,
        }
    }

    /// A Livox Avia-like solid-state sensor: a 70.4° × 77.2° view ahead drawn as a rosette
    /// ([`ScanPattern::Rosette`]) by 6 beams, 800 firings each per 0.1 s sweep (4,800 rays, the
    /// density of the shared handheld Avia run's scans), 1-100 m.
    pub fn avia() -> Self {
        Self {
            name: "avia".into(),
            elevations: vec![0.0; 6],
            columns: 800,
            min_range: 1.0,
            max_range: 100.0,
            period: 0.1,
            pattern: ScanPattern::Rosette {
                half_width: 35.2f64.to_radians(),
                half_height: 38.6f64.to_radians(),
                prism_hz: [121.57, -77.73],
            },
        }
    }

    /// The same sensor spinning at `hz` revolutions per second (its `period` is `1 / hz`).
    pub fn at_rate(self, hz: f64) -> Self {
        Self { period: 1.0 / hz, ..self }
    }

    /// Number of beams (rings).
    pub fn beams(&self) -> usize {
        self.elevations.len()
    }

    /// Rays per sweep.
    pub fn rays_per_scan(&self) -> usize {
        self.beams() * self.columns
    }

    /// Azimuth of column `c`, radians.
    pub fn azimuth(&self, column: usize) -> f64 {
        PI - TAU * column as f64 / self.columns as f64
    }

    /// Seconds from the sweep start at which column `c` fires.
    pub fn firing_time(&self, column: usize) -> f64 {
        column as f64 / self.columns as f64 * self.period
    }

    /// Unit direction of beam `beam` in column `column` of a spinning head, sensor frame.
    pub fn direction(&self, beam: usize, column: usize) -> Vector3<f64> {
        let (se, ce) = self.elevations[beam].sin_cos();
        let (sa, ca) = self.azimuth(column).sin_cos();
        Vector3::new(ce * ca, ce * sa, se)
    }

    /// Unit direction of beam `beam` in column `column` of the sweep starting at `sweep_start`
    /// (seconds on the scenario clock), sensor frame: [`Self::direction`] for a spinning head,
    /// where the rosette's prisms stand at the firing time for a rosette.
    pub fn direction_at(&self, beam: usize, column: usize, sweep_start: f64) -> Vector3<f64> {
        let ScanPattern::Rosette { half_width, half_height, prism_hz } = self.pattern else {
            return self.direction(beam, column);
        };
        let t = sweep_start + self.firing_time(column);
        let first = TAU * (prism_hz[0] * t + beam as f64 / self.beams() as f64);
        let second = TAU * prism_hz[1] * t;
        // Each prism deflects by half the view: the sum of two unit turns, halved, spans the disc.
        let (u, v) = (0.5 * (first.cos() + second.cos()), 0.5 * (first.sin() + second.sin()));
        let (yaw, pitch) = (u * half_width, v * half_height);
        let (sp, cp) = pitch.sin_cos();
        let (sy, cy) = yaw.sin_cos();
        Vector3::new(cp * cy, cp * sy, sp)
    }

    /// Whether the points carry the beam as a ring: a spinning head's beams are scan lines, a
    /// rosette's are not.
    pub fn has_rings(&self) -> bool {
        self.pattern == ScanPattern::Spinning
    }
}

/// The built-in sensor models, by name.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SensorKind {
    /// [`SensorModel::vlp16`].
    Vlp16,
    /// [`SensorModel::hdl64`].
    Hdl64,
    /// [`SensorModel::ouster`] with 64 beams.
    Os64,
    /// [`SensorModel::ouster`] with 128 beams.
    Os128,
    /// [`SensorModel::avia`].
    Avia,
}

impl SensorKind {
    /// Every built-in model.
    pub const ALL: [SensorKind; 5] =
        [SensorKind::Vlp16, SensorKind::Hdl64, SensorKind::Os64, SensorKind::Os128, SensorKind::Avia];

    /// The model.
    pub fn model(self) -> SensorModel {
        match self {
            SensorKind::Vlp16 => SensorModel::vlp16(),
            SensorKind::Hdl64 => SensorModel::hdl64(),
            SensorKind::Os64 => SensorModel::ouster(64),
            SensorKind::Os128 => SensorModel::ouster(128),
            SensorKind::Avia => SensorModel::avia(),
        }
    }

    /// Its name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            SensorKind::Vlp16 => "vlp16",
            SensorKind::Hdl64 => "hdl64",
            SensorKind::Os64 => "os64",
            SensorKind::Os128 => "os128",
            SensorKind::Avia => "avia",
        }
    }
}

impl fmt::Display for SensorKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A sensor name that is not one of [`SensorKind::ALL`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown sensor {0:?}: expected vlp16, hdl64, os64, os128 or avia")]
pub struct UnknownSensor(pub String);

impl FromStr for SensorKind {
    type Err = UnknownSensor;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        SensorKind::ALL.into_iter().find(|k| k.name() == s).ok_or_else(|| UnknownSensor(s.to_owned()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vlp16_geometry() {
        let s = SensorModel::vlp16();
        assert_eq!(s.rays_per_scan(), 28_800);
        assert!((s.elevations[0].to_degrees() + 15.0).abs() < 1e-12);
        assert!((s.elevations[15].to_degrees() - 15.0).abs() < 1e-12);
        // Column 900 fires half-way through the sweep, straight ahead.
        assert!((s.direction(7, 900).y).abs() < 1e-12 && s.direction(7, 900).x > 0.99);
        assert!((s.firing_time(900) - 0.05).abs() < 1e-15);
        // Clockwise: a quarter sweep in, the beam points left (+y).
        assert!(s.direction(7, 450).y > 0.99);
    }

    #[test]
    fn hdl64_rings_ascend() {
        let s = SensorModel::hdl64();
        assert_eq!(s.beams(), 64);
        assert!(s.elevations.windows(2).all(|w| w[0] < w[1]));
        assert!((s.elevations[63].to_degrees() - 2.0).abs() < 1e-9);
    }

    #[test]
    fn ouster_beams_span_90_degrees_evenly() {
        for (kind, beams) in [(SensorKind::Os64, 64), (SensorKind::Os128, 128)] {
            let s = kind.model();
            assert_eq!((s.name.as_str(), s.beams(), s.columns), (kind.name(), beams, 1024));
            assert_eq!(s.rays_per_scan(), beams * 1024);
            assert_eq!((s.min_range, s.max_range, s.period), (0.3, 100.0, 0.1));
            let step = 90.0 / (beams - 1) as f64;
            for (i, e) in s.elevations.iter().enumerate() {
                assert!((e.to_degrees() - (-45.0 + step * i as f64)).abs() < 1e-12, "{kind} beam {i}");
            }
            assert!((s.elevations[beams - 1].to_degrees() - 45.0).abs() < 1e-12);
            assert_eq!(kind.name().parse::<SensorKind>(), Ok(kind));
        }
        // The top beam of column 0 looks backwards, 45° up.
        let d = SensorModel::ouster(64).direction(63, 0);
        let h = 0.5f64.sqrt();
        assert!((d - Vector3::new(-h, 0.0, h)).norm() < 1e-12, "{d}");
    }

    #[test]
    fn the_rosette_stays_in_its_view_and_fills_it_over_sweeps_not_within_one() {
        let s = SensorModel::avia();
        let ScanPattern::Rosette { half_width, half_height, .. } = s.pattern else { panic!("not a rosette") };
        assert!(!s.has_rings() && SensorModel::vlp16().has_rings());
        // The view as a 100 x 100 grid of (yaw, pitch) cells, of which the rosette's disc covers
        // π/4; the share of the disc's cells the rays of some sweeps hit.
        const N: usize = 100;
        let share = |sweeps: std::ops::Range<usize>| {
            let mut hit = vec![false; N * N];
            for sweep in sweeps {
                for c in 0..s.columns {
                    for b in 0..s.beams() {
                        let d = s.direction_at(b, c, sweep as f64 * s.period);
                        assert!((d.norm() - 1.0).abs() < 1e-12 && d.x > 0.0);
                        let yaw = d.y.atan2(d.x);
                        let pitch = d.z.asin();
                        assert!(yaw.abs() <= half_width + 1e-12 && pitch.abs() <= half_height + 1e-12);
                        let cell = |a: f64, half: f64| (((a / half + 1.0) * N as f64 / 2.0) as usize).min(N - 1);
                        hit[cell(yaw, half_width) * N + cell(pitch, half_height)] = true;
                    }
                }
            }
            hit.iter().filter(|&&h| h).count() as f64 / (std::f64::consts::FRAC_PI_4 * (N * N) as f64)
        };
        let (one, ten) = (share(0..1), share(0..10));
        assert!(one < 0.6, "one sweep already covers {one:.2} of the view");
        assert!(ten > 0.75, "ten sweeps cover only {ten:.2} of the view");
        // Not repetitive: the next sweep fires in other directions.
        let a = s.direction_at(0, 100, 0.0);
        let b = s.direction_at(0, 100, s.period);
        assert!(a.angle(&b) > 1e-3, "sweeps 0 and 1 fire alike");
    }

    #[test]
    fn a_rate_sets_the_period_and_the_firing_times() {
        let s = SensorModel::vlp16().at_rate(2.0);
        assert_eq!(s.period, 0.5);
        assert_eq!(s.firing_time(900), 0.25);
        assert_eq!(SensorModel::hdl64().at_rate(1.0).period, 1.0);
        assert_eq!(SensorModel::hdl64().at_rate(5.0), SensorModel { period: 0.2, ..SensorModel::hdl64() });
    }
}
