//! The simulator's packets through the robot side's decoders, against the simulator's exact truth:
//! decoded straight from the encoder, read back from a pcap capture through
//! `edge::recording::open`, and received live over UDP on 127.0.0.1.
//!
//! Every decoded return is matched to the simulated point it came from (sweep, column, ring) and
//! must lie within the packet format's quantisation of it: 1 mm of range for the VLP-16 (2 mm
//! steps) plus the angle the head turns during the VLP-16's per-laser firing stagger, which the
//! decoder models and the simulator (all beams of a column at once) does not; 0.5 mm for the Ouster.
//! Every simulated point of the covered sweeps must be decoded, once.

use std::collections::{HashMap, HashSet};
use std::f64::consts::{PI, TAU};
use std::path::Path;
use std::time::Duration;

use cloud::PointCloud;
use edge::live_sensor::LiveSensor;
use edge::packets::{Assembler, Rotation};
use edge::recording::{PacketOptions, RecordingOptions, assembler_for, rotation_cloud};
use nalgebra::Point3;
use sim::packets::pcap::{CaptureWriter, Network};
use sim::packets::udp::{Pace, UdpSender};
use sim::packets::{Encoder, Packet, PacketFormat, SensorClock};
use sim::{Scan, Scenario, SensorModel, SimConfig, Simulator};

const SEED: u64 = 23;
/// Sweeps streamed per test.
const SWEEPS: usize = 4;
/// First sweep streamed: the robot is moving by then, so the sweeps are skewed.
const FIRST_FRAME: usize = 20;

/// VLP-16 timing (User Manual, 9.4): lasers fire 2.304 µs apart, a block's two sequences span
/// 110.592 µs.
const VLP16_LASER_US: f64 = 2.304;
const VLP16_BLOCK_US: f64 = 110.592;

/// One sensor's run: the simulated sweeps and their packets.
struct Run {
    format: PacketFormat,
    sensor: SensorModel,
    scans: Vec<Scan>,
    packets: Vec<Packet>,
    metadata: Option<String>,
    calibration: Option<String>,
}

impl Run {
    fn new(sensor: SensorModel, format: PacketFormat) -> Run {
        let config = SimConfig { seed: SEED, sensor: sensor.clone(), ..SimConfig::default() };
        let sim = Simulator::new(Scenario::by_name("warehouse-small").unwrap(), 0, config).unwrap();
        let encoder = Encoder::new(format, &sensor, SensorClock::default()).unwrap();
        let mut scans = Vec::new();
        let mut packets = Vec::new();
        for frame in FIRST_FRAME..FIRST_FRAME + SWEEPS {
            let (scan, image) = sim.scan_and_range_image(frame);
            packets.extend(encoder.encode(&image).unwrap());
            scans.push(scan);
        }
        Run {
            format,
            sensor,
            scans,
            packets,
            metadata: encoder.metadata_json(),
            calibration: encoder.calibration_yaml(),
        }
    }

    /// Decoding options: the simulated sensor's description written into `dir`, the Ouster's
    /// metadata or the VLP-16's calibration (no per-laser vertical offsets).
    fn options(&self, dir: &Path) -> PacketOptions {
        let write = |name: &str, text: &String| {
            let path = dir.join(format!("{}-{name}", self.sensor.name));
            std::fs::write(&path, text).unwrap();
            path
        };
        PacketOptions {
            metadata: self.metadata.as_ref().map(|json| write("metadata.json", json)),
            calibration: self.calibration.as_ref().map(|yaml| write("calibration.yaml", yaml)),
            ..PacketOptions::default()
        }
    }

    /// Every packet through a fresh assembler, then its end: all the rotations.
    fn decode(&self, assembler: &mut dyn Assembler) -> Vec<Rotation> {
        let mut rotations = Vec::new();
        for packet in &self.packets {
            let received = packet.sent_ns as f64 * 1e-9;
            if let Some(rotation) = assembler.push(&packet.payload, received).unwrap() {
                rotations.push(rotation);
            }
        }
        rotations.extend(assembler.finish());
        rotations
    }

