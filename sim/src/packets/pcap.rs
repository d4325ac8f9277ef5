//! Packets as a classic pcap capture, as `tcpdump -w` on the sensor's network would record them.
//!
//! Each packet becomes an Ethernet II frame carrying an IPv4 datagram from the sensor
//! (192.168.1.201 by default) to the host (192.168.1.100) with a UDP datagram to the packet's port,
//! sent from the same port. A datagram larger than the link's MTU (every Ouster packet at 1500
//! bytes) is split into IPv4 fragments, as the sensor's IP stack does; all of a datagram's
//! fragments carry its send time. Nothing goes on a network: the addresses are only written.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::net::Ipv4Addr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use etherparse::{EtherType, Ethernet2Header, IpFragOffset, IpNumber, Ipv4Header, UdpHeader};
use pcap_file::pcap::{PcapHeader, PcapPacket, PcapWriter};
use pcap_file::{DataLink, Endianness};

use super::Packet;

/// Bytes of an IPv4 header without options.
const IPV4_HEADER_BYTES: usize = Ipv4Header::MIN_LEN;
/// Fragment offsets count 8-byte units.
const FRAGMENT_UNIT: usize = 8;
/// The largest frame a capture keeps whole.
const SNAPLEN: u32 = 65_535;
/// A hop limit as a sensor on the local network sends it.
const TIME_TO_LIVE: u8 = 64;

/// The network a capture is recorded on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Network {
    /// The sensor's address.
    pub sensor: Ipv4Addr,
    /// The host's address, where the packets go.
    pub host: Ipv4Addr,
    /// The sensor's MAC address (locally administered: not a vendor's).
    pub sensor_mac: [u8; 6],
    /// The host's MAC address.
    pub host_mac: [u8; 6],
    /// Largest IPv4 datagram on the link, bytes; larger ones are fragmented.
    pub mtu: usize,
}

impl Default for Network {
    fn default() -> Self {
        Network {
            sensor: Ipv4Addr::new(192, 168, 1, 201),
            host: Ipv4Addr::new(192, 168, 1, 100),
            sensor_mac: [0x02, 0x00, 0x00, 0x00, 0x00, 0x01],
            host_mac: [0x02, 0x00, 0x00, 0x00, 0x00, 0x02],
            mtu: 1500,
        }
    }
}

/// Why a capture cannot be written; names the file when there is one.
#[derive(Debug, thiserror::Error)]
pub enum CaptureWriteError {
    /// The file cannot be created or written.
    #[error("{}: cannot write the capture: {source}", path.display())]
    Io {
        /// The capture.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// The pcap container refused a frame or its header.
    #[error("{}: cannot write the capture: {detail}", path.display())]
    Pcap {
        /// The capture.
        path: PathBuf,
        /// What the writer said.
        detail: String,
    },
    /// A payload too large for one UDP datagram.
    #[error("a {len}-byte payload does not fit a UDP datagram")]
    TooLarge {
        /// Its bytes.
        len: usize,
    },
    /// An MTU too small to carry a fragment.
    #[error("an MTU of {mtu} bytes cannot carry IPv4 fragments")]
    Mtu {
        /// The MTU asked for.
        mtu: usize,
    },
}

/// Writes packets into a pcap capture, frame by frame.
pub struct CaptureWriter<W: Write> {
    writer: PcapWriter<W>,
    network: Network,
    /// Names the capture in errors.
    path: PathBuf,
    /// The IPv4 identification of the next datagram.
    identification: u16,
    frames: usize,
}

impl<W: Write> std::fmt::Debug for CaptureWriter<W> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CaptureWriter").field("path", &self.path).field("frames", &self.frames).finish_non_exhaustive()
    }
}

impl CaptureWriter<BufWriter<File>> {
    /// Creates (or truncates) the capture file `path`.
    pub fn create(path: &Path, network: Network) -> Result<Self, CaptureWriteError> {
        let file = File::create(path).map_err(|source| CaptureWriteError::Io { path: path.to_owned(), source })?;
        CaptureWriter::new(BufWriter::new(file), path, network)
    }
}

impl<W: Write> CaptureWriter<W> {
    /// A capture written to `writer`; `name` names it in errors.
    pub fn new(writer: W, name: &Path, network: Network) -> Result<Self, CaptureWriteError> {
        if network.mtu < IPV4_HEADER_BYTES + FRAGMENT_UNIT {
            return Err(CaptureWriteError::Mtu { mtu: network.mtu });
        }
        // Little-endian microsecond records: what tcpdump writes on the usual hosts.
        let header = PcapHeader {
            snaplen: SNAPLEN,
            datalink: DataLink::ETHERNET,
            endianness: Endianness::Little,
            ..PcapHeader::default()
        };
        let writer = PcapWriter::with_header(writer, header)
            .map_err(|e| CaptureWriteError::Pcap { path: name.to_owned(), detail: e.to_string() })?;
        Ok(CaptureWriter { writer, network, path: name.to_owned(), identification: 0, frames: 0 })
    }

    /// Appends one packet (one or more frames), stamped with its send time.
    pub fn write(&mut self, packet: &Packet) -> Result<(), CaptureWriteError> {
        let frames = frames_of(packet, &self.network, self.identification)?;
        self.identification = self.identification.wrapping_add(1);
        let timestamp = Duration::from_nanos(packet.sent_ns);
        for frame in &frames {
            let record = PcapPacket::new(timestamp, frame.len() as u32, frame);
            self.writer
                .write_packet(&record)
                .map_err(|e| CaptureWriteError::Pcap { path: self.path.clone(), detail: e.to_string() })?;
        }
        self.frames += frames.len();
        Ok(())
    }

