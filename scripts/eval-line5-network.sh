#!/usr/bin/env bash
# Lines of five of seeds training never draws (`replay train` draws seeds 1-48, then 1,000,001+
# and 2,000,049+): MFuseNet's default (the three-view network on each pair) against configs
# given, e.g. the shipped five-view file on all four views and a file trained on lines:
#
#   scripts/eval-line5-network.sh OUT_DIR '{}' '{"line_cross": true}' '{"weights": "train/line5/mfusenet-5view-lite.safetensors"}'
#
# AvgErr px / Bad1 % per line (two sets each, 640x360, --rectify), then the `thin` family's rows
# of five (384x288, seeds 1-3; a family training never draws); the first column is the inner
# pair alone (`--neighbours left,right`), against which a view added may cost at most 2 %.
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-out/line5h}"
shift || true
configs=("$@")
[ ${#configs[@]} -eq 0 ] && configs=('{}' '{"line_cross": true}')
cargo build --release -q -p record -p replay
mkdir -p "$out"
lines=(toy:311 workpiece:3011 workpiece:71 random:8 random:91 random:101 clutter:501 bin:12 fence:601)
for sp in "${lines[@]}"; do
    s=${sp%%:*} n=${sp##*:}
    [ -f "$out/$s$n.mcap" ] || target/release/record --rig line5 --scene "$s" --resolution 640x360 \
        --captures 2 --seed "$n" -o "$out/$s$n.mcap" -q
done
source scripts/family-logs.sh
family_logs thin "$out/thin" 3 384x288 line5
row() {
    target/release/replay eval "$@" --format json 2>/dev/null |
        python3 -c 'import json,sys; r=json.load(sys.stdin)[0]["mean"]; print("%.3f / %.2f" % (r["avg_err_px"], r["bad_1"]), end="")'
}
header="| line | three views (±1 only, default) |"; rule="|---|---|"
for c in "${configs[@]}"; do header+=" \`$c\` |"; rule+="---|"; done
echo "$header"; echo "$rule"
for sp in "${lines[@]}"; do
    s=${sp%%:*} n=${sp##*:}
    line="| $s $n | $(row "$out/$s$n.mcap" --rectify --neighbours left,right --methods mfusenet) |"
    for c in "${configs[@]}"; do line+=" $(row "$out/$s$n.mcap" --rectify --methods mfusenet --config "$c") |"; done
    echo "$line"
done
line="| thin rows 1-3 | $(row "${logs[@]}" --neighbours left,right --methods mfusenet) |"
for c in "${configs[@]}"; do line+=" $(row "${logs[@]}" --methods mfusenet --config "$c") |"; done
echo "$line"
