#!/usr/bin/env bash
# The demo's time: `replay demo` (record the five-view 960x540 toy capture, replay it with the
# demo's eleven methods, write the files and demo.rrd) with its wall time and peak RSS, then each
# method's own time from summary.json. Goal: the whole demo <= 30 s, mfusenet <= 5 s.
# Usage: scripts/bench-demo.sh [extra `replay demo` arguments]
source "$(dirname "$0")/bench-common.sh"
/usr/bin/time -f "%e %M" -o "$T/time" $R demo --out "$T/demo" -q "$@"
read -r wall rss < "$T/time"
echo "replay demo: ${wall} s wall, peak RSS $((rss / 1024)) MB (goal: 30 s)"
python3 - "$T/demo/results/summary.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
for s in d["sets"]:
    m = (s["outputs"].get("metrics") or {}).get("all") or {}
    print(f"  {s['method']:<16} {s['seconds']:6.2f} s  AvgErr {m.get('avg_err_px', float('nan')):.3f} px  Bad1 {m.get('bad_1', float('nan')):.2f} %")
print(f"  methods together {sum(s['seconds'] for s in d['sets']):.1f} s of the replay's {d['seconds']:.1f} s")
PY
