//! UDP datagrams out of a packet capture (pcap or pcapng), as a LiDAR sent them.
//!
//! Frames are Ethernet (with VLAN tags), Linux cooked (SLL) or raw IP; IPv4 and IPv6 datagrams
//! split into fragments, which a capture at the usual 1500-byte MTU holds for every Ouster packet,
//! are put back together. What is not UDP (ARP, TCP, ICMP) is passed over and counted, and so is a
//! frame the capture cut short (its snap length), since a part of a LiDAR packet decodes to
//! nothing sensible.

use std::fs::File;
use std::io::BufReader;
use std::net::IpAddr;
use std::path::Path;

use etherparse::defrag::IpDefragPool;
use etherparse::{NetSlice, SlicedPacket, TransportSlice, UdpSlice};
use pcap_file::DataLink;
use pcap_file::pcap::PcapReader;
use pcap_file::pcapng::blocks::interface_description::InterfaceDescriptionOption;
use pcap_file::pcapng::{Block, PcapNgReader};

/// One UDP datagram of the capture.
#[derive(Clone, Debug, PartialEq)]
pub struct Datagram {
    /// When the capture saw it (its last fragment), seconds since the Unix epoch.
    pub received: f64,
    /// The sender's address.
    pub source: IpAddr,
    /// The port it was sent to.
    pub destination_port: u16,
    /// The UDP payload.
    pub payload: Vec<u8>,
}

/// What the capture held besides the datagrams delivered.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CaptureCounts {
    /// Frames read.
    pub frames: usize,
    /// Frames that carry no UDP (other protocols, link types not decoded).
    pub not_udp: usize,
    /// Frames cut short by the capture's snap length, or whose headers do not parse.
    pub damaged: usize,
}

/// Why a capture cannot be read on.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    /// The file cannot be opened or read.
    #[error("cannot read: {0}")]
    Io(#[from] std::io::Error),
    /// Neither a pcap nor a pcapng file (its first bytes say).
    #[error("not a pcap or pcapng capture (magic number {magic:#010x})")]
    Format {
        /// The first four bytes, little-endian.
        magic: u32,
    },
    /// The container is damaged or cut; the datagrams before were delivered.
    #[error("damaged after {frames} frames: {detail}")]
    Damaged {
        /// Frames read before the damage.
        frames: usize,
        /// What the reader found.
        detail: String,
    },
}

/// An open capture: [`Capture::next_datagram`] until `None`.
pub struct Capture {
    reader: Reader,
    /// Fragments waiting for the rest of their datagram, by when they arrived.
    defrag: IpDefragPool<f64, ()>,
    counts: CaptureCounts,
    done: bool,
}

/// Seconds after which the fragments of a datagram whose other fragments never came are dropped:
/// a sensor sends a packet's fragments back to back, well within a millisecond.
const FRAGMENT_TIMEOUT_S: f64 = 1.0;

enum Reader {
    Pcap { reader: PcapReader<BufReader<File>>, link: DataLink },
    PcapNg { reader: PcapNgReader<BufReader<File>> },
}

/// A frame of the capture: its link type, arrival time and bytes.
struct Frame {
    link: DataLink,
    received: f64,
    data: Vec<u8>,
    cut: bool,
}

impl std::fmt::Debug for Capture {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Capture").field("counts", &self.counts).finish_non_exhaustive()
    }
}

/// The first four bytes of a pcapng file (its section header block type).
const PCAPNG_MAGIC: u32 = 0x0A0D_0D0A;
/// The first four bytes of a pcap file, read little-endian: micro- or nanosecond stamps, either
/// byte order.
const PCAP_MAGICS: [u32; 4] = [0xA1B2_C3D4, 0xD4C3_B2A1, 0xA1B2_3C4D, 0x4D3C_B2A1];

/// The first four bytes of a file, little-endian.
fn magic_of(path: &Path) -> std::io::Result<u32> {
    let mut head = [0u8; 4];
    std::io::Read::read_exact(&mut File::open(path)?, &mut head)?;
    Ok(u32::from_le_bytes(head))
}

/// Whether `path` starts as a pcap or pcapng file does.
pub fn is_capture(path: &Path) -> bool {
    magic_of(path).is_ok_and(|m| m == PCAPNG_MAGIC || PCAP_MAGICS.contains(&m))
}

impl Capture {
    /// Opens a pcap or pcapng file, told apart by its magic number.
    pub fn open(path: &Path) -> Result<Capture, CaptureError> {
        let magic = magic_of(path)?;
        let file = BufReader::new(File::open(path)?);
        let damaged = |e: pcap_file::PcapError| CaptureError::Damaged { frames: 0, detail: e.to_string() };
        let reader = match magic {
            PCAPNG_MAGIC => Reader::PcapNg { reader: PcapNgReader::new(file).map_err(damaged)? },
            m if PCAP_MAGICS.contains(&m) => {
                let reader = PcapReader::new(file).map_err(damaged)?;
                let link = reader.header().datalink;
                Reader::Pcap { reader, link }
            }
            _ => return Err(CaptureError::Format { magic }),
        };
        Ok(Capture { reader, defrag: IpDefragPool::new(), counts: CaptureCounts::default(), done: false })
    }

    /// What was read so far besides the datagrams.
    pub fn counts(&self) -> CaptureCounts {
        self.counts
    }

