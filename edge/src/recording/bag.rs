//! ROS 1 bag files (format 2.0), streamed chunk by chunk from the front.
//!
//! Hand-written rather than the `rosbag` crate because a recording cut short (a full disk, a
//! crashed recorder) has no index at its end, and the crate's reader is index-driven and
//! memory-maps the file. The format is small: after the magic line, every record is
//! `header_len u32, header (fields "name=value", each length-prefixed), data_len u32, data`, with
//! the record kind in the header's `op` field. Messages live in chunk records (compression
//! `none`, `bz2` or `lz4`, the latter the LZ4 *frame* format) together with the connection records
//! that name their topics, so one pass from the front finds everything. The index section at the
//! end only speeds up listing topics.
//!
//! Damage: a file that ends inside a record keeps everything before the cut, including the
//! complete messages of a cut chunk (uncompressed data as is, compressed data as far as the
//! decompressor gets), then reports the byte offset. A bag whose header says it has no index
//! (`index_pos` 0: the recorder never closed it) is reported as truncated after its last message.

use std::collections::{HashMap, VecDeque};
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;

use super::pointcloud2::WireFormat;
use super::{Listing, RawMessage, RecordingErrorKind, TopicInfo};

/// The first line of every bag of format 2.0.
const MAGIC: &[u8] = b"#ROSBAG V2.0\n";

/// Record kinds (the header's `op` field).
mod op {
    pub const MESSAGE_DATA: u8 = 0x02;
    pub const BAG_HEADER: u8 = 0x03;
    pub const CHUNK: u8 = 0x05;
    pub const CHUNK_INFO: u8 = 0x06;
    pub const CONNECTION: u8 = 0x07;
}

/// A record header: its fields in file order.
struct Fields(Vec<(String, Vec<u8>)>);

impl Fields {
    /// Parses `len u32, "name=value"` fields.
    fn parse(mut bytes: &[u8]) -> Result<Self, String> {
        let mut fields = Vec::new();
        while !bytes.is_empty() {
            let (len, rest) = split_u32(bytes).ok_or("a header field length is cut short")?;
            let field = rest.get(..len as usize).ok_or("a header field runs past its header")?;
            let eq = field.iter().position(|&b| b == b'=').ok_or("a header field has no '='")?;
            fields.push((String::from_utf8_lossy(&field[..eq]).into_owned(), field[eq + 1..].to_vec()));
            bytes = &rest[len as usize..];
        }
        Ok(Fields(fields))
    }

    fn get(&self, name: &str) -> Option<&[u8]> {
        self.0.iter().find(|(n, _)| n == name).map(|(_, v)| v.as_slice())
    }

    fn op(&self) -> Option<u8> {
        self.get("op").and_then(|v| v.first().copied())
    }

    fn u32(&self, name: &str) -> Option<u32> {
        Some(u32::from_le_bytes(self.get(name)?.try_into().ok()?))
    }

    fn u64(&self, name: &str) -> Option<u64> {
        Some(u64::from_le_bytes(self.get(name)?.try_into().ok()?))
    }

    /// A `time` field (secs u32, nsecs u32) in seconds.
    fn time(&self, name: &str) -> Option<f64> {
        let v = self.get(name)?;
        let secs = u32::from_le_bytes(v.get(..4)?.try_into().ok()?);
        let nsecs = u32::from_le_bytes(v.get(4..8)?.try_into().ok()?);
        Some(f64::from(secs) + f64::from(nsecs) * 1e-9)
    }

    fn string(&self, name: &str) -> Option<String> {
        Some(String::from_utf8_lossy(self.get(name)?).into_owned())
    }
}

/// A little-endian u32 and the bytes after it.
fn split_u32(bytes: &[u8]) -> Option<(u32, &[u8])> {
    let (head, rest) = bytes.split_first_chunk::<4>()?;
    Some((u32::from_le_bytes(*head), rest))
}

/// One record read from the file.
struct Record {
    /// File offset of the record's first byte.
    offset: u64,
    header: Fields,
    /// The data, or the part of it before the end of a truncated file.
    data: Vec<u8>,
    /// Declared data length (larger than `data.len()` when the file ends inside the data).
    declared: u32,
}

impl Record {
    fn complete(&self) -> bool {
        self.data.len() == self.declared as usize
    }
}

