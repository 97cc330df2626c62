#!/usr/bin/env bash
# Does a farther group help MFuseNet? Simulated lines of five (`record --rig line5`) replayed with
# their three nearest views (left, right) and with all five, and crosses at two baselines
# (`record --rig grid-cross`) with the cross and with both crosses, each at the farther votes
# given (`mfusenet`'s `farther_vote`); 640x360, two sets each. Prints AvgErr px and the change
# against the nearest group alone, per capture and vote. The captures are kept in OUT_DIR.
#
#   scripts/eval-votes.sh [OUT_DIR] [VOTES] [LINES] [CROSSES]
#     default out/votes, "1 0.5", "random:8 random:9 workpiece:71 toy:3 clutter:5", "random:8 bin:11";
#     an empty LINES or CROSSES ("") leaves that kind out
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-out/votes}"
votes="${2:-1 0.5}"
lines="${3-random:8 random:9 workpiece:71 toy:3 clutter:5}"
crosses="${4-random:8 bin:11}"
mkdir -p "$out"
cargo build --release -q -p record -p replay
record=target/release/record
replay=target/release/replay
eval_json() { # LOG NEIGHBOURS CONFIG OUT
    "$replay" eval "$1" --rectify --neighbours "$2" --methods mfusenet --config "$3" --format json 2>/dev/null >"$4"
}
rows=()
for kind in line cross; do
    if [ "$kind" = line ]; then specs=$lines rig=line5 near=left,right all=left,right,left2,right2
    else specs=$crosses rig=grid-cross near=left,right,top,bottom all=left,right,top,bottom,left2,right2,top2,bottom2; fi
    for spec in $specs; do
        scene=${spec%%:*} seed=${spec##*:}
        log="$out/$kind-$scene-$seed.mcap"
        [ -f "$log" ] || "$record" --rig "$rig" --scene "$scene" --seed "$seed" --resolution 640x360 \
            --captures 2 -o "$log" -q --no-blueprint
        eval_json "$log" "$near" '{}' "$out/$kind-$scene-$seed-near.json"
        for vote in $votes; do
            eval_json "$log" "$all" "{\"farther_vote\": $vote}" "$out/$kind-$scene-$seed-all-$vote.json"
        done
        rows+=("$kind-$scene-$seed")
    done
done
python3 - "$out" "$votes" "${rows[@]}" <<'PY'
import json, os, sys
out, votes, rows = sys.argv[1], sys.argv[2].split(), sys.argv[3:]
err = lambda name: json.load(open(os.path.join(out, name + ".json")))[0]["mean"]["avg_err_px"]
print("| capture | nearest group | " + " | ".join(f"every view, vote {v}" for v in votes) + " |")
print("|---|---|" + "---|" * len(votes))
for row in rows:
    near = err(f"{row}-near")
    cells = [f"{err(f'{row}-all-{v}'):.4f} ({100 * (err(f'{row}-all-{v}') / near - 1):+.1f} %)" for v in votes]
    print(f"| {row} | {near:.4f} | " + " | ".join(cells) + " |")
PY
