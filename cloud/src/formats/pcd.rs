//! PCD files (Point Cloud Library), header versions 0.5 to 0.7, with `DATA` ascii, binary or
//! binary_compressed.
//!
//! Fields of any TYPE/SIZE (F4 F8, U1 to U8, I1 to I8) and any COUNT are read; a field with
//! COUNT > 1 feeds its first element. Organized clouds (HEIGHT > 1) are flattened row by row.
//! As in PCL, older headers may omit TYPE (F), SIZE (4), COUNT (1), WIDTH and HEIGHT (POINTS x 1)
//! or POINTS (WIDTH x HEIGHT). VIEWPOINT is ignored. Binary data is little-endian.

use super::lzf;
use super::record::{CloudBuilder, FieldMap, Lines, Role, Scalar, Value, Values, binary_rows, capacity, text_rows};
use super::{LoadedCloud, ParseError};
use crate::PointCloud;

/// How PCD point data is stored (the header's DATA line).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PcdEncoding {
    /// One text line per point.
    Ascii,
    /// Little-endian records, one per point.
    Binary,
    /// LZF-compressed data stored field by field.
    BinaryCompressed,
}

impl PcdEncoding {
    /// The word on the DATA line.
    fn keyword(self) -> &'static str {
        match self {
            PcdEncoding::Ascii => "ascii",
            PcdEncoding::Binary => "binary",
            PcdEncoding::BinaryCompressed => "binary_compressed",
        }
    }
}

/// One FIELDS entry.
#[derive(Debug)]
struct Field {
    name: String,
    scalar: Scalar,
    count: usize,
}

impl Field {
    /// A field from its FIELDS, TYPE, SIZE and COUNT entries; the line numbers are for errors.
    fn parse(
        name: &str,
        (kind, size): (&str, &str),
        count: &str,
        type_line: usize,
        count_line: usize,
    ) -> Result<Field, ParseError> {
        let scalar = pcd_scalar(kind, size).ok_or_else(|| {
            let reason = format!("field {name}: unsupported TYPE {kind} SIZE {size}");
            ParseError::syntax(type_line, reason)
        })?;
        let count = count.parse::<usize>().ok().filter(|&c| c > 0).ok_or_else(|| {
            let reason = format!("field {name}: COUNT {count:?} is not a positive integer");
            ParseError::syntax(count_line, reason)
        })?;
        Ok(Field { name: name.to_owned(), scalar, count })
    }

    /// Bytes the field occupies in one point (checked against overflow when the header is read).
    fn bytes(&self) -> usize {
        self.scalar.size() * self.count
    }
}

/// A checked header.
#[derive(Debug)]
struct Header {
    fields: Vec<Field>,
    points: usize,
    /// Bytes of one point in binary data.
    point_size: usize,
    encoding: PcdEncoding,
}

impl Header {
    /// Byte offset of each field within a binary point.
    fn offsets(&self) -> Vec<usize> {
        let mut at = 0;
        self.fields
            .iter()
            .map(|f| {
                at += f.bytes();
                at - f.bytes()
            })
            .collect()
    }

    /// Bytes of all points in binary data.
    fn data_len(&self) -> Result<usize, ParseError> {
        let (points, point_size) = (self.points, self.point_size);
        points.checked_mul(point_size).ok_or(ParseError::TooLarge { points, point_size })
    }
}

/// Parses a PCD file.
pub fn parse(bytes: &[u8]) -> Result<LoadedCloud, ParseError> {
    let mut lines = Lines::new(bytes);
    let header = parse_header(&mut lines)?;
    let named = header.fields.iter().enumerate().map(|(i, f)| (i, f.name.as_str(), f.scalar));
    let map = FieldMap::new(named)?;
    match header.encoding {
        PcdEncoding::Ascii => read_ascii(lines, &header, &map),
        PcdEncoding::Binary => read_binary(lines.rest(), &header, &map),
        PcdEncoding::BinaryCompressed => read_compressed(lines.rest(), &header, &map),
    }
}

/// A header line's values with its line number.
type Entry<'a> = Option<(usize, Vec<&'a str>)>;

/// Header lines as found, before they are checked against each other.
#[derive(Default)]
struct RawHeader<'a> {
    fields: Entry<'a>,
    sizes: Entry<'a>,
    types: Entry<'a>,
    counts: Entry<'a>,
    width: Option<(usize, usize)>,
    height: Option<(usize, usize)>,
    points: Option<(usize, usize)>,
}

