//! The Ouster packet decoder against ouster-sdk's points on real captures, and on synthetic packets
//! whose every point follows from the XYZLut equations.

use std::f64::consts::TAU;
use std::path::Path;

use edge::packets::ouster::{Metadata, MetadataError, OusterAssembler, Profile};
use edge::packets::{Assembler, PacketError, Return, ReturnChoice, Rotation};
use edge::recording::capture::{Capture, Datagram};
use serde_json::{Value, json};
use testkit::{Rng, shared_data};

// ---------------------------------------------------------------------------------------------
// Real captures against ouster-sdk 1.0.1's XYZLut.

/// The UDP datagrams of a capture, read by the product's capture reader (itself tested against
/// captures written byte by byte in `capture.rs`).
fn udp_payloads(path: &Path) -> Vec<Datagram> {
    Capture::open(path).unwrap().collect::<Result<_, _>>().unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The lidar port: the metadata's, else the port of the datagrams of a lidar packet's size.
fn lidar_port(metadata: &Metadata, datagrams: &[Datagram]) -> u16 {
    metadata.udp_port_lidar.unwrap_or_else(|| {
        let packet = datagrams.iter().find(|d| d.payload.len() == metadata.lidar_packet_bytes());
        packet.expect("no datagram of a lidar packet's size").destination_port
    })
}

/// Every rotation of a stream, the one `finish` returns included.
fn rotations<'a>(assembler: &mut dyn Assembler, payloads: impl IntoIterator<Item = (&'a [u8], f64)>) -> Vec<Rotation> {
    let mut out = Vec::new();
    for (payload, time) in payloads {
        if let Some(rotation) = assembler.push(payload, time).expect("a lidar packet") {
            out.push(rotation);
        }
    }
    out.extend(assembler.finish());
    out
}

/// Reference points: float32 records `x y z ring`.
fn reference_points(path: &Path) -> Vec<([f32; 3], u16)> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert_eq!(bytes.len() % 16, 0, "{}", path.display());
    bytes
        .chunks_exact(16)
        .map(|record| {
            let f = |i: usize| f32::from_le_bytes(record[4 * i..4 * i + 4].try_into().unwrap());
            ([f(0), f(1), f(2)], f(3) as u16)
        })
        .collect()
}

/// Points by ring, each ring in the order given.
fn by_ring(points: impl IntoIterator<Item = ([f32; 3], u16)>) -> Vec<Vec<[f32; 3]>> {
    let mut rings: Vec<Vec<[f32; 3]>> = Vec::new();
    for (position, ring) in points {
        let ring = usize::from(ring);
        if rings.len() <= ring {
            rings.resize(ring + 1, Vec::new());
        }
        rings[ring].push(position);
    }
    rings
}

fn distance(a: [f32; 3], b: [f32; 3]) -> f64 {
    (0..3).map(|i| f64::from(a[i] - b[i]).powi(2)).sum::<f64>().sqrt()
}

fn percentile(values: &mut [f64], fraction: f64) -> f64 {
    values.sort_by(f64::total_cmp);
    let index = ((values.len() as f64 - 1.0) * fraction).round() as usize;
    values.get(index).copied().unwrap_or(0.0)
}

/// Decodes `NAME.pcap` with `NAME.json` and compares every scan with `NAME_reference/`.
fn check_capture(name: &str) {
    let folder = shared_data("lidar_packets");
    let text = std::fs::read_to_string(folder.join(format!("{name}.json"))).unwrap();
    let metadata = Metadata::from_json(&text).unwrap();
    let datagrams = udp_payloads(&folder.join(format!("{name}.pcap")));
    let port = lidar_port(&metadata, &datagrams);
    let lidar: Vec<&Datagram> = datagrams.iter().filter(|d| d.destination_port == port).collect();
    let mut assembler = OusterAssembler::new(metadata.clone(), ReturnChoice::First);
    let scans = rotations(&mut assembler, lidar.iter().map(|d| (d.payload.as_slice(), d.received)));

    let mut references: Vec<_> = std::fs::read_dir(folder.join(format!("{name}_reference")))
        .unwrap()
        .map(|entry| entry.unwrap().path())
        .filter(|path| path.extension().is_some_and(|ext| ext == "bin"))
        .collect();
    references.sort();
    assert_eq!(scans.len(), references.len(), "{name}: scans decoded vs reference scans");

    let (mut distances, mut ours, mut theirs) = (Vec::new(), 0usize, 0usize);
    for (scan, reference) in scans.iter().zip(&references) {
        let expected = by_ring(reference_points(reference));
        let got = by_ring(scan.returns.iter().map(|r| (r.position, r.ring)));
        ours += scan.returns.len();
        theirs += expected.iter().map(Vec::len).sum::<usize>();
        for (got, expected) in got.iter().zip(&expected) {
            distances.extend(got.iter().zip(expected).map(|(a, b)| distance(*a, *b)));
        }
        check_scan_times(scan, &metadata);
    }
    let p99 = percentile(&mut distances, 0.99);
    let count_difference = (ours as f64 - theirs as f64).abs() / theirs as f64;
    println!(
        "{name}: {} scans, {ours} points (reference {theirs}, {:.3} % apart), p99 distance {:.2e} m, max {:.2e} m",
        scans.len(),
        count_difference * 100.0,
        p99,
        distances.last().copied().unwrap_or(0.0)
    );
    assert!(p99 < 1e-3, "{name}: p99 distance {p99} m");
    assert!(count_difference <= 0.01, "{name}: {ours} points, reference {theirs}");
    assert_eq!(distances.len(), theirs.min(ours), "{name}: every ring matched whole");
}

