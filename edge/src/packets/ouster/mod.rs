//! Ouster lidar packets (OS0, OS1, OS2; 32, 64 or 128 beams): metadata and payloads in, one
//! rotation (frame) at a time out, with the points ouster-sdk's `XYZLut` gives.
//!
//! How the stream is read:
//! - A rotation is one frame: the packets (LEGACY: the columns) of one `frame_id`. A packet of a
//!   new frame closes the one in progress; a late packet of the frame just closed is dropped.
//!   A change of the packet header's `init_id` (the sensor re-initialised) closes it too.
//! - Columns whose status bit 0 is clear are skipped, as ouster-sdk skips them, and so are columns
//!   whose measurement id is past the frame or already received (a duplicated packet).
//! - `gaps` counts the columns of the metadata's column window the frame did not deliver. Where the
//!   stream began (or the sensor re-initialised) mid-frame, the columns before the first received
//!   are not gaps: the rotation is `partial`; likewise the columns after the last received when
//!   the stream ends ([`Assembler::finish`]) or the sensor resets.
//! - `time` is from the column timestamps, in seconds from the rotation's earliest column.
//! - `intensity` is the calibrated reflectivity: unlike signal it does not fall with range, which
//!   is what scan matching on intensity wants, and every profile has it (the low-data one has no
//!   signal).
//! - Returns come column by column, in the window's order, beams in the metadata's order within a
//!   column; a rotation with reordered packets is sorted back into that order.
//! - Payload sizes: a lidar packet's size (from the metadata) is decoded; a LEGACY IMU packet
//!   (48 bytes) is `Ok(None)`; anything else is [`PacketError::Length`]. The IMU packets of newer
//!   IMU profiles come to the IMU port, which callers do not feed here; at another size they are
//!   a `Length` error, dropped like any stray datagram.

mod metadata;
mod profile;
mod xyz;

pub use metadata::{Metadata, MetadataError};
pub use profile::Profile;

use super::{Assembler, PacketError, Return, ReturnChoice, Rotation, reuse};
use profile::{Column, Echo, LEGACY_IMU_PACKET_BYTES, PacketFormat, Pixel};
use xyz::XyzLut;

const SENSOR: &str = "Ouster";

/// Cuts a stream of one Ouster sensor's lidar packets into rotations.
#[derive(Debug)]
pub struct OusterAssembler {
    /// What decodes the packets; the metadata's error when it is unusable (every push reports it).
    decoder: Result<Decoder, MetadataError>,
    frames: Frames,
}

impl OusterAssembler {
    /// An assembler for the sensor `metadata` describes, keeping `choice` of a dual profile's
    /// returns. Metadata that fails [`Metadata::validate`] gives an assembler whose every push is
    /// an error naming the problem.
    pub fn new(metadata: Metadata, choice: ReturnChoice) -> OusterAssembler {
        let decoder = metadata.validate().map(|()| Decoder::new(&metadata, choice));
        OusterAssembler { decoder, frames: Frames::default() }
    }
}

impl Assembler for OusterAssembler {
    fn push(&mut self, payload: &[u8], received: f64) -> Result<Option<Rotation>, PacketError> {
        let decoder = self.decoder.as_ref().map_err(|e| invalid(format!("unusable metadata: {e}")))?;
        let Some(key) = decoder.frame_of(payload)? else {
            return Ok(None);
        };
        if self.frames.is_late(key) {
            return Ok(None);
        }
        let done = self.frames.close_if_new(key, &decoder.window);
        let scan = self.frames.current(key, received, &decoder.window);
        for column in decoder.format.columns(payload) {
            scan.add_column(decoder, &column);
        }
        Ok(done)
    }

    fn finish(&mut self) -> Option<Rotation> {
        let scan = std::mem::take(&mut self.frames).scan?;
        let window = &self.decoder.as_ref().ok()?.window;
        scan.close(Ending::StreamEnd, window, &mut Vec::new()).filter(|rotation| !rotation.returns.is_empty())
    }

