//! sensor_msgs/PointCloud2: the ROS 1 and CDR (ROS 2) wire formats, and conversion to a [`PointCloud`].
//!
//! Both wire formats carry the same fields; they differ in the header (ROS 1 has a `seq`), in
//! alignment (CDR aligns each primitive to its size, counted from the end of the 4-byte
//! encapsulation header; ROS 1 packs) and in strings (CDR counts and stores a trailing NUL).
//! The point bytes are borrowed from the message, never copied before conversion.

use cloud::formats::Scalar;
use cloud::{Channels, PointCloud};
use nalgebra::Point3;

/// Why a PointCloud2 message could not be decoded or converted.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum MessageError {
    /// The message ends before a field it must hold.
    #[error("message of {len} bytes ends while reading {what} ({needed} bytes at byte {at})")]
    Short {
        /// The field being read.
        what: &'static str,
        /// Byte offset of the field in the message.
        at: usize,
        /// Bytes the field needs.
        needed: usize,
        /// Length of the message.
        len: usize,
    },
    /// A CDR encapsulation other than plain CDR (XCDR1), little or big endian.
    #[error("CDR encapsulation {0:#06x} is not supported (only 0x0000 CDR_BE and 0x0001 CDR_LE)")]
    Encapsulation(u16),
    /// A required coordinate field is absent.
    #[error("no `{0}` field")]
    MissingField(&'static str),
    /// A field datatype outside PointCloud2's INT8 (1) ..= FLOAT64 (8).
    #[error("field `{name}` has datatype {code}, PointCloud2 defines 1 (INT8) to 8 (FLOAT64)")]
    Datatype {
        /// The field's name.
        name: String,
        /// The datatype code found.
        code: u8,
    },
    /// A field whose bytes extend past the end of a point.
    #[error("field `{name}` ({size} bytes at offset {offset}) does not fit in point_step {point_step}")]
    FieldOutsidePoint {
        /// The field's name.
        name: String,
        /// Its offset within a point.
        offset: u32,
        /// Its size in bytes.
        size: u32,
        /// Bytes per point.
        point_step: u32,
    },
    /// Rows shorter than their points.
    #[error("row_step {row_step} is smaller than width {width} x point_step {point_step}")]
    RowStep {
        /// Bytes per row.
        row_step: u32,
        /// Points per row.
        width: u32,
        /// Bytes per point.
        point_step: u32,
    },
    /// Point data shorter than the declared rows.
    #[error("data holds {len} bytes, height {height} x row_step {row_step} needs {needed}")]
    DataTooShort {
        /// Bytes present.
        len: usize,
        /// Rows declared.
        height: u32,
        /// Bytes per row.
        row_step: u32,
        /// Bytes needed.
        needed: u64,
    },
}

/// The wire format a message is serialised in.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WireFormat {
    /// ROS 1 serialisation (bags, and MCAP channels with message encoding `ros1`).
    Ros1,
    /// OMG CDR with its encapsulation header (ROS 2, MCAP channels with message encoding `cdr`).
    Cdr,
}

/// One PointField: a named channel at `offset` within each point.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PointField {
    /// Field name (`x`, `intensity`, ...).
    pub name: String,
    /// Byte offset within a point.
    pub offset: u32,
    /// Datatype code, 1 (INT8) to 8 (FLOAT64).
    pub datatype: u8,
    /// Number of elements (only the first is read).
    pub count: u32,
}

/// A decoded PointCloud2 whose point bytes borrow from the message.
#[derive(Clone, Debug, PartialEq)]
pub struct PointCloud2<'a> {
    /// header.stamp in seconds.
    pub stamp: f64,
    /// Rows (1 for an unorganised cloud).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// The channels of each point.
    pub fields: Vec<PointField>,
    /// Byte order of the point data.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The point bytes.
    pub data: &'a [u8],
}

/// A converted cloud and how many points had a non-finite coordinate and were dropped.
#[derive(Clone, Debug, PartialEq)]
pub struct Converted {
    /// The finite points.
    pub cloud: PointCloud,
    /// Points dropped for a NaN or infinite coordinate.
    pub dropped_non_finite: usize,
}

