//! File formats: KITTI .bin, PCD and PLY, and rigid transforms as text.
//!
//! Each format module has a pure `parse(&[u8])` and `encode(&PointCloud, ..) -> Vec<u8>`;
//! [`read_cloud`] and [`write_cloud`] are the only functions that touch files. Parsers never
//! panic and never trust counts in a header to size an allocation. Points with a NaN or
//! infinite coordinate are dropped and counted in [`LoadedCloud::dropped_non_finite`].
//!
//! Channel mapping for PCD and PLY (field names are matched case-insensitively):
//! - `x`, `y`, `z` are required;
//! - intensity: `intensity`, else any name containing `intensity` (`scalar_intensity`),
//!   else `i`, else a name containing `reflectivity` or `reflectance`;
//! - ring: `ring`;
//! - time: `time`, else `t`, else `timestamp`. Integer time fields are taken as nanoseconds
//!   (Ouster's `t` is u32 ns since the sweep start) and converted to seconds; float time
//!   fields are taken as seconds. Absolute (epoch) float timestamps lose their sub-second
//!   precision in the f32 channel.
//!
//! Other fields (rgb, normals, `_` padding, PLY list properties) are skipped.

pub mod kitti;
mod lzf;
pub mod pcd;
pub mod ply;
mod record;
pub mod transform;

use std::path::{Path, PathBuf};

pub use lzf::LzfError;
pub use pcd::PcdEncoding;
pub use ply::PlyEncoding;
pub use record::Scalar;
pub use transform::{TransformError, read_transform};

use crate::PointCloud;
use crate::point_cloud::InvalidCloud;

/// A cloud read from a file, with the number of non-finite points that were left out.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LoadedCloud {
    /// The finite points and their channels.
    pub cloud: PointCloud,
    /// How many points had a NaN or infinite coordinate and were dropped.
    pub dropped_non_finite: usize,
}

/// A file format and encoding the writers produce.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FileFormat {
    /// KITTI velodyne `.bin`: little-endian f32 `x y z intensity` records.
    KittiBin,
    /// PCD with the given DATA encoding.
    Pcd(PcdEncoding),
    /// PLY with the given format.
    Ply(PlyEncoding),
}

impl FileFormat {
    /// Every format and encoding the writers support.
    pub const ALL: [FileFormat; 7] = [
        FileFormat::KittiBin,
        FileFormat::Pcd(PcdEncoding::Ascii),
        FileFormat::Pcd(PcdEncoding::Binary),
        FileFormat::Pcd(PcdEncoding::BinaryCompressed),
        FileFormat::Ply(PlyEncoding::Ascii),
        FileFormat::Ply(PlyEncoding::BinaryLittleEndian),
        FileFormat::Ply(PlyEncoding::BinaryBigEndian),
    ];

    /// The file extension [`read_cloud`] recognises for this format, without the dot.
    pub fn extension(self) -> &'static str {
        match self {
            FileFormat::KittiBin => "bin",
            FileFormat::Pcd(_) => "pcd",
            FileFormat::Ply(_) => "ply",
        }
    }
}

/// Why a byte slice is not a valid point-cloud file.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ParseError {
    /// A KITTI file whose size is not a whole number of 16-byte records.
    #[error("KITTI .bin size {len} bytes is not a multiple of 16 (f32 x y z intensity records)")]
    KittiSize {
        /// The file size in bytes.
        len: usize,
    },
    /// A malformed header or ASCII data line.
    #[error("line {line}: {reason}")]
    Syntax {
        /// 1-based line number in the file.
        line: usize,
        /// What is wrong with it.
        reason: String,
    },
    /// A header line the format requires is absent.
    #[error("the header has no `{0}` line")]
    MissingHeaderLine(&'static str),
    /// A required field (x, y or z) is absent.
    #[error("no `{0}` field")]
    MissingField(&'static str),
    /// A data encoding or file format this reader does not handle.
    #[error("unsupported {what} {found:?}, expected {expected}")]
    Unsupported {
        /// Which header item.
        what: &'static str,
        /// The value found.
        found: String,
        /// The values supported.
        expected: &'static str,
    },
    /// Binary data shorter than the header promises.
    #[error(
        "truncated binary data: header declares {points} points of {point_size} bytes, \
         file has {available} bytes after the header"
    )]
    Truncated {
        /// Points declared.
        points: usize,
        /// Bytes per point.
        point_size: usize,
        /// Bytes present after the header.
        available: usize,
    },
    /// Declared sizes that overflow the address space.
    #[error("header declares {points} points of {point_size} bytes, more than memory can address")]
    TooLarge {
        /// Points declared.
        points: usize,
        /// Bytes per point.
        point_size: usize,
    },
    /// ASCII data with fewer records than declared.
    #[error("truncated data: header declares {declared} {what}, file holds {found}")]
    MissingRecords {
        /// What the records are ("points", "vertex records", ...).
        what: String,
        /// Records declared.
        declared: usize,
        /// Records present.
        found: usize,
    },
    /// A PLY binary record that is cut short or holds an impossible list length.
    #[error("truncated or corrupt binary data: element `{element}` record {record} at byte {offset}")]
    BadRecord {
        /// The element's name.
        element: String,
        /// 0-based record index within the element.
        record: usize,
        /// File offset where reading failed.
        offset: usize,
    },
    /// A PCD binary_compressed block whose size fields disagree with the header or the file.
    #[error("binary_compressed block: {0}")]
    CompressedBlock(String),
    /// A PCD binary_compressed block whose LZF data is corrupt.
    #[error("binary_compressed block: {0}")]
    Lzf(#[from] LzfError),
}

