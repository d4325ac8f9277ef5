//! Per-laser calibration: velodyne_pointcloud's YAML format, and the conversion of one return
//! (raw distance, intensity, azimuth) to a point with it.
//!
//! The conversion is velodyne-decoder 3.0.0's, the reference the tests compare against. It differs
//! from velodyne_pointcloud's in two places: the vertical offset raises the point (`z += offset`)
//! rather than moving the beam origin along the vertical axis of the laser, and z takes the mean
//! of the two-point-corrected distances. The focal distance is read in metres, as
//! velodyne-decoder and the HDL-64E calibration files give it.

use super::yaml::{self, Entry, Item};

/// One sensor's calibration: every laser's angles, offsets and corrections.
#[derive(Clone, Debug, PartialEq)]
pub struct Calibration {
    /// Metres per distance unit of the packets (0.002 for most models, 0.004 for the VLP-32C).
    pub distance_resolution: f32,
    /// One entry per laser, indexed by the laser id of the packets.
    pub lasers: Vec<LaserCorrection>,
}

/// One laser's calibration, in the units of velodyne_pointcloud's YAML files (radians, metres).
#[derive(Clone, Debug, PartialEq)]
pub struct LaserCorrection {
    /// Azimuth of the beam relative to the packet's azimuth, radians, positive clockwise.
    pub rot_correction: f64,
    /// Elevation of the beam, radians, positive up.
    pub vert_correction: f64,
    /// Added to the measured distance, metres.
    pub dist_correction: f64,
    /// The two-point distance corrections along x and y (HDL-64E), when the file gives both.
    pub two_point: Option<TwoPointCorrection>,
    /// Height of the beam's origin above the sensor's origin, metres.
    pub vert_offset_correction: f64,
    /// Sideways offset of the beam's origin, metres.
    pub horiz_offset_correction: f64,
    /// Distance of the best focus, metres (HDL-64E intensity correction).
    pub focal_distance: f64,
    /// Strength of the intensity correction away from the focus (HDL-64E).
    pub focal_slope: f64,
    /// Corrected intensities are clamped to `min_intensity..=max_intensity`.
    pub min_intensity: f64,
    /// See `min_intensity`.
    pub max_intensity: f64,
}

/// The distance corrections measured at 2.4 m (x) and 1.93 m (y); linear in between and 25.04 m.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TwoPointCorrection {
    /// velodyne_pointcloud's `dist_correction_x`, metres.
    pub x: f64,
    /// velodyne_pointcloud's `dist_correction_y`, metres.
    pub y: f64,
}

/// Why a calibration file could not be read.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum CalibrationError {
    /// The text is not the YAML subset these files use.
    #[error("calibration line {line}: {reason}")]
    Syntax {
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// A value is not a finite number (or, for `two_pt_correction_available`, a boolean).
    #[error("calibration line {line}: `{field}` must be {expected}, found `{value}`")]
    Value {
        /// 1-based line number.
        line: usize,
        /// The key.
        field: String,
        /// What the key holds.
        expected: &'static str,
        /// The text found.
        value: String,
    },
    /// A laser (the item at `line`) or the file lacks a key that has no default.
    #[error("calibration line {line}: missing `{field}`")]
    Missing {
        /// The laser item's line, or 0 for the whole file.
        line: usize,
        /// The key.
        field: &'static str,
    },
    /// The laser ids are not 0..n, each once.
    #[error("calibration: {reason}")]
    LaserIds {
        /// Which id is wrong.
        reason: String,
    },
    /// `num_lasers` disagrees with the number of lasers listed.
    #[error("calibration: num_lasers is {declared} but {listed} lasers are listed")]
    NumLasers {
        /// `num_lasers`.
        declared: usize,
        /// Items of `lasers`.
        listed: usize,
    },
    /// `distance_resolution` is not positive.
    #[error("calibration: distance_resolution must be positive, found {0}")]
    Resolution(f64),
}

