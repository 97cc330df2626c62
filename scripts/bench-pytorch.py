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
import resource
import time

import torch
from torch import nn
import torch.nn.functional as F


def conv_bn(cin, cout, k, stride=1):
    # Conv3d without bias, then BatchNorm3d: `<name>.0.weight`, `<name>.1.{weight,bias,running_*}`.
    return nn.Sequential(nn.Conv3d(cin, cout, k, stride=stride, padding=k // 2, bias=False), nn.BatchNorm3d(cout))


def up_bn(cin, cout):
    # ConvTranspose3d k3 s2 p1 op1 (doubles D, H, W), no bias, then BatchNorm3d.
    return nn.Sequential(
        nn.ConvTranspose3d(cin, cout, 3, stride=2, padding=1, output_padding=1, bias=False), nn.BatchNorm3d(cout)
    )


class Reference(nn.Module):
    """MFuseNet for `views` cost volumes of shape [B, D, H, W] (D, H, W multiples of 4)."""

    def __init__(self, views):
        super().__init__()
        self.views = views
        relu = lambda: nn.ReLU(True)  # noqa: E731
        self.feature = nn.Sequential(
            conv_bn(1, 4, 7), relu(), conv_bn(4, 4, 5), relu(), conv_bn(4, 4, 5), relu(), conv_bn(4, 4, 3), relu()
        )
        self.concat = conv_bn(4 * views, 4, 7)
        self.down1 = conv_bn(4, 4, 3, stride=2)
        self.dconv1 = conv_bn(4, 4, 3)
        self.down2 = conv_bn(4, 4, 3, stride=2)
        self.dconv21 = conv_bn(4, 4, 7)
        self.dconv22 = conv_bn(4, 4, 3)
        self.up1 = up_bn(4, 4)
        self.uconv1 = conv_bn(8, 4, 3)
        self.up2 = up_bn(4, 4)
        self.uconv2 = conv_bn(8, 4, 7)
        self.distill1 = conv_bn(4, 4, 5)
        self.classify = nn.Conv3d(4, 1, 3, padding=1)

    def logits(self, volumes):
        # volumes: `views` tensors [B, D, H, W] -> logits [B, D, H, W]
        c = torch.cat([self.feature(v.unsqueeze(1)) for v in volumes], 1)  # [B, 4N, D, H, W]
        c = F.relu(self.concat(c))  # [B, 4, D, H, W]
        d1 = F.relu(self.down1(c))  # [B, 4, D/2, H/2, W/2]
        d1 = F.relu(self.dconv1(d1)) + d1
        d2 = F.relu(self.down2(d1))  # [B, 4, D/4, H/4, W/4]
        d2 = F.relu(self.dconv21(d2)) + d2
        d2 = F.relu(self.dconv22(d2)) + d2
        u1 = F.relu(self.uconv1(torch.cat((F.relu(self.up1(d2)), d1), 1)))  # [B, 4, D/2, H/2, W/2]
        u2 = F.relu(self.uconv2(torch.cat((F.relu(self.up2(u1)), c), 1)))  # [B, 4, D, H, W]
        c = F.relu(self.distill1(u2)) + u2
        return self.classify(c).squeeze(1)  # [B, D, H, W]

    def forward(self, volumes):
        p = F.softmax(self.logits(volumes), dim=1)
        d = torch.arange(p.shape[1], dtype=p.dtype).view(1, -1, 1, 1)
        return (p * d).sum(1)  # [B, H, W]


def parameter_count(net):
    return sum(p.numel() for p in net.parameters())


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, default=2, help="cost volumes (1, 2 or 4) for the inference timing")
    parser.add_argument("--disparities", type=int, default=32)
    parser.add_argument("--height", type=int, default=372)
    parser.add_argument("--width", type=int, default=428)
    parser.add_argument("--repeats", type=int, default=2, help="inference runs (the fastest is reported)")
    parser.add_argument("--train-steps", type=int, default=3, help="training steps per variant (0: none)")
    parser.add_argument("--weights", help="a shipped safetensors file to load with load_state_dict first")
    args = parser.parse_args()

    torch.manual_seed(1)
    net = Reference(args.views).eval()
    if args.weights:
        from safetensors.torch import load_file

        state = load_file(args.weights)
        net.load_state_dict(state, strict=True)  # every name and shape must fit
    result = {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "parameters": {n: parameter_count(Reference(n)) for n in (1, 2, 4)},
    }

    shape = [1, args.disparities, args.height, args.width]
    volumes = [torch.rand(shape) for _ in range(args.views)]
    times = []
    with torch.no_grad():
        for _ in range(args.repeats):
            start = time.perf_counter()
            disparity = net(volumes)
            times.append(time.perf_counter() - start)
    result["inference"] = {
        "views": args.views,
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
