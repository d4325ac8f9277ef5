//! Helpers the multi-host system test (`tests/tests/hosts.rs`) runs inside its network namespaces:
//!
//! - `hosts-tool relay LISTEN TARGET DELAY_MS`: a TCP relay that holds every chunk it reads
//!   `DELAY_MS` milliseconds before writing it on, in each direction. It stands in for netem's
//!   `delay`, which this machine's kernel lacks (`CONFIG_NET_SCH_NETEM` is off). Each direction
//!   holds at most [`QUEUE_CHUNKS`] chunks of [`CHUNK_BYTES`] (128 KiB: at 200 ms, up to 640 kB/s,
//!   more than the lossy link behind it carries), so a slow far side slows the near one down
//!   instead of queueing seconds of data here that a real link would not hold.
//! - `hosts-tool keyframes ZENOH_CONFIG FLEET ROBOT`: asks the robot's keyframe store for everything
//!   it holds and prints one line per keyframe: its sequence number, the bytes of its message and
//!   the points of its cloud.
//! - `hosts-tool observe ZENOH_CONFIG FLEET OUT`: a zenoh session that keeps the station's newest
//!   global map (its protobuf bytes) in the file `OUT`, replaced atomically: from every map the
//!   station publishes and from a query every half second (after a restart of the station or of
//!   the router the subscription alone may miss the one that matters). A map of a lower revision
//!   than one already written is not written (a query's answer may arrive after a newer push).

use std::io::{Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use prost::Message;
use proto::{Fleet, GlobalMap, Keyframe, KeyframeRequest, keyexpr};

/// Chunks in flight per direction of a relayed connection.
const QUEUE_CHUNKS: usize = 8;
/// Largest chunk read at once.
const CHUNK_BYTES: usize = 16 * 1024;

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result = match args.iter().map(String::as_str).collect::<Vec<_>>().as_slice() {
        ["relay", listen, target, delay_ms] => relay(listen, target, delay_ms),
        ["observe", config, fleet, out] => observe(Path::new(config), fleet, Path::new(out)),
        ["keyframes", config, fleet, robot] => keyframes(Path::new(config), fleet, robot),
        _ => Err("usage: hosts-tool relay LISTEN TARGET DELAY_MS | observe ZENOH_CONFIG FLEET OUT \
                  | keyframes ZENOH_CONFIG FLEET ROBOT"
            .into()),
    };
    if let Err(e) = result {
        eprintln!("hosts-tool: {e}");
        std::process::exit(1);
    }
}

type Failure = Box<dyn std::error::Error>;

/// `HH:MM:SS.mmm` UTC, the clock of the other processes' log lines.
fn now() -> String {
    let t = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
    let (s, ms) = (t.as_secs() % 86_400, t.subsec_millis());
    format!("{:02}:{:02}:{:02}.{ms:03}", s / 3600, s / 60 % 60, s % 60)
}

fn relay(listen: &str, target: &str, delay_ms: &str) -> Result<(), Failure> {
    let listen: SocketAddr = listen.parse()?;
    let target: SocketAddr = target.parse()?;
    let delay = Duration::from_millis(delay_ms.parse()?);
    let listener = TcpListener::bind(listen)?;
    eprintln!("{} relaying {listen} -> {target}, {delay:?} each way", now());
    for near in listener.incoming() {
        let near = near?;
        match TcpStream::connect_timeout(&target, Duration::from_secs(5)) {
            Ok(far) => {
                eprintln!("{} connection from {:?} relayed to {target}", now(), near.peer_addr());
                connect_both(near, far, delay)?;
            }
            // The far side is down (a router restarting): the near side sees its connection closed
            // and retries, as it would had it dialled the far side itself.
            Err(e) => eprintln!("{} cannot reach {target}: {e}", now()),
        }
    }
    Ok(())
}

/// Relays both directions, each on two threads (a reader stamping chunks, a writer waiting them out).
fn connect_both(near: TcpStream, far: TcpStream, delay: Duration) -> std::io::Result<()> {
    near.set_nodelay(true)?;
    far.set_nodelay(true)?;
    for (from, to) in [(near.try_clone()?, far.try_clone()?), (far, near)] {
        let (tx, rx) = mpsc::sync_channel::<(Instant, Vec<u8>)>(QUEUE_CHUNKS);
        let reader = from.try_clone()?;
        std::thread::spawn(move || read_chunks(reader, tx, delay));
        std::thread::spawn(move || write_chunks(to, from, rx));
    }
    Ok(())
}