/// Decodes a serialised PointCloud2 in `format`.
pub fn decode(bytes: &[u8], format: WireFormat) -> Result<PointCloud2<'_>, MessageError> {
    match format {
        WireFormat::Ros1 => decode_ros1(bytes),
        WireFormat::Cdr => decode_cdr(bytes),
    }
}

/// Decodes the ROS 1 serialisation: `Header{seq, stamp{secs u32, nsecs u32}, frame_id}` first.
pub fn decode_ros1(bytes: &[u8]) -> Result<PointCloud2<'_>, MessageError> {
    let mut c = Cursor { bytes, pos: 0, origin: 0, big_endian: false, wire: WireFormat::Ros1 };
    c.u32("header.seq")?;
    let stamp = f64::from(c.u32("header.stamp.secs")?) + f64::from(c.u32("header.stamp.nsecs")?) * 1e-9;
    c.string("header.frame_id")?;
    decode_body(&mut c, stamp)
}

/// Decodes CDR: a 4-byte encapsulation header, then `Header{stamp{sec i32, nanosec u32}, frame_id}`.
pub fn decode_cdr(bytes: &[u8]) -> Result<PointCloud2<'_>, MessageError> {
    let mut c = Cursor { bytes, pos: 0, origin: 0, big_endian: true, wire: WireFormat::Cdr };
    let kind = c.u16("encapsulation header")?;
    c.u16("encapsulation options")?;
    c.big_endian = match kind {
        0x0000 => true,
        0x0001 => false,
        other => return Err(MessageError::Encapsulation(other)),
    };
    c.origin = c.pos;
    let stamp = f64::from(c.i32("header.stamp.sec")?) + f64::from(c.u32("header.stamp.nanosec")?) * 1e-9;
    c.string("header.frame_id")?;
    decode_body(&mut c, stamp)
}

/// The fields after the header, identical in both formats up to alignment.
fn decode_body<'a>(c: &mut Cursor<'a>, stamp: f64) -> Result<PointCloud2<'a>, MessageError> {
    let height = c.u32("height")?;
    let width = c.u32("width")?;
    let fields = decode_fields(c)?;
    let is_bigendian = c.u8("is_bigendian")? != 0;
    let point_step = c.u32("point_step")?;
    let row_step = c.u32("row_step")?;
    let len = c.u32("data length")? as usize;
    let data = c.take(len, "data")?;
    // is_dense is not read: finiteness is checked per point anyway.
    Ok(PointCloud2 { stamp, height, width, fields, is_bigendian, point_step, row_step, data })
}

/// The `fields` sequence; the count is not trusted to size an allocation.
fn decode_fields(c: &mut Cursor<'_>) -> Result<Vec<PointField>, MessageError> {
    let count = c.u32("fields length")?;
    let mut fields = Vec::new();
    for _ in 0..count {
        let name = c.string("field name")?;
        let offset = c.u32("field offset")?;
        let datatype = c.u8("field datatype")?;
        let count = c.u32("field count")?;
        fields.push(PointField { name, offset, datatype, count });
    }
    Ok(fields)
}

/// A read position in a serialised message.
struct Cursor<'a> {
    bytes: &'a [u8],
    pos: usize,
    /// Where CDR alignment is counted from (the end of the encapsulation header).
    origin: usize,
    big_endian: bool,
    wire: WireFormat,
}

