//! Process plumbing shared by `emr-edge` and `emr-station`: how a Zenoh session is configured and
//! opened, how they log, how they hear that they must stop.
//!
//! Without a configuration file a session is a **peer on loopback**: it listens only on the
//! `tcp/127.0.0.1:PORT` endpoints it is given, connects only to the ones it is given, and never
//! scouts (multicast and gossip off), so nothing leaves the machine. Anything else (a robot talking
//! to a router over the network, client mode) goes through a zenoh JSON5 configuration file
//! (`--zenoh FILE`), as in `deploy/`.

use std::net::{Ipv4Addr, TcpListener};
use std::path::{Path, PathBuf};
use std::time::Duration;

pub mod ros2;

use zenoh::Session;

/// Why a session could not be configured or opened.
#[derive(Debug, thiserror::Error)]
pub enum BusError {
    /// An endpoint given on the command line is not `tcp/127.0.0.1:PORT`.
    #[error(
        "endpoint {endpoint:?} is not tcp/127.0.0.1:PORT; other addresses need a zenoh configuration file (--zenoh)"
    )]
    NotLoopback {
        /// The rejected endpoint.
        endpoint: String,
    },
    /// The zenoh configuration file could not be read or parsed.
    #[error("zenoh configuration {path}: {message}")]
    ConfigFile {
        /// The file.
        path: PathBuf,
        /// What zenoh said.
        message: String,
    },
    /// Zenoh refused a setting.
    #[error("zenoh setting {key}: {message}")]
    Setting {
        /// The configuration key.
        key: &'static str,
        /// What zenoh said.
        message: String,
    },
    /// The session could not be opened (for example, the listen port is taken).
    #[error("cannot open the zenoh session: {0}")]
    Open(String),
}

/// How to reach the rest of the system.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Network {
    /// Peer mode on loopback, with explicit endpoints and no scouting.
    Loopback {
        /// Endpoints to listen on (`tcp/127.0.0.1:PORT`); may be empty for a peer that only connects.
        listen: Vec<String>,
        /// Endpoints of other peers to connect to (`tcp/127.0.0.1:PORT`).
        connect: Vec<String>,
    },
    /// A zenoh JSON5 configuration file, used as it is.
    File(PathBuf),
}

impl Network {
    /// A loopback peer listening on `listen` ports and connecting to `connect` ports of 127.0.0.1.
    pub fn loopback_ports(listen: &[u16], connect: &[u16]) -> Self {
        Network::Loopback {
            listen: listen.iter().map(|p| endpoint(*p)).collect(),
            connect: connect.iter().map(|p| endpoint(*p)).collect(),
        }
    }

