#!/usr/bin/env bash
# MFuseNet on simulated five-view captures never used for training: the stereo,
# three-view and five-view networks on the same captures, with SGM peers, AvgErr and Bad1 overall
# and in the occluded and specular regions of the ground truth.
#
#   scripts/eval-simulated.sh [OUT_DIR] [SCENES]   # default train/eval-simulated (git-ignored), 8
#
# Captures: 448x336 (the training resolution), 15 mm baseline, 32 disparities; seeds from 900 up,
# which `replay train` never draws (training uses seeds 1..=train_sets, validation 1_000_001..).
# SCENES (a multiple of 4) = half random scenes (the seeds listed below: the first from 900 whose
# stations the arm reached before every family's camera was drawn within reach), a quarter toy scenes (seeds 904, 905, then 908 up) and a quarter workpieces of mirror-like metal
# (906, 907, then 908 up). The default 8 are the set docs/results.md's table was first measured on;
# every larger set contains them.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-train/eval-simulated}
SCENES=${2:-8}
[ $((SCENES % 4)) -eq 0 ] && [ "$SCENES" -ge 4 ] || { echo "SCENES must be a positive multiple of 4, got $SCENES" >&2; exit 2; }
mkdir -p "$OUT"
cargo build --release -q -p record -p replay
R=target/release/replay
# The captures of this set only (OUT may hold a larger set's too).
logs=()
capture() { # scene seed
    local log="$OUT/$1-$2.mcap"
    [ -f "$log" ] || target/release/record --rig five-view --scene "$1" --seed "$2" --resolution 448x336 \
        --baseline-mm 15 --samples-per-pixel 2 -o "$log" -q --no-blueprint 2>/dev/null || return 1
    logs+=("$log")
}
# The held-out random scenes, fixed: once the generator skipped seeds whose camera it drew out of
# the arm's reach (901, 903, 907, …); now every seed is reachable, and these keep their scenes.
random_seeds=(900 902 904 905 906 909 912 913 914 915 916 917 918 920 921 922)
[ $((SCENES / 2)) -le ${#random_seeds[@]} ] || { echo "at most $((2 * ${#random_seeds[@]})) scenes, got $SCENES" >&2; exit 2; }
for seed in "${random_seeds[@]:0:$((SCENES / 2))}"; do capture random "$seed"; done
extra=$((SCENES / 4 - 2))
for family in toy workpiece; do
    if [ "$family" = toy ]; then seeds=(904 905); else seeds=(906 907); fi
    [ "$extra" -gt 0 ] && seeds+=($(seq 908 $((907 + extra))))
    for seed in "${seeds[@]:0:$((SCENES / 4))}"; do capture "$family" "$seed"; done
done
common=(--num-disparities 32 --format json -q)
$R eval "${logs[@]}" --methods sgm-stereo,mfusenet-stereo "${common[@]}" > "$OUT/stereo.json"
$R eval "${logs[@]}" --methods sgm-heuristic,mfusenet --neighbours left,right "${common[@]}" > "$OUT/three.json"
$R eval "${logs[@]}" --methods sgm-heuristic,mfusenet "${common[@]}" > "$OUT/five.json"
python3 - "$OUT" <<'PY'
import json, sys
out = sys.argv[1]
print(f"| method | views | AvgErr | Bad1 (%) | AvgErr occluded | Bad1 occluded (%) | AvgErr specular | Bad1 specular (%) |")
print("|---|---|---|---|---|---|---|---|")
for file, views in (("stereo", 2), ("three", 3), ("five", 5)):
    for row in json.load(open(f"{out}/{file}.json")):
        m, o, s = row["mean"], row["occluded"], row["specular"]
        print(f"| {row['method']} | {views} | {m['avg_err_px']:.3f} | {m['bad_1']:.2f} | {o['avg_err_px']:.3f} | {o['bad_1']:.2f} | {s['avg_err_px']:.3f} | {s['bad_1']:.2f} |")
PY
