#!/usr/bin/env python3
"""Continue a `replay train` run in PyTorch: on a GPU where one is lent, on CPU otherwise.

`replay train` stays the trainer CI tests and the default; this script moves a run to a GPU and
back. It reads the run folder `replay train --dir RUN` made:

  RUN/checkpoint.safetensors  weights `model.<state_dict name>`, Adam's moments `adam_m.<name>` and
                              `adam_v.<name>`, the moving average `average.<name>` when the run
                              keeps one (`average_decay` in `train_config`), metadata
                              `train_config`, `adam_step`, `adam_learning_rate`, `average_decay`,
                              `average_updates`, `train_seconds`, `dataset_key`
  RUN/curves.csv              step, loss, val_avg_err_px, val_bad1_percent

and the run's dataset cache (`--dataset-dir`, the `train-NNNN-<key>.safetensors` and
`val-NNNN-<key>.safetensors` samples: four u8 volumes `[H, W, D]` and the truth in slices). It
trains the same network (`mfusenet_torch.Reference`) the way `replay train` does: random crops
with at least half their pixels labelled (hopeless crops redrawn unless `keep_hopeless`), the
disparity shift and mirror flips of the configuration, frozen BatchNorm statistics (recalibrated
every `recalibrate_every` steps when set), smooth-L1 of the soft-argmin, gradients clipped to a
global norm of 1, Adam with the learning rate quartered for the last quarter of the steps, and
the moving average of the weights updated after every step as `replay train` does (decay
min(`average_decay`, (1 + n) / (10 + n)) after n updates), which is then what validates. One
step here takes `--batch` crops (the loss is the mean of their per-crop losses); `replay train`
takes one, so the checkpoint records `torch_batch` and `torch_steps`.

The checkpoint and curves are written back in the same format (every `checkpoint_every` steps
and at the end), with `train_config`'s `steps` set to the total this run trains to. Then

  replay train <the run's options> --steps <that total> --dir RUN

resumes it on CPU: with nothing left to train it validates and writes the weights and their
metadata (the `torch_*` keys are carried into them). Run it on a machine where the run folder and
dataset exist (`replay train ... --steps 0` makes both: the dataset, and the step-0 checkpoint of
`--init-weights` or of a seeded initialisation).

  python3 scripts/train-torch.py --dir train/5view --dataset-dir train/dataset --budget-s 300
"""

import argparse
import copy
import csv
import json
import math
import os
import re
import sys
import time

import torch
import torch.nn.functional as F
from safetensors import safe_open
from safetensors.torch import save_file

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from mfusenet_torch import Reference  # noqa: E402

# `fuse::mfusenet::input::STEPS_PER_UNIT`: a byte of cost is 1/128 of a unit.
STEPS_PER_UNIT = 128.0
# `replay::train::dataset::{HOPELESS_ERROR_PX, HOPELESS_FRACTION}`.
HOPELESS_ERROR_PX = 3.0
HOPELESS_FRACTION = 0.4
# `replay::train::schedule::{MAX_GRADIENT_NORM, CALIBRATION_CROPS}`.
MAX_GRADIENT_NORM = 1.0
CALIBRATION_CROPS = 32
# Which of a sample's volumes (left, right, top, bottom first) each variant takes in validation
# and the fixed networks in training (0: the view-count-agnostic network, `--views any`, whose
# training crops take a random subset of all the sample keeps).
VIEW_INDICES = {0: [0, 1, 2, 3], 1: [1], 2: [0, 1], 4: [0, 1, 2, 3]}
# `replay::train::dataset::{neighbours_kept, MAX_DRAWN_VIEWS}`: a grid-cross capture's sample
# keeps twelve volumes (the cross, the diagonals, the cross at two baselines), a five-view one
# four; a crop of the view-count-agnostic network draws at most six.
KEPT = {"five-view": 4, "grid-cross": 12}
MAX_DRAWN_VIEWS = 6
OFFSETS = {1: [(1, 0)], 2: [(-1, 0), (1, 0)], 4: [(-1, 0), (1, 0), (0, -1), (0, 1)]}


def log(message):
    print(message, flush=True)


