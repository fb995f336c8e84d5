"""Writes the Human3.6M pose fixtures of crates/mvmp-data/tests/fixtures/h36m with cdflib, the library
the Human3.6M tool-chains read these files with, so that mvmp's CDF reader is tested on files it did not
write. Each file holds the variable `Pose` as the dataset's D3_Positions files do: 32 joints x (x, y, z)
millimetres per frame. Joint j of frame f is (1000 + 10 j + 5 f, -400 + 20 (j % 3), 900 - 25 j + f).

    pip install cdflib numpy && python3 scripts/h36m_cdf_fixtures.py

It also writes a camera-parameters.json in the published layout with made-up cameras.
"""
import os

import numpy as np
from cdflib.cdfwrite import CDF

OUT = os.path.join(os.path.dirname(__file__), "..", "crates", "mvmp-data", "tests", "fixtures", "h36m")
FRAMES = 5
CDF_FLOAT, CDF_DOUBLE = 44, 45


def poses(frames):
    j = np.arange(32)[None, :]
    f = np.arange(frames)[:, None]
    x = 1000 + 10 * j + 5 * f
    y = -400 + 20 * (j % 3) + 0 * f
    z = 900 - 25 * j + f
    return np.stack([x, y, z], axis=-1).reshape(frames, 96)


def write(name, data, data_type, majority="Row_major", compress=0, var_type="zVariable", one_record=True):
    path = os.path.join(OUT, name)
    if os.path.exists(path):
        os.remove(path)
    spec = {"Majority": majority, "Compressed": 0}
    if var_type == "rVariable":
        spec["rDim_sizes"] = [96]
    cdf = CDF(path, cdf_spec=spec)
    var = {
        "Variable": "Pose",
        "Var_Type": var_type,
        "Data_Type": data_type,
        "Num_Elements": 1,
        "Rec_Vary": True,
        "Compress": compress,
    }
    if one_record:
        # As in the dataset: one record holding a [frames, 96] array. cdflib writes the buffer as given,
        # so a column-major file gets the array in column-major (Fortran) element order.
        var["Dim_Sizes"] = [data.shape[0], 96]
        values = data[None] if majority == "Row_major" else np.ascontiguousarray(data.T)[None]
    else:
        # One record per frame.
        var["Dim_Sizes"] = [96]
        values = data
    if var_type == "rVariable":
        var.pop("Dim_Sizes")
        var["Dim_Vary"] = [True]
    cdf.write_var(var, var_attrs={}, var_data=values)
    cdf.close()


os.makedirs(OUT, exist_ok=True)
p = poses(FRAMES)
write("pose_float_one_record.cdf", p.astype(np.float32), CDF_FLOAT)
write("pose_double_gzip.cdf", p.astype(np.float64), CDF_DOUBLE, compress=6)
write("pose_double_column_major.cdf", p.astype(np.float64), CDF_DOUBLE, majority="Column_major")
write("pose_double_rvariable.cdf", p.astype(np.float64), CDF_DOUBLE, var_type="rVariable", one_record=False)


def look_at(centre, target):
    z = (target - centre) / np.linalg.norm(target - centre)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


# camera-parameters.json in the published layout (not the dataset's numbers): the four camera ids on a
# 4 m circle, 1.5 m up, looking at (0, 0, 0.9 m), for subjects S9 and S11; millimetres.
cameras = ["54138969", "55011271", "58860488", "60457274"]
intrinsics, extrinsics = {}, {}
for s in ["S9", "S11"]:
    extrinsics[s] = {}
    for i, cam in enumerate(cameras):
        a = i * np.pi / 2 + 0.4
        c = np.array([4000 * np.cos(a), 4000 * np.sin(a), 1500.0])
        r = look_at(c, np.array([0.0, 0.0, 900.0]))
        t = -r @ c
        extrinsics[s][cam] = {"R": r.tolist(), "t": [[v] for v in t]}
        intrinsics[cam] = {
            "calibration_matrix": [[1145.0, 0.0, 500.0], [0.0, 1145.0, 500.0], [0.0, 0.0, 1.0]],
            "distortion": [-0.2, 0.24, -0.001, -0.002, -0.002],
        }
import json

with open(os.path.join(OUT, "camera-parameters.json"), "w") as f:
    json.dump({"intrinsics": intrinsics, "extrinsics": extrinsics}, f, indent=1)
