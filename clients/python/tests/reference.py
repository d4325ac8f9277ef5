"""A plain, slow encoder of the cloud codec for the tests: written from the byte layout at the top
of proto/src/codec.rs, independently of the decoder, so that round trips test the decoder against
the format rather than against itself. (The Rust test checks the decoder against the Rust encoder.)"""

import struct

import zstandard

HALF = 1 << 31


def wrap(v):
    return ((v + HALF) % (1 << 32)) - HALF


def zigzag(v):
    v = wrap(v)
    return ((v << 1) ^ (v >> 31)) & 0xFFFFFFFF


def dominant(b):
    m = [abs(v) for v in b]
    if m[0] >= m[1] and m[0] >= m[2]:
        return 0
    return 1 if m[1] >= m[2] else 2


def slope(v, vd):
    return round(float(v) * 65536.0 / float(vd if vd else 1))


def scan_residual(p, a, b):
    d = dominant(b)
    axes = [d, (d + 1) % 3, (d + 2) % 3]
    lin = [wrap(2 * a[k] - b[k]) for k in range(3)]
    s = p[d] - lin[d]
    out = [wrap(p[d] - a[d])]
    for m in axes[1:]:
        guess = wrap(lin[m] + ((s * slope(b[m], b[d]) + (1 << 15)) >> 16))
        out.append(wrap(p[m] - guess))
    return out


def residual_streams(points, predictor):
    """Three lists of zigzag codes, one per stream."""
    streams = [[], [], []]
    a = b = [0, 0, 0]
    for i, p in enumerate(points):
        r = [wrap(p[k] - a[k]) for k in range(3)] if predictor == 0 else scan_residual(p, a, b)
        for k in range(3):
            streams[k].append(zigzag(r[k]))
        a, b = p, (p if i == 0 else a)
    return streams


def delta_stream(values):
    out, previous = [], 0
    for v in values:
        out.append(zigzag(v - previous))
        previous = v
    return out


def stream_bytes(codes, level=1):
    """Four byte planes, least significant first; an all-zero plane as a bare zero length."""
    out = b""
    compressor = zstandard.ZstdCompressor(level=level, write_checksum=True, write_content_size=True)
    for shift in (0, 8, 16, 24):
        plane = bytes((c >> shift) & 0xFF for c in codes)
        if not any(plane):
            out += struct.pack("<I", 0)
            continue
        frame = compressor.compress(plane)
        out += struct.pack("<I", len(frame)) + frame
    return out


def encode(points, predictor=0, intensity=None, ring=None, time=None, steps=(1e-3, 1e-3, 1e-6), reordered=False):
    """An encoded cloud from quantised values: ``points`` a list of [x, y, z] ints, channels lists
    of ints (ring: raw indices)."""
    flags = (intensity is not None) | (ring is not None) << 1 | (time is not None) << 2 | reordered << 3
    out = b"EMPC" + bytes([1, flags, predictor, 0]) + struct.pack("<dddQ", *steps, len(points))
    for codes in residual_streams(points, predictor):
        out += stream_bytes(codes)
    for channel in (intensity, ring, time):
        if channel is not None:
            out += stream_bytes(delta_stream(channel))
    return out
