//! Point-cloud codec: error bounds and sizes on real KITTI scans, edge cases, reordering, and
//! decoding of truncated, corrupted and hostile input.

use std::path::PathBuf;

use cloud::PointCloud;
use nalgebra::Point3;
use proptest::prelude::*;
use proto::codec::{self, CodecConfig, DecodeError, DecodeLimits, EncodeError};
use testkit::Rng;

/// Offset of the point count in the header.
const COUNT_AT: usize = 32;
/// Header length.
const HEADER: usize = 40;

/// Every KITTI scan (sorted by name) with its reflectance as intensity.
fn kitti_scans() -> Vec<(String, PointCloud)> {
    let dir = testkit::shared_data("kitti00/velodyne");
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("KITTI scans expected in {}: {e}", dir.display()))
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "bin"))
        .collect();
    paths.sort();
    assert!(!paths.is_empty(), "no .bin scan in {}", dir.display());
    paths.iter().map(|p| (p.file_name().unwrap().to_string_lossy().into_owned(), read_kitti(p))).collect()
}

/// A KITTI `.bin`: little-endian f32 records x, y, z, reflectance.
fn read_kitti(path: &PathBuf) -> PointCloud {
    let bytes = std::fs::read(path).unwrap();
    assert_eq!(bytes.len() % 16, 0, "{}", path.display());
    let f = |r: &[u8], i: usize| f32::from_le_bytes(r[4 * i..4 * i + 4].try_into().unwrap());
    let mut cloud =
        PointCloud::from_points(bytes.chunks_exact(16).map(|r| Point3::new(f(r, 0), f(r, 1), f(r, 2))).collect());
    cloud.intensity = Some(bytes.chunks_exact(16).map(|r| f(r, 3)).collect());
    cloud
}

/// Ring and time for a KITTI scan, which has neither: KITTI stores the beams one after the
/// other, each sweeping counter-clockwise from +x, so a new ring starts where the azimuth
/// wraps from below +x (y < 0) to above it; time follows the azimuth over a 0.1 s sweep.
fn with_ring_and_time(mut cloud: PointCloud) -> PointCloud {
    let mut ring = 0u16;
    let mut rings = Vec::with_capacity(cloud.len());
    let mut times = Vec::with_capacity(cloud.len());
    for (i, p) in cloud.points.iter().enumerate() {
        if i > 0 {
            let q = cloud.points[i - 1];
            if q.y < 0.0 && p.y >= 0.0 && p.x > 0.0 {
                ring += 1;
            }
        }
        let azimuth = f64::from(p.y).atan2(f64::from(p.x)).rem_euclid(std::f64::consts::TAU);
        rings.push(ring);
        times.push((0.1 * azimuth / std::f64::consts::TAU) as f32);
    }
    cloud.ring = Some(rings);
    cloud.time = Some(times);
    cloud
}

/// Largest error allowed on a value `x` quantised with `step`: half a step, plus the rounding
/// of the decoded value to f32 (half an ulp: 2^-24 relative; the value is `q * step`, at most
/// `|x| + step` in magnitude). Quantisation itself is computed in f64, whose error (2^-52
/// relative) is covered by the same term. At 120 m and 1 mm this is 0.5 mm + 7 µm.
fn bound(x: f32, step: f64) -> f64 {
    step / 2.0 + (f64::from(x.abs()) + step) * 2f64.powi(-24)
}

/// Asserts that `decoded` matches `original` point for point within the configured steps.
fn assert_within_bounds(original: &PointCloud, decoded: &PointCloud, config: &CodecConfig) {
    assert_eq!(decoded.len(), original.len());
    for (i, (a, b)) in original.xyz().iter().zip(decoded.xyz()).enumerate() {
        for k in 0..3 {
            let error = (f64::from(a[k]) - f64::from(b[k])).abs();
            assert!(
                error <= bound(a[k], config.step),
                "point {i} axis {k}: {} -> {} (step {})",
                a[k],
                b[k],
                config.step
            );
        }
    }
    let scalars = [
        ("intensity", &original.intensity, &decoded.intensity, config.intensity_step),
        ("time", &original.time, &decoded.time, config.time_step),
    ];
    for (name, a, b, step) in scalars {
        assert_eq!(a.is_some(), b.is_some(), "{name} presence");
        for (i, (&x, &y)) in a.iter().flatten().zip(b.iter().flatten()).enumerate() {
            assert!((f64::from(x) - f64::from(y)).abs() <= bound(x, step), "{name} {i}: {x} -> {y}");
        }
    }
    assert_eq!(decoded.ring, original.ring);
}