/// Times run from zero over one frame period, never backwards along a ring.
fn check_scan_times(scan: &Rotation, metadata: &Metadata) {
    let period = 1.0 / 10.0 * 1.01;
    let first = scan.returns.iter().map(|r| r.time).fold(f32::INFINITY, f32::min);
    assert!(first.abs() < 1e-3, "the earliest return is at {first} s");
    for ring in 0..metadata.pixels_per_column as u16 {
        let times: Vec<f32> = scan.returns.iter().filter(|r| r.ring == ring).map(|r| r.time).collect();
        assert!(times.windows(2).all(|w| w[0] <= w[1]), "ring {ring}: times go backwards");
        assert!(times.iter().all(|&t| (0.0..period as f32).contains(&t)), "ring {ring}: a time past the period");
    }
}

#[test]
fn os1_32_legacy_matches_ouster_sdk() {
    check_capture("os1-32-legacy");
}

#[test]
fn os2_128_rng19_matches_ouster_sdk() {
    check_capture("os2-128-rng19");
}

#[test]
fn the_captures_are_whole_frames_without_gaps() {
    for name in ["os1-32-legacy", "os2-128-rng19"] {
        let folder = shared_data("lidar_packets");
        let metadata =
            Metadata::from_json(&std::fs::read_to_string(folder.join(format!("{name}.json"))).unwrap()).unwrap();
        let datagrams = udp_payloads(&folder.join(format!("{name}.pcap")));
        let mut assembler = OusterAssembler::new(metadata, ReturnChoice::First);
        // The IMU packets go to the assembler too: they are skipped, not errors.
        let mut scans = Vec::new();
        for datagram in &datagrams {
            scans.extend(assembler.push(&datagram.payload, datagram.received).unwrap());
        }
        scans.extend(assembler.finish());
        assert_eq!(scans.len(), 1, "{name}");
        assert_eq!((scans[0].gaps, scans[0].partial), (0, false), "{name}");
        let first_lidar = datagrams.iter().find(|d| d.payload.len() != 48).unwrap();
        assert_eq!(scans[0].stamp, first_lidar.received, "{name}");
    }
}

#[test]
fn the_real_metadata_reads_as_its_sensor() {
    let folder = shared_data("lidar_packets");
    let os1 = Metadata::from_json(&std::fs::read_to_string(folder.join("os1-32-legacy.json")).unwrap()).unwrap();
    assert_eq!((os1.profile, os1.pixels_per_column, os1.columns_per_frame), (Profile::Legacy, 32, 1024));
    assert_eq!((os1.prod_line.as_deref(), os1.firmware.as_deref()), (Some("OS-1-32-G"), Some("v2.1.1")));
    assert_eq!(os1.beam_to_lidar_transform[3], 15.806);
    assert_eq!(os1.udp_port_lidar, None);
    let os2 = Metadata::from_json(&std::fs::read_to_string(folder.join("os2-128-rng19.json")).unwrap()).unwrap();
    assert_eq!(
        (os2.profile, os2.pixels_per_column, os2.lidar_packet_bytes()),
        (Profile::Rng19Rfl8Sig16Nir16, 128, 24832)
    );
    assert_eq!((os2.udp_port_lidar, os2.initialization_id), (Some(7502), Some(5_431_293)));
}

// ---------------------------------------------------------------------------------------------
// Synthetic packets.

const BEAMS: usize = 32;
const COLUMNS: usize = 512;
const PER_PACKET: usize = 16;
const PACKETS_PER_FRAME: usize = COLUMNS / PER_PACKET;
/// 512 columns at 10 Hz.
const COLUMN_NS: u64 = 195_312;
const FIRST_NS: u64 = 1_000_000_000_000;
const INIT_ID: u32 = 0x12_3456;
const BEAM_ORIGIN_MM: f64 = 15.806;
const LIDAR_TO_SENSOR: [f64; 16] = [-1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 36.18, 0.0, 0.0, 0.0, 1.0];

fn altitude(beam: usize) -> f64 {
    15.0 - beam as f64
}

fn azimuth(beam: usize) -> f64 {
    [4.2, 1.4, -1.4, -4.2][beam % 4]
}

/// Flat (firmware 2.x) metadata of the synthetic sensor.
fn flat_json(profile: Profile, column_window: [usize; 2]) -> Value {
    json!({
        "beam_altitude_angles": (0..BEAMS).map(altitude).collect::<Vec<_>>(),
        "beam_azimuth_angles": (0..BEAMS).map(azimuth).collect::<Vec<_>>(),
        "lidar_origin_to_beam_origin_mm": BEAM_ORIGIN_MM,
        "lidar_to_sensor_transform": LIDAR_TO_SENSOR,
        "lidar_mode": "512x10",
        "prod_line": "OS-1-32-U",
        "build_rev": "v2.3.0",
        "initialization_id": INIT_ID,
        "udp_port_lidar": 7502,
        "udp_port_imu": 7503,
        "data_format": {
            "pixels_per_column": BEAMS,
            "columns_per_packet": PER_PACKET,
            "columns_per_frame": COLUMNS,
            "column_window": column_window,
            "pixel_shift_by_row": (0..BEAMS).map(|beam| [12, 8, 4, 0][beam % 4]).collect::<Vec<_>>(),
            "udp_profile_lidar": profile.name(),
        }
    })
}

