//! The Velodyne decoder against velodyne-decoder 3.0.0 on real captures, on packets built here
//! whose points can be worked out by hand, and on random and damaged payloads.

use edge::packets::velodyne::{Calibration, CalibrationError, Model, VelodyneAssembler, VelodyneOptions};
use edge::packets::{Assembler, PacketError, Return, ReturnChoice, Rotation};
use edge::recording::capture::Capture;
use std::path::Path;
use testkit::Rng;

// ---------------------------------------------------------------------------------------------
// Reading the captures and the reference scans.

/// The UDP payloads of a capture with their capture times, read by the product's capture reader
/// (itself tested against captures written byte by byte in `capture.rs`).
fn udp_payloads(path: &Path) -> Vec<(f64, Vec<u8>)> {
    let datagrams = Capture::open(path).unwrap().collect::<Result<Vec<_>, _>>();
    let datagrams = datagrams.unwrap_or_else(|error| panic!("{}: {error}", path.display()));
    datagrams.into_iter().map(|d| (d.received, d.payload)).collect()
}

/// One point of a reference scan: x y z intensity time ring (time from the scan's last packet).
#[derive(Clone, Copy, Debug)]
struct Reference {
    position: [f32; 3],
    intensity: f32,
    time: f32,
    ring: u16,
}

fn reference_scans(name: &str) -> Vec<Vec<Reference>> {
    let folder = testkit::shared_data(&format!("lidar_packets/{name}_reference"));
    let mut files: Vec<_> = std::fs::read_dir(&folder).unwrap().map(|entry| entry.unwrap().path()).collect();
    files.sort();
    files
        .iter()
        .map(|file| {
            let bytes = std::fs::read(file).unwrap();
            let floats: Vec<f32> =
                bytes.chunks_exact(4).map(|word| f32::from_le_bytes(word.try_into().unwrap())).collect();
            floats
                .chunks_exact(6)
                .map(|p| Reference { position: [p[0], p[1], p[2]], intensity: p[3], time: p[4], ring: p[5] as u16 })
                .collect()
        })
        .collect()
}

/// Every rotation of a stream, the last from `finish`.
fn rotations(assembler: &mut VelodyneAssembler, payloads: &[(f64, Vec<u8>)]) -> Vec<Rotation> {
    let mut rotations = Vec::new();
    for (received, payload) in payloads {
        if let Some(rotation) = assembler.push(payload, *received).expect("a packet of the capture") {
            rotations.push(rotation);
        }
    }
    rotations.extend(assembler.finish());
    rotations
}

/// How one decoded rotation compares with its reference scan.
#[derive(Debug)]
struct Comparison {
    decoded: usize,
    reference: usize,
    matched: usize,
    p99_distance: f64,
    intensity_mismatches: usize,
}

/// Pairs points of the same ring fired at the same time. Reference times count from the scan's
/// last packet and ours from its first firing, so the reference is first shifted by the
/// difference of the two scans' earliest times; a wrong shift leaves the points unmatched.
fn compare(decoded: &[Return], reference: &[Reference]) -> Comparison {
    const SAME_FIRING_S: f64 = 0.5e-6;
    let earliest = |times: &mut dyn Iterator<Item = f32>| times.map(f64::from).fold(f64::INFINITY, f64::min);
    let shift = earliest(&mut reference.iter().map(|p| p.time)) - earliest(&mut decoded.iter().map(|r| r.time));
    let rings = decoded.iter().map(|r| r.ring).chain(reference.iter().map(|p| p.ring)).max().unwrap_or(0);
    let (mut distances, mut intensity_mismatches) = (Vec::new(), 0);
    for ring in 0..=rings {
        let mut ours: Vec<&Return> = decoded.iter().filter(|r| r.ring == ring).collect();
        let mut theirs: Vec<&Reference> = reference.iter().filter(|p| p.ring == ring).collect();
        ours.sort_by(|a, b| a.time.total_cmp(&b.time));
        theirs.sort_by(|a, b| a.time.total_cmp(&b.time));
        let (mut i, mut j) = (0, 0);
        while i < ours.len() && j < theirs.len() {
            let difference = f64::from(ours[i].time) - (f64::from(theirs[j].time) - shift);
            if difference.abs() <= SAME_FIRING_S {
                let squared: f32 = (0..3).map(|k| (ours[i].position[k] - theirs[j].position[k]).powi(2)).sum();
                distances.push(f64::from(squared.sqrt()));
                intensity_mismatches += usize::from(ours[i].intensity != theirs[j].intensity);
                i += 1;
                j += 1;
            } else if difference < 0.0 {
                i += 1;
            } else {
                j += 1;
            }
        }
    }
    distances.sort_by(f64::total_cmp);
    let p99_distance = distances.get(distances.len() * 99 / 100).copied().unwrap_or(f64::INFINITY);
    Comparison {
        decoded: decoded.len(),
        reference: reference.len(),
        matched: distances.len(),
        p99_distance,
        intensity_mismatches,
    }
}