    fn recycle(&mut self, returns: Vec<Return>) {
        self.frames.spare = returns;
    }
}

/// Where the stream is: the frame in progress and the one before.
#[derive(Debug, Default)]
struct Frames {
    scan: Option<Scan>,
    /// The frame last closed: its late packets are dropped rather than opening a rotation.
    closed: Option<FrameKey>,
    /// Whether the next rotation starts where the last one ended (not at the stream's start or
    /// after a reset), so that the columns before its first are gaps, not a partial start.
    follows_previous: bool,
    /// Returns of the last rotation closed: the next one's is reserved at once rather than grown.
    last_returns: usize,
    /// A rotation's returns given back by the caller ([`Assembler::recycle`]).
    spare: Vec<Return>,
    /// The last closed rotation's column per return, for the next one to write into.
    spare_columns: Vec<u16>,
}

impl Frames {
    /// A packet of the frame just closed, arriving after the next one began.
    fn is_late(&self, key: FrameKey) -> bool {
        self.closed == Some(key) && self.scan.as_ref().is_none_or(|scan| scan.key != key)
    }

    /// Closes the rotation in progress if `key` is another frame.
    fn close_if_new(&mut self, key: FrameKey, window: &Window) -> Option<Rotation> {
        let scan = self.scan.take_if(|scan| scan.key != key)?;
        let ending = if scan.key.init_id == key.init_id { Ending::NextFrame } else { Ending::Reset };
        self.closed = Some(scan.key);
        self.follows_previous = ending == Ending::NextFrame;
        self.last_returns = scan.returns.len();
        scan.close(ending, window, &mut self.spare_columns)
    }

    /// The rotation of frame `key`, opened by this packet if it is the frame's first.
    fn current(&mut self, key: FrameKey, received: f64, window: &Window) -> &mut Scan {
        let (follows_previous, capacity) = (self.follows_previous, self.last_returns);
        let (spare, spare_columns) = (&mut self.spare, &mut self.spare_columns);
        self.scan.get_or_insert_with(|| {
            Scan::new(key, received, follows_previous, window, reuse(spare, capacity), reuse(spare_columns, capacity))
        })
    }
}

fn invalid(reason: String) -> PacketError {
    PacketError::Invalid { sensor: SENSOR, reason }
}

/// A frame of one initialisation of the sensor (LEGACY packets carry no init id).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct FrameKey {
    frame_id: u16,
    init_id: Option<u32>,
}

/// Why a rotation ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Ending {
    /// The next frame began: missing columns at the end are gaps.
    NextFrame,
    /// The sensor re-initialised: the frame was cut short.
    Reset,
    /// The stream ended.
    StreamEnd,
}

/// The metadata's column window: which measurement ids a whole frame holds, in the order sent.
#[derive(Clone, Copy, Debug)]
struct Window {
    first: usize,
    columns: usize,
    columns_per_frame: usize,
}

impl Window {
    /// The measurement id's place in the window's order (past the window's columns if outside it).
    fn position(&self, measurement_id: usize) -> usize {
        (measurement_id + self.columns_per_frame - self.first) % self.columns_per_frame.max(1)
    }

    fn measurement_id(&self, position: usize) -> usize {
        (self.first + position) % self.columns_per_frame.max(1)
    }
}

/// Everything fixed by the metadata.
#[derive(Debug)]
struct Decoder {
    format: PacketFormat,
    xyz: XyzLut,
    window: Window,
    choice: ReturnChoice,
}

impl Decoder {
    fn new(metadata: &Metadata, choice: ReturnChoice) -> Decoder {
        Decoder {
            format: PacketFormat::new(metadata.profile, metadata.pixels_per_column, metadata.columns_per_packet),
            xyz: XyzLut::new(metadata),
            window: Window {
                first: metadata.column_window[0],
                columns: metadata.window_columns(),
                columns_per_frame: metadata.columns_per_frame,
            },
            choice,
        }
    }

