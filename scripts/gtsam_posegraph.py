# GTSAM's Levenberg-Marquardt on a g2o pose graph, exactly as data/posegraph/README.md measured it:
# `readG2o(path, True)`, a PriorFactorPose3 on the first pose at its initial value with variances
# (1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4) (GTSAM's tangent order is rotation first), default
# LevenbergMarquardtParams. Prints the initial and final error (0.5 * sum of squared Mahalanobis
# norms, the prior included), the iterations and the optimiser time: median of --runs runs of
# optimiser construction plus optimize(), file reading excluded.
#
# Run (from the repository root, release binary built):
#   pip install gtsam==4.3.0
#   python3 scripts/gtsam_posegraph.py ../shared/data/posegraph/parking-garage.g2o
# Ours on the same file:
#   ./target/release/emr-edge posegraph ../shared/data/posegraph/parking-garage.g2o --out /tmp/pg.g2o
#   ./target/release/emr-eval posegraph
import argparse
import statistics
import time

import gtsam

parser = argparse.ArgumentParser()
parser.add_argument("file", help="3-D pose graph in g2o format (VERTEX_SE3:QUAT, EDGE_SE3:QUAT)")
parser.add_argument("--runs", type=int, default=3, help="timed runs (the median is printed)")
parser.add_argument("--out", help="write the optimised poses here (g2o)")
args = parser.parse_args()

graph, initial = gtsam.readG2o(args.file, True)
first = initial.keys()[0]
prior = gtsam.noiseModel.Diagonal.Variances([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4])
graph.add(gtsam.PriorFactorPose3(first, initial.atPose3(first), prior))

times, result, iterations = [], None, 0
for _ in range(max(args.runs, 1)):
    start = time.perf_counter()
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams())
    result = optimizer.optimize()
    times.append(time.perf_counter() - start)
    iterations = optimizer.iterations()

print(f"poses {initial.size()} factors {graph.size()} (the prior included)")
print(f"initial error {graph.error(initial):.6f}")
print(f"final error {graph.error(result):.6f}")
print(f"iterations {iterations}")
print(f"optimiser {statistics.median(times) * 1e3:.1f} ms (median of {len(times)})")
if args.out:
    gtsam.writeG2o(graph, result, args.out)
