//! The packet encoders against the simulator's own truth: exact packet structure (sizes, counts,
//! flags, azimuths, timestamps, column headers, metadata), and points rebuilt from the packets with
//! the vendors' published equations equal to the simulated cloud. Then the capture writer and the
//! UDP sender carry the same bytes.

use std::collections::BTreeMap;
use std::f64::consts::TAU;
use std::net::UdpSocket;
use std::time::Duration;

use nalgebra::{Matrix4, Point3, Vector4};
use pcap_file::pcap::PcapReader;
use serde_json::Value;
use sim::packets::pcap::{CaptureWriter, Network};
use sim::packets::udp::{Pace, SendError, UdpSender};
use sim::packets::{Encoder, Packet, PacketFormat, SensorClock, ouster, reflectivity_of, velodyne};
use sim::{RangeImage, Scan, Scenario, SensorModel, SimConfig, Simulator};

const SEED: u64 = 11;

fn simulator(sensor: SensorModel) -> Simulator {
    let config = SimConfig { seed: SEED, sensor, ..SimConfig::default() };
    Simulator::new(Scenario::by_name("warehouse-small").unwrap(), 0, config).unwrap()
}

fn u16_at(bytes: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([bytes[at], bytes[at + 1]])
}

fn u32_at(bytes: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap())
}

fn u64_at(bytes: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap())
}

/// Asserts that points keyed by (column, ring) are the cloud's, one for one, within `tolerance`
/// metres; returns the largest error.
fn assert_points_match(
    decoded: &BTreeMap<(usize, u16), Point3<f64>>,
    scan: &Scan,
    columns: usize,
    tolerance: f64,
) -> f64 {
    let cloud = &scan.cloud;
    let rings = cloud.ring.as_ref().unwrap();
    let times = cloud.time.as_ref().unwrap();
    assert_eq!(decoded.len(), cloud.len(), "one decoded point per simulated point");
    let mut worst = 0.0f64;
    for ((point, &ring), &time) in cloud.points.iter().zip(rings).zip(times) {
        let column = (f64::from(time) / 0.1 * columns as f64).round() as usize;
        let got = decoded.get(&(column, ring)).unwrap_or_else(|| panic!("no point for column {column} ring {ring}"));
        let error = (got - point.cast::<f64>()).norm();
        assert!(error <= tolerance, "column {column} ring {ring}: {got} vs {point}, {error} m");
        worst = worst.max(error);
    }
    worst
}

#[test]
fn the_range_image_is_the_scan_before_its_points() {
    let sim = simulator(SensorModel::vlp16());
    let (scan, image) = sim.scan_and_range_image(3);
    assert_eq!(scan, sim.scan(3), "one cast gives the same sweep");
    assert_eq!(image, sim.range_image(3));
    let sensor = &sim.config().sensor;
    assert_eq!((image.columns(), image.beams, image.frame, image.stamp), (1800, 16, 3, scan.stamp));
    assert_eq!(image.returns(), scan.cloud.len());
    let mut points = scan.cloud.points.iter();
    for column in 0..image.columns() {
        assert_eq!(image.column_times[column], sensor.firing_time(column));
        for beam in 0..image.beams {
            let Some(cell) = image.get(column, beam) else { continue };
            let p = sensor.direction(beam, column) * cell.range;
            assert_eq!(points.next().unwrap(), &Point3::new(p.x as f32, p.y as f32, p.z as f32));
        }
    }
    assert_eq!(image.get(0, 16), None, "no beam 16");
}

/// The points of VLP-16 packets by the manual's equations (x right, y forward), turned into the sim's
/// frame (x forward, y left), keyed by (column, ring); each block's second sequence at the
/// azimuth half-way to the next block.
fn velodyne_points(packets: &[Packet], columns: usize) -> BTreeMap<(usize, u16), Point3<f64>> {
    let mut points = BTreeMap::new();
    for (p, packet) in packets.iter().enumerate() {
        for block in 0..velodyne::BLOCKS {
            let bytes = &packet.payload[block * velodyne::BLOCK_BYTES..][..velodyne::BLOCK_BYTES];
            let azimuth = f64::from(u16_at(bytes, 2)) / 100.0;
            for sequence in 0..2 {
                let column = p * 24 + block * 2 + sequence;
                let alpha = (azimuth + sequence as f64 * 360.0 / columns as f64).to_radians();
                for laser in 0..16 {
                    let at = 4 + (sequence * 16 + laser) * 3;
                    let distance = f64::from(u16_at(bytes, at)) * velodyne::DISTANCE_UNIT_M;
                    if distance == 0.0 {
                        continue;
                    }
                    let omega = velodyne::laser_elevation_deg(laser).to_radians();
                    let (x_right, y_forward, z) = (
                        distance * omega.cos() * alpha.sin(),
                        distance * omega.cos() * alpha.cos(),
                        distance * omega.sin(),
                    );
                    let ring = ((velodyne::laser_elevation_deg(laser) + 15.0) / 2.0) as u16;
                    points.insert((column, ring), Point3::new(y_forward, -x_right, z));
                }
            }
        }
    }
    points
}