/// Reads header lines up to and including DATA.
fn parse_header(lines: &mut Lines<'_>) -> Result<Header, ParseError> {
    let mut raw = RawHeader::default();
    while let Some(line) = lines.next_text() {
        let (number, text) = line?;
        let mut tokens = text.split_ascii_whitespace();
        let key = tokens.next().unwrap_or_default();
        let values: Vec<&str> = tokens.collect();
        let entry = Some((number, values));
        match key.to_ascii_uppercase().as_str() {
            k if k.starts_with('#') => {}
            "VERSION" | "VIEWPOINT" => {}
            "FIELDS" | "COLUMNS" => raw.fields = entry,
            "SIZE" => raw.sizes = entry,
            "TYPE" => raw.types = entry,
            "COUNT" => raw.counts = entry,
            "WIDTH" => raw.width = single_number(entry)?,
            "HEIGHT" => raw.height = single_number(entry)?,
            "POINTS" => raw.points = single_number(entry)?,
            "DATA" => return raw.finish(data_encoding(entry)?),
            _ => {
                return Err(ParseError::syntax(number, format!("unknown header key {key:?}")));
            }
        }
    }
    Err(ParseError::MissingHeaderLine("DATA"))
}

/// The one non-negative integer of a WIDTH, HEIGHT or POINTS line.
fn single_number(entry: Entry<'_>) -> Result<Option<(usize, usize)>, ParseError> {
    let Some((line, values)) = entry else {
        return Ok(None);
    };
    match values.as_slice() {
        [v] => v
            .parse()
            .map(|n| Some((line, n)))
            .map_err(|_| ParseError::syntax(line, format!("{v:?} is not a non-negative integer"))),
        _ => Err(ParseError::syntax(line, format!("expected one value, found {}", values.len()))),
    }
}

/// The encoding named on the DATA line.
fn data_encoding(entry: Entry<'_>) -> Result<PcdEncoding, ParseError> {
    let found = entry.and_then(|(_, values)| values.first().map(|v| v.to_ascii_lowercase()));
    [PcdEncoding::Ascii, PcdEncoding::Binary, PcdEncoding::BinaryCompressed]
        .into_iter()
        .find(|e| found.as_deref() == Some(e.keyword()))
        .ok_or_else(|| ParseError::Unsupported {
            what: "DATA kind",
            found: found.unwrap_or_default(),
            expected: "ascii, binary or binary_compressed",
        })
}

impl RawHeader<'_> {
    /// Checks the lines against each other and builds the header.
    fn finish(self, encoding: PcdEncoding) -> Result<Header, ParseError> {
        let points = self.point_count()?;
        let (_, names) = self.fields.ok_or(ParseError::MissingHeaderLine("FIELDS"))?;
        let n = names.len();
        let (size_line, sizes) = per_field(self.sizes, n, "SIZE", "4")?;
        let (type_line, types) = per_field(self.types, n, "TYPE", "F")?;
        let (count_line, counts) = per_field(self.counts, n, "COUNT", "1")?;
        let type_line = type_line.max(size_line);
        let fields = (0..n)
            .map(|i| Field::parse(names[i], (types[i], sizes[i]), counts[i], type_line, count_line))
            .collect::<Result<Vec<_>, _>>()?;
        let point_size = fields
            .iter()
            .try_fold(0usize, |sum, f| f.scalar.size().checked_mul(f.count)?.checked_add(sum))
            .ok_or_else(|| ParseError::syntax(count_line, "fields add up to an impossible point size"))?;
        Ok(Header { fields, points, point_size, encoding })
    }

    /// POINTS, or WIDTH x HEIGHT when POINTS is absent; both must agree when present.
    fn point_count(&self) -> Result<usize, ParseError> {
        let height = self.height.map_or(1, |(_, h)| h);
        let grid = match self.width {
            Some((line, w)) => {
                Some(w.checked_mul(height).ok_or_else(|| ParseError::syntax(line, "WIDTH x HEIGHT overflows"))?)
            }
            None => None,
        };
        match (self.points, grid) {
            (Some((line, p)), Some(g)) if p != g => {
                Err(ParseError::syntax(line, format!("POINTS {p} differs from WIDTH x HEIGHT = {g}")))
            }
            (Some((_, p)), _) => Ok(p),
            (None, Some(g)) => Ok(g),
            (None, None) => Err(ParseError::MissingHeaderLine("POINTS")),
        }
    }
}

