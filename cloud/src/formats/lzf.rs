//! LZF compression, the liblzf format PCL uses for `DATA binary_compressed`.
//!
//! Hand-written because the `lzf` crate is deprecated. The stream is a sequence of tokens, each
//! opened by a control byte `c`: `c < 32` announces `c + 1` literal bytes; otherwise `c >> 5` is
//! the match length minus 2 (7 means "plus the next byte") and the low 5 bits, with the byte after
//! the length, hold the match distance minus 1.

/// Longest literal run one control byte can announce.
const MAX_LITERAL: usize = 1 << 5;
/// Farthest back a match may point (13 bits of distance).
const MAX_DISTANCE: usize = 1 << 13;
/// Longest match: length code 7, plus an extension byte of 255, plus the implicit 2.
const MAX_MATCH: usize = 7 + 255 + 2;
/// Size of the compressor's match-finding table, as a power of two.
const HASH_BITS: u32 = 14;

/// Why LZF data cannot be decompressed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LzfError {
    /// The data ends in the middle of a token.
    #[error("LZF data ends inside the token at byte {0}")]
    Truncated(usize),
    /// A match points before the start of the output.
    #[error("LZF match at byte {at} reaches {distance} bytes back but only {written} are decoded")]
    BadReference {
        /// Offset of the token in the compressed data.
        at: usize,
        /// How far back the match points.
        distance: usize,
        /// Bytes decoded so far.
        written: usize,
    },
    /// The data decodes to more bytes than expected.
    #[error("LZF data decodes to more than the expected {expected} bytes")]
    Overflow {
        /// The expected decompressed size.
        expected: usize,
    },
    /// The data decodes to fewer bytes than expected.
    #[error("LZF data decodes to {found} bytes, expected {expected}")]
    Short {
        /// Bytes actually decoded.
        found: usize,
        /// The expected decompressed size.
        expected: usize,
    },
}

/// Decompresses `input`, which must decode to exactly `expected` bytes.
pub fn decompress(input: &[u8], expected: usize) -> Result<Vec<u8>, LzfError> {
    // A 3-byte token yields at most MAX_MATCH bytes, so a hostile `expected` cannot make us
    // reserve more than the input could ever produce.
    let bound = input.len().saturating_mul(MAX_MATCH / 3 + 1);
    let mut out = Vec::with_capacity(expected.min(bound));
    let mut pos = 0;
    while let Some(&ctrl) = input.get(pos) {
        let ctrl = usize::from(ctrl);
        pos = if ctrl < MAX_LITERAL {
            copy_literals(input, pos, ctrl + 1, &mut out, expected)?
        } else {
            copy_match(input, pos, ctrl, &mut out, expected)?
        };
    }
    if out.len() != expected {
        return Err(LzfError::Short { found: out.len(), expected });
    }
    Ok(out)
}

/// Appends the `len` literal bytes following the control byte at `at`; returns the next token's offset.
fn copy_literals(input: &[u8], at: usize, len: usize, out: &mut Vec<u8>, expected: usize) -> Result<usize, LzfError> {
    let run = input.get(at + 1..at + 1 + len).ok_or(LzfError::Truncated(at))?;
    if out.len() + len > expected {
        return Err(LzfError::Overflow { expected });
    }
    out.extend_from_slice(run);
    Ok(at + 1 + len)
}

/// Appends the match whose control byte `ctrl` is at `at`; returns the next token's offset.
fn copy_match(input: &[u8], at: usize, ctrl: usize, out: &mut Vec<u8>, expected: usize) -> Result<usize, LzfError> {
    let byte = |i: usize| input.get(i).map(|&b| usize::from(b)).ok_or(LzfError::Truncated(at));
    let mut next = at + 1;
    let mut len = ctrl >> 5;
    if len == 7 {
        len += byte(next)?;
        next += 1;
    }
    let len = len + 2;
    let distance = ((ctrl & 0x1f) << 8 | byte(next)?) + 1;
    let written = out.len();
    if distance > written {
        return Err(LzfError::BadReference { at, distance, written });
    }
    if written + len > expected {
        return Err(LzfError::Overflow { expected });
    }
    let from = written - distance;
    if distance >= len {
        out.extend_from_within(from..from + len);
    } else {
        // The match overlaps its own output (a repeating pattern): bytes must be copied one by
        // one so that each copy sees the bytes just written.
        for k in from..from + len {
            out.push(out[k]);
        }
    }
    Ok(next + 1)
}

/// Compresses `input`; the result may be slightly larger than the input when it does not compress.
pub fn compress(input: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(input.len() + input.len() / MAX_LITERAL + 1);
    // Last position + 1 at which each 3-byte hash was seen; 0 means never.
    let mut table = vec![0usize; 1 << HASH_BITS];
    let mut literal_start = 0;
    let mut pos = 0;
    while pos + 3 <= input.len() {
        let slot = &mut table[hash(&input[pos..pos + 3])];
        let candidate = slot.checked_sub(1);
        *slot = pos + 1;
        match candidate.and_then(|c| match_len(input, c, pos).map(|len| (c, len))) {
            Some((c, len)) => {
                push_literals(&mut out, &input[literal_start..pos]);
                push_match(&mut out, pos - c, len);
                pos += len;
                literal_start = pos;
            }
            None => pos += 1,
        }
    }
    push_literals(&mut out, &input[literal_start..]);
    out
}

/// Table index for the three bytes starting a potential match.
fn hash(bytes: &[u8]) -> usize {
    let v = bytes.iter().fold(0u32, |acc, &b| acc << 8 | u32::from(b));
    (v.wrapping_mul(2_654_435_761) >> (32 - HASH_BITS)) as usize
}

