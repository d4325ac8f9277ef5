//! The simulator speaks packets: sweeps as the UDP payloads a real LiDAR sends, so that the packet
//! decoders, captures and live sources of the robot side can be tested against exact truth.
//!
//! An [`Encoder`] turns one [`RangeImage`] (a sweep before its ranges became points) into the
//! packets of one rotation, in the order and at the times the sensor sends them:
//!
//! - [`velodyne`]: a VLP-16 in single (strongest) return mode, 1206-byte payloads for port 2368;
//! - [`ouster`]: an Ouster OS0 in the LEGACY lidar profile for port 7502, with the metadata JSON
//!   that describes it (firmware 2.x layout).
//!
//! The encoders do no I/O. [`pcap`] writes packets as a classic pcap capture (Ethernet, IPv4, UDP)
//! and [`udp`] sends them to a loopback address, paced as the sensor sends them or as fast as
//! possible.
//!
//! Written from the vendors' manuals (VLP-16 User Manual, chapter 9; Ouster Software User Manual,
//! "Lidar Data Format" and "Coordinate Frames and XYZ Calculation"). Where the simulator is
//! simpler than the sensor, the packets say what the simulator measured:
//!
//! - The simulator fires all beams of a column at one instant; a VLP-16 fires its 16 lasers 2.304 µs
//!   apart and its firing sequences every 55.296 µs, and decoders place each return at its laser's
//!   time and at the azimuth the head has turned to by then. A decoded return is therefore off the
//!   simulated point by the angle the head turns in that stagger: up to 0.125° at 10 Hz for the
//!   last laser of a sequence (about 2 mm at 1 m), and its time by up to ~41 µs. Ouster columns
//!   carry one timestamp for all pixels and no such offset.
//! - The head turns at exactly the simulated rate: a VLP-16 column every `period / 1800` (55.56 µs
//!   at 10 Hz) rather than every 55.296 µs.
//! - A real VLP-16's beams leave its lens up to 11.2 mm above or below the origin, and decoders
//!   raise each laser's points by its published vertical correction; the simulator casts every
//!   beam from the origin. Decoded with the published table, a return sits that offset above the
//!   simulated point; decoded with [`Vlp16Encoder::calibration_yaml`], on it.
//! - No position (GPS) packets, no IMU packets.

pub mod ouster;
pub mod pcap;
pub mod udp;
pub mod velodyne;

use crate::sensor::{SensorKind, SensorModel};
use crate::simulator::RangeImage;

pub use ouster::OusterEncoder;
pub use velodyne::Vlp16Encoder;

/// Unix time of the scenario clock's zero by default: 2023-11-14 22:13:20 UTC. Fixed, so that
/// captures of the same seed are byte-identical.
pub const DEFAULT_EPOCH_NS: u64 = 1_700_000_000 * NANOS_PER_SECOND;

const NANOS_PER_SECOND: u64 = 1_000_000_000;

/// One UDP payload and when the sensor sends it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Packet {
    /// The UDP payload.
    pub payload: Vec<u8>,
    /// When the sensor sends it (right after its last firing), Unix nanoseconds on the sensor's
    /// clock; packets of a stream are sent in order.
    pub sent_ns: u64,
    /// The sensor's data port, where the packet goes.
    pub port: u16,
}

/// Where the scenario clock's zero lies on the sensor's clock (and the capture's).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SensorClock {
    /// Unix nanoseconds at scenario time 0.
    pub epoch_ns: u64,
}

impl Default for SensorClock {
    fn default() -> Self {
        SensorClock { epoch_ns: DEFAULT_EPOCH_NS }
    }
}

impl SensorClock {
    /// Unix nanoseconds at scenario time `t` seconds (the scenario clock never runs backwards
    /// of its zero; earlier times clamp to the epoch).
    pub fn ns(&self, t: f64) -> u64 {
        let offset = (t.max(0.0) * NANOS_PER_SECOND as f64).round() as u64;
        self.epoch_ns.saturating_add(offset)
    }
}

/// The packet layouts the simulator can send.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PacketFormat {
    /// Velodyne VLP-16, single strongest return.
    Vlp16,
    /// Ouster, LEGACY lidar profile.
    OusterLegacy,
}

impl PacketFormat {
    /// The format a built-in sensor sends; `None` for the HDL-64E-like model, whose packets would
    /// need a per-laser calibration file to decode, and for the rosette, whose vendor format is
    /// not one the edge decodes.
    pub fn of(kind: SensorKind) -> Option<PacketFormat> {
        match kind {
            SensorKind::Vlp16 => Some(PacketFormat::Vlp16),
            SensorKind::Os64 | SensorKind::Os128 => Some(PacketFormat::OusterLegacy),
            SensorKind::Hdl64 | SensorKind::Avia => None,
        }
    }

    /// The UDP port the sensor sends its data packets to by default.
    pub fn port(self) -> u16 {
        match self {
            PacketFormat::Vlp16 => velodyne::DATA_PORT,
            PacketFormat::OusterLegacy => ouster::DATA_PORT,
        }
    }

    /// Name for messages.
    pub fn name(self) -> &'static str {
        match self {
            PacketFormat::Vlp16 => "VLP-16",
            PacketFormat::OusterLegacy => "Ouster LEGACY",
        }
    }
}

