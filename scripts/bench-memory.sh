#!/usr/bin/env bash
# Peak memory of every method on a five-view 1920x1080 capture with 128 disparities, the limit
# 1.5 GB each: one `replay` process per method (method time from its summary.json, wall time and
# peak RSS from /usr/bin/time), then a verdict per method. The graph-cut fusions take about four
# minutes each here; METHODS=a,b limits the run.
# Usage: [METHODS=list] scripts/bench-memory.sh [capture.mcap]   (records the toy capture unless given)
source "$(dirname "$0")/bench-common.sh"
LIMIT_MB=1536
capture=${1:-}
if [ -z "$capture" ]; then
    capture=$T/capture.mcap
    target/release/record --rig five-view -o "$capture" -q
fi
methods=${METHODS:-$($R --list-methods | awk '{print $1}' | paste -sd, -)}
status=0
for method in ${methods//,/ }; do
    out=$T/$method
    /usr/bin/time -f "%e %M" -o "$T/time" $R "$capture" --method "$method" --num-disparities 128 \
        --outputs none --out "$out" -q > /dev/null 2>&1 || { echo "{\"method\": \"$method\", \"error\": \"replay failed\"}"; status=1; continue; }
    read -r wall rss_kb < "$T/time"
    secs=$(python3 -c "import json,sys; s=json.load(open(sys.argv[1])); print(s['sets'][0]['seconds'])" "$out/summary.json" 2>/dev/null || echo null)
    mb=$((rss_kb / 1024))
    verdict=ok
    [ "$mb" -gt "$LIMIT_MB" ] && { verdict=FAIL; status=1; }
    printf '{"method": "%s", "method_secs": %s, "wall_secs": %s, "peak_rss_mb": %d, "limit_mb": %d, "verdict": "%s"}\n' \
        "$method" "$secs" "$wall" "$mb" "$LIMIT_MB" "$verdict"
done
exit $status