/// The values of a per-field line (`default` for every field when the line is absent).
fn per_field<'a>(
    entry: Entry<'a>,
    fields: usize,
    key: &str,
    default: &'a str,
) -> Result<(usize, Vec<&'a str>), ParseError> {
    match entry {
        None => Ok((0, vec![default; fields])),
        Some((line, values)) if values.len() == fields => Ok((line, values)),
        Some((line, values)) => {
            let reason = format!("{key} has {} values for {fields} fields", values.len());
            Err(ParseError::syntax(line, reason))
        }
    }
}

/// The scalar type for a TYPE letter and SIZE.
fn pcd_scalar(kind: &str, size: &str) -> Option<Scalar> {
    let scalar = match (kind.to_ascii_uppercase().as_str(), size) {
        ("F", "4") => Scalar::F32,
        ("F", "8") => Scalar::F64,
        ("U", "1") => Scalar::U8,
        ("U", "2") => Scalar::U16,
        ("U", "4") => Scalar::U32,
        ("U", "8") => Scalar::U64,
        ("I", "1") => Scalar::I8,
        ("I", "2") => Scalar::I16,
        ("I", "4") => Scalar::I32,
        ("I", "8") => Scalar::I64,
        _ => return None,
    };
    Some(scalar)
}

/// The TYPE letter the writers use for a scalar.
fn type_letter(scalar: Scalar) -> &'static str {
    match scalar {
        Scalar::F32 | Scalar::F64 => "F",
        Scalar::U8 | Scalar::U16 | Scalar::U32 | Scalar::U64 => "U",
        Scalar::I8 | Scalar::I16 | Scalar::I32 | Scalar::I64 => "I",
    }
}

/// Reads one text line per point.
fn read_ascii(mut lines: Lines<'_>, header: &Header, map: &FieldMap) -> Result<LoadedCloud, ParseError> {
    let mut first_token = Vec::with_capacity(header.fields.len());
    let mut per_point = 0;
    for field in &header.fields {
        first_token.push(per_point);
        per_point += field.count;
    }
    let wanted: Vec<(usize, Role, Scalar)> =
        map.roles().map(|(role, field, scalar)| (first_token[field], role, scalar)).collect();
    let room = capacity(header.points, lines.rest().len(), per_point.saturating_mul(2));
    let mut builder = map.builder(room);
    let mut values: Values = [0.0; 6];
    for found in 0..header.points {
        let Some(line) = lines.next_text() else {
            let what = "points".to_owned();
            return Err(ParseError::MissingRecords { what, declared: header.points, found });
        };
        let (number, text) = line?;
        parse_ascii_point(number, text, per_point, &wanted, &mut values)?;
        builder.push(&values);
    }
    Ok(builder.finish())
}

/// Fills `values` from one ASCII point line of `per_point` tokens.
fn parse_ascii_point(
    number: usize,
    text: &str,
    per_point: usize,
    wanted: &[(usize, Role, Scalar)],
    values: &mut Values,
) -> Result<(), ParseError> {
    let mut found = 0;
    for (k, token) in text.split_ascii_whitespace().enumerate() {
        found = k + 1;
        for &(_, role, scalar) in wanted.iter().filter(|w| w.0 == k) {
            values[role as usize] = scalar.parse_text(token).ok_or_else(|| {
                ParseError::syntax(number, format!("{} value {token:?} is not a number", role.name()))
            })?;
        }
    }
    if found != per_point {
        return Err(ParseError::syntax(number, format!("expected {per_point} values, found {found}")));
    }
    Ok(())
}

/// Where a role's values sit in decoded binary data: point `i`'s at `base + i * stride`.
struct Column {
    role: Role,
    base: usize,
    stride: usize,
    scalar: Scalar,
}

/// Reads point records stored one after another.
fn read_binary(body: &[u8], header: &Header, map: &FieldMap) -> Result<LoadedCloud, ParseError> {
    let needed = header.data_len()?;
    let data = body.get(..needed).ok_or(ParseError::Truncated {
        points: header.points,
        point_size: header.point_size,
        available: body.len(),
    })?;
    let offsets = header.offsets();
    let columns: Vec<Column> = map
        .roles()
        .map(|(role, field, scalar)| Column { role, base: offsets[field], stride: header.point_size, scalar })
        .collect();
    Ok(read_columns(data, header.points, &columns, map.builder(header.points)))
}