/// Decodes a capture with the default options and checks every rotation against its reference.
fn check_capture(name: &str, model: Model, expected_partial: &[bool]) {
    let payloads = udp_payloads(&testkit::shared_data(&format!("lidar_packets/{name}.pcap")));
    let mut assembler = VelodyneAssembler::new(VelodyneOptions::default()).unwrap();
    let decoded = rotations(&mut assembler, &payloads);
    assert_eq!(assembler.model(), Some(model));
    let reference = reference_scans(name);
    assert_eq!(decoded.len(), reference.len(), "{name}: rotations");
    let partial: Vec<bool> = decoded.iter().map(|rotation| rotation.partial).collect();
    assert_eq!(partial, expected_partial, "{name}: partial flags");
    for (index, (rotation, reference)) in decoded.iter().zip(&reference).enumerate() {
        let comparison = compare(&rotation.returns, reference);
        println!("{name} rotation {index}: {comparison:?}, gaps {}", rotation.gaps);
        let count_difference = comparison.decoded.abs_diff(comparison.reference) as f64 / comparison.reference as f64;
        assert!(count_difference <= 0.01, "{name} rotation {index}: point counts differ: {comparison:?}");
        assert!(comparison.matched as f64 >= 0.99 * comparison.reference as f64, "{name} {index}: {comparison:?}");
        assert!(comparison.p99_distance <= 1e-3, "{name} rotation {index}: {comparison:?}");
        assert!(comparison.intensity_mismatches == 0, "{name} rotation {index}: {comparison:?}");
        assert_eq!(rotation.gaps, 0, "{name} rotation {index}: the capture loses no packet");
        assert!(rotation.returns.iter().all(|r| r.time >= 0.0), "{name} {index}: times from the first firing");
    }
    // The first rotation is stamped with the arrival of the capture's first data packet.
    let first_data = payloads.iter().find(|(_, payload)| payload.len() == 1206).unwrap();
    assert_eq!(decoded[0].stamp, first_data.0);
}

/// Rotations written into the returns of the one before (given back as a live source does) are
/// the rotations decoded into fresh memory, nothing of the earlier rotation left in them.
#[test]
fn a_rotation_given_back_holds_the_next_one_and_nothing_of_its_own() {
    let payloads = udp_payloads(&testkit::shared_data("lidar_packets/vlp16.pcap"));
    let fresh = rotations(&mut VelodyneAssembler::new(VelodyneOptions::default()).unwrap(), &payloads);
    let mut assembler = VelodyneAssembler::new(VelodyneOptions::default()).unwrap();
    let (mut recycled, mut given_back) = (Vec::new(), None);
    for (received, payload) in &payloads {
        if let Some(rotation) = assembler.push(payload, *received).unwrap() {
            recycled.push(rotation.clone());
            let mut returns = rotation.returns;
            returns.iter_mut().for_each(|r| r.position = [f32::NAN; 3]);
            given_back = Some(returns.as_ptr());
            assembler.recycle(returns);
        }
    }
    let last = assembler.finish().expect("the capture's unfinished rotation");
    assert_eq!(Some(last.returns.as_ptr()), given_back, "the last rotation not in the returns given back");
    recycled.push(last);
    assert!(fresh.len() >= 2, "the capture holds {} rotations", fresh.len());
    assert_eq!(recycled, fresh);
}

#[test]
fn vlp16_capture_matches_velodyne_decoder() {
    // One whole turn from the first packet, then the capture's unfinished one.
    check_capture("vlp16", Model::Vlp16, &[false, true]);
}

#[test]
fn hdl32e_capture_matches_velodyne_decoder() {
    // The capture covers 215 degrees: one partial rotation; position packets are skipped.
    check_capture("hdl32e", Model::Hdl32e, &[true]);
}

// ---------------------------------------------------------------------------------------------
// Packets built here.

const UPPER: u16 = 0xEEFF;
const LOWER: u16 = 0xDDFF;

/// One block: flag, azimuth (0.01°), and 32 (distance, intensity).
#[derive(Clone)]
struct Block {
    flag: u16,
    azimuth: u16,
    returns: [(u16, u8); 32],
}