fn metadata(profile: Profile) -> Metadata {
    Metadata::from_json(&flat_json(profile, [0, COLUMNS - 1]).to_string()).unwrap()
}

/// The two returns of a pixel: (range mm, reflectivity). Some first ranges are zero; some second
/// ranges are zero or equal to the first.
fn echoes(profile: Profile, column: usize, beam: usize) -> [(u32, u8); 2] {
    let first = if (column * 7 + beam).is_multiple_of(11) { 0 } else { 1000 + 37 * beam as u32 + 13 * column as u32 };
    let second = match (column + beam) % 13 {
        0 => 0,
        1 => first,
        _ => first + 2500,
    };
    // The low-data profile counts in units of 8 mm.
    let unit = if profile == Profile::Rng15Rfl8Nir8 { 8 } else { 1 };
    let reflectivity = |salt: usize| ((column * 3 + beam * 5 + salt) % 250) as u8 + 1;
    [(first / unit * unit, reflectivity(0)), (second / unit * unit, reflectivity(7))]
}

/// The pixel's bytes; the flag bits ouster-sdk masks off are set, to check they are ignored.
fn pixel_bytes(profile: Profile, [(range, reflectivity), (range2, reflectivity2)]: [(u32, u8); 2]) -> Vec<u8> {
    let mut out = Vec::new();
    match profile {
        Profile::Legacy => {
            out.extend((range | 0xf0_0000).to_le_bytes());
            out.extend(u16::from(reflectivity).to_le_bytes());
            out.extend([0x11, 0x22, 0x33, 0x44, 0, 0]); // signal, near-infrared, unused
        }
        Profile::Rng19Rfl8Sig16Nir16 => {
            out.extend((range | 0xf8_0000).to_le_bytes());
            out.extend([reflectivity, 0, 0x11, 0x22, 0x33, 0x44, 0, 0]);
        }
        Profile::Rng19Rfl8Sig16Nir16Dual => {
            out.extend((range | 0xf8_0000 | u32::from(reflectivity) << 24).to_le_bytes());
            out.extend((range2 | 0xf8_0000 | u32::from(reflectivity2) << 24).to_le_bytes());
            out.extend([0x11, 0x22, 0x33, 0x44, 0x55, 0x66, 0, 0]);
        }
        Profile::Rng15Rfl8Nir8 => {
            out.extend(((range / 8) | 0x8000).to_le_bytes()[..2].iter());
            out.extend([reflectivity, 0x5a]);
        }
    }
    assert_eq!(out.len(), profile.pixel_bytes());
    out
}

/// Which columns a packet marks invalid.
type Invalid = fn(usize) -> bool;

fn all_valid(_: usize) -> bool {
    false
}

/// A packet of frame `frame_id` holding the columns from `first_column`.
fn packet(profile: Profile, frame_id: u16, first_column: usize, invalid: Invalid) -> Vec<u8> {
    let legacy = profile == Profile::Legacy;
    let mut out = Vec::new();
    if !legacy {
        out.extend(1u16.to_le_bytes()); // packet_type: lidar data
        out.extend(frame_id.to_le_bytes());
        out.extend(&INIT_ID.to_le_bytes()[..3]);
        out.extend(&992_210_000_957u64.to_le_bytes()[..5]);
        out.extend([0, 0, 0, 0, 3, 4, 0, 0]); // reserved, countdowns, shutdown and shot limiting
        out.resize(32, 0);
    }
    for column in first_column..first_column + PER_PACKET {
        let valid = !invalid(column);
        out.extend((FIRST_NS + column as u64 * COLUMN_NS).to_le_bytes());
        out.extend((column as u16).to_le_bytes());
        if legacy {
            out.extend(frame_id.to_le_bytes());
            out.extend((column as u32 * 176).to_le_bytes()); // encoder count
        } else {
            out.extend(u16::from(valid).to_le_bytes());
        }
        for beam in 0..BEAMS {
            out.extend(pixel_bytes(profile, echoes(profile, column, beam)));
        }
        if legacy {
            out.extend(if valid { u32::MAX } else { 0 }.to_le_bytes());
        }
    }
    if !legacy {
        out.extend([0u8; 32]);
    }
    assert_eq!(out.len(), profile.lidar_packet_bytes(BEAMS, PER_PACKET));
    out
}

/// The packets of one whole frame, in order.
fn frame(profile: Profile, frame_id: u16) -> Vec<Vec<u8>> {
    (0..PACKETS_PER_FRAME).map(|p| packet(profile, frame_id, p * PER_PACKET, all_valid)).collect()
}

