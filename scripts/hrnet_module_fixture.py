#!/usr/bin/env python3
"""Reference output of one HRNet HighResolutionModule (2 branches, 1 BasicBlock each, with fuse layers),
computed independently with numpy, batch norm in inference mode.

Writes crates/mvmp-backbone/tests/fixtures/hrnet_module.json. Weights follow a closed formula that the
Rust test reproduces (PyTorch layouts: conv weight [out, in, kh, kw]; BN eps 1e-5).
Module (pose_hrnet.py): each branch runs its blocks (conv3x3-BN-ReLU-conv3x3-BN + identity, ReLU); output i
sums, over branches j, x_j itself (j == i), conv1x1-BN then nearest upsampling (j > i), or stride-2
conv3x3-BN chains (j < i), then ReLU.
Usage: python scripts/hrnet_module_fixture.py
"""
import json
import math
import os

import numpy as np

C0, C1, H, W = 8, 16, 8, 12


def formula(shape, a, b, scale):
    n = int(np.prod(shape))
    i = np.arange(n, dtype=np.float64)
    return (np.sin(i * a + b) * scale).reshape(shape)


def conv(x, w, stride, pad):
    ci, h, wd = x.shape
    co, _, kh, kw = w.shape
    xp = np.pad(x, ((0, 0), (pad, pad), (pad, pad)))
    oh = (h + 2 * pad - kh) // stride + 1
    ow = (wd + 2 * pad - kw) // stride + 1
    out = np.zeros((co, oh, ow))
    for ky in range(kh):
        for kx in range(kw):
            patch = xp[:, ky:ky + stride * oh:stride, kx:kx + stride * ow:stride]
            out += np.einsum("oc,chw->ohw", w[:, :, ky, kx], patch)
    return out


def bn(x, name, c):
    g = 1.0 + formula((c,), 0.3, len(name) * 0.1, 0.1)
    b = formula((c,), 0.7, len(name) * 0.2, 0.1)
    m = formula((c,), 1.1, len(name) * 0.3, 0.1)
    v = 1.0 + np.abs(formula((c,), 1.3, len(name) * 0.4, 0.5))
    return (x - m[:, None, None]) / np.sqrt(v[:, None, None] + 1e-5) * g[:, None, None] + b[:, None, None]


def cw(name, co, ci, k):
    return formula((co, ci, k, k), 0.37 + len(name) * 0.01, len(name) * 0.05, 0.2)


def relu(x):
    return np.maximum(x, 0.0)


def block(x, p, c):
    r = relu(bn(conv(x, cw(p + ".conv1", c, c, 3), 1, 1), p + ".bn1", c))
    r = bn(conv(r, cw(p + ".conv2", c, c, 3), 1, 1), p + ".bn2", c)
    return relu(r + x)


def main():
    x0 = formula((C0, H, W), 0.13, 0.5, 1.0)
    x1 = formula((C1, H // 2, W // 2), 0.17, 0.9, 1.0)
    y0 = block(x0, "branches.0.0", C0)
    y1 = block(x1, "branches.1.0", C1)
    up = bn(conv(y1, cw("fuse_layers.0.1.0", C0, C1, 1), 1, 0), "fuse_layers.0.1.1", C0)
    up = up.repeat(2, axis=1).repeat(2, axis=2)
    out0 = relu(y0 + up)
    down = bn(conv(y0, cw("fuse_layers.1.0.0.0", C1, C0, 3), 2, 1), "fuse_layers.1.0.0.1", C1)
    out1 = relu(down + y1)
    res = {"x0": x0.tolist(), "x1": x1.tolist(), "y0": out0.tolist(), "y1": out1.tolist()}
    path = os.path.join(os.path.dirname(__file__), "..", "crates", "mvmp-backbone", "tests", "fixtures", "hrnet_module.json")
    with open(path, "w") as f:
        json.dump(res, f)
    print("wrote", os.path.normpath(path))


if __name__ == "__main__":
    main()
