#!/usr/bin/env python3
"""Writes the ROS 1 bag fixtures of edge/tests/integration/recordings.rs with a real bag writer (rosbags).

No Rust crate writes ROS 1 bags, so the fixtures come from Python's `rosbags` package
(`pip install rosbags`), which writes format 2.0 with uncompressed, bz2 and lz4 chunks. The
points are subsampled from the real KITTI scans 000000..000002 in ../shared/data.

Outputs, in edge/tests/fixtures/:
- kitti3.bag, kitti3_bz2.bag, kitti3_lz4.bag: the same messages, three chunk compressions:
  - /velodyne_points: float32 x y z intensity, uint16 ring, float32 time at an unaligned offset
    (point_step 22), the ring and per-point time of the KITTI HDL-64 scan lines;
  - /points_f64: big-endian float64 x y z and uint8 intensity, no ring or time (point_step 25);
  - /ouster/points: an organised 2-row cloud with row padding, NaN points and points at the
    origin, uint16 intensity, uint32 `t` in nanoseconds, uint8 ring, and int8/int16/int32 fields
    the reader must skip; the third scan has a zero header stamp (the reader uses the record time);
  - /chatter: std_msgs/String, which the reader must ignore.
- kitti3_expected.bin: what a reader must return for each topic and scan (format below).
- kitti3*.layout: for each chunk of the bag, the byte offset where it ends and how many messages of
  each point-cloud topic the chunks up to it hold (a truncated file must keep at least those).

Expected file, little-endian, per (topic, scan) in the order above:
  u32 topic index (0, 1, 2), u32 point count n, u32 dropped points, f64 stamp seconds,
  u8 has intensity, u8 has ring, u8 has time, u8 0, then n records of
  f32 x, f32 y, f32 z, f32 intensity, u32 ring, f32 time (0 where absent).

Deterministic: running it again rewrites identical files (bz2 and lz4 included).
"""

import struct
import sys
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_typestore

ROOT = Path(__file__).resolve().parents[1]
KITTI = ROOT.parent / "shared" / "data" / "kitti00" / "velodyne"
OUT = ROOT / "edge" / "tests" / "fixtures"
TOPICS = ["/velodyne_points", "/points_f64", "/ouster/points"]
SCANS = 3
BASE_SEC = 1_700_000_000

ts = get_typestore(Stores.ROS1_NOETIC)
PointCloud2 = ts.types["sensor_msgs/msg/PointCloud2"]
PointField = ts.types["sensor_msgs/msg/PointField"]
Header = ts.types["std_msgs/msg/Header"]
Time = ts.types["builtin_interfaces/msg/Time"]
String = ts.types["std_msgs/msg/String"]
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = range(1, 9)


def kitti_scan(index):
    """KITTI points (n x 4 float32) with each point's laser (0 = lowest beam) and sweep time."""
    pts = np.fromfile(KITTI / f"{index:06d}.bin", dtype="<f4").reshape(-1, 4)
    az = np.arctan2(pts[:, 1].astype(np.float64), pts[:, 0].astype(np.float64))
    # KITTI stores each laser's revolution in turn, starting at the front (azimuth 0) and turning
    # counter-clockwise: a new scan line starts where the azimuth crosses 0 upwards.
    starts = (az[:-1] < 0) & (az[1:] >= 0) & (np.abs(az[1:] - az[:-1]) < 1.0)
    line = np.concatenate([[0], np.cumsum(starts)])
    ring = np.clip(63 - line, 0, 63).astype(np.uint16)
    time = np.mod(az, 2 * np.pi) / (2 * np.pi) * 0.1
    return pts, ring, time


def sample(n_total, count, seed):
    return np.linspace(seed, n_total - 1, count).astype(np.int64)


def message(stamp, height, width, fields, big_endian, point_step, row_step, data):
    sec, nsec = stamp
    return PointCloud2(
        header=Header(seq=0, stamp=Time(sec=sec, nanosec=nsec), frame_id="lidar"),
        height=height,
        width=width,
        fields=[PointField(name=n, offset=o, datatype=d, count=1) for n, o, d in fields],
        is_bigendian=big_endian,
        point_step=point_step,
        row_step=row_step,
        data=np.frombuffer(bytes(data), dtype=np.uint8),
        is_dense=False,
    )