impl<'a> Cursor<'a> {
    /// The next `n` bytes.
    fn take(&mut self, n: usize, what: &'static str) -> Result<&'a [u8], MessageError> {
        let short = || MessageError::Short { what, at: self.pos, needed: n, len: self.bytes.len() };
        let end = self.pos.checked_add(n).ok_or_else(short)?;
        let slice = self.bytes.get(self.pos..end).ok_or_else(short)?;
        self.pos = end;
        Ok(slice)
    }

    /// The next `N` bytes of a primitive, after CDR alignment to `N`.
    fn primitive<const N: usize>(&mut self, what: &'static str) -> Result<[u8; N], MessageError> {
        if self.wire == WireFormat::Cdr {
            let misalignment = (self.pos - self.origin) % N;
            if misalignment != 0 {
                self.take(N - misalignment, what)?;
            }
        }
        let mut out = [0; N];
        out.copy_from_slice(self.take(N, what)?);
        if self.big_endian {
            out.reverse();
        }
        Ok(out)
    }

    fn u8(&mut self, what: &'static str) -> Result<u8, MessageError> {
        Ok(self.primitive::<1>(what)?[0])
    }

    fn u16(&mut self, what: &'static str) -> Result<u16, MessageError> {
        Ok(u16::from_le_bytes(self.primitive(what)?))
    }

    fn u32(&mut self, what: &'static str) -> Result<u32, MessageError> {
        Ok(u32::from_le_bytes(self.primitive(what)?))
    }

    fn i32(&mut self, what: &'static str) -> Result<i32, MessageError> {
        Ok(i32::from_le_bytes(self.primitive(what)?))
    }

    /// A length-prefixed string; CDR counts and stores a trailing NUL, ROS 1 does not.
    fn string(&mut self, what: &'static str) -> Result<String, MessageError> {
        let len = self.u32(what)? as usize;
        let bytes = self.take(len, what)?;
        let bytes = match self.wire {
            WireFormat::Cdr => bytes.strip_suffix(&[0]).unwrap_or(bytes),
            WireFormat::Ros1 => bytes,
        };
        Ok(String::from_utf8_lossy(bytes).into_owned())
    }
}

/// The scalar type of a PointField datatype code, 1 (INT8) to 8 (FLOAT64).
fn datatype(code: u8) -> Option<Scalar> {
    use Scalar::*;
    [I8, U8, I16, U16, I32, U32, F32, F64].get(usize::from(code).checked_sub(1)?).copied()
}

/// Reads one field out of a point's bytes.
#[derive(Clone, Copy, Debug)]
struct FieldReader {
    offset: usize,
    datatype: Scalar,
    big_endian: bool,
}

impl FieldReader {
    /// The field's value in `point`; the layout check guarantees it lies inside, so a miss reads NaN.
    fn read(&self, point: &[u8]) -> f64 {
        point.get(self.offset..).and_then(|b| self.datatype.decode(b, self.big_endian)).unwrap_or(f64::NAN)
    }
}

/// Where each channel sits in a point.
struct Layout {
    xyz: [FieldReader; 3],
    intensity: Option<FieldReader>,
    ring: Option<FieldReader>,
    time: Option<FieldReader>,
}

impl Layout {
    /// Resolves the channels of `msg` by field name (case-insensitive), checking each fits a point.
    ///
    /// Intensity: `intensity`, else a name containing `intensity`, else `i`, else a name containing
    /// `reflectivity` or `reflectance`. Ring: `ring`. Time: `time`, else `t`, else `timestamp`.
    fn new(msg: &PointCloud2<'_>) -> Result<Self, MessageError> {
        let find = |pred: &dyn Fn(&str) -> bool| -> Result<Option<FieldReader>, MessageError> {
            msg.fields.iter().find(|f| pred(&f.name.to_ascii_lowercase())).map(|f| field_reader(msg, f)).transpose()
        };
        let named = |name: &'static str| find(&|n| n == name);
        let required = |name: &'static str| named(name)?.ok_or(MessageError::MissingField(name));
        let intensity = first_some([
            named("intensity")?,
            find(&|n| n.contains("intensity"))?,
            named("i")?,
            find(&|n| n.contains("reflectivity") || n.contains("reflectance"))?,
        ]);
        Ok(Layout {
            xyz: [required("x")?, required("y")?, required("z")?],
            intensity,
            ring: named("ring")?,
            time: first_some([named("time")?, named("t")?, named("timestamp")?]),
        })
    }

