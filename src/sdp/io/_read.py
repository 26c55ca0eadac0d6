"""Reading a point cloud into memory: :func:`read_points` picks the format's reader by file
extension and returns a :class:`~sdp.io.Cloud`.

Readers use the field's libraries, one module per format: pypcd4 (PCD v0.7 ascii / binary /
binary_compressed), plyfile (PLY), laspy with the lazrs backend (LAS/LAZ, scaled integers kept
exact), NumPy (NPY/NPZ, XYZ/TXT/CSV text), pye57 (E57, :mod:`sdp.io._e57`: every scan with its
pose). Rows whose x, y or z is NaN (sensors' missing
returns, e.g. the organized Kinect PCD files), and points at exactly (0, 0, 0) in organized PCD
files (the other marker of a missing return, e.g. the DLUT laser scans), are dropped and
counted; other per-point fields (``label``, ``rgb``, ``intensity``, ``classification``, …) stay
aligned with the points kept.

Every reader's library error becomes a one-line :class:`~sdp.io.CloudFileError` naming the
file. ``tests/test_fuzz.py`` feeds cut, bit-flipped and random files of every format to the
readers and to ``sdp change``.
"""

from __future__ import annotations

import os
from functools import partial
from pathlib import Path

import numpy as np

from ..errors import MissingDependencyError
from ._cloud import Cloud, CloudFileError, EmptyCloudError, input_format, library_error, unreadable
from ._e57 import read_e57
from ._las import read_las
from ._numpy import read_npy, read_npz
from ._pcd import pcd_image, read_pcd
from ._ply import read_ply
from ._text import read_text

__all__ = ["read_points", "header_point_count"]

_READERS = {"pcd": read_pcd, "ply": read_ply, "las": read_las, "text": read_text, "npy": read_npy,
            "npz": read_npz, "e57": read_e57}