fn packet(blocks: &[Block], timestamp_us: u32, return_mode: u8, product_id: u8) -> Vec<u8> {
    assert_eq!(blocks.len(), 12);
    let mut bytes = Vec::with_capacity(1206);
    for block in blocks {
        bytes.extend(block.flag.to_le_bytes());
        bytes.extend(block.azimuth.to_le_bytes());
        for (distance, intensity) in block.returns {
            bytes.extend(distance.to_le_bytes());
            bytes.push(intensity);
        }
    }
    bytes.extend(timestamp_us.to_le_bytes());
    bytes.extend([return_mode, product_id]);
    bytes
}

/// A single-return VLP-16 packet: block `i` at `azimuth + i * step`, every return at `distance`
/// with its channel as intensity.
fn vlp16_packet(azimuth: u32, step: u32, distance: u16, timestamp_us: u32) -> Vec<u8> {
    let blocks: Vec<Block> = (0..12)
        .map(|i| Block {
            flag: UPPER,
            azimuth: ((azimuth + i * step) % 36000) as u16,
            returns: std::array::from_fn(|channel| (distance, channel as u8)),
        })
        .collect();
    packet(&blocks, timestamp_us, 0x37, 0x22)
}

/// A VLP-16 spinning at about 10 Hz: packets 1.327 ms and 4.8° apart, 75 to a turn.
struct Vlp16Stream {
    first_azimuth: u32,
}

impl Vlp16Stream {
    /// 12 blocks of 110.592 us each, 0.4° apart.
    const PACKET_US: f64 = 1327.104;
    const BLOCK_STEP: u32 = 40;

    fn packet(&self, k: u32) -> (f64, Vec<u8>) {
        let azimuth = self.first_azimuth + k * 12 * Self::BLOCK_STEP;
        let timestamp = (1_000_000.0 + f64::from(k) * Self::PACKET_US).round() as u32;
        (f64::from(k) * Self::PACKET_US * 1e-6, vlp16_packet(azimuth, Self::BLOCK_STEP, 5000, timestamp))
    }
}

fn options(model: Option<Model>) -> VelodyneOptions {
    VelodyneOptions { model, ..Default::default() }
}

fn decode_one(options: VelodyneOptions, payload: &[u8]) -> Rotation {
    let mut assembler = VelodyneAssembler::new(options).unwrap();
    assert_eq!(assembler.push(payload, 7.0).unwrap(), None);
    assembler.finish().expect("the packet's returns")
}

fn close(a: f32, b: f64, tolerance: f64) -> bool {
    (f64::from(a) - b).abs() <= tolerance
}

#[test]
fn a_vlp16_packet_gives_positions_times_and_rings_of_the_manual() {
    // Block i at i * 0.40°, all returns at 10 m.
    let rotation = decode_one(options(None), &vlp16_packet(0, 40, 5000, 123_456));
    assert_eq!(rotation.returns.len(), 384);
    assert_eq!(rotation.stamp, 7.0);
    let [first, second, .., last] = rotation.returns[..] else { panic!() };
    // Laser 0: -15°, 11.23 mm above the origin, straight ahead.
    let elevation = (-15f64).to_radians();
    assert!(close(first.position[0], 10.0 * elevation.cos(), 1e-5), "{first:?}");
    assert!(close(first.position[1], 0.0, 1e-6) && close(first.position[2], 10.0 * elevation.sin() + 0.0112298, 1e-5));
    assert_eq!((first.ring, first.time, first.intensity), (0, 0.0, 0.0));
    // Laser 1 (+1°) is the ninth from the bottom, fired 2.304 us later.
    assert_eq!(second.ring, 8);
    assert!(close(second.time, 2.304e-6, 1e-9));
    // The last return: block 11, second firing sequence, laser 15 (+15°).
    assert_eq!(last.ring, 15);
    assert!(close(last.time, (11.0 * 110.592 + 55.296 + 15.0 * 2.304) * 1e-6, 1e-9));
    // The second firing sequence of block 0 is half way to block 1: 0.20°, seen as -y.
    let sequence_two = rotation.returns[16];
    let azimuth = f64::from(-sequence_two.position[1]).atan2(f64::from(sequence_two.position[0])).to_degrees();
    assert!((azimuth - 0.20).abs() < 1e-4, "{azimuth}");
}

#[test]
fn returns_outside_the_range_or_empty_are_left_out() {
    let mut blocks: Vec<Block> =
        (0..12).map(|i| Block { flag: UPPER, azimuth: 100 * i, returns: [(5000, 1); 32] }).collect();
    blocks[0].returns[0] = (0, 1); // no return
    blocks[0].returns[1] = (49, 1); // 9.8 cm, below velodyne-decoder's 0.1 m
    blocks[0].returns[2] = (50, 1); // 10 cm: kept
    let rotation = decode_one(options(None), &packet(&blocks, 0, 0x37, 0x22));
    assert_eq!(rotation.returns.len(), 382);
    let near = VelodyneOptions { max_range: 5.0, ..options(None) };
    let mut assembler = VelodyneAssembler::new(near).unwrap();
    assembler.push(&packet(&blocks, 0, 0x37, 0x22), 0.0).unwrap();
    assert_eq!(assembler.finish().map(|rotation| rotation.returns.len()), Some(1));
}

