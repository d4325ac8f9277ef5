#!/usr/bin/env python3
"""The vendors' reference decoders on the shared packet captures: median seconds to decode each
capture (file read included, a few hundred kB from the page cache) and the real-time factor, the
figures `emr-eval packets` gives for ours.

    pip install velodyne-decoder==3.0.0 ouster-sdk==1.0.1
    python3 scripts/compare_packet_decoders.py [../shared/data/lidar_packets] [--repeat 20]
"""
import argparse
import pathlib
import statistics
import struct
import time


def capture_span(path):
    """Seconds from the first captured frame to the last (classic pcap, microseconds)."""
    data = path.read_bytes()
    offset, stamps = 24, []
    while offset + 16 <= len(data):
        seconds, micros, included, _ = struct.unpack_from("<IIII", data, offset)
        stamps.append(seconds + micros * 1e-6)
        offset += 16 + included
    return stamps[-1] - stamps[0]


def velodyne(path):
    import velodyne_decoder as vd

    return sum(len(cloud) for _, cloud in vd.read_pcap(str(path)))


def ouster(path):
    import numpy as np
    from ouster.sdk import core, open_source

    source = open_source(str(path), meta=[str(path.with_suffix(".json"))], index=False)
    lut = core.XYZLut(source.sensor_info[0])
    points = 0
    for scans in source:
        for scan in scans:
            lut(scan.field(core.ChanField.RANGE))  # the points, as the comparison times them
            points += int(np.count_nonzero(scan.field(core.ChanField.RANGE)))
    return points


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("data", nargs="?", default="../shared/data/lidar_packets")
    parser.add_argument("--repeat", type=int, default=20)
    args = parser.parse_args()
    print("| capture | decoder | points | sent in | decoded in (median) | x real time |")
    print("|---|---|---|---|---|---|")
    for path in sorted(pathlib.Path(args.data).glob("*.pcap")):
        decode = ouster if path.with_suffix(".json").exists() else velodyne
        name = "ouster-sdk 1.0.1" if decode is ouster else "velodyne-decoder 3.0.0"
        times, points = [], 0
        for _ in range(args.repeat):
            start = time.perf_counter()
            points = decode(path)
            times.append(time.perf_counter() - start)
        sent = capture_span(path)
        took = statistics.median(times)
        print(f"| {path.name} | {name} | {points} | {sent * 1e3:.1f} ms | {took * 1e3:.2f} ms | {sent / took:.0f} |")


if __name__ == "__main__":
    main()