    fn channels(&self) -> Channels {
        Channels { intensity: self.intensity.is_some(), ring: self.ring.is_some(), time: self.time.is_some() }
    }
}

/// The first present option.
fn first_some<const N: usize>(options: [Option<FieldReader>; N]) -> Option<FieldReader> {
    options.into_iter().flatten().next()
}

/// A reader for `field`, if its datatype is valid and it lies inside a point.
fn field_reader(msg: &PointCloud2<'_>, field: &PointField) -> Result<FieldReader, MessageError> {
    let datatype = datatype(field.datatype)
        .ok_or_else(|| MessageError::Datatype { name: field.name.clone(), code: field.datatype })?;
    let size = datatype.size() as u32;
    if field.offset.checked_add(size).is_none_or(|end| end > msg.point_step) {
        return Err(MessageError::FieldOutsidePoint {
            name: field.name.clone(),
            offset: field.offset,
            size,
            point_step: msg.point_step,
        });
    }
    Ok(FieldReader { offset: field.offset as usize, datatype, big_endian: msg.is_bigendian })
}

impl PointCloud2<'_> {
    /// Converts to a [`PointCloud`], row by row, dropping points with a non-finite coordinate.
    ///
    /// Any datatype converts to the channel's type: intensity to f32; ring to u16 (rounded, clamped
    /// to 0..=65535). Integer time fields are nanoseconds, float ones seconds (as in
    /// `cloud::formats`); the time channel is then made relative to the earliest point, so drivers
    /// that stamp the sweep end (negative offsets) or store absolute times all give
    /// seconds-since-sweep-start.
    pub fn to_cloud(&self) -> Result<Converted, MessageError> {
        let layout = Layout::new(self)?;
        self.check_extent()?;
        let n = self.height as usize * self.width as usize;
        let mut cloud = PointCloud::with_capacity(n, layout.channels());
        let mut times = Vec::with_capacity(if layout.time.is_some() { n } else { 0 });
        let mut dropped_non_finite = 0;
        for point in self.points() {
            let [x, y, z] = layout.xyz.map(|f| f.read(point) as f32);
            if !(x.is_finite() && y.is_finite() && z.is_finite()) {
                dropped_non_finite += 1;
                continue;
            }
            cloud.points.push(Point3::new(x, y, z));
            push_channels(&mut cloud, &mut times, &layout, point);
        }
        if let Some(time) = &layout.time {
            cloud.time = Some(relative_seconds(&times, time.datatype));
        }
        Ok(Converted { cloud, dropped_non_finite })
    }

    /// Checks that rows hold their points and the data holds the rows.
    fn check_extent(&self) -> Result<(), MessageError> {
        if u64::from(self.row_step) < u64::from(self.width) * u64::from(self.point_step) {
            return Err(MessageError::RowStep {
                row_step: self.row_step,
                width: self.width,
                point_step: self.point_step,
            });
        }
        let needed = u64::from(self.height) * u64::from(self.row_step);
        if (self.data.len() as u64) < needed {
            return Err(MessageError::DataTooShort {
                len: self.data.len(),
                height: self.height,
                row_step: self.row_step,
                needed,
            });
        }
        Ok(())
    }

    /// Each point's bytes, row-major; [`Self::check_extent`] must have passed.
    fn points(&self) -> impl Iterator<Item = &[u8]> {
        let (row_step, point_step) = (self.row_step as usize, self.point_step as usize);
        let rows = self.data.chunks(row_step.max(1)).take(self.height as usize);
        rows.flat_map(move |row| row.chunks(point_step.max(1)).take(self.width as usize))
    }
}

/// Appends the optional channels of `point`; times are kept in f64 until made relative.
fn push_channels(cloud: &mut PointCloud, times: &mut Vec<f64>, layout: &Layout, point: &[u8]) {
    if let (Some(v), Some(f)) = (&mut cloud.intensity, &layout.intensity) {
        v.push(f.read(point) as f32);
    }
    if let (Some(v), Some(f)) = (&mut cloud.ring, &layout.ring) {
        // `as` saturates (and maps NaN to 0), which is the clamp we want.
        v.push(f.read(point).round() as u16);
    }
    if let Some(f) = &layout.time {
        times.push(f.read(point));
    }
}

