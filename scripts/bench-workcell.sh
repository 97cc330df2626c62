#!/usr/bin/env bash
# The workcell speed figures in one run on one host (docs/benchmarks.md, "Workcell speed"):
#   1. record, five-view 1920x1080 toy capture (4 samples per pixel): wall time, best of 3 (goal <= 5 s);
#   2. bm-heuristic and sgm-heuristic on it with 128 disparities against OpenCV StereoBM (four
#      pairs) and StereoSGBM MODE_HH (one pair): scripts/bench-replay.py (goals <= 1.0 x, <= 0.5 x,
#      process wall <= 1.2 x the method's time);
#   3. mfusenet on a five-view 640x360 toy capture with its working range (the lite network on 16 + 8 slices of context) and on
#      the demo's 960x540 capture: method time, AvgErr, Bad1 (goal <= 5 s at 960x540);
#   4. with TORCH_PYTHON (a Python with torch and safetensors): the same network in PyTorch on
#      the 640x360 capture's shape (and on 40 slices), N = 4, and on Middlebury third size, N = 2, against ours (goals
#      <= 0.10 x and <= 0.25 x);
#   5. `replay demo`, whole (goal <= 30 s).
# With OLD=DIR (a folder holding an earlier build's `record` and `replay`), each of our figures is
# measured for that build too, interleaved, so that before and after share the run.
# Usage: [OLD=DIR] [TORCH_PYTHON=…] scripts/bench-workcell.sh
source "$(dirname "$0")/bench-common.sh"
builds=("new:target/release")
[ -n "${OLD:-}" ] && builds=("old:$OLD" "${builds[@]}")

best_wall() { # best_wall N CMD… → the least wall time of N runs
    local n=$1 best=; shift
    for _ in $(seq "$n"); do
        /usr/bin/time -f "%e" -o "$T/t" "$@" > /dev/null 2>&1
        local t; t=$(cat "$T/t")
        if [ -z "$best" ] || awk -v a="$t" -v b="$best" 'BEGIN { exit !(a < b) }'; then best=$t; fi
    done
    echo "$best"
}

method_line() { # method_line SUMMARY → "seconds AvgErr Bad1"
    python3 -c "import json,sys;d=json.load(open(sys.argv[1]));s=d['sets'][0];m=s['outputs']['metrics']['all'];print(f\"{s['seconds']:.2f} s, AvgErr {m['avg_err_px']:.3f} px, Bad1 {m['bad_1']:.2f} %\")" "$1"
}

echo "== 1. record, five-view 1920x1080"
for b in "${builds[@]}"; do
    echo "${b%%:*}: $(best_wall 3 "${b#*:}/record" --rig five-view -o "$T/hd-${b%%:*}.mcap" -q --no-blueprint) s"
done

echo "== 2. bm-heuristic and sgm-heuristic against OpenCV (1080p five-view, 128 disparities)"
for b in "${builds[@]}"; do
    echo "${b%%:*}:"
    REPLAY="${b#*:}/replay" .venv/bin/python scripts/bench-replay.py "$T/hd-new.mcap"
done

echo "== 3. mfusenet"
target/release/record --rig five-view --resolution 640x360 --log-working-range -o "$T/toy640.mcap" -q --no-blueprint
target/release/replay demo --out "$T/demo-capture" --method bm-stereo -q > /dev/null
for b in "${builds[@]}"; do
    "${b#*:}/replay" "$T/toy640.mcap" --method mfusenet --out "$T/m640-${b%%:*}" -q
    echo "${b%%:*} 640x360: $(method_line "$T/m640-${b%%:*}/summary.json")"
    "${b#*:}/replay" "$T/demo-capture/capture.mcap" --method mfusenet --out "$T/m960-${b%%:*}" -q
    echo "${b%%:*} 960x540 (the demo's capture, default range): $(method_line "$T/m960-${b%%:*}/summary.json")"
done

if [ -n "${TORCH_PYTHON:-}" ]; then
    echo "== 4. the reference network in PyTorch (network only, best of 2)"
    # The default five-view network (lite) on the shape our run gave it (its slices, context and
    # padding included: the summary's details), and on the 40 slices it had when narrow ranges
    # were widened to 32 disparities.
    slices=$(python3 -c "import json,sys;print(json.load(open(sys.argv[1]))['sets'][0]['details']['network_num_disparities'])" "$T/m640-new/summary.json")
    for dd in $(printf '%s\n' "$slices" 40 | sort -un); do
        "$TORCH_PYTHON" scripts/bench-pytorch.py --views 4 --architecture lite --disparities "$dd" --height 360 --width 640 --train-steps 0 \
            --weights fuse/weights/mfusenet-5view-lite.safetensors | python3 -c "import json,sys;d=json.load(sys.stdin);print(f\"pytorch {d['torch']}, lite N=4 $dd×360×640: {d['inference']['seconds']:.2f} s\")"
    done
    "$TORCH_PYTHON" scripts/bench-pytorch.py --train-steps 0 --weights fuse/weights/mfusenet-3view.safetensors \
        | python3 -c "import json,sys;d=json.load(sys.stdin);print(f\"pytorch {d['torch']}, N=2 32x372x428: {d['inference']['seconds']:.2f} s\")"
    DATA=../shared/data/middlebury2006-third-dev
    if [ -d "$DATA" ]; then
        target/release/record import "$DATA" --focal-px 1246.67 -o "$T/midd.mcap" -q --no-blueprint
        for b in "${builds[@]}"; do
            "${b#*:}/replay" "$T/midd.mcap" --sets 0 --method mfusenet --out "$T/midd-${b%%:*}" -q
            echo "${b%%:*} Middlebury set 0 (Aloe) three-view: $(method_line "$T/midd-${b%%:*}/summary.json")"
        done
    else
        echo "skipped the Middlebury figure: $DATA is missing (the shared evaluation data sits beside the checkout)"
    fi
else
    echo "== 4. skipped the PyTorch peer: set TORCH_PYTHON to a Python with torch and safetensors"
fi

echo "== 5. replay demo"
for b in "${builds[@]}"; do
    /usr/bin/time -f "%e %M" -o "$T/t" "${b#*:}/replay" demo --out "$T/demo-${b%%:*}" -q
    read -r wall rss < "$T/t"
    echo "${b%%:*}: ${wall} s wall, peak RSS $((rss / 1024)) MB"
done
