"""ASTM E57 files (terrestrial laser scans): every scan of a file in one frame, with its pose.

An E57 file holds one or more scans (``data3D``), each with its pose (a rotation quaternion and
a translation from the scan's own frame to the file's) and its points in Cartesian or spherical
coordinates, often structured (``rowIndex``, ``columnIndex``: the scanner's grid), with intensity
and colour. :func:`read_e57` reads every scan, moves its points by its pose, keeps intensity
(``intensity``), colour (``red``, ``green``, ``blue``) and the grid (``row``, ``column``) as fields,
marks the points flagged invalid (``cartesianInvalidState`` / ``sphericalInvalidState`` ≠ 0) as
NaN so that :func:`sdp.io.read_points` drops and counts them, and records per point which scan
saw it (the ``scan`` field), where each scanner stood (the poses' translations: a scanner sits
at its scan frame's origin; a file of several scans, some without a pose, records no scanner) and
which way its vertical axis points (the pose's rotation of the scan frame's z: E57's spherical
elevation is measured from the scan frame's xy-plane, the scanner's horizon).

The reader is pye57 (MIT; Python bindings of libE57Format, the reference implementation of the
standard, maintained, with wheels for Linux, macOS and Windows), not the Rust-based ``e57``
crate's Python bindings: pye57 reads and writes (the tests write multi-scan files with it),
exposes each scan's header (poses, grid bounds) and reads spherical scans; it is the ``scans``
extra (``pip install 'sdp[scans]'``).

References
----------
.. [1] ASTM E2807-11, "Standard Specification for 3D Imaging Data Exchange, Version 1.0" (E57).
.. [2] D. Huber, "The ASTM E57 file format for 3D imaging data exchange", Proc. SPIE 7864, 2011.
"""

from __future__ import annotations

import numpy as np

from ..errors import require
from ._cloud import CloudFileError

__all__ = ["read_e57", "e57_scans", "e57_start"]

_E57_SIGNATURE = b"ASTM-E57"


def _open(path):
    """The pye57 reader of ``path`` (one-line errors for a missing extra or a file that is not E57)."""
    pye57 = require("pye57", "scans", "reading E57 files")
    with open(path, "rb") as f:
        head = f.read(8)
    if head != _E57_SIGNATURE:
        raise CloudFileError(f"{path}: can't read as e57 (no ASTM-E57 signature: not an E57 file)")
    return pye57.E57(str(path))


def _rotation(q: np.ndarray) -> np.ndarray:
    """The 3×3 rotation of a quaternion ``w, x, y, z`` (normalized first)."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _pose(header, path, index: int) -> tuple[np.ndarray, np.ndarray]:
    """(rotation quaternion w, x, y, z; translation) of scan ``index``, identity when it has no pose."""
    if not header.has_pose():
        return np.array([1.0, 0, 0, 0]), np.zeros(3)
    q = np.asarray(header.rotation, np.float64).reshape(4)
    t = np.asarray(header.translation, np.float64).reshape(3)
    if not (np.isfinite(q).all() and np.isfinite(t).all() and np.linalg.norm(q) > 0):
        raise CloudFileError(f"{path}: scan {index}'s pose is not finite or its rotation is zero: rotation "
                             f"{q.tolist()}, translation {t.tolist()}")
    return q, t


def e57_scans(path) -> list[dict]:
    """Per scan of an E57 file: its name, point count, fields, pose (rotation ``w x y z``,
    translation) and grid (rows, columns; None when unstructured): what ``sdp info`` lists."""
    e = _open(path)
    out = []
    for i in range(e.scan_count):
        h = e.get_header(i)
        q, t = _pose(h, path, i)
        fields = list(h.point_fields)
        grid = None
        if "rowIndex" in fields and "columnIndex" in fields:
            try:
                grid = [int(h.rowMaximum) - int(h.rowMinimum) + 1, int(h.columnMaximum) - int(h.columnMinimum) + 1]
            except Exception:  # indexBounds are optional in the standard
                grid = None
        name = h["name"].value() if h.node.isDefined("name") else None
        out.append({"scan": i, "name": name, "points": int(h.point_count), "fields": fields,
                    "rotation": q.tolist(), "translation": t.tolist(), "pose": bool(h.has_pose()), "grid": grid})
    return out


def e57_start(path) -> float | None:
    """The earliest ``acquisitionStart`` of the file's scans, GPS seconds (None: none recorded, or 0)."""
    e = _open(path)
    starts = []
    for i in range(e.scan_count):
        node = e.get_header(i).node
        if node.isDefined("acquisitionStart/dateTimeValue"):  # asked first: pye57 prints a missing path
            value = float(node["acquisitionStart"]["dateTimeValue"].value())
            if np.isfinite(value) and value > 0:
                starts.append(value)
    return min(starts) if starts else None


