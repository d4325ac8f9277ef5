//! File-format tests: real scans against independently decoded values, exact round trips
//! through every encoding, hand-made files with unusual layouts, and corrupt or hostile input.

use std::path::{Path, PathBuf};

use cloud::formats::{
    self, FileFormat, FormatErrorKind, LoadedCloud, ParseError, PcdEncoding, PlyEncoding, kitti, pcd, ply,
};
use cloud::{Channels, PointCloud};
use nalgebra::Point3;
use proptest::prelude::*;
use testkit::shared_data as data;

/// A path for a file this test writes.
fn scratch(name: &str) -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join(format!("cloud-formats-{name}"))
}

/// The parser for a format, as `read_cloud` would choose it.
fn parse(format: FileFormat, bytes: &[u8]) -> Result<LoadedCloud, ParseError> {
    match format {
        FileFormat::KittiBin => kitti::parse(bytes),
        FileFormat::Pcd(_) => pcd::parse(bytes),
        FileFormat::Ply(_) => ply::parse(bytes),
    }
}

/// The first KITTI scan of sequence 00.
fn kitti_scan() -> PointCloud {
    let read = formats::read_cloud(&data("kitti00/velodyne/000000.bin")).expect("KITTI scan");
    assert_eq!(read.dropped_non_finite, 0);
    read.cloud
}

/// A deterministic cloud of `n` points whose values are random finite bit patterns
/// (subnormals, huge exponents, negative zero...), the hardest case for text round trips.
fn random_cloud(n: usize, channels: Channels, seed: u64) -> PointCloud {
    let mut state = seed;
    let mut bits = move || {
        state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        (state >> 32) as u32
    };
    let mut finite = move || loop {
        let v = f32::from_bits(bits());
        if v.is_finite() {
            return v;
        }
    };
    let mut cloud = PointCloud::with_capacity(n, channels);
    for _ in 0..n {
        cloud.points.push(Point3::new(finite(), finite(), finite()));
        if let Some(v) = &mut cloud.intensity {
            v.push(finite());
        }
        if let Some(v) = &mut cloud.ring {
            v.push(finite().to_bits() as u16);
        }
        if let Some(v) = &mut cloud.time {
            v.push(finite());
        }
    }
    cloud
}

/// Bit-exact comparison (`==` would accept 0.0 for -0.0).
fn assert_identical(found: &PointCloud, expected: &PointCloud, context: &str) {
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let xyz = |c: &PointCloud| c.xyz().iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(found.len(), expected.len(), "{context}: point count");
    assert!(xyz(found) == xyz(expected), "{context}: positions differ");
    assert_eq!(found.intensity.as_deref().map(bits), expected.intensity.as_deref().map(bits), "{context}");
    assert_eq!(found.ring, expected.ring, "{context}");
    assert_eq!(found.time.as_deref().map(bits), expected.time.as_deref().map(bits), "{context}");
}

const ALL_CHANNELS: Channels = Channels { intensity: true, ring: true, time: true };

// ---------------------------------------------------------------------------------------------
// Real files

#[test]
fn kitti_scan_matches_an_independent_decode() {
    let cloud = kitti_scan();
    assert_eq!(cloud.len(), 124_668);
    assert_eq!(cloud.channels(), Channels { intensity: true, ..Channels::default() });
    // Values decoded separately with Python's struct module, written as shortest f32 decimals.
    let first = cloud.points[0];
    assert_eq!(first, Point3::new(52.89794, 0.022_989_739, 1.997_994_5));
    assert!((first.x - 52.898).abs() < 1e-3 && (first.y - 0.0230).abs() < 1e-4 && (first.z - 1.998).abs() < 1e-3);
    let intensity = cloud.intensity.as_ref().unwrap();
    assert!((intensity[0] - 0.08).abs() < 1e-6);
    assert_eq!(cloud.points[1000], Point3::new(-40.693_954, -3.200_848_8, 1.590_856_1));
    assert_eq!(intensity[1000], 0.22);
    assert_eq!(cloud.points[124_667], Point3::new(4.092_375_3, -1.507_196_2, -1.895_561_1));
    assert_eq!(intensity[124_667], 0.0);
}

