#!/usr/bin/env bash
# MFuseNet's speed in f32 and in bfloat16 products (`{"precision": "bf16"}`) against PyTorch's
# forward of the same network on the same shape, in one run on one host (ratios, not absolute
# times: docs/benchmarks.md):
#   - the five-view 640x360 toy capture with its working range (the lite network);
#   - the demo's 960x540 capture (`replay demo`'s, default range);
#   - Middlebury Aloe, three views (the paper's 7³ network).
# Our figure is the method's seconds from `replay`'s summary (cost volumes and post-processing
# included); PyTorch's the network's forward alone (best of 2), 2 threads. PyTorch's lite network
# loads the lite file as it was before its sharp fine-tuning (the reference code has no sharp
# volumes; the cost per voxel is the same but for the sharp volumes' channels in `concat`).
#
#   TORCH_PYTHON=.venv-torch/bin/python [ROUNDS=3] scripts/bench-precision.sh
source "$(dirname "$0")/bench-common.sh"
ROUNDS=${ROUNDS:-3}
grep -qm1 avx512_bf16 /proc/cpuinfo || echo "note: this host has no AVX512-BF16: bf16 runs in f32" >&2
echo "host: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs), $(nproc) vCPUs, flags: $(grep -om1 'avx512_bf16\|avx512f' /proc/cpuinfo | sort -u | xargs)"
target/release/record --rig five-view --resolution 640x360 --log-working-range -o "$T/toy640.mcap" -q --no-blueprint
target/release/replay demo --out "$T/demo-capture" --method bm-stereo -q > /dev/null
DATA=../shared/data/middlebury2006-third-dev
[ -d "$DATA" ] || { echo "$DATA is missing (the shared evaluation data sits beside the checkout)" >&2; exit 1; }
target/release/record import "$DATA" --focal-px 1246.67 -o "$T/midd.mcap" -q --no-blueprint
seconds() { # seconds SUMMARY → "seconds AvgErr slices"
    python3 -c "import json,sys;s=json.load(open(sys.argv[1]))['sets'][0];m=s['outputs'].get('metrics',{}).get('all',{});print(f\"{s['seconds']:.2f} {m.get('avg_err_px', float('nan')):.4f} {s['details'].get('network_num_disparities')} {s['details'].get('precision')}\")" "$1"
}
torch_forward() { # torch_forward ARGS… → seconds
    "$TORCH_PYTHON" scripts/bench-pytorch.py --train-steps 0 "$@" | python3 -c "import json,sys;print(f\"{json.load(sys.stdin)['inference']['seconds']:.2f}\")"
}
echo "| round | capture | precision | method s | AvgErr | network slices | PyTorch s | ratio |"
echo "|---|---|---|---|---|---|---|---|"
for r in $(seq "$ROUNDS"); do
    for capture in toy640 demo aloe; do
        case $capture in
            toy640) log=$T/toy640.mcap; extra=() ;;
            demo) log=$T/demo-capture/capture.mcap; extra=() ;;
            aloe) log=$T/midd.mcap; extra=(--sets 0) ;;
        esac
        torch=nan
        for p in f32 bf16; do
            target/release/replay "$log" "${extra[@]}" --method mfusenet --outputs none --out "$T/$capture-$p" -q --config "{\"precision\":\"$p\"}"
            read -r s err slices ran <<< "$(seconds "$T/$capture-$p/summary.json")"
            if [ "$torch" = nan ] && [ -n "${TORCH_PYTHON:-}" ]; then
                case $capture in
                    toy640) torch=$(torch_forward --views 4 --architecture lite --disparities "$slices" --height 360 --width 640 \
                        --weights fuse/weights/runs/mfusenet-any-lite/init.safetensors) ;;
                    demo) torch=$(torch_forward --views 4 --architecture lite --disparities "$slices" --height 540 --width 960 \
                        --weights fuse/weights/runs/mfusenet-any-lite/init.safetensors) ;;
                    aloe) torch=$(torch_forward --weights fuse/weights/mfusenet-3view.safetensors) ;;
                esac
            fi
            ratio=$(python3 -c "import sys;t=float(sys.argv[2]);print(f'{float(sys.argv[1])/t:.3f}' if t==t else '–')" "$s" "$torch")
            echo "| $r | $capture | $ran | $s | $err | $slices | $torch | $ratio |"
        done
    done
done
