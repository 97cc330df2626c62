#!/usr/bin/env bash
# Middlebury 2006 (third size) with more views of its line than the paper's three: view1 as the
# reference with view0 at -1, view2 at +1, then view3 at +2, view4 at +3 … up to all seven; and
# view5 as the reference (ground truth disp5) with view4/view6 at ∓1, then view3 at -2 … view0 at -5.
# Each set against its three-view subset, for the methods given (default bm-heuristic and
# sgm-heuristic); occlusion figures are over the pixels hidden in a direct neighbour, the same
# region for every row.
#
#   scripts/eval-line.sh [METHODS] [DATA_DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
methods="${1:-bm-heuristic,sgm-heuristic}"
data="${2:-../shared/data/middlebury2006-third-dev}"
if [ ! -d "$data" ]; then
    echo "evaluation data missing: $data (../shared/data must sit beside the checkout)" >&2
    exit 1
fi
cargo build --release -q -p replay
replay=target/release/replay
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT

run() { # NAME VIEWS GROUND_TRUTH
    "$replay" eval "$data" --methods "$methods" --views "$2" --ground-truth "$3" --ground-truth-scale 12 \
        --num-disparities 32 --format json 2>/dev/null >"$out/$1.json"
    echo "$1|$2" >>"$out/order"
}
run r1-3 view0@-1,view1@0,view2@1 disp1.png
run r1-4 view0@-1,view1@0,view2@1,view3@2 disp1.png
run r1-5 view0@-1,view1@0,view2@1,view3@2,view4@3 disp1.png
run r1-6 view0@-1,view1@0,view2@1,view3@2,view4@3,view5@4 disp1.png
run r1-7 view0@-1,view1@0,view2@1,view3@2,view4@3,view5@4,view6@5 disp1.png
run r5-3 view4@-1,view5@0,view6@1 disp5.png
run r5-4 view3@-2,view4@-1,view5@0,view6@1 disp5.png
run r5-5 view2@-3,view3@-2,view4@-1,view5@0,view6@1 disp5.png
run r5-7 view0@-5,view1@-4,view2@-3,view3@-2,view4@-1,view5@0,view6@1 disp5.png

python3 - "$out" <<'PY'
import json, sys, os
out = sys.argv[1]
rows = [line.strip().split("|") for line in open(os.path.join(out, "order"))]
base = {}
print("| reference | views (offsets) | method | RMS | AvgErr | Bad1 % | AvgErr vs 3 views | occl. AvgErr | occl. Bad1 % | occl. AvgErr vs 3 views |")
print("|---|---|---|---|---|---|---|---|---|---|")
for name, views in rows:
    ref = name.split("-")[0]
    for r in json.load(open(os.path.join(out, name + ".json"))):
        m, o = r["mean"], r["occluded"]
        key = (ref, r["method"])
        if name.endswith("-3"):
            base[key] = (m["avg_err_px"], o["avg_err_px"])
        b = base.get(key)
        change = lambda now, then: f"{100 * (now - then) / then:+.1f} %" if then else "–"
        print(f"| view{ref[1:]} | {views.replace('view', 'v')} | {r['method']} | {m['rms']:.3f} | {m['avg_err_px']:.3f} | "
              f"{m['bad_1']:.2f} | {change(m['avg_err_px'], b[0]) if b else '–'} | {o['avg_err_px']:.3f} | {o['bad_1']:.2f} | "
              f"{change(o['avg_err_px'], b[1]) if b else '–'} |")
PY