fn round_trip(cloud: &PointCloud, config: &CodecConfig) -> (Vec<u8>, PointCloud) {
    let bytes = codec::encode(cloud, config).unwrap();
    let decoded = codec::decode(&bytes).unwrap();
    (bytes, decoded)
}

fn cloud_of(points: &[[f32; 3]]) -> PointCloud {
    PointCloud::from_points(points.iter().map(|&p| Point3::from(p)).collect())
}

/// `n` points uniform in a 200 m cube around the origin, with every channel.
fn random_cloud(n: usize, seed: u64) -> PointCloud {
    let mut rng = Rng::new(seed);
    let mut cloud =
        cloud_of(&(0..n).map(|_| [0; 3].map(|_: i32| rng.uniform(-100.0, 100.0) as f32)).collect::<Vec<_>>());
    cloud.intensity = Some((0..n).map(|_| rng.uniform(0.0, 255.0) as f32).collect());
    cloud.ring = Some((0..n).map(|_| rng.below(128) as u16).collect());
    cloud.time = Some((0..n).map(|_| rng.uniform(0.0, 0.1) as f32).collect());
    cloud
}

#[test]
fn kitti_scans_decode_within_half_a_step_and_3x_smaller_than_raw_xyz() {
    let config = CodecConfig::default();
    for (name, scan) in kitti_scans() {
        let xyz = PointCloud::from_points(scan.points.clone());
        let (bytes, decoded) = round_trip(&xyz, &config);
        assert_within_bounds(&xyz, &decoded, &config);
        let ratio = 12.0 * xyz.len() as f64 / bytes.len() as f64;
        assert!(ratio >= 3.0, "{name}: only {ratio:.2}x smaller than raw f32 xyz");
        assert_eq!(bytes[6], 1, "{name}: a scan in sensor order should use the scan predictor");

        let full = with_ring_and_time(scan);
        let (full_bytes, decoded) = round_trip(&full, &config);
        assert_within_bounds(&full, &decoded, &config);
        println!("{name}: {} points, xyz {ratio:.2}x, with all channels {} bytes", xyz.len(), full_bytes.len());
    }
}

#[test]
fn far_negative_and_mixed_points_are_not_clipped() {
    let points = [
        [150.0, -150.0, 2.5],
        [1000.0, 999.999, -1000.0],
        [-123.456_79, 0.000_4, -0.000_6],
        [2_000_000.0, -2_000_000.0, 0.0], // 2000 km: within an i32 of millimetres
        [0.0, 0.0, 0.0],
        [-150.25, 150.125, -3.0],
    ];
    let config = CodecConfig::default();
    let cloud = cloud_of(&points);
    let (_, decoded) = round_trip(&cloud, &config);
    assert_within_bounds(&cloud, &decoded, &config);
}

