//! Scans from a capture of LiDAR packets: the capture's datagrams through a packet decoder.
//!
//! Which sensor sent them is read from what lies beside the capture: Ouster metadata (the
//! capture's name with `.json`, or [`PacketOptions::metadata`]) means an Ouster; otherwise the
//! packets are taken for a Velodyne's, whose model their factory bytes name and whose calibration
//! may lie beside the capture too (its name with `.yaml`). The decoder locks on
//! to the port of the first rotation it completes (or [`PacketOptions::port`]), so a capture that
//! also holds position, IMU or other traffic reads as the sensor's scans alone; two sensors of one
//! kind in one capture need the port named.

use std::path::{Path, PathBuf};

use cloud::PointCloud;
use nalgebra::Point3;

use super::capture::Capture;
use super::{RawScan, RecordingErrorKind};
use crate::packets::ouster::{Metadata, OusterAssembler};
use crate::packets::velodyne::{Calibration, Model, VelodyneAssembler, VelodyneOptions};
use crate::packets::{Assembler, PacketError, Return, ReturnChoice, Rotation};

/// How to decode the packets of a capture or a live sensor.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PacketOptions {
    /// Ouster metadata JSON. Default: the capture's name with `.json`, if present.
    pub metadata: Option<PathBuf>,
    /// Velodyne calibration in velodyne_pointcloud's YAML format; required for an HDL-64E, whose
    /// beams are calibrated one by one. Default: the capture's name with `.yaml`, if present, else
    /// the model's published table.
    pub calibration: Option<PathBuf>,
    /// The Velodyne model. Default: read from the packets' factory bytes; an HDL-64E, whose
    /// packets do not say which it is, must be named.
    pub model: Option<Model>,
    /// Which return of a multi-return sensor to keep. Default: the first (strongest).
    pub returns: ReturnChoice,
    /// The sensor's data port. Default: the port of the first rotation decoded.
    pub port: Option<u16>,
}

/// The decoder packets need, as [`PacketOptions`] and the files beside the capture (if they come
/// from one) say.
pub fn assembler_for(
    capture: Option<&Path>,
    options: &PacketOptions,
) -> Result<Box<dyn Assembler + Send>, RecordingErrorKind> {
    let beside = |extension: &str| capture.map(|c| c.with_extension(extension)).filter(|b| b.is_file());
    let metadata = options.metadata.clone().or_else(|| beside("json"));
    if let Some(path) = metadata {
        let metadata = parse_file(&path, Metadata::from_json)?;
        return Ok(Box::new(OusterAssembler::new(metadata, options.returns)));
    }
    let calibration = match options.calibration.clone().or_else(|| beside("yaml")) {
        Some(path) => Some(parse_file(&path, Calibration::from_yaml)?),
        None => None,
    };
    let velodyne =
        VelodyneOptions { model: options.model, calibration, returns: options.returns, ..VelodyneOptions::default() };
    let assembler = VelodyneAssembler::new(velodyne).map_err(|e| RecordingErrorKind::SensorSetup(e.to_string()))?;
    Ok(Box::new(assembler))
}

/// A sensor file read and parsed, either failure naming the file.
fn parse_file<T, E: std::fmt::Display>(
    path: &Path,
    parse: impl FnOnce(&str) -> Result<T, E>,
) -> Result<T, RecordingErrorKind> {
    let fail = |e: &dyn std::fmt::Display| RecordingErrorKind::SensorSetup(format!("{}: {e}", path.display()));
    let text = std::fs::read_to_string(path).map_err(|e| fail(&e))?;
    parse(&text).map_err(|e| fail(&e))
}

/// Datagrams in, rotations out: the part of a packet source that is the same for a capture and a
/// socket.
pub struct PacketDecoder {
    assembler: Box<dyn Assembler + Send>,
    port: Option<u16>,
    /// Datagrams of the sensor's port that did not decode, the last reason kept.
    pub undecoded: usize,
    /// Why the last of those did not decode.
    pub last_error: Option<PacketError>,
}

impl PacketDecoder {
    /// A decoder; `port` as [`PacketOptions::port`].
    pub fn new(assembler: Box<dyn Assembler + Send>, port: Option<u16>) -> Self {
        PacketDecoder { assembler, port, undecoded: 0, last_error: None }
    }

    /// Feeds one datagram; the rotation it completes, if any.
    pub fn push(&mut self, port: u16, payload: &[u8], received: f64) -> Option<Rotation> {
        if self.port.is_some_and(|p| p != port) {
            return None;
        }
        match self.assembler.push(payload, received) {
            Ok(Some(rotation)) => {
                self.port.get_or_insert(port);
                Some(rotation)
            }
            Ok(None) => None,
            // Before the port is known, other traffic is expected and not counted.
            Err(e) if self.port.is_some() => {
                self.undecoded += 1;
                self.last_error = Some(e);
                None
            }
            Err(_) => None,
        }
    }

    /// The rotation in progress at the end.
    pub fn finish(&mut self) -> Option<Rotation> {
        self.assembler.finish()
    }

    /// Gives a rotation's returns back for the next rotation ([`Assembler::recycle`]).
    pub fn recycle(&mut self, returns: Vec<Return>) {
        self.assembler.recycle(returns);
    }
}

/// A rotation as a cloud with intensity, ring and per-point time.
pub fn rotation_cloud(rotation: &Rotation) -> PointCloud {
    let returns = &rotation.returns;
    PointCloud {
        points: returns.iter().map(|r| Point3::from(r.position)).collect(),
        intensity: Some(returns.iter().map(|r| r.intensity).collect()),
        ring: Some(returns.iter().map(|r| r.ring).collect()),
        time: Some(returns.iter().map(|r| r.time).collect()),
    }
}

/// The scans of a capture file.
pub(super) struct PacketScans {
    capture: Capture,
    decoder: PacketDecoder,
    index: usize,
    finished: bool,
}

impl PacketScans {
    pub(super) fn open(path: &Path, options: &PacketOptions) -> Result<Self, RecordingErrorKind> {
        let capture = Capture::open(path).map_err(RecordingErrorKind::Capture)?;
        let decoder = PacketDecoder::new(assembler_for(Some(path), options)?, options.port);
        Ok(PacketScans { capture, decoder, index: 0, finished: false })
    }

    pub(super) fn next_scan(&mut self) -> Option<Result<RawScan, RecordingErrorKind>> {
        while !self.finished {
            let rotation = match self.capture.next_datagram() {
                Some(Ok(d)) => self.decoder.push(d.destination_port, &d.payload, d.received),
                Some(Err(e)) => {
                    self.finished = true;
                    return Some(Err(RecordingErrorKind::Capture(e)));
                }
                None => {
                    self.finished = true;
                    self.decoder.finish()
                }
            };
            if let Some(rotation) = rotation {
                return Some(Ok(self.scan_of(rotation)));
            }
        }
        None
    }

    fn scan_of(&mut self, rotation: Rotation) -> RawScan {
        let index = self.index;
        self.index += 1;
        let scan = RawScan {
            cloud: rotation_cloud(&rotation),
            stamp: rotation.stamp,
            index,
            dropped: 0,
            gaps: rotation.gaps,
            partial: rotation.partial,
        };
        self.decoder.recycle(rotation.returns);
        scan
    }
}
