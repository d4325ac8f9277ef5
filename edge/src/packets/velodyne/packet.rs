//! The layout of a Velodyne data packet: 12 blocks of 100 bytes (flag, azimuth, 32 returns),
//! then a 4-byte timestamp and the two factory bytes (return mode, product id).

use super::Model;
use super::calibration::Raw;
use crate::packets::PacketError;

pub(super) const SENSOR: &str = "Velodyne";
/// Bytes of a data packet's UDP payload.
pub(super) const DATA_LEN: usize = 1206;
/// Bytes of a position (GPS/PPS) packet: the HDL-32E's older firmware, then every current model.
const POSITION_LENS: [usize; 2] = [512, 554];
pub(super) const BLOCKS: usize = 12;
pub(super) const CHANNELS: usize = 32;
const BLOCK_LEN: usize = 100;
const AZIMUTH_UNITS: u16 = 36000;

/// Block flags: every block of the 16- and 32-laser models is an upper block; the HDL-64E
/// alternates upper (lasers 0-31) and lower (lasers 32-63) blocks.
const UPPER_BLOCK: u16 = 0xEEFF;
const LOWER_BLOCK: u16 = 0xDDFF;

/// Return-mode factory byte.
const STRONGEST: u8 = 0x37;
const LAST: u8 = 0x38;
const DUAL: u8 = 0x39;
/// Older firmware (HDL-32E before 2.2.20) leaves both factory bytes zero.
const UNSET: u8 = 0x00;

/// Product ids of the factory byte that this decoder does not handle.
const VELARRAY: u8 = 0x31;
const VLS128: u8 = 0xA1;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Bank {
    Upper,
    Lower,
}

#[derive(Clone, Debug, PartialEq)]
pub(super) struct Block {
    pub bank: Bank,
    /// Hundredths of a degree, clockwise seen from above, 0 at the front.
    pub azimuth: u16,
    pub returns: [Raw; CHANNELS],
}

#[derive(Clone, Debug, PartialEq)]
pub(super) struct DataPacket {
    pub blocks: [Block; BLOCKS],
    /// Microseconds past the hour of the packet's first firing.
    pub timestamp_us: u32,
    pub return_mode: u8,
    pub product_id: u8,
}

/// Whether a packet holds one return per firing or two (the strongest and the last).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum ReturnMode {
    Single,
    Dual,
}

/// The data packet of a payload; `None` for a position packet.
pub(super) fn read(payload: &[u8]) -> Result<Option<DataPacket>, PacketError> {
    if POSITION_LENS.contains(&payload.len()) {
        return Ok(None);
    }
    if payload.len() != DATA_LEN {
        return Err(PacketError::Length {
            sensor: SENSOR,
            len: payload.len(),
            expected: format!("{DATA_LEN} bytes (data) or 554 / 512 bytes (position)"),
        });
    }
    let Some((blocks, &[t0, t1, t2, t3, return_mode, product_id])) = payload.split_at_checked(BLOCKS * BLOCK_LEN)
    else {
        return Err(invalid("the packet's tail is not 6 bytes".into()));
    };
    let blocks = read_blocks(blocks)?;
    Ok(Some(DataPacket { blocks, timestamp_us: u32::from_le_bytes([t0, t1, t2, t3]), return_mode, product_id }))
}

fn read_blocks(bytes: &[u8]) -> Result<[Block; BLOCKS], PacketError> {
    let blocks: Vec<Block> = bytes
        .chunks_exact(BLOCK_LEN)
        .enumerate()
        .map(|(index, block)| read_block(index, block))
        .collect::<Result<_, _>>()?;
    blocks.try_into().map_err(|_| invalid("the packet does not hold 12 blocks".into()))
}