#[test]
fn absurd_or_non_finite_values_are_refused_not_wrapped() {
    let config = CodecConfig::default();
    let refused = |cloud: &PointCloud| codec::encode(cloud, &config).unwrap_err();
    let far = cloud_of(&[[1.0, 2.0, 3.0], [1.0, 3_000_000.0, 3.0]]); // 3000 km at 1 mm overflows an i32
    assert!(
        matches!(refused(&far), EncodeError::OutOfRange { channel: "xyz", index: 1, value } if value == 3_000_000.0)
    );
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        assert!(matches!(
            refused(&cloud_of(&[[0.0, 0.0, bad]])),
            EncodeError::OutOfRange { channel: "xyz", index: 0, .. }
        ));
    }
    let mut cloud = cloud_of(&[[1.0, 2.0, 3.0]; 3]);
    cloud.intensity = Some(vec![0.5, f32::NAN, 0.5]);
    assert!(matches!(refused(&cloud), EncodeError::OutOfRange { channel: "intensity", index: 1, .. }));
    cloud.intensity = None;
    cloud.time = Some(vec![0.0, 0.05, 1e4]); // 10^4 s at 1 µs overflows an i32
    assert!(matches!(refused(&cloud), EncodeError::OutOfRange { channel: "time", index: 2, .. }));
    cloud.time = Some(vec![0.0]);
    assert!(matches!(refused(&cloud), EncodeError::ChannelLength { channel: "time", len: 1, points: 3 }));
}

#[test]
fn other_steps_keep_their_bound() {
    let scan = PointCloud::from_points(kitti_scans().swap_remove(0).1.points);
    let random = random_cloud(5000, 7);
    for step in [0.01, 0.05, 1e-4, 0.003] {
        let config = CodecConfig { step, intensity_step: 0.5, time_step: 1e-5, ..CodecConfig::default() };
        for cloud in [&scan, &random] {
            let (_, decoded) = round_trip(cloud, &config);
            assert_within_bounds(cloud, &decoded, &config);
        }
    }
}

#[test]
fn empty_single_and_identical_clouds_round_trip() {
    let config = CodecConfig::default();
    let (bytes, decoded) = round_trip(&PointCloud::default(), &config);
    assert!(decoded.is_empty() && decoded.intensity.is_none());
    assert_eq!(bytes.len(), HEADER + 3 * 4 * 4, "an empty cloud is a header and zero-length planes");

    let mut one = cloud_of(&[[-12.345, 67.891, -0.5]]);
    one.intensity = Some(vec![0.37]);
    one.ring = Some(vec![63]);
    one.time = Some(vec![0.0999]);
    let (_, decoded) = round_trip(&one, &config);
    assert_within_bounds(&one, &decoded, &config);

    let mut same = random_cloud(1, 3);
    for _ in 0..14 {
        same.extend(&same.clone());
    }
    let (bytes, decoded) = round_trip(&same, &config);
    assert_within_bounds(&same, &decoded, &config);
    assert!(bytes.len() < 1000, "{} identical points took {} bytes", same.len(), bytes.len());
}

/// A cloud whose values sit a random fraction (below 0.4) of a step away from known multiples
/// of the steps, so the expected quantised values are exact, with no ties to round.
fn cloud_on_grid(n: usize, config: &CodecConfig, seed: u64) -> (PointCloud, Vec<[i64; 6]>) {
    let mut rng = Rng::new(seed);
    let mut near = |q: i64, step: f64| ((q as f64 + rng.uniform(-0.4, 0.4)) * step) as f32;
    let mut cloud = PointCloud::with_capacity(n, cloud::Channels { intensity: true, ring: true, time: true });
    let mut expected = Vec::with_capacity(n);
    for i in 0..n as i64 {
        let q = [(i * 7919) % 20_011 - 10_000, (i * 104_729) % 30_011 - 15_000, (i * 31) % 4001 - 2000];
        let (qi, ring, qt) = ((i * 13) % 1000, (i % 64) as u16, (i * 17) % 100_000);
        let [x, y, z] = q.map(|q| near(q, config.step));
        cloud.points.push(Point3::new(x, y, z));
        cloud.intensity.as_mut().unwrap().push(near(qi, config.intensity_step));
        cloud.ring.as_mut().unwrap().push(ring);
        cloud.time.as_mut().unwrap().push(near(qt, config.time_step));
        expected.push([q[0], q[1], q[2], qi, i64::from(ring), qt]);
    }
    (cloud, expected)
}