impl LaserCorrection {
    /// A laser at elevation `vert_correction_deg` and azimuth offset `rot_correction_deg`, raised
    /// by `vert_offset_mm`, with no other correction: the published tables of the 16- and 32-laser
    /// models are in this form.
    pub fn from_angles(vert_correction_deg: f64, rot_correction_deg: f64, vert_offset_mm: f64) -> Self {
        Self {
            rot_correction: rot_correction_deg.to_radians(),
            vert_correction: vert_correction_deg.to_radians(),
            vert_offset_correction: vert_offset_mm * 1e-3,
            ..Self::default()
        }
    }
}

impl Default for LaserCorrection {
    fn default() -> Self {
        Self {
            rot_correction: 0.0,
            vert_correction: 0.0,
            dist_correction: 0.0,
            two_point: None,
            vert_offset_correction: 0.0,
            horiz_offset_correction: 0.0,
            focal_distance: 0.0,
            focal_slope: 0.0,
            min_intensity: 0.0,
            max_intensity: 255.0,
        }
    }
}

impl Calibration {
    /// Reads velodyne_pointcloud's calibration YAML (`lasers`, `num_lasers`,
    /// `distance_resolution`; both the flow and the block style of the laser items).
    pub fn from_yaml(text: &str) -> Result<Self, CalibrationError> {
        let document = yaml::parse(text)?;
        let items = document.lasers.ok_or(CalibrationError::Missing { line: 0, field: "lasers" })?;
        let mut distance_resolution = 0.002;
        let mut num_lasers = None;
        for entry in &document.scalars {
            match entry.key.as_str() {
                "distance_resolution" => distance_resolution = number(entry)?,
                "num_lasers" => num_lasers = Some(count(entry)?),
                _ => {}
            }
        }
        if distance_resolution <= 0.0 {
            return Err(CalibrationError::Resolution(distance_resolution));
        }
        let lasers = order_by_laser_id(items.iter().map(read_laser).collect::<Result<_, _>>()?)?;
        if let Some(declared) = num_lasers
            && declared != lasers.len()
        {
            return Err(CalibrationError::NumLasers { declared, listed: lasers.len() });
        }
        Ok(Self { distance_resolution: distance_resolution as f32, lasers })
    }

    /// velodyne_pointcloud's `ring` of every laser: its rank by elevation, 0 the lowest.
    pub fn rings(&self) -> Vec<u16> {
        let mut by_elevation: Vec<usize> = (0..self.lasers.len()).collect();
        by_elevation.sort_by(|&a, &b| self.lasers[a].vert_correction.total_cmp(&self.lasers[b].vert_correction));
        let mut rings = vec![0; self.lasers.len()];
        for (ring, &laser) in by_elevation.iter().enumerate() {
            rings[laser] = ring as u16;
        }
        rings
    }
}

/// One laser item into its id and corrections.
fn read_laser(item: &Item) -> Result<(usize, usize, LaserCorrection), CalibrationError> {
    let mut laser = LaserCorrection::default();
    let (mut id, mut rot, mut vert) = (None, None, None);
    let (mut x, mut y, mut two_point_flag) = (None, None, None);
    for entry in &item.entries {
        match entry.key.as_str() {
            "laser_id" => id = Some(count(entry)?),
            "rot_correction" => rot = Some(number(entry)?),
            "vert_correction" => vert = Some(number(entry)?),
            "dist_correction" => laser.dist_correction = number(entry)?,
            "dist_correction_x" => x = Some(number(entry)?),
            "dist_correction_y" => y = Some(number(entry)?),
            "two_pt_correction_available" => two_point_flag = Some(boolean(entry)?),
            "vert_offset_correction" => laser.vert_offset_correction = number(entry)?,
            "horiz_offset_correction" => laser.horiz_offset_correction = number(entry)?,
            "focal_distance" => laser.focal_distance = number(entry)?,
            "focal_slope" => laser.focal_slope = number(entry)?,
            "min_intensity" => laser.min_intensity = number(entry)?,
            "max_intensity" => laser.max_intensity = number(entry)?,
            _ => {}
        }
    }
    let missing = |field| CalibrationError::Missing { line: item.line, field };
    laser.rot_correction = rot.ok_or(missing("rot_correction"))?;
    laser.vert_correction = vert.ok_or(missing("vert_correction"))?;
    // Both corrections are needed; a file may also switch them off explicitly.
    if let (Some(x), Some(y), None | Some(true)) = (x, y, two_point_flag) {
        laser.two_point = Some(TwoPointCorrection { x, y });
    }
    Ok((id.ok_or(missing("laser_id"))?, item.line, laser))
}

