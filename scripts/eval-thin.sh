#!/usr/bin/env bash
# Thin structures and wide occlusions: simulated five-view captures of the `thin` family (rods,
# wires, lamp arms, slats and leaves 1-6 px wide before a far floor, a near board; never used for
# training: `replay train --scenes` refuses it), 640x360, over the working range the log carries
# (64 disparities: MFuseNet goes coarse to fine). Every method given (default mfusenet,
# sgm-heuristic, bm-heuristic and gc-heuristic, graph cuts with their occlusions filled as on
# Middlebury): AvgErr / Bad1 overall and in the occluded pixels, and the first set's error maps
# (OUT/maps/<method>_error_0.0-4.0px.png, 0 … 4 px).
#
#   scripts/eval-thin.sh [OUT_DIR] [SCENES] [METHODS]    (default out/thin, 4 scenes)
#   RIG=line5 RESOLUTION=384x288 scripts/eval-thin.sh out/thin-line5 3
#       the same family as a row of five views at 384x288 (disparities of about 6-16 px): the
#       shape of the classic five-view benchmark row whose lamp arm and tripod MFuseNet loses
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-out/thin}"
scenes="${2:-4}"
methods="${3:-mfusenet,sgm-heuristic,bm-heuristic,gc-heuristic}"
mkdir -p "$out/maps"
cargo build --release -q -p record -p replay
source scripts/family-logs.sh
family_logs thin "$out/thin" "$scenes" "${RESOLUTION:-640x360}" "${RIG:-five-view}"
IFS=, read -ra list <<<"$methods"
for m in "${list[@]}"; do
    config=()
    case "$m" in gc-*) config=(--config '{"fill_occlusions": true}') ;; esac
    target/release/replay eval "${logs[@]}" --methods "$m" "${config[@]}" --format json 2>/dev/null >"$out/$m.json"
    target/release/replay "${logs[0]}" --method "$m" "${config[@]}" --out "$out/first-$m" -q 2>/dev/null
    cp "$out/first-$m"/*/"${m}_error_0.0-4.0px.png" "$out/maps/"
done
python3 - "$out" "$methods" <<'PY'
import json, os, sys
out, methods = sys.argv[1], sys.argv[2].split(",")
print("| method | AvgErr | Bad1 % | Bad2 % | occluded AvgErr | occluded Bad1 % | seconds |")
print("|---|---|---|---|---|---|---|")
for m in methods:
    r = json.load(open(os.path.join(out, m + ".json")))[0]
    a, o = r["mean"], r["occluded"] or {}
    print(f"| {m} | {a['avg_err_px']:.3f} | {a['bad_1']:.2f} | {a['bad_2']:.2f} | "
          f"{o.get('avg_err_px', float('nan')):.3f} | {o.get('bad_1', float('nan')):.2f} | {r['seconds']:.1f} |")
PY