    /// The simulated points by (sweep, column, sim ring): position and time from the sweep start.
    fn truth(&self) -> HashMap<(usize, usize, u16), (Point3<f64>, f64)> {
        let mut truth = HashMap::new();
        for (sweep, scan) in self.scans.iter().enumerate() {
            let cloud = &scan.cloud;
            for ((p, &ring), &time) in
                cloud.points.iter().zip(cloud.ring.as_ref().unwrap()).zip(cloud.time.as_ref().unwrap())
            {
                let column = (f64::from(time) / self.sensor.period * self.sensor.columns as f64).round() as usize;
                truth.insert((sweep, column, ring), (p.cast::<f64>(), f64::from(time)));
            }
        }
        truth
    }

    /// The sim column whose azimuth a decoded point lies at. A VLP-16 return lies up to 0.135° past
    /// its column's azimuth in the direction the head turns (its laser fired later), never before:
    /// the column is the one at or just before the point, with a margin for rounding.
    fn column_of(&self, p: &Point3<f64>) -> usize {
        let columns = self.sensor.columns as f64;
        let turned = ((PI - p.y.atan2(p.x)) / TAU * columns).rem_euclid(columns);
        let column = match self.format {
            PacketFormat::Vlp16 => (turned + 0.1).floor(),
            PacketFormat::OusterLegacy => turned.round(),
        };
        column as usize % self.sensor.columns
    }

    /// The sim ring of a decoded ring: the VLP-16's rings are the sim's, an Ouster's count from
    /// its highest beam.
    fn sim_ring(&self, ring: u16) -> u16 {
        match self.format {
            PacketFormat::Vlp16 => ring,
            PacketFormat::OusterLegacy => (self.sensor.beams() - 1) as u16 - ring,
        }
    }
}

/// The largest errors of a comparison.
#[derive(Debug, Default)]
struct Errors {
    /// Between decoded and simulated points, metres.
    position: f64,
    /// Of the range, metres.
    range: f64,
    /// Between decoded points turned back by their laser's firing stagger and simulated points,
    /// metres: what is left once the stagger the simulator does not model is taken out.
    unstaggered: f64,
    /// Of times relative to the rotation's first return, seconds.
    time: f64,
    /// Points compared.
    points: usize,
}

/// The VLP-16 User Manual's vertical correction of each laser id (Table 9-1), millimetres: how
/// far above the origin its beam leaves. Decoders apply it by default; the simulator has none.
const VLP16_VERTICAL_CORRECTION_MM: [f64; 16] =
    [11.2, -0.7, 9.7, -2.2, 8.1, -3.7, 6.6, -5.1, 5.1, -6.6, 3.7, -8.1, 2.2, -9.7, 0.7, -11.2];

/// The laser id of a VLP-16 ring: lasers interleave in elevation (−15°, +1°, −13°, +3°, ...).
fn vlp16_laser(ring: u16) -> usize {
    usize::from(if ring < 8 { 2 * ring } else { 2 * ring - 15 })
}

/// How the decoder was set up for a VLP-16.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Geometry {
    /// With the simulated sensor's description: the decoded points are the simulated ones.
    Simulated,
    /// With a real VLP-16's published table: each point raised by its laser's vertical correction
    /// (the manual gives it to 0.1 mm).
    Published,
}

/// A decoded point's allowed distance from the simulated one: the range step, and for the VLP-16
/// the turn of the head between its column's azimuth and its laser's firing (as decoders
/// interpolate it from the block azimuths, rounded to 0.01°).
fn position_tolerance(run: &Run, ring: u16, truth: &Point3<f64>) -> f64 {
    match run.format {
        PacketFormat::Vlp16 => {
            let stagger_deg = stagger_deg(ring) + AZIMUTH_ROUNDING_DEG;
            0.001 + 1e-4 + truth.xy().coords.norm() * stagger_deg.to_radians()
        }
        PacketFormat::OusterLegacy => 0.0005 + 1e-5,
    }
}

/// Decoders round each firing's interpolated azimuth to the packets' 0.01°.
const AZIMUTH_ROUNDING_DEG: f64 = 0.0051;

/// How far the head turns (clockwise, degrees) between a block's azimuth and the firing of the
/// laser of `ring` in its first sequence: 0.4° a block at the sim's 1800 columns per turn.
fn stagger_deg(ring: u16) -> f64 {
    0.4 * VLP16_LASER_US * vlp16_laser(ring) as f64 / VLP16_BLOCK_US
}