    /// The payload's frame; `None` for a payload without points (an IMU packet, or a LEGACY
    /// packet without one valid column, which names no frame).
    fn frame_of(&self, payload: &[u8]) -> Result<Option<FrameKey>, PacketError> {
        let expected = self.format.packet_bytes();
        if payload.len() == LEGACY_IMU_PACKET_BYTES && expected != LEGACY_IMU_PACKET_BYTES {
            return Ok(None);
        }
        if payload.len() != expected {
            let expected = format!("{expected} bytes, or {LEGACY_IMU_PACKET_BYTES} for IMU packets");
            return Err(PacketError::Length { sensor: SENSOR, len: payload.len(), expected });
        }
        let header = self.format.header(payload).map_err(invalid)?;
        let legacy_frame_id =
            || self.format.columns(payload).find(|column| column.valid).and_then(|column| column.frame_id);
        let frame_id = header.frame_id.or_else(legacy_frame_id);
        Ok(frame_id.map(|frame_id| FrameKey { frame_id, init_id: header.init_id }))
    }

    /// The returns of a pixel that `choice` keeps, before dropping those without a range.
    fn chosen(&self, pixel: Pixel) -> [Option<Echo>; 2] {
        match self.choice {
            ReturnChoice::First => [Some(pixel.first), None],
            ReturnChoice::Second => [pixel.second, None],
            ReturnChoice::Both => {
                [Some(pixel.first), pixel.second.filter(|second| second.range_mm != pixel.first.range_mm)]
            }
        }
    }
}

/// The rotation in progress.
#[derive(Debug)]
struct Scan {
    key: FrameKey,
    stamp: f64,
    follows_previous: bool,
    /// The returns, complete but for their times, which wait for the rotation's earliest column.
    returns: Vec<Return>,
    /// Per return, its column's measurement id.
    return_columns: Vec<u16>,
    /// Per measurement id, its column's timestamp (ns), once the column came.
    column_ns: Vec<u64>,
    /// Per measurement id, whether its column came.
    received: Vec<bool>,
    columns: usize,
    earliest_ns: u64,
    last_order: usize,
    reordered: bool,
}

impl Scan {
    /// A rotation written into `returns` and `return_columns` (empty, with room reserved).
    fn new(
        key: FrameKey,
        stamp: f64,
        follows_previous: bool,
        window: &Window,
        returns: Vec<Return>,
        return_columns: Vec<u16>,
    ) -> Scan {
        Scan {
            key,
            stamp,
            follows_previous,
            return_columns,
            returns,
            column_ns: vec![0; window.columns_per_frame],
            received: vec![false; window.columns_per_frame],
            columns: 0,
            earliest_ns: u64::MAX,
            last_order: 0,
            reordered: false,
        }
    }

    /// Decodes a column into returns, unless it is invalid, of another frame or already in.
    fn add_column(&mut self, decoder: &Decoder, column: &Column) {
        let Some(measurement_id) = self.accept(decoder, column) else { return };
        self.column_ns[measurement_id] = column.timestamp_ns;
        for (beam, pixel) in decoder.format.pixels(column).enumerate() {
            for echo in decoder.chosen(pixel).into_iter().flatten().filter(|echo| echo.range_mm > 0) {
                let Some(xyz) = decoder.xyz.point(measurement_id, beam, echo.range_mm) else { continue };
                self.returns.push(Return {
                    position: xyz,
                    intensity: f32::from(echo.reflectivity),
                    ring: u16::try_from(beam).unwrap_or(u16::MAX),
                    time: 0.0,
                });
                self.return_columns.push(column.measurement_id);
            }
        }
    }