/// The point ouster-sdk's XYZLut gives, written out as its equations.
fn xyzlut(column: usize, beam: usize, range_mm: u32) -> [f64; 3] {
    let encoder = TAU * (1.0 - column as f64 / COLUMNS as f64);
    let azimuth = -azimuth(beam).to_radians();
    let altitude = altitude(beam).to_radians();
    let direction =
        [(encoder + azimuth).cos() * altitude.cos(), (encoder + azimuth).sin() * altitude.cos(), altitude.sin()];
    let n = BEAM_ORIGIN_MM;
    let offset = [encoder.cos() * n - direction[0] * n, encoder.sin() * n - direction[1] * n, -direction[2] * n];
    let lidar: Vec<f64> = (0..3).map(|i| direction[i] * f64::from(range_mm) + offset[i]).collect();
    let t = LIDAR_TO_SENSOR;
    std::array::from_fn(|row| {
        let sensor = (0..3).map(|i| t[4 * row + i] * lidar[i]).sum::<f64>() + t[4 * row + 3];
        sensor / 1000.0
    })
}

/// What a whole frame should decode to, in the decoder's order (column by column).
fn expected_returns(
    profile: Profile,
    choice: ReturnChoice,
    columns: impl Iterator<Item = usize>,
) -> Vec<(usize, Return)> {
    let mut out = Vec::new();
    for column in columns {
        for beam in 0..BEAMS {
            let [first, second] = echoes(profile, column, beam);
            let kept = match choice {
                ReturnChoice::First => vec![first],
                ReturnChoice::Second if profile.is_dual() => vec![second],
                ReturnChoice::Second => vec![],
                ReturnChoice::Both if profile.is_dual() && second.0 != first.0 => vec![first, second],
                ReturnChoice::Both => vec![first],
            };
            for (range, reflectivity) in kept.into_iter().filter(|(range, _)| *range > 0) {
                let p = xyzlut(column, beam, range);
                let position = [p[0] as f32, p[1] as f32, p[2] as f32];
                let time = (column as f64 * COLUMN_NS as f64 * 1e-9) as f32;
                out.push((column, Return { position, intensity: f32::from(reflectivity), ring: beam as u16, time }));
            }
        }
    }
    out
}

fn assert_same_returns(got: &[Return], expected: &[(usize, Return)], time_offset: f32) {
    assert_eq!(got.len(), expected.len(), "number of returns");
    for (got, (column, expected)) in got.iter().zip(expected) {
        let error = distance(got.position, expected.position);
        assert!(error < 2e-6, "column {column} ring {}: {:?} vs {:?}", expected.ring, got.position, expected.position);
        assert_eq!((got.ring, got.intensity), (expected.ring, expected.intensity), "column {column}");
        assert!((got.time - (expected.time - time_offset)).abs() < 1e-7, "column {column}: time {}", got.time);
    }
}

/// Pushes `packets` (received 1 ms apart from `start`), returning the rotations pushes gave.
fn push_all(assembler: &mut OusterAssembler, packets: &[Vec<u8>], start: f64) -> Vec<Rotation> {
    let mut out = Vec::new();
    for (i, packet) in packets.iter().enumerate() {
        out.extend(assembler.push(packet, start + i as f64 * 1e-3).unwrap());
    }
    out
}

/// One whole frame followed by the first packet of the next: the frame comes out, whole.
fn check_whole_frame(profile: Profile, choice: ReturnChoice) {
    let mut assembler = OusterAssembler::new(metadata(profile), choice);
    let mut packets = frame(profile, 7);
    packets.push(packet(profile, 8, 0, all_valid));
    let rotations = push_all(&mut assembler, &packets, 50.0);
    assert_eq!(rotations.len(), 1, "{profile:?}: one frame closed by the next");
    let rotation = &rotations[0];
    assert_eq!((rotation.stamp, rotation.gaps, rotation.partial), (50.0, 0, false), "{profile:?}");
    assert_same_returns(&rotation.returns, &expected_returns(profile, choice, 0..COLUMNS), 0.0);
}

/// Rotations written into returns given back (as a live source gives back each rotation once it
/// made its cloud) hold exactly their own returns, nothing of the earlier rotation. A rotation
/// closes on the next frame's first packet, which opens the next rotation at once, so the returns
/// of a rotation hold the one after the next.
#[test]
fn a_rotation_given_back_holds_a_later_one_and_nothing_of_its_own() {
    let profile = Profile::Rng19Rfl8Sig16Nir16;
    let mut assembler = OusterAssembler::new(metadata(profile), ReturnChoice::First);
    let expected = expected_returns(profile, ReturnChoice::First, 0..COLUMNS);
    let mut given_back = Vec::new();
    for frame_id in 7..12u16 {
        let mut packets = frame(profile, frame_id);
        packets.push(packet(profile, frame_id + 1, 0, all_valid));
        let [rotation] = &mut push_all(&mut assembler, &packets, f64::from(frame_id))[..] else {
            panic!("frame {frame_id}: not one rotation")
        };
        assert_same_returns(&rotation.returns, &expected, 0.0);
        if given_back.len() >= 2 {
            let two_before = given_back[given_back.len() - 2];
            assert_eq!(rotation.returns.as_ptr(), two_before, "frame {frame_id}: not in the returns given back");
        }
        // Garbage where a later rotation will be written: it must not survive.
        let mut returns = std::mem::take(&mut rotation.returns);
        returns.iter_mut().for_each(|r| r.position = [f32::NAN; 3]);
        returns.push(Return { position: [1.0; 3], intensity: 0.0, ring: 0, time: 0.0 });
        given_back.push(returns.as_ptr());
        assembler.recycle(returns);
    }
}

