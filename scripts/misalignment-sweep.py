#!/usr/bin/env python3
"""Misalignment sweep of `replay check`: SEEDS simulated five-view captures (640x360, one set) per
kind of error (roll, pitch, yaw of one view, its out-of-plane offset, a hand-eye rotation) with
sizes drawn so that the true worst epipolar error spans about 0.3-3 px, plus SEEDS clean captures.
A case's size is the check's `true_epipolar_error_px` (from the simulator's true poses, worst
neighbour); it must be warned from the warning limit (0.5 px) and failed from the failure limit
(1.5 px), and a clean capture must raise nothing.

Usage: scripts/misalignment-sweep.py [--seeds 50] [--kinds hand-eye,clean] [--keep] [--out out/misalignment]
                                     [--record ...] [--replay ...]
Prints a JSON line per case, then the table (Markdown) and a summary; exit 1 on any miss.
"""
import argparse, json, os, random, subprocess, sys

KINDS = {
    # kind: (record arguments for a magnitude, magnitude range drawn log-uniformly)
    "roll": (lambda role, m: ["--rotation-error", f"{role}:z:{m:.4f}"], (0.04, 0.7)),
    "pitch": (lambda role, m: ["--rotation-error", f"{role}:x:{m:.4f}"], (0.02, 0.4)),
    "yaw": (lambda role, m: ["--rotation-error", f"{role}:y:{m:.4f}"], (0.02, 0.4)),
    "out-of-plane": (lambda role, m: ["--offset-error", f"{role}:z:{m:.3f}"], (0.5, 10.0)),
    "hand-eye": (lambda role, m: ["--hand-eye-error-deg", f"0,0,{m:.4f}"], (0.3, 7.0)),
    "clean": (lambda role, m: [], (0.0, 0.0)),
}
RANK = {"ok": 0, "warn": 1, "fail": 2}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--out", default="out/misalignment")
    parser.add_argument("--record", default="target/release/record")
    parser.add_argument("--replay", default="target/release/replay")
    parser.add_argument("--warn-px", type=float, default=0.5)
    parser.add_argument("--fail-px", type=float, default=1.5)
    parser.add_argument("--samples-per-pixel", type=int, default=4,
                        help="the recorder's anti-aliasing (4, its default, integrates over the pixel as a sensor does)")
    parser.add_argument("--kinds", default=",".join(KINDS), help="comma-separated subset of " + ",".join(KINDS))
    parser.add_argument("--keep", action="store_true", help="keep the logs and reuse those already there")
    args = parser.parse_args()
    kinds = args.kinds.split(",")
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        parser.error(f"unknown kinds {unknown}")
    os.makedirs(args.out, exist_ok=True)
    rows, misses = [], 0
    for kind in kinds:
        arguments, (low, high) = KINDS[kind]
        for seed in range(1, args.seeds + 1):
            rng = random.Random(f"{kind}-{seed}")
            role = rng.choice(["left", "right", "top", "bottom"])
            size = low * (high / low) ** rng.random() if high > 0 else 0.0
            log = os.path.join(args.out, f"{kind}-{seed}.mcap")
            if not (args.keep and os.path.exists(log)):
                subprocess.run([args.record, "--resolution", "640x360", "--captures", "1", "--samples-per-pixel",
                                str(args.samples_per_pixel),
                                "--seed", str(seed), "--no-blueprint", "-q", "-o", log, *arguments(role, size)],
                               check=True)
            check = subprocess.run([args.replay, "check", log, "--json", "-q", "--warn-px", str(args.warn_px),
                                    "--fail-px", str(args.fail_px)], capture_output=True)
            neighbours = json.loads(check.stdout)[0]["neighbours"]
            truth = max(n.get("true_epipolar_error_px", 0.0) for n in neighbours)
            status = max((n["status"] for n in neighbours), key=RANK.get)
            shift = max(abs(n["image_shift_px"]["value"]) for n in neighbours if n["image_shift_px"])
            epipolar = max(n["epipolar_error_px"]["value"] for n in neighbours)
            wanted = "fail" if truth >= args.fail_px else "warn" if truth >= args.warn_px else "ok"
            miss = RANK[status] < RANK[wanted] or (kind == "clean" and status != "ok")
            misses += miss
            row = {"kind": kind, "seed": seed, "role": role, "size": round(size, 4), "true_px": round(truth, 3),
                   "epipolar_px": round(epipolar, 3), "image_shift_px": round(shift, 3), "status": status,
                   "wanted_at_least": wanted, "miss": miss}
            rows.append(row)
            print(json.dumps(row), flush=True)
            if not args.keep:
                os.remove(log)
    print("\n| kind | cases | true error < 0.5 px: ok / warn / fail | 0.5–1.5 px: warned or failed | ≥ 1.5 px: failed | misses |")
    print("|---|---|---|---|---|---|")
    for kind in kinds:
        r = [x for x in rows if x["kind"] == kind]
        small = [x for x in r if x["true_px"] < args.warn_px]
        mid = [x for x in r if args.warn_px <= x["true_px"] < args.fail_px]
        big = [x for x in r if x["true_px"] >= args.fail_px]
        count = lambda xs, s: sum(1 for x in xs if x["status"] == s)
        print(f"| {kind} | {len(r)} | {count(small, 'ok')} / {count(small, 'warn')} / {count(small, 'fail')} | "
              f"{len(mid) - count(mid, 'ok')} of {len(mid)} | {count(big, 'fail')} of {len(big)} | {sum(x['miss'] for x in r)} |")
    print(json.dumps({"cases": len(rows), "misses": misses}))
    return 1 if misses else 0


if __name__ == "__main__":
    sys.exit(main())
