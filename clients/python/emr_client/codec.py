"""Decoder of the EMR point-cloud codec (``CompressedCloud.data``), byte layout version 1.

The layout is documented at the top of proto/src/codec.rs; this module follows it field by field
and decodes bit for bit what the Rust decoder does: the same f32 coordinates, intensities and times,
the same ring indices. Like the Rust decoder it checks every length against the input before
allocating, and any malformed input raises ``CodecError`` naming what is wrong and where.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from typing import Optional

import numpy as np
import zstandard

from . import predict

MAGIC = b"EMPC"
VERSION = 1
HEADER_LEN = 40
FLAG_INTENSITY = 1
FLAG_RING = 2
FLAG_TIME = 4
FLAG_REORDERED = 8
KNOWN_FLAGS = FLAG_INTENSITY | FLAG_RING | FLAG_TIME | FLAG_REORDERED
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
PLANES = 4
# The default bound on the declared point count, as the Rust decoder's ``DecodeLimits``.
MAX_POINTS = 1 << 26
# Largest step whose 2^31 multiple is still a finite f32 (f32::MAX / 2^31).
F32_MAX = float(np.finfo(np.float32).max)


class CodecError(ValueError):
    """Bytes that are not a valid encoded cloud; the message says what and at which offset."""


@dataclasses.dataclass
class Cloud:
    """A decoded cloud: ``xyz`` is n x 3 float32; each channel an n-vector or None when absent."""

    xyz: np.ndarray
    intensity: Optional[np.ndarray] = None
    ring: Optional[np.ndarray] = None
    time: Optional[np.ndarray] = None
    # The header: quantisation steps, xyz predictor ("delta" or "scan"), Z-order flag.
    step: float = 1e-3
    intensity_step: float = 1e-3
    time_step: float = 1e-6
    predictor: str = "delta"
    reordered: bool = False

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclasses.dataclass
class Header:
    """The 40-byte header, validated."""

    flags: int
    predictor: int
    step: float
    intensity_step: float
    time_step: float
    count: int


def decode_cloud(data: bytes, max_points: int = MAX_POINTS) -> Cloud:
    """Decodes an encoded cloud; refuses more than ``max_points`` points before allocating."""
    header, quantised = decode_quantised(data, max_points)
    cloud = Cloud(
        xyz=dequantise(quantised["xyz"], header.step),
        step=header.step,
        intensity_step=header.intensity_step,
        time_step=header.time_step,
        predictor=predict.PREDICTORS[header.predictor],
        reordered=bool(header.flags & FLAG_REORDERED),
    )
    if "intensity" in quantised:
        cloud.intensity = dequantise(quantised["intensity"], header.intensity_step)
    if "ring" in quantised:
        cloud.ring = quantised["ring"].astype(np.uint16)
    if "time" in quantised:
        cloud.time = dequantise(quantised["time"], header.time_step)
    return cloud


def decode_quantised(data: bytes, max_points: int = MAX_POINTS) -> tuple:
    """The header and the integer values before dequantisation: ``xyz`` (n x 3), and per present
    channel ``intensity``, ``ring`` and ``time`` (n), all int64. The exact quantities the format
    defines, for callers that compare clouds in steps."""
    data = memoryview(data).cast("B")
    header = parse_header(data)
    if header.count > max_points:
        raise CodecError(f"{header.count} points declared, limit is {max_points}")
    n = header.count
    channels = [name for flag, name in _CHANNELS if header.flags & flag]
    sections = _locate_sections(data, n, 3 + len(channels))
    dctx = zstandard.ZstdDecompressor()
    residuals = np.stack([predict.unzigzag(_read_stream(dctx, s, n)) for s in sections[:3]])
    out = {"xyz": predict.reconstruct(residuals, header.predictor)}
    for name, section in zip(channels, sections[3:]):
        deltas = predict.unzigzag(_read_stream(dctx, section, n))
        out[name] = _rings(deltas) if name == "ring" else predict.wrap(np.cumsum(deltas & predict.MASK32))
    return header, out


_CHANNELS = ((FLAG_INTENSITY, "intensity"), (FLAG_RING, "ring"), (FLAG_TIME, "time"))


def dequantise(q: np.ndarray, step: float) -> np.ndarray:
    """``f32(f64(q) * step)``, as the encoder defines decoded values."""
    return (q.astype(np.float64) * step).astype(np.float32)


def parse_header(data: memoryview) -> Header:
    """The header fields, each checked as the Rust decoder checks them."""
    if len(data) < HEADER_LEN:
        raise CodecError(f"truncated input: {HEADER_LEN} header bytes needed, {len(data)} given")
    magic, version, flags, predictor, reserved, step, istep, tstep, count = struct.unpack_from(
        "<4sBBBBdddQ", data, 0
    )
    if magic != MAGIC:
        raise CodecError(f"not an encoded point cloud: magic {bytes(magic)!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise CodecError(f"unsupported codec version {version} (this decoder reads {VERSION})")
    if flags & ~KNOWN_FLAGS or reserved != 0:
        raise CodecError(f"unknown flags {flags:#04x} or reserved byte {reserved:#04x}")
    if predictor not in predict.PREDICTORS:
        raise CodecError(f"unknown predictor {predictor}")
    for name, value in (("step", step), ("intensity_step", istep), ("time_step", tstep)):
        if not _valid_step(value):
            raise CodecError(f"invalid {name} {value} in header")
    return Header(flags, predictor, step, istep, tstep, count)


def _valid_step(step: float) -> bool:
    """Finite, positive, and small enough that ``2^31 * step`` is a finite f32."""
    return math.isfinite(step) and step > 0.0 and step * 2.0**31 <= F32_MAX


def _locate_sections(data: memoryview, n: int, streams: int) -> list:
    """Every stream's four planes as (offset, frame or None for an all-zero plane), checked."""
    offset = HEADER_LEN
    sections = []
    for _ in range(streams):
        planes = []
        for _ in range(PLANES):
            (length,) = struct.unpack_from("<I", _take(data, offset, 4), 0)
            offset += 4
            if length == 0:
                planes.append((offset, None))
                continue
            frame = _take(data, offset, length)
            _check_frame(frame, offset, n)
            planes.append((offset, frame))
            offset += length
        sections.append(planes)
    if offset != len(data):
        raise CodecError(f"{len(data) - offset} unexpected bytes after the last stream")
    return sections


