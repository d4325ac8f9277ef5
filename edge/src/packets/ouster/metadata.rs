//! Ouster sensor metadata: the JSON the sensor serves and ouster-sdk saves beside a capture.
//!
//! Two layouts hold the same fields. Firmware 2.0-2.3 puts them at the top level, the packet
//! layout under `data_format`. Firmware 3.x (and ouster-sdk 0.11 onwards, whatever the firmware)
//! groups them: `beam_intrinsics`, `lidar_intrinsics`, `lidar_data_format`, `config_params`,
//! `sensor_info`. Both parse to the same [`Metadata`].

use serde_json::{Map, Value};

use super::profile::Profile;

/// Why metadata cannot be used; names the field, as the layout it was read from spells it.
#[derive(Debug, thiserror::Error, Clone, PartialEq, Eq)]
pub enum MetadataError {
    /// The text is not JSON, or not a JSON object.
    #[error("Ouster metadata is not a JSON object: {0}")]
    Json(String),
    /// A field the decoder needs is absent (or null).
    #[error("Ouster metadata has no `{field}`")]
    Missing {
        /// The field's path, e.g. `data_format.columns_per_frame`.
        field: String,
    },
    /// A field holds a value the decoder cannot use.
    #[error("Ouster metadata `{field}`: {reason}")]
    Invalid {
        /// The field's path or name.
        field: String,
        /// What is wrong with it.
        reason: String,
    },
}

/// The most beams a sensor has (128 today); more means the metadata is not a sensor's.
const MAX_BEAMS: usize = 256;
/// The widest frame of any sensor mode (4096x5); measurement ids would allow 65,536, but the
/// decoder's per-pixel table of such a frame would be hundreds of megabytes made of a mistake.
const MAX_COLUMNS_PER_FRAME: usize = 4096;
/// A packet is one UDP datagram.
const MAX_PACKET_BYTES: usize = 65_535;

/// What the decoder needs to know of one sensor. Angles in degrees, transforms row-major 4x4 with
/// translations in millimetres, as in the JSON.
#[derive(Clone, Debug, PartialEq)]
pub struct Metadata {
    /// The product line, e.g. `OS-1-32-G`.
    pub prod_line: Option<String>,
    /// The firmware's `build_rev`, e.g. `v2.3.0`.
    pub firmware: Option<String>,
    /// e.g. `1024x10`: columns per frame by frames per second.
    pub lidar_mode: Option<String>,
    /// `udp_profile_lidar`; LEGACY when absent (firmware before 2.2 knows no other).
    pub profile: Profile,
    /// Beams.
    pub pixels_per_column: usize,
    /// Columns (measurement ids) in one lidar packet, 16 on every model so far.
    pub columns_per_packet: usize,
    /// Columns in a whole turn: the lidar mode's first number (512, 1024, 2048).
    pub columns_per_frame: usize,
    /// First and last measurement id the sensor sends (inclusive; wraps past the frame's end when
    /// the first is larger).
    pub column_window: [usize; 2],
    /// Per beam, the column shift that aligns a range image (destaggering); not used for points.
    pub pixel_shift_by_row: Vec<i64>,
    /// Per beam, elevation (up positive).
    pub beam_altitude_angles: Vec<f64>,
    /// Per beam, azimuth offset from its column's encoder angle.
    pub beam_azimuth_angles: Vec<f64>,
    /// Beam origin in the lidar frame (from `lidar_origin_to_beam_origin_mm` when absent).
    pub beam_to_lidar_transform: [f64; 16],
    /// Lidar frame to sensor frame.
    pub lidar_to_sensor_transform: [f64; 16],
    /// The port the lidar packets go to, where the metadata names it.
    pub udp_port_lidar: Option<u16>,
    /// The port the IMU packets go to, where the metadata names it.
    pub udp_port_imu: Option<u16>,
    /// Changes each time the sensor initialises; the packet headers of non-LEGACY profiles carry it.
    pub initialization_id: Option<u32>,
}

impl Metadata {
    /// Parses either layout and checks the result (see [`Metadata::validate`]).
    pub fn from_json(text: &str) -> Result<Metadata, MetadataError> {
        let root: Value = serde_json::from_str(text).map_err(|e| MetadataError::Json(e.to_string()))?;
        let root = root.as_object().ok_or_else(|| MetadataError::Json("the top level is not an object".into()))?;
        let metadata = Document::new(root).metadata()?;
        metadata.validate()?;
        Ok(metadata)
    }

