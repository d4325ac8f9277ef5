//! Ouster lidar data packets in the LEGACY profile (the firmware 1.x/2.x layout) and the metadata
//! JSON that describes them, as the Ouster Software User Manual lays them out.
//!
//! A packet is 16 columns. A column is a 16-byte header (timestamp in ns, measurement id, frame id,
//! encoder count), one 12-byte pixel per beam (range in mm in the low 20 bits of a u32,
//! reflectivity, signal photons, near-infrared photons, an unused u16) and the status word
//! `0xFFFFFFFF` of a valid column. All fields are little-endian.
//!
//! Geometry. Ouster's XYZ equations put measurement id `m` of `W` at encoder angle
//! `θ = 2π·(1 − m/W)` in the lidar frame, a beam at `(r − n)·(cos(θ + θa)·cos φ, sin(θ + θa)·cos φ,
//! sin φ)` plus the beam origin offset `n·(cos θ, sin θ, 0)`, with `θa` its azimuth offset and `φ`
//! its altitude; the metadata's `lidar_to_sensor_transform` then takes the point into the sensor
//! frame. With no offsets (`n = 0`, `θa = 0`) and the lidar frame turned by 180° about z (the
//! transform `diag(−1, −1, 1)`, as on real sensors, but with no translation), measurement id `m`
//! looks along `π − 2π·m/W` in the sensor frame: the sim's column `m` exactly. So the sim's columns
//! are the measurement ids, a frame starts behind the sensor (as Ouster's do) and the decoded
//! sensor-frame point is the sim's `range · direction`.
//!
//! Beams are listed from the highest to the lowest, as a sensor's metadata lists them: pixel `p`
//! of a column is the sim's beam `beams − 1 − p` (for the sim's ascending elevations).

use std::f64::consts::TAU;

use serde_json::json;

use super::{EncodeError, Packet, PacketFormat, SensorClock, check_shape, quantise, reflectivity_of};
use crate::sensor::SensorModel;
use crate::simulator::{RangeImage, RangeReturn};

/// The port lidar data packets go to.
pub const DATA_PORT: u16 = 7502;
/// The port IMU packets go to (none are sent; the metadata names it).
pub const IMU_PORT: u16 = 7503;
/// Columns per packet.
pub const COLUMNS_PER_PACKET: usize = 16;
/// Bytes of a column's header.
pub const COLUMN_HEADER_BYTES: usize = 16;
/// Bytes of one pixel.
pub const PIXEL_BYTES: usize = 12;
/// Bytes of a column's trailing status word.
pub const STATUS_BYTES: usize = 4;
/// The status word of a column with valid data.
pub const STATUS_VALID: u32 = 0xFFFF_FFFF;
/// Encoder ticks per revolution.
pub const ENCODER_TICKS: u64 = 90_112;
/// Measurement ids are 16 bits (and every column gets its own encoder tick).
const MAX_COLUMNS: usize = 1 << 16;
/// The range field's 20 bits, in millimetres.
pub const MAX_RANGE_MM: u64 = (1 << 20) - 1;
/// The firmware whose metadata layout [`OusterEncoder::metadata_json`] follows.
pub const FIRMWARE: &str = "v2.3.0";

/// Near-infrared (ambient) photons reported by every pixel: the simulator has no sunlight.
const AMBIENT_PHOTONS: u16 = 50;
/// Signal photons of a 100 % reflective target at 1 m, facing the beam; falls with the square of
/// the range. Decoders of points do not read it.
const SIGNAL_AT_ONE_METRE: f64 = 20_000.0;

/// The lidar-to-sensor transform, row-major, millimetres: a half turn about z.
const LIDAR_TO_SENSOR: [f64; 16] = [-1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];
const IDENTITY: [f64; 16] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];

/// Bytes of a packet with `beams` pixels per column.
pub fn packet_bytes(beams: usize) -> usize {
    COLUMNS_PER_PACKET * column_bytes(beams)
}

/// Bytes of a column with `beams` pixels.
pub fn column_bytes(beams: usize) -> usize {
    COLUMN_HEADER_BYTES + beams * PIXEL_BYTES + STATUS_BYTES
}