/// The lasers in id order, checking that the ids are exactly 0..n.
fn order_by_laser_id(
    mut lasers: Vec<(usize, usize, LaserCorrection)>,
) -> Result<Vec<LaserCorrection>, CalibrationError> {
    if lasers.is_empty() {
        return Err(CalibrationError::LaserIds { reason: "no lasers are listed".into() });
    }
    lasers.sort_by_key(|(id, _, _)| *id);
    for (expected, (id, line, _)) in lasers.iter().enumerate() {
        if *id != expected {
            let reason = if *id < expected {
                format!("laser_id {id} appears twice (line {line})")
            } else {
                format!("laser_id {expected} is missing ({} lasers listed, ids must be 0..{0})", lasers.len())
            };
            return Err(CalibrationError::LaserIds { reason });
        }
    }
    Ok(lasers.into_iter().map(|(_, _, laser)| laser).collect())
}

fn number(entry: &Entry) -> Result<f64, CalibrationError> {
    entry.value.parse::<f64>().ok().filter(|value| value.is_finite()).ok_or_else(|| invalid(entry, "a finite number"))
}

fn count(entry: &Entry) -> Result<usize, CalibrationError> {
    entry.value.parse::<usize>().map_err(|_| invalid(entry, "a non-negative integer"))
}

fn boolean(entry: &Entry) -> Result<bool, CalibrationError> {
    match entry.value.as_str() {
        "true" | "True" | "TRUE" => Ok(true),
        "false" | "False" | "FALSE" => Ok(false),
        _ => Err(invalid(entry, "true or false")),
    }
}

fn invalid(entry: &Entry, expected: &'static str) -> CalibrationError {
    CalibrationError::Value { line: entry.line, field: entry.key.clone(), expected, value: entry.value.clone() }
}

/// A laser's calibration in the form the conversion uses, computed once per sensor.
#[derive(Clone, Debug)]
pub(super) struct Beam {
    pub ring: u16,
    sin_vert: f64,
    cos_vert: f64,
    sin_rot_correction: f64,
    cos_rot_correction: f64,
    dist_correction: f32,
    two_point: Option<TwoPointCorrection>,
    vert_offset: f64,
    horiz_offset: f64,
    /// `(1 - focal distance / 131 m)²`: the focus term of the intensity correction.
    focal_term: f64,
    focal_slope: f64,
    min_intensity: f64,
    max_intensity: f64,
}

/// The two-point correction is interpolated from these distances and switched off beyond the last.
const TWO_POINT_X_NEAR: f64 = 2.4;
const TWO_POINT_Y_NEAR: f64 = 1.93;
const TWO_POINT_FAR: f64 = 25.04;
/// The longest distance the packets can hold at 2 mm resolution, metres: the intensity
/// correction's scale.
const FOCAL_SCALE_M: f64 = 131.0;

impl Beam {
    pub fn all(calibration: &Calibration) -> Vec<Self> {
        let rings = calibration.rings();
        calibration.lasers.iter().zip(rings).map(|(laser, ring)| Self::new(laser, ring)).collect()
    }

    fn new(laser: &LaserCorrection, ring: u16) -> Self {
        Self {
            ring,
            sin_vert: laser.vert_correction.sin(),
            cos_vert: laser.vert_correction.cos(),
            sin_rot_correction: laser.rot_correction.sin(),
            cos_rot_correction: laser.rot_correction.cos(),
            dist_correction: laser.dist_correction as f32,
            two_point: laser.two_point,
            vert_offset: laser.vert_offset_correction,
            horiz_offset: laser.horiz_offset_correction,
            focal_term: (1.0 - laser.focal_distance / FOCAL_SCALE_M).powi(2),
            focal_slope: laser.focal_slope,
            min_intensity: laser.min_intensity,
            max_intensity: laser.max_intensity,
        }
    }