#[test]
fn vlp16_packets_are_the_sensors_layout_and_hold_the_sims_points() {
    let sim = simulator(SensorModel::vlp16());
    let clock = SensorClock::default();
    let encoder = Encoder::new(PacketFormat::Vlp16, &sim.config().sensor, clock).unwrap();
    let (scan, image) = sim.scan_and_range_image(5);
    let packets = encoder.encode(&image).unwrap();
    assert_eq!(packets.len(), 75, "1800 firing sequences, 24 per packet");
    assert_eq!(encoder.packets_per_sweep(), 75);
    assert_eq!(encoder.metadata_json(), None);

    let mut azimuths = Vec::new();
    for (p, packet) in packets.iter().enumerate() {
        let bytes = &packet.payload;
        assert_eq!((bytes.len(), packet.port), (1206, 2368));
        assert_eq!(&bytes[1204..], &[0x37, 0x22], "strongest return, VLP-16");
        for block in 0..12 {
            assert_eq!(&bytes[block * 100..block * 100 + 2], &[0xFF, 0xEE], "packet {p} block {block} flag");
            azimuths.push(u16_at(bytes, block * 100 + 2));
        }
        let first_firing = image.stamp + image.column_times[p * 24];
        let expected_micros = clock.ns(first_firing) / 1_000 % 3_600_000_000;
        assert_eq!(u64::from(u32_at(bytes, 1200)), expected_micros, "packet {p} timestamp");
        let column_ns = 0.1 / 1800.0 * 1e9;
        let late = (packet.sent_ns - clock.ns(first_firing)) as f64 - 24.0 * column_ns;
        assert!(late.abs() <= 2.0, "packet {p} sent {late} ns off the end of its last firing");
    }
    // Clockwise from behind: 180.00° and 0.40° more per block, wrapping once, when facing forward.
    assert_eq!(azimuths[0], 18_000);
    let steps: Vec<u32> = azimuths.windows(2).map(|w| (u32::from(w[1]) + 36_000 - u32::from(w[0])) % 36_000).collect();
    assert!(steps.iter().all(|&s| s == 40), "every block 0.4° on");
    assert_eq!(azimuths.windows(2).filter(|w| w[1] < w[0]).count(), 1, "one wrap per sweep");
    assert_eq!(azimuths[450], 0, "block 450 holds column 900, which faces forward");
    assert!(packets.windows(2).all(|w| w[1].sent_ns > w[0].sent_ns));

    // Distances within half a 2 mm step, reflectivity on the 0-100 scale, returns where the sim has them.
    let vlp = sim::packets::Vlp16Encoder::new(&sim.config().sensor, clock).unwrap();
    let mut returns = 0;
    for (p, packet) in packets.iter().enumerate() {
        for block in 0..12 {
            for sequence in 0..2 {
                let column = p * 24 + block * 2 + sequence;
                for laser in 0..16 {
                    let at = block * 100 + 4 + (sequence * 16 + laser) * 3;
                    let (distance, reflectivity) = (u16_at(&packet.payload, at), packet.payload[at + 2]);
                    let cell = image.get(column, vlp.beam_of_laser(laser).unwrap());
                    match cell {
                        Some(cell) => {
                            returns += 1;
                            assert!((f64::from(distance) * 0.002 - cell.range).abs() <= 0.001 + 1e-9);
                            assert_eq!(reflectivity, reflectivity_of(cell.intensity));
                        }
                        None => assert_eq!((distance, reflectivity), (0, 0)),
                    }
                }
            }
        }
    }
    assert_eq!(returns, scan.cloud.len());
    // The manual's equations give back the sim's points, to the distance step (1 mm) and f32.
    let worst = assert_points_match(&velodyne_points(&packets, 1800), &scan, 1800, 0.001 + 1e-5);
    assert!(worst > 0.0);
}

