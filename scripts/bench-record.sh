#!/usr/bin/env bash
# Recording speed: a five-view 1920x1080 capture of the toy scene (4 samples per pixel), goal
# <= 5 s wall with a peak RSS <= 1.5 GB on the 2-core machine. Runs the release binary three times
# and reports every run (verdict FAIL above the goal).
# Usage: scripts/bench-record.sh [extra record arguments]
set -euo pipefail
cd "$(dirname "$0")/.."
WALL_LIMIT_SECS=5
RSS_LIMIT_KB=$((1536 * 1024))
cargo build --release --quiet -p record
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
status=0
for run in 1 2 3; do
    /usr/bin/time -f "%e %M" -o "$out/time" target/release/record --rig five-view -o "$out/capture.mcap" -q "$@"
    read -r wall rss_kb < "$out/time"
    size=$(stat -c %s "$out/capture.mcap")
    verdict=ok
    awk -v w="$wall" -v l="$WALL_LIMIT_SECS" 'BEGIN { exit !(w > l) }' && verdict=FAIL
    [ "$rss_kb" -gt "$RSS_LIMIT_KB" ] && verdict=FAIL
    [ "$verdict" = ok ] || status=1
    printf '{"run": %d, "wall_secs": %s, "peak_rss_mb": %.1f, "log_mb": %.1f, "limits": {"wall_secs": %d, "peak_rss_mb": 1536}, "verdict": "%s"}\n' \
        "$run" "$wall" "$(awk -v k="$rss_kb" 'BEGIN { print k / 1024 }')" "$(awk -v b="$size" 'BEGIN { print b / 1e6 }')" "$WALL_LIMIT_SECS" "$verdict"
done
exit $status