#[test]
fn gicp_source_ply_reads_x_y_z_scalar_intensity() {
    let read = formats::read_cloud(&data("gicp_pair/source.ply")).unwrap();
    assert_eq!(read.dropped_non_finite, 0);
    let cloud = read.cloud;
    assert_eq!(cloud.len(), 69_792);
    assert_eq!(cloud.channels(), Channels { intensity: true, ..Channels::default() });
    let intensity = cloud.intensity.as_ref().unwrap();
    assert_eq!(cloud.points[0], Point3::new(0.004_045_109_3, 2.575_194_6, -1.527_217_4));
    assert_eq!(intensity[0], 70.0);
    assert_eq!(cloud.points[69_791], Point3::new(-0.004_093_722, 1.804_250_7, 0.339_939_24));
    assert_eq!(intensity[69_791], 36.0);
}

#[test]
fn real_ply_cut_mid_record_names_the_record_and_offset() {
    let bytes = std::fs::read(data("gicp_pair/source.ply")).unwrap();
    let header_len = 268; // measured independently: end of "end_header\n"
    let cut = header_len + 16 * 100 + 5;
    let err = ply::parse(&bytes[..cut]).unwrap_err();
    let expected = ParseError::BadRecord { element: "vertex".into(), record: 100, offset: header_len + 1600 };
    assert_eq!(err, expected);
}

// ---------------------------------------------------------------------------------------------
// Round trips

#[test]
fn every_encoding_round_trips_random_bit_patterns_exactly() {
    let kinds = [
        ALL_CHANNELS,
        Channels::default(),
        Channels { intensity: true, ..Channels::default() },
        Channels { ring: true, time: true, ..Channels::default() },
    ];
    for (seed, channels) in kinds.into_iter().enumerate() {
        let cloud = random_cloud(500, channels, seed as u64);
        for format in FileFormat::ALL {
            let expected = if format == FileFormat::KittiBin {
                // KITTI stores intensity only, always.
                let intensity = Some(cloud.intensity.clone().unwrap_or_else(|| vec![0.0; cloud.len()]));
                PointCloud { intensity, ring: None, time: None, ..cloud.clone() }
            } else {
                cloud.clone()
            };
            let read = parse(format, &formats::encode(&cloud, format)).unwrap();
            assert_eq!(read.dropped_non_finite, 0);
            assert_identical(&read.cloud, &expected, &format!("{format:?} {channels:?}"));
        }
    }
}

#[test]
fn empty_clouds_round_trip_in_every_encoding() {
    let empty = PointCloud::with_capacity(0, ALL_CHANNELS);
    for format in FileFormat::ALL {
        let read = parse(format, &formats::encode(&empty, format)).unwrap();
        assert!(read.cloud.is_empty(), "{format:?}");
    }
}

#[test]
fn real_kitti_scan_round_trips_through_files_in_every_encoding() {
    let scan = kitti_scan();
    for format in FileFormat::ALL {
        let path = scratch(&format!("{format:?}.{}", format.extension()).replace(['(', ')'], "_"));
        formats::write_cloud(&path, &scan, format).unwrap();
        let read = formats::read_cloud(&path).unwrap();
        std::fs::remove_file(&path).unwrap();
        assert_identical(&read.cloud, &scan, &format!("{format:?}"));
    }
}

#[test]
fn binary_compressed_is_smaller_than_binary_on_a_real_scan() {
    let scan = kitti_scan();
    let binary = pcd::encode(&scan, PcdEncoding::Binary).len();
    let compressed = pcd::encode(&scan, PcdEncoding::BinaryCompressed).len();
    assert!(compressed < binary, "{compressed} >= {binary}");
}

#[test]
fn extension_matching_is_case_insensitive() {
    let path = scratch("upper.PCD");
    let cloud = random_cloud(3, ALL_CHANNELS, 9);
    formats::write_cloud(&path, &cloud, FileFormat::Pcd(PcdEncoding::Binary)).unwrap();
    let read = formats::read_cloud(&path).unwrap();
    std::fs::remove_file(&path).unwrap();
    assert_identical(&read.cloud, &cloud, "upper-case extension");
}

// ---------------------------------------------------------------------------------------------
// Hand-made PCD files

/// A hand-made binary point: the bytes of each field, in FIELDS order.
type RawPoint = Vec<Vec<u8>>;

/// Points stored one record after another (DATA binary).
fn records(points: &[RawPoint]) -> Vec<u8> {
    points.iter().flatten().flatten().copied().collect()
}

