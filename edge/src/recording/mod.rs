//! Scan sources for real recordings: a directory of scan files, a ROS 1 `.bag`, or an `.mcap`.
//!
//! [`open`] picks the reader from the input (a directory, or the `.bag` / `.mcap` extension) and
//! returns a [`Recording`], an iterator of [`Scan`]s read lazily: a bag or MCAP file is streamed
//! chunk by chunk, so memory stays at about one chunk whatever the file size.
//!
//! Every scan goes through the same steps: points with a NaN or infinite coordinate, and (by
//! default) points exactly at the origin, are dropped and counted in [`Scan::dropped`]; missing
//! ring and time channels are derived if [`RecordingOptions`] asks for it.
//!
//! Stamps ([`Scan::stamp`], seconds): the message's `header.stamp` for bags and MCAP (the record
//! or log time if the header stamp is zero), so usually absolute (Unix) time; for a directory the
//! values in its `times.txt`, or `index * directory_period_s` without one.
//!
//! Errors come in two kinds (see [`RecordingError::is_fatal`]): a bad message or scan file is
//! reported as one `Err` item and reading goes on; damage to the container (truncation,
//! corruption) is reported after every scan before it, and ends the iteration.

mod bag;
pub mod capture;
mod convert;
mod directory;
mod mcap_file;
mod packet_scans;
pub mod pointcloud2;
pub mod rings;
pub mod sweep_time;

use std::path::{Path, PathBuf};

use cloud::PointCloud;
use cloud::formats::FormatError;

pub use convert::{ConvertError, ConvertSummary, convert};
pub use packet_scans::{PacketDecoder, PacketOptions, assembler_for, rotation_cloud};
pub use pointcloud2::MessageError;
pub use rings::{ClusterOptions, RingClusters, RingModel, cluster_rings};
pub use sweep_time::{Spin, TimeModel, times_from_azimuth};

use pointcloud2::WireFormat;

/// One scan of a recording.
#[derive(Clone, Debug, PartialEq)]
pub struct Scan {
    /// The valid points and their channels.
    pub cloud: PointCloud,
    /// Seconds; see the module doc for where it comes from.
    pub stamp: f64,
    /// Position in the recording: the file's rank in a directory, the message's rank on the topic.
    pub index: usize,
    /// Points dropped as invalid (non-finite, or at the origin when that is dropped).
    pub dropped: usize,
    /// Packets (Velodyne) or columns (Ouster) of the rotation lost before decoding; 0 for
    /// recordings of point clouds.
    pub gaps: usize,
    /// The scan covers only part of a rotation: a capture's first or last.
    pub partial: bool,
}

/// Settings of [`open`].
#[derive(Clone, Debug, PartialEq)]
pub struct RecordingOptions {
    /// Topic to read from a bag or MCAP file. Default `None`: the only sensor_msgs/PointCloud2 topic.
    pub topic: Option<String>,
    /// How to fill a missing ring channel. Default [`RingModel::None`] (left absent).
    pub rings: RingModel,
    /// How to fill a missing time channel. Default [`TimeModel::None`] (left absent).
    pub times: TimeModel,
    /// Seconds between the scans of a directory without `times.txt`. Default 0.1 (10 Hz, as KITTI).
    pub directory_period_s: f64,
    /// Drop points exactly at (0, 0, 0), which organised clouds (Ouster, Livox) use for "no
    /// return". Default `true`.
    pub drop_origin_points: bool,
    /// How to decode a capture of LiDAR packets.
    pub packets: PacketOptions,
}

impl Default for RecordingOptions {
    fn default() -> Self {
        Self {
            topic: None,
            rings: RingModel::None,
            times: TimeModel::None,
            directory_period_s: 0.1,
            drop_origin_points: true,
            packets: PacketOptions::default(),
        }
    }
}

/// The kind of input, chosen by [`open`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RecordingKind {
    /// A directory of `.bin`, `.pcd` or `.ply` scans.
    Directory,
    /// A ROS 1 bag (format 2.0).
    Bag,
    /// An MCAP file.
    Mcap,
    /// A capture of LiDAR packets (pcap or pcapng).
    Pcap,
}