/// Reads a binary_compressed block.
fn read_compressed(body: &[u8], header: &Header, map: &FieldMap) -> Result<LoadedCloud, ParseError> {
    let data = decompress_block(body, header)?;
    // PCL stores this block field by field: every point's x, then every point's y, ...
    let offsets = header.offsets();
    let columns: Vec<Column> = map
        .roles()
        .map(|(role, field, scalar)| Column {
            role,
            base: offsets[field] * header.points,
            stride: header.fields[field].bytes(),
            scalar,
        })
        .collect();
    let builder = map.builder(header.points);
    Ok(read_columns(&data, header.points, &columns, builder))
}

/// The point data of a binary_compressed block (u32 compressed size, u32 raw size, LZF data),
/// checked against the size the header implies.
fn decompress_block(body: &[u8], header: &Header) -> Result<Vec<u8>, ParseError> {
    let expected = header.data_len()?;
    if expected == 0 {
        return Ok(Vec::new());
    }
    let block = ParseError::CompressedBlock;
    let sizes = u32_prefix(body).and_then(|(packed_len, rest)| {
        let (raw_len, rest) = u32_prefix(rest)?;
        Some((packed_len, raw_len, rest))
    });
    let Some((packed_len, raw_len, rest)) = sizes else {
        let available = body.len();
        return Err(block(format!("needs an 8-byte size prefix, file has {available} bytes after the header")));
    };
    if raw_len != expected {
        let (points, size) = (header.points, header.point_size);
        let reason = format!("{raw_len} bytes uncompressed, but the header declares {points} points of {size} bytes");
        return Err(block(reason));
    }
    let packed = rest.get(..packed_len).ok_or_else(|| {
        block(format!("{packed_len} bytes compressed, but the file has {} after the size prefix", rest.len()))
    })?;
    Ok(lzf::decompress(packed, expected)?)
}

/// A little-endian u32 at the start of `bytes`, and the bytes after it.
fn u32_prefix(bytes: &[u8]) -> Option<(usize, &[u8])> {
    let (word, rest) = bytes.split_first_chunk::<4>()?;
    Some((u32::from_le_bytes(*word) as usize, rest))
}

/// Decodes `points` points from `data`, which the caller checked holds all of them.
fn read_columns(data: &[u8], points: usize, columns: &[Column], mut builder: CloudBuilder) -> LoadedCloud {
    let mut values: Values = [0.0; 6];
    for i in 0..points {
        for c in columns {
            // Never out of range given the caller's check; NaN would drop the point, not panic.
            let at = data.get(c.base + i * c.stride..);
            values[c.role as usize] = at.and_then(|b| c.scalar.decode(b, false)).unwrap_or(f64::NAN);
        }
        builder.push(&values);
    }
    builder.finish()
}

/// Encodes a cloud as PCD v0.7: x y z (F4) and whichever of intensity (F4), ring (U2) and
/// time (F4) the cloud has.
///
/// # Panics
/// For [`PcdEncoding::BinaryCompressed`] when the point data does not fit its 32-bit size
/// fields (about 4 GiB); [`fits_compressed`] tells beforehand.
pub fn encode(cloud: &PointCloud, encoding: PcdEncoding) -> Vec<u8> {
    let roles = Role::written(cloud);
    let mut out = header_text(cloud.len(), &roles, encoding).into_bytes();
    match encoding {
        PcdEncoding::Ascii => out.extend_from_slice(text_rows(cloud, &roles).as_bytes()),
        PcdEncoding::Binary => out.extend(binary_rows(cloud, &roles, false)),
        PcdEncoding::BinaryCompressed => out.extend(compressed_block(cloud, &roles)),
    }
    out
}

/// True when `cloud` fits the 32-bit size fields of binary_compressed.
pub fn fits_compressed(cloud: &PointCloud) -> bool {
    let record: usize = Role::written(cloud).iter().map(|r| r.written_scalar().size()).sum();
    // LZF output can exceed its input by one control byte per 32 literals.
    let worst = cloud.len().checked_mul(record).and_then(|raw| raw.checked_add(raw / 32 + 1));
    worst.is_some_and(|n| u32::try_from(n).is_ok())
}