    /// Appends packets in order.
    pub fn write_all(&mut self, packets: &[Packet]) -> Result<(), CaptureWriteError> {
        packets.iter().try_for_each(|p| self.write(p))
    }

    /// Frames written so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Flushes the capture and gives back the writer.
    pub fn finish(self) -> Result<W, CaptureWriteError> {
        let mut writer = self.writer.into_writer();
        writer.flush().map_err(|source| CaptureWriteError::Io { path: self.path, source })?;
        Ok(writer)
    }
}

/// The Ethernet frames that carry one packet: a UDP datagram from the sensor to the host, split into
/// IPv4 fragments where it exceeds the MTU. `identification` ties the fragments together.
pub fn frames_of(packet: &Packet, network: &Network, identification: u16) -> Result<Vec<Vec<u8>>, CaptureWriteError> {
    let datagram = udp_datagram(packet, network)?;
    // Every fragment but the last carries a multiple of 8 bytes.
    let per_fragment = (network.mtu.saturating_sub(IPV4_HEADER_BYTES)) / FRAGMENT_UNIT * FRAGMENT_UNIT;
    if per_fragment == 0 {
        return Err(CaptureWriteError::Mtu { mtu: network.mtu });
    }
    let count = datagram.len().div_ceil(per_fragment);
    let ethernet =
        Ethernet2Header { source: network.sensor_mac, destination: network.host_mac, ether_type: EtherType::IPV4 }
            .to_bytes();
    datagram
        .chunks(per_fragment)
        .enumerate()
        .map(|(i, chunk)| {
            let fragment = Fragment { offset: i * per_fragment, more: i + 1 < count, identification };
            let ip = ipv4_header(network, chunk.len(), fragment)?;
            let mut frame = Vec::with_capacity(ethernet.len() + IPV4_HEADER_BYTES + chunk.len());
            frame.extend_from_slice(&ethernet);
            frame.extend_from_slice(&ip.to_bytes());
            frame.extend_from_slice(chunk);
            Ok(frame)
        })
        .collect()
}

/// The UDP header and payload: the IPv4 payload before fragmentation.
fn udp_datagram(packet: &Packet, network: &Network) -> Result<Vec<u8>, CaptureWriteError> {
    let too_large = |_| CaptureWriteError::TooLarge { len: packet.payload.len() };
    let whole_len = u16::try_from(UdpHeader::LEN + packet.payload.len()).map_err(too_large)?;
    let pseudo =
        Ipv4Header::new(whole_len, TIME_TO_LIVE, IpNumber::UDP, network.sensor.octets(), network.host.octets())
            .map_err(|_| CaptureWriteError::TooLarge { len: packet.payload.len() })?;
    // The sensor sends from its data port to the same port on the host.
    let udp = UdpHeader::with_ipv4_checksum(packet.port, packet.port, &pseudo, &packet.payload)
        .map_err(|_| CaptureWriteError::TooLarge { len: packet.payload.len() })?;
    let mut datagram = Vec::with_capacity(UdpHeader::LEN + packet.payload.len());
    datagram.extend_from_slice(&udp.to_bytes());
    datagram.extend_from_slice(&packet.payload);
    Ok(datagram)
}

/// Where a fragment lies in its datagram.
#[derive(Clone, Copy)]
struct Fragment {
    /// Bytes from the datagram's start.
    offset: usize,
    /// More fragments follow.
    more: bool,
    identification: u16,
}

fn ipv4_header(network: &Network, payload_len: usize, fragment: Fragment) -> Result<Ipv4Header, CaptureWriteError> {
    let too_large = || CaptureWriteError::TooLarge { len: payload_len };
    let len = u16::try_from(payload_len).map_err(|_| too_large())?;
    let mut header = Ipv4Header::new(len, TIME_TO_LIVE, IpNumber::UDP, network.sensor.octets(), network.host.octets())
        .map_err(|_| too_large())?;
    let units = u16::try_from(fragment.offset / FRAGMENT_UNIT).map_err(|_| too_large())?;
    header.fragment_offset = IpFragOffset::try_new(units).map_err(|_| too_large())?;
    header.more_fragments = fragment.more;
    header.dont_fragment = false;
    header.identification = fragment.identification;
    header.header_checksum = header.calc_header_checksum();
    Ok(header)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn packet(len: usize) -> Packet {
        Packet { payload: (0..len).map(|i| i as u8).collect(), sent_ns: 1_000_000_123_456, port: 7502 }
    }

    #[test]
    fn a_small_packet_is_one_frame() {
        let frames = frames_of(&packet(1206), &Network::default(), 7).unwrap();
        assert_eq!(frames.len(), 1);
        assert_eq!(frames[0].len(), 14 + 20 + 8 + 1206);
        // IPv4, no fragment offset, no more fragments.
        assert_eq!(&frames[0][12..14], &[0x08, 0x00]);
        assert_eq!(&frames[0][20..22], &[0x00, 0x00]);
    }

    #[test]
    fn a_large_packet_is_fragmented_in_8_byte_units() {
        let frames = frames_of(&packet(12_608), &Network::default(), 7).unwrap();
        // 12 616 bytes of UDP datagram in fragments of 1480.
        assert_eq!(frames.len(), 9);
        let ip_payload: usize = frames.iter().map(|f| f.len() - 14 - 20).sum();
        assert_eq!(ip_payload, 12_616);
        for (i, frame) in frames.iter().enumerate() {
            let flags_offset = u16::from_be_bytes([frame[20], frame[21]]);
            assert_eq!(usize::from(flags_offset & 0x1FFF) * 8, i * 1480);
            assert_eq!(flags_offset & 0x2000 != 0, i < 8, "more fragments flag of fragment {i}");
            assert!(frame.len() <= 14 + 1500);
        }
    }
}
