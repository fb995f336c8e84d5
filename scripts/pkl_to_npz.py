#!/usr/bin/env python3
"""Convert an official SMPL-X .pkl body model to the .npz layout that mvmp reads.

Usage: python scripts/pkl_to_npz.py SMPLX_NEUTRAL.pkl [OUT.npz]

Needs numpy only (and scipy if the pickle stores a sparse J_regressor). Keys whose values are not arrays
(dictionaries such as joint2num) are stored as object arrays, which mvmp skips, exactly as in the
official npz files.
"""
import pickle
import sys

import numpy as np


def main() -> int:
    if len(sys.argv) not in (2, 3):
        print(__doc__, file=sys.stderr)
        return 2
    src = sys.argv[1]
    out = sys.argv[2] if len(sys.argv) == 3 else src.rsplit(".", 1)[0] + ".npz"
    with open(src, "rb") as f:
        data = pickle.load(f, encoding="latin1")
    arrays = {}
    for key, value in data.items():
        if hasattr(value, "toarray"):  # scipy sparse (J_regressor in some releases)
            value = value.toarray()
        arrays[key] = np.asarray(value)
    np.savez(out, **arrays)
    print(f"wrote {out}: {', '.join(sorted(arrays))}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
