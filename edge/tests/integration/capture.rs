//! Packet captures: the UDP datagrams out of pcap and pcapng files, written here byte by byte from
//! the formats' specifications (not with the reader's own crates), fragments put back together.

use std::net::{IpAddr, Ipv4Addr};
use std::path::Path;

use edge::recording::capture::{Capture, CaptureError, Datagram};

const SENSOR: [u8; 4] = [192, 168, 1, 201];
const HOST: [u8; 4] = [192, 168, 1, 100];

/// An Ethernet II + IPv4 frame around `ip_payload` (no options; the checksum is left 0, which
/// readers do not check and captures with checksum offload commonly hold).
fn ipv4_frame(ip_payload: &[u8], protocol: u8, identification: u16, offset_bytes: usize, more: bool) -> Vec<u8> {
    let mut frame = vec![0u8; 12];
    frame.extend_from_slice(&[0x08, 0x00]);
    let total = 20 + ip_payload.len();
    let flags_offset = (u16::from(more) << 13) | (offset_bytes / 8) as u16;
    frame.extend_from_slice(&[0x45, 0]);
    frame.extend_from_slice(&(total as u16).to_be_bytes());
    frame.extend_from_slice(&identification.to_be_bytes());
    frame.extend_from_slice(&flags_offset.to_be_bytes());
    frame.extend_from_slice(&[64, protocol, 0, 0]);
    frame.extend_from_slice(&SENSOR);
    frame.extend_from_slice(&HOST);
    frame.extend_from_slice(ip_payload);
    frame
}

/// A UDP header and payload.
fn udp(port: u16, payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(&2368u16.to_be_bytes());
    out.extend_from_slice(&port.to_be_bytes());
    out.extend_from_slice(&((8 + payload.len()) as u16).to_be_bytes());
    out.extend_from_slice(&[0, 0]);
    out.extend_from_slice(payload);
    out
}

/// The frames of one UDP datagram, split into IPv4 fragments of at most `mtu_payload` bytes (a
/// multiple of 8) when it does not fit.
fn udp_frames(port: u16, payload: &[u8], identification: u16, mtu_payload: usize) -> Vec<Vec<u8>> {
    let datagram = udp(port, payload);
    let pieces: Vec<&[u8]> = datagram.chunks(mtu_payload).collect();
    let last = pieces.len() - 1;
    pieces
        .iter()
        .enumerate()
        .map(|(i, piece)| ipv4_frame(piece, 17, identification, i * mtu_payload, i < last))
        .collect()
}

/// A classic pcap file (little-endian, microseconds, Ethernet) of `(seconds, frame, original
/// length)` records.
fn pcap(records: &[(f64, Vec<u8>, usize)]) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(&0xA1B2_C3D4u32.to_le_bytes());
    out.extend_from_slice(&2u16.to_le_bytes());
    out.extend_from_slice(&4u16.to_le_bytes());
    for word in [0u32, 0, 65535, 1] {
        out.extend_from_slice(&word.to_le_bytes());
    }
    for (time, frame, original) in records {
        let micros = (time * 1e6).round() as u64;
        for word in [(micros / 1_000_000) as u32, (micros % 1_000_000) as u32, frame.len() as u32, *original as u32] {
            out.extend_from_slice(&word.to_le_bytes());
        }
        out.extend_from_slice(frame);
    }
    out
}

/// A pcapng block: type, length, body padded to 4 bytes, length again.
fn block(kind: u32, body: &[u8]) -> Vec<u8> {
    let padded = body.len().div_ceil(4) * 4;
    let len = (12 + padded) as u32;
    let mut out = Vec::new();
    out.extend_from_slice(&kind.to_le_bytes());
    out.extend_from_slice(&len.to_le_bytes());
    out.extend_from_slice(body);
    out.resize(8 + padded, 0);
    out.extend_from_slice(&len.to_le_bytes());
    out
}

/// A pcapng file with one Ethernet interface stamping in nanoseconds (`if_tsresol` 9).
fn pcapng(records: &[(f64, Vec<u8>)]) -> Vec<u8> {
    let mut section = Vec::new();
    section.extend_from_slice(&0x1A2B_3C4Du32.to_le_bytes());
    section.extend_from_slice(&1u16.to_le_bytes());
    section.extend_from_slice(&0u16.to_le_bytes());
    section.extend_from_slice(&(-1i64).to_le_bytes());
    let mut out = block(0x0A0D_0D0A, &section);
    let mut interface = Vec::new();
    interface.extend_from_slice(&1u16.to_le_bytes());
    interface.extend_from_slice(&0u16.to_le_bytes());
    interface.extend_from_slice(&0u32.to_le_bytes());
    interface.extend_from_slice(&[9, 0, 1, 0, 9, 0, 0, 0]);
    interface.extend_from_slice(&[0, 0, 0, 0]);
    out.extend(block(1, &interface));
    for (time, frame) in records {
        let nanos = (time * 1e9).round() as u64;
        let mut body = Vec::new();
        for word in [0u32, (nanos >> 32) as u32, nanos as u32, frame.len() as u32, frame.len() as u32] {
            body.extend_from_slice(&word.to_le_bytes());
        }
        body.extend_from_slice(frame);
        out.extend(block(6, &body));
    }
    out
}

