//! Decoders of LiDAR UDP packets (Velodyne, Ouster): payloads in, one rotation of the head out.
//!
//! No I/O here: the callers read packets from a capture file or a socket and feed each UDP payload
//! to an [`Assembler`], which decodes it and cuts the stream into rotations. A rotation with lost or
//! reordered packets is still a rotation, its gaps counted; a payload that is not a packet of the
//! sensor is an error for that payload only, never a panic.
//!
//! Points are in the frame the vendors' reference decoders give: velodyne_pointcloud's for Velodyne
//! (x forward, y left, z up), ouster-sdk's `XYZLut` sensor frame for Ouster.

pub mod ouster;
pub mod velodyne;

/// Which return of a beam to keep when the sensor reports more than one.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum ReturnChoice {
    /// The strongest (Velodyne dual mode) or the first return of a dual-return profile (Ouster):
    /// what velodyne_decoder and ouster-sdk's RANGE field give. In single-return modes, the return.
    #[default]
    First,
    /// The other return of a dual-return mode (Velodyne: the last; Ouster: RANGE2); nothing in a
    /// single-return mode.
    Second,
    /// Both returns of a dual-return mode (a beam's second only where it differs from its first).
    Both,
}

/// One return of one beam, in the sensor frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Return {
    /// Metres.
    pub position: [f32; 3],
    /// The sensor's calibrated reflectivity or intensity, as its reference decoder reports it.
    pub intensity: f32,
    /// Beam index, 0 at the lowest elevation for Velodyne (velodyne_pointcloud's ring), the
    /// metadata's beam order for Ouster.
    pub ring: u16,
    /// Seconds from the rotation's first firing.
    pub time: f32,
}

/// One rotation of the head, cut at a fixed azimuth (Velodyne) or frame id (Ouster).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Rotation {
    /// The valid returns (range zero, below the sensor's minimum, left out).
    pub returns: Vec<Return>,
    /// Seconds, on the clock of the `received` values given to [`Assembler::push`]: when the
    /// rotation's first packet arrived.
    pub stamp: f64,
    /// Packets (Velodyne) or columns (Ouster) expected within the rotation and not received.
    pub gaps: usize,
    /// The rotation did not cover the whole turn: a capture's first or last, or one cut short by
    /// a reset of the sensor.
    pub partial: bool,
}

/// Why a payload could not be decoded. The payload is skipped; the stream goes on.
#[derive(Debug, thiserror::Error, Clone, PartialEq, Eq)]
pub enum PacketError {
    /// The payload's length is not one this sensor sends.
    #[error("a {len}-byte payload is not a {sensor} packet (expected {expected})")]
    Length {
        /// The sensor the assembler decodes.
        sensor: &'static str,
        /// Bytes received.
        len: usize,
        /// What the sensor sends, e.g. "1206 bytes".
        expected: String,
    },
    /// A field holds a value the sensor does not send (a block flag, a return mode, a model).
    #[error("{sensor} packet: {reason}")]
    Invalid {
        /// The sensor the assembler decodes.
        sensor: &'static str,
        /// What is wrong, naming the field.
        reason: String,
    },
}

/// Decodes a stream of payloads of one sensor and cuts it into rotations.
pub trait Assembler {
    /// Feeds one UDP payload, received at `received` seconds (capture or host clock). Returns the
    /// rotation this payload completed, if any. Payloads the sensor sends that carry no points
    /// (Velodyne position packets, Ouster IMU packets) are skipped with `Ok(None)`.
    fn push(&mut self, payload: &[u8], received: f64) -> Result<Option<Rotation>, PacketError>;

    /// The rotation in progress at the end of the stream, if it holds returns; marked partial
    /// when it stopped short of the end of the turn.
    fn finish(&mut self) -> Option<Rotation>;

    /// Gives back the returns of a rotation the caller is done with: the next rotation is
    /// written into them instead of into fresh memory, whose every page the kernel would first
    /// have to hand over (a 128-beam rotation is about 3 MB, a third of its decoding time).
    fn recycle(&mut self, returns: Vec<Return>);
}

/// A buffer for the next rotation, room for `capacity` items: the spare one (emptied) if any,
/// else a fresh one.
pub(crate) fn reuse<T>(spare: &mut Vec<T>, capacity: usize) -> Vec<T> {
    let mut returns = std::mem::take(spare);
    returns.clear();
    returns.reserve(capacity);
    returns
}