impl ParseError {
    /// A [`ParseError::Syntax`] at `line`.
    pub(crate) fn syntax(line: usize, reason: impl Into<String>) -> Self {
        ParseError::Syntax { line, reason: reason.into() }
    }
}

/// Why a file could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum FormatErrorKind {
    /// The file could not be read.
    #[error("cannot read: {0}")]
    Read(std::io::Error),
    /// The file could not be written.
    #[error("cannot write: {0}")]
    Write(std::io::Error),
    /// The contents are not a valid file of the format.
    #[error(transparent)]
    Parse(#[from] ParseError),
    /// The extension names no supported format.
    #[error("unsupported extension {found:?}: supported are .bin (KITTI), .pcd and .ply")]
    UnsupportedExtension {
        /// The extension found, without the dot (empty when there is none).
        found: String,
    },
    /// The cloud breaks the [`PointCloud`] invariant, so writing it would store garbage.
    #[error("cannot write an invalid cloud: {0}")]
    InvalidCloud(#[from] InvalidCloud),
    /// The cloud is too big for the format's size fields.
    #[error("{points} points exceed what {format:?} can store")]
    TooLarge {
        /// Points in the cloud.
        points: usize,
        /// The format asked for.
        format: FileFormat,
    },
}

/// A failed read or write: the file and the reason.
#[derive(Debug, thiserror::Error)]
#[error("{}: {kind}", path.display())]
pub struct FormatError {
    /// The file concerned.
    pub path: PathBuf,
    /// What went wrong.
    pub kind: FormatErrorKind,
}

/// The parser for a file, chosen by its extension.
type Parser = fn(&[u8]) -> Result<LoadedCloud, ParseError>;

/// Reads a `.bin` (KITTI), `.pcd` or `.ply` file, choosing the parser by extension.
pub fn read_cloud(path: &Path) -> Result<LoadedCloud, FormatError> {
    let fail = |kind| FormatError { path: path.to_owned(), kind };
    let parse = parser_for(path).map_err(fail)?;
    let bytes = std::fs::read(path).map_err(|e| fail(FormatErrorKind::Read(e)))?;
    parse(&bytes).map_err(|e| fail(e.into()))
}

/// The parser matching the extension of `path` (case-insensitive).
fn parser_for(path: &Path) -> Result<Parser, FormatErrorKind> {
    let extension = path.extension().map(|e| e.to_string_lossy().to_ascii_lowercase());
    match extension.as_deref() {
        Some("bin") => Ok(kitti::parse),
        Some("pcd") => Ok(pcd::parse),
        Some("ply") => Ok(ply::parse),
        other => Err(FormatErrorKind::UnsupportedExtension { found: other.unwrap_or("").to_owned() }),
    }
}

/// Writes `cloud` to `path` in `format`; the extension is not checked, but [`read_cloud`]
/// will only read the file back if it matches [`FileFormat::extension`].
pub fn write_cloud(path: &Path, cloud: &PointCloud, format: FileFormat) -> Result<(), FormatError> {
    let fail = |kind| FormatError { path: path.to_owned(), kind };
    cloud.validate().map_err(|e| fail(e.into()))?;
    if format == FileFormat::Pcd(PcdEncoding::BinaryCompressed) && !pcd::fits_compressed(cloud) {
        return Err(fail(FormatErrorKind::TooLarge { points: cloud.len(), format }));
    }
    std::fs::write(path, encode(cloud, format)).map_err(|e| fail(FormatErrorKind::Write(e)))
}

/// The bytes of `cloud` in `format`, as [`write_cloud`] stores them.
///
/// # Panics
/// For PCD binary_compressed when the point data exceeds 4 GiB (see [`pcd::encode`]).
pub fn encode(cloud: &PointCloud, format: FileFormat) -> Vec<u8> {
    match format {
        FileFormat::KittiBin => kitti::encode(cloud),
        FileFormat::Pcd(encoding) => pcd::encode(cloud, encoding),
        FileFormat::Ply(encoding) => ply::encode(cloud, encoding),
    }
}