    /// The point of one return and its corrected intensity, or `None` when its distance is
    /// outside `range` (metres). `azimuth` is the firing's, in hundredths of a degree.
    pub fn point(&self, raw: Raw, azimuth: u16, resolution: f32, range: (f32, f32)) -> Option<([f32; 3], f32)> {
        // Single precision here, as the reference decoder, so that the same returns pass the limits.
        let raw_distance = raw.distance as f32 * resolution;
        let distance = raw_distance + self.dist_correction;
        if !(range.0..=range.1).contains(&distance) {
            return None;
        }
        // sin and cos of (azimuth - rot_correction) by the angle-difference identities, from a
        // table of the packets' 36,000 azimuths, as velodyne_pointcloud computes them: per point
        // a sin_cos was most of the decoder's time.
        let (sin_azimuth, cos_azimuth) = azimuth_sin_cos(azimuth);
        let sin_rot = sin_azimuth * self.cos_rot_correction - cos_azimuth * self.sin_rot_correction;
        let cos_rot = cos_azimuth * self.cos_rot_correction + sin_azimuth * self.sin_rot_correction;
        let (distance_x, distance_y) = self.two_point_distances(f64::from(distance), raw_distance, sin_rot, cos_rot);
        // The packets' azimuth turns clockwise from the front: x forward, y left, z up.
        let x = distance_y * self.cos_vert * cos_rot + self.horiz_offset * sin_rot;
        let y = self.horiz_offset * cos_rot - distance_x * self.cos_vert * sin_rot;
        let z = 0.5 * (distance_x + distance_y) * self.sin_vert + self.vert_offset;
        Some(([x as f32, y as f32, z as f32], self.intensity(raw) as f32))
    }

    /// The distance along x and along y after the two-point correction, which velodyne's manual
    /// gives for distances up to 25.04 m.
    fn two_point_distances(&self, distance: f64, raw_distance: f32, sin_rot: f64, cos_rot: f64) -> (f64, f64) {
        let Some(two_point) = self.two_point.filter(|_| raw_distance < TWO_POINT_FAR as f32) else {
            return (distance, distance);
        };
        let horizontal = distance * self.cos_vert;
        let along_x = (horizontal * sin_rot - self.horiz_offset * cos_rot).abs();
        let along_y = (horizontal * cos_rot + self.horiz_offset * sin_rot).abs();
        // The correction is measured at the near distance and equals `dist_correction` at 25.04 m.
        let base = f64::from(self.dist_correction);
        let correction =
            |near: f64, at_near: f64, along: f64| (base - at_near) * (along - near) / (TWO_POINT_FAR - near) + at_near;
        let corrected_x = correction(TWO_POINT_X_NEAR, two_point.x, along_x);
        let corrected_y = correction(TWO_POINT_Y_NEAR, two_point.y, along_y);
        (distance + corrected_x - base, distance + corrected_y - base)
    }

    /// The HDL-64E's intensity correction: returns far from the laser's focus are brightened.
    fn intensity(&self, raw: Raw) -> f64 {
        let distance_term = (1.0 - f64::from(raw.distance) / 65535.0).powi(2);
        let corrected = f64::from(raw.intensity) + 256.0 * self.focal_slope * (self.focal_term - distance_term).abs();
        corrected.clamp(self.min_intensity.min(self.max_intensity), self.max_intensity)
    }
}

/// sin and cos of a packet azimuth (hundredths of a degree; wrapped at 360 degrees).
fn azimuth_sin_cos(azimuth: u16) -> (f64, f64) {
    static TABLE: std::sync::OnceLock<Vec<(f64, f64)>> = std::sync::OnceLock::new();
    let table = TABLE.get_or_init(|| (0..36_000u32).map(|a| (f64::from(a) * 0.01).to_radians().sin_cos()).collect());
    table[usize::from(azimuth) % table.len()]
}

