#!/usr/bin/env bash
# Remakes the shipped MFuseNet weights (fuse/weights/*.safetensors) exactly as recorded in
# fuse/weights/README.md: the three variants trained by `replay train` on simulated captures,
# one after the other (each run resumes from its checkpoint when restarted), then copied into
# fuse/weights/. Runs in train/ (git-ignored); about 80 minutes on a 2-vCPU host.
#
#   scripts/train-weights.sh            # all three
#   scripts/train-weights.sh 2          # only the three-view network
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release -q -p replay
mkdir -p train
# A copy, so that rebuilding the workspace does not touch a running training.
cp target/release/replay train/replay-bin
variants=${*:-2 1 4}
common=(--train-sets 100 --val-sets 6)
for views in $variants; do
    case $views in
        1) name=mfusenet-stereo steps=1000 crop=128 tune=600 ;;
        2) name=mfusenet-3view steps=1600 crop=128 tune=600 ;;
        4) name=mfusenet-5view steps=700 crop=96 tune=0 ;;
        *) echo "unknown variant $views (1, 2 or 4)" >&2; exit 2 ;;
    esac
    # Stage 1: from a random initialisation, baselines uniform in 6-28 mm.
    train/replay-bin train --views "$views" --steps "$steps" --crop "$crop" "${common[@]}" \
        --baseline-mm 6,28 --baseline-draw uniform --dir "train/$name"
    out="train/$name/$name.safetensors"
    if [ "$tune" -gt 0 ]; then
        # Stage 2: fine-tuned at half the learning rate on captures whose baselines are drawn
        # log-uniformly from 3-30 mm (small disparities, as in far backgrounds, as common as large).
        train/replay-bin train --views "$views" --steps "$tune" --crop "$crop" "${common[@]}" \
            --baseline-mm 3,30 --baseline-draw log-uniform --learning-rate 0.00025 \
            --init-weights "$out" --dir "train/$name-ft"
        out="train/$name-ft/$name.safetensors"
        dir="train/$name-ft"
    else
        dir="train/$name"
    fi
    cp "$out" fuse/weights/
    echo "$name: $(python3 -c "import json;d=json.load(open('$dir/training.json'));print(f\"{d['steps_done']} steps, {d['train_seconds']/60:.1f} min, validation AvgErr {d['val_avg_err_px']:.3f} px, Bad1 {d['val_bad1_percent']:.2f} %\")")"
done
