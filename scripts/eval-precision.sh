#!/usr/bin/env bash
# MFuseNet's convolutions in f32 against bfloat16 products (`{"precision": "bf16"}`, where the
# host has AVX512-BF16): AvgErr, Bad1 and the method's seconds on the same sets, the two
# precisions interleaved per set so that both share the host's state.
#   1. the seven Middlebury 2006 dev scenes (three views, the paper's 7³ network);
#   2. the held-out simulated captures of scripts/eval-simulated.sh (made by it when missing):
#      stereo, three and five views;
#   3. the toy five-view 640x360 capture and the demo's 960x540 capture (the lite network).
#
#   scripts/eval-precision.sh [OUT_DIR]     # default out/eval-precision (git-ignored)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-out/eval-precision}
mkdir -p "$OUT"
cargo build --release -q -p record -p replay
R=target/release/replay
grep -qm1 avx512_bf16 /proc/cpuinfo || echo "note: this host has no AVX512-BF16: both precisions run in f32" >&2
echo "host: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(nproc) vCPUs"
SIM=train/eval-simulated
[ -f "$SIM/random-900.mcap" ] || scripts/eval-simulated.sh "$SIM" 8 > /dev/null
sim_logs=("$SIM"/random-900.mcap "$SIM"/random-902.mcap "$SIM"/random-904.mcap "$SIM"/random-905.mcap \
    "$SIM"/toy-904.mcap "$SIM"/toy-905.mcap "$SIM"/workpiece-906.mcap "$SIM"/workpiece-907.mcap)
[ -f "$OUT/toy640.mcap" ] || target/release/record --rig five-view --resolution 640x360 --log-working-range \
    -o "$OUT/toy640.mcap" -q --no-blueprint
[ -f "$OUT/demo540.mcap" ] || target/release/record --rig five-view --resolution 960x540 --log-working-range \
    -o "$OUT/demo540.mcap" -q --no-blueprint
row() { # row NAME JSON → markdown cells
    python3 -c "import json,sys;r=json.load(open(sys.argv[1]))[0];m=r['mean'];print(f\"| {sys.argv[2]} | {m['avg_err_px']:.4f} | {m['bad_1']:.2f} | {r.get('seconds_total', r.get('seconds', float('nan'))):.1f} |\")" "$1" "$2"
}
echo "| set, precision | AvgErr | Bad1 (%) | seconds |"
echo "|---|---|---|---|"
for p in f32 bf16; do
    $R eval ../shared/data/middlebury2006-third-dev --methods mfusenet --config "{\"precision\":\"$p\"}" --format json -q > "$OUT/midd-$p.json"
    row "$OUT/midd-$p.json" "Middlebury dev, three views, $p"
done
common=(--num-disparities 32 --format json -q)
for views in stereo three five; do
    for p in f32 bf16; do
        case $views in
            stereo) args=(--methods mfusenet-stereo) ;;
            three) args=(--methods mfusenet --neighbours left,right) ;;
            five) args=(--methods mfusenet) ;;
        esac
        $R eval "${sim_logs[@]}" "${args[@]}" --config "{\"precision\":\"$p\"}" "${common[@]}" > "$OUT/sim-$views-$p.json"
        row "$OUT/sim-$views-$p.json" "held-out simulated, $views, $p"
    done
done
for capture in toy640 demo540; do
    for p in f32 bf16; do
        $R eval "$OUT/$capture.mcap" --methods mfusenet --config "{\"precision\":\"$p\"}" --format json -q > "$OUT/$capture-$p.json"
        row "$OUT/$capture-$p.json" "$capture, $p"
    done
done
