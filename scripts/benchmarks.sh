#!/usr/bin/env bash
# Regenerates every figure of docs/benchmarks.md: one command per table, as the page gives it, each
# writing what it prints to out/benchmarks/SECTION.txt. The page's tables are transcribed from those
# files. Hours on 2 cores in all; run one section with `--only SECTION`, list them with `--list`.
# The peer comparisons need the Python peers (docs/benchmarks.md names them); a section whose peer
# is missing fails on its own and the others go on.
set -uo pipefail
cd "$(dirname "$0")/.."

out=out/benchmarks
data=../shared/data
eval=./target/release/emr-eval
edge=./target/release/emr-edge
demo=./target/release/emr-demo

codec() { "$eval" codec "$data/kitti00"; }
odometry() {
    "$eval" odometry sim:warehouse-small:1 --frames 1800 --runs 3
    "$eval" odometry sim:campus:1 --preset outdoor --frames 600
    "$eval" odometry "$data/kitti00" --preset outdoor --no-deskew --frames 16 --runs 5
    for seed in 0 1 2 3; do
        for robot in warehouse-small:1 warehouse-small:2 warehouse-large:1 warehouse-large:2 campus:1; do
            preset=indoor
            [ "${robot%%:*}" = campus ] && preset=outdoor
            "$edge" odometry "sim:$robot" --preset "$preset" --no-loops --seed "$seed" \
                --out "$out/odometry/$robot-$seed" >/dev/null
            echo "$robot seed $seed: $(python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))["ate_rmse_m"])' \
                "$out/odometry/$robot-$seed/stats.json")"
        done
    done
}
kiss() {
    python3 scripts/compare_kiss_icp.py "$data/kitti00" "$out/kiss-kitti00"
    "$edge" odometry "$data/livox_hku2/scans" --out "$out/livox" --no-loops >/dev/null
    "$edge" eval --gt "$data/livox_hku2/odom_poses.txt" --est "$out/livox/poses_kitti.txt"
    python3 scripts/compare_kiss_icp.py "$data/livox_hku2/scans" "$out/kiss-livox"
}
packets() {
    "$edge" convert "$data/lidar_packets/vlp16.pcap" --out "$out/vlp16"
    "$eval" packets --repeat 400
    python3 scripts/compare_packet_decoders.py
}
live() {
    local d="$out/live" port=47123 router=tcp/127.0.0.1:47447
    rm -rf "$d" && mkdir -p "$d"
    ./target/release/emr-station run --fleet live --data-dir "$d/station" --listen "$router" &
    local station=$!
    sleep 3
    "$edge" run --fleet live --robot 1 --source "udp:127.0.0.1:$port" --max-frames 599 --exit-when-done \
        --summary "$d/live.json" --poses "$d/live.txt" --connect "$router" &
    local receiver=$!
    sleep 3
    "$edge" sim --scenario warehouse-small --frames 600 --send "127.0.0.1:$port" --rate realtime --pcap "$d/vlp16.pcap"
    wait "$receiver"
    "$edge" run --fleet live --robot 1 --source "pcap:$d/vlp16.pcap" --rate max --max-frames 599 --exit-when-done \
        --summary "$d/files.json" --poses "$d/files.txt" --connect "$router"
    kill "$station"
    "$edge" odometry sim:warehouse-small:1 --max-frames 599 --out "$d/truth" >/dev/null
    cat "$d/live.json" "$d/files.json"
    "$edge" eval --gt "$d/truth/poses_gt_kitti.txt" --est "$d/live.txt"
    "$edge" eval --gt "$d/truth/poses_gt_kitti.txt" --est "$d/files.txt"
}
robustness() {
    "$eval" robustness --kiss
    "$eval" robustness --part held-back --seeds 3 --kiss
}
loops() { "$eval" loops; }
posegraph() {
    "$eval" posegraph --write-synthetic "$out/synthetic5000.g2o"
    "$edge" posegraph "$data/posegraph/parking-garage.g2o" --out "$out/parking-garage.g2o"
    python3 scripts/gtsam_posegraph.py "$data/posegraph/parking-garage.g2o"
}
gicp() {
    "$eval" gicp --runs 100
    python3 scripts/compare_small_gicp.py 30
}
merge() {
    "$eval" merge --runs 5
    "$eval" global --runs 20
}
demo() {
    for scenario in warehouse-small warehouse-large campus aisles; do
        RUST_LOG=station=warn "$demo" run --scenario "$scenario" --out "$out/demo-$scenario" \
            --no-foxglove --no-record
    done
    for seed in 0 1 2; do
        RUST_LOG=station=warn "$demo" run --scenario warehouse-large --restart 1@600 \
            --out "$out/restart-$seed" --no-foxglove --no-record --seed "$seed"
    done
}
joint() {
    cargo nextest run --release -p station --test joint --no-capture
    "$eval" load --robots 16 --seconds 40 --joint --json
}
load() {
    "$eval" load --robots 16 --seconds 40 --json
    "$eval" load --robots 32 --seconds 40 --json
}
report() {
    "$eval" report --out "$out/report-ws" --scenario warehouse-small
    "$eval" report --out "$out/report-200" --frames 200
}
sim() { "$eval" sim --frames 30; }
hosts() {
    EMR_ZENOHD=$(bash deploy/zenohd.sh) cargo nextest run -p tests --test hosts --no-capture
}

sections=(codec odometry kiss packets live robustness loops posegraph gicp merge demo joint load report sim hosts)
case "${1:-}" in
--list) printf '%s\n' "${sections[@]}"; exit 0 ;;
--only) sections=("$2") ;;
"") ;;
*) echo "usage: $0 [--list | --only SECTION]" >&2; exit 2 ;;
esac

cargo build --release --locked -p eval -p edge -p station -p demo --bins || exit 1
mkdir -p "$out"
failed=()
for i in "${!sections[@]}"; do
    s=${sections[$i]}
    if ! declare -F "$s" >/dev/null; then
        echo "no section $s (--list names them)" >&2
        exit 2
    fi
    echo "[$((i + 1))/${#sections[@]}] $s -> $out/$s.txt" >&2
    start=$SECONDS
    if ! "$s" >"$out/$s.txt" 2>&1; then
        failed+=("$s")
    fi
    echo "    $((SECONDS - start)) s" >&2
done
if [ ${#failed[@]} -gt 0 ]; then
    echo "failed: ${failed[*]} (their files say why)" >&2
    exit 1
fi
