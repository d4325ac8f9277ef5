//! Where each return of a packet sits in the firing sequence of its model: its column (one
//! firing of every laser), its laser, which of a dual-return pair it is, when it was fired and at
//! which azimuth.

use super::Model;
use super::calibration::{Beam, Calibration};
use super::packet::{BLOCKS, Bank, DataPacket, ReturnMode};
use crate::packets::{Return, ReturnChoice};

/// Which return of its beam a block holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Role {
    /// Single-return mode: the one return.
    Only,
    /// Dual-return mode: the strongest return.
    Strongest,
    /// Dual-return mode: the last return; `partner` is the block with the strongest of the same
    /// firing.
    Last { partner: usize },
}

/// A block's place in the packet's firings.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Place {
    column: usize,
    role: Role,
}

impl Model {
    /// Columns (firings of every laser) in one packet.
    pub(super) fn columns(self, mode: ReturnMode) -> usize {
        let blocks_per_column = if self.is_hdl64e() { 2 } else { 1 };
        let returns = match mode {
            ReturnMode::Single => 1,
            ReturnMode::Dual => 2,
        };
        BLOCKS / (blocks_per_column * returns)
    }

    /// The column and role of block `block`. The 16- and 32-laser models give a column one
    /// block per return, the last return first; the HDL-64E gives it an upper and a lower block
    /// per return, the strongest first.
    fn place(self, mode: ReturnMode, block: usize) -> Place {
        match (mode, self.is_hdl64e()) {
            (ReturnMode::Single, false) => Place { column: block, role: Role::Only },
            (ReturnMode::Single, true) => Place { column: block / 2, role: Role::Only },
            (ReturnMode::Dual, false) => {
                let role = if block.is_multiple_of(2) { Role::Last { partner: block + 1 } } else { Role::Strongest };
                Place { column: block / 2, role }
            }
            (ReturnMode::Dual, true) => {
                let role =
                    if (block / 2).is_multiple_of(2) { Role::Strongest } else { Role::Last { partner: block - 2 } };
                Place { column: block / 4, role }
            }
        }
    }

    /// Seconds from the packet's first firing to the firing of `channel` in `column`, from the
    /// timing tables of Velodyne's manuals.
    pub(super) fn firing_time(self, column: usize, channel: usize) -> f32 {
        let (column, sequence_step) = (column as f64, (channel % 16) as f64);
        let micros = match self {
            // A column is two firing sequences of the 16 lasers, 55.296 us each, 2.304 us apart.
            Model::Vlp16 | Model::Vlp16HiRes => {
                110.592 * column + 55.296 * (channel / 16) as f64 + 2.304 * sequence_step
            }
            // The 32 lasers fire in pairs, 2.304 us apart, in a 55.296 us sequence.
            Model::Vlp32c => 55.296 * column + 2.304 * (channel / 2) as f64,
            // One laser every 1.152 us, 46.08 us per sequence with the recharge.
            Model::Hdl32e => 46.08 * column + 1.152 * channel as f64,
            // Lasers fire four at a time (one per group of the upper and lower banks at once).
            Model::Hdl64eS2 => 48.0 * column + 6.0 * (channel / 4) as f64 + s2_group_offset(channel % 4),
            Model::Hdl64eS3 => 57.6 * column + 7.2 * (channel / 4) as f64 + s3_group_offset(channel % 4),
        };
        (micros * 1e-6) as f32
    }

    /// The laser id of channel `channel` of a block of `bank`.
    fn laser(self, bank: Bank, channel: usize) -> usize {
        match (self.lasers(), bank) {
            (16, _) => channel % 16,
            (_, Bank::Lower) => 32 + channel,
            (_, Bank::Upper) => channel,
        }
    }
}

fn s2_group_offset(index: usize) -> f64 {
    match index {
        0 => 0.0,
        1 => 1.26,
        2 => 2.46,
        _ => 3.66,
    }
}

fn s3_group_offset(index: usize) -> f64 {
    match index {
        0 => 0.0,
        1 => 1.3,
        2 => 2.5,
        _ => 3.7,
    }
}

/// Turns data packets of one model into returns, with one calibration and one return choice.
#[derive(Clone, Debug)]
pub(super) struct PacketDecoder {
    model: Model,
    beams: Vec<Beam>,
    distance_resolution: f32,
    returns: ReturnChoice,
    range: (f32, f32),
}

impl PacketDecoder {
    pub fn new(model: Model, calibration: &Calibration, returns: ReturnChoice, range: (f32, f32)) -> Self {
        Self {
            model,
            beams: Beam::all(calibration),
            distance_resolution: calibration.distance_resolution,
            returns,
            range,
        }
    }

