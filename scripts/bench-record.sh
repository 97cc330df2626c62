#!/usr/bin/env bash
# Recording speed: a five-view 1920x1080 capture of the toy scene (4 samples per pixel), goal
# <= 5 s wall with a peak RSS <= 1.5 GB on the 2-core machine. Runs the release binary RUNS times
# (default 3) and reports every run (verdict FAIL above the goal), then the minimum and median.
# OLD=PATH (another build's `record` binary) interleaves it run by run, for a same-run comparison.
# Usage: [RUNS=N] [OLD=path/to/record] scripts/bench-record.sh [extra record arguments]
set -euo pipefail
cd "$(dirname "$0")/.."
WALL_LIMIT_SECS=5
RSS_LIMIT_KB=$((1536 * 1024))
RUNS=${RUNS:-3}
cargo build --release --quiet -p record
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
builds=(target/release/record)
[ -n "${OLD:-}" ] && builds+=("$OLD")
status=0
for run in $(seq "$RUNS"); do
    for bin in "${builds[@]}"; do
        /usr/bin/time -f "%e %M" -o "$out/time" "$bin" --rig five-view -o "$out/capture.mcap" -q "$@"
        read -r wall rss_kb < "$out/time"
        echo "$bin $wall" >> "$out/walls"
        size=$(stat -c %s "$out/capture.mcap")
        verdict=ok
        awk -v w="$wall" -v l="$WALL_LIMIT_SECS" 'BEGIN { exit !(w > l) }' && verdict=FAIL
        [ "$rss_kb" -gt "$RSS_LIMIT_KB" ] && verdict=FAIL
        [ "$bin" = target/release/record ] && [ "$verdict" != ok ] && status=1
        printf '{"build": "%s", "run": %d, "wall_secs": %s, "peak_rss_mb": %.1f, "log_mb": %.1f, "limits": {"wall_secs": %d, "peak_rss_mb": 1536}, "verdict": "%s"}\n' \
            "$bin" "$run" "$wall" "$(awk -v k="$rss_kb" 'BEGIN { print k / 1024 }')" "$(awk -v b="$size" 'BEGIN { print b / 1e6 }')" "$WALL_LIMIT_SECS" "$verdict"
    done
done
for bin in "${builds[@]}"; do
    awk -v b="$bin" '$1 == b { print $2 }' "$out/walls" | sort -n | awk -v b="$bin" '
        { w[NR] = $1 }
        END { m = (NR % 2) ? w[(NR + 1) / 2] : (w[NR / 2] + w[NR / 2 + 1]) / 2;
              printf "{\"build\": \"%s\", \"runs\": %d, \"wall_min_secs\": %s, \"wall_median_secs\": %.2f}\n", b, NR, w[1], m }'
done
exit $status