class Expected:
    """Accumulates the expected-values file."""

    def __init__(self):
        self.out = bytearray()

    def add(self, topic, stamp, dropped, xyz, intensity=None, ring=None, time=None):
        n = len(xyz)
        self.out += struct.pack("<IIId4B", topic, n, dropped, stamp,
                                intensity is not None, ring is not None, time is not None, 0)
        rec = np.zeros(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<f4"), ("r", "<u4"), ("t", "<f4")])
        rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        if intensity is not None:
            rec["i"] = intensity
        if ring is not None:
            rec["r"] = ring
        if time is not None:
            rec["t"] = time
        self.out += rec.tobytes()


def velodyne_points(scan, stamp, expected):
    """float32 xyz + intensity, uint16 ring, float32 time at offset 18 (unaligned)."""
    pts, ring, time = kitti_scan(scan)
    idx = sample(len(pts), 300, scan)
    t = time[idx] - time[idx].min()  # the reader makes times relative to the earliest point
    t = t.astype(np.float32)
    step = 22
    rec = np.zeros(len(idx), dtype=[("xyzi", "<f4", 4), ("ring", "<u2"), ("time", "<f4")])
    assert rec.itemsize == step
    rec["xyzi"] = pts[idx]
    rec["ring"] = ring[idx]
    rec["time"] = t
    fields = [("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 12, FLOAT32),
              ("ring", 16, UINT16), ("time", 18, FLOAT32)]
    msg = message(stamp, 1, len(idx), fields, False, step, step * len(idx), rec.tobytes())
    expected.add(0, stamp[0] + stamp[1] * 1e-9, 0, pts[idx, :3], pts[idx, 3], ring[idx], t)
    return msg


def points_f64(scan, stamp, expected):
    """Big-endian float64 xyz (not exactly representable in float32) and uint8 intensity."""
    pts, _, _ = kitti_scan(scan)
    idx = sample(len(pts), 250, scan + 7)
    xyz = pts[idx, :3].astype(np.float64) + 1.234567e-6
    intensity = np.round(pts[idx, 3] * 255).astype(np.uint8)
    rec = np.zeros(len(idx), dtype=[("xyz", ">f8", 3), ("i", "u1")])
    rec["xyz"], rec["i"] = xyz, intensity
    fields = [("x", 0, FLOAT64), ("y", 8, FLOAT64), ("z", 16, FLOAT64), ("intensity", 24, UINT8)]
    msg = message(stamp, 1, len(idx), fields, True, 25, 25 * len(idx), rec.tobytes())
    expected.add(1, stamp[0] + stamp[1] * 1e-9, 0, xyz.astype(np.float32), intensity.astype(np.float32))
    return msg


def ouster_points(scan, stamp, record_time, expected):
    """Organised 2 x 120 cloud with NaNs, origin points, row padding and fields to skip."""
    pts, _, _ = kitti_scan(scan)
    height, width, step, row_pad = 2, 120, 32, 16
    idx = sample(len(pts), height * width, scan + 3)
    xyz = pts[idx, :3].copy()
    col = np.tile(np.arange(width), height)
    row = np.repeat(np.arange(height), width)
    xyz[(np.arange(len(idx)) % 7 == 3)] = np.nan           # no return, as NaN
    xyz[(np.arange(len(idx)) % 11 == 5), :] = 0.0           # no return, as the origin
    t_ns = (col * (100_000_000 // width)).astype(np.uint32)  # Ouster: t per column, from 0
    intensity = np.round(pts[idx, 3] * 1000).astype(np.uint16)
    rec = np.zeros(len(idx), dtype=[("xyz", "<f4", 3), ("i", "<u2"), ("t", "<u4"), ("ring", "u1"),
                                    ("pad", "u1"), ("ambient", "<i2"), ("noise", "<i4"), ("flags", "i1"),
                                    ("pad2", "u1", 5)])
    assert rec.itemsize == step
    rec["xyz"], rec["i"], rec["t"], rec["ring"] = xyz, intensity, t_ns, row
    rec["ambient"], rec["noise"], rec["flags"] = -(col.astype(np.int16)), -100000, -3
    data = bytearray()
    for r in range(height):
        data += rec[r * width:(r + 1) * width].tobytes() + b"\xee" * row_pad
    fields = [("x", 0, FLOAT32), ("y", 4, FLOAT32), ("z", 8, FLOAT32), ("intensity", 12, UINT16),
              ("t", 14, UINT32), ("ring", 18, UINT8), ("ambient", 20, INT16), ("noise", 22, INT32),
              ("flags", 26, INT8)]
    msg = message(stamp, height, width, fields, False, step, width * step + row_pad, data)
    valid = np.isfinite(xyz).all(axis=1) & (xyz != 0).any(axis=1)
    assert valid[0], "the first point must be valid: the reader's time zero is the earliest finite point"
    stamp_s = stamp[0] + stamp[1] * 1e-9 if stamp != (0, 0) else record_time * 1e-9
    time = (t_ns[valid].astype(np.float64) * 1e-9).astype(np.float32)
    expected.add(2, stamp_s, int((~valid).sum()), xyz[valid], intensity[valid].astype(np.float32),
                 row[valid], time)
    return msg


def layout(path):
    """(end offset, messages per point-cloud topic so far) for each chunk, parsing the bag anew."""
    data = path.read_bytes()
    pos, conns, counts, rows = 13, {}, [0, 0, 0], []

    def fields(header):
        out, i = {}, 0
        while i < len(header):
            (n,), i = struct.unpack_from("<I", header, i), i + 4
            name, _, value = header[i:i + n].partition(b"=")
            out[name.decode()], i = value, i + n
        return out

    while pos < len(data):
        (hlen,) = struct.unpack_from("<I", data, pos)
        header = fields(data[pos + 4:pos + 4 + hlen])
        (dlen,) = struct.unpack_from("<I", data, pos + 4 + hlen)
        end = pos + 8 + hlen + dlen
        if header["op"] == b"\x05":
            body = data[pos + 8 + hlen:end]
            comp = header["compression"].decode()
            if comp == "bz2":
                import bz2
                body = bz2.decompress(body)
            elif comp == "lz4":
                import lz4.frame
                body = lz4.frame.decompress(body)
            i = 0
            while i < len(body):
                (h,) = struct.unpack_from("<I", body, i)
                inner = fields(body[i + 4:i + 4 + h])
                (d,) = struct.unpack_from("<I", body, i + 4 + h)
                if inner["op"] == b"\x07":
                    conns[inner["conn"]] = inner["topic"].decode()
                elif inner["op"] == b"\x02" and conns.get(inner["conn"]) in TOPICS:
                    counts[TOPICS.index(conns[inner["conn"]])] += 1
                i += 8 + h + d
            rows.append((end, *counts))
        pos = end
    return rows


def write_bag(path, compression, chunk_threshold, messages):
    path.unlink(missing_ok=True)
    writer = Writer(path)
    if compression:
        writer.set_compression(compression)
    writer.chunk_threshold = chunk_threshold
    with writer:
        conns = {t: writer.add_connection(t, "sensor_msgs/msg/PointCloud2", typestore=ts) for t in TOPICS}
        conns["/chatter"] = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=ts)
        for topic, time_ns, msg in messages:
            typename = "std_msgs/msg/String" if topic == "/chatter" else "sensor_msgs/msg/PointCloud2"
            writer.write(conns[topic], time_ns, ts.serialize_ros1(msg, typename))
    rows = layout(path)
    path.with_suffix(".layout").write_text("".join(" ".join(map(str, r)) + "\n" for r in rows))


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    expected = Expected()
    per_topic = {t: [] for t in TOPICS}
    chatter = []
    for scan in range(SCANS):
        record_time = (BASE_SEC + scan) * 10**9 + 50_000_000
        stamp = (BASE_SEC + scan, 100_000_000 * scan + 123)
        per_topic[TOPICS[0]].append((record_time, velodyne_points(scan, stamp, expected)))
        per_topic[TOPICS[1]].append((record_time + 1000, points_f64(scan, stamp, expected)))
        ouster_stamp = (0, 0) if scan == 2 else stamp
        per_topic[TOPICS[2]].append((record_time + 2000, ouster_points(scan, ouster_stamp, record_time + 2000, expected)))
        chatter.append((record_time + 3000, String(data=f"scan {scan}")))
    (OUT / "kitti3_expected.bin").write_bytes(bytes(expected.out))
    # Interleave topics in time order, as a recorder would.
    messages = sorted(((t, topic, m) for topic, items in [*per_topic.items(), ("/chatter", chatter)]
                       for t, m in items), key=lambda x: x[0])
    messages = [(topic, t, m) for t, topic, m in messages]
    write_bag(OUT / "kitti3.bag", None, 1, messages)  # one message per chunk
    write_bag(OUT / "kitti3_bz2.bag", Writer.CompressionFormat.BZ2, 1 << 20, messages)  # one chunk
    write_bag(OUT / "kitti3_lz4.bag", Writer.CompressionFormat.LZ4, 20_000, messages)  # a few chunks
    for f in sorted(OUT.glob("kitti3*")):
        print(f"{f.relative_to(ROOT)}: {f.stat().st_size} bytes", file=sys.stderr)


if __name__ == "__main__":
    main()