    /// The column's measurement id if it is one to decode, noting it as received.
    fn accept(&mut self, decoder: &Decoder, column: &Column) -> Option<usize> {
        let of_this_frame = column.frame_id.is_none_or(|frame_id| frame_id == self.key.frame_id);
        if !column.valid || !of_this_frame {
            return None;
        }
        let measurement_id = usize::from(column.measurement_id);
        let seen = self.received.get_mut(measurement_id)?; // None: past the frame
        if *seen {
            return None; // a duplicated packet
        }
        *seen = true;
        let order = decoder.window.position(measurement_id);
        self.reordered |= self.columns > 0 && order < self.last_order;
        self.last_order = self.last_order.max(order);
        self.columns += 1;
        self.earliest_ns = self.earliest_ns.min(column.timestamp_ns);
        Some(measurement_id)
    }

    /// The rotation, or `None` when no valid column came; its per-return columns go back into
    /// `columns_back` for the next rotation.
    fn close(mut self, ending: Ending, window: &Window, columns_back: &mut Vec<u16>) -> Option<Rotation> {
        if self.columns == 0 {
            return None;
        }
        let coverage = Coverage::of(&self.received, window);
        let leading_are_gaps = self.follows_previous;
        let trailing_are_gaps = ending == Ending::NextFrame;
        let gaps = coverage.inside
            + if leading_are_gaps { coverage.before } else { 0 }
            + if trailing_are_gaps { coverage.after } else { 0 };
        let partial = (!leading_are_gaps && coverage.before > 0) || (!trailing_are_gaps && coverage.after > 0);
        let earliest_ns = self.earliest_ns;
        let columns = std::mem::take(&mut self.return_columns);
        for (point, &id) in self.returns.iter_mut().zip(&columns) {
            let column_ns = self.column_ns[usize::from(id)];
            point.time = (column_ns.saturating_sub(earliest_ns) as f64 * 1e-9) as f32;
        }
        let returns = if self.reordered {
            // Back into the window's order (stable: a column's returns keep theirs).
            let mut order: Vec<usize> = (0..self.returns.len()).collect();
            order.sort_by_key(|&i| window.position(usize::from(columns[i])));
            order.into_iter().map(|i| self.returns[i]).collect()
        } else {
            self.returns
        };
        *columns_back = columns;
        Some(Rotation { returns, stamp: self.stamp, gaps, partial })
    }
}

/// Which of the window's columns a frame delivered: the missing ones before the first received,
/// between the first and last received, and after the last.
#[derive(Debug, PartialEq, Eq)]
struct Coverage {
    before: usize,
    inside: usize,
    after: usize,
}

impl Coverage {
    fn of(received: &[bool], window: &Window) -> Coverage {
        let came = |position: usize| received.get(window.measurement_id(position)).copied().unwrap_or(false);
        let positions = 0..window.columns;
        let (Some(first), Some(last)) = (positions.clone().find(|&p| came(p)), positions.rev().find(|&p| came(p)))
        else {
            return Coverage { before: window.columns, inside: 0, after: 0 };
        };
        let inside = (first..=last).filter(|&p| !came(p)).count();
        Coverage { before: first, inside, after: window.columns - 1 - last }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn window() -> Window {
        Window { first: 6, columns: 6, columns_per_frame: 8 }
    }

    #[test]
    fn a_wrapped_window_orders_columns_from_its_first() {
        let window = window();
        assert_eq!(window.position(6), 0);
        assert_eq!(window.position(3), 5);
        assert_eq!(window.measurement_id(2), 0);
        // 4 and 5 are outside the window [6, 3].
        assert!(window.position(4) >= window.columns);
    }

    #[test]
    fn coverage_splits_missing_columns_around_those_received() {
        let window = window();
        let mut received = vec![false; 8];
        for id in [7, 1, 2] {
            received[id] = true;
        }
        assert_eq!(Coverage::of(&received, &window), Coverage { before: 1, inside: 1, after: 1 });
        assert_eq!(Coverage::of(&[false; 8], &window), Coverage { before: 6, inside: 0, after: 0 });
    }
}