#[test]
fn legacy_points_follow_the_xyzlut_equations() {
    check_whole_frame(Profile::Legacy, ReturnChoice::First);
}

#[test]
fn rng19_points_follow_the_xyzlut_equations() {
    check_whole_frame(Profile::Rng19Rfl8Sig16Nir16, ReturnChoice::First);
}

#[test]
fn low_data_points_follow_the_xyzlut_equations() {
    check_whole_frame(Profile::Rng15Rfl8Nir8, ReturnChoice::First);
}

#[test]
fn dual_return_profile_keeps_the_chosen_returns() {
    for choice in [ReturnChoice::First, ReturnChoice::Second, ReturnChoice::Both] {
        check_whole_frame(Profile::Rng19Rfl8Sig16Nir16Dual, choice);
    }
}

#[test]
fn single_return_profiles_have_no_second_return() {
    let mut assembler = OusterAssembler::new(metadata(Profile::Rng19Rfl8Sig16Nir16), ReturnChoice::Second);
    push_all(&mut assembler, &frame(Profile::Rng19Rfl8Sig16Nir16, 7), 0.0);
    assert_eq!(assembler.finish(), None, "no returns, so no rotation");
}

#[test]
fn frames_are_cut_at_the_frame_id_and_the_last_is_partial() {
    let profile = Profile::Rng19Rfl8Sig16Nir16;
    let mut assembler = OusterAssembler::new(metadata(profile), ReturnChoice::First);
    let whole = frame(profile, 7);
    // Nothing comes out until a packet of the next frame does.
    assert!(push_all(&mut assembler, &whole, 0.0).is_empty());
    let next: Vec<Vec<u8>> = frame(profile, 8).into_iter().take(10).collect();
    let closed = push_all(&mut assembler, &next, 1.0);
    assert_eq!(closed.len(), 1);
    assert_eq!((closed[0].gaps, closed[0].partial, closed[0].stamp), (0, false, 0.0));
    let last = assembler.finish().expect("the frame in progress");
    assert_eq!((last.gaps, last.partial, last.stamp), (0, true, 1.0));
    assert_same_returns(&last.returns, &expected_returns(profile, ReturnChoice::First, 0..10 * PER_PACKET), 0.0);
    assert_eq!(assembler.finish(), None, "finish empties the assembler");
}

#[test]
fn a_stream_starting_mid_frame_gives_a_partial_first_rotation() {
    let profile = Profile::Legacy;
    let mut assembler = OusterAssembler::new(metadata(profile), ReturnChoice::First);
    let mut packets: Vec<Vec<u8>> = frame(profile, 7).into_iter().skip(20).collect();
    packets.extend(frame(profile, 8));
    packets.push(packet(profile, 9, 0, all_valid));
    let rotations = push_all(&mut assembler, &packets, 0.0);
    assert_eq!(rotations.len(), 2);
    assert_eq!((rotations[0].gaps, rotations[0].partial), (0, true), "missing start: partial, not gaps");
    assert_eq!((rotations[1].gaps, rotations[1].partial), (0, false));
    // Times count from the rotation's first column, not the frame's column 0.
    let first_column = 20 * PER_PACKET;
    let offset = (first_column as f64 * COLUMN_NS as f64 * 1e-9) as f32;
    assert_same_returns(
        &rotations[0].returns,
        &expected_returns(profile, ReturnChoice::First, first_column..COLUMNS),
        offset,
    );
}

#[test]
fn a_dropped_packet_is_counted_in_gaps() {
    for profile in [Profile::Legacy, Profile::Rng19Rfl8Sig16Nir16] {
        let mut assembler = OusterAssembler::new(metadata(profile), ReturnChoice::First);
        let mut packets = frame(profile, 7);
        packets.remove(5);
        packets.push(packet(profile, 8, 0, all_valid));
        let rotations = push_all(&mut assembler, &packets, 0.0);
        assert_eq!(rotations.len(), 1);
        assert_eq!((rotations[0].gaps, rotations[0].partial), (PER_PACKET, false), "{profile:?}");
        let kept = (0..COLUMNS).filter(|column| column / PER_PACKET != 5);
        assert_same_returns(&rotations[0].returns, &expected_returns(profile, ReturnChoice::First, kept), 0.0);
    }
}

#[test]
fn a_lost_last_packet_is_a_gap_when_the_next_frame_follows() {
    let profile = Profile::Rng19Rfl8Sig16Nir16;
    let mut assembler = OusterAssembler::new(metadata(profile), ReturnChoice::First);
    let mut packets = frame(profile, 7);
    packets.pop();
    packets.extend(frame(profile, 8));
    packets.push(packet(profile, 9, 0, all_valid));
    let rotations = push_all(&mut assembler, &packets, 0.0);
    assert_eq!(rotations.iter().map(|r| (r.gaps, r.partial)).collect::<Vec<_>>(), [(PER_PACKET, false), (0, false)]);
}