fn read_block(index: usize, bytes: &[u8]) -> Result<Block, PacketError> {
    let [f0, f1, a0, a1, data @ ..] = bytes else {
        return Err(invalid(format!("block {index} is shorter than its header")));
    };
    let bank = match u16::from_le_bytes([*f0, *f1]) {
        UPPER_BLOCK => Bank::Upper,
        LOWER_BLOCK => Bank::Lower,
        flag => return Err(invalid(format!("block {index} flag {flag:#06X} (expected 0xEEFF or 0xDDFF)"))),
    };
    let azimuth = u16::from_le_bytes([*a0, *a1]);
    if azimuth >= AZIMUTH_UNITS {
        return Err(invalid(format!("block {index} azimuth {azimuth} (expected below {AZIMUTH_UNITS})")));
    }
    let mut returns = [Raw::default(); CHANNELS];
    for (raw, bytes) in returns.iter_mut().zip(data.chunks_exact(3)) {
        if let [d0, d1, intensity] = *bytes {
            *raw = Raw { distance: u16::from_le_bytes([d0, d1]), intensity };
        }
    }
    Ok(Block { bank, azimuth, returns })
}

impl DataPacket {
    fn has_lower_blocks(&self) -> bool {
        self.blocks.iter().any(|block| block.bank == Bank::Lower)
    }

    /// The model the factory bytes (or, for the HDL-64E, the lower blocks) name.
    pub fn detect_model(&self) -> Result<Model, PacketError> {
        if self.has_lower_blocks() {
            return Err(invalid(
                "the packet is an HDL-64E's (upper and lower blocks); set the model (S2 or S3) and its calibration"
                    .into(),
            ));
        }
        match self.product_id {
            UNSET => Err(invalid("product id 0x00 (older firmware does not name the model); set the model".into())),
            VELARRAY | VLS128 => {
                Err(invalid(format!("product id {:#04X} is a model this decoder does not support", self.product_id)))
            }
            id => Model::from_product_id(id).ok_or_else(|| invalid(format!("unknown product id {id:#04X}"))),
        }
    }

    /// Checks that the packet is one `model` sends.
    pub fn check_model(&self, model: Model) -> Result<(), PacketError> {
        if model.is_hdl64e() {
            // The HDL-64E's factory bytes carry status information, not a product id.
            return Ok(());
        }
        if self.has_lower_blocks() {
            return Err(invalid(format!("a lower block (0xDDFF) in a {} packet", model.name())));
        }
        match self.product_id {
            UNSET => Ok(()),
            id if Model::from_product_id(id) == Some(model) => Ok(()),
            id => Err(invalid(format!("product id {id:#04X} is not the configured {}", model.name()))),
        }
    }

    pub fn return_mode(&self, model: Model) -> Result<ReturnMode, PacketError> {
        if model.is_hdl64e() {
            // The HDL-64E does not say; in dual mode four blocks share a firing azimuth.
            let [first, _, third, ..] = &self.blocks;
            let dual = first.azimuth == third.azimuth;
            return Ok(if dual { ReturnMode::Dual } else { ReturnMode::Single });
        }
        match self.return_mode {
            STRONGEST | LAST | UNSET => Ok(ReturnMode::Single),
            DUAL => Ok(ReturnMode::Dual),
            mode => Err(invalid(format!("return mode {mode:#04X} (expected 0x37, 0x38 or 0x39)"))),
        }
    }

    /// The azimuth that decides the packet's rotation: its last block's, as velodyne-decoder.
    pub fn last_azimuth(&self) -> u16 {
        let [.., last] = &self.blocks;
        last.azimuth
    }

    /// Hundredths of a degree the head turns from the first to the last block.
    pub fn azimuth_span(&self) -> u32 {
        let [first, .., last] = &self.blocks;
        let units = u32::from(AZIMUTH_UNITS);
        (u32::from(last.azimuth) + units - u32::from(first.azimuth)) % units
    }
}

fn invalid(reason: String) -> PacketError {
    PacketError::Invalid { sensor: SENSOR, reason }
}