/// Points stored field by field (the layout inside binary_compressed).
fn by_field(points: &[RawPoint]) -> Vec<u8> {
    let fields = points.first().map_or(0, Vec::len);
    (0..fields).flat_map(|f| points.iter().flat_map(move |p| p[f].clone())).collect()
}

/// A binary_compressed block whose LZF stream is literal runs only, built without our compressor.
fn literal_block(raw: &[u8]) -> Vec<u8> {
    let packed: Vec<u8> =
        raw.chunks(32).flat_map(|c| std::iter::once(c.len() as u8 - 1).chain(c.iter().copied())).collect();
    let mut block = (packed.len() as u32).to_le_bytes().to_vec();
    block.extend((raw.len() as u32).to_le_bytes());
    block.extend(packed);
    block
}

/// A PCD file of `header` (without DATA), `DATA kind`, then `body`.
fn pcd_file(header: &str, kind: &str, body: &[u8]) -> Vec<u8> {
    let mut bytes = format!("{header}DATA {kind}\n").into_bytes();
    bytes.extend_from_slice(body);
    bytes
}

const MIXED_HEADER: &str = "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n\
    FIELDS x y z intensity ring t rgb\nSIZE 8 4 2 1 1 4 4\nTYPE F F I U U U F\nCOUNT 1 1 1 1 1 1 1\n\
    WIDTH 2\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\n";

fn mixed_points() -> Vec<RawPoint> {
    vec![
        vec![
            1.5f64.to_le_bytes().into(),
            (-2.25f32).to_le_bytes().into(),
            (-3i16).to_le_bytes().into(),
            vec![200],
            vec![5],
            50_000_000u32.to_le_bytes().into(),
            f32::from_bits(0x00ff_00ff).to_le_bytes().into(),
        ],
        vec![
            0.1f64.to_le_bytes().into(),
            7.0f32.to_le_bytes().into(),
            32_767i16.to_le_bytes().into(),
            vec![0],
            vec![63],
            99_999_999u32.to_le_bytes().into(),
            f32::NAN.to_le_bytes().into(),
        ],
    ]
}

fn assert_mixed(read: &LoadedCloud, context: &str) {
    let c = &read.cloud;
    assert_eq!(read.dropped_non_finite, 0, "{context}");
    assert_eq!(c.points, vec![Point3::new(1.5, -2.25, -3.0), Point3::new(0.1, 7.0, 32_767.0)], "{context}");
    assert_eq!(c.intensity, Some(vec![200.0, 0.0]), "{context}");
    assert_eq!(c.ring, Some(vec![5, 63]), "{context}");
    // Ouster-style u32 `t` is nanoseconds.
    let time = c.time.as_ref().unwrap();
    assert!((time[0] - 0.05).abs() < 1e-9 && (f64::from(time[1]) - 0.099_999_999).abs() < 1e-8, "{context}: {time:?}");
}

#[test]
fn pcd_mixed_field_types_read_alike_in_all_encodings() {
    let points = mixed_points();
    assert_mixed(&pcd::parse(&pcd_file(MIXED_HEADER, "binary", &records(&points))).unwrap(), "binary");
    let block = literal_block(&by_field(&points));
    assert_mixed(&pcd::parse(&pcd_file(MIXED_HEADER, "binary_compressed", &block)).unwrap(), "compressed");
    let text = "1.5 -2.25 -3 200 5 50000000 0.1\n0.1 7 32767 0 63 99999999 nan\n";
    assert_mixed(&pcd::parse(&pcd_file(MIXED_HEADER, "ascii", text.as_bytes())).unwrap(), "ascii");
}

const COUNT_HEADER: &str = "VERSION 0.7\nFIELDS descriptor x y z intensity _\nSIZE 4 4 4 4 2 1\n\
    TYPE F F F F U U\nCOUNT 3 1 1 1 2 3\nWIDTH 2\nHEIGHT 1\nPOINTS 2\n";

