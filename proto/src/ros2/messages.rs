//! The ROS 2 messages the fleet publishes, as their IDL lays them out, and their CDR payloads: the
//! 4-byte encapsulation header (plain CDR, little endian) and the body, each primitive aligned to
//! its size from the body's start. `cdr_encoding` lays out the body from these serde types; field
//! order is the message definition's, which is the wire's.

use byteorder::LittleEndian;
use nalgebra::{Isometry3, UnitQuaternion};
use serde::{Deserialize, Serialize};

use crate::Timestamp;

/// The encapsulation header of a little-endian plain CDR payload (CDR_LE, options 0).
pub const CDR_LE: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Why a payload could not be made or read.
#[derive(Debug, thiserror::Error)]
pub enum CdrError {
    /// The serializer refused the message.
    #[error("CDR: {0}")]
    Cdr(String),
    /// The payload does not start with the little-endian plain CDR header.
    #[error("payload does not start with the CDR_LE encapsulation header (00 01 00 00)")]
    Encapsulation,
}

/// A message's CDR payload: [`CDR_LE`] and its body.
pub fn to_cdr<T: Serialize>(message: &T) -> Result<Vec<u8>, CdrError> {
    let body = cdr_encoding::to_vec::<T, LittleEndian>(message).map_err(|e| CdrError::Cdr(e.to_string()))?;
    let mut payload = Vec::with_capacity(CDR_LE.len() + body.len());
    payload.extend_from_slice(&CDR_LE);
    payload.extend_from_slice(&body);
    Ok(payload)
}

/// A message read back from a little-endian CDR payload.
pub fn from_cdr<T: for<'de> Deserialize<'de>>(payload: &[u8]) -> Result<T, CdrError> {
    let body = payload.strip_prefix(&CDR_LE[..]).ok_or(CdrError::Encapsulation)?;
    cdr_encoding::from_bytes::<T, LittleEndian>(body).map(|(m, _)| m).map_err(|e| CdrError::Cdr(e.to_string()))
}

/// builtin_interfaces/msg/Time.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds within the second.
    pub nanosec: u32,
}

impl From<&Timestamp> for Time {
    fn from(t: &Timestamp) -> Self {
        Time { sec: t.sec.clamp(0, i64::from(i32::MAX)) as i32, nanosec: t.nanosec }
    }
}

impl Time {
    /// A time from seconds (negative and non-finite clamp to 0).
    pub fn from_secs_f64(secs: f64) -> Self {
        let secs = if secs.is_finite() { secs.max(0.0) } else { 0.0 };
        let whole = secs.floor();
        let nanosec = ((secs - whole) * 1e9).round().min(999_999_999.0) as u32;
        Time { sec: whole.min(i32::MAX as f64) as i32, nanosec }
    }
}

/// std_msgs/msg/Header.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    /// When the data was taken.
    pub stamp: Time,
    /// The frame the data is in.
    pub frame_id: String,
}

/// sensor_msgs/msg/PointField.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PointField {
    /// Channel name.
    pub name: String,
    /// Byte offset within a point.
    pub offset: u32,
    /// Datatype: 1 INT8 .. 8 FLOAT64 (the `PointField` constants below).
    pub datatype: u8,
    /// Elements in the field.
    pub count: u32,
}

impl PointField {
    /// `uint8` datatype.
    pub const UINT8: u8 = 2;
    /// `uint16` datatype.
    pub const UINT16: u8 = 4;
    /// `uint32` datatype.
    pub const UINT32: u8 = 6;
    /// `float32` datatype.
    pub const FLOAT32: u8 = 7;
    /// `float64` datatype.
    pub const FLOAT64: u8 = 8;

    /// One element of `datatype` named `name` at `offset`.
    pub fn new(name: &str, offset: u32, datatype: u8) -> Self {
        PointField { name: name.into(), offset, datatype, count: 1 }
    }
}

/// sensor_msgs/msg/PointCloud2.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PointCloud2 {
    /// Stamp and frame.
    pub header: Header,
    /// Rows (1: unorganised).
    pub height: u32,
    /// Points per row.
    pub width: u32,
    /// The channels of each point.
    pub fields: Vec<PointField>,
    /// Byte order of `data`.
    pub is_bigendian: bool,
    /// Bytes per point.
    pub point_step: u32,
    /// Bytes per row.
    pub row_step: u32,
    /// The points.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
    /// No invalid (NaN) points.
    pub is_dense: bool,
}

/// geometry_msgs/msg/Point and geometry_msgs/msg/Vector3 (the same layout).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Vector3 {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
}

/// geometry_msgs/msg/Quaternion.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 }
    }
}

impl From<&UnitQuaternion<f64>> for Quaternion {
    fn from(q: &UnitQuaternion<f64>) -> Self {
        Quaternion { x: q.i, y: q.j, z: q.k, w: q.w }
    }
}

/// geometry_msgs/msg/Pose.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position.
    pub position: Vector3,
    /// Orientation.
    pub orientation: Quaternion,
}

