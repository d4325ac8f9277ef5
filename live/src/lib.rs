//! What people look at: the live view (the Foxglove WebSocket protocol, served by the Foxglove SDK)
//! and recordings (MCAP files, written by the same SDK), shared by the station, the edge and the demo.
//!
//! A [`Live`] owns one Foxglove context and its sinks: a WebSocket server ([`Live::serve`]) and/or
//! an MCAP recording ([`Live::record`]). Callers publish through the topic helpers of [`view`]
//! (the same topic names for every program, see [`topics`]), built from the conversions of
//! [`convert`].
//!
//! Off the hot path: a message is built only when some sink takes it. Topics that describe a state
//! (the map, the frames, trajectories, statuses) are *latched* while a server runs: their newest
//! message is kept and sent to every client that subscribes later, so a viewer opened after the
//! merge sees the map at once. Streams (keyframes) are built only while someone subscribes or
//! records.

pub mod convert;
mod latch;
pub mod topics;
pub mod view;

use std::collections::HashMap;
use std::io::{Seek, Write};
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard};

use foxglove::websocket::ShutdownHandle;
use foxglove::{Context, Encode, McapWriterHandle, PartialMetadata, RawChannel, WebSocketServerHandle};

use latch::Latch;

/// What a recording can be written to: a file, or memory in tests.
pub trait RecordTarget: Write + Seek + Send + 'static {}
impl<T: Write + Seek + Send + 'static> RecordTarget for T {}

/// Why a sink could not start or finish.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    /// The WebSocket server could not listen on the address (busy port, address not on this host).
    #[error("cannot serve the Foxglove live view on {addr}")]
    Serve {
        /// The address asked for.
        addr: SocketAddr,
        /// What the SDK said.
        source: foxglove::FoxgloveError,
    },
    /// The MCAP recording could not be started or finished.
    #[error("the MCAP recording failed")]
    Record(#[source] foxglove::FoxgloveError),
    /// The recording's last bytes could not be written.
    #[error("cannot write the end of the MCAP recording")]
    Flush(#[source] std::io::Error),
    /// The recording's file could not be created.
    #[error("cannot create the recording {}", path.display())]
    Create {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        source: std::io::Error,
    },
}

/// When a message was made: its timestamp and MCAP log time.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum Stamp {
    /// The wall clock at publication (live systems).
    #[default]
    Now,
    /// Seconds since the Unix epoch (replayed sensor time).
    Seconds(f64),
}

impl Stamp {
    fn timestamp(self) -> foxglove::messages::Timestamp {
        match self {
            Stamp::Now => foxglove::messages::Timestamp::now(),
            Stamp::Seconds(s) => foxglove::messages::Timestamp::saturating_from_epoch_secs_f64(s),
        }
    }

    fn metadata(self) -> PartialMetadata {
        match self {
            Stamp::Now => PartialMetadata::default(),
            Stamp::Seconds(_) => PartialMetadata::with_log_time(self.timestamp()),
        }
    }
}

/// Whether a topic's newest message is kept for clients that subscribe later.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// A state: the newest message replaces the earlier ones (map, frames, trajectory, status).
    Latched,
    /// A stream: each message is an event of its own (keyframes, scans).
    Stream,
}

type Recording = McapWriterHandle<Box<dyn RecordTarget>>;

/// Which sinks a program attaches (its `--foxglove` and `--record` options).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Sinks {
    /// Serve the live view on this address (default none).
    pub foxglove: Option<SocketAddr>,
    /// Record to this MCAP file (default none).
    pub record: Option<std::path::PathBuf>,
}

impl Sinks {
    /// Whether no sink is asked for.
    pub fn is_empty(&self) -> bool {
        self.foxglove.is_none() && self.record.is_none()
    }
}

/// The live view's context and sinks. Publishing with no sink attached builds nothing.
pub struct Live {
    context: Arc<Context>,
    channels: Mutex<HashMap<String, Arc<RawChannel>>>,
    latch: Arc<Latch>,
    server: Mutex<Option<WebSocketServerHandle>>,
    /// Where the server listens.
    address: Mutex<Option<SocketAddr>>,
    recording: Mutex<Option<Recording>>,
}

impl Default for Live {
    fn default() -> Self {
        Self::new()
    }
}

impl Live {
    /// A context with no sink yet.
    pub fn new() -> Self {
        Live {
            context: Context::new(),
            channels: Mutex::default(),
            latch: Arc::default(),
            server: Mutex::default(),
            address: Mutex::default(),
            recording: Mutex::default(),
        }
    }

    /// A live view with the `sinks` asked for, or `None` when none is (callers then build no
    /// view at all). Needs a tokio runtime when a server is asked for.
    pub async fn open(sinks: &Sinks, name: &str) -> Result<Option<Arc<Live>>, LiveError> {
        if sinks.is_empty() {
            return Ok(None);
        }
        let live = Live::new();
        if let Some(addr) = sinks.foxglove {
            live.serve(addr, name).await?;
        }
        if let Some(path) = &sinks.record {
            live.record_file(path)?;
        }
        Ok(Some(Arc::new(live)))
    }

    /// The address the server listens on, if one runs.
    pub fn address(&self) -> Option<SocketAddr> {
        *lock(&self.address)
    }

