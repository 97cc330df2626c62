#!/usr/bin/env bash
# Does adding a view help? Simulated captures of the `bin` family (never used for training:
# `replay train --scenes` refuses it), 640x360, two sets each: a 3 x 3 grid replayed with 2, 3,
# 5 and 9 views (right; left, right; the cross; all), and a line of five with 3 and 5 views.
# Every method given (default mfusenet, sgm-heuristic, bm-heuristic and gc-heuristic, graph cuts
# with their occlusions filled as on Middlebury); AvgErr / Bad1 and the change against the row
# before.
#
#   scripts/eval-views.sh [OUT_DIR] [METHODS]     (default out/views; the captures are kept there)
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-out/views}"
methods="${2:-mfusenet,sgm-heuristic,bm-heuristic,gc-heuristic}"
mkdir -p "$out"
cargo build --release -q -p record -p replay
record=target/release/record
replay=target/release/replay
[ -f "$out/grid.mcap" ] || "$record" --rig grid3x3 --scene bin --resolution 640x360 --captures 2 --seed 11 \
    -o "$out/grid.mcap" -q --no-blueprint
[ -f "$out/line.mcap" ] || "$record" --rig line5 --scene bin --resolution 640x360 --captures 2 --seed 12 \
    -o "$out/line.mcap" -q --no-blueprint
run() { # LOG VIEWS NEIGHBOURS(or "all")
    local subset=()
    [ "$3" = all ] || subset=(--neighbours "$3")
    local config=()
    IFS=, read -ra list <<<"$methods"
    for m in "${list[@]}"; do
        config=()
        case "$m" in gc-*) config=(--config '{"fill_occlusions": true}') ;; esac
        "$replay" eval "$out/$1.mcap" --rectify "${subset[@]}" --methods "$m" "${config[@]}" --format json \
            2>/dev/null >"$out/$1-$2-$m.json"
        echo "$1|$2|$m" >>"$out/order"
    done
}
rm -f "$out/order"
run grid 2 right
run grid 3 left,right
run grid 5 left,right,top,bottom
run grid 9 all
run line 3 left,right
run line 5 all
python3 - "$out" <<'PY'
import json, os, sys
out = sys.argv[1]
rows = [l.strip().split("|") for l in open(os.path.join(out, "order"))]
last = {}
print("| capture | views | method | AvgErr | Bad1 % | AvgErr vs fewer views | occluded AvgErr | seconds |")
print("|---|---|---|---|---|---|---|---|")
for log, views, method in rows:
    r = json.load(open(os.path.join(out, f"{log}-{views}-{method}.json")))[0]
    m, o = r["mean"], r["occluded"] or {}
    key = (log, method)
    change = f"{100 * (m['avg_err_px'] / last[key] - 1):+.1f} %" if key in last else "–"
    last[key] = m["avg_err_px"]
    print(f"| bin {log} | {views} | {method} | {m['avg_err_px']:.3f} | {m['bad_1']:.2f} | {change} | "
          f"{o.get('avg_err_px', float('nan')):.3f} | {r['seconds']:.1f} |")
PY
