//! Velodyne VLP-16 (and Puck LITE / Hi-Res), VLP-32C, HDL-32E and HDL-64E S2/S3 data packets.
//!
//! A data packet (1206 bytes) holds 12 blocks of 32 returns, each block one firing azimuth; the
//! per-laser angles come from the model's published table or, for the HDL-64E, from the unit's
//! calibration file. Points, rings and per-point times are those of velodyne-decoder 3.0.0 (the
//! reference the tests compare against): velodyne_pointcloud's frame (x forward, y left, z up),
//! ring 0 the lowest beam, the firing times of the manuals' timing tables, and the azimuth of every
//! firing interpolated between blocks and rounded to the packets' 0.01°.
//!
//! Rotations are cut where the head passes a fixed azimuth, by default the azimuth of the first
//! data packet, as velodyne-decoder does by default (its first rotation is then a whole turn).

mod calibration;
mod firing;
mod packet;
mod rotation;
mod tables;
mod yaml;

pub use calibration::{Calibration, CalibrationError, LaserCorrection, TwoPointCorrection};

use super::{Assembler, PacketError, Return, ReturnChoice, Rotation};
use firing::PacketDecoder;
use packet::{DataPacket, ReturnMode};
use rotation::{Cutter, DecodedPacket};

/// The sensor models this decoder knows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, clap::ValueEnum)]
pub enum Model {
    /// VLP-16 (product id 0x22) and Puck LITE (0x23): 16 lasers over ±15°.
    Vlp16,
    /// Puck Hi-Res (0x24): the VLP-16's timing, 16 lasers over ±10°.
    Vlp16HiRes,
    /// VLP-32C (0x28).
    Vlp32c,
    /// HDL-32E (0x21).
    Hdl32e,
    /// HDL-64E S2 and S2.1 (no product id; every unit calibrated).
    Hdl64eS2,
    /// HDL-64E S3 (no product id; every unit calibrated).
    Hdl64eS3,
}

impl Model {
    pub fn name(self) -> &'static str {
        match self {
            Model::Vlp16 => "VLP-16",
            Model::Vlp16HiRes => "Puck Hi-Res",
            Model::Vlp32c => "VLP-32C",
            Model::Hdl32e => "HDL-32E",
            Model::Hdl64eS2 => "HDL-64E S2",
            Model::Hdl64eS3 => "HDL-64E S3",
        }
    }

    /// Lasers, and entries of its calibration.
    pub fn lasers(self) -> usize {
        match self {
            Model::Vlp16 | Model::Vlp16HiRes => 16,
            Model::Vlp32c | Model::Hdl32e => 32,
            Model::Hdl64eS2 | Model::Hdl64eS3 => 64,
        }
    }

    /// The model a data packet's product-id factory byte (byte 1205) names.
    pub fn from_product_id(id: u8) -> Option<Self> {
        match id {
            0x21 => Some(Model::Hdl32e),
            0x22 | 0x23 => Some(Model::Vlp16),
            0x24 => Some(Model::Vlp16HiRes),
            0x28 => Some(Model::Vlp32c),
            _ => None,
        }
    }

    /// The published calibration of the 16- and 32-laser models; `None` for the HDL-64E.
    pub fn default_calibration(self) -> Option<Calibration> {
        tables::default_calibration(self)
    }

    fn is_hdl64e(self) -> bool {
        matches!(self, Model::Hdl64eS2 | Model::Hdl64eS3)
    }
}

/// How to decode and cut a Velodyne stream.
#[derive(Clone, Debug, PartialEq)]
pub struct VelodyneOptions {
    /// `None`: read from the factory bytes of the first data packet (the HDL-64E must be named).
    pub model: Option<Model>,
    /// `None`: the model's published table; required for the HDL-64E.
    pub calibration: Option<Calibration>,
    /// Which return of a dual-return stream to keep.
    pub returns: ReturnChoice,
    /// Where rotations are cut, degrees in the packets' azimuth (clockwise seen from above, 0 at
    /// the front). `None`: at the first data packet's azimuth, velodyne-decoder's default.
    pub cut_azimuth_deg: Option<f64>,
    /// Returns nearer than this are left out, metres (velodyne-decoder's default 0.1).
    pub min_range: f32,
    /// Returns farther than this are left out, metres (velodyne-decoder's default 200).
    pub max_range: f32,
}

impl Default for VelodyneOptions {
    fn default() -> Self {
        Self {
            model: None,
            calibration: None,
            returns: ReturnChoice::First,
            cut_azimuth_deg: None,
            min_range: 0.1,
            max_range: 200.0,
        }
    }
}

