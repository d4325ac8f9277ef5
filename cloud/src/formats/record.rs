//! What PCD and PLY share: numeric field types, which named field feeds which cloud channel,
//! assembling the cloud while dropping non-finite points, and splitting text into lines.

use nalgebra::Point3;

use super::{LoadedCloud, ParseError};
use crate::{Channels, PointCloud};

/// A numeric type a field is stored as.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Scalar {
    /// Signed 8-bit integer.
    I8,
    /// Unsigned 8-bit integer.
    U8,
    /// Signed 16-bit integer.
    I16,
    /// Unsigned 16-bit integer.
    U16,
    /// Signed 32-bit integer.
    I32,
    /// Unsigned 32-bit integer.
    U32,
    /// Signed 64-bit integer.
    I64,
    /// Unsigned 64-bit integer.
    U64,
    /// IEEE 754 single precision.
    F32,
    /// IEEE 754 double precision.
    F64,
}

/// Reads a `$t` from the start of `$bytes` in the requested byte order, as f64.
macro_rules! decode_as {
    ($t:ty, $bytes:expr, $big:expr) => {{
        let raw = $bytes.get(..size_of::<$t>())?.try_into().ok()?;
        Some((if $big { <$t>::from_be_bytes(raw) } else { <$t>::from_le_bytes(raw) }) as f64)
    }};
}

impl Scalar {
    /// Bytes one value occupies.
    pub fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::I64 | Scalar::U64 | Scalar::F64 => 8,
        }
    }

    /// True for the integer types.
    pub fn is_integer(self) -> bool {
        !matches!(self, Scalar::F32 | Scalar::F64)
    }

    /// Decodes the value at the start of `bytes`; `None` when `bytes` is too short.
    pub fn decode(self, bytes: &[u8], big_endian: bool) -> Option<f64> {
        match self {
            Scalar::I8 => decode_as!(i8, bytes, big_endian),
            Scalar::U8 => decode_as!(u8, bytes, big_endian),
            Scalar::I16 => decode_as!(i16, bytes, big_endian),
            Scalar::U16 => decode_as!(u16, bytes, big_endian),
            Scalar::I32 => decode_as!(i32, bytes, big_endian),
            Scalar::U32 => decode_as!(u32, bytes, big_endian),
            Scalar::I64 => decode_as!(i64, bytes, big_endian),
            Scalar::U64 => decode_as!(u64, bytes, big_endian),
            Scalar::F32 => decode_as!(f32, bytes, big_endian),
            Scalar::F64 => decode_as!(f64, bytes, big_endian),
        }
    }

    /// Parses one ASCII value.
    pub(crate) fn parse_text(self, token: &str) -> Option<f64> {
        match self {
            // Parsing at the field's own precision: going through f64 first could round twice
            // and break exact round trips of f32 text.
            Scalar::F32 => token.parse::<f32>().ok().map(f64::from),
            Scalar::F64 => token.parse().ok(),
            // Some tools print integer fields as "3.0"; accept any number.
            _ => token
                .parse::<i64>()
                .map(|v| v as f64)
                .or_else(|_| token.parse::<u64>().map(|v| v as f64))
                .or_else(|_| token.parse::<f64>())
                .ok(),
        }
    }
}

/// The cloud channel a file field feeds (also the order the writers emit fields in).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Role {
    X,
    Y,
    Z,
    Intensity,
    Ring,
    Time,
}

/// Number of roles, the length of a [`Values`] record.
const ROLES: usize = 6;

/// One decoded point: the value for each [`Role`], indexed by `role as usize`.
pub(crate) type Values = [f64; ROLES];

impl Role {
    /// The role a field named `name` plays and its rank: the lowest rank wins among fields
    /// competing for one role (e.g. `intensity` beats `i`, which beats `reflectivity`).
    fn of(name: &str) -> Option<(Role, u8)> {
        let name = name.to_ascii_lowercase();
        let found = match name.as_str() {
            "x" => (Role::X, 0),
            "y" => (Role::Y, 0),
            "z" => (Role::Z, 0),
            "intensity" => (Role::Intensity, 0),
            n if n.contains("intensity") => (Role::Intensity, 1),
            "i" => (Role::Intensity, 2),
            n if n.contains("reflectivity") || n.contains("reflectance") => (Role::Intensity, 3),
            "ring" => (Role::Ring, 0),
            "time" => (Role::Time, 0),
            "t" => (Role::Time, 1),
            "timestamp" => (Role::Time, 2),
            _ => return None,
        };
        Some(found)
    }