/// A decoded VLP-16 point turned back (counter-clockwise) by its laser's stagger, with the
/// distance that leaves to the simulated point allowed: the range step and the azimuth rounding.
fn unstaggered(ring: u16, p: &Point3<f64>, truth: &Point3<f64>) -> (Point3<f64>, f64) {
    let back = nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::z_axis(), stagger_deg(ring).to_radians());
    (back * p, 0.001 + 1e-4 + truth.xy().coords.norm() * AZIMUTH_ROUNDING_DEG.to_radians())
}

/// Decoded times may differ from the simulated ones (relative to the rotation's first return) by
/// the VLP-16's laser stagger and its 55.296 µs sequences against the sim's 55.56 µs columns, on
/// both ends of the difference; Ouster columns carry exact timestamps.
fn time_tolerance(run: &Run) -> f64 {
    match run.format {
        PacketFormat::Vlp16 => 2.0 * (15.0 * VLP16_LASER_US + 23.0 * 0.26 + 1.0) * 1e-6,
        PacketFormat::OusterLegacy => 1e-6,
    }
}

/// Matches every decoded return, rotation after rotation, to the simulated point it came from and
/// checks it; then checks that every simulated point between the first and the last matched one
/// was decoded. Returns the errors and the (sweep, column) span covered.
fn compare(run: &Run, rotations: &[PointCloud], geometry: Geometry) -> (Errors, (usize, usize), (usize, usize)) {
    let truth = run.truth();
    let mut errors = Errors::default();
    let mut matched = HashSet::new();
    // Columns only grow through the stream; a smaller one means the next sweep has begun.
    let (mut sweep, mut last_column) = (0usize, 0usize);
    for (r, cloud) in rotations.iter().enumerate() {
        let rings = cloud.ring.as_ref().expect("rings");
        let times = cloud.time.as_ref().expect("times");
        let mut first: Option<(f64, f64)> = None;
        for ((p, &ring), &time) in cloud.points.iter().zip(rings).zip(times) {
            let p = p.cast::<f64>();
            let column = run.column_of(&p);
            if column < last_column {
                sweep += 1;
            }
            last_column = column;
            let key = (sweep, column, run.sim_ring(ring));
            let Some(&(expected, sim_time)) = truth.get(&key) else {
                panic!("rotation {r}: {p} (ring {ring}) has no simulated point at sweep/column/ring {key:?}");
            };
            check_position(run, geometry, key, &p, &expected, &mut errors);
            // Times count from the rotation's first firing: compare them from its first return.
            let absolute = sweep as f64 * run.sensor.period + sim_time;
            let (first_decoded, first_sim) = *first.get_or_insert((f64::from(time), absolute));
            let time_error = ((f64::from(time) - first_decoded) - (absolute - first_sim)).abs();
            assert!(time_error <= time_tolerance(run), "rotation {r} {key:?}: time off by {time_error} s");
            errors.time = errors.time.max(time_error);
            assert!(matched.insert(key), "{key:?} decoded twice");
            errors.points += 1;
        }
    }
    let start = matched.iter().map(|&(s, c, _)| (s, c)).min().expect("points decoded");
    let end = matched.iter().map(|&(s, c, _)| (s, c)).max().unwrap();
    let lost =
        truth.keys().filter(|&&(s, c, r)| (start..=end).contains(&(s, c)) && !matched.contains(&(s, c, r))).count();
    assert_eq!(lost, 0, "simulated points between {start:?} and {end:?} not decoded");
    (errors, start, end)
}