/// A dual-return VLP-16 packet: each column a last block (4 m) then a strongest block (3 m),
/// except channel 5 where both blocks hold the same echo.
fn vlp16_dual_packet() -> Vec<u8> {
    let blocks: Vec<Block> = (0..12)
        .map(|i| {
            let distance = if i % 2 == 0 { 2000 } else { 1500 };
            let mut returns = [(distance, 10); 32];
            returns[5] = (2500, 10);
            Block { flag: UPPER, azimuth: 80 * (i / 2), returns }
        })
        .collect();
    packet(&blocks, 0, 0x39, 0x22)
}

#[test]
fn dual_returns_give_the_strongest_by_default_and_the_last_on_request() {
    let distances = |choice| {
        let rotation = decode_one(VelodyneOptions { returns: choice, ..options(None) }, &vlp16_dual_packet());
        let mut distances: Vec<u32> = rotation
            .returns
            .iter()
            .map(|r| (r.position.iter().map(|c| c * c).sum::<f32>().sqrt() * 10.0).round() as u32)
            .collect();
        distances.sort_unstable();
        distances.dedup_by_key(|d| *d);
        (rotation.returns.len(), distances, rotation.returns)
    };
    // Ranges are a few mm off whole decimetres by the lasers' vertical offsets.
    let (count, first, returns) = distances(ReturnChoice::First);
    assert_eq!((count, first), (192, vec![30, 50]));
    // The two returns of one firing share its time.
    assert!(returns.iter().all(|r| r.time < 6.0 * 110.592e-6));
    let (count, second, _) = distances(ReturnChoice::Second);
    assert_eq!((count, second), (192, vec![40, 50]));
    // Both: the echo repeated in both blocks (channel 5 of each of the 6 columns) once.
    let (count, both, _) = distances(ReturnChoice::Both);
    assert_eq!((count, both), (384 - 6, vec![30, 40, 50]));
}

#[test]
fn a_single_return_stream_has_no_second_return() {
    let payload = vlp16_packet(0, 40, 5000, 0);
    let mut assembler =
        VelodyneAssembler::new(VelodyneOptions { returns: ReturnChoice::Second, ..options(None) }).unwrap();
    assert_eq!(assembler.push(&payload, 0.0).unwrap(), None);
    assert_eq!(assembler.finish(), None);
}

#[test]
fn rotations_are_cut_at_the_configured_azimuth() {
    // 75 packets per turn; the stream starts at 100° and runs 3.2 turns, cut at 0°.
    let stream = Vlp16Stream { first_azimuth: 10_000 };
    let cut = VelodyneOptions { cut_azimuth_deg: Some(0.0), ..options(Some(Model::Vlp16)) };
    let mut assembler = VelodyneAssembler::new(cut).unwrap();
    let payloads: Vec<_> = (0..240).map(|k| stream.packet(k)).collect();
    let rotations = rotations(&mut assembler, &payloads);
    let partial: Vec<bool> = rotations.iter().map(|rotation| rotation.partial).collect();
    assert_eq!(partial, [true, false, false, true]);
    assert!(rotations.iter().all(|rotation| rotation.gaps == 0), "{:?}", gaps(&rotations));
    // A whole rotation spans a turn: from just past the cut to just past it again.
    let whole = &rotations[1];
    let packets = whole.returns.len() / 384;
    assert!(packets == 75 || packets == 76, "{packets}");
    let azimuths: Vec<f64> = whole.returns.iter().map(azimuth_deg).collect();
    assert!(
        azimuths[0] < 4.8 && azimuths[azimuths.len() - 1] < 4.8,
        "{} {}",
        azimuths[0],
        azimuths[azimuths.len() - 1]
    );
    // Its times count from its first firing, one packet after another.
    assert_eq!(whole.returns[0].time, 0.0);
    let span = f64::from(whole.returns.last().unwrap().time);
    assert!((span - ((packets - 1) as f64 * 1327.104 + 11.0 * 110.592 + 55.296 + 15.0 * 2.304) * 1e-6).abs() < 2e-6);
    // Stamped with the arrival of its first packet.
    let first_packet = rotations[0].returns.len() / 384;
    assert_eq!(whole.stamp, payloads[first_packet].0);
}