/// Reads chunks and queues each with the time it is due, until end of stream or an error (dropping
/// `tx` then ends the writer once it has drained the queue).
fn read_chunks(mut from: TcpStream, tx: mpsc::SyncSender<(Instant, Vec<u8>)>, delay: Duration) {
    let mut buf = vec![0u8; CHUNK_BYTES];
    loop {
        match from.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => {
                if tx.send((Instant::now() + delay, buf[..n].to_vec())).is_err() {
                    break;
                }
            }
        }
    }
}

/// Writes each chunk when it is due; when the queue ends or a write fails, closes both sockets of
/// the connection (the other direction's reader then ends too).
fn write_chunks(mut to: TcpStream, from: TcpStream, rx: mpsc::Receiver<(Instant, Vec<u8>)>) {
    for (due, chunk) in rx {
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
        if to.write_all(&chunk).is_err() {
            break;
        }
    }
    if to.shutdown(Shutdown::Both).is_ok() {
        eprintln!("{} connection {:?} -> {:?} closed", now(), from.peer_addr(), to.peer_addr());
    }
    let _ = from.shutdown(Shutdown::Both);
}

fn observe(config: &Path, fleet: &str, out: &Path) -> Result<(), Failure> {
    let fleet = Fleet::new(fleet)?;
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
    runtime.block_on(async {
        let session = bus::Network::File(config.to_owned()).open().await?;
        let subscriber = session.declare_subscriber(keyexpr::global_map(&fleet)).await.map_err(|e| e.to_string())?;
        let mut tick = tokio::time::interval(Duration::from_millis(500));
        let mut written = Written { path: out.to_owned(), revision: None };
        loop {
            tokio::select! {
                sample = subscriber.recv_async() => {
                    let Ok(sample) = sample else { break };
                    written.offer(&sample.payload().to_bytes());
                }
                _ = tick.tick() => {
                    let fetched = station::service::client::fetch_global_map(&session, &fleet, Duration::from_secs(1));
                    if let Ok((_, bytes)) = fetched.await {
                        written.offer(&bytes);
                    }
                }
            }
        }
        Ok(())
    })
}

fn keyframes(config: &Path, fleet: &str, robot: &str) -> Result<(), Failure> {
    let fleet = Fleet::new(fleet)?;
    let robot: u32 = robot.parse()?;
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build()?;
    runtime.block_on(async {
        let session = bus::Network::File(config.to_owned()).open().await?;
        let request = KeyframeRequest { seqs: vec![], from_seq: Some(0), limit: None, session: None }.encode_to_vec();
        let replies = session
            .get(keyexpr::keyframe_store(&fleet, robot))
            .payload(request)
            .consolidation(zenoh::query::ConsolidationMode::None)
            .timeout(Duration::from_secs(10))
            .await
            .map_err(|e| e.to_string())?;
        while let Ok(reply) = replies.recv_async().await {
            let sample = reply.result().map_err(|e| format!("{:?}", e.payload().to_bytes()))?;
            let bytes = sample.payload().to_bytes();
            let kf = Keyframe::decode(bytes.as_ref())?;
            println!("{} {} {}", kf.seq, bytes.len(), kf.cloud.map_or(0, |c| c.points));
        }
        Ok(())
    })
}

/// The map file and the revision it holds.
struct Written {
    path: PathBuf,
    revision: Option<u64>,
}

impl Written {
    /// Writes `bytes` (a `GlobalMap`) unless it is malformed or older than what the file holds.
    fn offer(&mut self, bytes: &[u8]) {
        let Ok(map) = GlobalMap::decode(bytes) else {
            return eprintln!("a malformed global map ({} bytes)", bytes.len());
        };
        if self.revision.is_some_and(|r| map.revision < r) {
            return;
        }
        let partial = self.path.with_extension("partial");
        match std::fs::write(&partial, bytes).and_then(|()| std::fs::rename(&partial, &self.path)) {
            Ok(()) => self.revision = Some(map.revision),
            Err(e) => eprintln!("cannot write {}: {e}", self.path.display()),
        }
    }
}