/// Why [`VelodyneOptions`] cannot be used.
#[derive(Debug, thiserror::Error, Clone, PartialEq)]
pub enum OptionsError {
    /// The HDL-64E has no published table.
    #[error("the {model} needs its calibration (velodyne_pointcloud's YAML)")]
    MissingCalibration {
        /// The model's name.
        model: &'static str,
    },
    /// The calibration is another model's.
    #[error("the calibration has {lasers} lasers, the {model} has {expected}")]
    LaserCount {
        /// The model's name.
        model: &'static str,
        /// Lasers of the calibration.
        lasers: usize,
        /// Lasers of the model.
        expected: usize,
    },
    /// A number out of its range.
    #[error("`{field}` must be {expected}, found {value}")]
    Value {
        /// The option.
        field: &'static str,
        /// Its valid range.
        expected: &'static str,
        /// What was given.
        value: f64,
    },
}

/// Decodes one Velodyne sensor's UDP payloads and cuts them into rotations.
#[derive(Clone, Debug)]
pub struct VelodyneAssembler {
    options: VelodyneOptions,
    /// Built once the model is known: at construction, or from the first data packet.
    decoder: Option<PacketDecoder>,
    clock: HourClock,
    cutter: Cutter,
}

impl VelodyneAssembler {
    pub fn new(options: VelodyneOptions) -> Result<Self, OptionsError> {
        check_options(&options)?;
        let decoder = match options.model {
            Some(model) => Some(build_decoder(model, &options)?),
            None => None,
        };
        let cut = options.cut_azimuth_deg.map(|degrees| ((degrees * 100.0).round() as i64).rem_euclid(36000) as u16);
        Ok(Self { options, decoder, clock: HourClock::default(), cutter: Cutter::new(cut) })
    }

    /// The model decoded: configured, or read from the first data packet.
    pub fn model(&self) -> Option<Model> {
        self.decoder.as_ref().map(PacketDecoder::model)
    }

    /// The decoder for `packet`'s model, built from its factory bytes on the first data packet.
    fn decoder_for(&mut self, packet: &DataPacket) -> Result<&PacketDecoder, PacketError> {
        if let Some(decoder) = &self.decoder {
            packet.check_model(decoder.model())?;
        } else {
            let model = packet.detect_model()?;
            let decoder = build_decoder(model, &self.options)
                .map_err(|error| PacketError::Invalid { sensor: packet::SENSOR, reason: error.to_string() })?;
            self.decoder = Some(decoder);
        }
        self.decoder.as_ref().ok_or(PacketError::Invalid { sensor: packet::SENSOR, reason: "no model".into() })
    }

    fn decode(&mut self, packet: &DataPacket, received: f64) -> Result<DecodedPacket, PacketError> {
        let decoder = self.decoder_for(packet)?;
        let mode = packet.return_mode(decoder.model())?;
        let mut returns = Vec::with_capacity(packet::BLOCKS * packet::CHANNELS);
        decoder.decode(packet, mode, &mut returns);
        let step = packet_step(decoder.model(), mode, packet);
        let start = self.clock.seconds(packet.timestamp_us);
        Ok(DecodedPacket { start, received, azimuth: packet.last_azimuth(), step, returns })
    }
}

impl Assembler for VelodyneAssembler {
    fn push(&mut self, payload: &[u8], received: f64) -> Result<Option<Rotation>, PacketError> {
        let Some(packet) = packet::read(payload)? else {
            return Ok(None);
        };
        let decoded = self.decode(&packet, received)?;
        Ok(self.cutter.push(decoded))
    }

    fn finish(&mut self) -> Option<Rotation> {
        self.cutter.finish()
    }

    fn recycle(&mut self, returns: Vec<Return>) {
        self.cutter.recycle(returns);
    }
}

fn check_options(options: &VelodyneOptions) -> Result<(), OptionsError> {
    let value = |field, expected, value: f64| Err(OptionsError::Value { field, expected, value });
    if !(options.min_range >= 0.0 && options.min_range <= options.max_range && options.max_range.is_finite()) {
        return value("min_range", "finite, at least 0 and at most max_range", f64::from(options.min_range));
    }
    if let Some(degrees) = options.cut_azimuth_deg.filter(|degrees| !degrees.is_finite()) {
        return value("cut_azimuth_deg", "finite", degrees);
    }
    if let Some(calibration) = &options.calibration {
        let resolution = calibration.distance_resolution;
        if !(resolution > 0.0 && resolution.is_finite()) {
            return value("calibration.distance_resolution", "positive", f64::from(resolution));
        }
    }
    Ok(())
}

