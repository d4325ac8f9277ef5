# Open3D 0.20 global registration (the tutorial pipeline) on one pair of clouds, timed and checked
# against a reference transform; optionally also the error of our transform against the same
# reference. SOURCE is moved onto TARGET; TRUTH (4x4 row-major, or a KITTI 3x4 line) maps SOURCE
# points into the TARGET frame. Clouds: .ply (x y z ...) or KITTI .bin.
#
# Pipeline, per the Open3D "Global registration" tutorial, voxel v:
#   voxel_down_sample(v); estimate_normals(KDTreeSearchParamHybrid(2v, 30));
#   compute_fpfh_feature(KDTreeSearchParamHybrid(5v, 100));
#   registration_ransac_based_on_feature_matching(mutual_filter=True, 1.5v, PointToPoint, 3-point
#   samples, [EdgeLength(0.9), Distance(1.5v)], RANSACConvergenceCriteria(100000, 0.999))
#   = "global" (both clouds' preprocessing + RANSAC); then the tutorial's refinement, point-to-plane
#   ICP on the full clouds at 0.4v from the RANSAC result, normals of the full clouds (2v, 30)
#   computed inside the timed "ICP" step. Every run is seeded (o3d.utility.random.seed(seed + run)).
#
# Threads: Open3D is limited to --threads (default 2, what `emr-station` uses on this 2-core
# machine): OMP_NUM_THREADS is set before Open3D is imported and the process is pinned to that many
# CPUs (sched_setaffinity), so neither OpenMP nor TBB can use more.
#
# Commands (from the repository root, release binaries built):
#   cargo build --release -p station --bin emr-station && cargo build --release -p sim --example sim_maps
#   ./target/release/examples/sim_maps warehouse-large /tmp/simcmp/wl       # map0.ply map1.ply truth_0_1.txt
#   ./target/release/examples/sim_maps campus /tmp/simcmp/campus
#   # ours: timing + error (truth_0_1 maps map1 into map0's frame)
#   ./target/release/emr-eval merge /tmp/simcmp/wl/map1.ply /tmp/simcmp/wl/map0.ply \
#       --reference /tmp/simcmp/wl/truth_0_1.txt --preset indoor --runs 3
#   ./target/release/emr-station align /tmp/simcmp/wl/map1.ply /tmp/simcmp/wl/map0.ply \
#       --method global --preset indoor > /tmp/simcmp/wl/ours.txt
#   # Open3D, plus the error of our printed transform
#   python3 scripts/compare_open3d.py /tmp/simcmp/wl/map1.ply /tmp/simcmp/wl/map0.ply \
#       /tmp/simcmp/wl/truth_0_1.txt --voxel 0.1 --runs 3 --ours-transform /tmp/simcmp/wl/ours.txt
#   python3 scripts/compare_open3d.py /tmp/simcmp/wl/map1.ply /tmp/simcmp/wl/map0.ply \
#       /tmp/simcmp/wl/truth_0_1.txt --voxel 0.4 --runs 3
#   # (campus: the same with /tmp/simcmp/campus, --preset outdoor, --voxel 0.4 / 0.5)
#   # KITTI 08 reverse revisit (reference good to ~0.1 m only):
#   D=../shared/data/kitti08_revisit
#   ./target/release/emr-eval merge $D/001500.bin $D/000720.bin \
#       --reference $D/T_000720_001500.txt --runs 3
#   python3 scripts/compare_open3d.py $D/001500.bin $D/000720.bin $D/T_000720_001500.txt --voxel 0.5 --runs 3
# --runs 0 runs no Open3D at all (only --ours-transform is checked).
import argparse
import os
import sys
import time

parser = argparse.ArgumentParser(description=__doc__)
parser.add_argument("source", help="cloud to move (.ply or KITTI .bin)")
parser.add_argument("target", help="cloud to align to")
parser.add_argument("truth", help="4x4 (or 3x4) text: SOURCE points into the TARGET frame")
parser.add_argument("--voxel", type=float, default=0.5, help="Open3D voxel v (m)")
parser.add_argument("--runs", type=int, default=3, help="timed runs (median reported); 0: no Open3D")
parser.add_argument("--threads", type=int, default=2, help="CPU threads Open3D may use")
parser.add_argument("--seed", type=int, default=0, help="RANSAC seed of the first run")
parser.add_argument("--ours-transform", help="file with our 4x4 (`emr-station align` output: the first "
                    "four lines of four numbers are read)")