#[test]
fn pcd_fields_with_count_above_one_feed_their_first_element() {
    let point = |x: f32, intensity: u16| -> RawPoint {
        vec![
            [9.0f32, 8.0, 7.0].iter().flat_map(|v| v.to_le_bytes()).collect(),
            x.to_le_bytes().into(),
            (x + 1.0).to_le_bytes().into(),
            (x + 2.0).to_le_bytes().into(),
            [intensity, 9].iter().flat_map(|v| v.to_le_bytes()).collect(),
            vec![0xaa; 3],
        ]
    };
    let points = vec![point(1.0, 700), point(4.0, 65_535)];
    let expected_points = vec![Point3::new(1.0, 2.0, 3.0), Point3::new(4.0, 5.0, 6.0)];
    let text = "9 8 7 1 2 3 700 9 170 170 170\n9 8 7 4 5 6 65535 9 170 170 170\n";
    let files = [
        pcd_file(COUNT_HEADER, "binary", &records(&points)),
        pcd_file(COUNT_HEADER, "binary_compressed", &literal_block(&by_field(&points))),
        pcd_file(COUNT_HEADER, "ascii", text.as_bytes()),
    ];
    for bytes in files {
        let read = pcd::parse(&bytes).unwrap();
        assert_eq!(read.cloud.points, expected_points);
        assert_eq!(read.cloud.intensity, Some(vec![700.0, 65_535.0]));
    }
}

#[test]
fn pcd_organized_cloud_drops_and_counts_invalid_pixels() {
    let header = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 2\nPOINTS 6\n";
    let text = "1 1 1\nnan nan nan\n2 2 2\n3 3 3\n4 inf 4\n5 5 5\n";
    let values = [
        1.0,
        1.0,
        1.0,
        f32::NAN,
        f32::NAN,
        f32::NAN,
        2.0,
        2.0,
        2.0,
        3.0,
        3.0,
        3.0,
        4.0,
        f32::INFINITY,
        4.0,
        5.0,
        5.0,
        5.0,
    ];
    let body: Vec<u8> = values.iter().flat_map(|v: &f32| v.to_le_bytes()).collect();
    let expected: Vec<_> = [1.0, 2.0, 3.0, 5.0].iter().map(|&v| Point3::new(v, v, v)).collect();
    for bytes in [pcd_file(header, "ascii", text.as_bytes()), pcd_file(header, "binary", &body)] {
        let read = pcd::parse(&bytes).unwrap();
        assert_eq!(read.dropped_non_finite, 2);
        assert_eq!(read.cloud.points, expected);
    }
}

#[test]
fn pcd_f64_coordinates_beyond_f32_are_dropped_as_non_finite() {
    let header = "FIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nPOINTS 2\n";
    let body: Vec<u8> = [1e300f64, 0.0, 0.0, 1.0, 2.0, 3.0].iter().flat_map(|v| v.to_le_bytes()).collect();
    let read = pcd::parse(&pcd_file(header, "binary", &body)).unwrap();
    assert_eq!(read.dropped_non_finite, 1);
    assert_eq!(read.cloud.points, vec![Point3::new(1.0, 2.0, 3.0)]);
}

#[test]
fn pcd_float_time_is_seconds_and_i_is_an_intensity_fallback() {
    let header = "FIELDS x y z i timestamp\nSIZE 4 4 4 4 8\nTYPE F F F F F\nPOINTS 1\n";
    let read = pcd::parse(&pcd_file(header, "ascii", b"1 2 3 0.5 0.0625\n")).unwrap();
    assert_eq!(read.cloud.intensity, Some(vec![0.5]));
    assert_eq!(read.cloud.time, Some(vec![0.0625]));
}

// ---------------------------------------------------------------------------------------------
// Hand-made PLY files

/// Vertex records of the mixed-type PLY files, in the requested byte order.
fn ply_vertices(big: bool) -> Vec<u8> {
    let mut out = Vec::new();
    let mut put = |le: Vec<u8>| {
        let mut v = le;
        if big {
            v.reverse();
        }
        out.extend(v);
    };
    for (x, y, z, intensity, ring, t) in
        [(1.5f64, -2.0f32, -7i32, 9u8, 31u16, 1_000u32), (f64::NAN, 0.0, 0, 0, 0, 0), (0.25, 8.5, 70_000, 255, 2, 0)]
    {
        put(x.to_le_bytes().into());
        put(y.to_le_bytes().into());
        put(z.to_le_bytes().into());
        put(vec![intensity]);
        put(ring.to_le_bytes().into());
        put(t.to_le_bytes().into());
    }
    out
}

const PLY_VERTEX_ELEMENT: &str = "element vertex 3\nproperty double x\nproperty float32 y\nproperty int z\n\
    property uchar reflectance\nproperty ushort ring\nproperty uint t\n";