impl From<&Isometry3<f64>> for Pose {
    fn from(p: &Isometry3<f64>) -> Self {
        let t = p.translation.vector;
        Pose { position: Vector3 { x: t.x, y: t.y, z: t.z }, orientation: Quaternion::from(&p.rotation) }
    }
}

/// geometry_msgs/msg/PoseStamped.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    /// Stamp and frame.
    pub header: Header,
    /// The pose.
    pub pose: Pose,
}

/// nav_msgs/msg/Path.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Path {
    /// Stamp and frame.
    pub header: Header,
    /// The poses, oldest first.
    pub poses: Vec<PoseStamped>,
}

/// geometry_msgs/msg/Transform.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Transform {
    /// Translation.
    pub translation: Vector3,
    /// Rotation.
    pub rotation: Quaternion,
}

impl From<&Isometry3<f64>> for Transform {
    fn from(p: &Isometry3<f64>) -> Self {
        let pose = Pose::from(p);
        Transform { translation: pose.position, rotation: pose.orientation }
    }
}

/// geometry_msgs/msg/TransformStamped.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TransformStamped {
    /// Stamp and parent frame.
    pub header: Header,
    /// The child frame.
    pub child_frame_id: String,
    /// Child to parent.
    pub transform: Transform,
}

/// tf2_msgs/msg/TFMessage.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TfMessage {
    /// The transforms.
    pub transforms: Vec<TransformStamped>,
}

/// A 6x6 row-major covariance (`float64[36]`): a fixed-size array, laid out without a length.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Covariance(pub [f64; 36]);

impl Default for Covariance {
    fn default() -> Self {
        Covariance([0.0; 36])
    }
}

impl Serialize for Covariance {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        use serde::ser::SerializeTuple;
        let mut tuple = serializer.serialize_tuple(36)?;
        for v in &self.0 {
            tuple.serialize_element(v)?;
        }
        tuple.end()
    }
}

impl<'de> Deserialize<'de> for Covariance {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        struct Visitor;
        impl<'de> serde::de::Visitor<'de> for Visitor {
            type Value = Covariance;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("36 float64")
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<Covariance, A::Error> {
                let mut out = [0.0; 36];
                for (i, v) in out.iter_mut().enumerate() {
                    *v = seq.next_element()?.ok_or_else(|| serde::de::Error::invalid_length(i, &self))?;
                }
                Ok(Covariance(out))
            }
        }
        deserializer.deserialize_tuple(36, Visitor)
    }
}

/// geometry_msgs/msg/PoseWithCovariance.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseWithCovariance {
    /// The pose.
    pub pose: Pose,
    /// Its covariance (x, y, z, rotation about x, y, z).
    pub covariance: Covariance,
}

/// geometry_msgs/msg/Twist.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Twist {
    /// Linear velocity.
    pub linear: Vector3,
    /// Angular velocity.
    pub angular: Vector3,
}

/// geometry_msgs/msg/TwistWithCovariance.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TwistWithCovariance {
    /// The twist.
    pub twist: Twist,
    /// Its covariance.
    pub covariance: Covariance,
}

/// nav_msgs/msg/Odometry.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Odometry {
    /// Stamp and the pose's frame.
    pub header: Header,
    /// The twist's frame.
    pub child_frame_id: String,
    /// The pose.
    pub pose: PoseWithCovariance,
    /// The velocity.
    pub twist: TwistWithCovariance,
}

/// std_msgs/msg/String.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StringMessage {
    /// The text.
    pub data: String,
}

/// A PointCloud2 of float32 x, y, z and intensity, then `extra` uint32 channels, one row, from
/// points given as (position, intensity, extra values).
pub fn xyzi_cloud(
    header: Header,
    extra: &[&str],
    points: impl ExactSizeIterator<Item = ([f32; 4], Vec<u32>)>,
) -> PointCloud2 {
    let mut fields: Vec<PointField> = ["x", "y", "z", "intensity"]
        .iter()
        .enumerate()
        .map(|(i, n)| PointField::new(n, 4 * i as u32, PointField::FLOAT32))
        .collect();
    for (i, name) in extra.iter().enumerate() {
        fields.push(PointField::new(name, 16 + 4 * i as u32, PointField::UINT32));
    }
    let point_step = 16 + 4 * extra.len() as u32;
    let width = points.len() as u32;
    let mut data = Vec::with_capacity(points.len() * point_step as usize);
    let mut is_dense = true;
    for (xyzi, values) in points {
        is_dense &= xyzi[..3].iter().all(|v| v.is_finite());
        for v in xyzi {
            data.extend_from_slice(&v.to_le_bytes());
        }
        for k in 0..extra.len() {
            data.extend_from_slice(&values.get(k).copied().unwrap_or(0).to_le_bytes());
        }
    }
    PointCloud2 {
        header,
        height: 1,
        width,
        fields,
        is_bigendian: false,
        point_step,
        row_step: point_step * width,
        data,
        is_dense,
    }
}