/// The quantised values of every decoded point (exact: decoded values are within a tiny
/// fraction of a step of their multiple).
fn quantised_points(cloud: &PointCloud, config: &CodecConfig) -> Vec<[i64; 6]> {
    let q = |v: f32, step: f64| (f64::from(v) / step).round() as i64;
    (0..cloud.len())
        .map(|i| {
            let p = cloud.xyz()[i];
            let channel = |c: &Option<Vec<f32>>, step| q(c.as_ref().unwrap()[i], step);
            let ring = i64::from(cloud.ring.as_ref().unwrap()[i]);
            [
                q(p[0], config.step),
                q(p[1], config.step),
                q(p[2], config.step),
                channel(&cloud.intensity, config.intensity_step),
                ring,
                channel(&cloud.time, config.time_step),
            ]
        })
        .collect()
}

#[test]
fn reordering_keeps_every_point_with_its_channels() {
    let config = CodecConfig { step: 0.01, reorder: true, ..CodecConfig::default() };
    let (cloud, mut expected) = cloud_on_grid(20_000, &config, 11);
    let (bytes, decoded) = round_trip(&cloud, &config);
    assert_eq!(bytes[5] & 8, 8, "reordered flag");
    let mut got = quantised_points(&decoded, &config);
    assert_ne!(got, expected, "points should have been reordered");
    got.sort_unstable();
    expected.sort_unstable();
    assert_eq!(got, expected);
}

#[test]
fn reordering_shrinks_a_shuffled_voxel_map() {
    // A downsampled keyframe: one point per 20 cm voxel of a real scan, in hash-map order.
    let scan = kitti_scans().swap_remove(0).1;
    let mut seen = std::collections::HashSet::new();
    let keep: Vec<usize> =
        (0..scan.len()).filter(|&i| seen.insert(scan.xyz()[i].map(|c| (c / 0.2).floor() as i32))).collect();
    let mut voxels = scan.select(&keep);
    let mut order: Vec<usize> = (0..voxels.len()).collect();
    Rng::new(5).shuffle(&mut order);
    voxels = voxels.select(&order);
    let ordered = codec::encode(&voxels, &CodecConfig::default()).unwrap();
    let config = CodecConfig { reorder: true, ..CodecConfig::default() };
    let (reordered, decoded) = round_trip(&voxels, &config);
    assert_eq!(decoded.len(), voxels.len());
    let ratio = |bytes: &[u8]| 12.0 * voxels.len() as f64 / bytes.len() as f64;
    println!(
        "{} voxels, with intensity: kept order {:.2}x, reordered {:.2}x",
        voxels.len(),
        ratio(&ordered),
        ratio(&reordered)
    );
    assert!(reordered.len() * 10 < ordered.len() * 8, "reordering saved less than 20 %");
}

#[test]
fn every_truncation_and_any_trailing_byte_is_an_error() {
    let mut cloud = random_cloud(300, 1);
    cloud.time = None;
    for config in [CodecConfig::default(), CodecConfig { reorder: true, ..CodecConfig::default() }] {
        let bytes = codec::encode(&cloud, &config).unwrap();
        for len in 0..bytes.len() {
            assert!(codec::decode(&bytes[..len]).is_err(), "prefix of {len} bytes decoded");
        }
        let mut longer = bytes.clone();
        longer.push(0);
        assert!(matches!(codec::decode(&longer), Err(DecodeError::TrailingBytes(1))));
    }
}

#[test]
fn absurd_counts_are_refused_before_allocating() {
    let bytes = codec::encode(&random_cloud(100, 2), &CodecConfig::default()).unwrap();
    let with_count = |count: u64| {
        let mut b = bytes.clone();
        b[COUNT_AT..COUNT_AT + 8].copy_from_slice(&count.to_le_bytes());
        b
    };
    for count in [u64::MAX, 1 << 63, (1 << 26) + 1] {
        assert!(matches!(codec::decode(&with_count(count)), Err(DecodeError::TooManyPoints { .. })), "{count}");
    }
    // Within the limit but disagreeing with the frames: refused from the frame headers alone.
    for count in [1 << 26, 101, 99, 0] {
        assert!(matches!(codec::decode(&with_count(count)), Err(DecodeError::BadSection { .. })), "{count}");
    }
    let small = DecodeLimits { max_points: 50 };
    assert!(matches!(
        codec::decode_with_limits(&bytes, &small),
        Err(DecodeError::TooManyPoints { count: 100, max: 50 })
    ));
    assert!(codec::decode_with_limits(&bytes, &DecodeLimits { max_points: 100 }).is_ok());
}