fn assert_ply_vertices(read: &LoadedCloud, context: &str) {
    assert_eq!(read.dropped_non_finite, 1, "{context}");
    let c = &read.cloud;
    assert_eq!(c.points, vec![Point3::new(1.5, -2.0, -7.0), Point3::new(0.25, 8.5, 70_000.0)], "{context}");
    assert_eq!(c.intensity, Some(vec![9.0, 255.0]), "{context}");
    assert_eq!(c.ring, Some(vec![31, 2]), "{context}");
    assert_eq!(c.time, Some(vec![1e-6, 0.0]), "{context}");
}

#[test]
fn ply_binary_with_faces_after_the_vertices() {
    for (big, format) in [(false, "binary_little_endian"), (true, "binary_big_endian")] {
        let header = format!(
            "ply\nformat {format} 1.0\ncomment made by hand\nobj_info nothing\n{PLY_VERTEX_ELEMENT}\
             element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        );
        let mut bytes = header.into_bytes();
        bytes.extend(ply_vertices(big));
        bytes.push(3);
        for i in 0..3i32 {
            bytes.extend(if big { i.to_be_bytes() } else { i.to_le_bytes() });
        }
        assert_ply_vertices(&ply::parse(&bytes).unwrap(), format);
    }
}

#[test]
fn ply_binary_skips_list_and_fixed_elements_before_the_vertices() {
    for (big, format) in [(false, "binary_little_endian"), (true, "binary_big_endian")] {
        let header = format!(
            "ply\nformat {format} 1.0\nelement face 2\nproperty list uchar int vertex_indices\n\
             property short flags\nelement edge 1\nproperty int a\nproperty int b\n{PLY_VERTEX_ELEMENT}end_header\n"
        );
        let int = |v: i32| {
            if big { v.to_be_bytes() } else { v.to_le_bytes() }
        };
        let mut bytes = header.into_bytes();
        for len in [3u8, 4] {
            bytes.push(len);
            (0..i32::from(len)).for_each(|i| bytes.extend(int(i)));
            bytes.extend([0, 1]);
        }
        bytes.extend(int(0));
        bytes.extend(int(1));
        bytes.extend(ply_vertices(big));
        assert_ply_vertices(&ply::parse(&bytes).unwrap(), format);
    }
}

#[test]
fn ply_ascii_skips_faces_and_reads_scalar_intensity() {
    let text = "ply\nformat ascii 1.0\ncomment hi\nelement face 2\nproperty list uchar int vertex_indices\n\
        element vertex 3\nproperty float x\nproperty float y\nproperty float z\nproperty float scalar_Intensity\n\
        property uchar red\nend_header\n3 0 1 2\n4 0 1 2 3\n1 2 3 0.5 255\nnan 0 0 1 0\n4 5 6 0.25 0\n";
    let read = ply::parse(text.as_bytes()).unwrap();
    assert_eq!(read.dropped_non_finite, 1);
    assert_eq!(read.cloud.points, vec![Point3::new(1.0, 2.0, 3.0), Point3::new(4.0, 5.0, 6.0)]);
    assert_eq!(read.cloud.intensity, Some(vec![0.5, 0.25]));
    assert_eq!(read.cloud.ring, None);
}

#[test]
fn ply_accepts_crlf_headers() {
    let text = "ply\r\nformat ascii 1.0\r\nelement vertex 1\r\nproperty float x\r\nproperty float y\r\n\
        property float z\r\nend_header\r\n1 2 3\r\n";
    assert_eq!(ply::parse(text.as_bytes()).unwrap().cloud.points, vec![Point3::new(1.0, 2.0, 3.0)]);
}

// ---------------------------------------------------------------------------------------------
// Corrupt and hostile input

#[test]
fn every_truncation_of_every_encoding_errs_or_reads_fewer_points() {
    let cloud = random_cloud(6, ALL_CHANNELS, 77);
    for format in FileFormat::ALL {
        let bytes = formats::encode(&cloud, format);
        for cut in 0..bytes.len() {
            let result = parse(format, &bytes[..cut]);
            match (format, result) {
                (_, Err(_)) => {}
                (FileFormat::KittiBin, Ok(read)) => assert_eq!(read.cloud.len(), cut / 16),
                // A cut inside the last number of a text file still reads as a number.
                (FileFormat::Pcd(PcdEncoding::Ascii) | FileFormat::Ply(PlyEncoding::Ascii), Ok(read)) => {
                    assert!(read.cloud.len() <= cloud.len(), "{format:?} cut {cut}");
                    read.cloud.validate().unwrap();
                }
                (_, Ok(_)) => panic!("{format:?} cut at {cut} of {} bytes was accepted", bytes.len()),
            }
        }
    }
}

#[test]
fn garbage_headers_are_rejected() {
    let cases: [&[u8]; 6] = [
        b"",
        b"hello world\n",
        b"\x00\xff\xfe binary\n",
        b"FIELDS x y z\nPOINTS 1\n",
        b"ply\n",
        b"ply\nformat ascii 1.0\nelement vertex x\nend_header\n",
    ];
    for bytes in cases {
        assert!(pcd::parse(bytes).is_err(), "pcd accepted {bytes:?}");
        assert!(ply::parse(bytes).is_err(), "ply accepted {bytes:?}");
    }
    assert_eq!(pcd::parse(b"").unwrap_err(), ParseError::MissingHeaderLine("DATA"));
    assert_eq!(ply::parse(b"ply\nformat ascii 1.0\n").unwrap_err(), ParseError::MissingHeaderLine("end_header"));
    let err = pcd::parse(b"FIELDS x y z\nBOGUS 1\nDATA ascii\n").unwrap_err();
    assert_eq!(err, ParseError::Syntax { line: 2, reason: "unknown header key \"BOGUS\"".into() });
    let err = ply::parse(b"ply\nformat ascii 1.0\nproperty float x\nend_header\n").unwrap_err();
    assert_eq!(err, ParseError::Syntax { line: 3, reason: "property declared before any element".into() });
    assert_eq!(pcd::parse(b"FIELDS x y\nPOINTS 0\nDATA ascii\n").unwrap_err(), ParseError::MissingField("z"));
}

const XYZ: &str = "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n";

#[test]
fn absurd_pcd_point_counts_fail_without_allocating() {
    let two_points = [0u8; 24];
    let header = format!("{XYZ}POINTS 999999999999\n");
    let err = pcd::parse(&pcd_file(&header, "binary", &two_points)).unwrap_err();
    assert_eq!(err, ParseError::Truncated { points: 999_999_999_999, point_size: 12, available: 24 });
    let err = pcd::parse(&pcd_file(&header, "ascii", b"1 2 3\n4 5 6\n")).unwrap_err();
    let expected = ParseError::MissingRecords { what: "points".into(), declared: 999_999_999_999, found: 2 };
    assert_eq!(err, expected);
    let err = pcd::parse(&pcd_file(&header, "binary_compressed", &literal_block(&two_points))).unwrap_err();
    assert!(matches!(err, ParseError::CompressedBlock(_)), "{err}");

    let header = format!("{XYZ}POINTS 18446744073709551615\n");
    let err = pcd::parse(&pcd_file(&header, "binary", &two_points)).unwrap_err();
    assert_eq!(err, ParseError::TooLarge { points: usize::MAX, point_size: 12 });
    let err = pcd::parse(&pcd_file(&format!("{XYZ}POINTS 99999999999999999999\n"), "binary", &[])).unwrap_err();
    assert!(matches!(err, ParseError::Syntax { line: 5, .. }), "{err}");
}

#[test]
fn absurd_pcd_counts_and_sizes_fail_cleanly() {
    let huge_count = "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 999999999999999 1 1\nPOINTS 1\n";
    let err = pcd::parse(&pcd_file(huge_count, "binary", &[0; 12])).unwrap_err();
    assert!(matches!(err, ParseError::Truncated { points: 1, .. }), "{err}");
    let err = pcd::parse(&pcd_file(huge_count, "ascii", b"1 2 3\n")).unwrap_err();
    assert!(matches!(err, ParseError::Syntax { line: 7, .. }), "{err}");
    let overflow = "FIELDS x y z\nSIZE 8 4 4\nTYPE F F F\nCOUNT 18446744073709551615 1 1\nPOINTS 1\n";
    let err = pcd::parse(&pcd_file(overflow, "binary", &[])).unwrap_err();
    assert!(matches!(err, ParseError::Syntax { line: 4, .. }), "{err}");
    let zero = "FIELDS x y z\nCOUNT 0 1 1\nPOINTS 1\n";
    assert!(matches!(pcd::parse(&pcd_file(zero, "ascii", b"1 2 3\n")), Err(ParseError::Syntax { line: 2, .. })));
}

#[test]
fn absurd_ply_element_counts_fail_without_allocating() {
    let vertex = "property float x\nproperty float y\nproperty float z\n";
    for format in ["binary_little_endian", "binary_big_endian"] {
        let header = format!("ply\nformat {format} 1.0\nelement vertex 999999999999999\n{vertex}end_header\n");
        let mut bytes = header.clone().into_bytes();
        bytes.extend([0; 24]);
        let err = ply::parse(&bytes).unwrap_err();
        let expected = ParseError::BadRecord { element: "vertex".into(), record: 2, offset: header.len() + 24 };
        assert_eq!(err, expected);
    }
    let text = format!("ply\nformat ascii 1.0\nelement vertex 999999999999999\n{vertex}end_header\n1 2 3\n");
    let expected =
        ParseError::MissingRecords { what: "`vertex` records".into(), declared: 999_999_999_999_999, found: 1 };
    assert_eq!(ply::parse(text.as_bytes()).unwrap_err(), expected);

    // Elements before the vertices: fixed-size, list-holding and property-less ones.
    for element in [
        "element face 999999999999999\nproperty int a\n",
        "element face 999999999999999\nproperty list uint uchar idx\n",
    ] {
        let header = format!("ply\nformat binary_little_endian 1.0\n{element}element vertex 1\n{vertex}end_header\n");
        let mut bytes = header.into_bytes();
        bytes.extend([0; 64]);
        assert!(matches!(ply::parse(&bytes), Err(ParseError::BadRecord { .. })), "{element}");
    }
    let nothing = format!(
        "ply\nformat binary_little_endian 1.0\nelement nothing 18446744073709551615\nelement vertex 1\n{vertex}end_header\n"
    );
    let mut bytes = nothing.into_bytes();
    bytes.extend([0; 12]);
    assert_eq!(ply::parse(&bytes).unwrap().cloud.len(), 1);
    let list_len = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex 1\n{vertex}property list uint64 double n\nend_header\n"
    );
    let mut bytes = list_len.into_bytes();
    bytes.extend([0; 12]);
    bytes.extend(u64::MAX.to_le_bytes());
    assert!(matches!(ply::parse(&bytes), Err(ParseError::BadRecord { record: 0, .. })));
}

