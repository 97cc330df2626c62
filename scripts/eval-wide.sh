#!/usr/bin/env bash
# Every method on wide disparity ranges at large sizes, where MFuseNet goes coarse to fine:
#  1. the seven Middlebury 2006 dev scenes upsampled 3x (1239-1395 x 1110 px, three views,
#     searched over 0..96; scripts/make-upsampled.py makes them);
#  2. simulated five-view 1920x1080 captures with 128 disparities of the `bin` family (parts in a
#     tote), which no network was trained on (seeds 1.., 20 mm baseline).
#
#   scripts/eval-wide.sh [OUT_DIR] [CAPTURES] [METHODS]
#
# OUT_DIR defaults to out/eval-wide (git-ignored), CAPTURES to 4, METHODS to every method but
# three of the graph-cuts family (`all` runs those too): graph cuts take 2-3 min per upsampled
# scene or 1080p capture on 2 vCPUs, and `gc-heuristic` is the family's best at third size.
# Prints one table per benchmark; eval.md/.csv/.json in OUT_DIR/{x3,bin1080}.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-out/eval-wide}
CAPTURES=${2:-4}
METHODS=${3:-bm-stereo,bm-mean,bm-min,bm-heuristic,sgm-stereo,sgm-mean,sgm-min,sgm-heuristic,gc-heuristic,mfusenet-stereo,mfusenet}
if [ "$METHODS" = all ]; then
    METHODS=bm-stereo,bm-mean,bm-min,bm-heuristic,sgm-stereo,sgm-mean,sgm-min,sgm-heuristic,gc-stereo,gc-mean,gc-min,gc-heuristic,mfusenet-stereo,mfusenet
fi
mkdir -p "$OUT"
cargo build --release -q -p record -p replay
PY=python3
[ -x .venv/bin/python ] && PY=.venv/bin/python
[ -d "$OUT/middlebury2006-x3" ] || "$PY" scripts/make-upsampled.py ../shared/data/middlebury2006-third-dev "$OUT/middlebury2006-x3"
logs=()
for seed in $(seq 1 "$CAPTURES"); do
    log="$OUT/bin1080-$seed.mcap"
    [ -f "$log" ] || target/release/record --rig five-view --scene bin --seed "$seed" --resolution 1920x1080 \
        --baseline-mm 20 --samples-per-pixel 2 -o "$log" -q --no-blueprint
    logs+=("$log")
done
echo "== Middlebury 2006 dev scenes upsampled 3x, three views, disparities 0..96"
target/release/replay eval "$OUT/middlebury2006-x3" --methods "$METHODS" --out "$OUT/x3" -q
echo
echo "== simulated bin family (never trained on), five views, 1920x1080, disparities 0..128"
target/release/replay eval "${logs[@]}" --num-disparities 128 --methods "$METHODS" --out "$OUT/bin1080" -q
