//! Packets sent as UDP datagrams to a local address, as the sensor would send them to its host.
//!
//! Only loopback targets are accepted: the simulator must not spray LiDAR traffic on a real
//! network, where a robot's odometry could take it for its sensor's. The socket is bound to the
//! loopback address of the target's family, never to every interface.
//!
//! Pacing: in [`Pace::Realtime`], each packet leaves at its send time relative to the first packet
//! sent, measured from the instant that one left; the sleeps target those due times, so the pace
//! does not drift with the time spent encoding or sending. A packet already late leaves at once.

use std::net::{Ipv4Addr, Ipv6Addr, SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use super::Packet;

/// How fast packets are sent.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Pace {
    /// At the sensor's pace: each packet at its send time after the first.
    #[default]
    Realtime,
    /// As fast as the socket takes them (a receiver's buffer may overflow and drop some).
    Max,
}

/// Why packets cannot be sent; names the target.
#[derive(Debug, thiserror::Error)]
pub enum SendError {
    /// The target is not a loopback address.
    #[error("refusing to send LiDAR packets to {target}: only loopback addresses (127.0.0.0/8, ::1) are allowed")]
    NotLoopback {
        /// The address asked for.
        target: SocketAddr,
    },
    /// The socket cannot be opened or the datagram not sent.
    #[error("sending LiDAR packets to {target}: {source}")]
    Io {
        /// The target.
        target: SocketAddr,
        /// Why.
        source: std::io::Error,
    },
}

/// Sends packets to one loopback address.
#[derive(Debug)]
pub struct UdpSender {
    socket: UdpSocket,
    target: SocketAddr,
    pace: Pace,
    /// When the first packet left, and its send time on the sensor's clock.
    origin: Option<(Instant, u64)>,
    sent: usize,
}

impl UdpSender {
    /// A sender to `target`, which must be a loopback address.
    pub fn new(target: SocketAddr, pace: Pace) -> Result<UdpSender, SendError> {
        if !target.ip().is_loopback() {
            return Err(SendError::NotLoopback { target });
        }
        let local: SocketAddr = match target {
            SocketAddr::V4(_) => (Ipv4Addr::LOCALHOST, 0).into(),
            SocketAddr::V6(_) => (Ipv6Addr::LOCALHOST, 0).into(),
        };
        let socket = UdpSocket::bind(local).map_err(|source| SendError::Io { target, source })?;
        Ok(UdpSender { socket, target, pace, origin: None, sent: 0 })
    }

    /// The target address.
    pub fn target(&self) -> SocketAddr {
        self.target
    }

    /// Datagrams sent so far.
    pub fn sent(&self) -> usize {
        self.sent
    }

    /// Sends one packet, waiting for its due time first in [`Pace::Realtime`].
    pub fn send(&mut self, packet: &Packet) -> Result<(), SendError> {
        if self.pace == Pace::Realtime {
            self.wait_for(packet.sent_ns);
        }
        let target = self.target;
        self.socket.send_to(&packet.payload, target).map_err(|source| SendError::Io { target, source })?;
        self.sent += 1;
        Ok(())
    }

    /// Sends packets in order.
    pub fn send_all(&mut self, packets: &[Packet]) -> Result<(), SendError> {
        packets.iter().try_for_each(|p| self.send(p))
    }

    /// Sleeps until the packet sent at `sent_ns` is due; the first packet sets the origin.
    fn wait_for(&mut self, sent_ns: u64) {
        let &mut (start, first_ns) = self.origin.get_or_insert_with(|| (Instant::now(), sent_ns));
        let due = start + Duration::from_nanos(sent_ns.saturating_sub(first_ns));
        let now = Instant::now();
        if due > now {
            std::thread::sleep(due - now);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn other_addresses_are_refused() {
        for target in ["192.168.1.100:2368", "0.0.0.0:2368", "[2001:db8::1]:7502"] {
            let target: SocketAddr = target.parse().unwrap();
            assert!(matches!(UdpSender::new(target, Pace::Max), Err(SendError::NotLoopback { .. })), "{target}");
        }
    }
}
