//! MCAP files (ROS 2, Foxglove): the container through the `mcap` crate, streamed from a file.
//!
//! Messages are read in file order by `mcap::io::MessageReader`, which pulls bytes as it needs
//! them and decompresses chunks incrementally, so memory stays at about one chunk and a file cut
//! inside a chunk still yields the chunk's complete messages before the error. Channels with
//! message encoding `cdr` (ROS 2) and `ros1` are decoded.

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, Read, Seek};
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use mcap::McapError;
use mcap::records::{Record, op};
use mcap::sans_io::{LinearReadEvent, LinearReader, SummaryReadEvent, SummaryReader, SummaryReaderOptions};

use super::pointcloud2::WireFormat;
use super::{Listing, RawMessage, RecordingErrorKind, TopicInfo};

/// A reader that counts the bytes it has handed out, so damage can be located. The count is
/// shared with the reader's owner (atomic only so that a recording can move between threads).
struct Counting<R> {
    inner: R,
    count: Arc<AtomicU64>,
}

impl<R: Read> Read for Counting<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.count.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }
}

/// Messages of one topic, streamed from an MCAP file.
pub(super) struct McapSource {
    reader: mcap::io::MessageReader<Counting<BufReader<File>>>,
    read: Arc<AtomicU64>,
    topic: String,
    /// Messages on the topic found so far (the next message's index).
    found: usize,
    done: bool,
}

impl McapSource {
    /// Opens `path` to stream the messages of `topic`.
    pub(super) fn open(path: &Path, topic: &str) -> Result<Self, RecordingErrorKind> {
        let file = File::open(path).map_err(RecordingErrorKind::Io)?;
        let read = Arc::new(AtomicU64::new(0));
        let counting = Counting { inner: BufReader::new(file), count: Arc::clone(&read) };
        let reader = mcap::io::MessageReader::new(counting);
        Ok(McapSource { reader, read, topic: topic.to_owned(), found: 0, done: false })
    }

    /// The next message on the topic, then any damage found, then `None`.
    pub(super) fn next_message(&mut self) -> Option<Result<RawMessage, RecordingErrorKind>> {
        if self.done {
            return None;
        }
        let result = self.next_on_topic();
        if !matches!(result, Some(Ok(_))) {
            self.done = true;
        }
        result
    }

    fn next_on_topic(&mut self) -> Option<Result<RawMessage, RecordingErrorKind>> {
        for item in self.reader.by_ref() {
            let message = match item {
                Ok(message) => message,
                Err(e) => {
                    return Some(Err(damage(e, self.read.load(Ordering::Relaxed), self.found)));
                }
            };
            if message.channel.topic != self.topic {
                continue;
            }
            let format = match wire_format(&message.channel.message_encoding) {
                Some(format) => format,
                None => return Some(Err(unsupported_encoding(&message.channel))),
            };
            let index = self.found;
            self.found += 1;
            return Some(Ok(RawMessage {
                index,
                offset: None,
                receive_time: message.log_time as f64 * 1e-9,
                data: message.data.into_owned(),
                format,
            }));
        }
        None
    }
}

/// The wire format for an MCAP message encoding.
fn wire_format(encoding: &str) -> Option<WireFormat> {
    match encoding {
        "cdr" => Some(WireFormat::Cdr),
        "ros1" => Some(WireFormat::Ros1),
        _ => None,
    }
}

fn unsupported_encoding(channel: &mcap::Channel<'_>) -> RecordingErrorKind {
    RecordingErrorKind::Encoding { topic: channel.topic.clone(), encoding: channel.message_encoding.clone() }
}