#[test]
fn a_reordered_packet_gives_the_same_rotation() {
    for profile in [Profile::Legacy, Profile::Rng19Rfl8Sig16Nir16Dual] {
        let mut in_order = frame(profile, 7);
        in_order.push(packet(profile, 8, 0, all_valid));
        let mut reordered = in_order.clone();
        reordered.swap(0, 1);
        reordered.swap(10, 14);
        let decode = |packets: &[Vec<u8>]| {
            let mut assembler = OusterAssembler::new(metadata(profile), ReturnChoice::Both);
            let mut rotations = push_all(&mut assembler, packets, 0.0);
            assert_eq!(rotations.len(), 1);
            let mut rotation = rotations.remove(0);
            rotation.stamp = 0.0; // the first packet to arrive differs
            rotation
        };
        let expected = decode(&in_order);
        assert_eq!(decode(&reordered), expected, "{profile:?}");
        assert_eq!(expected.gaps, 0);
    }
}

#[test]
fn a_late_packet_of_the_previous_frame_is_dropped() {
    let profile = Profile::Rng19Rfl8Sig16Nir16;
    let mut assembler = OusterAssembler::new(metadata(profile), ReturnChoice::First);
    let mut packets = frame(profile, 7);
    let late = packets.remove(31);
    packets.extend(frame(profile, 8).into_iter().take(3));
    packets.push(late);
    packets.extend(frame(profile, 8).into_iter().skip(3));
    packets.push(packet(profile, 9, 0, all_valid));
    let rotations = push_all(&mut assembler, &packets, 0.0);
    assert_eq!(rotations.iter().map(|r| (r.gaps, r.partial)).collect::<Vec<_>>(), [(PER_PACKET, false), (0, false)]);
}

#[test]
fn invalid_columns_are_skipped_and_counted_as_gaps() {
    for profile in [Profile::Legacy, Profile::Rng15Rfl8Nir8] {
        let invalid: Invalid = |column| column % 5 == 2;
        let mut packets: Vec<Vec<u8>> =
            (0..PACKETS_PER_FRAME).map(|p| packet(profile, 7, p * PER_PACKET, invalid)).collect();
        packets.push(packet(profile, 8, 0, all_valid));
        let mut assembler = OusterAssembler::new(metadata(profile), ReturnChoice::First);
        let rotations = push_all(&mut assembler, &packets, 0.0);
        let invalid_columns = (0..COLUMNS).filter(|&c| invalid(c)).count();
        assert_eq!(rotations[0].gaps, invalid_columns, "{profile:?}");
        let valid = (0..COLUMNS).filter(|&c| !invalid(c));
        assert_same_returns(&rotations[0].returns, &expected_returns(profile, ReturnChoice::First, valid), 0.0);
    }
}

#[test]
fn a_column_window_counts_gaps_within_it_only() {
    let profile = Profile::Rng19Rfl8Sig16Nir16;
    let metadata = Metadata::from_json(&flat_json(profile, [128, 383]).to_string()).unwrap();
    assert_eq!(metadata.window_columns(), 256);
    let window_packets =
        |frame_id| -> Vec<Vec<u8>> { (8..24).map(|p| packet(profile, frame_id, p * PER_PACKET, all_valid)).collect() };
    let mut packets = window_packets(7);
    packets.remove(3);
    packets.extend(window_packets(8));
    let mut assembler = OusterAssembler::new(metadata, ReturnChoice::First);
    let rotations = rotations(&mut assembler, packets.iter().map(|p| (p.as_slice(), 0.0)));
    let summary: Vec<_> = rotations.iter().map(|r| (r.gaps, r.partial)).collect();
    // The first starts at the window's first column, so it is whole; the last reaches its end.
    assert_eq!(summary, [(PER_PACKET, false), (0, false)]);
    let first_column = 128;
    let offset = (first_column as f64 * COLUMN_NS as f64 * 1e-9) as f32;
    assert_same_returns(&rotations[1].returns, &expected_returns(profile, ReturnChoice::First, 128..384), offset);
}

#[test]
fn a_sensor_reset_cuts_the_frame_short() {
    let profile = Profile::Rng19Rfl8Sig16Nir16;
    let mut assembler = OusterAssembler::new(metadata(profile), ReturnChoice::First);
    let mut packets: Vec<Vec<u8>> = frame(profile, 7).into_iter().take(12).collect();
    let mut restarted = frame(profile, 0);
    for packet in &mut restarted {
        packet[4] ^= 0xff; // another init_id
    }
    packets.extend(restarted);
    let rotations = push_all(&mut assembler, &packets, 0.0);
    assert_eq!(rotations.iter().map(|r| (r.gaps, r.partial)).collect::<Vec<_>>(), [(0, true)]);
    let after_reset = assembler.finish().unwrap();
    assert_eq!((after_reset.gaps, after_reset.partial), (0, false), "a whole frame after the reset");
}