fn read_all(path: &Path) -> (Vec<Datagram>, Option<CaptureError>, Capture) {
    let mut capture = Capture::open(path).unwrap();
    let mut datagrams = Vec::new();
    let mut error = None;
    while let Some(item) = capture.next_datagram() {
        match item {
            Ok(d) => datagrams.push(d),
            Err(e) => error = Some(e),
        }
    }
    (datagrams, error, capture)
}

fn payload(seed: u8, len: usize) -> Vec<u8> {
    (0..len).map(|i| (i as u8).wrapping_mul(31).wrapping_add(seed)).collect()
}

#[test]
fn a_pcap_gives_its_udp_payloads_with_times_and_ports_and_skips_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("capture.pcap");
    let (a, b) = (payload(1, 1206), payload(2, 512));
    let mut tcp_header = [0u8; 20];
    tcp_header[12] = 5 << 4; // data offset: 5 words, no options
    let tcp = ipv4_frame(&tcp_header, 6, 9, 0, false);
    let mut cut = udp_frames(2368, &payload(3, 1206), 10, 4096).remove(0);
    let original = cut.len();
    cut.truncate(600);
    let whole = |time: f64, frame: Vec<u8>| (time, frame.clone(), frame.len());
    let records = vec![
        whole(1000.25, udp_frames(2368, &a, 1, 4096).remove(0)),
        whole(1000.5, tcp),
        (1000.75, cut, original),
        whole(1001.0, udp_frames(8308, &b, 2, 4096).remove(0)),
    ];
    std::fs::write(&path, pcap(&records)).unwrap();

    let (datagrams, error, capture) = read_all(&path);
    assert!(error.is_none(), "{error:?}");
    assert_eq!(datagrams.len(), 2);
    assert_eq!((datagrams[0].destination_port, &datagrams[0].payload), (2368, &a));
    assert_eq!((datagrams[1].destination_port, &datagrams[1].payload), (8308, &b));
    assert_eq!(datagrams[0].source, IpAddr::V4(Ipv4Addr::from(SENSOR)));
    assert!((datagrams[0].received - 1000.25).abs() < 1e-6 && (datagrams[1].received - 1001.0).abs() < 1e-6);
    let counts = capture.counts();
    assert_eq!((counts.frames, counts.not_udp, counts.damaged), (4, 1, 1));
}

#[test]
fn fragments_are_put_back_together_in_any_order_and_a_lost_one_loses_only_its_datagram() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("fragments.pcap");
    // An Ouster OS-128 packet is about 25 kB: 17 fragments at a 1500-byte MTU.
    let big = payload(7, 24_832);
    let mut frames = udp_frames(7502, &big, 100, 1480);
    assert!(frames.len() > 10);
    frames.swap(2, 5);
    let lost = udp_frames(7502, &payload(8, 24_832), 101, 1480);
    let mut records: Vec<(f64, Vec<u8>, usize)> = Vec::new();
    for (i, f) in lost.iter().enumerate().filter(|(i, _)| *i != 3) {
        records.push((10.0 + i as f64 * 1e-5, f.clone(), f.len()));
    }
    for (i, f) in frames.iter().enumerate() {
        records.push((10.01 + i as f64 * 1e-5, f.clone(), f.len()));
    }
    std::fs::write(&path, pcap(&records)).unwrap();

    let (datagrams, error, _) = read_all(&path);
    assert!(error.is_none(), "{error:?}");
    assert_eq!(datagrams.len(), 1, "only the datagram with all its fragments");
    assert_eq!(datagrams[0].payload, big);
    assert_eq!(datagrams[0].destination_port, 7502);
}

#[test]
fn a_pcapng_with_nanosecond_stamps_reads_the_same_datagrams() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("capture.pcapng");
    let payloads: Vec<Vec<u8>> = (0..5).map(|i| payload(i, 1206)).collect();
    let records: Vec<(f64, Vec<u8>)> = payloads
        .iter()
        .enumerate()
        .map(|(i, p)| (1_700_000_000.0 + i as f64 * 0.001_327, udp_frames(2368, p, i as u16, 4096).remove(0)))
        .collect();
    std::fs::write(&path, pcapng(&records)).unwrap();

    let (datagrams, error, _) = read_all(&path);
    assert!(error.is_none(), "{error:?}");
    assert_eq!(datagrams.iter().map(|d| d.payload.clone()).collect::<Vec<_>>(), payloads);
    for (d, (t, _)) in datagrams.iter().zip(&records) {
        assert!((d.received - t).abs() < 1e-6, "{} vs {t}", d.received);
    }
}

#[test]
fn a_cut_capture_gives_what_came_before_then_says_where_it_broke() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("cut.pcap");
    let records: Vec<_> = (0..3)
        .map(|i| {
            let f = udp_frames(2368, &payload(i, 1206), u16::from(i), 4096).remove(0);
            (f64::from(i), f.clone(), f.len())
        })
        .collect();
    let bytes = pcap(&records);
    std::fs::write(&path, &bytes[..bytes.len() - 100]).unwrap();

    let (datagrams, error, _) = read_all(&path);
    assert_eq!(datagrams.len(), 2);
    let error = error.expect("the cut is reported");
    assert!(matches!(error, CaptureError::Damaged { frames: 2, .. }), "{error}");
}

#[test]
fn a_file_that_is_no_capture_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("notes.pcap");
    std::fs::write(&path, b"hello, this is text").unwrap();
    let err = Capture::open(&path).unwrap_err();
    assert!(err.to_string().contains("not a pcap or pcapng"), "{err}");
}
