#!/usr/bin/env bash
# A simulated line of five (record --rig line5: views at -2 … 2 baselines along x) through every
# method, against its three-view subset (--neighbours left,right), on the toy scene and on the
# reflective workpiece. Graph cuts with their occlusions filled (fill_occlusions), as on Middlebury.
# Occlusion figures are over the pixels hidden in a direct neighbour: the same region for both.
#
#   scripts/eval-line5.sh [OUT_DIR]      (default out/line5; the captures are kept there)
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-out/line5}"
mkdir -p "$out"
cargo build --release -q -p record -p replay
record=target/release/record
replay=target/release/replay
[ -f "$out/toy.mcap" ] || "$record" --rig line5 --scene toy --resolution 640x360 --captures 2 --seed 3 -o "$out/toy.mcap" -q
[ -f "$out/workpiece.mcap" ] || "$record" --rig line5 --scene workpiece --resolution 640x360 --captures 2 --seed 7 -o "$out/workpiece.mcap" -q
classical=bm-stereo,bm-mean,bm-min,bm-heuristic,sgm-stereo,sgm-mean,sgm-min,sgm-heuristic,mfusenet-stereo,mfusenet
cuts=gc-stereo,gc-mean,gc-min,gc-heuristic
for log in toy workpiece; do
    for views in five three; do
        subset=()
        [ "$views" = three ] && subset=(--neighbours left,right)
        "$replay" eval "$out/$log.mcap" --rectify "${subset[@]}" --methods "$classical" --format json \
            2>/dev/null >"$out/$log-$views.json"
        "$replay" eval "$out/$log.mcap" --rectify "${subset[@]}" --methods "$cuts" --format json \
            --config '{"fill_occlusions": true}' 2>/dev/null >"$out/$log-$views-gcfill.json"
    done
done
python3 - "$out" <<'PY'
import json, os, sys
out = sys.argv[1]
def load(name):
    rows = {}
    for suffix in ("", "-gcfill"):
        for r in json.load(open(os.path.join(out, name + suffix + ".json"))):
            rows[r["method"]] = r
    return rows
order = ["bm-stereo", "bm-mean", "bm-min", "bm-heuristic", "sgm-stereo", "sgm-mean", "sgm-min", "sgm-heuristic",
         "gc-stereo", "gc-mean", "gc-min", "gc-heuristic", "mfusenet-stereo", "mfusenet"]
print("| scene | method | AvgErr 3 → 5 views | Bad1 % 3 → 5 | occluded AvgErr 3 → 5 | specular AvgErr 3 → 5 |")
print("|---|---|---|---|---|---|")
for log in ("toy", "workpiece"):
    three, five = load(log + "-three"), load(log + "-five")
    for m in order:
        t, f = three[m], five[m]
        def cell(region, field, fmt="{:.3f}"):
            a, b = t[region], f[region]
            if a is None or b is None:
                return "–"
            x, y = a[field], b[field]
            change = f" ({100 * (y - x) / x:+.0f} %)" if x else ""
            return f"{fmt.format(x)} → {fmt.format(y)}{change}"
        print(f"| {log} | {m} | {cell('mean', 'avg_err_px')} | {cell('mean', 'bad_1', '{:.2f}')} | "
              f"{cell('occluded', 'avg_err_px')} | {cell('specular', 'avg_err_px')} |")
PY