    /// The field name the writers use.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Role::X => "x",
            Role::Y => "y",
            Role::Z => "z",
            Role::Intensity => "intensity",
            Role::Ring => "ring",
            Role::Time => "time",
        }
    }

    /// The type the writers store this role as.
    pub(crate) fn written_scalar(self) -> Scalar {
        if self == Role::Ring { Scalar::U16 } else { Scalar::F32 }
    }

    /// The roles a cloud's writer emits: x y z, then each channel present.
    pub(crate) fn written(cloud: &PointCloud) -> Vec<Role> {
        let channels = cloud.channels();
        let optional =
            [(channels.intensity, Role::Intensity), (channels.ring, Role::Ring), (channels.time, Role::Time)];
        let present = optional.into_iter().filter(|&(p, _)| p).map(|(_, role)| role);
        [Role::X, Role::Y, Role::Z].into_iter().chain(present).collect()
    }
}

/// For each role, the index and type of the file field that feeds it.
#[derive(Debug)]
pub(crate) struct FieldMap {
    slots: [Option<(usize, Scalar)>; ROLES],
}

impl FieldMap {
    /// Assigns `(index, name, type)` fields to roles; x, y and z are required.
    pub(crate) fn new<'a>(fields: impl IntoIterator<Item = (usize, &'a str, Scalar)>) -> Result<Self, ParseError> {
        let mut best: [Option<(u8, usize, Scalar)>; ROLES] = [None; ROLES];
        for (index, name, scalar) in fields {
            let Some((role, rank)) = Role::of(name) else {
                continue;
            };
            let slot = &mut best[role as usize];
            if slot.is_none_or(|(held, ..)| rank < held) {
                *slot = Some((rank, index, scalar));
            }
        }
        for role in [Role::X, Role::Y, Role::Z] {
            if best[role as usize].is_none() {
                return Err(ParseError::MissingField(role.name()));
            }
        }
        Ok(Self { slots: best.map(|slot| slot.map(|(_, index, scalar)| (index, scalar))) })
    }

    /// The roles that have a field, with the field's index and type.
    pub(crate) fn roles(&self) -> impl Iterator<Item = (Role, usize, Scalar)> + '_ {
        const ALL: [Role; ROLES] = [Role::X, Role::Y, Role::Z, Role::Intensity, Role::Ring, Role::Time];
        ALL.into_iter().filter_map(|role| self.slots[role as usize].map(|(i, s)| (role, i, s)))
    }

    /// The role field `index` feeds, if any.
    pub(crate) fn role_of(&self, index: usize) -> Option<Role> {
        self.roles().find(|&(_, i, _)| i == index).map(|(role, ..)| role)
    }

    /// An empty cloud builder for the channels this file carries.
    pub(crate) fn builder(&self, capacity: usize) -> CloudBuilder {
        let has = |role: Role| self.slots[role as usize].is_some();
        let channels = Channels { intensity: has(Role::Intensity), ring: has(Role::Ring), time: has(Role::Time) };
        // Integer time fields can only be nanoseconds (Ouster's `t` is u32 ns since the sweep
        // start); float ones are taken as seconds already.
        let time_integer = self.slots[Role::Time as usize].is_some_and(|(_, s)| s.is_integer());
        CloudBuilder::new(channels, if time_integer { 1e-9 } else { 1.0 }, capacity)
    }
}

/// Collects decoded points into a cloud, dropping and counting the non-finite ones.
pub(crate) struct CloudBuilder {
    cloud: PointCloud,
    dropped: usize,
    time_scale: f64,
}

impl CloudBuilder {
    /// A builder for `channels`; time values are multiplied by `time_scale` to get seconds.
    pub(crate) fn new(channels: Channels, time_scale: f64, capacity: usize) -> Self {
        Self { cloud: PointCloud::with_capacity(capacity, channels), dropped: 0, time_scale }
    }