    /// The zenoh configuration this stands for.
    pub fn config(&self) -> Result<zenoh::Config, BusError> {
        match self {
            Network::File(path) => zenoh::Config::from_file(path)
                .map_err(|e| BusError::ConfigFile { path: path.clone(), message: e.to_string() }),
            Network::Loopback { listen, connect } => {
                for e in listen.iter().chain(connect) {
                    check_loopback(e)?;
                }
                let mut c = zenoh::Config::default();
                set(&mut c, "mode", r#""peer""#)?;
                set(&mut c, "listen/endpoints", &json_list(listen))?;
                set(&mut c, "connect/endpoints", &json_list(connect))?;
                set(&mut c, "scouting/multicast/enabled", "false")?;
                set(&mut c, "scouting/gossip/enabled", "false")?;
                Ok(c)
            }
        }
    }

    /// Opens a session.
    pub async fn open(&self) -> Result<Session, BusError> {
        let config = self.config()?;
        zenoh::open(config).await.map_err(|e| BusError::Open(e.to_string()))
    }

    /// Opens a session, trying again for as long as it cannot: a robot may boot before its router
    /// is up or reachable, and a zenoh client gives up at its first failed connection. Waits 1 s,
    /// then twice as long each time up to [`JOIN_RETRY_MAX`], each failure logged. Settings that
    /// cannot work (an unreadable file, an endpoint off loopback) fail at once.
    pub async fn open_patiently(&self) -> Result<Session, BusError> {
        let config = self.config()?;
        let mut wait = Duration::from_secs(1);
        loop {
            match zenoh::open(config.clone()).await {
                Ok(session) => return Ok(session),
                Err(e) => tracing::warn!("cannot join {}: {e}; trying again in {} s", describe(self), wait.as_secs()),
            }
            tokio::time::sleep(wait).await;
            wait = (wait * 2).min(JOIN_RETRY_MAX);
        }
    }
}

/// Longest wait between two tries of [`Network::open_patiently`].
pub const JOIN_RETRY_MAX: Duration = Duration::from_secs(10);

/// The station's zenoh port: where it listens and where edges and tools connect by default
/// (zenoh's own default port, so a stock `zenohd` router also sits there).
pub const DEFAULT_PORT: u16 = 7447;

/// `tcp/127.0.0.1:PORT`.
pub fn endpoint(port: u16) -> String {
    format!("tcp/127.0.0.1:{port}")
}

/// A TCP port on 127.0.0.1 that was free a moment ago (tests run in parallel: each picks its own).
pub fn free_port() -> std::io::Result<u16> {
    Ok(TcpListener::bind((Ipv4Addr::LOCALHOST, 0))?.local_addr()?.port())
}

/// Accepts `tcp/127.0.0.1:PORT` only: the command line never opens the system to the network.
fn check_loopback(e: &str) -> Result<(), BusError> {
    let port = e.strip_prefix("tcp/127.0.0.1:").and_then(|p| p.parse::<u16>().ok());
    match port {
        Some(p) if p != 0 => Ok(()),
        _ => Err(BusError::NotLoopback { endpoint: e.to_owned() }),
    }
}

fn json_list(items: &[String]) -> String {
    let quoted: Vec<String> = items.iter().map(|i| format!("{i:?}")).collect();
    format!("[{}]", quoted.join(","))
}

fn set(c: &mut zenoh::Config, key: &'static str, value: &str) -> Result<(), BusError> {
    c.insert_json5(key, value).map_err(|e| BusError::Setting { key, message: e.to_string() })
}

/// The network options both binaries take.
#[derive(Clone, Debug, Default, clap::Args)]
pub struct NetworkArgs {
    /// Zenoh JSON5 configuration file (client mode, a router, other interfaces). Without it the
    /// process is a loopback peer with the --listen / --connect endpoints below and no scouting.
    #[arg(long, value_name = "FILE", conflicts_with_all = ["listen", "connect"])]
    pub zenoh: Option<PathBuf>,
    /// Loopback endpoint to listen on, `tcp/127.0.0.1:PORT` (repeatable).
    #[arg(long, value_name = "ENDPOINT")]
    pub listen: Vec<String>,
    /// Loopback endpoint of a peer to connect to, `tcp/127.0.0.1:PORT` (repeatable).
    #[arg(long, value_name = "ENDPOINT")]
    pub connect: Vec<String>,
}

impl NetworkArgs {
    /// The network these options describe; `default_listen` is used when neither a file nor any
    /// endpoint is given.
    pub fn network(&self, default_listen: &[u16]) -> Network {
        match &self.zenoh {
            Some(path) => Network::File(path.clone()),
            None if self.listen.is_empty() && self.connect.is_empty() => Network::loopback_ports(default_listen, &[]),
            None => Network::Loopback { listen: self.listen.clone(), connect: self.connect.clone() },
        }
    }
}

impl NetworkArgs {
    /// The network of a process that joins a station (an edge, a tool): without options, a peer
    /// connecting to `tcp/127.0.0.1:PORT` and listening on nothing, so that it never competes with
    /// the station for its port.
    pub fn joining(&self, port: u16) -> Network {
        match &self.zenoh {
            Some(path) => Network::File(path.clone()),
            None if self.listen.is_empty() && self.connect.is_empty() => Network::loopback_ports(&[], &[port]),
            None => Network::Loopback { listen: self.listen.clone(), connect: self.connect.clone() },
        }
    }
}

/// Logs to stderr: on a terminal progress and info, headless (a robot's service, a pipe) warnings
/// and errors (a skipped scan must be seen in a service's log too), unless RUST_LOG says otherwise.
pub fn init_logging() {
    use std::io::IsTerminal;
    // zenoh's own info lines (session ids, endpoints, a gossip warning our loopback config causes on
    // purpose) are noise to an operator; RUST_LOG=zenoh=info brings them back.
    // kiddo 6.3 warns "Leaf array should be contiguous. Construction invariant failed" when a
    // tree's leaves come out non-contiguous, a case its construction then handles with a leaf map
    // (its own comment calls the check a temporary self-test); the 32-robot load bench logged it
    // 48 times in a run whose 32 placements all came out within 6 mm of the truth.
    // RUST_LOG=kiddo=warn brings it back.
    let terminal = std::io::stderr().is_terminal();
    let default = if terminal { "info,zenoh=error,kiddo=error" } else { "warn,zenoh=error,kiddo=error" };
    // An empty RUST_LOG (set but blank, as some shells and CI runners leave it) is no setting, not
    // "errors only", which is what the filter would make of it.
    let filter = std::env::var("RUST_LOG").ok().filter(|v| !v.trim().is_empty()).unwrap_or_else(|| default.into());
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::new(filter))
        .with_ansi(terminal)
        .with_writer(std::io::stderr)
        .init();
}