/// The header for `points` points of `roles`.
fn header_text(points: usize, roles: &[Role], encoding: PcdEncoding) -> String {
    let join = |f: &dyn Fn(Role) -> String| roles.iter().map(|&r| f(r)).collect::<Vec<_>>().join(" ");
    let names = join(&|r| r.name().to_owned());
    let sizes = join(&|r| r.written_scalar().size().to_string());
    let types = join(&|r| type_letter(r.written_scalar()).to_owned());
    let counts = join(&|_| "1".to_owned());
    format!(
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS {names}\nSIZE {sizes}\n\
         TYPE {types}\nCOUNT {counts}\nWIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n\
         POINTS {points}\nDATA {}\n",
        encoding.keyword()
    )
}

/// The binary_compressed block: sizes, then the LZF of the fields stored one after another.
fn compressed_block(cloud: &PointCloud, roles: &[Role]) -> Vec<u8> {
    let mut raw = Vec::new();
    for &role in roles {
        for i in 0..cloud.len() {
            Value::of(cloud, role, i).put_bytes(&mut raw, false);
        }
    }
    let packed = lzf::compress(&raw);
    let word =
        |n: usize| u32::try_from(n).expect("binary_compressed holds at most 4 GiB; see fits_compressed").to_le_bytes();
    [word(packed.len()), word(raw.len())].concat().into_iter().chain(packed).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEADER: &str = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n";

    #[test]
    fn old_headers_get_pcl_defaults() {
        let text = "# v0.5\nCOLUMNS x y z\nPOINTS 2\nDATA ascii\n1 2 3\n4 5 6\n";
        let read = parse(text.as_bytes()).unwrap();
        assert_eq!(read.cloud.len(), 2);
        assert_eq!(read.cloud.points[1].z, 6.0);
    }

    #[test]
    fn points_must_match_width_times_height() {
        let text = format!("{HEADER}WIDTH 2\nHEIGHT 2\nPOINTS 3\nDATA ascii\n");
        let err = parse(text.as_bytes()).unwrap_err();
        assert_eq!(err, ParseError::syntax(8, "POINTS 3 differs from WIDTH x HEIGHT = 4"));
    }

    #[test]
    fn field_lines_must_have_one_value_per_field() {
        let text = "FIELDS x y z\nSIZE 4 4\nPOINTS 0\nDATA ascii\n";
        assert_eq!(parse(text.as_bytes()).unwrap_err(), ParseError::syntax(2, "SIZE has 2 values for 3 fields"));
    }

    #[test]
    fn unsupported_type_and_size_is_named() {
        let text = "FIELDS x y z\nSIZE 4 4 2\nTYPE F F F\nPOINTS 0\nDATA ascii\n";
        let err = parse(text.as_bytes()).unwrap_err();
        assert_eq!(err, ParseError::syntax(3, "field z: unsupported TYPE F SIZE 2"));
    }

    #[test]
    fn unknown_data_kind_is_unsupported() {
        let text = format!("{HEADER}POINTS 0\nDATA bzip2\n");
        let err = parse(text.as_bytes()).unwrap_err();
        assert!(matches!(err, ParseError::Unsupported { what: "DATA kind", .. }), "{err}");
        assert!(err.to_string().contains("\"bzip2\""), "{err}");
    }

    #[test]
    fn ascii_lines_must_have_every_value() {
        let text = format!("{HEADER}POINTS 2\nDATA ascii\n1 2 3\n4 5\n");
        let err = parse(text.as_bytes()).unwrap_err();
        assert_eq!(err, ParseError::syntax(9, "expected 3 values, found 2"));
    }

    #[test]
    fn compressed_size_mismatch_is_reported() {
        let mut bytes = format!("{HEADER}POINTS 1\nDATA binary_compressed\n").into_bytes();
        bytes.extend([4, 0, 0, 0, 11, 0, 0, 0, 0, 0, 0, 0]);
        let err = parse(&bytes).unwrap_err();
        assert!(matches!(err, ParseError::CompressedBlock(_)), "{err}");
    }

    #[test]
    fn header_lists_present_channels_only() {
        let mut cloud = PointCloud::from_points(vec![nalgebra::Point3::new(1.0, 2.0, 3.0)]);
        cloud.ring = Some(vec![7]);
        let text = String::from_utf8(encode(&cloud, PcdEncoding::Ascii)).unwrap();
        assert!(text.contains("FIELDS x y z ring\nSIZE 4 4 4 2\nTYPE F F F U\n"), "{text}");
        assert!(text.ends_with("DATA ascii\n1 2 3 7\n"), "{text}");
    }
}