impl RecordingKind {
    /// The kind of `input`: a directory, else by extension (case-insensitive), else a packet
    /// capture if its first bytes say so (`tcpdump -w` names no extension).
    pub fn of(input: &Path) -> Result<Self, RecordingErrorKind> {
        if input.is_dir() {
            return Ok(RecordingKind::Directory);
        }
        let extension = input.extension().map(|e| e.to_string_lossy().to_ascii_lowercase());
        match extension.as_deref() {
            Some("bag") => Ok(RecordingKind::Bag),
            Some("mcap") => Ok(RecordingKind::Mcap),
            Some("pcap" | "pcapng") => Ok(RecordingKind::Pcap),
            _ if !input.exists() => Err(RecordingErrorKind::Io(std::io::ErrorKind::NotFound.into())),
            _ if capture::is_capture(input) => Ok(RecordingKind::Pcap),
            _ => Err(RecordingErrorKind::Unsupported),
        }
    }
}

/// A topic of a bag or MCAP file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TopicInfo {
    /// Topic name.
    pub topic: String,
    /// Message type (`sensor_msgs/PointCloud2` in ROS 1, `sensor_msgs/msg/PointCloud2` in ROS 2).
    pub message_type: String,
}

impl TopicInfo {
    /// Whether the topic carries sensor_msgs/PointCloud2 (ROS 1 or ROS 2 spelling).
    pub fn is_point_cloud2(&self) -> bool {
        matches!(self.message_type.as_str(), "sensor_msgs/PointCloud2" | "sensor_msgs/msg/PointCloud2")
    }
}

/// A failure to open or read a recording: the file and the reason.
#[derive(Debug, thiserror::Error)]
#[error("{}: {kind}", path.display())]
pub struct RecordingError {
    /// The recording (file or directory).
    pub path: PathBuf,
    /// What went wrong.
    pub kind: RecordingErrorKind,
}

impl RecordingError {
    /// Whether the error ends the recording (damage to the container) rather than one scan.
    pub fn is_fatal(&self) -> bool {
        self.kind.is_fatal()
    }
}

/// Why a recording could not be opened or read.
#[derive(Debug, thiserror::Error)]
pub enum RecordingErrorKind {
    /// The file or directory could not be read.
    #[error("cannot read: {0}")]
    Io(std::io::Error),
    /// Neither a directory nor a `.bag`, `.mcap`, `.pcap` or `.pcapng` file.
    #[error("not a recording: expected a directory of scans, a .bag, .mcap, .pcap or .pcapng file")]
    Unsupported,
    /// A packet capture that cannot be read on; the scans before were delivered.
    #[error(transparent)]
    Capture(capture::CaptureError),
    /// The sensor's metadata or calibration cannot be read.
    #[error("sensor setup: {0}")]
    SensorSetup(String),
    /// A directory without scan files.
    #[error("no .bin, .pcd or .ply scans in the directory (nor in its velodyne/ folder)")]
    NoScans,
    /// A line of `times.txt` that is not a number.
    #[error("{}: line {line} ({text:?}) is not a number of seconds", file.display())]
    TimesSyntax {
        /// The times file.
        file: PathBuf,
        /// 1-based line number.
        line: usize,
        /// The line.
        text: String,
    },
    /// `times.txt` with a different number of stamps than scan files.
    #[error(
        "{}: {stamps} stamps for {scans} scan files (one line per scan expected, or a line for every index the scan files are named by)",
        file.display()
    )]
    TimesCount {
        /// The times file.
        file: PathBuf,
        /// Stamps found.
        stamps: usize,
        /// Scan files found.
        scans: usize,
    },
    /// A scan file of a directory that could not be read.
    #[error("scan {index}: {source}")]
    ScanFile {
        /// The scan's index.
        index: usize,
        /// The reader's error, naming the file.
        source: FormatError,
    },
    /// A ROS 1 bag of another format version.
    #[error("ROS bag format {0} is not supported, only 2.0")]
    BagVersion(String),
    /// The requested topic is not in the recording.
    #[error("no topic {topic:?}; the recording has: {}", describe(.available))]
    UnknownTopic {
        /// The topic asked for.
        topic: String,
        /// The topics present.
        available: Vec<TopicInfo>,
    },
    /// The requested topic does not carry point clouds.
    #[error("topic {topic:?} carries {message_type}, not sensor_msgs/PointCloud2")]
    NotPointCloud {
        /// The topic asked for.
        topic: String,
        /// Its message type.
        message_type: String,
    },
    /// No topic was given and none carries PointCloud2.
    #[error("no sensor_msgs/PointCloud2 topic; the recording has: {}", describe(.available))]
    NoPointCloudTopic {
        /// The topics present.
        available: Vec<TopicInfo>,
    },
    /// No topic was given and several carry PointCloud2.
    #[error("several sensor_msgs/PointCloud2 topics, choose one: {}", describe(.candidates))]
    AmbiguousTopic {
        /// The PointCloud2 topics.
        candidates: Vec<TopicInfo>,
    },
    /// An MCAP channel whose message encoding is neither `cdr` nor `ros1`.
    #[error("topic {topic:?} uses message encoding {encoding:?}; only cdr and ros1 are decoded")]
    Encoding {
        /// The topic.
        topic: String,
        /// Its message encoding.
        encoding: String,
    },
    /// The file ends early; the scans before were delivered.
    #[error("truncated at byte {offset}, after {scans} scans: {detail}")]
    Truncated {
        /// Where the damage was found: the file's length, or how far the reader got.
        offset: u64,
        /// Scan messages delivered before it.
        scans: usize,
        /// What was cut.
        detail: String,
    },
    /// The file is damaged; the scans before were delivered.
    #[error("corrupt at byte {offset}, after {scans} scans: {detail}")]
    Corrupt {
        /// Where the damage was found (the record, or how far the reader got).
        offset: u64,
        /// Scan messages delivered before it.
        scans: usize,
        /// What is wrong.
        detail: String,
    },
    /// A PointCloud2 message that cannot be decoded; the next one is read after it.
    #[error("scan {index}{}: {reason}", at_record(.offset))]
    Message {
        /// The message's index on the topic.
        index: usize,
        /// File offset of the record (or chunk) holding it, when known.
        offset: Option<u64>,
        /// What is wrong with it.
        reason: MessageError,
    },
}