/// Resolves on SIGINT (Ctrl-C) or SIGTERM. The handlers are installed when this is called (inside a
/// tokio runtime), so a signal that comes before the future is first polled still stops cleanly.
pub fn shutdown_signal() -> std::io::Result<impl Future<Output = ()>> {
    use tokio::signal::unix::{SignalKind, signal};
    let mut interrupt = signal(SignalKind::interrupt())?;
    let mut terminate = signal(SignalKind::terminate())?;
    Ok(async move {
        tokio::select! {
            _ = interrupt.recv() => {}
            _ = terminate.recv() => {}
        }
    })
}

/// A payload that is not the protobuf message its key expression promises.
#[derive(Debug, thiserror::Error)]
#[error("malformed {kind} on {key}: {source}")]
pub struct Malformed {
    /// The key expression it arrived on.
    pub key: String,
    /// The message type expected.
    pub kind: &'static str,
    /// What prost said.
    pub source: prost::DecodeError,
}

/// Decodes a sample's payload as `M`, naming the key expression on failure.
pub fn decode<M: prost::Message + Default>(sample: &zenoh::sample::Sample, kind: &'static str) -> Result<M, Malformed> {
    let bytes = sample.payload().to_bytes();
    M::decode(bytes.as_ref()).map_err(|source| Malformed { key: sample.key_expr().to_string(), kind, source })
}

/// Reads a zenoh configuration file's path for error messages.
pub fn describe(network: &Network) -> String {
    match network {
        Network::File(p) => format!("zenoh config {}", Path::new(p).display()),
        Network::Loopback { listen, connect } => {
            format!("loopback peer, listen {listen:?}, connect {connect:?}")
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn command_line_endpoints_must_be_loopback() {
        for bad in
            ["tcp/0.0.0.0:7447", "tcp/192.168.1.2:7447", "udp/127.0.0.1:7447", "tcp/127.0.0.1:0", "tcp/127.0.0.1:x"]
        {
            let n = Network::Loopback { listen: vec![bad.into()], connect: vec![] };
            assert!(matches!(n.config(), Err(BusError::NotLoopback { .. })), "{bad}");
            let n = Network::Loopback { listen: vec![], connect: vec![bad.into()] };
            assert!(matches!(n.config(), Err(BusError::NotLoopback { .. })), "{bad}");
        }
        assert!(Network::loopback_ports(&[7447], &[7448]).config().is_ok());
    }

    #[test]
    fn defaults_listen_for_a_station_and_connect_for_the_others() {
        let none = NetworkArgs::default();
        assert_eq!(none.network(&[7447]), Network::loopback_ports(&[7447], &[]));
        assert_eq!(none.joining(7447), Network::loopback_ports(&[], &[7447]));
        let given = NetworkArgs { connect: vec![endpoint(9000)], ..NetworkArgs::default() };
        assert_eq!(given.joining(7447), Network::loopback_ports(&[], &[9000]));
    }

    #[test]
    fn a_missing_config_file_is_named() {
        let err = Network::File("/nonexistent/zenoh.json5".into()).config().unwrap_err();
        assert!(err.to_string().contains("/nonexistent/zenoh.json5"), "{err}");
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn two_loopback_peers_talk() {
        let port = free_port().unwrap();
        let a = Network::loopback_ports(&[port], &[]).open().await.unwrap();
        let b = Network::loopback_ports(&[], &[port]).open().await.unwrap();
        let sub = a.declare_subscriber("emr/test/bus").await.unwrap();
        let publisher =
            b.declare_publisher("emr/test/bus").congestion_control(zenoh::qos::CongestionControl::Block).await.unwrap();
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(10);
        while !publisher.matching_status().await.unwrap().matching() {
            assert!(std::time::Instant::now() < deadline, "peers never matched");
            tokio::time::sleep(std::time::Duration::from_millis(20)).await;
        }
        publisher.put(vec![1u8, 2, 3]).await.unwrap();
        let got = sub.recv_async().await.unwrap();
        assert_eq!(got.payload().to_bytes().as_ref(), &[1, 2, 3]);
    }
}