    /// Checks that the fields agree with each other and describe a packet a sensor can send.
    pub fn validate(&self) -> Result<(), MetadataError> {
        let invalid = |field: &str, reason: String| Err(MetadataError::Invalid { field: field.into(), reason });
        let beams = self.pixels_per_column;
        if !(1..=MAX_BEAMS).contains(&beams) {
            return invalid("pixels_per_column", format!("{beams} is not in 1..={MAX_BEAMS}"));
        }
        let columns = self.columns_per_frame;
        if !(1..=MAX_COLUMNS_PER_FRAME).contains(&columns) {
            return invalid("columns_per_frame", format!("{columns} is not in 1..={MAX_COLUMNS_PER_FRAME}"));
        }
        if !(1..=columns).contains(&self.columns_per_packet) {
            return invalid("columns_per_packet", format!("{} is not in 1..={columns}", self.columns_per_packet));
        }
        if self.lidar_packet_bytes() > MAX_PACKET_BYTES {
            return invalid(
                "columns_per_packet",
                format!("a packet of {} bytes is no UDP payload", self.lidar_packet_bytes()),
            );
        }
        if let Some(&end) = self.column_window.iter().find(|&&end| end >= columns) {
            return invalid("column_window", format!("{end} is past the frame's {columns} columns"));
        }
        check_per_beam("beam_altitude_angles", &self.beam_altitude_angles, beams)?;
        check_per_beam("beam_azimuth_angles", &self.beam_azimuth_angles, beams)?;
        if self.pixel_shift_by_row.len() != beams {
            return invalid(
                "pixel_shift_by_row",
                format!("{} values for {beams} beams", self.pixel_shift_by_row.len()),
            );
        }
        check_finite("beam_to_lidar_transform", &self.beam_to_lidar_transform)?;
        check_finite("lidar_to_sensor_transform", &self.lidar_to_sensor_transform)
    }

    /// Bytes of one lidar packet: what [`crate::packets::Assembler::push`] accepts.
    pub fn lidar_packet_bytes(&self) -> usize {
        self.profile.lidar_packet_bytes(self.pixels_per_column, self.columns_per_packet)
    }

    /// The columns within [`Metadata::column_window`]: those a whole frame holds.
    pub fn window_columns(&self) -> usize {
        let [first, last] = self.column_window;
        if first <= last { last - first + 1 } else { self.columns_per_frame.saturating_sub(first) + last + 1 }
    }
}

fn check_per_beam(field: &str, values: &[f64], beams: usize) -> Result<(), MetadataError> {
    if values.len() != beams {
        return Err(MetadataError::Invalid {
            field: field.into(),
            reason: format!("{} values for {beams} beams", values.len()),
        });
    }
    check_finite(field, values)
}

fn check_finite(field: &str, values: &[f64]) -> Result<(), MetadataError> {
    match values.iter().find(|value| !value.is_finite()) {
        Some(value) => Err(MetadataError::Invalid { field: field.into(), reason: format!("{value} is not a number") }),
        None => Ok(()),
    }
}

/// A group of fields, which the nested layout keeps in a section of its own.
#[derive(Clone, Copy)]
enum Section {
    Beams,
    Lidar,
    Format,
    Config,
    Sensor,
}

/// The JSON object and which layout it has.
struct Document<'a> {
    root: &'a Map<String, Value>,
    nested: bool,
}

impl<'a> Document<'a> {
    fn new(root: &'a Map<String, Value>) -> Self {
        let nested = ["lidar_data_format", "beam_intrinsics", "sensor_info"].iter().any(|key| root.contains_key(*key));
        Document { root, nested }
    }