impl RecordingErrorKind {
    /// Whether reading cannot go on after this error.
    pub fn is_fatal(&self) -> bool {
        !matches!(self, RecordingErrorKind::ScanFile { .. } | RecordingErrorKind::Message { .. })
    }
}

/// `topic (type), ...`, or `no topics`.
fn describe(topics: &[TopicInfo]) -> String {
    if topics.is_empty() {
        return "no topics".to_owned();
    }
    let items: Vec<String> = topics.iter().map(|t| format!("{} ({})", t.topic, t.message_type)).collect();
    items.join(", ")
}

fn at_record(offset: &Option<u64>) -> String {
    offset.map(|o| format!(" (record at byte {o})")).unwrap_or_default()
}

/// The topics a bag or MCAP file lists, and any damage that stopped the listing early.
struct Listing {
    topics: Vec<TopicInfo>,
    damage: Option<RecordingErrorKind>,
}

impl Listing {
    /// The topic to read; when it cannot be chosen in a damaged file, the damage is the error
    /// (the topic may lie beyond it).
    fn choose(self, wanted: Option<&str>) -> Result<String, RecordingErrorKind> {
        choose_topic(&self.topics, wanted).map_err(|e| self.damage.unwrap_or(e))
    }
}

/// A scan as a source delivers it, before the common steps.
struct RawScan {
    cloud: PointCloud,
    stamp: f64,
    index: usize,
    dropped: usize,
    gaps: usize,
    partial: bool,
}

/// A serialised PointCloud2 as a bag or MCAP source delivers it.
struct RawMessage {
    index: usize,
    offset: Option<u64>,
    /// Record time (bag) or log time (MCAP), seconds: the stamp when the header has none.
    receive_time: f64,
    data: Vec<u8>,
    format: WireFormat,
}

impl RawMessage {
    /// Decodes and converts the message.
    fn decode(self) -> Result<RawScan, RecordingErrorKind> {
        let fail = |reason| RecordingErrorKind::Message { index: self.index, offset: self.offset, reason };
        let message = pointcloud2::decode(&self.data, self.format).map_err(fail)?;
        let converted = message.to_cloud().map_err(fail)?;
        let stamp = if message.stamp != 0.0 { message.stamp } else { self.receive_time };
        Ok(RawScan {
            cloud: converted.cloud,
            stamp,
            index: self.index,
            dropped: converted.dropped_non_finite,
            gaps: 0,
            partial: false,
        })
    }
}

/// The reader behind a [`Recording`].
enum Source {
    Directory(directory::DirectorySource),
    Bag(bag::BagSource),
    Mcap(mcap_file::McapSource),
    Packets(packet_scans::PacketScans),
}

impl Source {
    fn next_scan(&mut self) -> Option<Result<RawScan, RecordingErrorKind>> {
        match self {
            Source::Directory(d) => d.next_scan(),
            Source::Bag(b) => b.next_message().map(|m| m.and_then(RawMessage::decode)),
            Source::Mcap(m) => m.next_message().map(|m| m.and_then(RawMessage::decode)),
            Source::Packets(p) => p.next_scan(),
        }
    }
}

