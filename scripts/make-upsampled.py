#!/usr/bin/env python3
"""Makes an upsampled copy of the Middlebury 2006 third-size dev scenes: a proxy for captures at
full size with wide disparity ranges (3x: 1239-1395 x 1110 px, disparities up to about 59 px,
searched over 0..96).

    .venv/bin/python scripts/make-upsampled.py [SRC] [DST] [--factor 3]
    target/release/replay eval DST --methods mfusenet,sgm-heuristic

SRC defaults to ../shared/data/middlebury2006-third-dev, DST to out/middlebury2006-x3 (ignored by
git; never commit the copies). Views are upsampled bicubically; the ground truth by nearest
neighbour, its values multiplied by the factor and stored as 16-bit PNGs (0 stays unknown). A
multiscopic.toml at the top describes the three-view sets (left view0, centre view1, right view2,
ground truth disp1.png / 12, focal length factor x 3740/3 px) and the searched range
(0 .. factor x 32), so that `replay eval DST` needs no flags.
"""

import argparse
import pathlib
import sys

import numpy as np
from PIL import Image


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("src", nargs="?", default="../shared/data/middlebury2006-third-dev")
    parser.add_argument("dst", nargs="?", default=None)
    parser.add_argument("--factor", type=int, default=3)
    args = parser.parse_args()
    src = pathlib.Path(args.src)
    if not src.is_dir():
        print(f"{src} is missing: the dev scenes live in ../shared/data (see its README)", file=sys.stderr)
        return 1
    factor = args.factor
    dst = pathlib.Path(args.dst or f"out/middlebury2006-x{factor}")
    scenes = sorted(p for p in src.iterdir() if (p / "view1.png").is_file())
    if not scenes:
        print(f"{src} holds no scene folder with view1.png", file=sys.stderr)
        return 1
    for scene in scenes:
        out = dst / scene.name
        out.mkdir(parents=True, exist_ok=True)
        for view in ("view0", "view1", "view2"):
            image = Image.open(scene / f"{view}.png").convert("RGB")
            image.resize((image.width * factor, image.height * factor), Image.BICUBIC).save(out / f"{view}.png")
        truth = np.asarray(Image.open(scene / "disp1.png").convert("L"), dtype=np.uint16)
        big = np.repeat(np.repeat(truth, factor, axis=0), factor, axis=1) * factor
        Image.fromarray(big.astype(np.uint16)).save(out / "disp1.png")
        print(f"{scene.name}: {big.shape[1]} x {big.shape[0]}, largest disparity {big.max() / 12:.1f} px")
    focal = 3740.0 / 3.0 * factor
    (dst / "multiscopic.toml").write_text(
        f"""# Middlebury 2006 third-size dev scenes upsampled {factor}x by scripts/make-upsampled.py
views = ["view0.png@-1", "view1.png@0", "view2.png@1"]
ground_truth = "disp1.png"
ground_truth_scale = 12
baseline_mm = 40
focal_px = {focal}
min_disparity = 0
num_disparities = {32 * factor}
"""
    )
    print(f"wrote {len(scenes)} scenes to {dst}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
