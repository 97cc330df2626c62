#!/usr/bin/env bash
# Sub-pixel precision: simulated five-view captures of the `slanted` family (one matte textured
# plane tilted 5-35 degrees, disparity exactly linear in the image; never used for training),
# 640x360 over the working range the log carries. For every method given (default mfusenet,
# sgm-heuristic, bm-heuristic, gc-heuristic): AvgErr, BadPix 0.07 and Bad0.5 against the exact
# truth, and pixel locking: the share of the first set's estimates by the distance of their
# fractional part to the nearest integer, in five bins of 0.1 px (the truth of a slanted plane
# is spread evenly: 20 % each; an estimate that locks to the pixel grid piles into the first).
#
#   scripts/eval-subpixel.sh [OUT_DIR] [SCENES] [METHODS] [RESOLUTION]   (default out/subpixel, 4, …, 640x360)
set -euo pipefail
cd "$(dirname "$0")/.."
out="${1:-out/subpixel}"
scenes="${2:-4}"
methods="${3:-mfusenet,sgm-heuristic,bm-heuristic,gc-heuristic}"
resolution="${4:-640x360}"
mkdir -p "$out"
cargo build --release -q -p record -p replay
source scripts/family-logs.sh
family_logs slanted "$out/slanted-$resolution" "$scenes" "$resolution"
IFS=, read -ra list <<<"$methods"
for m in "${list[@]}"; do
    target/release/replay eval "${logs[@]}" --methods "$m" --format json 2>/dev/null >"$out/$m.json"
    target/release/replay "${logs[0]}" --method "$m" --out "$out/first-$m" -q 2>/dev/null
done
python3 - "$out" "$methods" <<'PY'
import glob, json, os, struct, sys

out, methods = sys.argv[1], sys.argv[2].split(",")

def pfm(path):
    with open(path, "rb") as f:
        kind = f.readline().strip()
        width, height = map(int, f.readline().split())
        scale = float(f.readline())
        count = width * height * (3 if kind == b"PF" else 1)
        values = struct.unpack(("<" if scale < 0 else ">") + f"{count}f", f.read(4 * count))
    return values

print("| method | AvgErr (px) | BadPix 0.07 (%) | Bad0.5 (%) | bias (px) | locking: estimates within 0.0-0.1 / 0.1-0.2 / 0.2-0.3 / 0.3-0.4 / 0.4-0.5 px of an integer (%) |")
print("|---|---|---|---|---|---|")
for m in methods:
    r = json.load(open(os.path.join(out, m + ".json")))[0]
    a = r["mean"]
    bins = [0] * 5
    for path in glob.glob(os.path.join(out, f"first-{m}", "*", f"{m}_disparity.pfm")):
        for d in pfm(path):
            if d == d and abs(d) != float("inf"):
                distance = abs(d - round(d))
                bins[min(int(distance * 10), 4)] += 1
    total = max(sum(bins), 1)
    shares = " / ".join(f"{100 * b / total:.1f}" for b in bins)
    print(f"| {m} | {a['avg_err_px']:.3f} | {a['bad_0_07']:.1f} | {a['bad_0_5']:.2f} | {a['bias']:+.3f} | {shares} |")
PY