/// The decoder of `model` with the configured (or else the published) calibration.
fn build_decoder(model: Model, options: &VelodyneOptions) -> Result<PacketDecoder, OptionsError> {
    let calibration = match &options.calibration {
        Some(calibration) => calibration.clone(),
        None => model.default_calibration().ok_or(OptionsError::MissingCalibration { model: model.name() })?,
    };
    if calibration.lasers.len() != model.lasers() {
        return Err(OptionsError::LaserCount {
            model: model.name(),
            lasers: calibration.lasers.len(),
            expected: model.lasers(),
        });
    }
    let range = (options.min_range, options.max_range);
    Ok(PacketDecoder::new(model, &calibration, options.returns, range))
}

/// Hundredths of a degree from one packet to the next: the head turns as much between packets
/// as between the packet's columns.
fn packet_step(model: Model, mode: ReturnMode, packet: &DataPacket) -> f64 {
    let columns = model.columns(mode) as f64;
    f64::from(packet.azimuth_span()) * columns / (columns - 1.0)
}

/// The packets' timestamps count microseconds past the hour; this keeps them continuous across
/// the hour.
#[derive(Clone, Debug, Default)]
struct HourClock {
    hours: i64,
    last_micros: Option<i64>,
}

impl HourClock {
    const HOUR_MICROS: i64 = 3_600_000_000;

    /// Seconds since the first packet's hour.
    fn seconds(&mut self, timestamp_us: u32) -> f64 {
        let micros = i64::from(timestamp_us);
        let hour = match self.last_micros {
            // A jump back by more than half an hour is the next hour.
            Some(last) if micros + Self::HOUR_MICROS / 2 < last => {
                self.hours += 1;
                self.last_micros = Some(micros);
                self.hours
            }
            // A jump forward by as much is a late packet from before the new hour began.
            Some(last) if micros > last + Self::HOUR_MICROS / 2 => self.hours - 1,
            _ => {
                self.last_micros = Some(micros);
                self.hours
            }
        };
        (hour * Self::HOUR_MICROS + micros) as f64 * 1e-6
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_hour_clock_runs_on_across_the_hour() {
        let mut clock = HourClock::default();
        assert!((clock.seconds(3_599_999_000) - 3599.999).abs() < 1e-9);
        assert!((clock.seconds(500) - 3600.0005).abs() < 1e-9);
        // A straggler from before the hour, then the clock carries on.
        assert!((clock.seconds(3_599_999_500) - 3599.9995).abs() < 1e-9);
        assert!((clock.seconds(1_500) - 3600.0015).abs() < 1e-9);
    }

    #[test]
    fn product_ids_name_the_models() {
        assert_eq!(Model::from_product_id(0x21), Some(Model::Hdl32e));
        assert_eq!(Model::from_product_id(0x23), Some(Model::Vlp16));
        assert_eq!(Model::from_product_id(0x24), Some(Model::Vlp16HiRes));
        assert_eq!(Model::from_product_id(0x28), Some(Model::Vlp32c));
        assert_eq!(Model::from_product_id(0x31), None);
    }

    #[test]
    fn published_tables_have_one_entry_per_laser_and_rings_by_elevation() {
        for model in [Model::Vlp16, Model::Vlp16HiRes, Model::Vlp32c, Model::Hdl32e] {
            let calibration = model.default_calibration().unwrap();
            assert_eq!(calibration.lasers.len(), model.lasers(), "{}", model.name());
            let mut rings = calibration.rings();
            rings.sort_unstable();
            assert!(rings.iter().enumerate().all(|(index, &ring)| usize::from(ring) == index));
        }
        let vlp16 = Model::Vlp16.default_calibration().unwrap().rings();
        assert_eq!(vlp16[..3], [0, 8, 1]);
        assert!(Model::Hdl64eS3.default_calibration().is_none());
    }

    #[test]
    fn options_are_checked() {
        let hdl64 = VelodyneOptions { model: Some(Model::Hdl64eS3), ..Default::default() };
        assert_eq!(
            VelodyneAssembler::new(hdl64).unwrap_err(),
            OptionsError::MissingCalibration { model: "HDL-64E S3" }
        );
        let wrong = VelodyneOptions {
            model: Some(Model::Vlp16),
            calibration: Model::Hdl32e.default_calibration(),
            ..Default::default()
        };
        assert!(matches!(VelodyneAssembler::new(wrong), Err(OptionsError::LaserCount { lasers: 32, .. })));
        let range = VelodyneOptions { min_range: 5.0, max_range: 1.0, ..Default::default() };
        assert!(matches!(VelodyneAssembler::new(range), Err(OptionsError::Value { field: "min_range", .. })));
    }
}
