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
for views in $variants; do
    case $views in
        1) name=mfusenet-stereo steps=1000 crop=128 ;;
        2) name=mfusenet-3view steps=1600 crop=128 ;;
        4) name=mfusenet-5view steps=1000 crop=96 ;;
        *) echo "unknown variant $views (1, 2 or 4)" >&2; exit 2 ;;
    esac
    train/replay-bin train --views "$views" --steps "$steps" --crop "$crop" --train-sets 100 --val-sets 6 \
        --dir "train/$name"
    cp "train/$name/$name.safetensors" fuse/weights/
    echo "$name: $(python3 -c "import json;d=json.load(open('train/$name/training.json'));print(f\"{d['steps_done']} steps, {d['train_seconds']/60:.1f} min, validation AvgErr {d['val_avg_err_px']:.3f} px, Bad1 {d['val_bad1_percent']:.2f} %\")")"
done
