//! VLP-16 data packets in single return mode (strongest), laid out as the VLP-16 User Manual's
//! chapter 9 describes them.
//!
//! A payload is 1206 bytes: 12 data blocks of 100 bytes, then a 4-byte timestamp and the two
//! factory bytes. A block is the flag `0xFFEE`, the azimuth of its first firing sequence and two
//! firing sequences of 16 data points, each a distance (2 mm units, 0 = no return) and a calibrated
//! reflectivity. All multi-byte fields are little-endian.
//!
//! Geometry. The sim's column `c` of `C` fires at azimuth `π − 2π·c/C`, counter-clockwise from x
//! forward. A Velodyne's azimuth runs clockwise from the forward axis, so column `c` is reported at
//! `180° + 360°·c/C` (mod 360°): the sweep starts facing backwards and the azimuth grows through the
//! sweep, wrapping to 0 when the head faces forward half-way. At 1800 columns that is 18000 +
//! 20·c hundredths of a degree, exactly; the second sequence of a block sits half-way to the next
//! block, where decoders interpolate it. The sim's beams (−15° to +15° every 2°, ring 0 lowest) are
//! the VLP-16's lasers, which fire interleaved in elevation: laser 0 at −15°, 1 at +1°, 2 at −13°,
//! 3 at +3° and so on.

use super::{EncodeError, Packet, SensorClock, check_shape, quantise, reflectivity_of};
use crate::sensor::SensorModel;
use crate::simulator::RangeImage;

/// Bytes of a data packet's UDP payload.
pub const PAYLOAD_BYTES: usize = BLOCKS * BLOCK_BYTES + 4 + 2;
/// The port data packets go to.
pub const DATA_PORT: u16 = 2368;
/// Data blocks per packet.
pub const BLOCKS: usize = 12;
/// Bytes per data block.
pub const BLOCK_BYTES: usize = 100;
/// The flag that opens every data block: bytes `FF EE` (0xEEFF read little-endian).
pub const BLOCK_FLAG: [u8; 2] = [0xFF, 0xEE];
/// Firing sequences per data block.
pub const SEQUENCES_PER_BLOCK: usize = 2;
/// Firing sequences (sim columns) per packet.
pub const SEQUENCES_PER_PACKET: usize = BLOCKS * SEQUENCES_PER_BLOCK;
/// Lasers.
pub const LASERS: usize = 16;
/// The return mode factory byte: strongest return.
pub const RETURN_MODE_STRONGEST: u8 = 0x37;
/// The product id factory byte of the VLP-16 (and Puck LITE).
pub const PRODUCT_ID_VLP16: u8 = 0x22;
/// Metres per distance step.
pub const DISTANCE_UNIT_M: f64 = 0.002;
/// Azimuth steps per revolution (hundredths of a degree).
pub const AZIMUTH_STEPS: u64 = 36_000;
/// The timestamp counts microseconds past the hour and wraps there.
pub const MICROS_PER_HOUR: u64 = 3_600_000_000;
/// Offset of the timestamp in the payload.
pub const TIMESTAMP_OFFSET: usize = BLOCKS * BLOCK_BYTES;

/// How close a sim beam's elevation must be to a laser's to be that laser, radians.
const ELEVATION_TOLERANCE: f64 = 1e-6;

/// Elevation of laser `laser` (0..16), degrees: even lasers cover −15° to −1°, odd ones +1° to +15°.
pub fn laser_elevation_deg(laser: usize) -> f64 {
    if laser.is_multiple_of(2) { -15.0 + laser as f64 } else { laser as f64 }
}

/// The azimuth a VLP-16 reports for sim column `column` of `columns`, hundredths of a degree.
pub fn azimuth_of_column(column: usize, columns: usize) -> u16 {
    let turned = AZIMUTH_STEPS as f64 * column as f64 / columns as f64;
    ((turned + AZIMUTH_STEPS as f64 / 2.0).round() as u64 % AZIMUTH_STEPS) as u16
}