    fn section_name(&self, section: Section) -> Option<&'static str> {
        match (section, self.nested) {
            (Section::Format, false) => Some("data_format"),
            (_, false) => None,
            (Section::Beams, true) => Some("beam_intrinsics"),
            (Section::Lidar, true) => Some("lidar_intrinsics"),
            (Section::Format, true) => Some("lidar_data_format"),
            (Section::Config, true) => Some("config_params"),
            (Section::Sensor, true) => Some("sensor_info"),
        }
    }

    fn field(&self, section: Section, key: &str) -> Field<'a> {
        let (path, value) = match self.section_name(section) {
            Some(name) => (format!("{name}.{key}"), self.root.get(name).and_then(|section| section.get(key))),
            None => (key.to_string(), self.root.get(key)),
        };
        // ouster-sdk writes null for settings it does not know.
        Field { path, value: value.filter(|value| !value.is_null()) }
    }

    fn metadata(&self) -> Result<Metadata, MetadataError> {
        let lidar_mode = self.field(Section::Config, "lidar_mode").text()?;
        self.check_header_type()?;
        Ok(Metadata {
            prod_line: self.field(Section::Sensor, "prod_line").text()?,
            firmware: self.field(Section::Sensor, "build_rev").text()?,
            profile: self.profile()?,
            pixels_per_column: self.field(Section::Format, "pixels_per_column").count()?,
            columns_per_packet: self.field(Section::Format, "columns_per_packet").count()?,
            columns_per_frame: self.columns_per_frame(lidar_mode.as_deref())?,
            column_window: self.column_window(lidar_mode.as_deref())?,
            pixel_shift_by_row: self.pixel_shift_by_row()?,
            beam_altitude_angles: self.field(Section::Beams, "beam_altitude_angles").numbers()?,
            beam_azimuth_angles: self.field(Section::Beams, "beam_azimuth_angles").numbers()?,
            beam_to_lidar_transform: self.beam_to_lidar_transform()?,
            lidar_to_sensor_transform: self.field(Section::Lidar, "lidar_to_sensor_transform").transform()?,
            udp_port_lidar: self.field(Section::Config, "udp_port_lidar").port()?,
            udp_port_imu: self.field(Section::Config, "udp_port_imu").port()?,
            initialization_id: self.field(Section::Sensor, "initialization_id").optional_u32()?,
            lidar_mode,
        })
    }

    fn profile(&self) -> Result<Profile, MetadataError> {
        let field = self.field(Section::Format, "udp_profile_lidar");
        match field.text()? {
            None => Ok(Profile::Legacy),
            Some(name) => {
                Profile::from_name(&name).ok_or_else(|| field.invalid(format!("profile {name} is not supported")))
            }
        }
    }

    /// Firmware 3.1 can send a functional-safety packet header; only the standard one is read.
    fn check_header_type(&self) -> Result<(), MetadataError> {
        let field = self.field(Section::Format, "header_type");
        match field.text()? {
            Some(kind) if kind != "STANDARD" => Err(field.invalid(format!("header type {kind} is not supported"))),
            _ => Ok(()),
        }
    }

    /// From the data format, or the mode's first number (`1024x10`) in metadata that lacks it.
    fn columns_per_frame(&self, lidar_mode: Option<&str>) -> Result<usize, MetadataError> {
        let field = self.field(Section::Format, "columns_per_frame");
        if field.value.is_some() {
            return field.count();
        }
        lidar_mode.and_then(columns_of_mode).ok_or_else(|| field.missing())
    }

    fn column_window(&self, lidar_mode: Option<&str>) -> Result<[usize; 2], MetadataError> {
        let field = self.field(Section::Format, "column_window");
        if field.value.is_none() {
            let columns = self.columns_per_frame(lidar_mode)?;
            return Ok([0, columns.saturating_sub(1)]);
        }
        match field.counts()?.as_slice() {
            &[first, last] => Ok([first, last]),
            other => Err(field.invalid(format!("{} values, not [first, last]", other.len()))),
        }
    }

    fn pixel_shift_by_row(&self) -> Result<Vec<i64>, MetadataError> {
        let field = self.field(Section::Format, "pixel_shift_by_row");
        if field.value.is_none() {
            let beams = self.field(Section::Format, "pixels_per_column").count()?;
            return Ok(vec![0; beams]);
        }
        field
            .required_array()?
            .iter()
            .map(|value| value.as_i64().ok_or_else(|| field.invalid(format!("{value} is not an integer"))))
            .collect()
    }

    /// The transform where the metadata gives it, else a shift along x of the beam origin offset.
    fn beam_to_lidar_transform(&self) -> Result<[f64; 16], MetadataError> {
        let transform = self.field(Section::Beams, "beam_to_lidar_transform");
        if transform.value.is_some() {
            return transform.transform();
        }
        let offset = self.field(Section::Beams, "lidar_origin_to_beam_origin_mm").number()?;
        let mut matrix = IDENTITY;
        matrix[3] = offset;
        Ok(matrix)
    }
}

const IDENTITY: [f64; 16] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0];

/// `1024x10` -> 1024.
fn columns_of_mode(mode: &str) -> Option<usize> {
    mode.split('x').next()?.parse().ok()
}

/// One field's value (if present) and its path for error messages.
struct Field<'a> {
    path: String,
    value: Option<&'a Value>,
}

impl<'a> Field<'a> {
    fn missing(&self) -> MetadataError {
        MetadataError::Missing { field: self.path.clone() }
    }

    fn invalid(&self, reason: String) -> MetadataError {
        MetadataError::Invalid { field: self.path.clone(), reason }
    }