def _take(data: memoryview, offset: int, length: int) -> memoryview:
    """``length`` bytes at ``offset``, or an error saying where the input ended."""
    if len(data) - offset < length:
        raise CodecError(
            f"truncated input: {length} bytes needed at offset {offset}, {len(data) - offset} left"
        )
    return data[offset : offset + length]


def _check_frame(frame: memoryview, offset: int, n: int) -> None:
    """One standard zstd frame declaring ``n`` bytes of content, so that a hostile frame can
    neither make the decoder allocate more than ``n`` nor reach a legacy format."""
    if bytes(frame[:4]) != ZSTD_MAGIC:
        raise CodecError(f"bad section at offset {offset}: not a zstd frame")
    try:
        size = zstandard.frame_content_size(frame)
    except zstandard.ZstdError:
        raise CodecError(f"bad section at offset {offset}: corrupt zstd frame header") from None
    if size < 0:
        raise CodecError(f"bad section at offset {offset}: frame does not declare its size")
    if size != n:
        raise CodecError(f"bad section at offset {offset}: frame size {size} differs from the point count {n}")


def _read_stream(dctx: zstandard.ZstdDecompressor, planes: list, n: int) -> np.ndarray:
    """The ``n`` u32 values of a stream: its planes, least significant byte first, side by side."""
    values = np.zeros((n, PLANES), dtype=np.uint8)
    for k, (offset, frame) in enumerate(planes):
        if frame is None:
            continue
        try:
            plane = dctx.decompress(frame, max_output_size=n, allow_extra_data=False)
        except zstandard.ZstdError as e:
            raise CodecError(f"zstd failed on the frame at offset {offset}: {e}") from None
        if len(plane) != n:
            raise CodecError(f"bad section at offset {offset}: frame content shorter than declared")
        values[:, k] = np.frombuffer(plane, dtype=np.uint8)
    return values.view("<u4").reshape(n)


def _rings(deltas: np.ndarray) -> np.ndarray:
    """Ring indices from their deltas, exact (no wrapping) and each within 0..=65535."""
    rings = np.cumsum(deltas)
    bad = np.flatnonzero((rings < 0) | (rings > 0xFFFF))
    if bad.size:
        raise CodecError(f"ring of point {int(bad[0])} out of range ({int(rings[bad[0]])})")
    return rings
