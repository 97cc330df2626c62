#!/usr/bin/env bash
# The classical methods' time with another process on the host, as in a robot cell (drivers,
# a logger, a training run): `bm-heuristic` and `sgm-heuristic` on a five-view 1080p capture
# (128 disparities, `--outputs none`) alone and beside two busy loops at the lowest priority
# (`nice -n 19`, one per vCPU), each N times; with OLD=DIR, an earlier build's `replay`
# interleaved with this one's. Prints the method's seconds (summary.json) per run.
# Usage: [OLD=DIR] [RUNS=3] scripts/bench-contention.sh [capture.mcap]
source "$(dirname "$0")/bench-common.sh"
capture="${1:-$T/hd.mcap}"
[ -f "$capture" ] || target/release/record --rig five-view -o "$capture" -q --no-blueprint
builds=("new:target/release")
[ -n "${OLD:-}" ] && builds=("old:$OLD" "${builds[@]}")
runs="${RUNS:-3}"
measure() { # measure LABEL → one line per build and method
    for m in bm-heuristic sgm-heuristic; do
        for b in "${builds[@]}"; do
            times=()
            for _ in $(seq "$runs"); do
                "${b#*:}/replay" "$capture" --method "$m" --num-disparities 128 --outputs none --out "$T/c" -q
                times+=("$(python3 -c "import json,sys;print(f\"{json.load(open(sys.argv[1]))['sets'][0]['seconds']:.3f}\")" "$T/c/summary.json")")
            done
            echo "$1 ${b%%:*} $m: ${times[*]} s"
        done
    done
}
measure alone
hogs=()
for _ in $(seq "$(nproc)"); do
    nice -n 19 sh -c 'while :; do :; done' &
    hogs+=($!)
done
trap 'kill "${hogs[@]}" 2>/dev/null; rm -rf "$T"' EXIT
sleep 1
measure "beside $(nproc) busy loops at nice 19:"
