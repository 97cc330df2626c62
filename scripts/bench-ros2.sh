#!/usr/bin/env bash
# Reading ROS 2 bags against reading our own log (same-run ratios, this host):
#   1. a simulated five-view 1920x1080 capture written both ways (record, same seed): wall time and
#      peak RSS of `replay info` (reads every set, lists the topics), RUNS interleaved runs each;
#      goal: the bag costs <= 1.2x our own log;
#   2. a robot-style bag whose camera streams at 10 Hz through long rests (written by rosbags from
#      a Middlebury dev scene): peak RSS against the bytes of images it streams; goal: memory
#      bounded by the sets read (the reader keeps at most 256 MiB of image payloads, then reads
#      the chosen frames again).
# Usage: scripts/bench-ros2.sh [RUNS]   (default 5)
source "$(dirname "$0")/bench-common.sh"
RUNS=${1:-5}
PY=.venv/bin/python
target/release/record --rig five-view --seed 1 -o "$T/own.mcap" -q --no-blueprint
target/release/record --rig five-view --seed 1 --format ros2 -o "$T/bag" -q
echo "own log $(du -m "$T/own.mcap" | cut -f1) MB, bag $(du -sm "$T/bag" | cut -f1) MB"
for run in $(seq "$RUNS"); do
    for input in own.mcap bag; do
        /usr/bin/time -f "%e %M" -o "$T/time" "$R" info "$T/$input" --json > /dev/null
        read -r wall rss < "$T/time"
        echo "$input $wall $rss" >> "$T/times"
    done
done
awk '{ n[$1]++; w[$1, n[$1]] = $2; m[$1] = ($3 > m[$1] ? $3 : m[$1]) }
     END {
       for (k in n) { c = n[k]; for (i = 1; i <= c; i++) for (j = i + 1; j <= c; j++) if (w[k, j] < w[k, i]) { t = w[k, i]; w[k, i] = w[k, j]; w[k, j] = t }
                      med[k] = w[k, int((c + 1) / 2)]; printf "%-9s median wall %.3f s over %d runs, peak RSS %.0f MB\n", k, med[k], c, m[k] / 1024 }
       printf "bag / own log: %.2fx wall (goal <= 1.2x)\n", med["bag"] / med["own.mcap"]
     }' "$T/times"
if [ -x "$PY" ] && [ -d ../shared/data/middlebury2006-third-dev/Aloe ]; then
    for rest in 10 40; do
        "$PY" tests/python/write_ros2_capture.py ../shared/data/middlebury2006-third-dev/Aloe "$T/stream$rest" \
            --views view2@0,view1@-1,view3@1,view0@-2,view4@2 --rest-secs "$rest" > /dev/null
        frames=$("$R" info "$T/stream$rest" --json | "$PY" -c 'import json,sys; d=json.load(sys.stdin); print(sum(n for _, n in d["stream"]["image_topics"]))')
        /usr/bin/time -f "%e %M" -o "$T/time" "$R" info "$T/stream$rest" --json > /dev/null
        read -r wall rss < "$T/time"
        echo "streamed bag, ${rest} s per station: $frames frames of 427x370 rgb8 ($(( frames * 427 * 370 * 3 / 1048576 )) MB of pixels, file $(du -sm "$T/stream$rest" | cut -f1) MB): $wall s, peak RSS $(( rss / 1024 )) MB"
    done
else
    echo "streamed bags skipped: need .venv (scripts/test.sh makes it) and ../shared/data"
fi