def read_e57(path):
    """``(xyz, fields, None, None, False, sensors, poles)`` of an E57 file: every scan moved by its pose
    into the file's frame (invalid points as NaN rows), the fields ``scan`` (uint16: which scan, the
    scans that hold a valid point numbered in the file's order: a scan of none is no scanner),
    ``intensity``, ``red``/``green``/``blue`` and ``row``/``column`` where any scan has them (at
    the points of a scan without one: 0, or -1 for ``row`` and ``column``; a survey often has
    colour at some stations only), and the scanners' positions (k, 3) in the file's frame. A scan
    without a pose is in the file's frame (the standard's identity), its scanner at the origin: a
    single scan exported in its scanner's frame. A file of several scans some of which record no
    pose is a registered export whose stations were not kept (they cannot all have stood at the
    origin): its scanners are unknown (None), and it is compared as a file that records no sensor,
    rather than with rays made up from the origin. ``poles`` (k, 3): each scanner's vertical axis
    in the file's frame (its pose's rotation of the scan frame's z), by which its range image is
    laid out; a lone scan without a pose has the file's z if it is stored spherical (its
    elevations are measured from that frame's xy-plane), else none is known (Cartesian points in
    the file's frame say nothing of the scanner's axes): None, as without scanners."""
    e = _open(path)
    k = e.scan_count
    if k == 0:
        raise CloudFileError(f"{path}: the E57 file holds no scan")
    parts, sensors, poles, posed = [], [], [], True
    for i in range(k):
        h = e.get_header(i)
        q, t = _pose(h, path, i)
        if int(h.point_count) == 0:  # a scan of no record: libE57Format can't read its empty vector
            continue
        raw = e.read_scan_raw(i, ignore_unsupported_fields=True)
        part = _scan_points(raw, q, t, i, path)
        if not np.isfinite(part["xyz"]).all(axis=1).any():  # a scanner that saw nothing says nothing
            continue
        part["scan"][:] = len(sensors)
        parts.append(part)
        sensors.append(t)
        spherical = not _CARTESIAN <= raw.keys()  # elevations from the scan frame's xy-plane: its z is vertical
        poles.append(_rotation(q)[:, 2] if h.has_pose() or spherical else np.full(3, np.nan))
        posed &= bool(h.has_pose())
    sensors = np.array(sensors).reshape(-1, 3) if posed or len(sensors) == 1 else None
    poles = np.array(poles).reshape(-1, 3) if sensors is not None and np.isfinite(poles).all() else None
    if not parts:  # every scan empty: no point (said by the reader's caller)
        return np.zeros((0, 3)), {}, None, None, False, None, None
    xyz = np.concatenate([p.pop("xyz") for p in parts])
    fields = {}
    for name in sorted(set().union(*parts)):  # a field any scan has, filled where a scan lacks it
        kind = np.result_type(*(p[name] for p in parts if name in p))
        fill = -1 if name in ("row", "column") else 0
        if fill < 0 and kind.kind == "u":
            kind = np.result_type(kind, np.int8)  # signed, to hold -1
        fields[name] = np.concatenate([np.asarray(p[name], kind) if name in p else np.full(len(p["scan"]), fill, kind)
                                       for p in parts])
    return xyz, fields, None, None, False, sensors, poles


_FIELDS = {"intensity": "intensity", "colorRed": "red", "colorGreen": "green", "colorBlue": "blue",
           "rowIndex": "row", "columnIndex": "column"}


_CARTESIAN = {"cartesianX", "cartesianY", "cartesianZ"}


def _scan_points(raw: dict, q, t, index: int, path) -> dict:
    """World points (NaN where invalid) and fields of one scan's raw arrays."""
    if _CARTESIAN <= raw.keys():
        local = np.c_[raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]].astype(np.float64)
        invalid = raw.get("cartesianInvalidState")
    elif {"sphericalRange", "sphericalAzimuth", "sphericalElevation"} <= raw.keys():
        r = np.asarray(raw["sphericalRange"], np.float64)
        az = np.asarray(raw["sphericalAzimuth"], np.float64)
        el = np.asarray(raw["sphericalElevation"], np.float64)
        local = np.c_[r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
        invalid = raw.get("sphericalInvalidState")
    else:
        raise CloudFileError(f"{path}: scan {index} has neither Cartesian nor spherical coordinates")
    with np.errstate(invalid="ignore", over="ignore"):  # an infinite coordinate: a row the reader drops
        xyz = local @ _rotation(q).T + t
    if invalid is not None:
        xyz[np.asarray(invalid) != 0] = np.nan  # 1: no return, 2: direction only (E57 §8.4.19)
    out = {"xyz": xyz, "scan": np.full(len(xyz), index, np.uint16)}
    for src, dst in _FIELDS.items():
        if src in raw:
            out[dst] = np.asarray(raw[src])
    return out
