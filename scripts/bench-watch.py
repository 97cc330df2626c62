#!/usr/bin/env python3
"""The workcell's replay: `replay watch DIR` started once, a capture copied into DIR N times,
PAUSE seconds apart (each copy renamed into place, as the recorder does), and for each copy the
method's time (its summary.json) and the latency from the rename to that summary.json. The first
copy runs in a fresh process; the rest in one that has run a set (docs/benchmarks.md, "A watching
process for the workcell"). Against it, the same capture replayed by one process per copy, the
same PAUSE apart.

Usage: python3 scripts/bench-watch.py LOG METHOD [COPIES=6] [PAUSE_S=5] [-- replay options…]
  e.g. scripts/bench-watch.py out/toy640.mcap mfusenet 6 5 -- --outputs none
"""
import json
import os
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REPLAY = os.environ.get("REPLAY", os.path.join(ROOT, "target/release/replay"))


def read_summary(path, process):
    while True:
        try:
            return json.load(open(path))
        except (OSError, ValueError):
            if process is not None and process.poll() is not None:
                raise SystemExit(f"replay exited with {process.returncode} before writing {path}")
            time.sleep(0.002)


def run_watch(log, method, copies, pause_s, extra, work):
    """Per copy: (method seconds, seconds from the rename to its summary.json)."""
    folder, out = os.path.join(work, method + "-in"), os.path.join(work, method + "-watch")
    os.makedirs(folder)
    watcher = subprocess.Popen([REPLAY, "watch", folder, "--method", method, "--out", out, "--poll-ms", "5",
                                "--exit-after", str(copies), "-q"] + extra)
    runs = []
    for k in range(copies):
        time.sleep(pause_s)
        staging = os.path.join(folder, f".{k}.mcap.partial")
        subprocess.run(["cp", log, staging], check=True)
        renamed = time.perf_counter()
        os.rename(staging, os.path.join(folder, f"{k}.mcap"))
        summary = read_summary(os.path.join(out, str(k), "summary.json"), watcher)
        runs.append((sum(s["seconds"] for s in summary["sets"]), time.perf_counter() - renamed))
    watcher.wait(timeout=120)
    return runs


def run_processes(log, method, copies, pause_s, extra, work):
    """Per copy, one `replay LOG` process: (method seconds, process wall seconds)."""
    runs = []
    for k in range(copies):
        time.sleep(pause_s)
        out = os.path.join(work, f"{method}-process-{k}")
        start = time.perf_counter()
        subprocess.run([REPLAY, log, "--method", method, "--out", out, "-q"] + extra, check=True)
        wall = time.perf_counter() - start
        summary = read_summary(os.path.join(out, "summary.json"), None)
        runs.append((sum(s["seconds"] for s in summary["sets"]), wall))
    return runs


def main():
    args = sys.argv[1:]
    extra = args[args.index("--") + 1:] if "--" in args else []
    args = args[:args.index("--")] if "--" in args else args
    if len(args) < 2:
        raise SystemExit(__doc__)
    log, method = args[0], args[1]
    copies = int(args[2]) if len(args) > 2 else 6
    pause_s = float(args[3]) if len(args) > 3 else 5.0
    work = tempfile.mkdtemp()
    processes = run_processes(log, method, copies, pause_s, extra, work)
    watched = run_watch(log, method, copies, pause_s, extra, work)
    median = lambda xs: sorted(xs)[len(xs) // 2]
    print(json.dumps({
        "log": log, "method": method, "copies": copies, "pause_s": pause_s, "options": extra,
        "processes": {"method_s": [round(m, 3) for m, _ in processes], "wall_s": [round(w, 3) for _, w in processes],
                      "median_method_s": median([m for m, _ in processes])},
        "watch": {"method_s": [round(m, 3) for m, _ in watched], "latency_s": [round(l, 3) for _, l in watched],
                  "median_method_s_after_the_first": median([m for m, _ in watched[1:]]) if copies > 1 else None},
    }, indent=1))


if __name__ == "__main__":
    main()