    pub fn model(&self) -> Model {
        self.model
    }

    /// Appends the packet's valid returns to `out`, each timed from the packet's first firing.
    pub fn decode(&self, packet: &DataPacket, mode: ReturnMode, out: &mut Vec<Return>) {
        let rate = self.rotation_rate(packet, mode);
        for (index, block) in packet.blocks.iter().enumerate() {
            let place = self.model.place(mode, index);
            if !self.keeps(place.role) {
                continue;
            }
            let column_start = self.model.firing_time(place.column, 0);
            for (channel, &raw) in block.returns.iter().enumerate() {
                if raw.distance == 0 || self.repeats_strongest(packet, place.role, channel, raw.distance) {
                    continue;
                }
                let Some(beam) = self.beams.get(self.model.laser(block.bank, channel)) else { continue };
                let time = self.model.firing_time(place.column, channel);
                let azimuth = firing_azimuth(block.azimuth, rate, time - column_start);
                if let Some((position, intensity)) = beam.point(raw, azimuth, self.distance_resolution, self.range) {
                    out.push(Return { position, intensity, ring: beam.ring, time });
                }
            }
        }
    }

    fn keeps(&self, role: Role) -> bool {
        match (role, self.returns) {
            (Role::Only | Role::Strongest, choice) => choice != ReturnChoice::Second,
            (Role::Last { .. }, choice) => choice != ReturnChoice::First,
        }
    }

    /// With both returns kept, a last return equal to the strongest is the same echo reported
    /// twice (the sensor repeats a single echo in both blocks).
    fn repeats_strongest(&self, packet: &DataPacket, role: Role, channel: usize, distance: u16) -> bool {
        let Role::Last { partner } = role else { return false };
        self.returns == ReturnChoice::Both
            && packet.blocks.get(partner).and_then(|block| block.returns.get(channel)).map(|raw| raw.distance)
                == Some(distance)
    }

    /// Hundredths of a degree per second over the packet: the head turns while the lasers of a
    /// column fire one after the other.
    fn rotation_rate(&self, packet: &DataPacket, mode: ReturnMode) -> f32 {
        let last_column = self.model.columns(mode) - 1;
        let duration = self.model.firing_time(last_column, 0) - self.model.firing_time(0, 0);
        packet.azimuth_span() as f32 / duration
    }
}

/// The azimuth of a firing `elapsed` seconds after its block's first, in whole hundredths of a
/// degree as the reference decoders round it.
fn firing_azimuth(block_azimuth: u16, rate: f32, elapsed: f32) -> u16 {
    let units = (f32::from(block_azimuth) + rate * elapsed + 36000.0).round();
    (units as u32 % 36000) as u16
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timing_tables_follow_the_manuals() {
        let micros = |model: Model, column, channel| f64::from(model.firing_time(column, channel)) * 1e6;
        assert!((micros(Model::Vlp16, 1, 17) - (110.592 + 55.296 + 2.304)).abs() < 1e-3);
        assert!((micros(Model::Hdl32e, 2, 31) - (2.0 * 46.08 + 31.0 * 1.152)).abs() < 1e-3);
        assert!((micros(Model::Vlp32c, 1, 3) - (55.296 + 2.304)).abs() < 1e-3);
        assert!((micros(Model::Hdl64eS3, 1, 6) - (57.6 + 7.2 + 2.5)).abs() < 1e-3);
        assert!((micros(Model::Hdl64eS2, 0, 5) - (6.0 + 1.26)).abs() < 1e-3);
    }

    #[test]
    fn dual_blocks_pair_up_as_the_models_lay_them_out() {
        let roles: Vec<_> = (0..4).map(|block| Model::Vlp16.place(ReturnMode::Dual, block)).collect();
        assert_eq!(roles[0], Place { column: 0, role: Role::Last { partner: 1 } });
        assert_eq!(roles[1], Place { column: 0, role: Role::Strongest });
        assert_eq!(roles[3].column, 1);
        let hdl64: Vec<_> = (0..8).map(|block| Model::Hdl64eS3.place(ReturnMode::Dual, block).role).collect();
        assert_eq!(
            hdl64[..4],
            [Role::Strongest, Role::Strongest, Role::Last { partner: 0 }, Role::Last { partner: 1 }]
        );
        assert_eq!(Model::Hdl64eS3.place(ReturnMode::Dual, 7).column, 1);
        assert_eq!(Model::Hdl64eS2.columns(ReturnMode::Single), 6);
    }

    #[test]
    fn firing_azimuth_rounds_and_wraps() {
        assert_eq!(firing_azimuth(35999, 1000.0, 0.0021), 1);
        assert_eq!(firing_azimuth(100, 0.0, 1.0), 100);
    }
}