/// The azimuth of a point in the packets' convention (clockwise from the front), degrees.
fn azimuth_deg(point: &Return) -> f64 {
    f64::from(-point.position[1]).atan2(f64::from(point.position[0])).to_degrees().rem_euclid(360.0)
}

fn gaps(rotations: &[Rotation]) -> Vec<usize> {
    rotations.iter().map(|rotation| rotation.gaps).collect()
}

#[test]
fn the_default_cut_makes_the_first_rotation_a_whole_turn() {
    let stream = Vlp16Stream { first_azimuth: 12_345 };
    let mut assembler = VelodyneAssembler::new(options(None)).unwrap();
    let payloads: Vec<_> = (0..160).map(|k| stream.packet(k)).collect();
    let rotations = rotations(&mut assembler, &payloads);
    let partial: Vec<bool> = rotations.iter().map(|rotation| rotation.partial).collect();
    assert_eq!(partial, [false, false, true]);
    // The first packet's last block is at the cut; the packet that passes it again ends the turn.
    assert_eq!(rotations[0].returns.len(), 76 * 384);
}

#[test]
fn lost_packets_are_counted_as_gaps() {
    let stream = Vlp16Stream { first_azimuth: 0 };
    let all: Vec<_> = (0..240).map(|k| stream.packet(k)).collect();
    let lossless = rotations(&mut VelodyneAssembler::new(options(None)).unwrap(), &all);
    assert_eq!(gaps(&lossless), [0, 0, 0, 0]);
    // Drop one packet of the second rotation, three of the third, and the first of the fourth.
    let second_start = lossless[0].returns.len() / 384;
    let third_start = second_start + lossless[1].returns.len() / 384;
    let fourth_start = third_start + lossless[2].returns.len() / 384;
    let dropped = [second_start + 10, third_start + 40, third_start + 41, third_start + 42, fourth_start];
    let lossy: Vec<_> =
        all.iter().enumerate().filter(|(k, _)| !dropped.contains(k)).map(|(_, packet)| packet.clone()).collect();
    let rotations = rotations(&mut VelodyneAssembler::new(options(None)).unwrap(), &lossy);
    assert_eq!(gaps(&rotations), [0, 1, 3, 1]);
    assert_eq!(rotations[1].returns.len(), lossless[1].returns.len() - 384);
}

#[test]
fn a_reordered_packet_stays_in_its_rotation() {
    let stream = Vlp16Stream { first_azimuth: 0 };
    let in_order: Vec<_> = (0..170).map(|k| stream.packet(k)).collect();
    let expected = rotations(&mut VelodyneAssembler::new(options(None)).unwrap(), &in_order);
    // Swap two neighbours in the second half of the first turn: nothing changes, the returns are
    // put back in firing order.
    let mut shuffled = in_order.clone();
    shuffled.swap(50, 51);
    let got = rotations(&mut VelodyneAssembler::new(options(None)).unwrap(), &shuffled);
    assert_eq!(got, expected);
    // Swap the packet that passes the cut with the next: the next one ends the rotation, the late
    // one is dropped and counted as lost; the following rotation is whole.
    let last_of_first = expected[0].returns.len() / 384 - 1;
    let mut shuffled = in_order.clone();
    shuffled.swap(last_of_first, last_of_first + 1);
    let got = rotations(&mut VelodyneAssembler::new(options(None)).unwrap(), &shuffled);
    assert_eq!(got.len(), expected.len());
    assert_eq!(gaps(&got)[..2], [1, 0]);
    assert_eq!(got[0].returns.len(), expected[0].returns.len());
    assert_eq!(got[1].returns.len(), expected[1].returns.len() - 384);
    assert!(!got[1].partial);
}

#[test]
fn a_packet_from_a_finished_rotation_is_dropped() {
    let stream = Vlp16Stream { first_azimuth: 0 };
    let mut payloads: Vec<_> = (0..100).map(|k| stream.packet(k)).collect();
    let expected = rotations(&mut VelodyneAssembler::new(options(None)).unwrap(), &payloads);
    // Packet 70 arrives after the cut, late by ten packets: it is dropped, the count remembers it.
    let late = payloads.remove(70);
    payloads.insert(80, late);
    let got = rotations(&mut VelodyneAssembler::new(options(None)).unwrap(), &payloads);
    assert_eq!(got.len(), 2);
    assert_eq!(got[0].gaps, 1);
    assert_eq!(got[1].returns, expected[1].returns);
}