args = parser.parse_args()

# Before importing Open3D, so its OpenMP pool is sized accordingly.
os.environ["OMP_NUM_THREADS"] = str(args.threads)
os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[: args.threads])

import numpy as np  # noqa: E402
import open3d as o3d  # noqa: E402

reg = o3d.pipelines.registration


def read_matrix(path):
    """A 4x4 row-major matrix (one line of 16, or lines of 4) or a KITTI 3x4 line of 12; lines
    with anything else (such as `emr-station align`'s confidence line) are skipped."""
    values = []
    for line in open(path):
        try:
            row = [float(x) for x in line.split()]
        except ValueError:
            continue
        if len(row) in (12, 16) and not values:
            values = row
            break
        if len(row) == 4:
            values += row
            if len(values) == 16:
                break
    if len(values) not in (12, 16):
        sys.exit(f"{path}: no 4x4 or 3x4 matrix found")
    m = np.eye(4)
    m[:3, :] = np.array(values[:12]).reshape(3, 4)
    return m


def load(path):
    if path.lower().endswith(".bin"):
        pts = np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3].astype(np.float64)
        pc = o3d.geometry.PointCloud()
        pc.points = o3d.utility.Vector3dVector(pts)
        return pc
    pc = o3d.io.read_point_cloud(path)
    if pc.is_empty():
        sys.exit(f"{path}: no points read")
    return pc


def error(T, truth):
    """Translation (m) and rotation angle (deg) of truth^-1 T, as cloud::se3::pose_error."""
    D = np.linalg.inv(truth) @ T
    angle = np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))
    return np.linalg.norm(D[:3, 3]), angle


def fmt(e):
    return f"{e[0]:.4f} m {e[1]:.3f} deg"


def run_once(source, target, v, seed):
    o3d.utility.random.seed(seed)
    t0 = time.perf_counter()
    feats = []
    for pc in (source, target):
        down = pc.voxel_down_sample(v)
        down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
        fpfh = reg.compute_fpfh_feature(down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * v, max_nn=100))
        feats.append((down, fpfh))
    (sd, sf), (td, tf) = feats
    dist = 1.5 * v
    ransac = reg.registration_ransac_based_on_feature_matching(
        sd, td, sf, tf, True, dist, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(100000, 0.999))
    t1 = time.perf_counter()
    # The tutorial's refinement on the full clouds; their normals are part of its cost.
    src, tgt = o3d.geometry.PointCloud(source.points), o3d.geometry.PointCloud(target.points)
    for pc in (src, tgt):
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
    icp = reg.registration_icp(src, tgt, 0.4 * v, ransac.transformation,
                               reg.TransformationEstimationPointToPlane())
    t2 = time.perf_counter()
    return ransac, icp, t1 - t0, t2 - t1, (len(sd.points), len(td.points))


truth = read_matrix(args.truth)
if args.ours_transform:
    print(f"ours ({args.ours_transform}): error {fmt(error(read_matrix(args.ours_transform), truth))}")
if args.runs <= 0:
    sys.exit(0)

source, target = load(args.source), load(args.target)
print(f"Open3D {o3d.__version__}, {args.threads} thread(s), voxel {args.voxel} m: source "
      f"{len(source.points)} points, target {len(target.points)} points")
globals_s, icps_s = [], []
for run in range(args.runs):
    ransac, icp, tg, ti, (ns, nt) = run_once(source, target, args.voxel, args.seed + run)
    globals_s.append(tg)
    icps_s.append(ti)
    print(f"run {run} (seed {args.seed + run}, downsampled {ns}/{nt}): global {tg * 1e3:.0f} ms, "
          f"ICP {ti * 1e3:.0f} ms | RANSAC {fmt(error(ransac.transformation, truth))} "
          f"(fitness {ransac.fitness:.3f}, {len(ransac.correspondence_set)} inliers) | "
          f"ICP {fmt(error(icp.transformation, truth))} (fitness {icp.fitness:.3f})")
print(f"median: global {np.median(globals_s) * 1e3:.0f} ms, ICP {np.median(icps_s) * 1e3:.0f} ms, "
      f"total {np.median(np.add(globals_s, icps_s)) * 1e3:.0f} ms")
