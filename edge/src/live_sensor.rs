//! A live LiDAR: its UDP packets received on a thread of their own and decoded into scans.
//!
//! The receiving thread never waits on whoever takes the scans: a sensor sends whether or not the
//! odometry keeps up, and a socket buffer that fills drops packets from the middle of rotations.
//! So the thread decodes each packet as it comes and hands on whole rotations through a short
//! queue; when the queue is full, the rotation is dropped whole and counted, never cut.

use std::net::{SocketAddr, UdpSocket};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, TrySendError, sync_channel};
use std::thread::JoinHandle;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use crate::packets::{Assembler, Return, Rotation};
use crate::recording::PacketDecoder;

/// Rotations decoded and not yet taken: enough to ride out one slow scan of the odometry, few
/// enough that what is taken is recent.
const QUEUE: usize = 2;

/// The largest UDP payload (an Ouster OS-128 dual-return packet is about 33 kB).
const MAX_DATAGRAM: usize = 65_535;

/// How often the receiving thread looks whether it should stop.
const POLL: Duration = Duration::from_millis(200);

/// A rotation as the receiving thread hands it on.
#[derive(Debug)]
pub struct LiveRotation {
    /// The decoded rotation.
    pub rotation: Rotation,
    /// Whole rotations dropped since the previous one handed on, because it was not taken in time.
    pub dropped_before: usize,
}

/// What the receiving thread has counted so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LiveCounts {
    /// Datagrams received.
    pub datagrams: usize,
    /// Datagrams of the sensor's port that did not decode.
    pub undecoded: usize,
    /// Rotations decoded.
    pub rotations: usize,
    /// Rotations dropped because the queue was full.
    pub dropped: usize,
}

#[derive(Default)]
struct Counters {
    datagrams: AtomicUsize,
    undecoded: AtomicUsize,
    rotations: AtomicUsize,
    dropped: AtomicUsize,
}

/// A sensor streaming to a local address; scans are taken with [`LiveSensor::next_rotation`].
pub struct LiveSensor {
    address: SocketAddr,
    rotations: Receiver<LiveRotation>,
    /// Returns of rotations the caller is done with, back to the receiving thread.
    give_back: SyncSender<Vec<Return>>,
    counters: Arc<Counters>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for LiveSensor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveSensor").field("address", &self.address).finish_non_exhaustive()
    }
}

impl LiveSensor {
    /// Binds `address` (the local address the sensor sends to) and starts receiving: every
    /// datagram the socket gives was sent to its port, so there is no other port to tell apart.
    pub fn start(address: SocketAddr, assembler: Box<dyn Assembler + Send>) -> std::io::Result<LiveSensor> {
        let socket = UdpSocket::bind(address)?;
        socket.set_read_timeout(Some(POLL))?;
        let address = socket.local_addr()?;
        let (sender, rotations) = sync_channel(QUEUE);
        let (give_back, given_back) = sync_channel(1);
        let counters = Arc::new(Counters::default());
        let stop = Arc::new(AtomicBool::new(false));
        let receiver = Receiving {
            socket,
            decoder: PacketDecoder::new(assembler, None),
            port: address.port(),
            sender,
            given_back,
            counters: counters.clone(),
            stop: stop.clone(),
            dropped_since: 0,
        };
        let thread = std::thread::Builder::new().name("lidar-udp".into()).spawn(move || receiver.run())?;
        Ok(LiveSensor { address, rotations, give_back, counters, stop, thread: Some(thread) })
    }

    /// The bound address (with the port the system chose, if 0 was asked for).
    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// The next rotation, waiting up to `timeout`; `Err(Timeout)` when none came.
    pub fn next_rotation(&self, timeout: Duration) -> Result<LiveRotation, RecvTimeoutError> {
        self.rotations.recv_timeout(timeout)
    }

    /// Gives a rotation's returns back to the receiving thread, which writes the next rotation
    /// into them ([`Assembler::recycle`]); dropped if it still holds one.
    pub fn recycle(&self, returns: Vec<Return>) {
        let _ = self.give_back.try_send(returns);
    }

    /// What the receiving thread counted so far.
    pub fn counts(&self) -> LiveCounts {
        let c = &self.counters;
        LiveCounts {
            datagrams: c.datagrams.load(Ordering::Relaxed),
            undecoded: c.undecoded.load(Ordering::Relaxed),
            rotations: c.rotations.load(Ordering::Relaxed),
            dropped: c.dropped.load(Ordering::Relaxed),
        }
    }
}

impl Drop for LiveSensor {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// The receiving thread's state.
struct Receiving {
    socket: UdpSocket,
    decoder: PacketDecoder,
    /// The bound port: every datagram the socket gives was sent to it.
    port: u16,
    sender: SyncSender<LiveRotation>,
    given_back: Receiver<Vec<Return>>,
    counters: Arc<Counters>,
    stop: Arc<AtomicBool>,
    dropped_since: usize,
}

impl Receiving {
    fn run(mut self) {
        let mut buffer = vec![0u8; MAX_DATAGRAM];
        while !self.stop.load(Ordering::Relaxed) {
            let len = match self.socket.recv(&mut buffer) {
                Ok(len) => len,
                Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => continue,
                Err(e) => {
                    tracing::warn!("receiving LiDAR packets: {e}");
                    continue;
                }
            };
            self.counters.datagrams.fetch_add(1, Ordering::Relaxed);
            if let Ok(returns) = self.given_back.try_recv() {
                self.decoder.recycle(returns);
            }
            let rotation = self.decoder.push(self.port, &buffer[..len], now());
            self.counters.undecoded.store(self.decoder.undecoded, Ordering::Relaxed);
            if let Some(rotation) = rotation
                && !self.hand_on(rotation)
            {
                return;
            }
        }
    }

    /// Queues a rotation, or drops it when the queue is full; false once nobody takes them.
    fn hand_on(&mut self, rotation: Rotation) -> bool {
        self.counters.rotations.fetch_add(1, Ordering::Relaxed);
        match self.sender.try_send(LiveRotation { rotation, dropped_before: self.dropped_since }) {
            Ok(()) => {
                self.dropped_since = 0;
                true
            }
            Err(TrySendError::Full(dropped)) => {
                self.decoder.recycle(dropped.rotation.returns);
                self.dropped_since += 1;
                self.counters.dropped.fetch_add(1, Ordering::Relaxed);
                true
            }
            Err(TrySendError::Disconnected(_)) => false,
        }
    }
}

/// Host time, seconds since the Unix epoch.
fn now() -> f64 {
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or_default()
}
