#!/usr/bin/env bash
# One leg of a training run on a lent GPU machine: the dataset and (where the run folder has no
# checkpoint yet) the run's step-0 checkpoint made by `replay train`, then `scripts/train-torch.py`
# for BUDGET_S seconds in all, which leaves a checkpoint `replay train` resumes (same options,
# `--steps` the total it printed). Several legs may run at once on one GPU: the dataset is made
# by one at a time (a lock on the dataset folder), the others read it from the cache.
#
#   scripts/train-gpu.sh BUDGET_S RUN_DIR BATCH -- <replay train options without --dir/--steps>
#
# PYTHON names a Python with torch and safetensors (default python3). REPLAY names the binary
# (default target/release/replay; on the device machine a carried, stripped copy). PLAN_STEPS is
# the run's planned total, whose last quarter trains at a quarter of the learning rate (default:
# the checkpoint's `train_config` steps). The run folder's checkpoint.safetensors, curves.csv and
# the logs are what to bring back.
set -euo pipefail
cd "$(dirname "$0")/.."
started=$(date +%s)
budget="$1" run="$2" batch="$3"
shift 4
replay="${REPLAY:-target/release/replay}"
dataset="train/dataset"
for ((i = 1; i <= $#; i++)); do
    [ "${!i}" = "--dataset-dir" ] && { j=$((i + 1)); dataset="${!j}"; }
done
mkdir -p "$run" "$dataset"
# `--steps 0` in a folder of its own: the dataset (made here unless cached), and the checkpoint of
# the initial weights, which starts the run where the run folder has no checkpoint yet.
rm -rf "$run.start"
flock "$dataset/.lock" "$replay" train "$@" --steps 0 --dir "$run.start" -q
[ -f "$run/checkpoint.safetensors" ] || cp "$run.start/checkpoint.safetensors" "$run/"
left=$((budget - ($(date +%s) - started)))
echo "$(basename "$run"): dataset and checkpoint ready after $(($(date +%s) - started)) s; training for $left s"
plan=()
[ -n "${PLAN_STEPS:-}" ] && plan=(--plan-steps "$PLAN_STEPS")
"${PYTHON:-python3}" scripts/train-torch.py --dir "$run" --dataset-dir "$dataset" --budget-s "$left" --batch "$batch" "${plan[@]}"
