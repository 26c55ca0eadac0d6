"""The ``.sdpf`` file of a :class:`sdp.DensityField` (:meth:`~sdp.DensityField.save`, :meth:`~sdp.DensityField.load`).

A NumPy compressed zip (``numpy.savez_compressed``) of three arrays::

    meta     0-d str, JSON: format "sdp-field", format_version (1), voxel_size, block_origin (3 ints),
             shape_blocks (3 ints), block (8), h, sigma, truncate, n_points, n_dropped, method
    keys     int64 (m, 3): each block's position in the box of blocks (local block coordinates)
    blocks   float32 (m, 512): G at the 8³ nodes of each block (node x, y, z at column x*64 + y*8 + z)

A Boolean result (``method`` "union", "intersection" or "difference") is stored the same way,
its combined F as G := h − F. Files are written under a temporary name and renamed.
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path

import numpy as np

from ..errors import FieldFileError
from ._lattice import BLOCK, Grid

__all__ = ["FORMAT_VERSION", "write", "read"]

#: Version of the ``.sdpf`` file format written by :func:`write`.
FORMAT_VERSION = 1


def write(field, path: str | os.PathLike) -> Path:
    """Write ``field`` (a :class:`sdp.DensityField`) to ``path``; returns the path.

    The file is written under a temporary name and renamed, so a crash never leaves a
    half-written file and an existing file is replaced only once the new one is complete.
    """
    from ..io._output import atomic_path

    path = Path(path)
    meta = {"format": "sdp-field", "format_version": FORMAT_VERSION, "voxel_size": field.voxel_size,
            "block_origin": field.grid.block_origin.tolist(), "shape_blocks": list(field.grid.shape_blocks),
            "block": BLOCK, "h": field.h, "sigma": field.sigma, "truncate": field.truncate,
            "n_points": field.n_points, "n_dropped": field.n_dropped, "method": field.method}
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, meta=np.array(json.dumps(meta)), keys=field.blocks.keys, blocks=field.blocks.values)
    return path


def read(path: str | os.PathLike) -> dict:
    """The contents of a file written by :func:`write`, as the keyword arguments of
    :class:`sdp.DensityField` (``grid``, ``keys``, ``blocks``, ``h``, ``sigma``, ``truncate``,
    ``n_points``, ``n_dropped``, ``method``).

    Raises
    ------
    FieldFileError
        Missing, unreadable, or not sdp-field version :data:`FORMAT_VERSION`.
    """
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):  # an NPY array under the field's name
            raise ValueError("an array, not an archive of a field's arrays")
        with z:
            meta = json.loads(str(z["meta"]))
            keys, blocks = z["keys"], z["blocks"]
    except FileNotFoundError:
        raise FieldFileError(f"{path}: no such file") from None
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, json.JSONDecodeError, EOFError) as exc:
        why = "not an archive of arrays" if "allow_pickle" in str(exc) else f"{type(exc).__name__}: {exc}"
        raise FieldFileError(f"{path}: not a readable sdp field file ({why})") from None
    if meta.get("format") != "sdp-field" or meta.get("format_version") != FORMAT_VERSION:
        raise FieldFileError(f"{path}: format {meta.get('format')!r} version {meta.get('format_version')!r}; "
                             f"this sdp reads sdp-field version {FORMAT_VERSION}")
    grid = Grid(meta["voxel_size"], np.asarray(meta["block_origin"], np.int64), tuple(meta["shape_blocks"]))
    return dict(grid=grid, keys=keys, blocks=blocks, h=meta["h"], sigma=meta["sigma"], truncate=meta["truncate"],
                n_points=meta["n_points"], n_dropped=meta["n_dropped"], method=meta["method"])
