//! Streams of `u32` residuals on the wire: four byte planes, each an independent zstd frame.
//!
//! Splitting a stream into planes gives zstd's Huffman stage homogeneous data: the low bytes are
//! noisy, the high ones almost always zero (and then stored as a bare zero length).

use std::io;

use super::DecodeError;

/// Bytes in a stream value; one plane each.
const PLANES: usize = 4;

/// The first four bytes of every zstd frame (format 1, not legacy, not skippable).
const ZSTD_MAGIC: [u8; 4] = [0x28, 0xb5, 0x2f, 0xfd];

/// Appends streams to an encoded buffer, reusing one zstd context and the plane buffer.
pub(crate) struct SectionWriter {
    zstd: zstd::bulk::Compressor<'static>,
    plane: Vec<u8>,
    frame: Vec<u8>,
}

impl SectionWriter {
    /// A writer compressing at zstd `level` on the calling thread, with frame checksums on.
    pub(crate) fn new(level: i32) -> io::Result<Self> {
        use zstd::zstd_safe::CParameter;
        let mut zstd = zstd::bulk::Compressor::new(level)?;
        zstd.set_parameter(CParameter::ChecksumFlag(true))?;
        if level == 1 {
            // Residual planes hold few long repeats: a tiny match finder that only takes 7-byte
            // matches is 35 % faster than zstd's level 1 and 0.3-2 % smaller (KITTI, maps).
            zstd.set_parameter(CParameter::HashLog(6))?;
            zstd.set_parameter(CParameter::MinMatch(7))?;
        }
        Ok(Self { zstd, plane: Vec::new(), frame: Vec::new() })
    }

    /// Appends a stream as four planes, least significant byte first; `values` is iterated once
    /// per non-zero plane (one pass per plane is faster than splitting all four at once).
    pub(crate) fn write(&mut self, values: impl Iterator<Item = u32> + Clone, out: &mut Vec<u8>) -> io::Result<()> {
        let used_bits = values.clone().fold(0, |acc, v| acc | v);
        for byte in 0..PLANES {
            let shift = 8 * byte;
            if (used_bits >> shift) & 0xff == 0 {
                out.extend_from_slice(&0u32.to_le_bytes());
                continue;
            }
            self.plane.clear();
            self.plane.extend(values.clone().map(|v| (v >> shift) as u8));
            self.frame.clear();
            self.frame.reserve(zstd::zstd_safe::compress_bound(self.plane.len()));
            self.zstd.compress_to_buffer(&self.plane, &mut self.frame)?;
            let len = u32::try_from(self.frame.len()).map_err(io::Error::other)?;
            out.extend_from_slice(&len.to_le_bytes());
            out.extend_from_slice(&self.frame);
        }
        Ok(())
    }
}

/// One byte plane as found in the input, checked before anything is allocated for it.
#[derive(Clone, Copy)]
enum Plane<'a> {
    /// Stored as length 0: all bytes zero.
    Zero,
    /// A zstd frame declaring exactly the expected content size, and where it starts.
    Zstd(&'a [u8], usize),
}

/// A stream located in the input, not yet decompressed.
pub(crate) struct Section<'a>([Plane<'a>; PLANES]);

/// Walks the streams of a message, checking each before anything is allocated for it.
pub(crate) struct Cursor<'a> {
    input: &'a [u8],
    offset: usize,
    n: usize,
}

impl<'a> Cursor<'a> {
    /// A cursor over `input`, which starts at byte `offset` of the message, for streams of `n` values.
    pub(crate) fn new(input: &'a [u8], offset: usize, n: usize) -> Self {
        Self { input, offset, n }
    }

    /// Locates the next stream.
    pub(crate) fn section(&mut self) -> Result<Section<'a>, DecodeError> {
        let mut planes = [Plane::Zero; PLANES];
        for plane in &mut planes {
            let len = take(&mut self.input, &mut self.offset, 4)?;
            let len = u32::from_le_bytes([len[0], len[1], len[2], len[3]]) as usize;
            if len > 0 {
                let at = self.offset;
                let frame = take(&mut self.input, &mut self.offset, len)?;
                check_frame(frame, at, self.n)?;
                *plane = Plane::Zstd(frame, at);
            }
        }
        Ok(Section(planes))
    }

    /// Checks that nothing follows the last stream.
    pub(crate) fn finish(self) -> Result<(), DecodeError> {
        match self.input.len() {
            0 => Ok(()),
            extra => Err(DecodeError::TrailingBytes(extra)),
        }
    }
}

/// Splits `len` bytes off the front of `input`, or reports where the input ended early.
pub(crate) fn take<'a>(input: &mut &'a [u8], offset: &mut usize, len: usize) -> Result<&'a [u8], DecodeError> {
    if input.len() < len {
        return Err(DecodeError::Truncated { offset: *offset, needed: len, available: input.len() });
    }
    let (head, tail) = input.split_at(len);
    *input = tail;
    *offset += len;
    Ok(head)
}

/// Rejects anything but one standard zstd frame declaring `n` bytes of content, so a hostile
/// frame can neither make the decoder allocate more than `n` nor reach the legacy decoders.
fn check_frame(frame: &[u8], offset: usize, n: usize) -> Result<(), DecodeError> {
    if !frame.starts_with(&ZSTD_MAGIC) {
        return Err(DecodeError::BadSection { offset, reason: "not a zstd frame" });
    }
    match zstd::zstd_safe::get_frame_content_size(frame) {
        Ok(Some(size)) if size == n as u64 => Ok(()),
        Ok(Some(_)) => Err(DecodeError::BadSection { offset, reason: "frame size differs from the point count" }),
        Ok(None) => Err(DecodeError::BadSection { offset, reason: "frame does not declare its size" }),
        Err(_) => Err(DecodeError::BadSection { offset, reason: "corrupt zstd frame header" }),
    }
}

/// Decompresses located streams, reusing one zstd context and the plane buffers.
pub(crate) struct SectionReader {
    zstd: zstd::bulk::Decompressor<'static>,
    planes: [Vec<u8>; PLANES],
}

impl SectionReader {
    /// A reader with a fresh zstd context.
    pub(crate) fn new() -> Result<Self, DecodeError> {
        let zstd = zstd::bulk::Decompressor::new().map_err(|source| DecodeError::Zstd { offset: 0, source })?;
        Ok(Self { zstd, planes: Default::default() })
    }

    /// The `n` values of `section`, whose frames [`Cursor::section`] checked to hold `n` bytes.
    pub(crate) fn read(
        &mut self,
        section: &Section<'_>,
        n: usize,
    ) -> Result<impl ExactSizeIterator<Item = u32> + '_, DecodeError> {
        for (plane, stored) in self.planes.iter_mut().zip(&section.0) {
            plane.clear();
            match *stored {
                Plane::Zero => plane.resize(n, 0),
                Plane::Zstd(frame, offset) => {
                    plane.reserve_exact(n);
                    // The capacity bounds the output: a frame inflating beyond `n` is an error.
                    let len = self
                        .zstd
                        .decompress_to_buffer(frame, plane)
                        .map_err(|source| DecodeError::Zstd { offset, source })?;
                    if len != n {
                        return Err(DecodeError::BadSection { offset, reason: "frame content shorter than declared" });
                    }
                }
            }
        }
        let [b0, b1, b2, b3] = &self.planes;
        let bytes = b0.iter().zip(b1).zip(b2).zip(b3);
        Ok(bytes.map(|(((&b0, &b1), &b2), &b3)| u32::from_le_bytes([b0, b1, b2, b3])))
    }
}