/// Damage found while reading records: where and what.
struct Damage {
    offset: u64,
    truncated: bool,
    detail: String,
}

impl Damage {
    fn into_kind(self, scans: usize) -> RecordingErrorKind {
        let Damage { offset, truncated, detail } = self;
        if truncated {
            RecordingErrorKind::Truncated { offset, scans, detail }
        } else {
            RecordingErrorKind::Corrupt { offset, scans, detail }
        }
    }
}

/// What the bag header record says about the rest of the file.
#[derive(Clone, Copy)]
struct BagHeader {
    /// Offset of the index section; 0 while the recorder has not closed the file.
    index_pos: u64,
    /// Chunks in the file, each listed by a chunk info record in the index section.
    chunk_count: u32,
}

/// Sequential record reader over the file.
struct BagFile {
    reader: BufReader<File>,
    len: u64,
    pos: u64,
}

impl BagFile {
    /// Opens `path`, checks the magic and reads the bag header record.
    fn open(path: &Path) -> Result<(Self, BagHeader), RecordingErrorKind> {
        let file = File::open(path).map_err(RecordingErrorKind::Io)?;
        let len = file.metadata().map_err(RecordingErrorKind::Io)?.len();
        let mut bag = BagFile { reader: BufReader::new(file), len, pos: 0 };
        bag.check_magic()?;
        let header = match bag.next_record(|_| false) {
            Ok(Some(record)) if record.header.op() == Some(op::BAG_HEADER) => record.header,
            Ok(_) => {
                return Err(corrupt_at(MAGIC.len() as u64, "the first record is not a bag header"));
            }
            Err(damage) => return Err(damage.into_kind(0)),
        };
        let missing = |field| corrupt_at(MAGIC.len() as u64, &format!("the bag header lacks {field}"));
        let index_pos = header.u64("index_pos").ok_or_else(|| missing("index_pos"))?;
        let chunk_count = header.u32("chunk_count").ok_or_else(|| missing("chunk_count"))?;
        Ok((bag, BagHeader { index_pos, chunk_count }))
    }

    fn check_magic(&mut self) -> Result<(), RecordingErrorKind> {
        let mut magic = [0; MAGIC.len()];
        let got = read_up_to(&mut self.reader, &mut magic).map_err(RecordingErrorKind::Io)?;
        self.pos = got as u64;
        if magic.starts_with(b"#ROSBAG V") && got == MAGIC.len() && magic != MAGIC {
            let version = String::from_utf8_lossy(&magic[9..]).trim().to_owned();
            return Err(RecordingErrorKind::BagVersion(version));
        }
        if got < MAGIC.len() && MAGIC.starts_with(&magic[..got]) {
            let detail = "the file ends inside the magic line".to_owned();
            return Err(RecordingErrorKind::Truncated { offset: got as u64, scans: 0, detail });
        }
        if magic != MAGIC {
            return Err(corrupt_at(0, "no \"#ROSBAG V2.0\" magic line: not a ROS 1 bag"));
        }
        Ok(())
    }

    fn seek(&mut self, pos: u64) -> Result<(), RecordingErrorKind> {
        self.reader.seek(SeekFrom::Start(pos)).map_err(RecordingErrorKind::Io)?;
        self.pos = pos;
        Ok(())
    }

    /// The next record, `None` at the end of the file. Data is read only for the ops `keep`
    /// selects (others are skipped, their data left empty); a file ending inside kept data yields
    /// the record with the data present.
    fn next_record(&mut self, keep: impl Fn(u8) -> bool) -> Result<Option<Record>, Damage> {
        let offset = self.pos;
        if offset >= self.len {
            return Ok(None);
        }
        let header_len = self.length(offset, "record header length")?;
        let header_bytes = self.bytes(offset, header_len, "record header")?;
        let header = Fields::parse(&header_bytes).map_err(|detail| corrupt(offset, detail))?;
        let declared = self.length(offset, "record data length")?;
        let op = header.op().ok_or_else(|| corrupt(offset, "record header has no op field".into()))?;
        let available = declared.min(self.remaining());
        let data = if keep(op) {
            self.bytes(offset, available, "record data")?
        } else {
            self.skip(offset, available)?;
            Vec::new()
        };
        let record = Record { offset, header, data, declared: if keep(op) { declared } else { 0 } };
        if !keep(op) && available < declared {
            return Err(truncated(offset, self.len, format!("record data of {declared} bytes")));
        }
        Ok(Some(record))
    }