#[test]
fn kitti_file_of_the_wrong_size_names_the_file_and_size() {
    let path = scratch("ragged.bin");
    std::fs::write(&path, [0u8; 100]).unwrap();
    let err = formats::read_cloud(&path).unwrap_err();
    std::fs::remove_file(&path).unwrap();
    assert!(matches!(err.kind, FormatErrorKind::Parse(ParseError::KittiSize { len: 100 })));
    let message = err.to_string();
    assert!(message.starts_with(&format!("{}: ", path.display())), "{message}");
    assert!(message.contains("100 bytes is not a multiple of 16"), "{message}");
}

#[test]
fn truncated_binary_pcd_error_names_file_and_sizes() {
    let path = scratch("truncated.pcd");
    let header =
        "FIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH 1000\nHEIGHT 1\nPOINTS 1000\n";
    std::fs::write(&path, pcd_file(header, "binary", &[0; 8000])).unwrap();
    let err = formats::read_cloud(&path).unwrap_err();
    std::fs::remove_file(&path).unwrap();
    let expected = format!(
        "{}: truncated binary data: header declares 1000 points of 16 bytes, file has 8000 bytes after the header",
        path.display()
    );
    assert_eq!(err.to_string(), expected);
}

#[test]
fn unknown_extensions_list_the_supported_ones() {
    for name in ["scan.las", "scan"] {
        let err = formats::read_cloud(Path::new(name)).unwrap_err();
        assert!(matches!(err.kind, FormatErrorKind::UnsupportedExtension { .. }), "{err}");
        let message = err.to_string();
        assert!(message.starts_with(name) && [".bin", ".pcd", ".ply"].iter().all(|e| message.contains(e)), "{message}");
    }
}

