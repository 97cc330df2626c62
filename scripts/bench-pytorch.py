#!/usr/bin/env python3
"""PyTorch peer for `scripts/bench-mfusenet.sh`: the MFuseNet reference network on CPU.

The network is written here from the paper and the layer list of the authors' `FuseNetwork`
(`weihaosky/MFuseNet`, `network.py`): the same layers, shapes and `state_dict` names, so that our
shipped safetensors files load into it with `load_state_dict` (`--weights`, which also checks
that every name and shape fits). It times, on this host and with this host's thread count:

  1. eval-mode inference of one three-view Middlebury third-size shape (N = 2, 32 disparities,
     372 × 428 by default), cost volumes excluded (PyTorch has no matcher; ours are timed with them);
  2. one training step (train-mode forward, smooth-L1, backward, Adam) on the crop our
     `replay train` uses (128 × 128 × 32 for N = 1, 2; 96 × 96 × 32 for N = 4).

Needs `torch` (and `safetensors` for `--weights`) in the Python that runs it; the test venv does
not have them (torch is 5.4 GB installed, with its CUDA libraries): `python3 -m venv .venv-torch &&
.venv-torch/bin/pip install torch safetensors`, then `TORCH_PYTHON=.venv-torch/bin/python
scripts/bench-mfusenet.sh`.
"""

import argparse
import json
import os
import resource
import sys
import time

import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from mfusenet_torch import Reference  # noqa: E402


def parameter_count(net):
    return sum(p.numel() for p in net.parameters())


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=2, help="cost volumes (1, 2 or 4) for the inference timing")
    parser.add_argument("--architecture", default="paper", choices=sorted(Reference.KERNELS), help="kernel sizes (lite: about a fifth of the work per voxel)")
    parser.add_argument("--disparities", type=int, default=32)
    parser.add_argument("--height", type=int, default=372)
    parser.add_argument("--width", type=int, default=428)
    parser.add_argument("--repeats", type=int, default=2, help="inference runs (the fastest is reported)")
    parser.add_argument("--train-steps", type=int, default=3, help="training steps per variant (0: none)")
    parser.add_argument("--weights", help="a shipped safetensors file to load with load_state_dict first")
    args = parser.parse_args()

    torch.manual_seed(1)
    state, sharp = None, False
    if args.weights:
        from safetensors.torch import load_file

        state = load_file(args.weights)
        # A sharp file (5·N input channels in `concat`) takes a sharp volume per view as well.
        concat = state.get("concat.0.weight")
        sharp = concat is not None and args.views > 0 and concat.shape[1] == 5 * args.views
    net = Reference(args.views, args.architecture, sharp=sharp).eval()
    if state is not None:
        net.load_state_dict(state, strict=True)  # every name and shape must fit
    result = {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "parameters": {n: parameter_count(Reference(n)) for n in (1, 2, 4)},
    }

    shape = [1, args.disparities, args.height, args.width]
    volumes = [torch.rand(shape) for _ in range(args.views * (2 if sharp else 1))]
    times = []
    with torch.no_grad():
        for _ in range(args.repeats):
            start = time.perf_counter()
            disparity = net(volumes)
            times.append(time.perf_counter() - start)
    result["inference"] = {
        "views": args.views,
        "sharp": sharp,
        "shape": shape,
        "seconds": min(times),
        "all_seconds": times,
        "finite": bool(torch.isfinite(disparity).all()),
    }

    steps = {}
    for views, crop in ((1, 128), (2, 128), (4, 96)):
        if args.train_steps <= 0:
            break
        model = Reference(views).train()
        optimiser = torch.optim.Adam(model.parameters(), lr=5e-4)
        inputs = [torch.rand(1, args.disparities, crop, crop) for _ in range(views)]
        target = torch.rand(1, crop, crop) * (args.disparities - 1)
        step_times = []
        for _ in range(args.train_steps):
            start = time.perf_counter()
            optimiser.zero_grad()
            loss = F.smooth_l1_loss(model(inputs), target)
            loss.backward()
            optimiser.step()
            step_times.append(time.perf_counter() - start)
        steps[f"N={views}"] = {"crop": [args.disparities, crop, crop], "seconds": min(step_times)}
    result["train_step"] = steps
    result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(result))


if __name__ == "__main__":
    main()