    fn remaining(&self) -> u32 {
        u32::try_from(self.len.saturating_sub(self.pos)).unwrap_or(u32::MAX)
    }

    /// A u32 length field of the record at `offset`.
    fn length(&mut self, offset: u64, what: &str) -> Result<u32, Damage> {
        let bytes = self.bytes(offset, 4, what)?;
        Ok(u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]))
    }

    /// `n` bytes of the record at `offset`; damage if the file ends first.
    fn bytes(&mut self, offset: u64, n: u32, what: &str) -> Result<Vec<u8>, Damage> {
        if n > self.remaining() {
            return Err(truncated(offset, self.len, format!("{what} of {n} bytes")));
        }
        let mut buf = vec![0; n as usize];
        self.reader.read_exact(&mut buf).map_err(|e| corrupt(offset, format!("cannot read {what}: {e}")))?;
        self.pos += u64::from(n);
        Ok(buf)
    }

    fn skip(&mut self, offset: u64, n: u32) -> Result<(), Damage> {
        self.reader.seek_relative(i64::from(n)).map_err(|e| corrupt(offset, format!("cannot seek: {e}")))?;
        self.pos += u64::from(n);
        Ok(())
    }
}

/// `read` until `buf` is full or the file ends; the number of bytes read.
fn read_up_to(reader: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match reader.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

fn corrupt(offset: u64, detail: String) -> Damage {
    Damage { offset, truncated: false, detail }
}

fn corrupt_at(offset: u64, detail: &str) -> RecordingErrorKind {
    RecordingErrorKind::Corrupt { offset, scans: 0, detail: detail.to_owned() }
}

fn truncated(record: u64, len: u64, what: String) -> Damage {
    Damage {
        offset: len,
        truncated: true,
        detail: format!("the file ends inside the {what} of the record at byte {record}"),
    }
}

/// The records inside a chunk, as far as they could be recovered, and what stopped the recovery.
struct ChunkContents {
    bytes: Vec<u8>,
    damage: Option<Damage>,
}

/// Decompresses the chunk `record`; a truncated or corrupt chunk yields what decodes before the damage.
fn decompress_chunk(record: &Record, file_len: u64) -> ChunkContents {
    let offset = record.offset;
    let size = record.header.u32("size").unwrap_or(0);
    let compression = record.header.string("compression").unwrap_or_default();
    let mut bytes = Vec::with_capacity((size as usize).min(64 << 20));
    let result = match compression.as_str() {
        "none" => {
            bytes.extend_from_slice(&record.data);
            Ok(())
        }
        "bz2" => {
            bzip2::read::BzDecoder::new(record.data.as_slice()).take(u64::from(size)).read_to_end(&mut bytes).map(drop)
        }
        "lz4" => lz4_flex::frame::FrameDecoder::new(record.data.as_slice())
            .take(u64::from(size))
            .read_to_end(&mut bytes)
            .map(drop),
        other => {
            let detail = format!("chunk compression {other:?} is not supported (none, bz2, lz4)");
            return ChunkContents { bytes, damage: Some(corrupt(offset, detail)) };
        }
    };
    let damage = if !record.complete() {
        let what = format!("chunk data of {} bytes ({} present)", record.declared, record.data.len());
        Some(truncated(offset, file_len, what))
    } else if let Err(e) = result {
        Some(corrupt(offset, format!("chunk ({compression}) does not decompress: {e}")))
    } else if bytes.len() != size as usize {
        Some(corrupt(offset, format!("chunk decompresses to {} bytes, its header says {size}", bytes.len())))
    } else {
        None
    };
    ChunkContents { bytes, damage }
}

/// One record inside a chunk's decompressed bytes.
struct InnerRecord<'a> {
    header: Fields,
    data: &'a [u8],
}