#[test]
fn missing_file_error_names_the_path() {
    let path = scratch("does-not-exist.ply");
    let err = formats::read_cloud(&path).unwrap_err();
    assert!(matches!(err.kind, FormatErrorKind::Read(_)), "{err}");
    assert_eq!(err.path, path);
    assert!(err.to_string().starts_with(&format!("{}: cannot read: ", path.display())), "{err}");
}

#[test]
fn writing_an_invalid_cloud_or_to_a_bad_directory_fails_with_the_path() {
    let mut cloud = random_cloud(3, ALL_CHANNELS, 5);
    let path = scratch("no-such-dir/out.ply");
    let err = formats::write_cloud(&path, &cloud, FileFormat::Ply(PlyEncoding::Ascii)).unwrap_err();
    assert!(matches!(err.kind, FormatErrorKind::Write(_)), "{err}");
    assert!(err.to_string().starts_with(&path.display().to_string()), "{err}");

    cloud.ring.as_mut().unwrap().pop();
    let path = scratch("invalid.ply");
    let err = formats::write_cloud(&path, &cloud, FileFormat::Ply(PlyEncoding::Ascii)).unwrap_err();
    assert!(matches!(err.kind, FormatErrorKind::InvalidCloud(_)), "{err}");
    assert!(!path.exists());
}

