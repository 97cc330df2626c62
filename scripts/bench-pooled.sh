#!/usr/bin/env bash
# The view-count-agnostic MFuseNet's time per view against the fixed five-view networks': the
# method's seconds (`replay`'s summary, `--outputs none`) divided by the neighbours the network
# took, on two 640x360 captures: the held-out `bin` family's 3 x 3 grid (seed 11, as
# scripts/eval-pooled.sh) and the toy five-view cross. Rows, interleaved ROUNDS times (default 3):
#   lite five-view  the default five-view file (lite, sharp volumes), the cross's 4 neighbours
#   paper five-view {"architecture": "paper"}, the same 4
#   pooled, 4       a view-count-agnostic file on the same 4 ({"every_view": false})
#   pooled, 8       the same file on all 8 of the grid's neighbours ({"every_view": true})
# The pooled file is WEIGHTS (default the grid-cross run's starting file, committed in
# fuse/weights/runs/mfusenet-any-gridcross: the time does not depend on the weights' values).
#
#   scripts/bench-pooled.sh [WEIGHTS]        (ROUNDS=5 scripts/bench-pooled.sh for more rounds)
source "$(dirname "$0")/bench-common.sh"
weights="${1:-fuse/weights/runs/mfusenet-any-gridcross/init.safetensors}"
[ -f "$weights" ] || { echo "no weights file: $weights" >&2; exit 1; }
rounds="${ROUNDS:-3}"
target/release/record --rig grid3x3 --scene bin --resolution 640x360 --seed 11 -o "$T/grid.mcap" -q --no-blueprint
target/release/record --rig five-view --resolution 640x360 -o "$T/toy.mcap" -q --no-blueprint
run() { # LOG CONFIG → "seconds views AvgErr"
    $R "$T/$1.mcap" --method mfusenet --outputs none --out "$T/out" -q --config "$2"
    python3 -c "import json;s=json.load(open('$T/out/summary.json'))['sets'][0];print(s['seconds'], len(s['details']['views']), s['outputs']['metrics']['all']['avg_err_px'])"
}
declare -A total
rows=("grid|lite five-view|{}" "grid|paper five-view|{\"architecture\": \"paper\"}"
    "grid|pooled, 4|{\"weights\": \"$weights\", \"every_view\": false}"
    "grid|pooled, 8|{\"weights\": \"$weights\", \"every_view\": true}"
    "toy|lite five-view|{}" "toy|paper five-view|{\"architecture\": \"paper\"}"
    "toy|pooled, 4|{\"weights\": \"$weights\", \"every_view\": false}")
for round in $(seq "$rounds"); do
    for row in "${rows[@]}"; do
        IFS='|' read -r log name config <<<"$row"
        read -r seconds views err < <(run "$log" "$config")
        echo "round $round, $log, $name: ${seconds} s, $views views, AvgErr $err"
        total["$log|$name"]="${total["$log|$name"]:-} $seconds:$views"
    done
done
echo
echo "| capture | network | views | method s (median of $rounds) | s per view |"
echo "|---|---|---|---|---|"
for row in "${rows[@]}"; do
    IFS='|' read -r log name _ <<<"$row"
    python3 - "$log" "$name" ${total["$log|$name"]} <<'PY'
import statistics, sys
log, name, *cells = sys.argv[1:]
seconds = [float(c.split(":")[0]) for c in cells]
views = int(cells[0].split(":")[1])
m = statistics.median(seconds)
print(f"| {log} | {name} | {views} | {m:.2f} | {m / views:.2f} |")
PY
done