/// An opened recording: an iterator of scans in recording order.
pub struct Recording {
    path: PathBuf,
    kind: RecordingKind,
    topic: Option<String>,
    options: RecordingOptions,
    channels: ChannelDeriver,
    source: Source,
    done: bool,
}

impl std::fmt::Debug for Recording {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recording")
            .field("path", &self.path)
            .field("kind", &self.kind)
            .field("topic", &self.topic)
            .finish_non_exhaustive()
    }
}

/// Opens a recording; for a bag or MCAP file, resolves the topic (see [`RecordingOptions::topic`]).
pub fn open(input: &Path, options: &RecordingOptions) -> Result<Recording, RecordingError> {
    let fail = |kind| RecordingError { path: input.to_owned(), kind };
    let kind = RecordingKind::of(input).map_err(fail)?;
    let (source, topic) = match kind {
        RecordingKind::Directory => (
            Source::Directory(directory::DirectorySource::open(input, options.directory_period_s).map_err(fail)?),
            None,
        ),
        RecordingKind::Bag => {
            let topic = bag::list_topics(input).and_then(|l| l.choose(options.topic.as_deref())).map_err(fail)?;
            (Source::Bag(bag::BagSource::open(input, &topic).map_err(fail)?), Some(topic))
        }
        RecordingKind::Mcap => {
            let topic = mcap_file::list_topics(input).and_then(|l| l.choose(options.topic.as_deref())).map_err(fail)?;
            (Source::Mcap(mcap_file::McapSource::open(input, &topic).map_err(fail)?), Some(topic))
        }
        RecordingKind::Pcap => {
            (Source::Packets(packet_scans::PacketScans::open(input, &options.packets).map_err(fail)?), None)
        }
    };
    let channels = ChannelDeriver::new(options.clone());
    Ok(Recording { path: input.to_owned(), kind, topic, options: options.clone(), channels, source, done: false })
}

/// The topics of a bag or MCAP file (empty for a directory). A file without its index or summary
/// is read from the front to find them; if damaged, the topics before the damage are listed.
pub fn list_topics(input: &Path) -> Result<Vec<TopicInfo>, RecordingError> {
    let fail = |kind| RecordingError { path: input.to_owned(), kind };
    match RecordingKind::of(input).map_err(fail)? {
        RecordingKind::Directory => Ok(Vec::new()),
        RecordingKind::Bag => bag::list_topics(input).map(|l| l.topics).map_err(fail),
        RecordingKind::Mcap => mcap_file::list_topics(input).map(|l| l.topics).map_err(fail),
        RecordingKind::Pcap => Ok(Vec::new()),
    }
}

/// The topic to read: `wanted` if present and a PointCloud2, else the only PointCloud2 topic.
fn choose_topic(topics: &[TopicInfo], wanted: Option<&str>) -> Result<String, RecordingErrorKind> {
    if let Some(wanted) = wanted {
        let Some(found) = topics.iter().find(|t| t.topic == wanted) else {
            return Err(RecordingErrorKind::UnknownTopic { topic: wanted.to_owned(), available: topics.to_vec() });
        };
        if !found.is_point_cloud2() {
            return Err(RecordingErrorKind::NotPointCloud {
                topic: found.topic.clone(),
                message_type: found.message_type.clone(),
            });
        }
        return Ok(found.topic.clone());
    }
    let candidates: Vec<TopicInfo> = topics.iter().filter(|t| t.is_point_cloud2()).cloned().collect();
    match candidates.as_slice() {
        [only] => Ok(only.topic.clone()),
        [] => Err(RecordingErrorKind::NoPointCloudTopic { available: topics.to_vec() }),
        _ => Err(RecordingErrorKind::AmbiguousTopic { candidates }),
    }
}

impl Recording {
    /// The input path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// What kind of input it is.
    pub fn kind(&self) -> RecordingKind {
        self.kind
    }

    /// The topic read (bag and MCAP only).
    pub fn topic(&self) -> Option<&str> {
        self.topic.as_deref()
    }

    /// The common steps: drop invalid points, derive missing channels.
    fn finish(&mut self, raw: RawScan) -> Scan {
        finish(raw, &self.options, &mut self.channels)
    }
}

/// What every scan goes through: invalid points dropped, missing channels derived.
fn finish(raw: RawScan, options: &RecordingOptions, channels: &mut ChannelDeriver) -> Scan {
    let RawScan { mut cloud, stamp, index, mut dropped, gaps, partial } = raw;
    if options.drop_origin_points {
        dropped += drop_origin_points(&mut cloud);
    }
    channels.derive(&mut cloud);
    Scan { cloud, stamp, index, dropped, gaps, partial }
}