/// A header for `n` points of xyz only, followed by the given planes (length-prefixed).
fn message(n: u64, planes: &[&[u8]]) -> Vec<u8> {
    let mut b = b"EMPC".to_vec();
    b.extend_from_slice(&[1, 0, 0, 0]);
    for step in [1e-3f64, 1e-3, 1e-6] {
        b.extend_from_slice(&step.to_le_bytes());
    }
    b.extend_from_slice(&n.to_le_bytes());
    for plane in planes {
        b.extend_from_slice(&(plane.len() as u32).to_le_bytes());
        b.extend_from_slice(plane);
    }
    b
}

#[test]
fn zstd_bombs_and_foreign_frames_are_refused() {
    let n = 1000;
    let zero = &[][..];
    let decode = |frame: &[u8]| {
        let mut planes = vec![frame];
        planes.resize(12, zero);
        codec::decode(&message(n, &planes))
    };
    // Well-formed control: a frame of exactly n bytes decodes.
    let good = zstd::bulk::compress(&vec![7u8; n as usize], 1).unwrap();
    assert!(decode(&good).is_ok());
    // A frame that declares (and would inflate to) far more than n bytes.
    let bomb = zstd::bulk::compress(&vec![0u8; 1 << 24], 19).unwrap();
    assert!(bomb.len() < 1000);
    assert!(matches!(decode(&bomb), Err(DecodeError::BadSection { .. })));
    // A streamed frame that does not declare its size, and would inflate to 16 MB.
    let mut streamed = zstd::stream::Encoder::new(Vec::new(), 3).unwrap();
    std::io::Write::write_all(&mut streamed, &vec![0u8; 1 << 24]).unwrap();
    let streamed = streamed.finish().unwrap();
    assert!(matches!(decode(&streamed), Err(DecodeError::BadSection { .. })));
    // A frame that declares n bytes but carries more (a second frame appended): zstd stops at
    // the capacity of n bytes.
    let mut two = good.clone();
    two.extend_from_slice(&good);
    assert!(decode(&two).is_err());
    // Skippable frames and garbage.
    let skippable = [0x50, 0x2a, 0x4d, 0x18, 4, 0, 0, 0, 1, 2, 3, 4];
    assert!(matches!(decode(&skippable), Err(DecodeError::BadSection { .. })));
    assert!(matches!(decode(&[0xff; 64]), Err(DecodeError::BadSection { .. })));
    // A corrupted frame body is caught by zstd (or its checksum).
    let mut corrupt = codec::encode(&random_cloud(2000, 4), &CodecConfig::default()).unwrap();
    let middle = HEADER + 200;
    corrupt[middle] ^= 0x55;
    assert!(codec::decode(&corrupt).is_err());
}

#[test]
fn header_fields_are_validated() {
    let bytes = codec::encode(&random_cloud(10, 9), &CodecConfig::default()).unwrap();
    let patched = |at: usize, value: u8| {
        let mut b = bytes.clone();
        b[at] = value;
        codec::decode(&b)
    };
    assert!(matches!(patched(0, b'X'), Err(DecodeError::BadMagic)));
    assert!(matches!(patched(4, 2), Err(DecodeError::UnsupportedVersion(2))));
    assert!(matches!(patched(5, 0x1f), Err(DecodeError::UnknownFlags { .. })));
    assert!(matches!(patched(7, 1), Err(DecodeError::UnknownFlags { .. })));
    assert!(matches!(patched(6, 9), Err(DecodeError::UnknownPredictor(9))));
    assert!(matches!(patched(15, 0x7f), Err(DecodeError::InvalidStep { name: "step", .. }))); // 1e-3 -> 2^1014
    assert!(matches!(codec::decode(&bytes[..HEADER - 1]), Err(DecodeError::Truncated { offset: 0, .. })));
}