/// Encodes simulated sweeps of an Ouster-like sensor as its LEGACY lidar packets.
#[derive(Clone, Debug)]
pub struct OusterEncoder {
    /// The sim beam each pixel of a column holds, highest elevation first.
    beam_of_pixel: Vec<usize>,
    /// Elevations in pixel order, degrees.
    altitudes: Vec<f64>,
    columns: usize,
    period: f64,
    clock: SensorClock,
}

impl OusterEncoder {
    /// An encoder for `sensor`, which needs whole packets (16 columns) per sweep and at most 2^16
    /// columns.
    pub fn new(sensor: &SensorModel, clock: SensorClock) -> Result<OusterEncoder, EncodeError> {
        let unsupported = |reason: String| EncodeError::UnsupportedSensor {
            sensor: sensor.name.clone(),
            format: PacketFormat::OusterLegacy.name(),
            reason,
        };
        let columns = sensor.columns;
        if columns == 0 || !columns.is_multiple_of(COLUMNS_PER_PACKET) || columns > MAX_COLUMNS {
            return Err(unsupported(format!(
                "{columns} columns per sweep are not whole packets of {COLUMNS_PER_PACKET} with 16-bit measurement ids"
            )));
        }
        // Headers of IPv4 (20 bytes) and UDP (8) around the payload.
        if sensor.beams() == 0 || packet_bytes(sensor.beams()) > usize::from(u16::MAX) - 28 {
            return Err(unsupported(format!("{} beams do not fit a UDP packet", sensor.beams())));
        }
        let mut beam_of_pixel: Vec<usize> = (0..sensor.beams()).collect();
        beam_of_pixel.sort_by(|&a, &b| sensor.elevations[b].total_cmp(&sensor.elevations[a]));
        let altitudes = beam_of_pixel.iter().map(|&b| sensor.elevations[b].to_degrees()).collect();
        Ok(OusterEncoder { beam_of_pixel, altitudes, columns, period: sensor.period, clock })
    }

    /// Packets per sweep (64 for 1024 columns).
    pub fn packets_per_sweep(&self) -> usize {
        self.columns / COLUMNS_PER_PACKET
    }

    /// The sim beam (ring) that pixel `pixel` of a column holds.
    pub fn beam_of_pixel(&self, pixel: usize) -> Option<usize> {
        self.beam_of_pixel.get(pixel).copied()
    }

    /// Bytes of one packet.
    pub fn packet_bytes(&self) -> usize {
        packet_bytes(self.beam_of_pixel.len())
    }

    /// The packets of one sweep, in the order the sensor sends them; the frame id is the sweep's
    /// frame index (modulo 2^16).
    pub fn encode(&self, image: &RangeImage) -> Result<Vec<Packet>, EncodeError> {
        check_shape(image, self.columns, self.beam_of_pixel.len())?;
        Ok((0..self.packets_per_sweep()).map(|p| self.packet(image, p * COLUMNS_PER_PACKET)).collect())
    }

    /// The packet whose first column is `first`.
    fn packet(&self, image: &RangeImage, first: usize) -> Packet {
        let mut payload = Vec::with_capacity(self.packet_bytes());
        for column in first..first + COLUMNS_PER_PACKET {
            self.write_column(image, column, &mut payload);
        }
        // Sent once its last column has fired.
        let column_period = self.period / self.columns as f64;
        let last = first + COLUMNS_PER_PACKET - 1;
        let sent_ns = self.clock.ns(image.stamp + image.column_times[last] + column_period);
        Packet { payload, sent_ns, port: DATA_PORT }
    }

    /// One column: header, a pixel per beam from the highest, status.
    fn write_column(&self, image: &RangeImage, column: usize, out: &mut Vec<u8>) {
        let timestamp_ns = self.clock.ns(image.stamp + image.column_times[column]);
        let encoder_count = column as u64 * ENCODER_TICKS / self.columns as u64;
        out.extend_from_slice(&timestamp_ns.to_le_bytes());
        out.extend_from_slice(&(column as u16).to_le_bytes());
        out.extend_from_slice(&(image.frame as u16).to_le_bytes());
        out.extend_from_slice(&(encoder_count as u32).to_le_bytes());
        for &beam in &self.beam_of_pixel {
            write_pixel(image.get(column, beam), out);
        }
        out.extend_from_slice(&STATUS_VALID.to_le_bytes());
    }