/// The complete records of a chunk, in order; stops at the first that overruns the bytes.
fn inner_records(bytes: &[u8]) -> (Vec<InnerRecord<'_>>, Option<String>) {
    let mut records = Vec::new();
    let mut rest = bytes;
    while !rest.is_empty() {
        let at = bytes.len() - rest.len();
        let Some(parsed) = split_record(rest) else {
            return (records, Some(format!("the record at byte {at} of the chunk overruns it")));
        };
        let (header, data, after) = parsed;
        match Fields::parse(header) {
            Ok(header) => records.push(InnerRecord { header, data }),
            Err(e) => {
                return (records, Some(format!("the record at byte {at} of the chunk: {e}")));
            }
        }
        rest = after;
    }
    (records, None)
}

/// `(header, data, rest)` of the record at the start of `bytes`.
fn split_record(bytes: &[u8]) -> Option<(&[u8], &[u8], &[u8])> {
    let (header_len, rest) = split_u32(bytes)?;
    let (header, rest) = rest.split_at_checked(header_len as usize)?;
    let (data_len, rest) = split_u32(rest)?;
    let (data, rest) = rest.split_at_checked(data_len as usize)?;
    Some((header, data, rest))
}

/// Messages of one topic, streamed from the front of a bag.
pub(super) struct BagSource {
    file: BagFile,
    header: BagHeader,
    /// Chunk info records seen (the index section lists one per chunk).
    chunk_infos: u32,
    topic: String,
    /// Connection id -> whether it publishes `topic`.
    connections: HashMap<u32, bool>,
    pending: VecDeque<RawMessage>,
    /// The error to report once `pending` is drained.
    deferred: Option<RecordingErrorKind>,
    /// Messages on the topic found so far (the next message's index).
    found: usize,
    done: bool,
}

impl BagSource {
    /// Opens `path` to stream the messages of `topic`.
    pub(super) fn open(path: &Path, topic: &str) -> Result<Self, RecordingErrorKind> {
        let (file, header) = BagFile::open(path)?;
        Ok(BagSource {
            file,
            header,
            chunk_infos: 0,
            topic: topic.to_owned(),
            connections: HashMap::new(),
            pending: VecDeque::new(),
            deferred: None,
            found: 0,
            done: false,
        })
    }

    /// The next message on the topic, then any damage found, then `None`.
    pub(super) fn next_message(&mut self) -> Option<Result<RawMessage, RecordingErrorKind>> {
        loop {
            if let Some(message) = self.pending.pop_front() {
                return Some(Ok(message));
            }
            if let Some(error) = self.deferred.take() {
                self.done = true;
                return Some(Err(error));
            }
            if self.done {
                return None;
            }
            self.advance();
        }
    }

    /// Reads one record, queueing its messages or noting the damage or the end.
    fn advance(&mut self) {
        let keep = |op| matches!(op, op::CHUNK | op::CONNECTION | op::MESSAGE_DATA | op::CHUNK_INFO);
        match self.file.next_record(keep) {
            Ok(Some(record)) => self.take_record(record),
            Ok(None) => self.finish(),
            Err(damage) => self.deferred = Some(damage.into_kind(self.found)),
        }
    }

    fn take_record(&mut self, record: Record) {
        match record.header.op() {
            Some(op::CHUNK) => self.take_chunk(&record),
            Some(op::CONNECTION) => self.take_connection(&record.header),
            Some(op::MESSAGE_DATA) if record.complete() => {
                self.take_message(&record.header, &record.data, record.offset)
            }
            Some(op::CHUNK_INFO) => self.chunk_infos += 1,
            _ => {}
        }
        if !record.complete() && self.deferred.is_none() {
            let what = format!("data of {} bytes", record.declared);
            self.deferred = Some(truncated(record.offset, self.file.len, what).into_kind(self.found));
        }
    }

    fn take_chunk(&mut self, record: &Record) {
        let contents = decompress_chunk(record, self.file.len);
        let (records, problem) = inner_records(&contents.bytes);
        for inner in records {
            match inner.header.op() {
                Some(op::CONNECTION) => self.take_connection(&inner.header),
                Some(op::MESSAGE_DATA) => self.take_message(&inner.header, inner.data, record.offset),
                _ => {}
            }
        }
        // Damage to the chunk explains a cut inner record, so it is the one to report.
        let damage = contents.damage.or_else(|| problem.map(|p| corrupt(record.offset, p)));
        self.deferred = damage.map(|d| d.into_kind(self.found));
    }

    fn take_connection(&mut self, header: &Fields) {
        if let Some(id) = header.u32("conn") {
            let on_topic = header.string("topic").is_some_and(|t| t == self.topic);
            self.connections.insert(id, on_topic);
        }
    }