def mirror_order(offsets, vertical, horizontal):
    """`fuse::mfusenet::input::mirror_order`: which input goes to each slot of the mirrored set."""
    order = []
    for slot in offsets:
        mirrored = [(-x if horizontal else x, -y if vertical else y) for (x, y) in offsets]
        if slot not in mirrored:
            return None
        order.append(mirrored.index(slot))
    return order


class Dataset:
    """The cached samples on `device`: volumes `[K, D, H, W]` u8 (K = `kept`; a sharp run's
    `[2K, D, H, W]`, each neighbour's sharp volume after the K input volumes) and truth `[H, W]`
    (slices, 0 = unknown)."""

    def __init__(self, directory, key, count, prefix, depth, device, kept=4, sharp=False):
        self.volumes, self.truth = [], []
        self.kept, self.sharp = kept, sharp
        for index in range(count):
            path = os.path.join(directory, f"{prefix}-{index:04d}-{key}.safetensors")
            if not os.path.exists(path):
                sys.exit(f"error: {path} is missing: make the dataset with `replay train ... --steps 0` first")
            with safe_open(path, "pt") as f:
                names = [f"volume.{i}" for i in range(kept)] + ([f"sharp.{i}" for i in range(kept)] if sharp else [])
                volumes = torch.stack([f.get_tensor(name) for name in names])  # [K or 2K, H, W, D]
                truth = f.get_tensor("truth")  # [H, W]
            if volumes.shape[-1] != depth:
                sys.exit(f"error: {path} has {volumes.shape[-1]} slices, the run's configuration {depth}")
            self.volumes.append(volumes.permute(0, 3, 1, 2).contiguous().to(device))  # [K, D, H, W]
            self.truth.append(truth.to(device))

    def __len__(self):
        return len(self.volumes)


def crop(dataset, index, views, y0, x0, side, indices=None):
    """`fuse::mfusenet::train::crop`: inputs `[V, D, side, side]` (cost units), target and mask `[side, side]`."""
    indices = VIEW_INDICES[views] if indices is None else indices
    if dataset.sharp:
        # The views' volumes, then their sharp volumes (`Sample::inputs`).
        indices = list(indices) + [dataset.kept + i for i in indices]
    v = dataset.volumes[index][indices, :, y0 : y0 + side, x0 : x0 + side].float() / STEPS_PER_UNIT
    t = dataset.truth[index][y0 : y0 + side, x0 : x0 + side]
    depth = v.shape[1]
    mask = (t > 0) & (t <= depth - 1)
    return v, torch.where(mask, t, torch.zeros_like(t)), mask


def shifted(inputs, target, mask, slices, context):
    """`replay::train::schedule::shifted`: the first `slices` slices dropped."""
    if slices == 0:
        return inputs, target, mask
    mask = mask & (target >= slices + context)
    return inputs[:, slices:], (target - slices).clamp(min=0), mask


def winner_take_all_errors(inputs, target, mask):
    """`replay::train::dataset::winner_take_all_errors`: the summed volume's minimum, parabola-refined."""
    cost = inputs.sum(0)  # [D, H, W]
    depth = cost.shape[0]
    best = cost.argmin(0)
    estimate = best.float()
    inner = (best > 0) & (best + 1 < depth)
    b = best.clamp(1, depth - 2)
    left = cost.gather(0, (b - 1).unsqueeze(0))[0]
    centre = cost.gather(0, b.unsqueeze(0))[0]
    right = cost.gather(0, (b + 1).unsqueeze(0))[0]
    denominator = left - 2 * centre + right
    ok = inner & (denominator > 0)
    estimate = torch.where(ok, estimate + 0.5 * (left - right) / torch.where(ok, denominator, torch.ones_like(denominator)), estimate)
    return (estimate - target).abs()[mask]


def hopeless(inputs, target, mask):
    errors = winner_take_all_errors(inputs, target, mask)
    return (errors > HOPELESS_ERROR_PX).sum().item() > HOPELESS_FRACTION * errors.numel()


def crop_px_at(config, step):
    """`TrainConfig::crop_px_at`: the crop side of step `step` (0-based) under `crop_stages`."""
    side = config["crop_px"]
    for stage in config.get("crop_stages", []):
        if stage["from_step"] <= step:
            side = stage["crop_px"]
    return side