/// Small clouds with random channels and any f32 values, including NaN, infinities and huge ones.
fn any_cloud() -> impl Strategy<Value = PointCloud> {
    let value = prop_oneof![8 => -2000.0f32..2000.0, 1 => any::<f32>()];
    (0usize..60).prop_flat_map(move |n| {
        let points = prop::collection::vec([value.clone(), value.clone(), value.clone()], n);
        let channel = |s: BoxedStrategy<f32>| prop::option::of(prop::collection::vec(s, n));
        (
            points,
            channel((0.0f32..255.0).boxed()),
            prop::option::of(prop::collection::vec(any::<u16>(), n)),
            channel((0.0f32..0.2).boxed()),
        )
            .prop_map(|(points, intensity, ring, time)| PointCloud {
                points: points.into_iter().map(Point3::from).collect(),
                intensity,
                ring,
                time,
            })
    })
}

fn any_config() -> impl Strategy<Value = CodecConfig> {
    (prop::sample::select(vec![1e-4, 1e-3, 0.01, 0.25]), any::<bool>()).prop_map(|(step, reorder)| CodecConfig {
        step,
        reorder,
        ..CodecConfig::default()
    })
}

proptest! {
    #[test]
    fn arbitrary_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..600)) {
        let _ = codec::decode(&bytes);
    }

    #[test]
    fn arbitrary_bytes_after_a_valid_header_never_panic(
        flags in 0u8..16, predictor in 0u8..2, n in 0u64..64, tail in prop::collection::vec(any::<u8>(), 0..600),
    ) {
        let mut bytes = message(n, &[]);
        bytes[5] = flags;
        bytes[6] = predictor;
        bytes.extend_from_slice(&tail);
        let _ = codec::decode(&bytes);
    }

    #[test]
    fn any_cloud_encodes_within_bounds_or_is_refused(cloud in any_cloud(), config in any_config()) {
        match codec::encode(&cloud, &config) {
            Ok(bytes) => {
                let decoded = codec::decode(&bytes).unwrap();
                if config.reorder {
                    prop_assert_eq!(decoded.len(), cloud.len());
                    prop_assert_eq!(decoded.channels(), cloud.channels());
                } else {
                    assert_within_bounds(&cloud, &decoded, &config);
                }
            }
            Err(EncodeError::OutOfRange { .. }) => {
                let limit = 2f64.powi(31) * config.step;
                let too_far = |v: &f32| !v.is_finite() || f64::from(v.abs()) >= limit * 0.99;
                prop_assert!(cloud.xyz().as_flattened().iter().any(too_far));
            }
            Err(e) => prop_assert!(false, "unexpected error {}", e),
        }
    }

    #[test]
    fn corrupted_encodings_never_panic(
        cloud in any_cloud(), config in any_config(), flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 1..8),
    ) {
        let Ok(mut bytes) = codec::encode(&cloud, &config) else { return Ok(()) };
        for (at, mask) in flips {
            let at = at.index(bytes.len());
            bytes[at] ^= mask;
        }
        if let Ok(decoded) = codec::decode(&bytes) {
            // Whatever decodes is a consistent cloud of finite values.
            prop_assert!(decoded.validate().is_ok());
            prop_assert!(decoded.intensity.iter().flatten().chain(decoded.time.iter().flatten()).all(|v| v.is_finite()));
        }
    }

    #[test]
    fn truncated_encodings_are_errors(cloud in any_cloud(), config in any_config(), cut in any::<prop::sample::Index>()) {
        let Ok(bytes) = codec::encode(&cloud, &config) else { return Ok(()) };
        prop_assert!(codec::decode(&bytes[..cut.index(bytes.len())]).is_err());
    }
}
