#!/usr/bin/env python3
"""Reference output of one DINOv2 ViT block, computed independently with numpy.

Writes crates/mvmp-backbone/tests/fixtures/vit_block.json. The weights follow a closed formula (the
Rust test builds the same ones), in PyTorch's layout: Linear weight [out, in], y = x W^T + b.
Block (DINOv2): x = x + ls1 * proj(attn(norm1(x))); x = x + ls2 * fc2(gelu(fc1(norm2(x)))), LayerNorm eps
1e-6, exact (erf) GELU, qkv rows [q; k; v] ordered by head, softmax(q k^T / sqrt(d)) v.
Usage: python scripts/vit_block_fixture.py
"""
import json
import math
import os

import numpy as np

C, HEADS, N, HIDDEN = 8, 2, 5, 32


def formula(shape, a, b, scale):
    n = int(np.prod(shape))
    i = np.arange(n, dtype=np.float64)
    return (np.sin(i * a + b) * scale).reshape(shape)


def weights():
    return {
        "x": formula((N, C), 0.37, 0.1, 1.0),
        "norm1.weight": 1.0 + formula((C,), 0.5, 0.2, 0.1),
        "norm1.bias": formula((C,), 0.7, 0.3, 0.1),
        "attn.qkv.weight": formula((3 * C, C), 0.11, 0.4, 0.3),
        "attn.qkv.bias": formula((3 * C,), 0.13, 0.5, 0.1),
        "attn.proj.weight": formula((C, C), 0.17, 0.6, 0.3),
        "attn.proj.bias": formula((C,), 0.19, 0.7, 0.1),
        "ls1.gamma": 0.5 + formula((C,), 0.23, 0.8, 0.2),
        "norm2.weight": 1.0 + formula((C,), 0.29, 0.9, 0.1),
        "norm2.bias": formula((C,), 0.31, 1.0, 0.1),
        "mlp.fc1.weight": formula((HIDDEN, C), 0.41, 1.1, 0.3),
        "mlp.fc1.bias": formula((HIDDEN,), 0.43, 1.2, 0.1),
        "mlp.fc2.weight": formula((C, HIDDEN), 0.47, 1.3, 0.2),
        "mlp.fc2.bias": formula((C,), 0.53, 1.4, 0.1),
        "ls2.gamma": 0.5 + formula((C,), 0.59, 1.5, 0.2),
    }


def layer_norm(x, g, b, eps=1e-6):
    mu = x.mean(-1, keepdims=True)
    var = ((x - mu) ** 2).mean(-1, keepdims=True)
    return (x - mu) / np.sqrt(var + eps) * g + b


def block(w):
    x = w["x"]
    h = layer_norm(x, w["norm1.weight"], w["norm1.bias"])
    qkv = h @ w["attn.qkv.weight"].T + w["attn.qkv.bias"]
    d = C // HEADS
    qkv = qkv.reshape(N, 3, HEADS, d).transpose(1, 2, 0, 3)  # [3, heads, N, d]
    q, k, v = qkv[0], qkv[1], qkv[2]
    s = q @ k.transpose(0, 2, 1) / math.sqrt(d)
    s = np.exp(s - s.max(-1, keepdims=True))
    s = s / s.sum(-1, keepdims=True)
    o = (s @ v).transpose(1, 0, 2).reshape(N, C)
    o = o @ w["attn.proj.weight"].T + w["attn.proj.bias"]
    x = x + w["ls1.gamma"] * o
    h = layer_norm(x, w["norm2.weight"], w["norm2.bias"])
    h = h @ w["mlp.fc1.weight"].T + w["mlp.fc1.bias"]
    erf = np.vectorize(math.erf)
    h = 0.5 * h * (1.0 + erf(h / math.sqrt(2.0)))
    h = h @ w["mlp.fc2.weight"].T + w["mlp.fc2.bias"]
    return x + w["ls2.gamma"] * h


def main():
    w = weights()
    out = {"C": C, "heads": HEADS, "N": N, "hidden": HIDDEN, "x": w["x"].tolist(), "y": block(w).tolist()}
    path = os.path.join(os.path.dirname(__file__), "..", "crates", "mvmp-backbone", "tests", "fixtures", "vit_block.json")
    with open(path, "w") as f:
        json.dump(out, f, indent=1)
    print("wrote", os.path.normpath(path))


if __name__ == "__main__":
    main()