def random_crop(config, dataset, generator, slices, count=None, side=None):
    """`replay::train::schedule::random_crop` for one crop `side` px square (default
    `crop_px`) of a step whose shift is `slices`. For
    the view-count-agnostic network (views 0) the crop takes `count` of the sample's neighbours
    (drawn 1..min(K, 6) when None), chosen and ordered at random (`Sample::for_views_drawn`): the crops of one
    batch share the count so that they stack."""
    side = config["crop_px"] if side is None else side
    views = config["views"]
    example = None
    for _ in range(8):
        index = int(torch.randint(len(dataset), (1,), generator=generator))
        _, _, h, w = dataset.volumes[index].shape
        y0 = int(torch.randint(h - side + 1, (1,), generator=generator))
        x0 = int(torch.randint(w - side + 1, (1,), generator=generator))
        indices = None
        if views == 0:
            kept = dataset.volumes[index].shape[0]
            n = count if count is not None else int(torch.randint(1, min(kept, MAX_DRAWN_VIEWS) + 1, (1,), generator=generator))
            indices = torch.randperm(kept, generator=generator)[:n].tolist()
        inputs, target, mask = crop(dataset, index, views, y0, x0, side, indices)
        inputs, target, mask = shifted(inputs, target, mask, slices, config.get("context_below", 0))
        if config.get("flips", False) and views == 0:
            # The pooled network does not know which neighbour gave a volume: any mirror.
            flips = [bool(torch.randint(2, (1,), generator=generator)) for _ in range(2)]
            dims = [d for d, flip in zip((-2, -1), flips) if flip]
            if dims:
                inputs, target, mask = inputs.flip(dims), target.flip(dims), mask.flip(dims)
        elif config.get("flips", False):
            vertical, horizontal = (bool(torch.randint(2, (1,), generator=generator)) for _ in range(2))
            offsets = OFFSETS[views]
            vertical = vertical and mirror_order(offsets, True, False) is not None
            horizontal = horizontal and mirror_order(offsets, False, True) is not None
            order = mirror_order(offsets, vertical, horizontal)
            dims = [d for d, flip in ((-2, vertical), (-1, horizontal)) if flip]
            if order is not None and dims:
                if dataset.sharp:
                    order = order + [len(order) + i for i in order]
                inputs = inputs[order].flip(dims)
                target, mask = target.flip(dims), mask.flip(dims)
        example = (inputs, target, mask)
        enough = int(mask.sum()) * 2 > mask.numel()
        views_only = inputs[: inputs.shape[0] // 2] if dataset.sharp else inputs
        if enough and (config.get("keep_hopeless", False) or not hopeless(views_only, target, mask)):
            break
    return example


def soft_argmin(logits):
    """`fuse::nn::regression::soft_argmin` of `[B, D, H, W]` logits: `[B, H, W]`."""
    p = F.softmax(logits, dim=1)
    d = torch.arange(p.shape[1], dtype=p.dtype, device=p.device).view(1, -1, 1, 1)
    return (p * d).sum(1)


def loss_of(net, inputs, target, mask):
    """Mean over the batch of each crop's smooth-L1 (β = 1) over its labelled pixels."""
    disparity = soft_argmin(net.logits([inputs[:, v] for v in range(inputs.shape[1])]))
    per_pixel = F.smooth_l1_loss(disparity, target, reduction="none", beta=1.0) * mask
    counts = mask.flatten(1).sum(1).clamp(min=1)
    return (per_pixel.flatten(1).sum(1) / counts).mean()


@torch.no_grad()
def validate(net, config, dataset):
    """AvgErr (px) and Bad1 (%) of the soft-argmin on the centre crops (`validation_examples`)."""
    total, bad, count = 0.0, 0, 0
    for index in range(len(dataset)):
        _, _, h, w = dataset.volumes[index].shape
        side = min(w, h, 160) // 4 * 4
        inputs, target, mask = crop(dataset, index, config["views"], (h - side) // 2, (w - side) // 2, side)
        disparity = soft_argmin(net.logits([inputs[v : v + 1] for v in range(inputs.shape[0])]))[0]
        errors = (disparity - target).abs()[mask]
        total += float(errors.sum())
        bad += int((errors > 1.0).sum())
        count += errors.numel()
    count = max(count, 1)
    return total / count, 100.0 * bad / count


@torch.no_grad()
def recalibrate(net, calibration):
    """`fuse::mfusenet::train::recalibrate_batch_norm`: population statistics over the crops, one per batch."""
    norms = [m for m in net.modules() if isinstance(m, torch.nn.BatchNorm3d)]
    saved = [(m.num_batches_tracked.clone(), m.momentum) for m in norms]
    for m in norms:
        m.reset_running_stats()
        m.momentum = None
    net.train()
    for inputs, _, _ in calibration:
        net.logits([inputs[v : v + 1] for v in range(inputs.shape[0])])
    net.eval()
    for m, (count, momentum) in zip(norms, saved):
        m.num_batches_tracked += count
        m.momentum = momentum


def load_checkpoint(path, device):
    with safe_open(path, "pt") as f:
        metadata = f.metadata() or {}
        tensors = {k: f.get_tensor(k) for k in f.keys()}
    if "train_config" not in metadata:
        sys.exit(f"error: {path} has no `train_config`: not a checkpoint of `replay train`")
    config = json.loads(metadata["train_config"])
    # Older files spell some keys the short way (`crop`, `disparities`).
    config.setdefault("crop_px", config.get("crop"))
    config.setdefault("num_disparities", config.get("disparities"))
    architecture = metadata.get("architecture", config.get("architecture", "paper"))
    net = Reference(config["views"], architecture, sharp=bool(config.get("sharp"))).to(device)
    state = {k[len("model.") :]: v for k, v in tensors.items() if k.startswith("model.")}
    net.load_state_dict(state, strict=True)
    step = int(metadata.get("adam_step", "0"))
    optimiser = torch.optim.Adam(net.parameters(), lr=float(metadata.get("adam_learning_rate", config["learning_rate"])))
    for name, p in net.named_parameters():
        m, v = tensors.get(f"adam_m.{name}"), tensors.get(f"adam_v.{name}")
        if m is None or v is None or m.numel() != p.numel() or v.numel() != p.numel():
            sys.exit(f"error: {path} lacks Adam's moments for {name} (or their size is not {p.numel()})")
        optimiser.state[p] = {
            "step": torch.tensor(float(step)),
            "exp_avg": m.reshape(p.shape).to(device).clone(),
            "exp_avg_sq": v.reshape(p.shape).to(device).clone(),
        }
    average = None
    if config.get("average_decay", 0) > 0:
        # The checkpoint's average, or (switched on at this resume) one that starts here.
        kept = "average_decay" in metadata
        values = {}
        for name, p in net.named_parameters():
            a = tensors.get(f"average.{name}") if kept else p.detach()
            if a is None or a.numel() != p.numel():
                sys.exit(f"error: {path} lacks the moving average of {name} (or its size is not {p.numel()})")
            values[name] = a.reshape(p.shape).to(device).clone()
        average = {
            "decay": float(config["average_decay"]),
            "updates": int(metadata.get("average_updates", "0")) if kept else 0,
            "values": values,
        }
    return net, optimiser, step, config, metadata, average


@torch.no_grad()
def update_average(average, net):
    n = average["updates"]
    d = min(average["decay"], (1 + n) / (10 + n))
    for name, p in net.named_parameters():
        average["values"][name].mul_(d).add_(p.detach(), alpha=1 - d)
    average["updates"] = n + 1


def averaged(net, average, calibration):
    """`net` with its parameters replaced by the moving average: its BatchNorm statistics are
    `net`'s, re-estimated on `calibration` when the run recalibrates (as `replay train` does)."""
    if average is None:
        return net
    result = copy.deepcopy(net)
    with torch.no_grad():
        for name, p in result.named_parameters():
            p.copy_(average["values"][name])
    if calibration:
        recalibrate(result, calibration)
        result.eval()
    return result


def save_checkpoint(path, net, optimiser, step, metadata, average):
    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    metadata = dict(metadata)
    metadata.pop("average_decay", None)
    metadata.pop("average_updates", None)
    if average is not None:
        for name, value in average["values"].items():
            tensors[f"average.{name}"] = value.detach().flatten().cpu().contiguous()
        metadata["average_decay"] = repr(average["decay"])
        metadata["average_updates"] = str(average["updates"])
    for name, p in net.named_parameters():
        state = optimiser.state.get(p, {})
        zeros = torch.zeros(p.numel())
        tensors[f"adam_m.{name}"] = state.get("exp_avg", zeros).detach().flatten().cpu().contiguous()
        tensors[f"adam_v.{name}"] = state.get("exp_avg_sq", zeros).detach().flatten().cpu().contiguous()
    metadata = dict(metadata)
    metadata["adam_step"] = str(step)
    metadata["adam_learning_rate"] = repr(float(optimiser.param_groups[0]["lr"]))
    temporary = path + ".partial"
    save_file(tensors, temporary, metadata={k: str(v) for k, v in metadata.items()})
    os.replace(temporary, path)


def read_curves(path, up_to):
    if not os.path.exists(path):
        return []
    with open(path, newline="") as f:
        return [row for row in csv.DictReader(f) if int(row["step"]) <= up_to]


def write_curves(path, rows):
    with open(path + ".partial", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["step", "loss", "val_avg_err_px", "val_bad1_percent"])
        writer.writeheader()
        writer.writerows(rows)
    os.replace(path + ".partial", path)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dir", required=True, help="the run folder of `replay train` (checkpoint.safetensors, curves.csv)")
    parser.add_argument("--dataset-dir", default="train/dataset", help="the run's dataset cache")
    parser.add_argument("--steps", type=int, help="train to this many steps in all (default: the configuration's)")
    parser.add_argument(
        "--budget-s",
        type=float,
        help="instead of --steps: time the first steps, then train to as many steps (a multiple of 10) as fit in this many seconds",
    )
    parser.add_argument(
        "--plan-steps",
        type=int,
        help="with --budget-s: the run's planned total, whose last quarter runs at a quarter of the learning rate "
        "(default: the configuration's `steps`; a leg's own end never quarters it)",
    )
    parser.add_argument("--batch", type=int, default=4, help="crops per step")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--seed", type=int, default=1, help="seed of the crops drawn here")
    args = parser.parse_args()

    started = time.time()
    device = torch.device(args.device)
    torch.backends.cudnn.benchmark = False  # no faster here (scripts/bench-torch-train.py), and each new depth would search again
    checkpoint = os.path.join(args.dir, "checkpoint.safetensors")
    curves = os.path.join(args.dir, "curves.csv")
    net, optimiser, step, config, metadata, average = load_checkpoint(checkpoint, device)
    key = metadata.get("dataset_key")
    if key is None:
        sys.exit(f"error: {checkpoint} has no `dataset_key`: remake it with this version of `replay train`")
    depth = config["num_disparities"] + config.get("context_below", 0)
    kept = KEPT[config.get("rig", "five-view")]
    sharp = bool(config.get("sharp"))
    train_set = Dataset(args.dataset_dir, key, config["train_sets"], "train", depth, device, kept, sharp)
    val_set = Dataset(args.dataset_dir, key, config["val_sets"], "val", depth, device, kept, sharp)
    log(
        f"{config['views'] or 'any'} views, {len(train_set)} + {len(val_set)} captures on {device} "
        f"({torch.cuda.get_device_name(device) if device.type == 'cuda' else 'CPU'}), loaded in {time.time() - started:.1f} s; "
        f"resuming at step {step}"
    )
    generator = torch.Generator().manual_seed(args.seed * 1_000_003 + step)
    rows = read_curves(curves, step)
    net.eval()  # frozen BatchNorm statistics, as `replay train` trains by default
    calibration = []
    if config.get("recalibrate_every", 0) > 0 or config.get("statistics_momentum", 0) > 0:
        if config.get("statistics_momentum", 0) > 0:
            sys.exit("error: tracked BatchNorm statistics (`statistics_momentum`) are not implemented here")
        calibration_generator = torch.Generator().manual_seed(args.seed ^ 0x5EED)
        calibration = [random_crop(config, train_set, calibration_generator, 0) for _ in range(CALIBRATION_CROPS)]

    total = args.steps if args.steps is not None else (None if args.budget_s else config["steps"])
    # The learning-rate schedule's total: the run's plan, not a budgeted leg's end (legs of a few
    # hundred steps would otherwise all run at a quarter of the rate).
    plan = (args.plan_steps or config["steps"]) if total is None else total
    session_start, timing_started = step, None
    previous_seconds = float(metadata.get("train_seconds", "0"))
    loop_started = time.time()
    recent = []
    while total is None or step < total:
        # Steps 10 to 30 are timed (the first ones pick the convolution algorithms).
        if total is None and step - session_start == 10:
            timing_started = time.time()
        if total is None and step - session_start == 30:
            timed = (time.time() - timing_started) / 20
            remaining = args.budget_s - (time.time() - started) - 30
            reachable = int(step + remaining / timed)
            # A multiple of 10 (a multiple of 100 left up to 99 steps' time unused on a 15-minute lease).
            total = max(step, reachable // 10 * 10)
            log(f"{timed:.3f} s per step of {args.batch} crops: training to step {total}")
            if step >= total:
                break
        schedule_total = max(plan, total or 0)
        lr = config["learning_rate"] / 4 if step >= schedule_total * 3 // 4 else config["learning_rate"]
        for group in optimiser.param_groups:
            group["lr"] = lr
        shift = config.get("disparity_shift", 0)
        slices = 4 * int(torch.randint(shift // 4 + 1, (1,), generator=generator)) if shift else 0
        # The view-count-agnostic network: one count of views per batch (1..min(K, 6)), each crop its own.
        drawable = min(KEPT[config.get("rig", "five-view")], MAX_DRAWN_VIEWS)
        count = int(torch.randint(1, drawable + 1, (1,), generator=generator)) if config["views"] == 0 else None
        side = crop_px_at(config, step)
        batch = [random_crop(config, train_set, generator, slices, count, side) for _ in range(args.batch)]
        inputs = torch.stack([b[0] for b in batch])  # [B, V, D, H, W]
        target = torch.stack([b[1] for b in batch])  # [B, H, W]
        mask = torch.stack([b[2] for b in batch])
        optimiser.zero_grad(set_to_none=True)
        loss = loss_of(net, inputs, target, mask)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), MAX_GRADIENT_NORM)
        optimiser.step()
        if average is not None:
            update_average(average, net)
        step += 1
        every = config.get("recalibrate_every", 0)
        if every > 0 and step % every == 0:
            recalibrate(net, calibration)
        value = loss.item()
        recent = ([value] + recent)[:50]
        row = {"step": step, "loss": value, "val_avg_err_px": "", "val_bad1_percent": ""}
        if step % config["validate_every"] == 0 or step == total:
            avg, bad1 = validate(averaged(net, average, calibration), config, val_set)
            row["val_avg_err_px"], row["val_bad1_percent"] = avg, bad1
            log(f"step {step}: validation AvgErr {avg:.3f} px / Bad1 {bad1:.2f} %")
        rows.append(row)
        if step % 25 == 0:
            rate = (time.time() - loop_started) / (step - session_start)
            log(f"step {step}/{total or '?'}: loss {sum(recent) / len(recent):.4f} (mean of the last 50), {rate:.3f} s per step")
        if step % config["checkpoint_every"] == 0 or step == total:
            write_out(args, checkpoint, curves, net, optimiser, average, step, max(plan, total or step), metadata, previous_seconds, loop_started, session_start, rows)
    write_out(args, checkpoint, curves, net, optimiser, average, step, max(plan, total or step), metadata, previous_seconds, loop_started, session_start, rows)
    log(f"done: step {step} in {time.time() - started:.0f} s; finish with `replay train <the run's options> --steps {step} --dir {args.dir}`")


def write_out(args, checkpoint, curves, net, optimiser, average, step, total, metadata, previous_seconds, loop_started, session_start, rows):
    device = torch.device(args.device)
    metadata = dict(metadata)
    metadata["train_config"] = re.sub(r'"steps":\d+', f'"steps":{total}', metadata["train_config"], count=1)
    metadata["train_seconds"] = f"{previous_seconds + time.time() - loop_started:.1f}"
    done_here = step - session_start
    metadata["torch_batch"] = str(args.batch)
    metadata["torch_steps"] = str(int(metadata.get("torch_steps", "0")) + done_here)
    metadata["torch_device"] = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    metadata["torch_version"] = torch.__version__
    save_checkpoint(checkpoint, net, optimiser, step, metadata, average)
    write_curves(curves, rows)


if __name__ == "__main__":
    main()