/// An MCAP error as truncation (the file ends inside a record) or corruption, with the number of
/// bytes read when it was found.
fn damage(error: McapError, read: u64, scans: usize) -> RecordingErrorKind {
    match error {
        McapError::UnexpectedEof => RecordingErrorKind::Truncated {
            offset: read,
            scans,
            detail: "the file ends inside a record (or lacks its footer)".to_owned(),
        },
        McapError::Io(e) if e.kind() != std::io::ErrorKind::UnexpectedEof => RecordingErrorKind::Io(e),
        other => RecordingErrorKind::Corrupt { offset: read, scans, detail: mcap_error_text(&other) },
    }
}

/// The error's message with its source, which for a parse failure says which field.
fn mcap_error_text(error: &McapError) -> String {
    match std::error::Error::source(error) {
        Some(source) => format!("{error}: {source}"),
        None => error.to_string(),
    }
}

/// Topics of the MCAP file at `path`: from the summary section, or by reading the file from the
/// front when the summary is missing or names no channel (then the topics before any damage, and
/// the damage).
pub(super) fn list_topics(path: &Path) -> Result<Listing, RecordingErrorKind> {
    let summary = read_summary(path).ok().flatten().filter(|s| !s.channels.is_empty());
    let Some(summary) = summary else {
        return scan_channels(path);
    };
    let mut channels: Vec<_> = summary.channels.values().collect();
    channels.sort_by_key(|c| c.id);
    let topics = channels.into_iter().map(|c| topic_info(&c.topic, c.schema.as_ref().map(|s| s.name.as_str())));
    Ok(Listing { topics: topics.collect(), damage: None })
}

fn topic_info(topic: &str, schema: Option<&str>) -> TopicInfo {
    TopicInfo { topic: topic.to_owned(), message_type: schema.unwrap_or("(no schema)").to_owned() }
}

/// The summary section, `None` when the file has none.
fn read_summary(path: &Path) -> Result<Option<mcap::Summary>, McapError> {
    let mut file = File::open(path)?;
    let size = file.metadata()?.len();
    let mut reader = SummaryReader::new_with_options(SummaryReaderOptions::default().with_file_size(size));
    while let Some(event) = reader.next_event() {
        match event? {
            SummaryReadEvent::ReadRequest(need) => {
                let n = file.read(reader.insert(need))?;
                reader.notify_read(n);
            }
            SummaryReadEvent::SeekRequest(to) => reader.notify_seeked(file.seek(to)?),
        }
    }
    Ok(reader.finish())
}

/// Channels found by reading every record from the front, up to the first damage.
fn scan_channels(path: &Path) -> Result<Listing, RecordingErrorKind> {
    let mut file =
        Counting { inner: BufReader::new(File::open(path).map_err(RecordingErrorKind::Io)?), count: Arc::default() };
    let mut reader = LinearReader::new();
    let mut schemas: HashMap<u16, String> = HashMap::new();
    let mut topics = Vec::new();
    while let Some(event) = reader.next_event() {
        let event = match event {
            Ok(event) => event,
            Err(e) => {
                return Ok(Listing { topics, damage: Some(damage(e, file.count.load(Ordering::Relaxed), 0)) });
            }
        };
        match event {
            LinearReadEvent::ReadRequest(need) => {
                let n = file.read(reader.insert(need)).map_err(RecordingErrorKind::Io)?;
                reader.notify_read(n);
            }
            LinearReadEvent::Record { opcode, data } if opcode == op::SCHEMA || opcode == op::CHANNEL => {
                match mcap::parse_record(opcode, data) {
                    Ok(Record::Schema { header, .. }) => {
                        schemas.insert(header.id, header.name);
                    }
                    Ok(Record::Channel(c)) => {
                        let info = topic_info(&c.topic, schemas.get(&c.schema_id).map(String::as_str));
                        if !topics.contains(&info) {
                            topics.push(info);
                        }
                    }
                    Ok(_) => {}
                    Err(e) => {
                        return Ok(Listing { topics, damage: Some(damage(e, file.count.load(Ordering::Relaxed), 0)) });
                    }
                }
            }
            LinearReadEvent::Record { .. } => {}
        }
    }
    Ok(Listing { topics, damage: None })
}