    /// The metadata JSON of the sensor (firmware 2.x flat layout), which decoders need beside the
    /// packets: beams highest first, no beam offsets, the lidar frame a half turn from the sensor
    /// frame.
    pub fn metadata_json(&self) -> String {
        let beams = self.beam_of_pixel.len();
        let hz = (1.0 / self.period).round();
        let metadata = json!({
            "hostname": "os-simulated",
            "prod_line": format!("OS-0-{beams}"),
            "prod_pn": "simulated",
            "prod_sn": "000000000000",
            "build_rev": FIRMWARE,
            "status": "RUNNING",
            "lidar_mode": format!("{}x{hz}", self.columns),
            "timestamp_mode": "TIME_FROM_PTP_1588",
            "udp_port_lidar": DATA_PORT,
            "udp_port_imu": IMU_PORT,
            "beam_altitude_angles": self.altitudes,
            "beam_azimuth_angles": vec![0.0; beams],
            "lidar_origin_to_beam_origin_mm": 0.0,
            "lidar_to_sensor_transform": LIDAR_TO_SENSOR,
            "imu_to_sensor_transform": IDENTITY,
            "data_format": {
                "pixels_per_column": beams,
                "columns_per_packet": COLUMNS_PER_PACKET,
                "columns_per_frame": self.columns,
                "column_window": [0, self.columns - 1],
                "pixel_shift_by_row": vec![0; beams],
                "udp_profile_lidar": "LEGACY",
                "udp_profile_imu": "LEGACY",
            },
        });
        // A map of plain numbers and strings always serialises.
        serde_json::to_string_pretty(&metadata).unwrap_or_default()
    }

    /// The encoder angle of measurement id `column` in the lidar frame, radians, as Ouster's XYZ
    /// equations give it.
    pub fn encoder_angle(&self, column: usize) -> f64 {
        TAU * (1.0 - column as f64 / self.columns as f64)
    }
}

/// One pixel: range to the nearest millimetre (0 = no return), reflectivity, signal, ambient.
fn write_pixel(cell: Option<RangeReturn>, out: &mut Vec<u8>) {
    let range_mm = cell.and_then(|c| quantise(c.range, 0.001, MAX_RANGE_MM));
    let (range, reflectivity, signal) = match (cell, range_mm) {
        (Some(c), Some(mm)) => (mm as u32, u16::from(reflectivity_of(c.intensity)), signal_photons(c)),
        _ => (0, 0, 0),
    };
    out.extend_from_slice(&range.to_le_bytes());
    out.extend_from_slice(&reflectivity.to_le_bytes());
    out.extend_from_slice(&signal.to_le_bytes());
    out.extend_from_slice(&AMBIENT_PHOTONS.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
}

/// Signal photons of a return: the target's brightness falling with the square of the range.
fn signal_photons(cell: RangeReturn) -> u16 {
    let range = cell.range.max(1.0);
    (SIGNAL_AT_ONE_METRE * f64::from(cell.intensity) / (range * range)).round().clamp(0.0, f64::from(u16::MAX)) as u16
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixels_run_from_the_highest_beam() {
        let encoder = OusterEncoder::new(&SensorModel::ouster(64), SensorClock::default()).unwrap();
        assert_eq!(encoder.beam_of_pixel(0), Some(63));
        assert_eq!(encoder.beam_of_pixel(63), Some(0));
        assert_eq!(encoder.packet_bytes(), 12_608);
        assert_eq!(encoder.packets_per_sweep(), 64);
    }

    #[test]
    fn the_sensor_frame_azimuth_is_the_sims() {
        let sensor = SensorModel::ouster(16);
        let encoder = OusterEncoder::new(&sensor, SensorClock::default()).unwrap();
        for column in [0, 1, 256, 511, 700, 1023] {
            // The lidar-to-sensor half turn adds π to the encoder angle.
            let sensor_frame = encoder.encoder_angle(column) + std::f64::consts::PI;
            let d = sensor.direction(0, column);
            let expected = d.y.atan2(d.x);
            let diff = (sensor_frame - expected).rem_euclid(TAU);
            assert!(diff.min(TAU - diff) < 1e-9, "column {column}");
        }
    }

    #[test]
    fn sweeps_that_are_not_whole_packets_are_refused() {
        let odd = SensorModel { columns: 1000, ..SensorModel::ouster(64) };
        assert!(matches!(OusterEncoder::new(&odd, SensorClock::default()), Err(EncodeError::UnsupportedSensor { .. })));
    }
}