/// Times in seconds since the earliest one; integer fields are nanoseconds.
fn relative_seconds(raw: &[f64], datatype: Scalar) -> Vec<f32> {
    let scale = if datatype.is_integer() { 1e-9 } else { 1.0 };
    let start = raw.iter().copied().filter(|t| t.is_finite()).fold(f64::INFINITY, f64::min);
    raw.iter().map(|&t| ((t - start) * scale) as f32).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ROS 1 PointCloud2 with the given fields, one point per `points` entry (raw bytes).
    fn ros1_message(fields: &[(&str, u32, u8)], point_step: u32, points: &[Vec<u8>]) -> Vec<u8> {
        let mut m = Vec::new();
        let u32le = |m: &mut Vec<u8>, v: u32| m.extend_from_slice(&v.to_le_bytes());
        u32le(&mut m, 7); // seq
        u32le(&mut m, 100);
        u32le(&mut m, 500_000_000);
        u32le(&mut m, 4);
        m.extend_from_slice(b"lidr");
        u32le(&mut m, 1);
        u32le(&mut m, points.len() as u32);
        u32le(&mut m, fields.len() as u32);
        for (name, offset, datatype) in fields {
            u32le(&mut m, name.len() as u32);
            m.extend_from_slice(name.as_bytes());
            u32le(&mut m, *offset);
            m.push(*datatype);
            u32le(&mut m, 1);
        }
        m.push(0);
        u32le(&mut m, point_step);
        u32le(&mut m, point_step * points.len() as u32);
        let data: Vec<u8> = points.concat();
        u32le(&mut m, data.len() as u32);
        m.extend_from_slice(&data);
        m.push(1);
        m
    }

    #[test]
    fn every_datatype_converts_to_the_same_value() {
        type Encode = fn(i8) -> Vec<u8>;
        let encodings: [(u8, Encode); 8] = [
            (1, |v| v.to_le_bytes().to_vec()),
            (2, |v| (v as u8).to_le_bytes().to_vec()),
            (3, |v| i16::from(v).to_le_bytes().to_vec()),
            (4, |v| (v as u16).to_le_bytes().to_vec()),
            (5, |v| i32::from(v).to_le_bytes().to_vec()),
            (6, |v| (v as u32).to_le_bytes().to_vec()),
            (7, |v| f32::from(v).to_le_bytes().to_vec()),
            (8, |v| f64::from(v).to_le_bytes().to_vec()),
        ];
        for (code, encode) in encodings {
            let size = datatype(code).unwrap().size() as u32;
            let fields = [("x", 0, code), ("y", size, code), ("z", 2 * size, code)];
            let point = [encode(3), encode(4), encode(5)].concat();
            let bytes = ros1_message(&fields, 3 * size, &[point]);
            let msg = decode_ros1(&bytes).unwrap();
            assert_eq!(msg.stamp, 100.5);
            let out = msg.to_cloud().unwrap();
            assert_eq!(out.cloud.points, vec![Point3::new(3.0, 4.0, 5.0)], "datatype {code}");
        }
    }

    #[test]
    fn integer_time_is_nanoseconds_and_made_relative() {
        let fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("t", 12, 6)];
        let point = |t: u32| [1f32, 2.0, 3.0].iter().flat_map(|v| v.to_le_bytes()).chain(t.to_le_bytes()).collect();
        let bytes = ros1_message(&fields, 16, &[point(2_000_000), point(52_000_000)]);
        let out = decode_ros1(&bytes).unwrap().to_cloud().unwrap();
        assert_eq!(out.cloud.time, Some(vec![0.0, 0.05]));
    }

    #[test]
    fn bad_layouts_are_reported() {
        let fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 9)];
        let bytes = ros1_message(&fields, 12, &[vec![0; 12]]);
        let err = decode_ros1(&bytes).unwrap().to_cloud().unwrap_err();
        assert_eq!(err, MessageError::Datatype { name: "z".into(), code: 9 });
        let fields = [("x", 0, 7), ("y", 4, 7), ("z", 10, 7)];
        let bytes = ros1_message(&fields, 12, &[vec![0; 12]]);
        let err = decode_ros1(&bytes).unwrap().to_cloud().unwrap_err();
        assert!(matches!(err, MessageError::FieldOutsidePoint { offset: 10, .. }), "{err}");
        let fields = [("x", 0, 7), ("y", 4, 7)];
        let bytes = ros1_message(&fields, 12, &[vec![0; 12]]);
        assert_eq!(decode_ros1(&bytes).unwrap().to_cloud().unwrap_err(), MessageError::MissingField("z"));
    }

    #[test]
    fn every_prefix_of_a_message_is_an_error_not_a_panic() {
        let fields = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)];
        let bytes = ros1_message(&fields, 12, &[vec![0; 12], vec![1; 12]]);
        for cut in 0..bytes.len() - 1 {
            assert!(decode_ros1(&bytes[..cut]).is_err(), "cut at {cut}");
        }
    }
}
