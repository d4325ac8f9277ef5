//! Cutting the stream of decoded packets into rotations at a fixed azimuth.
//!
//! As velodyne-decoder, a packet belongs to a rotation by its last block's azimuth, and the first
//! packet whose last block passes the cut ends the rotation. Unlike a plain "the azimuth went
//! down" test, a rotation only ends on a drop of more than half a turn, so a reordered packet
//! stays in its rotation; one arriving after its rotation was cut is dropped.

use crate::packets::{Return, Rotation, reuse};

/// Hundredths of a degree in a turn.
const TURN: i32 = 36000;
const HALF_TURN: i32 = TURN / 2;
/// A rotation still open after this long (on the `received` clock) is cut: the sensor stopped,
/// restarted or lost most of its packets. velodyne-decoder uses the same limit (a ~4 Hz turn).
const MAX_ROTATION_SECONDS: f64 = 0.3;

/// One packet's returns and what the cut needs to know about it.
#[derive(Clone, Debug)]
pub(super) struct DecodedPacket {
    /// Seconds of the packet's first firing on the sensor's clock, continuous over hours.
    pub start: f64,
    /// When the packet arrived, on the caller's clock.
    pub received: f64,
    /// The last block's azimuth, hundredths of a degree.
    pub azimuth: u16,
    /// Hundredths of a degree from this packet to the next, estimated from its own blocks.
    pub step: f64,
    /// Timed from the packet's first firing.
    pub returns: Vec<Return>,
}

/// A packet and its place in its rotation: hundredths of a degree past the cut, beyond a turn
/// for the packet that ends the rotation.
#[derive(Clone, Debug)]
struct Placed {
    position: i32,
    packet: DecodedPacket,
}

/// The packet that ended a rotation at the cut.
#[derive(Clone, Copy, Debug)]
struct CutEnd {
    /// Hundredths of a degree past the cut.
    position: i32,
    start: f64,
}

/// The rotation being filled.
#[derive(Clone, Debug)]
struct Current {
    packets: Vec<Placed>,
    /// Set when the rotation began right after the previous one's cut.
    after_cut: Option<CutEnd>,
    /// When its first packet arrived.
    received: f64,
    earliest_start: f64,
    furthest: i32,
}

impl Current {
    fn new(first: &DecodedPacket, after_cut: Option<CutEnd>) -> Self {
        Self { packets: Vec::new(), after_cut, received: first.received, earliest_start: first.start, furthest: -1 }
    }

    fn add(&mut self, position: i32, packet: DecodedPacket) {
        self.furthest = self.furthest.max(position);
        self.earliest_start = self.earliest_start.min(packet.start);
        self.packets.push(Placed { position, packet });
    }

    /// The packet passes the cut: far into the turn, the azimuth dropped by more than half a turn.
    fn wraps(&self, position: i32) -> bool {
        self.furthest > HALF_TURN && position + HALF_TURN < self.furthest
    }

    /// The same packet received twice.
    fn holds(&self, packet: &DecodedPacket) -> bool {
        self.packets.iter().any(|placed| placed.packet.start == packet.start && placed.packet.azimuth == packet.azimuth)
    }

    /// The rotation, its returns written into `returns` (empty).
    fn into_rotation(self, ended_at_cut: bool, returns: Vec<Return>) -> Rotation {
        let gaps = self.gaps();
        let partial = !(ended_at_cut && self.after_cut.is_some());
        let mut packets = self.packets;
        packets.sort_by(|a, b| a.packet.start.total_cmp(&b.packet.start));
        // Sized at once: collecting the packets' returns one by one grew and copied the rotation
        // a dozen times.
        let mut returns = returns;
        returns.reserve(packets.iter().map(|placed| placed.packet.returns.len()).sum());
        for placed in &packets {
            let offset = placed.packet.start - self.earliest_start;
            returns.extend(
                placed.packet.returns.iter().map(|r| Return { time: (offset + f64::from(r.time)) as f32, ..*r }),
            );
        }
        Rotation { returns, stamp: self.received, gaps, partial }
    }

