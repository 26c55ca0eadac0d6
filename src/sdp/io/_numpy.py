"""NumPy files: NPY (one (n, 3) array) and NPZ (arrays ``xyz``, or ``x``, ``y``, ``z``, and
per-point fields beside them), read without pickles; NPZ written compressed."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._cloud import CloudFileError

__all__ = ["read_npy", "read_npz", "write_npz"]


def read_npy(path):
    """``(xyz, fields, None)`` of an NPY file: an (n, 3) array (its shape and type are checked by
    the caller), or a structured array with fields x, y, z (its other fields kept)."""
    a = np.load(path, allow_pickle=False)
    if not isinstance(a, np.ndarray):  # np.load opens a zip archive whatever its name
        a.close()
        raise CloudFileError(f"{path}: an NPZ archive, not an NPY array: name it .npz (or give format npz)")
    if a.dtype.names is None:
        return a, {}, None
    if not {"x", "y", "z"} <= set(a.dtype.names) or a.ndim != 1:
        raise CloudFileError(f"{path}: a structured array needs fields x, y, z in one dimension (has "
                             f"{list(a.dtype.names)}, shape {a.shape})")
    fields = {k: a[k] for k in a.dtype.names if k not in ("x", "y", "z") and a[k].ndim == 1}
    return np.c_[a["x"], a["y"], a["z"]], fields, None


def read_npz(path):
    """``(xyz, fields, None)`` of an NPZ file: its other arrays as long as ``xyz`` are fields."""
    with np.load(path, allow_pickle=False) as z:
        if "xyz" in z:
            xyz = z["xyz"]
        elif {"x", "y", "z"} <= set(z.files):
            xyz = np.c_[z["x"], z["y"], z["z"]]
        else:
            raise CloudFileError(f"{path}: NPZ needs an array 'xyz' or arrays 'x', 'y', 'z' (has {z.files})")
        fields = {k: z[k] for k in z.files if k not in ("xyz", "x", "y", "z")}
        fields = {k: v for k, v in fields.items() if v.ndim and len(v) == len(xyz)}  # not 0-d metadata
    return xyz, fields, None


def write_npz(tmp: Path, xyz: np.ndarray, fields: dict[str, np.ndarray]) -> None:
    """Write ``xyz`` and the fields, each as its own array, compressed.

    Written through an open file: given a name, NumPy appends ``.npz`` to any name that does not
    end in exactly that (``OUT.NPZ``), and the data would land beside the file named."""
    with open(tmp, "wb") as fh:
        np.savez_compressed(fh, xyz=xyz, **fields)
