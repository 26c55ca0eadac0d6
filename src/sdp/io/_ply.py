"""PLY files, with plyfile: points (vertices with any scalar properties) read and written, binary
PLY's vertices memory-mapped for :class:`sdp.io.PointSource`, and triangle meshes written. A
vertex list property (a list per point, such as the views a photogrammetry tool saw it in) is
left out with a notice, as Open3D and CloudCompare leave it: no field holds a list per point."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ._cloud import CloudFileError, notice

__all__ = ["read_ply", "write_ply", "write_ply_mesh", "ply_vertices", "ply_is_binary"]


def read_ply(path):
    """``(xyz, fields, None)`` of a PLY file's vertex element (other scalar properties as fields;
    list properties left out, with a :func:`~sdp.io._cloud.notice`)."""
    from plyfile import PlyData, PlyListProperty

    with warnings.catch_warnings():  # an ASCII PLY's empty list: NumPy's warning, of a property left out below
        warnings.filterwarnings("ignore", "loadtxt: input contained no data", UserWarning)
        ply = PlyData.read(str(path))
    if "vertex" not in ply:
        raise CloudFileError(f"{path}: PLY file has no vertex element")
    v = ply["vertex"].data
    names = v.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise CloudFileError(f"{path}: PLY vertices have no x, y, z (properties: {list(names)})")
    lists = [p.name for p in ply["vertex"].properties if isinstance(p, PlyListProperty)]
    if lists:
        notice(f"{path}: vertex list propert{'ies' if len(lists) > 1 else 'y'} {', '.join(map(repr, lists))} left "
               "out (a list per point, which no field holds; Open3D and CloudCompare leave them out too)")
    fields = {n: np.asarray(v[n]) for n in names if n not in ("x", "y", "z", *lists)}
    return np.c_[v["x"], v["y"], v["z"]], fields, None


def write_ply(tmp: Path, xyz: np.ndarray, fields: dict[str, np.ndarray]) -> None:
    """Write vertices x, y, z and a property per field, each in its numeric type (booleans as
    ``u1``; 64-bit integers, which PLY lacks, as 32-bit where their values fit, else ``f8``;
    other types as ``f8``), to ``tmp`` as binary PLY in the machine's byte order."""
    from plyfile import PlyData, PlyElement

    cols = [("x", xyz[:, 0]), ("y", xyz[:, 1]), ("z", xyz[:, 2])] + list(fields.items())
    arr = np.empty(len(xyz), dtype=[(n, _ply_type(v)) for n, v in cols])
    for n, v in cols:
        arr[n] = v
    PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp))


def _ply_type(v: np.ndarray) -> str:
    v = np.asarray(v)
    if v.dtype == bool:
        return "u1"
    if v.dtype.kind in "ui" and v.dtype.itemsize == 8:
        narrow = np.dtype(v.dtype.kind + "4")
        info = np.iinfo(narrow)
        return narrow.str.lstrip("<>=|") if not v.size or info.min <= v.min() and v.max() <= info.max else "f8"
    return v.dtype.str.lstrip("<>=|") if v.dtype.kind in "uif" else "f8"


def write_ply_mesh(tmp: Path, v: np.ndarray, f: np.ndarray) -> None:
    """Write vertices ``v`` (n, 3) float64 and triangles ``f`` (m, 3) (as int32 vertex indices)."""
    from plyfile import PlyData, PlyElement

    verts = np.rec.fromarrays(v.T, names="x,y,z")
    faces = np.empty(len(f), dtype=[("vertex_indices", "i4", (3,))])
    faces["vertex_indices"] = f
    PlyData([PlyElement.describe(verts, "vertex"), PlyElement.describe(faces, "face")]).write(str(tmp))


def ply_vertices(path):
    """The vertex element's records of a binary PLY file, memory-mapped."""
    from plyfile import PlyData

    return PlyData.read(str(path), mmap=True)["vertex"].data


def ply_is_binary(path) -> bool:
    """Whether the PLY header (its first 200 bytes) declares a binary format."""
    with open(path, "rb") as f:
        head = f.read(200).split(b"\n")
    return any(line.startswith(b"format binary") for line in head)