    /// Queues a message of our topic; `offset` is the record or chunk holding it.
    fn take_message(&mut self, header: &Fields, data: &[u8], offset: u64) {
        let on_topic = header.u32("conn").and_then(|id| self.connections.get(&id)).copied().unwrap_or(false);
        if !on_topic {
            return;
        }
        self.pending.push_back(RawMessage {
            index: self.found,
            offset: Some(offset),
            receive_time: header.time("time").unwrap_or(0.0),
            data: data.to_vec(),
            format: WireFormat::Ros1,
        });
        self.found += 1;
    }

    /// At the end of the file: a bag without its whole index was cut short.
    fn finish(&mut self) {
        self.done = true;
        let (len, BagHeader { index_pos, chunk_count }) = (self.file.len, self.header);
        let detail = match missing_index(index_pos, len) {
            Some(detail) => detail,
            None if self.chunk_infos < chunk_count => {
                format!("the index lists {} of the {chunk_count} chunks", self.chunk_infos)
            }
            None => return,
        };
        self.deferred = Some(RecordingErrorKind::Truncated { offset: len, scans: self.found, detail });
    }
}

/// Why a bag whose records end cleanly at `len` still lacks its index, if it does.
fn missing_index(index_pos: u64, len: u64) -> Option<String> {
    if index_pos == 0 {
        Some("the bag header has no index position (index_pos 0): the recorder never closed the file".to_owned())
    } else if index_pos >= len {
        Some(format!("the bag header puts the index at byte {index_pos}, past the end"))
    } else {
        None
    }
}

/// Topics of the bag at `path`: from the index section, or by reading every chunk if the index is
/// missing or damaged (then the topics before the damage, and the damage).
pub(super) fn list_topics(path: &Path) -> Result<Listing, RecordingErrorKind> {
    let (mut file, BagHeader { index_pos, .. }) = BagFile::open(path)?;
    let after_header = file.pos;
    if index_pos > after_header && index_pos < file.len {
        file.seek(index_pos)?;
        if let (topics, None) = connections_from(&mut file, false) {
            return Ok(Listing { topics, damage: None });
        }
        file.seek(after_header)?;
    }
    let (topics, damage) = connections_from(&mut file, true);
    let damage = damage.map(|d| d.into_kind(0)).or_else(|| {
        let detail = missing_index(index_pos, file.len)?;
        Some(RecordingErrorKind::Truncated { offset: file.len, scans: 0, detail })
    });
    Ok(Listing { topics, damage })
}

/// The connections of the records from the current position on, looking inside chunks if
/// `chunks`, up to the end or the first damage.
fn connections_from(file: &mut BagFile, chunks: bool) -> (Vec<TopicInfo>, Option<Damage>) {
    let mut topics = Vec::new();
    let keep = |op| op == op::CONNECTION || (chunks && op == op::CHUNK);
    loop {
        let record = match file.next_record(keep) {
            Ok(Some(record)) => record,
            Ok(None) => return (topics, None),
            Err(damage) => return (topics, Some(damage)),
        };
        match record.header.op() {
            Some(op::CONNECTION) => add_topic(&mut topics, &record.header, &record.data),
            Some(op::CHUNK) => {
                let contents = decompress_chunk(&record, file.len);
                for inner in inner_records(&contents.bytes).0 {
                    if inner.header.op() == Some(op::CONNECTION) {
                        add_topic(&mut topics, &inner.header, inner.data);
                    }
                }
                if contents.damage.is_some() {
                    return (topics, contents.damage);
                }
            }
            _ => {}
        }
        if !record.complete() {
            let what = format!("data of {} bytes", record.declared);
            return (topics, Some(truncated(record.offset, file.len, what)));
        }
    }
}

/// Adds the topic of a connection record (type from its data, a connection header) once.
fn add_topic(topics: &mut Vec<TopicInfo>, header: &Fields, data: &[u8]) {
    let Some(topic) = header.string("topic") else {
        return;
    };
    let message_type = Fields::parse(data).ok().and_then(|f| f.string("type")).unwrap_or_default();
    let info = TopicInfo { topic, message_type };
    if !topics.contains(&info) {
        topics.push(info);
    }
}