/// Encodes simulated sweeps of a VLP-16 as its data packets.
#[derive(Clone, Debug)]
pub struct Vlp16Encoder {
    /// The sim beam each laser id fires.
    beam_of_laser: [usize; LASERS],
    columns: usize,
    period: f64,
    clock: SensorClock,
}

impl Vlp16Encoder {
    /// An encoder for `sensor`, which must have the VLP-16's 16 elevations and a whole number of
    /// packets (24 columns) per sweep.
    pub fn new(sensor: &SensorModel, clock: SensorClock) -> Result<Vlp16Encoder, EncodeError> {
        let unsupported = |reason: String| EncodeError::UnsupportedSensor {
            sensor: sensor.name.clone(),
            format: super::PacketFormat::Vlp16.name(),
            reason,
        };
        if sensor.columns == 0 || !sensor.columns.is_multiple_of(SEQUENCES_PER_PACKET) {
            return Err(unsupported(format!(
                "{} columns per sweep are not whole packets of {SEQUENCES_PER_PACKET}",
                sensor.columns
            )));
        }
        let beam_of_laser = beams_of_lasers(sensor).map_err(unsupported)?;
        Ok(Vlp16Encoder { beam_of_laser, columns: sensor.columns, period: sensor.period, clock })
    }

    /// Packets per sweep (75 for 1800 columns).
    pub fn packets_per_sweep(&self) -> usize {
        self.columns / SEQUENCES_PER_PACKET
    }

    /// The sim beam (ring) that laser `laser` fires.
    pub fn beam_of_laser(&self, laser: usize) -> Option<usize> {
        self.beam_of_laser.get(laser).copied()
    }

    /// The simulated sensor's calibration in velodyne_pointcloud's YAML format: the lasers'
    /// elevations and no other correction. A real VLP-16's beams leave its lens up to 11.2 mm
    /// above or below the origin (the manual's per-laser vertical corrections, which decoders apply
    /// by default); the simulator casts every beam from the origin, so decoding its packets with
    /// this calibration gives back its points exactly.
    pub fn calibration_yaml(&self) -> String {
        let mut yaml = String::from("lasers:\n");
        for laser in 0..LASERS {
            yaml.push_str(&format!(
                "- {{dist_correction: 0.0, dist_correction_x: 0.0, dist_correction_y: 0.0, focal_distance: 0.0, \
                 focal_slope: 0.0, horiz_offset_correction: 0.0, laser_id: {laser}, rot_correction: 0.0, \
                 vert_correction: {:?}, vert_offset_correction: 0.0}}\n",
                laser_elevation_deg(laser).to_radians()
            ));
        }
        yaml.push_str(&format!("num_lasers: {LASERS}\ndistance_resolution: {DISTANCE_UNIT_M:?}\n"));
        yaml
    }

    /// The packets of one sweep, in the order the sensor sends them.
    pub fn encode(&self, image: &RangeImage) -> Result<Vec<Packet>, EncodeError> {
        check_shape(image, self.columns, LASERS)?;
        Ok((0..self.packets_per_sweep()).map(|p| self.packet(image, p * SEQUENCES_PER_PACKET)).collect())
    }

    /// The packet whose first firing sequence is column `first`.
    fn packet(&self, image: &RangeImage, first: usize) -> Packet {
        let mut payload = Vec::with_capacity(PAYLOAD_BYTES);
        for block in 0..BLOCKS {
            self.write_block(image, first + block * SEQUENCES_PER_BLOCK, &mut payload);
        }
        let first_firing = image.stamp + image.column_times[first];
        // The timestamp is the time of the packet's first firing.
        let micros = self.clock.ns(first_firing) / 1_000 % MICROS_PER_HOUR;
        payload.extend_from_slice(&(micros as u32).to_le_bytes());
        payload.extend_from_slice(&[RETURN_MODE_STRONGEST, PRODUCT_ID_VLP16]);
        // Sent once its last sequence has fired.
        let column_period = self.period / self.columns as f64;
        let sent_ns = self.clock.ns(first_firing + SEQUENCES_PER_PACKET as f64 * column_period);
        Packet { payload, sent_ns, port: DATA_PORT }
    }

