#!/usr/bin/env bash
# MFuseNet on irregular view sets (what a planner or a partial capture leaves: an L of two views,
# a cross missing one arm, a diagonal beside an axis view): simulated 3 x 3 grids of families no
# network was trained on (`bin`, `thin`) and of mirror-like workpieces at seeds training never
# draws, 640x360, two sets each, replayed with subsets of their neighbours. `mfusenet` (default:
# the odd views at the nearest baseline each run the stereo network in the vote) against
# `{"every_view": false}` (one network: the stereo one on one view of an L, the three-view one
# on the pair of a T), sgm-heuristic and gc-heuristic (occlusions filled). AvgErr / Bad1 %, and
# the networks the default ran.
#
#   scripts/eval-irregular.sh [OUT_DIR] [METHODS]   (default out/irregular; captures kept there)
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-out/irregular}"
methods="${2:-mfusenet,mfusenet-fixed,sgm-heuristic,gc-heuristic}"
mkdir -p "$out"
cargo build --release -q -p record -p replay
record=target/release/record
replay=target/release/replay
grid() { # NAME SCENE SEED
    [ -f "$out/$1.mcap" ] || "$record" --rig grid3x3 --scene "$2" --resolution 640x360 --captures 2 \
        --seed "$3" --log-working-range -o "$out/$1.mcap" -q --no-blueprint
}
grid bin bin 11
grid thin thin 21
grid workpiece workpiece 3011
subsets=(left,top right,bottom top,left,top-right top-left,right left,right,top left,top,bottom left,right left,right,top,bottom)
rm -f "$out/order"
for log in bin thin workpiece; do
    for s in "${subsets[@]}"; do
        IFS=, read -ra list <<<"$methods"
        for m in "${list[@]}"; do
            config='{}'
            method=$m
            case "$m" in
                gc-*) config='{"fill_occlusions": true}' ;;
                mfusenet-fixed) method=mfusenet config='{"every_view": false}' ;;
            esac
            "$replay" eval "$out/$log.mcap" --rectify --neighbours "$s" --methods "$method" --config "$config" \
                --format json 2>/dev/null >"$out/$log-$s-$m.json"
            echo "$log|$s|$m" >>"$out/order"
        done
        "$replay" "$out/$log.mcap" --rectify --neighbours "$s" --method mfusenet --outputs none --sets 0 \
            --out "$out/run" -q
        python3 -c "import json,sys; d=json.load(open('$out/run/summary.json')); print(json.dumps(d['sets'][0]['details']))" \
            >"$out/$log-$s-network.json" 2>/dev/null || true
    done
done
python3 - "$out" <<'PY'
import json, os, sys
out = sys.argv[1]
rows = [l.strip().split("|") for l in open(os.path.join(out, "order"))]
table = {}
for log, s, m in rows:
    r = json.load(open(os.path.join(out, f"{log}-{s}-{m}.json")))[0]["mean"]
    table.setdefault((log, s), {})[m] = r
methods = list(dict.fromkeys(m for _, _, m in rows))
print("| capture | views | " + " | ".join(methods) + " | the default's network |")
print("|---|---|" + "---|" * (len(methods) + 1))
for (log, s), row in table.items():
    try:
        d = json.load(open(os.path.join(out, f"{log}-{s}-network.json")))
        net = "; ".join(d["networks"]) if "networks" in d else f"{d.get('network')} [{', '.join(d.get('views') or [])}]"
    except Exception:
        net = "?"
    cells = [f"{row[m]['avg_err_px']:.3f} / {row[m]['bad_1']:.2f}" if m in row else "–" for m in methods]
    print(f"| {log} | {s} | " + " | ".join(cells) + f" | {net} |")
PY