/// Length of the match between `candidate` and `pos` (candidate < pos), if usable (>= 3 bytes).
fn match_len(input: &[u8], candidate: usize, pos: usize) -> Option<usize> {
    if pos - candidate > MAX_DISTANCE {
        return None;
    }
    let limit = (input.len() - pos).min(MAX_MATCH);
    let ahead = &input[pos..pos + limit];
    let len = input[candidate..].iter().zip(ahead).take_while(|(a, b)| a == b).count();
    (len >= 3).then_some(len)
}

/// Emits `bytes` as literal runs of at most [`MAX_LITERAL`] bytes.
fn push_literals(out: &mut Vec<u8>, bytes: &[u8]) {
    for run in bytes.chunks(MAX_LITERAL) {
        out.push((run.len() - 1) as u8);
        out.extend_from_slice(run);
    }
}

/// Emits a match of `len` bytes (3..=MAX_MATCH) starting `distance` bytes back (1..=MAX_DISTANCE).
fn push_match(out: &mut Vec<u8>, distance: usize, len: usize) {
    let d = distance - 1;
    let l = len - 2;
    if l < 7 {
        out.push((l << 5 | d >> 8) as u8);
    } else {
        out.push((7 << 5 | d >> 8) as u8);
        out.push((l - 7) as u8);
    }
    out.push((d & 0xff) as u8);
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn round_trip(data: &[u8]) {
        let packed = compress(data);
        assert_eq!(decompress(&packed, data.len()).as_deref(), Ok(data));
    }

    #[test]
    fn empty_input_round_trips() {
        assert!(compress(&[]).is_empty());
        round_trip(&[]);
    }

    #[test]
    fn real_scan_round_trips_and_shrinks() {
        let data = std::fs::read(testkit::shared_data("kitti00/velodyne/000000.bin")).expect("KITTI test scan");
        let packed = compress(&data);
        assert!(packed.len() < data.len(), "{} >= {}", packed.len(), data.len());
        round_trip(&data);
    }

    #[test]
    fn long_runs_use_maximal_overlapping_matches() {
        let data = vec![7u8; 10_000];
        let packed = compress(&data);
        // One literal, then matches of MAX_MATCH bytes, three bytes each.
        assert!(packed.len() < 3 * (data.len() / MAX_MATCH + 2), "{}", packed.len());
        round_trip(&data);
    }

    #[test]
    fn matches_at_the_distance_limit_round_trip() {
        let block: Vec<u8> = (0..MAX_DISTANCE).map(|i| (i * 7919 % 251) as u8).collect();
        let data = [block.as_slice(), block.as_slice(), &block[..100]].concat();
        round_trip(&data);
    }

    #[test]
    fn known_stream_decodes() {
        // "abc" as literals, then a 6-byte match 3 back: "abcabcabc".
        let stream = [2, b'a', b'b', b'c', 4 << 5, 2];
        assert_eq!(decompress(&stream, 9).as_deref(), Ok(&b"abcabcabc"[..]));
    }

    #[test]
    fn decodes_what_liblzf_produced() {
        // liblzf 3.6 `lzf_compress` output for TEXT (generated once with the C library).
        const TEXT: &[u8] = b"the point cloud library, the point cloud file, \
                              aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa!";
        const PACKED: [u8; 44] = [
            25, 116, 104, 101, 32, 112, 111, 105, 110, 116, 32, 99, 108, 111, 117, 100, 32, 108, 105, 98, 114, 97, 114,
            121, 44, 32, 116, 224, 6, 24, 6, 102, 105, 108, 101, 44, 32, 97, 224, 31, 0, 1, 97, 33,
        ];
        assert_eq!(decompress(&PACKED, TEXT.len()).as_deref(), Ok(TEXT));
    }

    #[test]
    fn reference_before_start_is_rejected() {
        let stream = [0, b'a', 1 << 5, 5];
        assert_eq!(decompress(&stream, 4), Err(LzfError::BadReference { at: 2, distance: 6, written: 1 }));
    }

    #[test]
    fn output_overflow_is_rejected() {
        assert_eq!(decompress(&[2, 1, 2, 3], 2), Err(LzfError::Overflow { expected: 2 }));
        assert_eq!(decompress(&[0, 1, 7 << 5, 200, 0], 50), Err(LzfError::Overflow { expected: 50 }));
    }

    #[test]
    fn short_and_cut_streams_are_rejected() {
        assert_eq!(decompress(&[1, 9, 9], 3), Err(LzfError::Short { found: 2, expected: 3 }));
        assert_eq!(decompress(&[5, 1, 2], 6), Err(LzfError::Truncated(0)));
        assert_eq!(decompress(&[0, 1, 7 << 5], 6), Err(LzfError::Truncated(2)));
        assert_eq!(decompress(&[0, 1, 1 << 5], 6), Err(LzfError::Truncated(2)));
    }

    proptest! {
        #[test]
        fn arbitrary_bytes_round_trip(data in proptest::collection::vec(any::<u8>(), 0..3000)) {
            round_trip(&data);
        }

        #[test]
        fn repetitive_bytes_round_trip(data in proptest::collection::vec(0u8..3, 0..3000)) {
            round_trip(&data);
        }

        #[test]
        fn decompressing_garbage_never_panics(
            data in proptest::collection::vec(any::<u8>(), 0..500),
            expected in 0usize..5000,
        ) {
            if let Ok(out) = decompress(&data, expected) {
                prop_assert_eq!(out.len(), expected);
            }
        }
    }
}