    /// [`Live::close`], then waits until the server's clients are let go.
    pub async fn finish(&self) -> Result<(), LiveError> {
        if let Some(shutdown) = self.close()? {
            shutdown.wait().await;
        }
        Ok(())
    }

    /// Starts the WebSocket server on `addr` (port 0: a free port) and returns the address it
    /// listens on. Needs a tokio runtime.
    pub async fn serve(&self, addr: SocketAddr, name: &str) -> Result<SocketAddr, LiveError> {
        let handle = foxglove::WebSocketServer::new()
            .context(&self.context)
            .name(name)
            .bind(addr.ip().to_string(), addr.port())
            .listener(Arc::clone(&self.latch) as Arc<dyn foxglove::websocket::ServerListener>)
            .start()
            .await
            .map_err(|source| LiveError::Serve { addr, source })?;
        let bound = SocketAddr::new(addr.ip(), handle.port());
        self.latch.enable();
        *lock(&self.server) = Some(handle);
        *lock(&self.address) = Some(bound);
        Ok(bound)
    }

    /// Records every topic to `target` as MCAP (zstd chunks) until [`Live::close`].
    pub fn record(&self, target: impl RecordTarget) -> Result<(), LiveError> {
        let target: Box<dyn RecordTarget> = Box::new(target);
        let handle = self.context.mcap_writer().create(target).map_err(LiveError::Record)?;
        *lock(&self.recording) = Some(handle);
        Ok(())
    }

    /// Records to a new file at `path` (created, or truncated), as [`Live::record`].
    pub fn record_file(&self, path: &std::path::Path) -> Result<(), LiveError> {
        let create = |source| LiveError::Create { path: path.to_owned(), source };
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(create)?;
        }
        let file = std::fs::File::create(path).map_err(create)?;
        self.record(std::io::BufWriter::new(file))
    }

    /// Whether any sink is attached (a server, even with no client, or a recording).
    pub fn is_active(&self) -> bool {
        lock(&self.server).is_some() || lock(&self.recording).is_some()
    }

    /// Finishes the recording (index and summary written, target flushed) and stops the server;
    /// returns the server's shutdown to wait for, if one ran.
    pub fn close(&self) -> Result<Option<ShutdownHandle>, LiveError> {
        let shutdown = lock(&self.server).take().map(WebSocketServerHandle::stop);
        if let Some(recording) = lock(&self.recording).take() {
            let mut target = recording.close().map_err(LiveError::Record)?;
            target.flush().map_err(LiveError::Flush)?;
        }
        Ok(shutdown)
    }

    /// Publishes the message `make` builds on `topic`, if anyone takes it: a subscriber or a
    /// recording, or (latched topics) a server whose later subscribers will get it.
    pub fn publish<T: Encode>(&self, topic: &str, kind: Kind, stamp: Stamp, make: impl FnOnce() -> T) {
        let channel = self.channel(topic, T::get_message_encoding, T::get_schema);
        self.emit(&channel, kind, stamp, || {
            let msg = make();
            let mut bytes = Vec::with_capacity(msg.encoded_len().unwrap_or(64));
            msg.encode(&mut bytes).map(|()| bytes).map_err(|e| e.to_string())
        });
    }

    /// Publishes a JSON message (no schema) on `topic`, as [`Live::publish`].
    pub fn publish_json(&self, topic: &str, kind: Kind, stamp: Stamp, make: impl FnOnce() -> serde_json::Value) {
        let channel = self.channel(topic, || "json".to_owned(), || None);
        self.emit(&channel, kind, stamp, || serde_json::to_vec(&make()).map_err(|e| e.to_string()));
    }

    /// The channel of `topic`, made on first use.
    fn channel(
        &self,
        topic: &str,
        encoding: impl FnOnce() -> String,
        schema: impl FnOnce() -> Option<foxglove::Schema>,
    ) -> Arc<RawChannel> {
        let mut channels = lock(&self.channels);
        if let Some(channel) = channels.get(topic) {
            return Arc::clone(channel);
        }
        let built = self.context.channel_builder(topic).message_encoding(encoding()).schema(schema()).build_raw();
        // The encoding is always set, the only thing build_raw checks.
        let channel = built.expect("message encoding is set");
        channels.insert(topic.to_owned(), Arc::clone(&channel));
        channel
    }

    fn emit(
        &self,
        channel: &Arc<RawChannel>,
        kind: Kind,
        stamp: Stamp,
        bytes: impl FnOnce() -> Result<Vec<u8>, String>,
    ) {
        let latch = kind == Kind::Latched && self.latch.enabled();
        if !channel.has_sinks() && !latch {
            return;
        }
        let bytes = match bytes() {
            Ok(b) => b,
            Err(e) => return tracing::warn!("cannot encode a message on {}: {e}", channel.topic()),
        };
        if channel.has_sinks() {
            channel.log_with_meta(&bytes, stamp.metadata());
        }
        if latch {
            self.latch.keep(channel, bytes);
        }
    }
}

impl Drop for Live {
    fn drop(&mut self) {
        if let Err(e) = self.close() {
            tracing::error!("{e}");
        }
    }
}

/// Locks a mutex; a panic elsewhere while holding it leaves data that is still usable here.
fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl std::fmt::Debug for Live {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Live")
            .field("server", &lock(&self.server).is_some())
            .field("recording", &lock(&self.recording).is_some())
            .finish_non_exhaustive()
    }
}