    /// A data block: flag, azimuth of its first sequence, then both sequences laser by laser.
    fn write_block(&self, image: &RangeImage, column: usize, out: &mut Vec<u8>) {
        out.extend_from_slice(&BLOCK_FLAG);
        out.extend_from_slice(&azimuth_of_column(column, self.columns).to_le_bytes());
        for sequence in column..column + SEQUENCES_PER_BLOCK {
            for &beam in &self.beam_of_laser {
                let (distance, reflectivity) = data_point(image, sequence, beam);
                out.extend_from_slice(&distance.to_le_bytes());
                out.push(reflectivity);
            }
        }
    }
}

/// The distance (2 mm steps, 0 for none) and reflectivity of one beam of one column.
fn data_point(image: &RangeImage, column: usize, beam: usize) -> (u16, u8) {
    let Some(cell) = image.get(column, beam) else { return (0, 0) };
    match quantise(cell.range, DISTANCE_UNIT_M, u64::from(u16::MAX)) {
        Some(steps) => (steps as u16, reflectivity_of(cell.intensity)),
        // Too close or too far to report: the sensor sends no return.
        None => (0, 0),
    }
}

/// The sim beam of each laser id, matched by elevation.
fn beams_of_lasers(sensor: &SensorModel) -> Result<[usize; LASERS], String> {
    if sensor.beams() != LASERS {
        return Err(format!("{} beams, a VLP-16 has {LASERS}", sensor.beams()));
    }
    let mut beams = [0; LASERS];
    for (laser, beam) in beams.iter_mut().enumerate() {
        let elevation = laser_elevation_deg(laser).to_radians();
        *beam = sensor
            .elevations
            .iter()
            .position(|e| (e - elevation).abs() < ELEVATION_TOLERANCE)
            .ok_or_else(|| format!("no beam at laser {laser}'s elevation {}°", laser_elevation_deg(laser)))?;
    }
    Ok(beams)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lasers_interleave_in_elevation() {
        let order: Vec<f64> = (0..LASERS).map(laser_elevation_deg).collect();
        assert_eq!(order[..6], [-15.0, 1.0, -13.0, 3.0, -11.0, 5.0]);
        assert_eq!(order[14..], [-1.0, 15.0]);
        let encoder = Vlp16Encoder::new(&SensorModel::vlp16(), SensorClock::default()).unwrap();
        let rings: Vec<usize> = (0..LASERS).map(|l| encoder.beam_of_laser(l).unwrap()).collect();
        assert_eq!(rings, [0, 8, 1, 9, 2, 10, 3, 11, 4, 12, 5, 13, 6, 14, 7, 15]);
    }

    #[test]
    fn azimuths_start_behind_and_turn_clockwise() {
        assert_eq!(azimuth_of_column(0, 1800), 18_000);
        assert_eq!(azimuth_of_column(1, 1800), 18_020);
        // A quarter sweep in, the sim's beam points left (+y): 270° clockwise from forward.
        assert_eq!(azimuth_of_column(450, 1800), 27_000);
        assert_eq!(azimuth_of_column(900, 1800), 0);
        assert_eq!(azimuth_of_column(1799, 1800), 17_980);
    }

    #[test]
    fn other_sensors_are_refused() {
        let clock = SensorClock::default();
        assert!(matches!(Vlp16Encoder::new(&SensorModel::hdl64(), clock), Err(EncodeError::UnsupportedSensor { .. })));
        let odd = SensorModel { columns: 1801, ..SensorModel::vlp16() };
        assert!(matches!(Vlp16Encoder::new(&odd, clock), Err(EncodeError::UnsupportedSensor { .. })));
    }
}