#[test]
fn times_run_on_across_the_hour() {
    let first = vlp16_packet(0, 40, 5000, 3_599_999_500);
    let second = vlp16_packet(480, 40, 5000, 827);
    let mut assembler = VelodyneAssembler::new(options(None)).unwrap();
    assembler.push(&first, 0.0).unwrap();
    assembler.push(&second, 0.0013).unwrap();
    let rotation = assembler.finish().unwrap();
    assert!(close(rotation.returns[384].time, 1327e-6, 1e-9), "{:?}", rotation.returns[384]);
}

#[test]
fn factory_bytes_name_the_model() {
    let mut vlp32c = vlp16_packet(0, 40, 5000, 0);
    vlp32c[1205] = 0x28;
    let mut assembler = VelodyneAssembler::new(options(None)).unwrap();
    assembler.push(&vlp32c, 0.0).unwrap();
    assert_eq!(assembler.model(), Some(Model::Vlp32c));
    // Another model's packet in the same stream is an error for that packet only.
    let vlp16 = vlp16_packet(480, 40, 5000, 1327);
    assert!(matches!(assembler.push(&vlp16, 0.0), Err(PacketError::Invalid { .. })));
    let mut hdl32e = vlp16_packet(0, 40, 5000, 0);
    hdl32e[1205] = 0x21;
    let mut assembler = VelodyneAssembler::new(options(None)).unwrap();
    assembler.push(&hdl32e, 0.0).unwrap();
    assert_eq!(assembler.model(), Some(Model::Hdl32e));
}

#[test]
fn a_vlp32c_packet_follows_its_table() {
    let mut payload = vlp16_packet(9000, 40, 2500, 0);
    payload[1205] = 0x28;
    let rotation = decode_one(options(None), &payload);
    // Channels 0 and 1 fire together, 2 and 3 2.304 us later.
    let times: Vec<f32> = rotation.returns[..4].iter().map(|r| r.time).collect();
    assert!(close(times[1], 0.0, 1e-12) && close(times[2], 2.304e-6, 1e-9) && close(times[3], 2.304e-6, 1e-9));
    // Laser 0: -25°, its rot_correction -1.4° turns it 1.4° clockwise of the block azimuth;
    // 10 m at 4 mm per unit, its origin 19.77 mm above the sensor's.
    let first = rotation.returns[0];
    assert_eq!(first.ring, 0);
    let range = first.position.iter().map(|c| f64::from(c * c)).sum::<f64>().sqrt();
    let offset = 0.0197714;
    let expected_range = (100.0 + offset * offset + 2.0 * 10.0 * offset * (-25f64).to_radians().sin()).sqrt();
    assert!((range - expected_range).abs() < 1e-4, "{range} {expected_range}");
    assert!((azimuth_deg(&first) - (90.0 + 1.4)).abs() < 1e-3, "{}", azimuth_deg(&first));
}

// ---------------------------------------------------------------------------------------------
// HDL-64E and its calibration file.

/// A 64-laser calibration in velodyne_pointcloud's flow style: laser k at -24° + k * 0.5°.
fn hdl64_calibration_yaml() -> String {
    let mut text = String::from("lasers:\n");
    for laser in 0..64 {
        let vert = (-24.0 + 0.5 * f64::from(laser)).to_radians();
        let extra = if laser == 32 { ", vert_offset_correction: 0.2,\n  horiz_offset_correction: 0.03" } else { "" };
        text += &format!(
            "- {{dist_correction: 0.0, laser_id: {laser}, rot_correction: 0.0,\n  vert_correction: {vert}{extra}}}\n"
        );
    }
    text + "num_lasers: 64\ndistance_resolution: 0.002\n"
}

fn hdl64_options(model: Model) -> VelodyneOptions {
    let calibration = Calibration::from_yaml(&hdl64_calibration_yaml()).unwrap();
    VelodyneOptions { model: Some(model), calibration: Some(calibration), ..Default::default() }
}

/// An HDL-64E packet: upper and lower blocks in turn; `dual` repeats each azimuth four times.
fn hdl64_packet(dual: bool) -> Vec<u8> {
    let blocks: Vec<Block> = (0..12)
        .map(|i| {
            let column = if dual { i / 4 } else { i / 2 };
            // In dual mode blocks 2-3 of a column hold the last returns: 6 m, the strongest 5 m.
            let distance = if dual && (i / 2) % 2 == 1 { 3000 } else { 2500 };
            Block {
                flag: if i % 2 == 0 { UPPER } else { LOWER },
                azimuth: (1000 + 30 * column) as u16,
                returns: [(distance, 50); 32],
            }
        })
        .collect();
    packet(&blocks, 0, 0x37, 0x00)
}

