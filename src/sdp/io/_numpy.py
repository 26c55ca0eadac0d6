"""NumPy files: NPY (one (n, 3) array) and NPZ (arrays ``xyz``, or ``x``, ``y``, ``z``, and
per-point fields beside them), read without pickles; NPZ written compressed."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._cloud import CloudFileError

__all__ = ["read_npy", "read_npz", "write_npz"]


def read_npy(path):
    """``(xyz, {}, None)`` of an NPY file (its shape is checked by the caller)."""
    return np.load(path, allow_pickle=False), {}, None


def read_npz(path):
    """``(xyz, fields, None)`` of an NPZ file: its other arrays as long as ``xyz`` are fields."""
    with np.load(path, allow_pickle=False) as z:
        if "xyz" in z:
            xyz = z["xyz"]
        elif {"x", "y", "z"} <= set(z.files):
            xyz = np.c_[z["x"], z["y"], z["z"]]
        else:
            raise CloudFileError(f"{path}: NPZ needs an array 'xyz' or arrays 'x', 'y', 'z' (has {z.files})")
        fields = {k: z[k] for k in z.files if k not in ("xyz", "x", "y", "z") and len(z[k]) == len(xyz)}
    return xyz, fields, None


def write_npz(tmp: Path, xyz: np.ndarray, fields: dict[str, np.ndarray]) -> None:
    """Write ``xyz`` and the fields, each as its own array, compressed."""
    np.savez_compressed(tmp, xyz=xyz, **fields)
