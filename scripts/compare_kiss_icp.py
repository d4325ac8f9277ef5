# KISS-ICP (PyPI kiss-icp 1.3.0, default configuration, one thread) on a directory of KITTI .bin
# scans: median milliseconds of register_frame per scan, and its poses as a KITTI file for
# `emr-edge eval` (KITTI .bin scans, or binary PCD as in livox_hku2). With --deskew, per-point times come from the azimuth (a spinning head turning
# clockwise from the back, as Velodynes and our simulator do), which is what KISS-ICP's own
# deskewing needs; without it, KISS-ICP registers the scans as they are.
#
# Run (from the repository root, release binaries built):
#   pip install kiss-icp==1.3.0
#   ./target/release/emr-edge sim --scenario warehouse-small --robot 1 --out /tmp/ws1 --frames 600
#   python3 scripts/compare_kiss_icp.py /tmp/ws1 /tmp/kiss-ws1 --deskew
#   ./target/release/emr-edge eval --gt /tmp/ws1/poses.txt --est /tmp/kiss-ws1/poses_kitti.txt
# Ours on the same scans (read into memory first, registration timed on one thread):
#   ./target/release/emr-eval odometry /tmp/ws1 --runs 3
import argparse, glob, os, time

import numpy as np
from kiss_icp.config import load_config
from kiss_icp.kiss_icp import KissICP

parser = argparse.ArgumentParser()
parser.add_argument("scans", help="directory of .bin scans (or with a velodyne/ subdirectory)")
parser.add_argument("out", help="output directory: poses_kitti.txt, timing.txt")
parser.add_argument("--deskew", action="store_true", help="per-point times from the azimuth")
parser.add_argument("--max-range", type=float, default=100.0)
args = parser.parse_args()

files = sorted(glob.glob(os.path.join(args.scans, "*.bin"))) or sorted(
    glob.glob(os.path.join(args.scans, "velodyne", "*.bin"))) or sorted(glob.glob(os.path.join(args.scans, "*.pcd")))
if not files:
    raise SystemExit(f"no .bin or .pcd scans in {args.scans}")


def read_scan(path):
    """x y z of a KITTI .bin (float32 x y z intensity) or a binary PCD whose fields are all float32."""
    if not path.endswith(".pcd"):
        return np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
    with open(path, "rb") as f:
        header = {}
        while True:
            line = f.readline().decode("ascii").strip()
            if line and not line.startswith("#"):
                key, *values = line.split()
                header[key] = values
                if key == "DATA":
                    break
        if header["DATA"] != ["binary"] or set(header["TYPE"]) != {"F"} or set(header["SIZE"]) != {"4"}:
            raise SystemExit(f"{path}: only binary PCD of float32 fields is read here")
        fields = header["FIELDS"]
        data = np.frombuffer(f.read(), dtype=np.float32).reshape(-1, len(fields))
    return data[:, [fields.index(c) for c in "xyz"]].astype(np.float64)
os.environ.setdefault("OMP_NUM_THREADS", "1")
config = load_config(None)
config.data.deskew = args.deskew
config.data.max_range = args.max_range
config.registration.max_num_threads = 1
odometry = KissICP(config=config)

scans = [read_scan(f) for f in files]
poses, ms, cpu = [], [], []
for points in scans:
    azimuth = np.arctan2(points[:, 1], points[:, 0])
    stamps = (np.pi - azimuth) / (2 * np.pi) if args.deskew else np.zeros(len(points))
    start, start_cpu = time.perf_counter(), time.thread_time()
    odometry.register_frame(points, stamps)
    ms.append((time.perf_counter() - start) * 1e3)
    cpu.append((time.thread_time() - start_cpu) * 1e3)
    poses.append(odometry.last_pose.copy())

os.makedirs(args.out, exist_ok=True)
np.savetxt(os.path.join(args.out, "poses_kitti.txt"), np.array([p[:3, :4].reshape(-1) for p in poses]))
with open(os.path.join(args.out, "timing.txt"), "w") as f:
    f.write(f"scans {len(ms)} median_ms {np.median(ms):.3f} mean_ms {np.mean(ms):.3f} "
            f"median_cpu_ms {np.median(cpu):.3f}\n")
print(f"KISS-ICP on {len(ms)} scans (deskew {args.deskew}): median {np.median(ms):.2f} ms per scan "
      f"(thread CPU {np.median(cpu):.2f} ms), mean {np.mean(ms):.2f} ms")