#[test]
fn an_hdl64e_packet_uses_both_banks_and_the_s3_timing() {
    let rotation = decode_one(hdl64_options(Model::Hdl64eS3), &hdl64_packet(false));
    assert_eq!(rotation.returns.len(), 384);
    // Block 1 is the lower block of the first column: lasers 32-63, fired with the upper ones.
    let lower = rotation.returns[32];
    assert_eq!(lower.ring, 32);
    assert_eq!(lower.time, 0.0);
    let laser_5 = rotation.returns[5];
    assert!(close(laser_5.time, (7.2 + 1.3) * 1e-6, 1e-9));
    // Laser 32 (-8°): raised by 0.2 m and shifted 3 cm to the left of its beam (azimuth 10°).
    let (elevation, azimuth) = ((-8.0f64).to_radians(), 10f64.to_radians());
    let horizontal = 5.0 * elevation.cos();
    let expected = [
        horizontal * azimuth.cos() + 0.03 * azimuth.sin(),
        0.03 * azimuth.cos() - horizontal * azimuth.sin(),
        5.0 * elevation.sin() + 0.2,
    ];
    for (got, want) in lower.position.iter().zip(expected) {
        assert!(close(*got, want, 1e-5), "{lower:?} {expected:?}");
    }
    let s2 = decode_one(hdl64_options(Model::Hdl64eS2), &hdl64_packet(false));
    assert!(close(s2.returns[5].time, (6.0 + 1.26) * 1e-6, 1e-9));
    assert!(close(s2.returns[64].time, 48e-6, 1e-9));
}

#[test]
fn an_hdl64e_dual_packet_puts_the_strongest_first() {
    let strongest = decode_one(hdl64_options(Model::Hdl64eS3), &hdl64_packet(true));
    assert_eq!(strongest.returns.len(), 192);
    // Laser 32 has offsets; the other ranges are the packet's.
    let range = |r: &Return| r.position.iter().map(|c| c * c).sum::<f32>().sqrt();
    let plain = |rotation: &Rotation| rotation.returns.iter().filter(|r| r.ring != 32).map(range).collect::<Vec<_>>();
    assert!(plain(&strongest).iter().all(|range| (range - 5.0).abs() < 1e-5));
    // The third column fires 2 x 57.6 us after the first.
    assert!(close(strongest.returns[128].time, 115.2e-6, 1e-9));
    let last = decode_one(
        VelodyneOptions { returns: ReturnChoice::Second, ..hdl64_options(Model::Hdl64eS3) },
        &hdl64_packet(true),
    );
    assert_eq!(last.returns.len(), 192);
    assert!(plain(&last).iter().all(|range| (range - 6.0).abs() < 1e-5));
}

#[test]
fn hdl64e_packets_need_the_model_named() {
    let mut assembler = VelodyneAssembler::new(options(None)).unwrap();
    let error = assembler.push(&hdl64_packet(false), 0.0).unwrap_err();
    assert!(error.to_string().contains("HDL-64E"), "{error}");
}

#[test]
fn the_block_style_calibration_reads_like_the_flow_style() {
    let block_style = "distance_resolution: 0.002\nlasers:\n  - laser_id: 1\n    rot_correction: -0.1\n    \
                       vert_correction: 0.05\n    dist_correction: 1.2\n    dist_correction_x: 1.25\n    \
                       dist_correction_y: 1.22\n    two_pt_correction_available: true\n    focal_distance: 10.5\n    \
                       focal_slope: 1.85\n    min_intensity: 5\n  - laser_id: 0\n    rot_correction: 0.0\n    \
                       vert_correction: -0.05\nstatus:\n  RPM: 600\nnum_lasers: 2\n";
    let calibration = Calibration::from_yaml(block_style).unwrap();
    assert_eq!(calibration.lasers.len(), 2);
    let laser = &calibration.lasers[1];
    assert_eq!((laser.rot_correction, laser.dist_correction, laser.min_intensity), (-0.1, 1.2, 5.0));
    assert_eq!(laser.two_point.map(|two| (two.x, two.y)), Some((1.25, 1.22)));
    assert_eq!(calibration.rings(), [0, 1]);
}

#[test]
fn calibration_errors_name_the_field() {
    let missing = Calibration::from_yaml("lasers:\n- {laser_id: 0, rot_correction: 0.0}\n").unwrap_err();
    assert_eq!(missing, CalibrationError::Missing { line: 2, field: "vert_correction" });
    assert_eq!(missing.to_string(), "calibration line 2: missing `vert_correction`");
    let bad = Calibration::from_yaml("lasers:\n- {laser_id: 0, rot_correction: x, vert_correction: 0}\n").unwrap_err();
    assert!(bad.to_string().contains("`rot_correction` must be a finite number, found `x`"), "{bad}");
    let twice = "lasers:\n- {laser_id: 0, rot_correction: 0, vert_correction: 0}\n\
                 - {laser_id: 0, rot_correction: 0, vert_correction: 0}\n";
    assert!(Calibration::from_yaml(twice).unwrap_err().to_string().contains("laser_id 0 appears twice"));
    let count = "lasers:\n- {laser_id: 0, rot_correction: 0, vert_correction: 0}\nnum_lasers: 2\n";
    assert_eq!(Calibration::from_yaml(count).unwrap_err(), CalibrationError::NumLasers { declared: 2, listed: 1 });
    assert!(matches!(
        Calibration::from_yaml("num_lasers: 2\n"),
        Err(CalibrationError::Missing { field: "lasers", .. })
    ));
}

