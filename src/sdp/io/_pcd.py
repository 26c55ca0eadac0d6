"""PCD files (PCL's format), read with pypcd4: v0.7 ascii, binary and binary_compressed.

Organized files (HEIGHT > 1: one point per pixel or ray) mark a missing return by NaN or by a
point at exactly (0, 0, 0); both become NaN here, dropped and counted by
:func:`sdp.io.read_points`. The header's VIEWPOINT (the sensor's pose) is returned with the
points. sdp writes no PCD.
"""

from __future__ import annotations

import numpy as np

from ._cloud import CloudFileError

__all__ = ["read_pcd"]


def read_pcd(path):
    """``(xyz, fields, None, viewpoint, organized)`` of a PCD file (x, y, z as float64, missing
    returns of an organized file as NaN; other fields in their declared integer types)."""
    from pypcd4 import PointCloud

    pc = PointCloud.from_path(path)
    names = list(pc.fields)
    if not {"x", "y", "z"} <= set(names):
        raise CloudFileError(f"{path}: PCD fields {names} have no x, y, z")
    data = pc.numpy()
    cols = {n: data[:, i] for i, n in enumerate(names)}
    fields = {n: _pcd_column(pc, n, cols[n]) for n in names if n not in ("x", "y", "z")}
    xyz = np.c_[cols["x"], cols["y"], cols["z"]]
    if pc.metadata.height > 1:  # organized scans mark a missing return by NaN or by (0, 0, 0)
        xyz[~xyz.any(axis=1)] = np.nan
    viewpoint = np.asarray(pc.metadata.viewpoint, dtype=np.float64)
    if viewpoint.shape != (7,) or not np.isfinite(viewpoint).all():
        raise CloudFileError(f"{path}: VIEWPOINT must be 7 finite numbers (tx ty tz qw qx qy qz), "
                             f"got {pc.metadata.viewpoint}")
    return xyz, fields, None, viewpoint, pc.metadata.height > 1


def _pcd_column(pc, name, col):
    """pypcd4 returns a float64 matrix; give each field back its declared type (labels, rgba)."""
    dtype = np.dtype(pc.types[list(pc.fields).index(name)])
    return col.astype(dtype) if dtype.kind in "ui" else col