/// The points of Ouster LEGACY packets by the manual's equations and the metadata's transform,
/// keyed by (measurement id, sim ring).
fn ouster_points(packets: &[Packet], metadata: &Value, beams: usize) -> BTreeMap<(usize, u16), Point3<f64>> {
    let numbers =
        |key: &str| -> Vec<f64> { metadata[key].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect() };
    let altitudes = numbers("beam_altitude_angles");
    let azimuths = numbers("beam_azimuth_angles");
    let n = metadata["lidar_origin_to_beam_origin_mm"].as_f64().unwrap();
    let transform = Matrix4::from_row_slice(&numbers("lidar_to_sensor_transform"));
    let width = metadata["data_format"]["columns_per_frame"].as_u64().unwrap() as f64;
    let column_bytes = ouster::column_bytes(beams);
    let mut points = BTreeMap::new();
    for packet in packets {
        for column in packet.payload.chunks_exact(column_bytes) {
            let measurement_id = u16_at(column, 8);
            let theta_encoder = TAU * (1.0 - f64::from(measurement_id) / width);
            for pixel in 0..beams {
                let range = f64::from(u32_at(column, 16 + pixel * 12) & 0xF_FFFF);
                if range == 0.0 {
                    continue;
                }
                let theta_azimuth = -TAU * azimuths[pixel] / 360.0;
                let phi = TAU * altitudes[pixel] / 360.0;
                let lidar = Vector4::new(
                    (range - n) * (theta_encoder + theta_azimuth).cos() * phi.cos() + n * theta_encoder.cos(),
                    (range - n) * (theta_encoder + theta_azimuth).sin() * phi.cos() + n * theta_encoder.sin(),
                    (range - n) * phi.sin(),
                    1.0,
                );
                let sensor = transform * lidar / 1000.0;
                let ring = (beams - 1 - pixel) as u16;
                points.insert((usize::from(measurement_id), ring), Point3::new(sensor.x, sensor.y, sensor.z));
            }
        }
    }
    points
}

#[test]
fn ouster_packets_are_legacy_columns_and_hold_the_sims_points() {
    let sim = simulator(SensorModel::ouster(64));
    let clock = SensorClock { epoch_ns: 1_650_000_000_123_456_789 };
    let encoder = Encoder::new(PacketFormat::OusterLegacy, &sim.config().sensor, clock).unwrap();
    let (scan, image) = sim.scan_and_range_image(70_000);
    let packets = encoder.encode(&image).unwrap();
    assert_eq!(packets.len(), 64, "1024 columns, 16 per packet");

    let column_bytes = 16 + 64 * 12 + 4;
    let mut next_id = 0u16;
    let mut returns = 0;
    for packet in &packets {
        assert_eq!((packet.payload.len(), packet.port), (16 * column_bytes, 7502));
        assert_eq!(packet.payload.len(), 12_608);
        for column in packet.payload.chunks_exact(column_bytes) {
            let id = usize::from(next_id);
            assert_eq!(u64_at(column, 0), clock.ns(image.stamp + image.column_times[id]), "column {id} timestamp");
            assert_eq!(u16_at(column, 8), next_id, "measurement ids count the columns");
            assert_eq!(u16_at(column, 10), (70_000 % 65_536) as u16, "frame id wraps at 2^16");
            assert_eq!(u32_at(column, 12), 88 * u32::from(next_id), "88 encoder ticks per column at 1024");
            assert_eq!(u32_at(column, column_bytes - 4), 0xFFFF_FFFF, "status of a valid column");
            for pixel in 0..64 {
                let at = 16 + pixel * 12;
                let range_mm = u32_at(column, at);
                match image.get(id, 63 - pixel) {
                    Some(cell) => {
                        returns += 1;
                        assert!((f64::from(range_mm) / 1000.0 - cell.range).abs() <= 0.0005 + 1e-9);
                        assert_eq!(u16_at(column, at + 4), u16::from(reflectivity_of(cell.intensity)));
                    }
                    None => assert_eq!((range_mm, u16_at(column, at + 4), u16_at(column, at + 6)), (0, 0, 0)),
                }
            }
            next_id += 1;
        }
    }
    assert_eq!(next_id, 1024);
    assert_eq!(returns, scan.cloud.len());
    // A packet every 16 columns of 97.66 µs (1.5625 ms); the last leaves when the sweep ends.
    assert!(packets.windows(2).all(|w| (w[1].sent_ns - w[0].sent_ns).abs_diff(1_562_500) <= 1));
    assert_eq!(packets.last().unwrap().sent_ns, clock.ns(image.stamp + 0.1));

    let metadata: Value = serde_json::from_str(&encoder.metadata_json().unwrap()).unwrap();
    let worst = assert_points_match(&ouster_points(&packets, &metadata, 64), &scan, 1024, 0.0005 + 1e-5);
    assert!(worst > 0.0);
}

