"""Reading and writing point clouds and fields, by file extension.

Readers use the field's libraries: pypcd4 (PCD v0.7 ascii / binary / binary_compressed),
plyfile (PLY), laspy with the lazrs backend (LAS/LAZ, scaled integers kept exact), NumPy
(NPY/NPZ, XYZ/TXT/CSV text). Rows whose x, y or z is NaN (sensors' missing returns, e.g. the
organized Kinect PCD files) are dropped and counted; other per-point fields (``label``,
``rgb``, ``intensity``, ``classification``, …) stay aligned with the points kept.
"""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import SDPError

__all__ = ["Cloud", "read_points", "CloudFileError", "FORMATS", "atomic_path"]

#: Extension → format name understood by :func:`read_points`.
FORMATS = {".pcd": "pcd", ".ply": "ply", ".las": "las", ".laz": "las", ".xyz": "text", ".txt": "text",
           ".csv": "text", ".pts": "text", ".npy": "npy", ".npz": "npz"}


class CloudFileError(SDPError, OSError):
    """A point-cloud file can't be read: unknown format, corrupt, empty, or without x/y/z."""


@dataclass
class Cloud:
    """Points read from a file.

    Attributes
    ----------
    xyz : ndarray (n, 3) float64
        World coordinates of the rows kept.
    fields : dict of str to ndarray
        Other per-point fields, aligned with ``xyz``.
    path : Path or None
        The file read.
    n_dropped : int
        Rows left out because x, y or z was NaN or infinite.
    las : object
        The ``laspy.LasData`` of LAS/LAZ input (kept so outputs can keep every dimension),
        else None.
    """

    xyz: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    path: Path | None = None
    n_dropped: int = 0
    las: object = None

    def __len__(self) -> int:
        return len(self.xyz)


def read_points(path: str | os.PathLike, *, format: str | None = None) -> Cloud:
    """Read a point cloud; the format comes from the extension unless ``format`` is given.

    Parameters
    ----------
    path : path-like
        A ``.pcd``, ``.ply``, ``.las``/``.laz``, ``.xyz``/``.txt``/``.csv``/``.pts``, ``.npy``
        or ``.npz`` file (NPZ: arrays ``xyz``, or ``x``, ``y``, ``z``).
    format : {"pcd", "ply", "las", "text", "npy", "npz"}, optional
        Override the extension.

    Raises
    ------
    CloudFileError
        Unknown format, missing file, unreadable content, no x/y/z, or no finite point.
    """
    path = Path(path)
    fmt = format or FORMATS.get(path.suffix.lower())
    if fmt not in set(FORMATS.values()):
        raise CloudFileError(f"{path}: unknown point-cloud format {path.suffix or '(no extension)'!r}; "
                             f"use one of {', '.join(sorted(FORMATS))} or pass format=")
    if not path.is_file():
        raise CloudFileError(f"{path}: no such file")
    try:
        xyz, fields, las = _READERS[fmt](path)
    except CloudFileError:
        raise
    except Exception as exc:  # libraries raise many types on corrupt input
        raise CloudFileError(f"{path}: can't read as {fmt} ({type(exc).__name__}: {exc})") from None
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise CloudFileError(f"{path}: expected x, y, z columns, got an array of shape {xyz.shape}")
    finite = np.isfinite(xyz).all(axis=1)
    dropped = int((~finite).sum())
    if dropped:
        xyz = xyz[finite]
        fields = {k: v[finite] for k, v in fields.items()}
    if len(xyz) == 0:
        raise CloudFileError(f"{path}: holds no point with finite x, y, z")
    return Cloud(np.ascontiguousarray(xyz), fields, path, dropped, las)


def _read_pcd(path):
    from pypcd4 import PointCloud

    pc = PointCloud.from_path(path)
    names = list(pc.fields)
    if not {"x", "y", "z"} <= set(names):
        raise CloudFileError(f"{path}: PCD fields {names} have no x, y, z")
    data = pc.numpy()
    cols = {n: data[:, i] for i, n in enumerate(names)}
    fields = {n: _pcd_column(pc, n, cols[n]) for n in names if n not in ("x", "y", "z")}
    return np.c_[cols["x"], cols["y"], cols["z"]], fields, None


def _pcd_column(pc, name, col):
    """pypcd4 returns a float64 matrix; give each field back its declared type (labels, rgba)."""
    dtype = np.dtype(pc.types[list(pc.fields).index(name)])
    return col.astype(dtype) if dtype.kind in "ui" else col


def _read_ply(path):
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    if "vertex" not in ply:
        raise CloudFileError(f"{path}: PLY file has no vertex element")
    v = ply["vertex"].data
    names = v.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise CloudFileError(f"{path}: PLY vertices have no x, y, z (properties: {list(names)})")
    fields = {n: np.asarray(v[n]) for n in names if n not in ("x", "y", "z")}
    return np.c_[v["x"], v["y"], v["z"]], fields, None


def _read_las(path):
    import laspy

    las = laspy.read(str(path))
    xyz = np.c_[las.x, las.y, las.z]  # scaled and offset, float64: large coordinates stay exact
    fields = {d: np.asarray(las[d]) for d in las.point_format.dimension_names if d not in ("X", "Y", "Z")}
    return xyz, fields, las


def _read_text(path):
    with open(path, encoding="utf-8", errors="replace") as fh:
        sample = fh.read(4096)
    delimiter = "," if "," in sample else None
    first = sample.splitlines()[0] if sample else ""
    skip = 0 if _is_numeric_row(first, delimiter) else 1
    arr = np.loadtxt(path, delimiter=delimiter, skiprows=skip, ndmin=2)
    if arr.shape[1] < 3:
        raise CloudFileError(f"{path}: expected at least 3 columns (x y z), found {arr.shape[1]}")
    names = [n.strip().lower() for n in first.replace(",", " ").split()] if skip else []
    fields = {(names[i] if i < len(names) else f"column{i}"): arr[:, i] for i in range(3, arr.shape[1])}
    return arr[:, :3], fields, None


def _is_numeric_row(line: str, delimiter) -> bool:
    try:
        [float(x) for x in line.split(delimiter) if x.strip()]
        return bool(line.strip())
    except ValueError:
        return False


def _read_npy(path):
    return np.load(path, allow_pickle=False), {}, None


def _read_npz(path):
    with np.load(path, allow_pickle=False) as z:
        if "xyz" in z:
            xyz = z["xyz"]
        elif {"x", "y", "z"} <= set(z.files):
            xyz = np.c_[z["x"], z["y"], z["z"]]
        else:
            raise CloudFileError(f"{path}: NPZ needs an array 'xyz' or arrays 'x', 'y', 'z' (has {z.files})")
        fields = {k: z[k] for k in z.files if k not in ("xyz", "x", "y", "z") and len(z[k]) == len(xyz)}
    return xyz, fields, None


_READERS = {"pcd": _read_pcd, "ply": _read_ply, "las": _read_las, "text": _read_text, "npy": _read_npy,
            "npz": _read_npz}


@contextmanager
def atomic_path(path: str | os.PathLike, *, inputs=()):
    """Yield a temporary path beside ``path``; rename it to ``path`` when the block succeeds.

    Refuses to overwrite any of ``inputs``; nothing is left behind on failure.
    """
    path = Path(path)
    for src in inputs:
        if Path(src).exists() and path.exists() and path.resolve() == Path(src).resolve():
            raise SDPError(f"{path}: refusing to overwrite an input file; choose another output name")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent if str(path.parent) else ".")
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)
