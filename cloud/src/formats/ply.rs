//! PLY files: ascii, binary_little_endian and binary_big_endian.
//!
//! Points come from the `vertex` element, whose properties may have any PLY scalar type
//! (char uchar short ushort int uint float double, the int8 to float64 aliases, and int64/uint64).
//! Other elements, before or after `vertex`, and list properties are skipped. In ascii data each
//! record is one line.

use super::record::{FieldMap, Lines, Role, Scalar, Values, binary_rows, capacity, text_rows};
use super::{LoadedCloud, ParseError};
use crate::PointCloud;

/// How PLY data is stored (the header's format line).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlyEncoding {
    /// One text line per record.
    Ascii,
    /// Binary records, least significant byte first.
    BinaryLittleEndian,
    /// Binary records, most significant byte first.
    BinaryBigEndian,
}

impl PlyEncoding {
    /// The word on the format line.
    fn keyword(self) -> &'static str {
        match self {
            PlyEncoding::Ascii => "ascii",
            PlyEncoding::BinaryLittleEndian => "binary_little_endian",
            PlyEncoding::BinaryBigEndian => "binary_big_endian",
        }
    }
}

/// One property of an element.
#[derive(Debug)]
enum Property {
    /// A single value.
    Scalar { name: String, scalar: Scalar },
    /// A length of type `count`, then that many values of type `item`.
    List { count: Scalar, item: Scalar },
}

/// One element declaration: `count` records of `properties`.
#[derive(Debug)]
struct Element {
    name: String,
    count: usize,
    properties: Vec<Property>,
}

impl Element {
    /// Bytes of one binary record, unless a list property makes the size vary.
    fn fixed_size(&self) -> Option<usize> {
        self.properties
            .iter()
            .map(|p| match p {
                Property::Scalar { scalar, .. } => Some(scalar.size()),
                Property::List { .. } => None,
            })
            .sum()
    }

    /// The fewest bytes one binary record can take (every list empty).
    fn min_size(&self) -> usize {
        let size = |p: &Property| match p {
            Property::Scalar { scalar, .. } => scalar.size(),
            Property::List { count, .. } => count.size(),
        };
        self.properties.iter().map(size).sum()
    }

    /// The error for record `record` of this element failing at file offset `offset`.
    fn bad_record(&self, record: usize, offset: usize) -> ParseError {
        ParseError::BadRecord { element: self.name.clone(), record, offset }
    }

    /// The error for ascii data ending after `found` records of this element.
    fn missing_records(&self, found: usize) -> ParseError {
        let what = format!("`{}` records", self.name);
        ParseError::MissingRecords { what, declared: self.count, found }
    }
}

/// Parses a PLY file.
pub fn parse(bytes: &[u8]) -> Result<LoadedCloud, ParseError> {
    let mut lines = Lines::new(bytes);
    let (encoding, elements) = parse_header(&mut lines)?;
    let vertex_at =
        elements.iter().position(|e| e.name == "vertex").ok_or(ParseError::MissingHeaderLine("element vertex"))?;
    let scalars = elements[vertex_at].properties.iter().enumerate().filter_map(|(i, p)| match p {
        Property::Scalar { name, scalar } => Some((i, name.as_str(), *scalar)),
        Property::List { .. } => None,
    });
    let map = FieldMap::new(scalars)?;
    // Whatever follows the vertices (faces, edges) is never needed.
    let (vertex, before) = (&elements[vertex_at], &elements[..vertex_at]);
    let header_len = bytes.len() - lines.rest().len();
    match encoding {
        PlyEncoding::Ascii => read_ascii(lines, before, vertex, &map),
        PlyEncoding::BinaryLittleEndian => {
            read_binary(Reader::new(lines.rest(), header_len, false), before, vertex, &map)
        }
        PlyEncoding::BinaryBigEndian => read_binary(Reader::new(lines.rest(), header_len, true), before, vertex, &map),
    }
}