    /// Adds one point, unless a coordinate is NaN or infinite (also after narrowing to f32).
    pub(crate) fn push(&mut self, v: &Values) {
        let p = Point3::new(v[0] as f32, v[1] as f32, v[2] as f32);
        if !p.coords.iter().all(|c| c.is_finite()) {
            self.dropped += 1;
            return;
        }
        self.cloud.points.push(p);
        if let Some(intensity) = &mut self.cloud.intensity {
            intensity.push(v[Role::Intensity as usize] as f32);
        }
        if let Some(ring) = &mut self.cloud.ring {
            // `as` saturates: rings outside 0..=65535 (or NaN, read as 0) are not real beams.
            ring.push(v[Role::Ring as usize] as u16);
        }
        if let Some(time) = &mut self.cloud.time {
            time.push((v[Role::Time as usize] * self.time_scale) as f32);
        }
    }

    /// The cloud and how many points were dropped.
    pub(crate) fn finish(self) -> LoadedCloud {
        LoadedCloud { cloud: self.cloud, dropped_non_finite: self.dropped }
    }
}

/// A value the writers emit for one point and role.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Value {
    F32(f32),
    U16(u16),
}

impl Value {
    /// Point `i`'s value for `role`; a channel shorter than the points reads as zero.
    pub(crate) fn of(cloud: &PointCloud, role: Role, i: usize) -> Value {
        let at =
            |channel: &Option<Vec<f32>>| Value::F32(channel.as_ref().and_then(|c| c.get(i)).copied().unwrap_or(0.0));
        match role {
            Role::X | Role::Y | Role::Z => {
                let p = cloud.points.get(i).copied().unwrap_or_else(Point3::origin);
                Value::F32(p[role as usize])
            }
            Role::Intensity => at(&cloud.intensity),
            Role::Time => at(&cloud.time),
            Role::Ring => Value::U16(cloud.ring.as_ref().and_then(|r| r.get(i)).copied().unwrap_or(0)),
        }
    }

    /// Appends the value's bytes in the requested byte order.
    pub(crate) fn put_bytes(self, out: &mut Vec<u8>, big_endian: bool) {
        match (self, big_endian) {
            (Value::F32(v), false) => out.extend_from_slice(&v.to_le_bytes()),
            (Value::F32(v), true) => out.extend_from_slice(&v.to_be_bytes()),
            (Value::U16(v), false) => out.extend_from_slice(&v.to_le_bytes()),
            (Value::U16(v), true) => out.extend_from_slice(&v.to_be_bytes()),
        }
    }

    /// Appends the value as text; Rust prints the shortest decimal that parses back to the same f32.
    pub(crate) fn put_text(self, out: &mut String) {
        use std::fmt::Write;
        let written = match self {
            Value::F32(v) => write!(out, "{v}"),
            Value::U16(v) => write!(out, "{v}"),
        };
        written.expect("formatting into a String cannot fail");
    }
}

/// Text points of `cloud` in `roles` order, one line per point, values separated by spaces.
pub(crate) fn text_rows(cloud: &PointCloud, roles: &[Role]) -> String {
    let mut out = String::with_capacity(cloud.len() * roles.len() * 10);
    for i in 0..cloud.len() {
        for (k, &role) in roles.iter().enumerate() {
            if k > 0 {
                out.push(' ');
            }
            Value::of(cloud, role, i).put_text(&mut out);
        }
        out.push('\n');
    }
    out
}

/// Binary points of `cloud` in `roles` order, one record per point.
pub(crate) fn binary_rows(cloud: &PointCloud, roles: &[Role], big_endian: bool) -> Vec<u8> {
    let record: usize = roles.iter().map(|r| r.written_scalar().size()).sum();
    let mut out = Vec::with_capacity(cloud.len() * record);
    for i in 0..cloud.len() {
        for &role in roles {
            Value::of(cloud, role, i).put_bytes(&mut out, big_endian);
        }
    }
    out
}

/// Text lines of a byte slice, numbered from 1; a trailing `\r` is removed.
pub(crate) struct Lines<'a> {
    rest: &'a [u8],
    number: usize,
}