/// Checks a decoded point against the simulated one (raised by its laser's published vertical
/// correction where the decoder applied the published table), and for the VLP-16 once more with
/// the laser's firing stagger taken out.
fn check_position(
    run: &Run,
    geometry: Geometry,
    key: (usize, usize, u16),
    p: &Point3<f64>,
    truth: &Point3<f64>,
    errors: &mut Errors,
) {
    let ring = key.2;
    let (mut expected, mut slack) = (*truth, 0.0);
    if geometry == Geometry::Published {
        expected.z += VLP16_VERTICAL_CORRECTION_MM[vlp16_laser(ring)] * 1e-3;
        // The manual gives the corrections to 0.1 mm.
        slack = 0.05e-3;
    }
    let error = (p - expected).norm();
    let tolerance = position_tolerance(run, ring, &expected) + slack;
    assert!(error <= tolerance, "{key:?}: {p} vs {expected}: {error} m > {tolerance} m");
    errors.position = errors.position.max(error);
    errors.range = errors.range.max((p.coords.norm() - expected.coords.norm()).abs());
    if run.format == PacketFormat::Vlp16 {
        let (turned, allowed) = unstaggered(ring, p, &expected);
        let left = (turned - expected).norm();
        assert!(left <= allowed + slack, "{key:?}: {left} m from the simulated point once unstaggered");
        errors.unstaggered = errors.unstaggered.max(left);
    }
}

/// All simulated points of all sweeps, in the first sweep's first column to the last's last.
fn assert_everything_decoded(run: &Run, start: (usize, usize), end: (usize, usize), errors: &Errors) {
    let total: usize = run.scans.iter().map(|s| s.cloud.len()).sum();
    assert_eq!(errors.points, total, "every simulated point decoded once");
    assert_eq!(start.0, 0);
    assert_eq!(end.0, SWEEPS - 1);
}

fn runs() -> [Run; 2] {
    [Run::new(SensorModel::vlp16(), PacketFormat::Vlp16), Run::new(SensorModel::ouster(64), PacketFormat::OusterLegacy)]
}

#[test]
fn decoded_packets_are_the_simulated_points() {
    let dir = tempfile::tempdir().unwrap();
    for run in runs() {
        let mut assembler = assembler_for(None, &run.options(dir.path())).unwrap();
        let rotations = run.decode(assembler.as_mut());
        let clouds: Vec<PointCloud> = rotations.iter().map(rotation_cloud).collect();
        let (errors, start, end) = compare(&run, &clouds, Geometry::Simulated);
        assert_everything_decoded(&run, start, end, &errors);
        assert!(rotations.iter().all(|r| r.gaps == 0), "no packet lost");
        eprintln!("{}: {} rotations, {errors:?}", run.format.name(), rotations.len());
    }
}

/// The scans of a capture, read as `emr-edge` reads a recording.
fn read_capture(path: &Path, options: &RecordingOptions) -> Vec<edge::recording::Scan> {
    edge::recording::open(path, options).unwrap().map(Result::unwrap).collect()
}

#[test]
fn a_capture_reads_back_as_the_simulated_points() {
    let dir = tempfile::tempdir().unwrap();
    for run in runs() {
        let path = dir.path().join(format!("{}.pcap", run.sensor.name));
        let mut writer = CaptureWriter::create(&path, Network::default()).unwrap();
        writer.write_all(&run.packets).unwrap();
        writer.finish().unwrap();
        if let Some(json) = &run.metadata {
            // Where the capture reader looks for an Ouster's metadata: the capture's name with .json.
            std::fs::write(path.with_extension("json"), json).unwrap();
        }
        let described = RecordingOptions { packets: run.options(dir.path()), ..RecordingOptions::default() };
        let scans = read_capture(&path, &described);
        // The same rotations as decoding the packets directly, stamped with the capture's times.
        let mut assembler = assembler_for(None, &run.options(dir.path())).unwrap();
        let direct = run.decode(assembler.as_mut());
        assert_eq!(scans.len(), direct.len());
        for (scan, rotation) in scans.iter().zip(&direct) {
            assert_eq!(scan.cloud, rotation_cloud(rotation));
            assert_eq!((scan.gaps, scan.partial, scan.dropped), (0, rotation.partial, 0));
        }
        let first_sent = run.packets[0].sent_ns as f64 * 1e-9;
        assert!((scans[0].stamp - first_sent).abs() < 1e-5, "stamped with the first packet's capture time");
        let clouds: Vec<PointCloud> = scans.into_iter().map(|s| s.cloud).collect();
        let (errors, start, end) = compare(&run, &clouds, Geometry::Simulated);
        assert_everything_decoded(&run, start, end, &errors);
        eprintln!("{} capture: {} scans, {errors:?}", run.format.name(), clouds.len());

        // With the default options: the Ouster's metadata is found beside the capture; a VLP-16
        // decodes with the published table, its points raised by the lasers' vertical corrections.
        let clouds: Vec<PointCloud> =
            read_capture(&path, &RecordingOptions::default()).into_iter().map(|s| s.cloud).collect();
        let geometry = if run.format == PacketFormat::Vlp16 { Geometry::Published } else { Geometry::Simulated };
        let (errors, start, end) = compare(&run, &clouds, geometry);
        assert_everything_decoded(&run, start, end, &errors);
        eprintln!("{} capture, default options: {errors:?}", run.format.name());
    }
}