// ---------------------------------------------------------------------------------------------
// Payloads that are not (or no longer) packets.

#[test]
fn position_packets_are_skipped_and_other_payloads_are_errors() {
    let mut assembler = VelodyneAssembler::new(options(None)).unwrap();
    assert_eq!(assembler.push(&[0; 554], 0.0), Ok(None));
    assert_eq!(assembler.push(&[0; 512], 0.0), Ok(None));
    assert!(matches!(assembler.push(&[0; 1205], 0.0), Err(PacketError::Length { len: 1205, .. })));
    let mut flag = vlp16_packet(0, 40, 5000, 0);
    flag[300] = 0x12;
    let error = assembler.push(&flag, 0.0).unwrap_err();
    assert!(error.to_string().contains("block 3 flag"), "{error}");
    let mut mode = vlp16_packet(0, 40, 5000, 0);
    mode[1204] = 0x55;
    assert!(assembler.push(&mode, 0.0).unwrap_err().to_string().contains("return mode 0x55"));
    let mut azimuth = vlp16_packet(0, 40, 5000, 0);
    azimuth[2..4].copy_from_slice(&36000u16.to_le_bytes());
    assert!(assembler.push(&azimuth, 0.0).unwrap_err().to_string().contains("azimuth 36000"));
    let mut velarray = vlp16_packet(0, 40, 5000, 0);
    velarray[1205] = 0x31;
    assert!(assembler.push(&velarray, 0.0).unwrap_err().to_string().contains("0x31"));
    assert_eq!(assembler.finish(), None);
}

/// Random lengths and bytes, real packets with bytes flipped, and truncated real packets: each
/// payload is accepted or refused, never a panic, and what comes out is finite.
#[test]
fn random_and_damaged_payloads_never_panic() {
    let real: Vec<Vec<u8>> = ["vlp16", "hdl32e"]
        .iter()
        .flat_map(|name| udp_payloads(&testkit::shared_data(&format!("lidar_packets/{name}.pcap"))))
        .map(|(_, payload)| payload)
        .collect();
    let mut rng = Rng::new(Rng::spread(0x7e1_0d7e));
    for case in 0..256 {
        let model = [None, Some(Model::Vlp16), Some(Model::Hdl32e), Some(Model::Vlp32c)][case % 4];
        let returns = [ReturnChoice::First, ReturnChoice::Second, ReturnChoice::Both][case % 3];
        let cut_azimuth_deg = (case % 5 == 0).then(|| rng.uniform(-720.0, 720.0));
        let mut assembler =
            VelodyneAssembler::new(VelodyneOptions { model, returns, cut_azimuth_deg, ..Default::default() }).unwrap();
        let mut outputs = Vec::new();
        for step in 0..40 {
            let payload = damaged_payload(&mut rng, &real);
            match assembler.push(&payload, step as f64 * 1e-3 + rng.uniform(-0.5, 0.5)) {
                Ok(rotation) => outputs.extend(rotation),
                Err(PacketError::Length { .. } | PacketError::Invalid { .. }) => {}
            }
        }
        outputs.extend(assembler.finish());
        for rotation in &outputs {
            assert!(rotation.returns.iter().all(|r| r.position.iter().all(|c| c.is_finite()) && r.time.is_finite()));
            assert!(rotation.returns.iter().all(|r| usize::from(r.ring) < 32 && r.time >= 0.0));
        }
    }
}

fn damaged_payload(rng: &mut Rng, real: &[Vec<u8>]) -> Vec<u8> {
    let original = &real[rng.below(real.len())];
    match rng.below(4) {
        0 => (0..rng.below(1400)).map(|_| rng.below(256) as u8).collect(),
        1 => (0..1206).map(|_| rng.below(256) as u8).collect(),
        2 => {
            let mut flipped = original.clone();
            for _ in 0..=rng.below(8) {
                let at = rng.below(flipped.len());
                flipped[at] ^= 1 << rng.below(8);
            }
            flipped
        }
        _ => original[..rng.below(original.len() + 1)].to_vec(),
    }
}