    /// Packets missing between the received ones, and before the first when the rotation began
    /// at the cut, counted in steps of the head's azimuth per packet.
    fn gaps(&self) -> usize {
        let step = median(self.packets.iter().map(|placed| placed.packet.step).collect());
        // No estimate (a stationary head, or damaged packets): nothing to count in.
        if step.is_nan() || step < 1.0 {
            return 0;
        }
        let missing = |from: i32, to: i32| ((f64::from(to - from) / step).round() as i64 - 1).max(0) as usize;
        let mut positions: Vec<i32> = self.packets.iter().map(|placed| placed.position).collect();
        positions.sort_unstable();
        let between: usize = positions.iter().zip(positions.iter().skip(1)).map(|(&a, &b)| missing(a, b)).sum();
        let before = match (self.after_cut, positions.first()) {
            (Some(end), Some(&first)) => missing(end.position, first),
            _ => 0,
        };
        between + before
    }
}

fn median(mut values: Vec<f64>) -> f64 {
    values.retain(|value| value.is_finite());
    values.sort_by(f64::total_cmp);
    values.get(values.len() / 2).copied().unwrap_or(0.0)
}

/// Cuts decoded packets into rotations.
#[derive(Clone, Debug)]
pub(super) struct Cutter {
    /// Hundredths of a degree; taken from the first packet when not configured.
    cut: Option<u16>,
    current: Option<Current>,
    /// Set when the next rotation begins right after a cut.
    next_after_cut: Option<CutEnd>,
    /// A rotation's returns given back by the caller ([`Cutter::recycle`]).
    spare: Vec<Return>,
}

impl Cutter {
    pub fn new(cut: Option<u16>) -> Self {
        Self { cut, current: None, next_after_cut: None, spare: Vec::new() }
    }

    /// Adds a packet; returns the rotation it completes, if any.
    pub fn push(&mut self, packet: DecodedPacket) -> Option<Rotation> {
        let cut = match self.cut {
            Some(cut) => cut,
            None => {
                // The first rotation starts at the stream's first packet and is a whole turn.
                self.cut = Some(packet.azimuth);
                self.next_after_cut = Some(CutEnd { position: 0, start: f64::NEG_INFINITY });
                packet.azimuth
            }
        };
        let position = (i32::from(packet.azimuth) - i32::from(cut)).rem_euclid(TURN);
        let mut finished = None;
        if self.is_straggler(position, &packet) {
            return None;
        }
        if let Some(current) = &self.current {
            if current.holds(&packet) {
                return None;
            }
            if packet.received - current.received > MAX_ROTATION_SECONDS {
                finished = self.emit(false);
            }
        }
        let next_after_cut = &mut self.next_after_cut;
        let current = self.current.get_or_insert_with(|| Current::new(&packet, next_after_cut.take()));
        if current.wraps(position) {
            self.next_after_cut = Some(CutEnd { position, start: packet.start });
            current.add(position + TURN, packet);
            return self.emit(true);
        }
        current.add(position, packet);
        finished
    }

    /// A packet of the previous rotation that arrives after the cut: older than the packets since,
    /// and half a turn behind them or not past the packet that ended the previous rotation.
    fn is_straggler(&self, position: i32, packet: &DecodedPacket) -> bool {
        let (oldest, furthest, cut_end) = match (&self.current, self.next_after_cut) {
            (Some(current), _) => (current.earliest_start, current.furthest, current.after_cut),
            (None, Some(end)) => (end.start, end.position, Some(end)),
            (None, None) => return false,
        };
        let behind = position > furthest + HALF_TURN || cut_end.is_some_and(|end| position <= end.position);
        behind && packet.start < oldest
    }

    /// The rotation in progress, if it holds returns.
    pub fn finish(&mut self) -> Option<Rotation> {
        self.emit(false).filter(|rotation| !rotation.returns.is_empty())
    }

    /// Takes back a rotation's returns for the next rotation ([`crate::packets::Assembler::recycle`]).
    pub fn recycle(&mut self, returns: Vec<Return>) {
        self.spare = returns;
    }

    fn emit(&mut self, ended_at_cut: bool) -> Option<Rotation> {
        let current = self.current.take()?;
        Some(current.into_rotation(ended_at_cut, reuse(&mut self.spare, 0)))
    }
}