#[test]
fn other_payloads_are_skipped_or_refused() {
    let profile = Profile::Rng19Rfl8Sig16Nir16;
    let mut assembler = OusterAssembler::new(metadata(profile), ReturnChoice::First);
    assert_eq!(assembler.push(&[0u8; 48], 0.0), Ok(None), "a LEGACY IMU packet");
    for len in [0, 1, 90, 1206, 24_832] {
        assert!(
            matches!(assembler.push(&vec![0u8; len], 0.0), Err(PacketError::Length { len: l, .. }) if l == len),
            "{len}"
        );
    }
    let mut not_lidar = packet(profile, 7, 0, all_valid);
    not_lidar[0] = 2;
    assert!(matches!(assembler.push(&not_lidar, 0.0), Err(PacketError::Invalid { .. })));
    assert_eq!(assembler.finish(), None);
}

#[test]
fn unusable_metadata_makes_every_push_an_error() {
    let mut metadata = metadata(Profile::Legacy);
    metadata.columns_per_frame = 0;
    let mut assembler = OusterAssembler::new(metadata, ReturnChoice::First);
    let result = assembler.push(&packet(Profile::Legacy, 7, 0, all_valid), 0.0);
    assert!(matches!(result, Err(PacketError::Invalid { reason, .. }) if reason.contains("columns_per_frame")));
    assert_eq!(assembler.finish(), None);
}

// ---------------------------------------------------------------------------------------------
// Metadata layouts.

/// The synthetic sensor's metadata as firmware 3.x and ouster-sdk 0.11+ lay it out.
fn nested_json(profile: Profile) -> Value {
    let flat = flat_json(profile, [0, COLUMNS - 1]);
    let format = &flat["data_format"];
    json!({
        "beam_intrinsics": {
            "beam_altitude_angles": flat["beam_altitude_angles"],
            "beam_azimuth_angles": flat["beam_azimuth_angles"],
            "beam_to_lidar_transform": [1, 0, 0, BEAM_ORIGIN_MM, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1],
            "lidar_origin_to_beam_origin_mm": BEAM_ORIGIN_MM
        },
        "calibration_status": {},
        "config_params": {
            "lidar_mode": "512x10",
            "udp_port_lidar": 7502,
            "udp_port_imu": 7503,
            "udp_profile_lidar": profile.name(),
            "columns_per_packet": PER_PACKET,
            "azimuth_window": [0, 360000]
        },
        "imu_intrinsics": {"imu_to_sensor_transform": [1, 0, 0, 6.253, 0, 1, 0, -11.775, 0, 0, 1, 7.645, 0, 0, 0, 1]},
        "lidar_data_format": {
            "column_window": format["column_window"],
            "columns_per_frame": COLUMNS,
            "columns_per_packet": PER_PACKET,
            "fps": 10,
            "header_type": "STANDARD",
            "pixel_shift_by_row": format["pixel_shift_by_row"],
            "pixels_per_column": BEAMS,
            "udp_profile_imu": "LEGACY",
            "udp_profile_lidar": profile.name()
        },
        "lidar_intrinsics": {"lidar_to_sensor_transform": LIDAR_TO_SENSOR},
        "ouster-sdk": {"client_version": "ouster_client 0.11.1", "output_source": "sensor_info_to_string"},
        "sensor_info": {
            "build_date": "2023-01-01T00:00:00Z",
            "build_rev": "v2.3.0",
            "image_rev": "ousteros-image-prod-aries-v2.3.0",
            "initialization_id": INIT_ID,
            "prod_line": "OS-1-32-U",
            "prod_pn": "840-102145-D",
            "prod_sn": "992210000957",
            "status": "RUNNING"
        },
        "user_data": ""
    })
}

#[test]
fn nested_metadata_parses_as_the_equivalent_flat_metadata() {
    for profile in Profile::ALL {
        let nested = Metadata::from_json(&nested_json(profile).to_string()).unwrap();
        assert_eq!(nested, metadata(profile), "{profile:?}");
    }
}

#[test]
fn nested_metadata_errors_name_the_section() {
    let mut json = nested_json(Profile::Legacy);
    json["lidar_intrinsics"].as_object_mut().unwrap().remove("lidar_to_sensor_transform");
    let error = Metadata::from_json(&json.to_string()).unwrap_err();
    assert_eq!(error, MetadataError::Missing { field: "lidar_intrinsics.lidar_to_sensor_transform".into() });
    let mut json = nested_json(Profile::Legacy);
    json["lidar_data_format"]["header_type"] = json!("FUSA");
    let error = Metadata::from_json(&json.to_string()).unwrap_err();
    assert!(
        matches!(error, MetadataError::Invalid { ref field, .. } if field == "lidar_data_format.header_type"),
        "{error}"
    );
    assert!(matches!(Metadata::from_json("[1, 2]"), Err(MetadataError::Json(_))));
    assert!(matches!(Metadata::from_json("{"), Err(MetadataError::Json(_))));
}