/// Why a sweep cannot be encoded.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EncodeError {
    /// The simulated sensor's geometry does not fit the packet format.
    #[error("sensor {sensor}: cannot send {format} packets: {reason}")]
    UnsupportedSensor {
        /// The sensor model's name.
        sensor: String,
        /// The packet format.
        format: &'static str,
        /// What does not fit.
        reason: String,
    },
    /// A range image of another sensor than the encoder's.
    #[error(
        "sweep {frame}: a range image of {columns} columns x {beams} beams, \
         the encoder's sensor has {expected_columns} x {expected_beams}"
    )]
    ImageShape {
        /// The sweep's frame index.
        frame: usize,
        /// Its columns.
        columns: usize,
        /// Its beams.
        beams: usize,
        /// The encoder's columns.
        expected_columns: usize,
        /// The encoder's beams.
        expected_beams: usize,
    },
}

/// An encoder of either format.
#[derive(Clone, Debug)]
pub enum Encoder {
    /// VLP-16 packets.
    Vlp16(Vlp16Encoder),
    /// Ouster LEGACY packets.
    Ouster(OusterEncoder),
}

impl Encoder {
    /// The encoder of `format` for the simulated `sensor`, its clock set by `clock`.
    pub fn new(format: PacketFormat, sensor: &SensorModel, clock: SensorClock) -> Result<Encoder, EncodeError> {
        match format {
            PacketFormat::Vlp16 => Vlp16Encoder::new(sensor, clock).map(Encoder::Vlp16),
            PacketFormat::OusterLegacy => OusterEncoder::new(sensor, clock).map(Encoder::Ouster),
        }
    }

    /// The packets of one sweep, in the order the sensor sends them.
    pub fn encode(&self, image: &RangeImage) -> Result<Vec<Packet>, EncodeError> {
        match self {
            Encoder::Vlp16(e) => e.encode(image),
            Encoder::Ouster(e) => e.encode(image),
        }
    }

    /// The format.
    pub fn format(&self) -> PacketFormat {
        match self {
            Encoder::Vlp16(_) => PacketFormat::Vlp16,
            Encoder::Ouster(_) => PacketFormat::OusterLegacy,
        }
    }

    /// Packets per sweep.
    pub fn packets_per_sweep(&self) -> usize {
        match self {
            Encoder::Vlp16(e) => e.packets_per_sweep(),
            Encoder::Ouster(e) => e.packets_per_sweep(),
        }
    }

    /// The simulated sensor's calibration for decoders of Velodyne packets (velodyne_pointcloud's
    /// YAML): without it, decoders apply a real VLP-16's per-laser vertical offsets, which the
    /// simulator does not have. `None` for Ouster, whose metadata holds its geometry.
    pub fn calibration_yaml(&self) -> Option<String> {
        match self {
            Encoder::Vlp16(e) => Some(e.calibration_yaml()),
            Encoder::Ouster(_) => None,
        }
    }

    /// The sensor metadata a decoder needs beside the packets (Ouster's JSON); `None` when the
    /// packets describe themselves (Velodyne's factory bytes name the model).
    pub fn metadata_json(&self) -> Option<String> {
        match self {
            Encoder::Vlp16(_) => None,
            Encoder::Ouster(e) => Some(e.metadata_json()),
        }
    }
}

/// Checks that a range image has the shape the encoder's sensor gives.
fn check_shape(image: &RangeImage, columns: usize, beams: usize) -> Result<(), EncodeError> {
    if image.columns() == columns && image.beams == beams {
        return Ok(());
    }
    Err(EncodeError::ImageShape {
        frame: image.frame,
        columns: image.columns(),
        beams: image.beams,
        expected_columns: columns,
        expected_beams: beams,
    })
}

/// `value / unit` rounded to the nearest step; `None` when that is zero (the formats' "no return")
/// or does not fit in `max`.
fn quantise(value: f64, unit: f64, max: u64) -> Option<u64> {
    let steps = (value / unit).round();
    (steps >= 1.0 && steps <= max as f64).then_some(steps as u64)
}

/// The simulated intensity (`reflectivity · |cos(incidence)|`, 0..1) on the calibrated
/// reflectivity scale both vendors use: 0-100 for diffuse targets of 0-100 % reflectivity (values
/// above 100 are kept for retro-reflectors, which the simulator does not model).
pub fn reflectivity_of(intensity: f32) -> u8 {
    (f64::from(intensity) * 100.0).round().clamp(0.0, 255.0) as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantise_rounds_and_rejects_zero_and_overflow() {
        assert_eq!(quantise(1.0009, 0.002, 65_535), Some(500));
        assert_eq!(quantise(1.0011, 0.002, 65_535), Some(501));
        assert_eq!(quantise(0.0009, 0.002, 65_535), None);
        assert_eq!(quantise(131.071, 0.002, 65_535), None);
    }

    #[test]
    fn reflectivity_is_a_percentage() {
        assert_eq!(reflectivity_of(0.0), 0);
        assert_eq!(reflectivity_of(0.456), 46);
        assert_eq!(reflectivity_of(1.0), 100);
        assert_eq!(reflectivity_of(-1.0), 0);
        assert_eq!(reflectivity_of(9.0), 255);
    }

    #[test]
    fn the_clock_counts_from_its_epoch() {
        let clock = SensorClock { epoch_ns: 5_000 };
        assert_eq!(clock.ns(0.0), 5_000);
        assert_eq!(clock.ns(1e-6), 6_000);
        assert_eq!(clock.ns(-3.0), 5_000);
    }
}