#[test]
fn ouster_metadata_describes_the_packets() {
    let sensor = SensorModel::ouster(64);
    let encoder = Encoder::new(PacketFormat::OusterLegacy, &sensor, SensorClock::default()).unwrap();
    let metadata: Value = serde_json::from_str(&encoder.metadata_json().unwrap()).unwrap();
    assert_eq!(metadata["prod_line"], "OS-0-64");
    assert_eq!(metadata["lidar_mode"], "1024x10");
    assert_eq!(metadata["udp_port_lidar"], 7502);
    assert_eq!(metadata["lidar_origin_to_beam_origin_mm"], 0.0);
    let altitudes = metadata["beam_altitude_angles"].as_array().unwrap();
    assert_eq!(altitudes.len(), 64);
    assert_eq!(altitudes[0].as_f64().unwrap(), 45.0, "the highest beam first");
    assert_eq!(altitudes[63].as_f64().unwrap(), -45.0);
    for (pixel, altitude) in altitudes.iter().enumerate() {
        // serde_json parses to within an ulp.
        assert!((altitude.as_f64().unwrap() - sensor.elevations[63 - pixel].to_degrees()).abs() < 1e-12);
    }
    assert!(metadata["beam_azimuth_angles"].as_array().unwrap().iter().all(|a| a.as_f64() == Some(0.0)));
    let transform: Vec<f64> =
        metadata["lidar_to_sensor_transform"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    assert_eq!(transform, [-1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
    let format = &metadata["data_format"];
    assert_eq!(format["pixels_per_column"], 64);
    assert_eq!(format["columns_per_packet"], 16);
    assert_eq!(format["columns_per_frame"], 1024);
    assert_eq!(format["column_window"], serde_json::json!([0, 1023]));
    assert_eq!(format["pixel_shift_by_row"], serde_json::json!(vec![0; 64]));
    assert_eq!(format["udp_profile_lidar"], "LEGACY");
}

#[test]
fn sensors_without_a_packet_format_are_refused() {
    let clock = SensorClock::default();
    assert!(Encoder::new(PacketFormat::Vlp16, &SensorModel::ouster(64), clock).is_err());
    assert!(Encoder::new(PacketFormat::Vlp16, &SensorModel::hdl64(), clock).is_err());
    let encoder = Encoder::new(PacketFormat::Vlp16, &SensorModel::vlp16(), clock).unwrap();
    let wrong: RangeImage = simulator(SensorModel::ouster(16)).range_image(0);
    assert!(encoder.encode(&wrong).is_err(), "a range image of another sensor");
}

/// The frames of a capture: (timestamp ns, bytes).
fn read_capture(bytes: &[u8]) -> Vec<(u128, Vec<u8>)> {
    let mut reader = PcapReader::new(bytes).unwrap();
    assert_eq!(reader.header().datalink, pcap_file::DataLink::ETHERNET);
    let mut frames = Vec::new();
    while let Some(packet) = reader.next_packet() {
        let packet = packet.unwrap();
        frames.push((packet.timestamp.as_nanos(), packet.data.into_owned()));
    }
    frames
}

/// The UDP payloads of a capture's frames, fragments put back together by identification.
fn udp_payloads(frames: &[(u128, Vec<u8>)]) -> Vec<(u128, u16, Vec<u8>)> {
    let mut datagrams = Vec::new();
    let mut partial: Vec<u8> = Vec::new();
    for (time, frame) in frames {
        assert_eq!(&frame[12..14], &[0x08, 0x00], "IPv4");
        let ip = &frame[14..];
        assert_eq!(&ip[12..20], &[192, 168, 1, 201, 192, 168, 1, 100]);
        assert_eq!(ip[9], 17, "UDP");
        let flags = u16::from_be_bytes([ip[6], ip[7]]);
        let offset = usize::from(flags & 0x1FFF) * 8;
        assert_eq!(offset, partial.len(), "fragments in order");
        partial.extend_from_slice(&ip[20..usize::from(u16::from_be_bytes([ip[2], ip[3]]))]);
        if flags & 0x2000 == 0 {
            let udp = std::mem::take(&mut partial);
            let port = u16::from_be_bytes([udp[2], udp[3]]);
            assert_eq!(usize::from(u16::from_be_bytes([udp[4], udp[5]])), udp.len(), "UDP length");
            datagrams.push((*time, port, udp[8..].to_vec()));
        }
    }
    assert!(partial.is_empty());
    datagrams
}

#[test]
fn captures_hold_the_packets_at_their_send_times() {
    for (sensor, format, frames_per_packet) in
        [(SensorModel::vlp16(), PacketFormat::Vlp16, 1), (SensorModel::ouster(64), PacketFormat::OusterLegacy, 9)]
    {
        let sim = simulator(sensor);
        let encoder = Encoder::new(format, &sim.config().sensor, SensorClock::default()).unwrap();
        let packets: Vec<Packet> = (0..2).flat_map(|f| encoder.encode(&sim.range_image(f)).unwrap()).collect();
        let mut writer = CaptureWriter::new(Vec::new(), "memory.pcap".as_ref(), Network::default()).unwrap();
        writer.write_all(&packets).unwrap();
        assert_eq!(writer.frames(), packets.len() * frames_per_packet);
        let bytes = writer.finish().unwrap();
        assert_eq!(&bytes[..4], &[0xD4, 0xC3, 0xB2, 0xA1], "little-endian microsecond pcap");
        let datagrams = udp_payloads(&read_capture(&bytes));
        assert_eq!(datagrams.len(), packets.len());
        for ((time, port, payload), packet) in datagrams.iter().zip(&packets) {
            assert_eq!(*time, u128::from(packet.sent_ns / 1_000 * 1_000), "microsecond stamps");
            assert_eq!((*port, payload), (format.port(), &packet.payload));
        }
    }
}

#[test]
fn udp_sends_every_packet_to_loopback_in_order() {
    let receiver = UdpSocket::bind("127.0.0.1:0").unwrap();
    receiver.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let sim = simulator(SensorModel::vlp16());
    let encoder = Encoder::new(PacketFormat::Vlp16, &sim.config().sensor, SensorClock::default()).unwrap();
    let packets = encoder.encode(&sim.range_image(1)).unwrap();
    let mut sender = UdpSender::new(receiver.local_addr().unwrap(), Pace::Realtime).unwrap();
    let sending = std::thread::spawn(move || sender.send_all(&packets).map(|()| (sender.sent(), packets)));
    let mut received = Vec::new();
    let mut buffer = [0u8; 2048];
    for _ in 0..75 {
        let len = receiver.recv(&mut buffer).unwrap();
        received.push(buffer[..len].to_vec());
    }
    let (sent, packets) = sending.join().unwrap().unwrap();
    assert_eq!(sent, 75);
    assert!(received.iter().zip(&packets).all(|(r, p)| r == &p.payload));
    let refused = UdpSender::new("10.0.0.1:2368".parse().unwrap(), Pace::Max);
    assert!(matches!(refused, Err(SendError::NotLoopback { .. })));
}

#[test]
fn the_vlp16_calibration_is_the_simulated_geometry() {
    let encoder = Encoder::new(PacketFormat::Vlp16, &SensorModel::vlp16(), SensorClock::default()).unwrap();
    let yaml = encoder.calibration_yaml().unwrap();
    let lasers: Vec<&str> = yaml.lines().filter(|l| l.starts_with("- {")).collect();
    assert_eq!(lasers.len(), 16);
    for (laser, line) in lasers.iter().enumerate() {
        assert!(line.contains(&format!("laser_id: {laser},")), "{line}");
        assert!(line.contains("vert_offset_correction: 0.0}"), "no vertical offset: {line}");
        let vert = line.split("vert_correction: ").nth(1).unwrap().split(',').next().unwrap();
        assert_eq!(vert.parse::<f64>().unwrap(), velodyne::laser_elevation_deg(laser).to_radians());
    }
    assert!(yaml.contains("num_lasers: 16\n") && yaml.contains("distance_resolution: 0.002\n"));
    let ouster = Encoder::new(PacketFormat::OusterLegacy, &SensorModel::ouster(64), SensorClock::default()).unwrap();
    assert_eq!(ouster.calibration_yaml(), None);
}
