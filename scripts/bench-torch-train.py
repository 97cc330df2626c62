#!/usr/bin/env python3
"""Seconds per training step of the MFuseNet reference network in PyTorch, on a GPU where one is
lent, in the settings `scripts/train-torch.py` could use: cuDNN's algorithm search on or off,
float32 (TF32 convolutions) or bfloat16 autocast, channels-last memory. Random inputs (the step's
cost does not depend on them); every setting's first steps (algorithm search, allocation) are
timed apart from the steady ones. Prints one JSON line per setting; stops starting new ones
after --max-seconds.

  python3 scripts/bench-torch-train.py --views 2 --crop 256 --depth 52 --batch 4
"""

import argparse
import json
import os
import sys
import time

import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from mfusenet_torch import Reference  # noqa: E402


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize()


def run(args, device, benchmark, bf16, channels_last):
    torch.backends.cudnn.benchmark = benchmark
    torch.manual_seed(1)
    net = Reference(args.views).to(device).eval()
    optimiser = torch.optim.Adam(net.parameters(), lr=2.5e-4)
    shape = (args.batch, args.depth, args.crop, args.crop)
    inputs = [torch.rand(shape, device=device) * 2 for _ in range(args.views)]
    target = torch.rand(args.batch, args.crop, args.crop, device=device) * (args.depth - 1)
    if channels_last:
        net = net.to(memory_format=torch.channels_last_3d)

    def step():
        optimiser.zero_grad(set_to_none=True)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
            logits = net.logits(inputs)
        p = F.softmax(logits.float(), dim=1)
        d = torch.arange(p.shape[1], device=device, dtype=p.dtype).view(1, -1, 1, 1)
        loss = F.smooth_l1_loss((p * d).sum(1), target)
        loss.backward()
        optimiser.step()

    warm = []
    for _ in range(args.warmup):
        start = time.perf_counter()
        step()
        sync(device)
        warm.append(round(time.perf_counter() - start, 3))
    start = time.perf_counter()
    for _ in range(args.steps):
        step()
    sync(device)
    steady = (time.perf_counter() - start) / args.steps
    peak = torch.cuda.max_memory_allocated(device) / 2**30 if device.type == "cuda" else None
    return {
        "views": args.views,
        "shape": list(shape),
        "cudnn_benchmark": benchmark,
        "bf16": bf16,
        "channels_last": channels_last,
        "warmup_seconds": warm,
        "seconds_per_step": round(steady, 4),
        "crops_per_second": round(args.batch / steady, 2),
        "peak_gib": round(peak, 2) if peak is not None else None,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--crop", type=int, default=256)
    parser.add_argument("--depth", type=int, default=52)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--max-seconds", type=float, default=120)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument(
        "--settings",
        default="0,0,0;1,0,0;0,1,0;0,0,1",
        help="semicolon-separated benchmark,bf16,channels_last triples (1 = on)",
    )
    args = parser.parse_args()
    device = torch.device(args.device)
    started = time.time()
    for setting in args.settings.split(";"):
        if time.time() - started > args.max_seconds:
            print(json.dumps({"skipped": setting, "reason": "--max-seconds reached"}), flush=True)
            continue
        benchmark, bf16, channels_last = (s == "1" for s in setting.split(","))
        try:
            print(json.dumps(run(args, device, benchmark, bf16, channels_last)), flush=True)
        except Exception as e:  # one setting failing (memory, an unsupported kernel) is a result too
            print(json.dumps({"setting": setting, "error": str(e)[:300]}), flush=True)


if __name__ == "__main__":
    main()
