"""Reads MFuseNet weight files with the reference safetensors client (numpy) and checks every
tensor name, shape and dtype against the state_dict of the authors' FuseNetwork, written out
here independently of our Rust code from the architecture (weihaosky/MFuseNet, network.py):
convbn3d = Sequential(Conv3d(bias=False), BatchNorm3d), convTbn3d likewise with ConvTranspose3d
(weight [in, out, k, k, k]), classify = Conv3d(4, 1, 3) with bias.

Usage: check_weights.py VIEWS FILE [VIEWS FILE ...]; prints one line per file, exits 1 on a
mismatch."""

import math
import sys

import numpy as np
from safetensors import safe_open
from safetensors.numpy import load_file


def state_dict(n_views):
    layers = [
        ("feature.0", "conv", 1, 4, 7),
        ("feature.2", "conv", 4, 4, 5),
        ("feature.4", "conv", 4, 4, 5),
        ("feature.6", "conv", 4, 4, 3),
        ("concat", "conv", 4 * n_views, 4, 7),
        ("down1", "conv", 4, 4, 3),
        ("dconv1", "conv", 4, 4, 3),
        ("down2", "conv", 4, 4, 3),
        ("dconv21", "conv", 4, 4, 7),
        ("dconv22", "conv", 4, 4, 3),
        ("up1", "transposed", 4, 4, 3),
        ("uconv1", "conv", 8, 4, 3),
        ("up2", "transposed", 4, 4, 3),
        ("uconv2", "conv", 8, 4, 7),
        ("distill1", "conv", 4, 4, 5),
    ]
    expected = {}
    for name, kind, cin, cout, k in layers:
        shape = (cin, cout, k, k, k) if kind == "transposed" else (cout, cin, k, k, k)
        expected[f"{name}.0.weight"] = shape
        for field in ("weight", "bias", "running_mean", "running_var"):
            expected[f"{name}.1.{field}"] = (cout,)
        expected[f"{name}.1.num_batches_tracked"] = ()
    expected["classify.weight"] = (1, 4, 3, 3, 3)
    expected["classify.bias"] = (1,)
    return expected


def trainable(expected):
    return sum(
        math.prod(shape)
        for name, shape in expected.items()
        if not name.endswith(("running_mean", "running_var", "num_batches_tracked"))
    )


def check(n_views, path):
    expected = state_dict(n_views)
    tensors = load_file(path)
    problems = []
    for name in sorted(set(expected) | set(tensors)):
        if name not in tensors:
            problems.append(f"missing {name}")
        elif name not in expected:
            problems.append(f"unexpected {name}")
        elif tuple(tensors[name].shape) != expected[name]:
            problems.append(f"{name}: shape {tuple(tensors[name].shape)}, expected {expected[name]}")
        elif name.endswith("num_batches_tracked"):
            if tensors[name].dtype != np.int64:
                problems.append(f"{name}: dtype {tensors[name].dtype}")
        elif tensors[name].dtype != np.float32 or not np.all(np.isfinite(tensors[name])):
            problems.append(f"{name}: dtype {tensors[name].dtype} or non-finite values")
        elif name.endswith("running_var") and np.any(tensors[name] < 0):
            problems.append(f"{name}: negative variance")
    with safe_open(path, framework="numpy") as f:
        metadata = f.metadata() or {}
    for key in ("variant", "views", "input_order", "input_normalisation", "input_steps_per_unit", "estimate", "made_by", "steps"):
        if key not in metadata:
            problems.append(f"metadata has no '{key}'")
    if metadata.get("estimate") not in (None, "soft-argmin", "refine"):
        problems.append(f"metadata estimate = {metadata.get('estimate')!r}, expected soft-argmin or refine")
    if metadata.get("views") != str(n_views):
        problems.append(f"metadata views = {metadata.get('views')}, expected {n_views}")
    parameters = trainable(expected)
    if problems:
        print(f"FAIL {path}: " + "; ".join(problems))
        return False
    print(f"ok {path}: {len(tensors)} tensors, {parameters} trainable parameters, variant {metadata['variant']}")
    return True


def main():
    args = sys.argv[1:]
    if not args or len(args) % 2:
        print(__doc__)
        return 2
    ok = all([check(int(args[i]), args[i + 1]) for i in range(0, len(args), 2)])
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
