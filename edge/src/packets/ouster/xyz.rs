//! Range to a point in the sensor frame, as ouster-sdk's `XYZLut` computes it.
//!
//! A beam leaves the lidar from a point `n` mm out from the rotation axis (the beam origin),
//! turned by the encoder angle of its column plus the beam's own azimuth offset, and tilted by its
//! altitude angle. The point in the lidar frame is `range * direction + offset`, where the offset
//! accounts for the beam origin; the metadata's lidar-to-sensor transform then moves it into the
//! sensor frame. Millimetres throughout, metres at the end.
//!
//! As ouster-sdk's `make_xyz_lut` does, the table holds each pixel's direction and offset already
//! moved into the sensor frame and scaled to metres, so that a point is three multiply-adds:
//! `xyz = direction * range + offset`. For an OS-128 at 1024 columns it is 6 MB, built once per
//! assembler; a table per column and one per beam would be small, but combining them costs a
//! rotation and the angle sums for every point, in the decoder's hottest loop.

use std::f64::consts::TAU;

use super::metadata::Metadata;

/// Millimetres to metres (ouster-sdk's `range_unit`).
const MM_TO_M: f64 = 0.001;

/// One pixel's geometry in the sensor frame, per millimetre of range.
#[derive(Clone, Copy, Debug, PartialEq)]
struct PixelRay {
    direction: [f64; 3],
    offset: [f64; 3],
}

/// The lookup of [`Metadata`]'s geometry, built once per assembler.
#[derive(Clone, Debug)]
pub(super) struct XyzLut {
    beams: usize,
    /// Column-major: the pixel of (column, beam) is at `column * beams + beam`.
    rays: Vec<PixelRay>,
}

impl XyzLut {
    pub fn new(metadata: &Metadata) -> XyzLut {
        let columns = metadata.columns_per_frame;
        let beams = metadata.beam_azimuth_angles.len().min(metadata.beam_altitude_angles.len());
        let beam = &metadata.beam_to_lidar_transform;
        let (beam_x_mm, beam_z_mm) = (beam[3], beam[11]);
        // ouster-sdk takes the x offset itself (sign included) when the beam origin is level.
        let beam_distance_mm = if beam_z_mm == 0.0 { beam_x_mm } else { beam_x_mm.hypot(beam_z_mm) };
        let t = &metadata.lidar_to_sensor_transform;
        let rotation = [[t[0], t[1], t[2]], [t[4], t[5], t[6]], [t[8], t[9], t[10]]];
        let translation = [t[3], t[7], t[11]];
        let rotate = |v: [f64; 3]| -> [f64; 3] {
            std::array::from_fn(|row| (0..3).map(|i| rotation[row][i] * v[i]).sum::<f64>())
        };
        // Per beam: its azimuth offset and the sine and cosine of its altitude.
        let angles: Vec<(f64, f64, f64)> = metadata
            .beam_azimuth_angles
            .iter()
            .zip(&metadata.beam_altitude_angles)
            .map(|(azimuth, altitude)| {
                let (sin_altitude, cos_altitude) = altitude.to_radians().sin_cos();
                (-azimuth.to_radians(), sin_altitude, cos_altitude)
            })
            .collect();
        let mut rays = Vec::with_capacity(columns.saturating_mul(beams));
        for column in 0..columns {
            // The encoder turns clockwise seen from above: column 0 looks along x, a quarter
            // turn later along -y.
            let encoder = TAU - column as f64 * TAU / columns as f64;
            let (sin_encoder, cos_encoder) = encoder.sin_cos();
            for &(azimuth, sin_altitude, cos_altitude) in &angles {
                let (sin_heading, cos_heading) = (encoder + azimuth).sin_cos();
                let direction = [cos_heading * cos_altitude, sin_heading * cos_altitude, sin_altitude];
                let offset = [
                    cos_encoder * beam_x_mm - direction[0] * beam_distance_mm,
                    sin_encoder * beam_x_mm - direction[1] * beam_distance_mm,
                    beam_z_mm - direction[2] * beam_distance_mm,
                ];
                let (direction, offset) = (rotate(direction), rotate(offset));
                rays.push(PixelRay {
                    direction: direction.map(|d| d * MM_TO_M),
                    offset: std::array::from_fn(|i| (offset[i] + translation[i]) * MM_TO_M),
                });
            }
        }
        XyzLut { beams, rays }
    }

    /// The point of `column` (measurement id) and `beam` at `range_mm`, in the sensor frame,
    /// metres; `None` for a column or beam the metadata does not have.
    pub fn point(&self, column: usize, beam: usize, range_mm: u32) -> Option<[f32; 3]> {
        if beam >= self.beams {
            return None;
        }
        let ray = self.rays.get(column.checked_mul(self.beams)?.checked_add(beam)?)?;
        let range = f64::from(range_mm);
        Some(std::array::from_fn(|i| (ray.direction[i] * range + ray.offset[i]) as f32))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::packets::ouster::Profile;

    fn metadata() -> Metadata {
        let identity = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
        Metadata {
            prod_line: None,
            firmware: None,
            lidar_mode: None,
            profile: Profile::Legacy,
            pixels_per_column: 2,
            columns_per_packet: 1,
            columns_per_frame: 4,
            column_window: [0, 3],
            pixel_shift_by_row: vec![0, 0],
            beam_altitude_angles: vec![0.0, 90.0],
            beam_azimuth_angles: vec![0.0, 0.0],
            beam_to_lidar_transform: identity,
            lidar_to_sensor_transform: identity,
            udp_port_lidar: None,
            udp_port_imu: None,
            initialization_id: None,
        }
    }

    #[test]
    fn column_zero_looks_along_x_and_the_head_turns_clockwise() {
        let lut = XyzLut::new(&metadata());
        let ahead = lut.point(0, 0, 1000).unwrap();
        assert!((ahead[0] - 1.0).abs() < 1e-6 && ahead[1].abs() < 1e-6, "{ahead:?}");
        // A quarter turn later the beam looks along -y (2*pi - pi/2).
        let quarter = lut.point(1, 0, 1000).unwrap();
        assert!((quarter[1] + 1.0).abs() < 1e-6 && quarter[0].abs() < 1e-6, "{quarter:?}");
        let up = lut.point(0, 1, 1000).unwrap();
        assert!((up[2] - 1.0).abs() < 1e-6, "{up:?}");
    }

    #[test]
    fn unknown_columns_and_beams_give_nothing() {
        let lut = XyzLut::new(&metadata());
        assert_eq!(lut.point(4, 0, 1000), None);
        assert_eq!(lut.point(0, 2, 1000), None);
    }
}