#[test]
fn packets_sent_over_udp_arrive_as_the_simulated_rotations() {
    let dir = tempfile::tempdir().unwrap();
    for run in runs() {
        let options = run.options(dir.path());
        let live = LiveSensor::start("127.0.0.1:0".parse().unwrap(), assembler_for(None, &options).unwrap()).unwrap();
        let mut sender = UdpSender::new(live.address(), Pace::Realtime).unwrap();
        let packets = run.packets.clone();
        let sending = std::thread::spawn(move || sender.send_all(&packets).map(|()| sender.sent()));
        // A live stream never ends: the rotation in progress when the packets stop is not handed on.
        let mut assembler = assembler_for(None, &options).unwrap();
        let mut expected = run.decode(assembler.as_mut());
        expected.pop();
        let mut received = Vec::new();
        while received.len() < expected.len() {
            let rotation = live.next_rotation(Duration::from_secs(10)).expect("a rotation within 10 s");
            assert_eq!(rotation.dropped_before, 0, "no rotation dropped");
            received.push(rotation.rotation);
        }
        assert_eq!(sending.join().unwrap().unwrap(), run.packets.len());
        for (got, want) in received.iter().zip(&expected) {
            assert_eq!((&got.returns, got.gaps, got.partial), (&want.returns, want.gaps, want.partial));
        }
        let clouds: Vec<PointCloud> = received.iter().map(rotation_cloud).collect();
        let (errors, start, end) = compare(&run, &clouds, Geometry::Simulated);
        // Every sweep but the last, whose rotation is still open, arrived whole.
        assert_eq!(start.0, 0, "from the first sweep");
        assert!(end.0 >= SWEEPS - 2, "covered to sweep {}", end.0);
        assert_eq!(live.counts().undecoded, 0);
        eprintln!("{} over UDP: {} rotations, {errors:?}", run.format.name(), received.len());
    }
}

fn emr_edge(args: &[&str]) -> std::process::Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_emr-edge")).args(args).output().unwrap()
}

#[test]
fn the_cli_writes_a_capture_of_the_simulated_sweeps_and_sends_only_to_loopback() {
    let dir = tempfile::tempdir().unwrap();
    let pcap = dir.path().join("os64.pcap");
    let args = ["sim", "--scenario", "warehouse-small", "--sensor", "os64", "--seed", "5", "--frames", "2"];
    let run = emr_edge(&[&args[..], &["--pcap", pcap.to_str().unwrap()]].concat());
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    assert!(pcap.with_extension("json").is_file(), "the metadata beside the capture");
    let scans = read_capture(&pcap, &RecordingOptions::default());
    let sensor = SensorModel::ouster(64);
    let config = SimConfig { seed: 5, sensor, ..SimConfig::default() };
    let sim = Simulator::new(Scenario::by_name("warehouse-small").unwrap(), 0, config).unwrap();
    assert_eq!(scans.len(), 2);
    for (frame, scan) in scans.iter().enumerate() {
        assert_eq!(scan.cloud.len(), sim.scan(frame).cloud.len(), "sweep {frame}");
    }

    let remote = emr_edge(&[&args[..], &["--send", "192.0.2.1:2368"]].concat());
    assert!(!remote.status.success());
    assert!(String::from_utf8_lossy(&remote.stderr).contains("only a loopback address"));
    let hdl = emr_edge(&["sim", "--scenario", "aisles", "--sensor", "hdl64", "--pcap", pcap.to_str().unwrap()]);
    assert!(!hdl.status.success());
    assert!(String::from_utf8_lossy(&hdl.stderr).contains("vlp16, os64 or os128"));
}
