"""Reads MFuseNet weight files with the reference safetensors client (numpy) and checks every
tensor name, shape and dtype against the state_dict of the authors' FuseNetwork, written out
here independently of our Rust code from the architecture (weihaosky/MFuseNet, network.py):
convbn3d = Sequential(Conv3d(bias=False), BatchNorm3d), convTbn3d likewise with ConvTranspose3d
(weight [in, out, k, k, k]), classify = Conv3d(4, 1, 3) with bias. A file whose metadata says
`architecture = lite` is checked against the lite kernels (feature 5, 3, 3, 3; concat 3; uconv2 3;
distill1 3; the rest as the paper's). A file whose metadata has a `sharp_spec` takes each view's
sharp volume into `concat` beside its four features (`concat.0.weight` with 5·N input channels).

Usage: check_weights.py VIEWS FILE [VIEWS FILE ...]; prints one line per file, exits 1 on a
mismatch."""

import math
import sys

import numpy as np
from safetensors import safe_open
from safetensors.numpy import load_file


KERNELS = {
    # feature.0, .2, .4, .6, concat, dconv21, uconv2, distill1
    "paper": (7, 5, 5, 3, 7, 7, 7, 5),
    "lite": (5, 3, 3, 3, 3, 7, 3, 3),
}


def state_dict(n_views, architecture="paper", sharp=False):
    f0, f2, f4, f6, kc, k21, ku2, kd1 = KERNELS[architecture]
    layers = [
        ("feature.0", "conv", 1, 4, f0),
        ("feature.2", "conv", 4, 4, f2),
        ("feature.4", "conv", 4, 4, f4),
        ("feature.6", "conv", 4, 4, f6),
        ("concat", "conv", (5 if sharp else 4) * n_views, 4, kc),
        ("down1", "conv", 4, 4, 3),
        ("dconv1", "conv", 4, 4, 3),
        ("down2", "conv", 4, 4, 3),
        ("dconv21", "conv", 4, 4, k21),
        ("dconv22", "conv", 4, 4, 3),
        ("up1", "transposed", 4, 4, 3),
        ("uconv1", "conv", 8, 4, 3),
        ("up2", "transposed", 4, 4, 3),
        ("uconv2", "conv", 8, 4, ku2),
        ("distill1", "conv", 4, 4, kd1),
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
    with safe_open(path, framework="numpy") as f:
        metadata = f.metadata() or {}
    architecture = metadata.get("architecture", "paper")
    if architecture not in KERNELS:
        print(f"FAIL {path}: metadata architecture = {architecture!r}, expected one of {sorted(KERNELS)}")
        return False
    sharp = "sharp_spec" in metadata
    expected = state_dict(n_views, architecture, sharp)
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
    print(f"ok {path}: {len(tensors)} tensors, {parameters} trainable parameters, variant {metadata['variant']}, architecture {architecture}{', sharp volumes' if sharp else ''}")
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