    fn required(&self) -> Result<&'a Value, MetadataError> {
        self.value.ok_or_else(|| self.missing())
    }

    fn required_array(&self) -> Result<&'a Vec<Value>, MetadataError> {
        self.required()?.as_array().ok_or_else(|| self.invalid("not an array".into()))
    }

    fn number(&self) -> Result<f64, MetadataError> {
        self.required()?.as_f64().ok_or_else(|| self.invalid("not a number".into()))
    }

    fn count(&self) -> Result<usize, MetadataError> {
        let value = self.required()?;
        value
            .as_u64()
            .and_then(|n| usize::try_from(n).ok())
            .ok_or_else(|| self.invalid(format!("{value} is not a count")))
    }

    fn numbers(&self) -> Result<Vec<f64>, MetadataError> {
        self.required_array()?
            .iter()
            .map(|value| value.as_f64().ok_or_else(|| self.invalid(format!("{value} is not a number"))))
            .collect()
    }

    fn counts(&self) -> Result<Vec<usize>, MetadataError> {
        let array = self.required_array()?;
        array
            .iter()
            .map(|value| {
                value
                    .as_u64()
                    .and_then(|n| usize::try_from(n).ok())
                    .ok_or_else(|| self.invalid(format!("{value} is not a count")))
            })
            .collect()
    }

    fn transform(&self) -> Result<[f64; 16], MetadataError> {
        let numbers = self.numbers()?;
        <[f64; 16]>::try_from(numbers.as_slice())
            .map_err(|_| self.invalid(format!("{} values, not the 16 of a 4x4 matrix", numbers.len())))
    }

    fn text(&self) -> Result<Option<String>, MetadataError> {
        self.value
            .map(|value| value.as_str().map(str::to_string).ok_or_else(|| self.invalid("not a string".into())))
            .transpose()
    }

    fn optional_u32(&self) -> Result<Option<u32>, MetadataError> {
        self.value
            .map(|value| {
                value
                    .as_u64()
                    .and_then(|n| u32::try_from(n).ok())
                    .ok_or_else(|| self.invalid(format!("{value} is not a u32")))
            })
            .transpose()
    }

    fn port(&self) -> Result<Option<u16>, MetadataError> {
        self.value
            .map(|value| {
                value
                    .as_u64()
                    .and_then(|n| u16::try_from(n).ok())
                    .ok_or_else(|| self.invalid(format!("{value} is not a port")))
            })
            .transpose()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const FLAT: &str = r#"{
        "beam_altitude_angles": [10.0, -10.0],
        "beam_azimuth_angles": [1.0, -1.0],
        "lidar_origin_to_beam_origin_mm": 12.5,
        "lidar_to_sensor_transform": [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 36.18, 0, 0, 0, 1],
        "lidar_mode": "512x10",
        "prod_line": "OS-1-16",
        "data_format": {"pixels_per_column": 2, "columns_per_packet": 16, "columns_per_frame": 512}
    }"#;

    #[test]
    fn flat_metadata_defaults_to_legacy_and_the_whole_frame() {
        let metadata = Metadata::from_json(FLAT).unwrap();
        assert_eq!(metadata.profile, Profile::Legacy);
        assert_eq!(metadata.column_window, [0, 511]);
        assert_eq!(metadata.window_columns(), 512);
        assert_eq!(metadata.pixel_shift_by_row, vec![0, 0]);
        assert_eq!(metadata.beam_to_lidar_transform[3], 12.5);
        assert_eq!(metadata.lidar_packet_bytes(), 16 * (16 + 2 * 12 + 4));
    }

    #[test]
    fn errors_name_the_field() {
        let missing = FLAT.replace("\"columns_per_frame\": 512", "\"fps\": 10").replace("512x10", "bogus");
        assert_eq!(
            Metadata::from_json(&missing),
            Err(MetadataError::Missing { field: "data_format.columns_per_frame".into() })
        );
        let short = FLAT.replace("[1.0, -1.0]", "[1.0]");
        assert!(
            matches!(Metadata::from_json(&short), Err(MetadataError::Invalid { field, .. }) if field == "beam_azimuth_angles")
        );
        let profile =
            FLAT.replace("\"columns_per_frame\": 512", "\"columns_per_frame\": 512, \"udp_profile_lidar\": \"X\"");
        assert!(
            matches!(Metadata::from_json(&profile), Err(MetadataError::Invalid { field, .. }) if field == "data_format.udp_profile_lidar")
        );
    }

    #[test]
    fn a_frame_wider_than_any_sensor_mode_is_refused() {
        let mut metadata = Metadata::from_json(FLAT).unwrap();
        metadata.columns_per_frame = 4096;
        metadata.column_window = [0, 4095];
        assert_eq!(metadata.validate(), Ok(()));
        metadata.columns_per_frame = 8192;
        assert!(
            matches!(metadata.validate(), Err(MetadataError::Invalid { field, .. }) if field == "columns_per_frame")
        );
    }

    #[test]
    fn wrapped_column_window_counts_both_ends() {
        let mut metadata = Metadata::from_json(FLAT).unwrap();
        metadata.column_window = [500, 9];
        assert_eq!(metadata.window_columns(), 12 + 10);
    }
}