/// Reads header lines up to and including `end_header`.
fn parse_header(lines: &mut Lines<'_>) -> Result<(PlyEncoding, Vec<Element>), ParseError> {
    match lines.next() {
        Some((_, magic)) if magic.trim_ascii_end() == b"ply" => {}
        _ => {
            return Err(ParseError::syntax(1, "not a PLY file: the first line is not `ply`"));
        }
    }
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    while let Some(line) = lines.next_text() {
        let (number, text) = line?;
        let mut tokens = text.split_ascii_whitespace();
        match tokens.next() {
            Some("comment" | "obj_info") => {}
            Some("format") => encoding = Some(parse_format(tokens.next().unwrap_or_default())?),
            Some("element") => elements.push(parse_element(number, tokens)?),
            Some("property") => {
                let element = elements
                    .last_mut()
                    .ok_or_else(|| ParseError::syntax(number, "property declared before any element"))?;
                element.properties.push(parse_property(number, tokens.collect())?);
            }
            Some("end_header") => {
                let encoding = encoding.ok_or(ParseError::MissingHeaderLine("format"))?;
                return Ok((encoding, elements));
            }
            other => {
                let reason = format!("unknown header keyword {:?}", other.unwrap_or_default());
                return Err(ParseError::syntax(number, reason));
            }
        }
    }
    Err(ParseError::MissingHeaderLine("end_header"))
}

/// The encoding named on the format line (the version is not checked).
fn parse_format(kind: &str) -> Result<PlyEncoding, ParseError> {
    [PlyEncoding::Ascii, PlyEncoding::BinaryLittleEndian, PlyEncoding::BinaryBigEndian]
        .into_iter()
        .find(|e| e.keyword() == kind)
        .ok_or_else(|| ParseError::Unsupported {
            what: "PLY format",
            found: kind.to_owned(),
            expected: "ascii, binary_little_endian or binary_big_endian",
        })
}

/// An `element NAME COUNT` line.
fn parse_element<'a>(number: usize, mut tokens: impl Iterator<Item = &'a str>) -> Result<Element, ParseError> {
    let (Some(name), Some(count), None) = (tokens.next(), tokens.next(), tokens.next()) else {
        return Err(ParseError::syntax(number, "expected `element NAME COUNT`"));
    };
    let count = count
        .parse()
        .map_err(|_| ParseError::syntax(number, format!("element count {count:?} is not a non-negative integer")))?;
    Ok(Element { name: name.to_owned(), count, properties: Vec::new() })
}

/// A `property TYPE NAME` or `property list COUNT_TYPE ITEM_TYPE NAME` line.
fn parse_property(number: usize, words: Vec<&str>) -> Result<Property, ParseError> {
    let scalar = |name: &str| {
        ply_scalar(name).ok_or_else(|| ParseError::syntax(number, format!("unknown property type {name:?}")))
    };
    match words.as_slice() {
        ["list", count, item, _] => {
            let count = scalar(count)?;
            if !count.is_integer() {
                return Err(ParseError::syntax(number, "list length type must be an integer type"));
            }
            Ok(Property::List { count, item: scalar(item)? })
        }
        [kind, name] => Ok(Property::Scalar { name: (*name).to_owned(), scalar: scalar(kind)? }),
        _ => Err(ParseError::syntax(
            number,
            "expected `property TYPE NAME` or `property list COUNT_TYPE ITEM_TYPE NAME`",
        )),
    }
}

/// The scalar type for a PLY type name.
fn ply_scalar(name: &str) -> Option<Scalar> {
    let scalar = match name {
        "char" | "int8" => Scalar::I8,
        "uchar" | "uint8" => Scalar::U8,
        "short" | "int16" => Scalar::I16,
        "ushort" | "uint16" => Scalar::U16,
        "int" | "int32" => Scalar::I32,
        "uint" | "uint32" => Scalar::U32,
        "int64" => Scalar::I64,
        "uint64" => Scalar::U64,
        "float" | "float32" => Scalar::F32,
        "double" | "float64" => Scalar::F64,
        _ => return None,
    };
    Some(scalar)
}

/// The PLY type name the writers use for a scalar.
fn ply_type_name(scalar: Scalar) -> &'static str {
    match scalar {
        Scalar::I8 => "char",
        Scalar::U8 => "uchar",
        Scalar::I16 => "short",
        Scalar::U16 => "ushort",
        Scalar::I32 => "int",
        Scalar::U32 => "uint",
        Scalar::I64 => "int64",
        Scalar::U64 => "uint64",
        Scalar::F32 => "float",
        Scalar::F64 => "double",
    }
}

/// The role each vertex property feeds, by property index.
fn vertex_roles(vertex: &Element, map: &FieldMap) -> Vec<Option<Role>> {
    (0..vertex.properties.len()).map(|i| map.role_of(i)).collect()
}

