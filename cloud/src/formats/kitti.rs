//! KITTI velodyne `.bin` scans: consecutive little-endian f32 records `x y z intensity`.

use super::record::CloudBuilder;
use super::{LoadedCloud, ParseError};
use crate::{Channels, PointCloud};

/// Bytes per point: four f32.
const RECORD: usize = 16;

/// Parses a KITTI scan; the result always has an intensity channel.
pub fn parse(bytes: &[u8]) -> Result<LoadedCloud, ParseError> {
    if !bytes.len().is_multiple_of(RECORD) {
        return Err(ParseError::KittiSize { len: bytes.len() });
    }
    let channels = Channels { intensity: true, ..Channels::default() };
    let mut builder = CloudBuilder::new(channels, 1.0, bytes.len() / RECORD);
    for record in bytes.chunks_exact(RECORD) {
        let mut values = [0.0; 6];
        for (value, b) in values.iter_mut().zip(record.chunks_exact(4)) {
            *value = f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]]));
        }
        builder.push(&values);
    }
    Ok(builder.finish())
}

/// Encodes a cloud as a KITTI scan; intensity is 0 where the cloud has none, ring and time are lost.
pub fn encode(cloud: &PointCloud) -> Vec<u8> {
    let mut out = Vec::with_capacity(cloud.len() * RECORD);
    for (i, p) in cloud.points.iter().enumerate() {
        let intensity = cloud.intensity.as_ref().and_then(|v| v.get(i)).copied().unwrap_or(0.0);
        for v in [p.x, p.y, p.z, intensity] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point3;

    #[test]
    fn records_decode_in_order() {
        let bytes: Vec<u8> = [1.0f32, 2.0, 3.0, 0.5, -1.0, f32::NAN, 0.0, 0.25, 4.0, 5.0, 6.0, 0.75]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let read = parse(&bytes).unwrap();
        assert_eq!(read.dropped_non_finite, 1);
        assert_eq!(read.cloud.points, vec![Point3::new(1.0, 2.0, 3.0), Point3::new(4.0, 5.0, 6.0)]);
        assert_eq!(read.cloud.intensity, Some(vec![0.5, 0.75]));
    }

    #[test]
    fn ragged_length_names_the_size() {
        assert_eq!(parse(&[0; 17]), Err(ParseError::KittiSize { len: 17 }));
        assert!(parse(&[0; 17]).unwrap_err().to_string().contains("17 bytes"));
    }

    #[test]
    fn empty_file_is_an_empty_scan() {
        assert!(parse(&[]).unwrap().cloud.is_empty());
    }
}
