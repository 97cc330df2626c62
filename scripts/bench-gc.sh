#!/usr/bin/env bash
# Graph-cuts benchmarks: prints the host's CPU, then
#  1. a three-view gc-heuristic run on each of the seven Middlebury third-size dev scenes (≈430×370,
#     the default 32 disparities, `replay` on an imported log): seconds per scene (the method's own
#     time and the whole process) and peak RSS, then the median;
#  2. growth with image size: a simulated three-view capture at 320×240, 640×480 and 1280×960
#     (32 disparities);
#  3. growth with disparity count: the 640×480 capture at 32, 64 and 128 disparities;
#  4. with --full: a five-view 1920×1080 capture (default 128 disparities).
# Peer: the IPOL KZ2 program takes a median 6.7 s per *stereo* pair of these scenes (range 0..24,
# single thread, Intel host; ../shared/data/README.md), Midd1 79 s.
source "$(dirname "$0")/bench-common.sh"

# One run of gc-heuristic on a log: "<method seconds> <process seconds> <peak RSS MB>".
run() { # log [replay options]
    /usr/bin/time -f "%e %M" -o "$T/time" $R "$1" --method gc-heuristic "${@:2}" --out "$T/out" -q
    read -r wall rss < "$T/time"
    method=$(python3 -c "import json;d=json.load(open('$T/out/summary.json'));print('%.2f' % sum(s['seconds'] for s in d['sets']))")
    echo "$method $wall $((rss / 1024))"
}

DATA=../shared/data/middlebury2006-third-dev
if [ -d "$DATA" ]; then
    target/release/record import "$DATA" --focal-px 1246.67 -o "$T/midd.mcap" -q --no-blueprint
    : > "$T/times"
    for set in 0 1 2 3 4 5 6; do
        read -r method wall rss <<< "$(run "$T/midd.mcap" --sets $set)"
        echo "middlebury three-view set $set: method ${method} s, process ${wall} s, peak RSS ${rss} MB"
        echo "$wall" >> "$T/times"
    done
    echo "median process time: $(sort -n "$T/times" | sed -n 4p) s (target ≤ 6.7 s; no scene over 30 s)"
else
    echo "skipped the Middlebury runs: $DATA is missing (the shared evaluation data sits beside the checkout)"
fi

for size in 320x240 640x480 1280x960; do
    target/release/record --rig three-view --resolution "$size" -o "$T/s$size.mcap" -q --no-blueprint
    read -r method wall rss <<< "$(run "$T/s$size.mcap" --num-disparities 32)"
    echo "three-view $size, 32 disparities: method ${method} s, peak RSS ${rss} MB"
done
for disparities in 32 64 128; do
    read -r method wall rss <<< "$(run "$T/s640x480.mcap" --num-disparities "$disparities")"
    echo "three-view 640x480, $disparities disparities: method ${method} s, peak RSS ${rss} MB"
done

if [ "${1:-}" = "--full" ]; then
    target/release/record --rig five-view -o "$T/hd.mcap" -q --no-blueprint
    read -r method wall rss <<< "$(run "$T/hd.mcap")"
    echo "five-view 1920x1080, 128 disparities: method ${method} s, process ${wall} s, peak RSS ${rss} MB"
fi
