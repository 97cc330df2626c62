#!/usr/bin/env bash
# Remakes the shipped MFuseNet weights (fuse/weights/*.safetensors) exactly as recorded in
# fuse/weights/README.md: the three variants trained by `replay train` on simulated captures,
# one after the other, in stages (each run resumes from its checkpoint when restarted), then
# copied into fuse/weights/. Runs in train/ (git-ignored); about three hours on a
# quiet 2-vCPU host for all three.
#
#   scripts/train-weights.sh            # all three
#   scripts/train-weights.sh 2          # only the three-view network
#   scripts/train-weights.sh 4-lite     # the lite five-view network's stage 1 (`--architecture lite`)
#
# The shipped lite five-view file is that stage 1 fine-tuned with sharp volumes for 6,074 steps
# of a 21,000-step schedule (its learning rate falls only in the last quarter): the run in
# fuse/weights/runs/mfusenet-5view-lite-sharp3, whose README has its options, its start (stage 1's
# file as shipped before 2026-12-02: `git show 269da01:fuse/weights/mfusenet-5view-lite.safetensors`)
# and how its average was written at that step. This script does not run it.
set -euo pipefail
cd "$(dirname "$0")/.."
cargo build --release -q -p replay
mkdir -p train
# A copy, so that rebuilding the workspace does not touch a running training.
cp target/release/replay train/replay-bin
common=(--train-sets 100 --val-sets 6)
# Stage 1: from a random initialisation, baselines uniform in 6-28 mm.
first() { # views name steps crop [more options]
    train/replay-bin train --views "$1" --steps "$3" --crop-px "$4" "${common[@]}" \
        --baseline-mm 6,28 --baseline-draw uniform --dir "train/$2" "${@:5}"
}
# Later stages: from the previous stage's weights at half the learning rate, on captures whose
# baselines are drawn log-uniformly from 3-30 mm (small disparities, as in far backgrounds, as
# common as large ones).
tune() { # views name steps crop from-dir to-dir [more options]
    train/replay-bin train --views "$1" --steps "$3" --crop-px "$4" "${common[@]}" \
        --baseline-mm 3,30 --baseline-draw log-uniform --learning-rate 0.00025 \
        --init-weights "train/$5/$2.safetensors" --dir "train/$6" "${@:7}"
}
ship() { # name dir
    # `replay train` writes the refined readout's locking curve (metadata `locking_curve`)
    # itself; the shipped files that predate it got theirs from `replay train --calibrate FILE`.
    cp "train/$2/$1.safetensors" fuse/weights/
    echo "$1: $(python3 -c "import json;d=json.load(open('train/$2/training.json'));print(f\"{d['steps_done']} steps in this stage, {d['train_seconds']/60:.1f} min, validation AvgErr {d['val_avg_err_px']:.3f} px, Bad1 {d['val_bad1_percent']:.2f} %\")")"
}
for views in ${*:-2 1 4}; do
    case $views in
        1)
            first 1 mfusenet-stereo 1000 128
            tune 1 mfusenet-stereo 600 128 mfusenet-stereo mfusenet-stereo-ft
            # Stages 3 and 4 as for the three-view network (stop 27: the same recipe for both,
            # so that the paper's comparison of the two is between equally trained networks).
            tune 1 mfusenet-stereo 1000 128 mfusenet-stereo-ft mfusenet-stereo-shift --disparity-shift 12 --validate-every 200
            tune 1 mfusenet-stereo 600 128 mfusenet-stereo-shift mfusenet-stereo-keep --disparity-shift 12 --keep-hopeless --validate-every 200
            ship mfusenet-stereo mfusenet-stereo-keep
            ;;
        2)
            first 2 mfusenet-3view 1600 128
            tune 2 mfusenet-3view 600 128 mfusenet-3view mfusenet-3view-ft
            # Stage 3: answers in the first slices of the range (crops drop 0-12 slices).
            tune 2 mfusenet-3view 1000 128 mfusenet-3view-ft mfusenet-3view-shift --disparity-shift 12 --validate-every 200
            # Stage 4: the same, keeping the crops whose inputs cannot tell (blank, periodic,
            # mirror-like) instead of drawing others.
            tune 2 mfusenet-3view 600 128 mfusenet-3view-shift mfusenet-3view-keep --disparity-shift 12 --keep-hopeless --validate-every 200
            ship mfusenet-3view mfusenet-3view-keep
            ;;
        4)
            first 4 mfusenet-5view 700 96
            ship mfusenet-5view mfusenet-5view
            ;;
        4-lite)
            # The paper five-view file's stage 1, three times its steps; trained without context,
            # so its metadata's `context_below` was set to 8 afterwards (fuse/weights/README.md).
            first 4 mfusenet-5view-lite 2100 96 --architecture lite
            ship mfusenet-5view-lite mfusenet-5view-lite
            echo "mfusenet-5view-lite: stage 1 only; the shipped file is its sharp fine-tuning (fuse/weights/runs/mfusenet-5view-lite-sharp3/README.md)"
            ;;
        *) echo "unknown variant $views (1, 2, 4 or 4-lite)" >&2; exit 2 ;;
    esac
done