/// Reads ascii data: skips the records of earlier elements, then parses the vertices.
fn read_ascii(
    mut lines: Lines<'_>,
    before: &[Element],
    vertex: &Element,
    map: &FieldMap,
) -> Result<LoadedCloud, ParseError> {
    for element in before.iter().filter(|e| !e.properties.is_empty()) {
        for found in 0..element.count {
            lines.next_text().unwrap_or_else(|| Err(element.missing_records(found)))?;
        }
    }
    let roles = vertex_roles(vertex, map);
    let room = capacity(vertex.count, lines.rest().len(), 2 * vertex.properties.len());
    let mut builder = map.builder(room);
    let mut values: Values = [0.0; 6];
    for found in 0..vertex.count {
        let (number, text) = lines.next_text().unwrap_or_else(|| Err(vertex.missing_records(found)))?;
        parse_ascii_record(number, text, &vertex.properties, &roles, &mut values)?;
        builder.push(&values);
    }
    Ok(builder.finish())
}

/// Fills `values` from one ascii vertex line.
fn parse_ascii_record(
    number: usize,
    text: &str,
    properties: &[Property],
    roles: &[Option<Role>],
    values: &mut Values,
) -> Result<(), ParseError> {
    let mut tokens = text.split_ascii_whitespace();
    let mut next =
        |what: &str| tokens.next().ok_or_else(|| ParseError::syntax(number, format!("missing value for {what}")));
    for (property, role) in properties.iter().zip(roles) {
        match property {
            Property::Scalar { name, scalar } => {
                let token = next(name)?;
                let value = scalar
                    .parse_text(token)
                    .ok_or_else(|| ParseError::syntax(number, format!("{name} value {token:?} is not a number")))?;
                if let Some(role) = role {
                    values[*role as usize] = value;
                }
            }
            Property::List { .. } => {
                let token = next("a list length")?;
                let len: usize = token.parse().map_err(|_| {
                    ParseError::syntax(number, format!("list length {token:?} is not a non-negative integer"))
                })?;
                for _ in 0..len {
                    next("a list item")?;
                }
            }
        }
    }
    match tokens.next() {
        Some(extra) => Err(ParseError::syntax(number, format!("unexpected extra value {extra:?}"))),
        None => Ok(()),
    }
}

/// A position in binary data.
struct Reader<'a> {
    bytes: &'a [u8],
    pos: usize,
    /// File offset of `bytes[0]`, for error messages.
    origin: usize,
    big_endian: bool,
}

impl<'a> Reader<'a> {
    /// A reader at the start of `bytes`, which begin at file offset `origin`.
    fn new(bytes: &'a [u8], origin: usize, big_endian: bool) -> Self {
        Self { bytes, pos: 0, origin, big_endian }
    }

    /// Bytes not read yet.
    fn remaining(&self) -> usize {
        self.bytes.len() - self.pos
    }

    /// Current file offset.
    fn offset(&self) -> usize {
        self.origin + self.pos
    }

    /// Reads one value; `None` at the end of the data.
    fn scalar(&mut self, scalar: Scalar) -> Option<f64> {
        let value = scalar.decode(self.bytes.get(self.pos..)?, self.big_endian)?;
        self.pos += scalar.size();
        Some(value)
    }

    /// Moves `n` bytes ahead; `None` if fewer remain.
    fn skip(&mut self, n: usize) -> Option<()> {
        if n > self.remaining() {
            return None;
        }
        self.pos += n;
        Some(())
    }

    /// Reads one record, storing the values of properties that feed a role.
    fn record(&mut self, properties: &[Property], roles: &[Option<Role>], values: &mut Values) -> Option<()> {
        for (i, property) in properties.iter().enumerate() {
            match property {
                Property::Scalar { scalar, .. } => {
                    let value = self.scalar(*scalar)?;
                    if let Some(Some(role)) = roles.get(i) {
                        values[*role as usize] = value;
                    }
                }
                Property::List { count, item } => {
                    let len = self.scalar(*count)?;
                    // Only corrupt data has a negative length; `as` saturates absurd ones.
                    if len < 0.0 {
                        return None;
                    }
                    self.skip((len as usize).checked_mul(item.size())?)?;
                }
            }
        }
        Some(())
    }

    /// Skips every record of `element`.
    fn skip_element(&mut self, element: &Element) -> Result<(), ParseError> {
        // Fixed-size records go in one step, so a hostile count cannot cost a long loop.
        if let Some(size) = element.fixed_size() {
            let fits = size.checked_mul(element.count).is_some_and(|n| n <= self.remaining());
            if !fits {
                let record = self.remaining() / size.max(1);
                return Err(element.bad_record(record, self.offset() + record * size));
            }
            self.pos += size * element.count;
            return Ok(());
        }
        // Each record consumes at least its list lengths, so this loop ends with the data.
        for record in 0..element.count {
            let at = self.offset();
            self.record(&element.properties, &[], &mut [0.0; 6]).ok_or_else(|| element.bad_record(record, at))?;
        }
        Ok(())
    }
}

