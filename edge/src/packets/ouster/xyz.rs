//! Range to a point in the sensor frame, as ouster-sdk's `XYZLut` computes it.
//!
//! A beam leaves the lidar from a point `n` mm out from the rotation axis (the beam origin),
//! turned by the encoder angle of its column plus the beam's own azimuth offset, and tilted by its
//! altitude angle. The point in the lidar frame is `range * direction + offset`, where the offset
//! accounts for the beam origin; the metadata's lidar-to-sensor transform then moves it into the
//! sensor frame. Millimetres throughout, metres at the end.
//!
//! The angles factor into a per-column part (the encoder) and a per-beam part, so the table is
//! `columns + beams` entries rather than ouster-sdk's `columns * beams`.

use std::f64::consts::TAU;

use super::metadata::Metadata;

/// Millimetres to metres (ouster-sdk's `range_unit`).
const MM_TO_M: f64 = 0.001;

#[derive(Clone, Debug)]
struct Beam {
    cos_azimuth: f64,
    sin_azimuth: f64,
    cos_altitude: f64,
    sin_altitude: f64,
}

/// The lookup of [`Metadata`]'s geometry, built once per assembler.
#[derive(Clone, Debug)]
pub(super) struct XyzLut {
    /// (cos, sin) of each column's encoder angle.
    encoder: Vec<(f64, f64)>,
    beams: Vec<Beam>,
    /// The beam origin's offset from the axis (x) and along it (z), beam_to_lidar's translation.
    beam_x_mm: f64,
    beam_z_mm: f64,
    /// How far back along the beam the range is measured from: the beam origin's distance from the
    /// lidar origin.
    beam_distance_mm: f64,
    /// lidar_to_sensor_transform, rotation rows and translation (mm).
    rotation: [[f64; 3]; 3],
    translation: [f64; 3],
}

impl XyzLut {
    pub fn new(metadata: &Metadata) -> XyzLut {
        let columns = metadata.columns_per_frame;
        let encoder = (0..columns)
            .map(|column| {
                // Column 0 is at the encoder's zero; the head turns clockwise seen from above.
                let angle = TAU - column as f64 * TAU / columns as f64;
                (angle.cos(), angle.sin())
            })
            .collect();
        let beams = metadata
            .beam_azimuth_angles
            .iter()
            .zip(&metadata.beam_altitude_angles)
            .map(|(azimuth, altitude)| {
                let azimuth = -azimuth.to_radians();
                let altitude = altitude.to_radians();
                Beam {
                    cos_azimuth: azimuth.cos(),
                    sin_azimuth: azimuth.sin(),
                    cos_altitude: altitude.cos(),
                    sin_altitude: altitude.sin(),
                }
            })
            .collect();
        let beam = &metadata.beam_to_lidar_transform;
        let (beam_x_mm, beam_z_mm) = (beam[3], beam[11]);
        let t = &metadata.lidar_to_sensor_transform;
        XyzLut {
            encoder,
            beams,
            beam_x_mm,
            beam_z_mm,
            // ouster-sdk takes the x offset itself (sign included) when the origin is level.
            beam_distance_mm: if beam_z_mm == 0.0 { beam_x_mm } else { beam_x_mm.hypot(beam_z_mm) },
            rotation: [[t[0], t[1], t[2]], [t[4], t[5], t[6]], [t[8], t[9], t[10]]],
            translation: [t[3], t[7], t[11]],
        }
    }

    /// The point of `range_mm` seen by `beam` in `column` (a measurement id), in metres in the
    /// sensor frame; `None` for a column or beam the metadata does not have.
    pub fn point(&self, column: usize, beam: usize, range_mm: u32) -> Option<[f32; 3]> {
        let &(cos_encoder, sin_encoder) = self.encoder.get(column)?;
        let beam = self.beams.get(beam)?;
        // cos and sin of (encoder + beam azimuth), by the angle-sum identities.
        let cos_heading = cos_encoder * beam.cos_azimuth - sin_encoder * beam.sin_azimuth;
        let sin_heading = sin_encoder * beam.cos_azimuth + cos_encoder * beam.sin_azimuth;
        let direction = [cos_heading * beam.cos_altitude, sin_heading * beam.cos_altitude, beam.sin_altitude];
        let offset = [
            cos_encoder * self.beam_x_mm - direction[0] * self.beam_distance_mm,
            sin_encoder * self.beam_x_mm - direction[1] * self.beam_distance_mm,
            self.beam_z_mm - direction[2] * self.beam_distance_mm,
        ];
        let range = f64::from(range_mm);
        let lidar: [f64; 3] = std::array::from_fn(|i| direction[i] * range + offset[i]);
        Some(std::array::from_fn(|row| {
            let rotated: f64 = (0..3).map(|i| self.rotation[row][i] * lidar[i]).sum();
            ((rotated + self.translation[row]) * MM_TO_M) as f32
        }))
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