#[test]
fn corrupt_lzf_in_a_pcd_is_an_error() {
    let header = format!("{XYZ}POINTS 1\n");
    // A match reaching 6 bytes back when nothing is decoded yet.
    let block = [4, 0, 0, 0, 12, 0, 0, 0, 0x20, 5, 0, 0];
    let err = pcd::parse(&pcd_file(&header, "binary_compressed", &block)).unwrap_err();
    assert!(matches!(err, ParseError::Lzf(formats::LzfError::BadReference { .. })), "{err}");
}

// ---------------------------------------------------------------------------------------------
// Arbitrary input never panics

/// Small valid files of every encoding, to mutate.
fn seeds() -> Vec<(FileFormat, Vec<u8>)> {
    let cloud = random_cloud(4, ALL_CHANNELS, 3);
    FileFormat::ALL.into_iter().map(|f| (f, formats::encode(&cloud, f))).collect()
}

/// Headers of each kind, to put arbitrary bodies behind.
const HEADERS: [&str; 6] = [
    "FIELDS x y z t\nSIZE 4 4 4 2\nTYPE F F F U\nPOINTS 3\nDATA ascii\n",
    "FIELDS x y z t\nSIZE 4 8 1 2\nTYPE F F I U\nCOUNT 1 2 1 3\nPOINTS 3\nDATA binary\n",
    "FIELDS x y z t\nSIZE 4 4 4 2\nTYPE F F F U\nPOINTS 3\nDATA binary_compressed\n",
    "ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int i\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
    "ply\nformat binary_little_endian 1.0\nelement face 2\nproperty list uchar int i\nelement vertex 3\nproperty double x\nproperty short y\nproperty float z\nproperty list char uchar n\nend_header\n",
    "ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nproperty ushort ring\nend_header\n",
];

/// Runs every parser on `bytes`; whatever they accept must uphold the cloud invariant.
fn parse_all(bytes: &[u8]) {
    let results = [kitti::parse(bytes), pcd::parse(bytes), ply::parse(bytes)];
    for read in results.into_iter().flatten() {
        read.cloud.validate().unwrap();
    }
}

proptest! {
    #[test]
    fn arbitrary_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..2000)) {
        parse_all(&bytes);
    }

    #[test]
    fn arbitrary_bodies_behind_valid_headers_never_panic(
        header in 0..HEADERS.len(),
        body in proptest::collection::vec(any::<u8>(), 0..400),
    ) {
        let mut bytes = HEADERS[header].as_bytes().to_vec();
        bytes.extend(body);
        parse_all(&bytes);
    }

    #[test]
    fn mutated_valid_files_never_panic(
        seed in 0..FileFormat::ALL.len(),
        edits in proptest::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
        cut in any::<prop::sample::Index>(),
    ) {
        let (format, mut bytes) = seeds().swap_remove(seed);
        for (at, value) in edits {
            let i = at.index(bytes.len());
            bytes[i] = value;
        }
        bytes.truncate(cut.index(bytes.len() + 1));
        if let Ok(read) = parse(format, &bytes) {
            read.cloud.validate().unwrap();
        }
    }
}