/// Reads binary data: skips earlier elements, then decodes the vertices.
fn read_binary(
    mut reader: Reader<'_>,
    before: &[Element],
    vertex: &Element,
    map: &FieldMap,
) -> Result<LoadedCloud, ParseError> {
    for element in before {
        reader.skip_element(element)?;
    }
    let roles = vertex_roles(vertex, map);
    let mut builder = map.builder(capacity(vertex.count, reader.remaining(), vertex.min_size()));
    let mut values: Values = [0.0; 6];
    for record in 0..vertex.count {
        let at = reader.offset();
        reader.record(&vertex.properties, &roles, &mut values).ok_or_else(|| vertex.bad_record(record, at))?;
        builder.push(&values);
    }
    Ok(builder.finish())
}

/// Encodes a cloud as PLY: a vertex element with x y z (float) and whichever of intensity
/// (float), ring (ushort) and time (float) the cloud has.
pub fn encode(cloud: &PointCloud, encoding: PlyEncoding) -> Vec<u8> {
    let roles = Role::written(cloud);
    let mut out = header_text(cloud.len(), &roles, encoding).into_bytes();
    match encoding {
        PlyEncoding::Ascii => out.extend_from_slice(text_rows(cloud, &roles).as_bytes()),
        PlyEncoding::BinaryLittleEndian => out.extend(binary_rows(cloud, &roles, false)),
        PlyEncoding::BinaryBigEndian => out.extend(binary_rows(cloud, &roles, true)),
    }
    out
}

/// The header for `points` vertices of `roles`.
fn header_text(points: usize, roles: &[Role], encoding: PlyEncoding) -> String {
    let mut text = format!(
        "ply\nformat {} 1.0\ncomment written by the cloud crate\nelement vertex {points}\n",
        encoding.keyword()
    );
    for role in roles {
        text += &format!("property {} {}\n", ply_type_name(role.written_scalar()), role.name());
    }
    text + "end_header\n"
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_needs_the_magic_line() {
        let err = parse(b"PLY\nformat ascii 1.0\nend_header\n").unwrap_err();
        assert_eq!(err, ParseError::syntax(1, "not a PLY file: the first line is not `ply`"));
    }

    #[test]
    fn header_needs_a_vertex_element() {
        let text = "ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n";
        assert_eq!(parse(text.as_bytes()).unwrap_err(), ParseError::MissingHeaderLine("element vertex"));
    }

    #[test]
    fn unknown_format_is_unsupported() {
        let err = parse(b"ply\nformat binary_middle_endian 1.0\nend_header\n").unwrap_err();
        assert!(matches!(err, ParseError::Unsupported { what: "PLY format", .. }), "{err}");
    }

    #[test]
    fn float_list_length_is_rejected() {
        let text = "ply\nformat ascii 1.0\nelement vertex 0\nproperty list float int idx\nend_header\n";
        let err = parse(text.as_bytes()).unwrap_err();
        assert_eq!(err, ParseError::syntax(4, "list length type must be an integer type"));
    }

    #[test]
    fn ascii_lists_on_vertices_are_skipped() {
        let text = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n\
                    property list uchar int n\nproperty float y\nproperty float z\nend_header\n1 2 7 7 2 3\n";
        let read = parse(text.as_bytes()).unwrap();
        assert_eq!(read.cloud.points, vec![nalgebra::Point3::new(1.0, 2.0, 3.0)]);
    }

    #[test]
    fn ascii_extra_values_are_rejected() {
        let text = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n\
                    property float z\nend_header\n1 2 3 4\n";
        let err = parse(text.as_bytes()).unwrap_err();
        assert_eq!(err, ParseError::syntax(8, "unexpected extra value \"4\""));
    }

    #[test]
    fn negative_binary_list_length_is_corrupt() {
        let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement face 1\nproperty list char int idx\n\
                          element vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
            .to_vec();
        let header_len = bytes.len();
        bytes.push(0xff);
        let err = parse(&bytes).unwrap_err();
        assert_eq!(err, ParseError::BadRecord { element: "face".into(), record: 0, offset: header_len });
    }
}
