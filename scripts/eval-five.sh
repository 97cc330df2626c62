#!/usr/bin/env bash
# A five-view network file against the shipped one, on the five-view sets a file is chosen on:
# the held-out `thin` family (seeds 1-4, the choice, and 5-8, a check), the 32 held-out
# simulated captures (`scripts/eval-simulated.sh`'s, 448x336), the 640x360 toy capture, the
# demo's 960x540 capture, the held-out `bin` grid's cross, and two `fence` captures (a training
# family: a sanity check, not a held-out one). AvgErr px / Bad1 % per set, one column per
# configuration.
#
#   scripts/eval-five.sh [CONFIG_JSON ...]    (default: '{}' only, the shipped file)
#   scripts/eval-five.sh '{}' '{"weights": "train/lite5-fence/mfusenet-5view-lite.safetensors"}'
#
# Captures are made when missing, in out/ (git-ignored): about 4 minutes the first time; each
# column then takes about 2.5 minutes on 2 vCPUs.
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -gt 0 ] || set -- '{}'
cargo build --release -q -p record -p replay
record=target/release/record
replay=target/release/replay
source scripts/family-logs.sh
family_logs thin out/thin/thin 8 640x360
thin=("${logs[@]}")
family_logs fence out/fence/fence 2 640x360
fence=("${logs[@]}")
[ "$(ls out/sim/*.mcap 2>/dev/null | wc -l)" -ge 32 ] || scripts/eval-simulated.sh out/sim 32 >/dev/null
[ -f out/toy640.mcap ] || "$record" --rig five-view --resolution 640x360 --log-working-range \
    -o out/toy640.mcap -q --no-blueprint
[ -f out/d/capture.mcap ] || "$replay" demo --out out/d -q
[ -f out/views/grid.mcap ] || scripts/eval-views.sh out/views mfusenet >/dev/null
row() { # CONFIG LOG... [OPTIONS...]
    local config=$1
    shift
    "$replay" eval "$@" --methods mfusenet --config "$config" --format json -q 2>/dev/null |
        python3 -c "import json,sys; m=json.load(sys.stdin)[0]['mean']; print(f\"{m['avg_err_px']:.3f} / {m['bad_1']:.2f}\")"
}
sets=(thin1-4 thin5-8 sim32 toy640 demo bin-cross fence1-2)
declare -A cells
for c in "$@"; do
    cells[$c,thin1-4]=$(row "$c" "${thin[@]:0:4}")
    cells[$c,thin5-8]=$(row "$c" "${thin[@]:4:4}")
    cells[$c,sim32]=$(row "$c" out/sim/*.mcap)
    cells[$c,toy640]=$(row "$c" out/toy640.mcap)
    cells[$c,demo]=$(row "$c" out/d/capture.mcap)
    cells[$c,bin-cross]=$(row "$c" out/views/grid.mcap --rectify --neighbours left,right,top,bottom)
    cells[$c,fence1-2]=$(row "$c" "${fence[@]}")
done
header="| set |"
rule="|---|"
for c in "$@"; do
    header+=" \`$c\` |"
    rule+="---|"
done
echo "$header"
echo "$rule"
for s in "${sets[@]}"; do
    line="| $s |"
    for c in "$@"; do line+=" ${cells[$c,$s]} |"; done
    echo "$line"
done
