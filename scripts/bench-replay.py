#!/usr/bin/env python3
"""Our classical methods against OpenCV on the same five-view 1920x1080 capture, in one run.

Records the capture (release `record`) unless given, reads its five images with the Python `mcap`
client, times OpenCV StereoBM on four pairs and StereoSGBM (MODE_HH) on one pair, then runs
`replay --method bm-heuristic` and `--method sgm-heuristic` (128 disparities) and reports the
method times (from replay's summary.json), the process wall times, peak RSS and the ratios with
their goals: bm-heuristic <= 1.0 x StereoBM, sgm-heuristic <= 0.5 x StereoSGBM, the process's wall
time <= 1.2 x the method's (reading, set assembly, evaluation and the result files), <= 1.5 GB.

Each method is timed twice: `warm`, the best of three runs back to back (the memory the last run
freed is still backed by the host), and `cold`, the median of three runs each after a pause of
PAUSE_S seconds, as a workcell runs one capture every few seconds (on virtual machines that hand
freed memory back to the host, a fresh page then costs a host fault). OpenCV is timed warm,
its objects reused across calls as an application would.

WATCH=N (default 6; 0 to skip) also times the workcell's process: `replay watch DIR` started once
per method, the capture copied into DIR N times, PAUSE_S seconds apart (renamed into place, as
the recorder does); for each copy the method's time and the latency from the rename to its
summary.json, the first copy (a fresh process) apart from the median of the rest (warm).

TRUTH=0 replays a copy of the capture without its ground truth (scripts/strip-truth.py: what a
real camera on the arm logs), so the process does what a workcell's does: no evaluation, no
ground truth read; OpenCV still reads the capture's images.

OUTPUTS=LIST passes `--outputs LIST` to replay (default: every result file; a workcell that needs
only the depth: OUTPUTS=depth). BM_CONFIG=JSON and SGM_CONFIG=JSON pass `--config JSON` to the
method (e.g. BM_CONFIG='{"colour": false}': block matching on luma, as StereoBM).

Usage: .venv/bin/python scripts/bench-replay.py [capture.mcap]
  (pip install -r scripts/requirements-bench.txt into the venv first)
"""
import json
import os
import subprocess
import sys
import tempfile
import time

import cv2
import numpy as np
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DISPARITIES = 128
REPEATS = 3
PROCESS_LIMIT = 1.2
# The replay binary measured (REPLAY=PATH for another build's).
REPLAY = os.environ.get("REPLAY", os.path.join(ROOT, "target/release/replay"))
RSS_LIMIT_MB = 1536
# The result files replay writes (`--outputs`).
OUTPUTS = os.environ.get("OUTPUTS", "all")
# Configuration overrides per method (`--config`).
CONFIGS = {"bm-heuristic": os.environ.get("BM_CONFIG"), "sgm-heuristic": os.environ.get("SGM_CONFIG")}
# Seconds of idle before each cold run (PAUSE_S=0 to skip the cold runs).
PAUSE_S = float(os.environ.get("PAUSE_S", "5"))
# Captures copied into a watched folder per method (WATCH=0 to skip).
WATCH = int(os.environ.get("WATCH", "6"))
# Whether replay reads the capture's ground truth (TRUTH=0: a copy without it).
TRUTH = os.environ.get("TRUTH", "1") != "0"


def images(path):
    out = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        topics = [f"/camera/{role}/image" for role in ("center", "left", "right", "top", "bottom")]
        for _, channel, _, msg in reader.iter_decoded_messages(topics=topics):
            if len(out) < 5:
                role = channel.topic.split("/")[2]
                rgb = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.width, 3)
                out[role] = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    return out


def pairs(views):
    """Each neighbour as OpenCV's (left, right) pair with the reference as `left`: flips and
    transposes turn every direction into the right-neighbour case."""
    c = views["center"]
    return [
        (c, views["right"]),
        (np.ascontiguousarray(c[:, ::-1]), np.ascontiguousarray(views["left"][:, ::-1])),
        (np.ascontiguousarray(c.T), np.ascontiguousarray(views["bottom"].T)),
        (np.ascontiguousarray(c[::-1, :].T), np.ascontiguousarray(views["top"][::-1, :].T)),
    ]


def best_of(fn):
    times = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def run_replay(log, method, out):
    start = time.perf_counter()
    rss_file = os.path.join(tempfile.mkdtemp(), "rss")
    subprocess.run(["/usr/bin/time", "-f", "%M", "-o", rss_file, REPLAY, log,
                    "--method", method, "--num-disparities", str(DISPARITIES), "--out", out, "-q"]
                   + ([] if OUTPUTS == "all" else ["--outputs", OUTPUTS])
                   + (["--config", CONFIGS[method]] if CONFIGS.get(method) else []), check=True)
    wall = time.perf_counter() - start
    peak_kb = int(open(rss_file).read().split()[-1])
    summary = json.load(open(os.path.join(out, "summary.json")))
    return summary["sets"][0]["seconds"], wall, peak_kb / 1024


