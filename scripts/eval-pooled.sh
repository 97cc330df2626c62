#!/usr/bin/env bash
# The view-count-agnostic MFuseNet (a `replay train --views any` weights file) against the
# default `mfusenet` (the fixed networks, one per baseline), on sets with more views than the
# nearest cross: the `bin` family's 3 x 3 grid replayed with 2, 3, 5 and 9 views and its line of
# five with 3 and 5 (the captures of scripts/eval-views.sh, never used for training), and the toy
# and workpiece lines of five of scripts/eval-line5.sh. The pooled file runs twice: on the
# nearest baseline's neighbours on the axes only ({"every_view": false}) and on every view
# ({"every_view": true}; a file's default follows its training rig).
# Prints a markdown table of AvgErr (px) / Bad1 (%), two sets per capture, --rectify.
#
#   scripts/eval-pooled.sh WEIGHTS [OUT_DIR]     (default out/pooled; the captures are kept there)
set -euo pipefail
cd "$(dirname "$0")/.."
weights="${1:?usage: scripts/eval-pooled.sh WEIGHTS.safetensors [OUT_DIR]}"
out="${2:-out/pooled}"
[ -f "$weights" ] || { echo "no weights file: $weights" >&2; exit 1; }
mkdir -p "$out"
cargo build --release -q -p record -p replay
record=target/release/record
replay=target/release/replay
capture() { # NAME RIG SCENE SEED
    [ -f "$out/$1.mcap" ] || "$record" --rig "$2" --scene "$3" --resolution 640x360 --captures 2 --seed "$4" \
        -o "$out/$1.mcap" -q --no-blueprint
}
capture grid grid3x3 bin 11
capture line line5 bin 12
capture toy line5 toy 3
capture workpiece line5 workpiece 7
cell() { # LOG NEIGHBOURS(or all) CONFIG → "AvgErr / Bad1"
    local subset=()
    [ "$2" = all ] || subset=(--neighbours "$2")
    "$replay" eval "$out/$1.mcap" --rectify "${subset[@]}" --methods mfusenet --config "$3" --format json 2>/dev/null |
        python3 -c "import json,sys;m=json.load(sys.stdin)[0]['mean'];print(f\"{m['avg_err_px']:.4f} / {m['bad_1']:.2f}\")"
}
nearest="{\"weights\": \"$weights\", \"every_view\": false}"
every="{\"weights\": \"$weights\", \"every_view\": true}"
echo "| set | pooled, nearest group | pooled, every view | default (fixed networks) |"
echo "|---|---|---|---|"
while read -r name log subset; do
    echo "| ${name//_/ } | $(cell "$log" "$subset" "$nearest") | $(cell "$log" "$subset" "$every") | $(cell "$log" "$subset" '{}') |"
done <<'ROWS'
grid,_2_views_(right) grid right
grid,_3_(left,_right) grid left,right
grid,_5_(the_cross) grid left,right,top,bottom
grid,_9 grid all
bin_line,_3 line left,right
bin_line,_5 line all
toy_line,_5 toy all
workpiece_line,_5 workpiece all
ROWS
