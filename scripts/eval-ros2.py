#!/usr/bin/env python3
"""A robot's ROS 2 bag against `record import` of the same images: every method's disparities and
metrics must agree (the bag's set is the imported one).

For each dev scene given, `tests/python/write_ros2_capture.py` writes a bag with `rosbags` the way
a UR + camera system records (the camera streaming at 10 Hz through the moves, /tf at 20 Hz, the
hand-eye transform on /tf_static, joints at 125 Hz out of order) of the paper's three views (view1
the reference, view0 and view2 its neighbours); `record import` reads the same folder. `replay
--method all` runs on both (0 … 32 disparities), and this prints per method the mean |Δ| of the two
disparity maps and each one's AvgErr / Bad1 against disp1.png / 12.

    .venv/bin/python scripts/eval-ros2.py [--no-build] [SCENE ...]   (default: Aloe; release binaries)
"""
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data" / "middlebury2006-third-dev"
if "--no-build" in sys.argv:
    sys.argv.remove("--no-build")
else:
    subprocess.run(["cargo", "build", "--release", "-q", "-p", "record", "-p", "replay"], cwd=ROOT, check=True)
RECORD, REPLAY = ROOT / "target/release/record", ROOT / "target/release/replay"


def pfm(path):
    with open(path, "rb") as f:
        f.readline()
        width, height = map(int, f.readline().split())
        scale = float(f.readline())
        data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4").reshape(height, width)
    return np.flipud(data)


def disparities(out):
    return {p.name.removesuffix("_disparity.pfm"): pfm(p) for p in out.glob("*/*_disparity.pfm")}


print("| scene | method | mean abs diff (px) | bag AvgErr / Bad1 | import AvgErr / Bad1 |")
print("|---|---|---|---|---|")
for scene in sys.argv[1:] or ["Aloe"]:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        bag, log = tmp / "bag", tmp / "import.mcap"
        subprocess.run([sys.executable, ROOT / "tests/python/write_ros2_capture.py", DATA / scene, bag,
                        "--views", "view1@0,view0@-1,view2@1"], check=True, stdout=subprocess.DEVNULL)
        subprocess.run([RECORD, "import", DATA / scene, "-o", log, "-q"], check=True)
        outputs = {}
        for name, source in [("bag", bag), ("import", log)]:
            subprocess.run([REPLAY, source, "--method", "all", "--min-disparity", "0", "--num-disparities", "32",
                            "--out", tmp / name, "-q"], check=True)
            outputs[name] = disparities(tmp / name)
        truth = np.asarray(Image.open(DATA / scene / "disp1.png"), dtype=np.float64) / 12.0
        known = truth > 0

        def metrics(d):
            ok = known & np.isfinite(d)
            error = np.abs(d[ok] - truth[ok])
            return error.mean(), 100.0 * (error > 1.0).mean()

        for method in sorted(outputs["import"]):
            a, b = outputs["bag"][method], outputs["import"][method]
            both = np.isfinite(a) & np.isfinite(b)
            diff = float(np.abs(a[both] - b[both]).mean()) if both.any() else float("nan")
            (ea, ba), (eb, bb) = metrics(a), metrics(b)
            print(f"| {scene} | {method} | {diff:.4f} | {ea:.3f} / {ba:.2f} | {eb:.3f} / {bb:.2f} |")