#[test]
fn a_beam_origin_above_the_lidar_origin_moves_points_as_ouster_sdk_does() {
    // ouster-sdk: offset z = beam_to_lidar z - direction z * |(x, z)|, with x and z the
    // transform's translation; a straight-up beam (altitude 90 degrees) at range r gives z = r - |(x, z)| + z.
    let mut json = nested_json(Profile::Legacy);
    json["beam_intrinsics"]["beam_to_lidar_transform"] = json!([1, 0, 0, 3.0, 0, 1, 0, 0, 0, 0, 1, 4.0, 0, 0, 0, 1]);
    json["beam_intrinsics"]["beam_altitude_angles"] = json!(vec![90.0; BEAMS]);
    json["lidar_intrinsics"]["lidar_to_sensor_transform"] = json!([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
    let metadata = Metadata::from_json(&json.to_string()).unwrap();
    let mut assembler = OusterAssembler::new(metadata, ReturnChoice::First);
    push_all(&mut assembler, &frame(Profile::Legacy, 7)[..1], 0.0);
    let rotation = assembler.finish().unwrap();
    let [first, _] = echoes(Profile::Legacy, 0, 1);
    let point = rotation.returns.iter().find(|r| r.ring == 1).unwrap();
    let expected_z = (f64::from(first.0) - 5.0 + 4.0) / 1000.0;
    // Column 0: x = cos(0) * 3 mm, the horizontal part of the beam being zero.
    assert!((f64::from(point.position[2]) - expected_z).abs() < 1e-6, "{:?}", point.position);
    assert!((f64::from(point.position[0]) - 0.003).abs() < 1e-6, "{:?}", point.position);
}

// ---------------------------------------------------------------------------------------------
// Fuzzing: random and mutated payloads and metadata never panic.

/// A JSON value with some numbers, strings and arrays replaced or removed.
fn mutate_json(value: &mut Value, rng: &mut Rng) {
    match value {
        Value::Object(map) => {
            let keys: Vec<String> = map.keys().cloned().collect();
            for key in keys {
                if rng.below(120) == 0 {
                    map.remove(&key);
                } else if let Some(child) = map.get_mut(&key) {
                    mutate_json(child, rng);
                }
            }
        }
        Value::Array(items) => {
            if rng.below(60) == 0 {
                items.truncate(rng.below(items.len() + 1));
            }
            items.iter_mut().for_each(|item| mutate_json(item, rng));
        }
        leaf => {
            if rng.below(120) == 0 {
                *leaf = match rng.below(8) {
                    0 => Value::Null,
                    1 => json!(-1),
                    2 => json!(rng.next_u64()),
                    3 => json!(rng.uniform(-1e6, 1e6)),
                    4 => json!(Profile::ALL[rng.below(4)].name()),
                    5 => json!([0, 4095]),
                    // Plausible sizes: beams, columns, windows that disagree with the rest.
                    _ => json!(rng.below(2049)),
                };
            }
        }
    }
}

/// A payload of a random length, a lidar packet's length, or a real packet with bytes flipped.
fn random_payload(rng: &mut Rng, valid: &[Vec<u8>], packet_bytes: usize) -> Vec<u8> {
    match rng.below(4) {
        0 => (0..rng.below(400)).map(|_| rng.next_u64() as u8).collect(),
        1 => (0..packet_bytes).map(|_| rng.next_u64() as u8).collect(),
        _ => {
            let mut packet = valid[rng.below(valid.len())].clone();
            for _ in 0..1 + rng.below(20) {
                let at = rng.below(packet.len().max(1));
                if let Some(byte) = packet.get_mut(at) {
                    *byte = rng.next_u64() as u8;
                }
            }
            // Headers and frame ids: flip the first bytes of a column more often.
            if rng.below(2) == 0 && packet.len() > 48 {
                let at = 32 + rng.below(16);
                packet[at] = rng.next_u64() as u8;
            }
            packet
        }
    }
}

#[test]
fn random_and_mutated_input_never_panics() {
    let mut rng = Rng::xorshift64_star(Rng::spread(0x57e2));
    for case in 0..512 {
        let profile = Profile::ALL[case % Profile::ALL.len()];
        let mut json = if case % 2 == 0 { flat_json(profile, [0, COLUMNS - 1]) } else { nested_json(profile) };
        mutate_json(&mut json, &mut rng);
        let metadata = match Metadata::from_json(&json.to_string()) {
            Ok(metadata) => metadata,
            Err(_) => metadata(profile),
        };
        let choice = [ReturnChoice::First, ReturnChoice::Second, ReturnChoice::Both][rng.below(3)];
        let packet_bytes = metadata.lidar_packet_bytes();
        let mut assembler = OusterAssembler::new(metadata, choice);
        let valid: Vec<Vec<u8>> =
            (0..4).map(|p| packet(profile, rng.below(3) as u16, p * PER_PACKET * 8, all_valid)).collect();
        for _ in 0..24 {
            let payload = random_payload(&mut rng, &valid, packet_bytes);
            if let Ok(Some(rotation)) = assembler.push(&payload, rng.f64()) {
                assert!(rotation.returns.iter().all(|r| r.position.iter().all(|c| c.is_finite())));
            }
        }
        let _ = assembler.finish();
    }
    // Text that is barely JSON.
    let alphabet = b"{}[]\":,0123456789.-eE truefalsnul";
    for _ in 0..200 {
        let text: String = (0..rng.below(64)).map(|_| char::from(alphabet[rng.below(alphabet.len())])).collect();
        let _ = Metadata::from_json(&text);
    }
}