/// A serialised ROS 2 PointCloud2 (CDR) received from elsewhere, made a scan as a recording's
/// message is: converted, invalid points dropped, missing channels derived by `channels` (made
/// with the same `options`). `receive_time` stands in for a header without a stamp.
pub fn cdr_scan(
    payload: &[u8],
    index: usize,
    receive_time: f64,
    options: &RecordingOptions,
    channels: &mut ChannelDeriver,
) -> Result<Scan, pointcloud2::MessageError> {
    let message = pointcloud2::decode_cdr(payload)?;
    let converted = message.to_cloud()?;
    let stamp = if message.stamp != 0.0 { message.stamp } else { receive_time };
    let raw = RawScan {
        cloud: converted.cloud,
        stamp,
        index,
        dropped: converted.dropped_non_finite,
        gaps: 0,
        partial: false,
    };
    Ok(finish(raw, options, channels))
}

/// Fills the ring and time channels scans lack as the options say (channels a scan has are kept):
/// what every scan of a recording goes through, and clouds that come from elsewhere can. Where
/// rings are clustered from elevations, the beams found in the first scan that needs them are
/// kept for the rest (a sensor's beams do not move), so the clustering runs once and not per scan.
///
/// Rings found automatically ([`RingModel::Auto`]) and times from azimuth assume a spinning head:
/// they are derived only once a scan of the recording showed one ([`sweep_time::is_spinning`]).
/// A solid-state sensor's scans keep neither channel: they have no scan lines and no sweep.
#[derive(Clone, Debug)]
pub struct ChannelDeriver {
    options: RecordingOptions,
    beams: Option<rings::Beams>,
    spinning: bool,
}

impl ChannelDeriver {
    /// Nothing clustered yet, no spinning head seen yet.
    pub fn new(options: RecordingOptions) -> Self {
        ChannelDeriver { options, beams: None, spinning: false }
    }

    /// Fills the channels `cloud` lacks.
    pub fn derive(&mut self, cloud: &mut PointCloud) {
        let assumes_spin =
            self.options.rings == RingModel::Auto || matches!(self.options.times, TimeModel::Azimuth { .. });
        if !self.spinning && assumes_spin && (cloud.ring.is_none() || cloud.time.is_none()) {
            self.spinning = sweep_time::is_spinning(&cloud.points);
        }
        if cloud.ring.is_none() && (self.spinning || self.options.rings != RingModel::Auto) {
            cloud.ring = self.rings(cloud);
        }
        if let (None, TimeModel::Azimuth { period_s, spin }, true) = (&cloud.time, self.options.times, self.spinning) {
            cloud.time = Some(times_from_azimuth(&cloud.points, period_s, spin));
        }
    }

    /// Rings of a cloud without them: from the point order when ring-major, else from the beams.
    fn rings(&mut self, cloud: &PointCloud) -> Option<Vec<u16>> {
        let clustering = match &self.options.rings {
            RingModel::Clustered(options) => options.clone(),
            RingModel::Auto => match rings::scan_order_rings(&cloud.points) {
                Some(rings) => return Some(rings),
                None => ClusterOptions::default(),
            },
            other => return rings::derive_rings(cloud, other),
        };
        if let Some(beams) = &self.beams {
            return Some(beams.assign(&cloud.points));
        }
        let clusters = cluster_rings(&cloud.points, &clustering);
        self.beams = Some(rings::Beams::of(&clusters));
        Some(clusters.ring)
    }
}

impl Iterator for Recording {
    type Item = Result<Scan, RecordingError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.done {
            return None;
        }
        match self.source.next_scan() {
            None => {
                self.done = true;
                None
            }
            Some(Ok(raw)) => Some(Ok(self.finish(raw))),
            Some(Err(kind)) => {
                self.done = kind.is_fatal();
                Some(Err(RecordingError { path: self.path.clone(), kind }))
            }
        }
    }
}

/// Removes the points at exactly (0, 0, 0); returns how many.
fn drop_origin_points(cloud: &mut PointCloud) -> usize {
    let keep: Vec<usize> = (0..cloud.len()).filter(|&i| cloud.points[i] != nalgebra::Point3::origin()).collect();
    let dropped = cloud.len() - keep.len();
    if dropped > 0 {
        *cloud = cloud.select(&keep);
    }
    dropped
}