def read_points(path: str | os.PathLike, *, format: str | None = None, fields: bool = True,
                allow_empty: bool = False) -> Cloud:
    """Read a point cloud; the format comes from the extension unless ``format`` is given.

    Parameters
    ----------
    path : path-like
        A ``.pcd``, ``.ply``, ``.las``/``.laz``, ``.xyz``/``.txt``/``.csv``/``.pts``, ``.npy``
        or ``.npz`` file (NPZ: arrays ``xyz``, or ``x``, ``y``, ``z``), or an ``.e57`` scan file
        (every scan moved by its pose, the ``scan`` field and :attr:`Cloud.sensors`; the
        ``scans`` extra).
    format : {"pcd", "ply", "las", "text", "npy", "npz", "e57"}, optional
        Override the extension.
    fields : bool
        False: the coordinates only (``Cloud.fields`` empty but for a multi-scan E57's ``scan``,
        which says where each point was seen from), for callers that need no other dimension (a
        LAS/LAZ file then skips unpacking them).
    allow_empty : bool
        True: a file that holds no point with finite x, y, z gives a cloud of none (a stream's
        frame from a blinded sensor), not an error.

    Raises
    ------
    CloudFileError
        Unknown format, missing file, unreadable content, no x/y/z, or no finite point (unless
        ``allow_empty``).

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> import sdp
    >>> folder = tempfile.TemporaryDirectory()
    >>> xyz = np.random.default_rng(0).random((100, 3))
    >>> path = sdp.write_points(Path(folder.name) / "cloud.ply", xyz, {"high": xyz[:, 2] > 0.5})
    >>> cloud = sdp.read_points(path)
    >>> bool(np.array_equal(cloud.xyz, xyz)), sorted(cloud.fields), cloud.n_dropped
    (True, ['high'], 0)
    >>> folder.cleanup()
    """
    if not isinstance(path, (str, os.PathLike)):
        raise CloudFileError(f"read_points takes a file's path, got {type(path).__name__}")
    path = Path(path)
    fmt = input_format(path, format)
    try:
        reader = partial(read_las, fields=False) if fmt == "las" and not fields else _READERS[fmt]
        xyz, values, las, *pose = reader(path)  # PCD adds its VIEWPOINT and whether organized, E57 its scanners
        if not fields:  # which scanner saw each point stays: it is where the point was seen from
            values = {"scan": values["scan"]} if "scan" in values else {}
        xyz = np.asarray(xyz)
        if xyz.dtype.kind not in "iuf":  # complex, text, structured: no coordinates to cast
            raise CloudFileError(f"{path}: coordinates of type {xyz.dtype} (expected real numbers)")
        with np.errstate(invalid="ignore"):  # a signalling NaN is a missing return as any NaN: dropped below
            xyz = xyz.astype(np.float64, copy=False)
    except EmptyCloudError:
        if not allow_empty:
            raise
        xyz, values, las, pose = np.zeros((0, 3)), {}, None, []
    except (CloudFileError, MissingDependencyError):
        raise
    except MemoryError:  # the file, or what the process already holds (a stream's window of frames)
        size = os.path.getsize(path) if os.path.isfile(path) else 0
        raise CloudFileError(f"{path}: out of memory reading it as {fmt} ({size / 2**20:,.1f} MB on disk, on top of "
                             "what the process already holds)") from None
    except BaseException as exc:  # libraries raise many types on corrupt input (lazrs: Rust panics)
        if not library_error(exc):
            raise
        raise unreadable(path, fmt, exc) from None
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise CloudFileError(f"{path}: expected x, y, z columns, got an array of shape {xyz.shape}")
    finite = None if np.isfinite(xyz).all() else np.isfinite(xyz).all(axis=1)  # rows: 10× the time of the whole
    dropped = 0 if finite is None else int((~finite).sum())
    if dropped:
        xyz = xyz[finite]
        values = {k: v[finite] for k, v in values.items()}
    if len(xyz) == 0 and not allow_empty:
        raise EmptyCloudError(f"{path}: holds no point with finite x, y, z")
    viewpoint, organized, sensors, poles = (list(pose) + [None, False, None, None][len(pose):])[:4]
    image = pixels = None
    if organized and fmt == "pcd":  # the camera's image: which pixels returned (the rest: rays that found nothing)
        image = pcd_image(path)
        if image is not None and image[0] * image[1] == dropped + len(xyz):
            pixels = np.arange(len(xyz)) if finite is None else np.flatnonzero(finite)
        else:
            image = None
    return Cloud(np.ascontiguousarray(xyz), values, path, dropped, las, viewpoint, organized, sensors,
                 0.0 if fmt in ("e57", "las") else None,  # a laser's range noise: millimetres at any range
                 image, pixels, poles=poles)


def header_point_count(path: str | os.PathLike, *, format: str | None = None) -> int | None:
    """The rows a point-cloud file announces in its header, read without its points: LAS/LAZ's
    point count, PCD's ``POINTS``, PLY's vertex count, the sum of an E57 file's scans, an NPY's
    rows; None for formats without one (text, NPZ) or a file that can't tell (its reader then
    says why). Lets a command refuse a file too large for the memory limit before reading it."""
    path = Path(path)
    try:
        kind = input_format(path, format)
        if kind == "las":
            from ._las import las_point_count

            return las_point_count(path)
        if kind == "npy":  # rows of an (n, 3) array, or of a structured one
            shape = np.load(path, mmap_mode="r", allow_pickle=False).shape
            return int(shape[0]) if shape else None
        if kind in ("pcd", "ply"):
            key = b"POINTS" if kind == "pcd" else b"element vertex"
            with open(path, "rb") as f:
                for line in f.read(65_536).split(b"\n")[:200]:
                    if line.startswith(key):
                        return int(line.split()[-1])
            return None
        if kind == "e57":
            from ._e57 import e57_scans

            return sum(scan["points"] for scan in e57_scans(path))
    except Exception:  # the reader says what is wrong
        return None
    return None
