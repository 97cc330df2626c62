#!/usr/bin/env bash
# MFuseNet benchmarks: prints the host's CPU, then
#  1. three-view Middlebury third-size inference, cost volumes included (`replay` on each of the
#     seven dev scenes, 32 disparities): seconds per scene and peak RSS;
#  2. one training step on the shipped weights' crops (128 × 128 × 32 for N = 1, 2; 96 × 96 × 32 for
#     N = 4; `replay train`, 20 steps);
#  3. with --full: five-view 1920×1080 with 128 disparities (record + replay mfusenet, which goes
#     coarse to fine there): time and peak RSS.
#  4. the PyTorch peer (`scripts/bench-pytorch.py`: the reference network, same shapes, this host)
#     when TORCH_PYTHON names a Python with torch and safetensors (e.g. `python3 -m venv
#     .venv-torch && .venv-torch/bin/pip install torch safetensors`: about a minute, 5.4 GB with
#     its CUDA libraries); else the figures measured before stand (12.7–13.0 s on AMD EPYC hosts, 14.0 s on
#     Intel; PyTorch 2.15 measured 9.3 s on the AMD host of docs/benchmarks.md's table).
source "$(dirname "$0")/bench-common.sh"

DATA=../shared/data/middlebury2006-third-dev
if [ -d "$DATA" ]; then
    target/release/record import "$DATA" --focal-px 1246.67 -o "$T/midd.mcap" -q --no-blueprint
    for set in 0 1 2 3 4 5 6; do
        /usr/bin/time -f "%e %M" -o "$T/time" $R "$T/midd.mcap" --sets $set --method mfusenet --out "$T/out" -q
        read -r wall rss < "$T/time"
        method=$(python3 -c "import json;d=json.load(open('$T/out/summary.json'));s=d['sets'][0];print(f\"{s['seconds']:.2f} {s['outputs']['name']}\")")
        echo "middlebury three-view set $set: method ${method%% *} s (${method#* }), process ${wall} s, peak RSS $((rss / 1024)) MB"
    done
else
    echo "skipped the Middlebury inference: $DATA is missing (the shared evaluation data sits beside the checkout)"
fi

for views in 1 2 4; do
    crop=128
    [ "$views" = 4 ] && crop=96
    $R train --views "$views" --steps 20 --crop-px "$crop" --train-sets 4 --val-sets 1 --validate-every 1000 \
        --dir "$T/train-$views" --dataset-dir "$T/dataset" -q
    python3 -c "import json;d=json.load(open('$T/train-$views/training.json'));print(f\"training step N=$views, ${crop}x${crop}x32 crop: {d['train_seconds']/d['steps_done']:.3f} s\")"
done

if [ -n "${TORCH_PYTHON:-}" ]; then
    "$TORCH_PYTHON" scripts/bench-pytorch.py --weights fuse/weights/mfusenet-3view.safetensors > "$T/torch.json"
    python3 - "$T/torch.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
i = d["inference"]
print(f"pytorch {d['torch']} ({d['threads']} threads), reference network with the shipped three-view weights, "
      f"N={i['views']} {i['shape'][1]}x{i['shape'][2]}x{i['shape'][3]}: {i['seconds']:.2f} s "
      f"(runs {', '.join(f'{s:.2f}' for s in i['all_seconds'])}), network only, peak RSS {d['peak_rss_mb']:.0f} MB")
for k, v in d["train_step"].items():
    print(f"pytorch training step {k}, {v['crop'][1]}x{v['crop'][2]}x{v['crop'][0]} crop: {v['seconds']:.3f} s")
print("parameters (N=1, 2, 4):", ", ".join(str(v) for v in d["parameters"].values()))
PY
else
    echo "skipped the PyTorch peer: set TORCH_PYTHON to a Python with torch and safetensors"
fi

if [ "${1:-}" = "--full" ]; then
    target/release/record --rig five-view -o "$T/hd.mcap" -q --no-blueprint
    /usr/bin/time -f "%e %M" -o "$T/time" $R "$T/hd.mcap" --method mfusenet --num-disparities 128 --out "$T/hd" -q
    read -r wall rss < "$T/time"
    echo "five-view 1920x1080, 128 disparities: ${wall} s, peak RSS $((rss / 1024)) MB"
fi