/// One return as the packet holds it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(super) struct Raw {
    /// In units of the calibration's distance resolution; 0 means no return.
    pub distance: u16,
    pub intensity: u8,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn beam(laser: LaserCorrection) -> Beam {
        Beam::new(&laser, 0)
    }

    const RANGE: (f32, f32) = (0.1, 200.0);

    #[test]
    fn a_plain_beam_points_along_its_azimuth_and_elevation() {
        let laser = LaserCorrection::from_angles(-15.0, 0.0, 0.0);
        let raw = Raw { distance: 5000, intensity: 7 };
        // Azimuth 90 degrees is to the right of the sensor: -y.
        let ([x, y, z], intensity) = beam(laser).point(raw, 9000, 0.002, RANGE).unwrap();
        let (horizontal, vertical) = (10.0 * 15f64.to_radians().cos(), -10.0 * 15f64.to_radians().sin());
        assert!(x.abs() < 1e-6 && (f64::from(y) + horizontal).abs() < 1e-5 && (f64::from(z) - vertical).abs() < 1e-5);
        assert_eq!(intensity, 7.0);
    }

    #[test]
    fn offsets_raise_and_shift_the_point() {
        let laser =
            LaserCorrection { vert_offset_correction: 0.1, horiz_offset_correction: 0.05, ..Default::default() };
        let ([x, y, z], _) = beam(laser).point(Raw { distance: 1000, intensity: 0 }, 0, 0.002, RANGE).unwrap();
        assert!((x - 2.0).abs() < 1e-6 && (y - 0.05).abs() < 1e-6 && (z - 0.1).abs() < 1e-6, "{x} {y} {z}");
    }

    #[test]
    fn the_range_limits_are_inclusive_and_apply_after_the_distance_correction() {
        let plain = beam(LaserCorrection::default());
        assert!(plain.point(Raw { distance: 50, intensity: 0 }, 0, 0.002, RANGE).is_some());
        assert!(plain.point(Raw { distance: 49, intensity: 0 }, 0, 0.002, RANGE).is_none());
        let corrected = beam(LaserCorrection { dist_correction: 0.5, ..Default::default() });
        assert!(corrected.point(Raw { distance: 49, intensity: 0 }, 0, 0.002, RANGE).is_some());
    }

    #[test]
    fn two_point_correction_interpolates_and_stops_at_25_metres() {
        let two_point = Some(TwoPointCorrection { x: 0.4, y: 0.3 });
        let laser = LaserCorrection { dist_correction: 0.5, two_point, ..Default::default() };
        // Straight ahead, 10.5 m after the correction: along x (sideways) 0, along y 10.5.
        let ([x, _, z], _) = beam(laser.clone()).point(Raw { distance: 5000, intensity: 0 }, 0, 0.002, RANGE).unwrap();
        let corrected_y = 10.5 + (0.5 - 0.3) * (10.5 - 1.93) / (25.04 - 1.93) + 0.3 - 0.5;
        assert!((f64::from(x) - corrected_y).abs() < 1e-5, "{x} {corrected_y}");
        // z takes the mean of both corrected distances; at zero elevation it is zero.
        assert!(z.abs() < 1e-6);
        let ([far_x, _, _], _) = beam(laser).point(Raw { distance: 12520, intensity: 0 }, 0, 0.002, RANGE).unwrap();
        assert!((far_x - 25.54).abs() < 1e-4, "{far_x}");
    }

    #[test]
    fn intensity_is_brightened_away_from_the_focus_and_clamped() {
        let laser = LaserCorrection { focal_distance: 10.0, focal_slope: 1.0, ..Default::default() };
        let near = beam(laser.clone()).intensity(Raw { distance: 1000, intensity: 7 });
        let expected = 7.0 + 256.0 * ((1.0f64 - 10.0 / 131.0).powi(2) - (1.0f64 - 1000.0 / 65535.0).powi(2)).abs();
        assert!((near - expected).abs() < 1e-9);
        let clamped =
            beam(LaserCorrection { max_intensity: 20.0, ..laser }).intensity(Raw { distance: 1000, intensity: 7 });
        assert_eq!(clamped, 20.0);
    }
}