    /// The next UDP datagram; `None` at the end, an error (after which `None`) where the file is
    /// damaged.
    pub fn next_datagram(&mut self) -> Option<Result<Datagram, CaptureError>> {
        while !self.done {
            let frame = match self.next_frame() {
                Some(Ok(frame)) => frame,
                Some(Err(e)) => {
                    self.done = true;
                    return Some(Err(e));
                }
                None => {
                    self.done = true;
                    return None;
                }
            };
            self.counts.frames += 1;
            if frame.cut {
                self.counts.damaged += 1;
                continue;
            }
            match self.udp_of(&frame) {
                Ok(Some(datagram)) => return Some(Ok(datagram)),
                Ok(None) => {}
                Err(Skip::NotUdp) => self.counts.not_udp += 1,
                Err(Skip::Damaged) => self.counts.damaged += 1,
            }
        }
        None
    }

    /// The next frame of either container, with its time in seconds.
    fn next_frame(&mut self) -> Option<Result<Frame, CaptureError>> {
        let frames = self.counts.frames;
        let damaged = move |e: pcap_file::PcapError| CaptureError::Damaged { frames, detail: e.to_string() };
        match &mut self.reader {
            Reader::Pcap { reader, link } => {
                let packet = match reader.next_packet()? {
                    Ok(packet) => packet,
                    Err(e) => return Some(Err(damaged(e))),
                };
                let cut = (packet.data.len() as u64) < u64::from(packet.orig_len);
                let received = packet.timestamp.as_secs_f64();
                Some(Ok(Frame { link: *link, received, data: packet.data.into_owned(), cut }))
            }
            Reader::PcapNg { reader } => loop {
                let block = match reader.next_block()? {
                    Ok(block) => block,
                    Err(e) => return Some(Err(damaged(e))),
                };
                let (interface, ticks, original, data) = match block {
                    Block::EnhancedPacket(p) => {
                        (p.interface_id, p.timestamp.as_nanos(), p.original_len, p.data.into_owned())
                    }
                    Block::SimplePacket(p) => (0, 0, p.original_len, p.data.into_owned()),
                    _ => continue,
                };
                let Some(description) = reader.interfaces().get(interface as usize) else {
                    return Some(Err(damaged(pcap_file::PcapError::InvalidField(
                        "packet of an undescribed interface",
                    ))));
                };
                let received = ticks as f64 * tick_seconds(&description.options);
                let cut = (data.len() as u64) < u64::from(original);
                return Some(Ok(Frame { link: description.linktype, received, data, cut }));
            },
        }
    }

    /// The UDP datagram a frame completes, if any.
    fn udp_of(&mut self, frame: &Frame) -> Result<Option<Datagram>, Skip> {
        let sliced = match frame.link {
            DataLink::ETHERNET => SlicedPacket::from_ethernet(&frame.data),
            DataLink::LINUX_SLL => SlicedPacket::from_linux_sll(&frame.data),
            DataLink::RAW | DataLink::IPV4 | DataLink::IPV6 => SlicedPacket::from_ip(&frame.data),
            _ => return Err(Skip::NotUdp),
        }
        .map_err(|_| Skip::Damaged)?;
        let source = match &sliced.net {
            Some(NetSlice::Ipv4(ip)) => IpAddr::V4(ip.header().source_addr()),
            Some(NetSlice::Ipv6(ip)) => IpAddr::V6(ip.header().source_addr()),
            _ => return Err(Skip::NotUdp),
        };
        if let Some(TransportSlice::Udp(udp)) = &sliced.transport {
            return Ok(Some(datagram(frame.received, source, udp)));
        }
        let fragmented = sliced.net.as_ref().and_then(|net| net.ip_payload_ref()).is_some_and(|p| p.fragmented);
        if !fragmented {
            return Err(Skip::NotUdp);
        }
        let now = frame.received;
        self.defrag.retain(|&first| now - first < FRAGMENT_TIMEOUT_S);
        match self.defrag.process_sliced_packet(&sliced, now, ()) {
            Ok(None) => Ok(None),
            Ok(Some(whole)) => {
                let result = match UdpSlice::from_slice(&whole.payload) {
                    Ok(udp) if whole.ip_number == etherparse::IpNumber::UDP => {
                        Ok(Some(datagram(frame.received, source, &udp)))
                    }
                    Ok(_) => Err(Skip::NotUdp),
                    Err(_) => Err(Skip::Damaged),
                };
                self.defrag.return_buf(whole);
                result
            }
            Err(_) => Err(Skip::Damaged),
        }
    }
}

/// Why a frame gives no datagram.
enum Skip {
    NotUdp,
    Damaged,
}

fn datagram(received: f64, source: IpAddr, udp: &UdpSlice) -> Datagram {
    Datagram { received, source, destination_port: udp.destination_port(), payload: udp.payload().to_vec() }
}

/// Seconds per timestamp tick of a pcapng interface: microseconds unless its `if_tsresol` says
/// otherwise (a power of ten, or of two when the high bit is set).
fn tick_seconds(options: &[InterfaceDescriptionOption]) -> f64 {
    let resolution = options.iter().find_map(|o| match o {
        InterfaceDescriptionOption::IfTsResol(r) => Some(*r),
        _ => None,
    });
    match resolution {
        Some(r) if r & 0x80 != 0 => 2f64.powi(-i32::from(r & 0x7F)),
        Some(r) => 10f64.powi(-i32::from(r)),
        None => 1e-6,
    }
}

impl Iterator for Capture {
    type Item = Result<Datagram, CaptureError>;

    fn next(&mut self) -> Option<Self::Item> {
        self.next_datagram()
    }
}
