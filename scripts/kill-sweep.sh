#!/usr/bin/env bash
# kill -9 sweep: starts `record --captures 6 --resolution 640x480` N times (default 20), kills it
# with SIGKILL at a random instant, recovers the temporary file it left with `replay recover` and
# checks that every set the recorder had reported done ("set k/6 done") is in the recovered log.
# Usage: scripts/kill-sweep.sh [N] [SEED] [MAX_MS]   (release binaries; one line per run; the kill
# instants are drawn from 300 ms to MAX_MS, default the length of one uninterrupted run)
set -uo pipefail
cd "$(dirname "$0")/.."
runs=${1:-20}
RANDOM=${2:-1}
cargo build --release --quiet -p record -p replay || exit 1
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
failures=0
max_ms=${3:-}
if [ -z "$max_ms" ]; then
    start=$(date +%s%N)
    target/release/record --resolution 640x480 --captures 6 -o "$work/full.mcap" -q
    max_ms=$(( ($(date +%s%N) - start) / 1000000 ))
    echo "{\"uninterrupted_run_ms\": $max_ms}"
fi
for run in $(seq 1 "$runs"); do
    dir="$work/$run"; mkdir -p "$dir"
    millis=$((300 + RANDOM % max_ms))
    RUST_LOG=info target/release/record --resolution 640x480 --captures 6 -o "$dir/capture.mcap" 2> "$dir/record.log" &
    pid=$!
    sleep "$(awk -v m="$millis" 'BEGIN { print m / 1000 }')"
    kill -9 "$pid" 2>/dev/null
    wait "$pid" 2>/dev/null
    done_sets=$(grep -c " done (" "$dir/record.log")
    left=$(ls -A "$dir" | grep -E '^\.capture\.mcap\.partial-|^capture\.mcap$' | head -1)
    if [ -z "$left" ]; then
        recovered=0
    else
        target/release/replay recover "$dir/$left" -o "$dir/fixed.mcap" -q >/dev/null 2>&1
        recovered=$(target/release/replay check "$dir/fixed.mcap" --json -q 2>/dev/null | python3 -c 'import json, sys; print(len(json.load(sys.stdin)))' 2>/dev/null)
        recovered=${recovered:-0}
    fi
    verdict=ok
    [ "$recovered" -ge "$done_sets" ] || { verdict=FAIL; failures=$((failures + 1)); }
    echo "{\"run\": $run, \"killed_after_ms\": $millis, \"reported_done\": $done_sets, \"recovered\": $recovered, \"file\": \"${left:-none}\", \"verdict\": \"$verdict\"}"
done
echo "{\"runs\": $runs, \"failures\": $failures}"
[ "$failures" = 0 ]