impl<'a> Lines<'a> {
    /// Lines of `bytes`.
    pub(crate) fn new(bytes: &'a [u8]) -> Self {
        Self { rest: bytes, number: 0 }
    }

    /// The bytes after the last line returned.
    pub(crate) fn rest(&self) -> &'a [u8] {
        self.rest
    }

    /// The next line holding something other than whitespace, as text.
    pub(crate) fn next_text(&mut self) -> Option<Result<(usize, &'a str), ParseError>> {
        for (number, line) in self.by_ref() {
            let text = match std::str::from_utf8(line) {
                Ok(text) => text,
                Err(_) => return Some(Err(ParseError::syntax(number, "line is not text"))),
            };
            if !text.trim_ascii().is_empty() {
                return Some(Ok((number, text)));
            }
        }
        None
    }
}

impl<'a> Iterator for Lines<'a> {
    type Item = (usize, &'a [u8]);

    fn next(&mut self) -> Option<Self::Item> {
        if self.rest.is_empty() {
            return None;
        }
        let (line, rest) = match self.rest.iter().position(|&b| b == b'\n') {
            Some(end) => (&self.rest[..end], &self.rest[end + 1..]),
            None => (self.rest, &[][..]),
        };
        self.rest = rest;
        self.number += 1;
        Some((self.number, line.strip_suffix(b"\r").unwrap_or(line)))
    }
}

/// Preallocation for `declared` records that cannot exceed what `available` bytes can hold,
/// so that a hostile header count does not reserve memory the file cannot fill.
pub(crate) fn capacity(declared: usize, available: usize, min_record_bytes: usize) -> usize {
    declared.min(available / min_record_bytes.max(1))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decode_reads_each_type_in_both_byte_orders() {
        assert_eq!(Scalar::I16.decode(&[0xff, 0xfe], false), Some(-257.0));
        assert_eq!(Scalar::I16.decode(&[0xff, 0xfe], true), Some(-2.0));
        assert_eq!(Scalar::U32.decode(&[1, 0, 0, 0, 9], false), Some(1.0));
        assert_eq!(Scalar::F64.decode(&2.5f64.to_be_bytes(), true), Some(2.5));
        assert_eq!(Scalar::U64.decode(&[0; 7], false), None);
        assert_eq!(Scalar::I8.decode(&[0x80], true), Some(-128.0));
    }

    #[test]
    fn parse_text_keeps_f32_exact_and_accepts_float_integers() {
        let v = 0.1f32 + 1e-9;
        assert_eq!(Scalar::F32.parse_text(&v.to_string()), Some(f64::from(v)));
        assert_eq!(Scalar::U8.parse_text("3.0"), Some(3.0));
        assert_eq!(Scalar::U64.parse_text("18446744073709551615"), Some(u64::MAX as f64));
        assert_eq!(Scalar::I32.parse_text("x"), None);
    }

    #[test]
    fn field_names_pick_the_best_candidate() {
        let fields = [
            (0, "reflectivity", Scalar::U16),
            (1, "X", Scalar::F32),
            (2, "y", Scalar::F32),
            (3, "z", Scalar::F32),
            (4, "scalar_Intensity", Scalar::F32),
            (5, "t", Scalar::U32),
            (6, "timestamp", Scalar::F64),
        ];
        let map = FieldMap::new(fields).unwrap();
        assert_eq!(map.role_of(4), Some(Role::Intensity));
        assert_eq!(map.role_of(0), None);
        assert_eq!(map.role_of(5), Some(Role::Time));
        assert_eq!(map.role_of(1), Some(Role::X));
    }

    #[test]
    fn missing_coordinate_is_an_error() {
        let fields = [(0, "x", Scalar::F32), (1, "y", Scalar::F32)];
        assert_eq!(FieldMap::new(fields).unwrap_err(), ParseError::MissingField("z"));
    }

    #[test]
    fn lines_strip_carriage_returns_and_report_the_rest() {
        let mut lines = Lines::new(b"a\r\n\nb\nrest");
        assert_eq!(lines.next(), Some((1, &b"a"[..])));
        assert_eq!(lines.next_text().unwrap().unwrap(), (3, "b"));
        assert_eq!(lines.rest(), b"rest");
    }
}