def load_script(name):
    """The module of `scripts/NAME` (a file name with hyphens, not importable by name)."""
    import importlib.util
    spec = importlib.util.spec_from_file_location(name.removesuffix(".py").replace("-", "_"),
                                                  os.path.join(ROOT, "scripts", name))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_watch(log, method, work):
    """`replay watch` on a folder into which `log` is copied WATCH times, PAUSE_S seconds apart
    (scripts/bench-watch.py): per copy (method seconds, latency from the rename to its summary.json)."""
    bench_watch = load_script("bench-watch.py")
    bench_watch.REPLAY = REPLAY
    extra = ["--num-disparities", str(DISPARITIES)] + ([] if OUTPUTS == "all" else ["--outputs", OUTPUTS]) \
        + (["--config", CONFIGS[method]] if CONFIGS.get(method) else [])
    return bench_watch.run_watch(log, method, WATCH, PAUSE_S, extra, work)


def main():
    subprocess.run(["cargo", "build", "--release", "--quiet", "-p", "record", "-p", "replay"], cwd=ROOT, check=True)
    work = tempfile.mkdtemp()
    log = sys.argv[1] if len(sys.argv) > 1 else os.path.join(work, "capture.mcap")
    if len(sys.argv) == 1:
        subprocess.run([os.path.join(ROOT, "target/release/record"), "-o", log, "-q"], check=True)
    views = images(log)
    cv2.setNumThreads(os.cpu_count() or 1)
    bm = cv2.StereoBM_create(numDisparities=DISPARITIES, blockSize=9)
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=DISPARITIES, blockSize=5, P1=8 * 3 * 25, P2=32 * 3 * 25,
                                 uniquenessRatio=5, speckleWindowSize=50, speckleRange=2, disp12MaxDiff=1,
                                 mode=cv2.STEREO_SGBM_MODE_HH)
    if not TRUTH:
        camera = os.path.join(work, "camera.mcap")
        load_script("strip-truth.py").strip(log, camera)
        log = camera
    four = pairs(views)
    opencv_bm = best_of(lambda: [bm.compute(l, r) for l, r in four])
    opencv_sgbm = best_of(lambda: sgbm.compute(four[0][0], four[0][1]))
    model = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), "?")
    results = {"host": f"{model}, {os.cpu_count()} vCPUs", "replay": REPLAY, "outputs": OUTPUTS, "configs": CONFIGS, "opencv": cv2.__version__, "threads": cv2.getNumThreads(), "opencv_bm_four_pairs_s": opencv_bm,
               "opencv_sgbm_hh_one_pair_s": opencv_sgbm, "ground_truth": TRUTH}
    for method, peer, limit in [("bm-heuristic", opencv_bm, 1.0), ("sgm-heuristic", opencv_sgbm, 0.5)]:
        out = os.path.join(work, method)
        warm = min((run_replay(log, method, out) for _ in range(REPEATS)), key=lambda r: r[0])
        runs = {"warm": warm}
        if PAUSE_S > 0:
            cold = []
            for _ in range(REPEATS):
                time.sleep(PAUSE_S)
                cold.append(run_replay(log, method, out))
            runs["cold"] = sorted(cold, key=lambda r: r[0])[len(cold) // 2]
        if WATCH > 1:
            watched = run_watch(log, method, work)
            rest = sorted(watched[1:])
            seconds, latency = rest[len(rest) // 2]
            results.setdefault(method, {})["watch"] = {
                "first": {"method_s": watched[0][0], "latency_s": watched[0][1],
                          "ratio_to_opencv": watched[0][0] / peer},
                "median_of_the_rest": {"method_s": seconds, "latency_s": latency,
                                       "ratio_to_opencv": seconds / peer, "goal_ratio": limit,
                                       "latency_to_method": latency / seconds,
                                       "goal_process_to_method": PROCESS_LIMIT},
                "every_copy": [{"method_s": m, "latency_s": l} for m, l in watched]}
        for kind, (seconds, wall, rss_mb) in runs.items():
            verdicts = []
            if seconds / peer > limit:
                verdicts.append("slower than the goal against OpenCV")
            if wall / seconds > PROCESS_LIMIT:
                verdicts.append("process overhead over the goal")
            if rss_mb > RSS_LIMIT_MB:
                verdicts.append("memory over the goal")
            results.setdefault(method, {})[kind] = {
                "method_s": seconds, "process_wall_s": wall, "peak_rss_mb": rss_mb,
                "ratio_to_opencv": seconds / peer, "goal_ratio": limit,
                "process_to_method": wall / seconds, "goal_process_to_method": PROCESS_LIMIT,
                "verdict": "; ".join(verdicts) or "ok"}
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
