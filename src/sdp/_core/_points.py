"""Validation of point arrays: every public entry point goes through :func:`as_points`.

Also holds :func:`finite_bounds` (a Numba kernel, cached on disk) and :func:`to_rows`, which maps
per-point results back over the input rows."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from ..errors import InvalidPointsError


class Points(NamedTuple):
    """A validated cloud: finite rows as C-contiguous float64, and what was dropped."""

    xyz: np.ndarray
    finite: np.ndarray | None  # None when every input row was finite, else the mask of kept rows
    lo: np.ndarray
    hi: np.ndarray
    dropped_before: int = 0  # rows the file reader dropped already (a Cloud's n_dropped)
    # an organized frame's (pixel of each row, (height, width), sensor origin): its pixels are
    # neighbourhoods (sdp.fields._spacing); None for other clouds and once moved
    image: tuple | None = None

    @property
    def n_dropped(self) -> int:
        return self.dropped_before + (0 if self.finite is None else int((~self.finite).sum()))

    def moved(self, xyz: np.ndarray) -> "Points":
        """The same cloud at new coordinates ``xyz`` (one row per finite point, e.g. registered),
        with their bounds."""
        return self._replace(xyz=xyz, lo=xyz.min(axis=0), hi=xyz.max(axis=0), image=None)


def as_points(points, *, name: str = "points") -> Points:
    """Validate an (n, 3) array-like of world coordinates, or a :class:`sdp.io.Cloud`.

    Rows with a NaN or infinite coordinate are dropped (sensors mark missing returns that
    way); :attr:`Points.finite` then holds the mask of the rows kept, so callers can report
    the count and map results back to the input rows. A cloud read from a file brings the
    count of rows its reader dropped. A table (an object with ``columns``, e.g. a pandas
    DataFrame) gives its ``x``, ``y`` and ``z`` columns by name; one without those names is read
    by position only if it has three columns.

    Raises
    ------
    InvalidPointsError
        If the array is not (n, 3) numeric, or holds no finite row; a table of more than three
        columns without ``x``, ``y``, ``z`` among them.
    """
    before, image = 0, None
    if hasattr(points, "xyz") and hasattr(points, "n_dropped"):  # a Cloud from sdp.read_points
        image = _image_of(points)
        points, before = points.xyz, int(points.n_dropped)
    elif not isinstance(points, np.ndarray) and getattr(points, "columns", None) is not None:
        points = _table_xyz(points, name)
    if np.iscomplexobj(points):  # NumPy would keep the real part with a warning
        raise InvalidPointsError(f"{name}: expected real x, y, z coordinates, got complex numbers")
    try:
        arr = np.ascontiguousarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidPointsError(f"{name}: expected an (n, 3) array of numbers ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidPointsError(f"{name}: expected an (n, 3) array of x, y, z coordinates, got shape {arr.shape}")
    lo, hi, bad = finite_bounds(arr)
    finite = None
    if bad:
        finite = np.isfinite(arr).all(axis=1)
        arr = np.ascontiguousarray(arr[finite])
    if arr.shape[0] == 0:
        what = "is empty" if finite is None else f"has no finite point (all {finite.size} rows hold NaN or Inf)"
        raise InvalidPointsError(f"{name} {what}: nothing to build a density field from")
    return Points(arr, finite, lo, hi, before, image if finite is None else None)


def _image_of(cloud) -> tuple | None:
    """:attr:`Points.image` of a cloud: an organized one with a pixel per row and its sensor's origin."""
    shape, pixels = getattr(cloud, "image", None), getattr(cloud, "pixels", None)
    origin = getattr(cloud, "sensor_origin", None)
    if shape is None or pixels is None or origin is None or len(pixels) != len(cloud.xyz):
        return None
    return pixels, tuple(shape), np.asarray(origin, np.float64)


def _table_xyz(table, name: str):
    """The ``x``, ``y``, ``z`` columns of a table (pandas, Polars) by name: by position, columns
    ordered z, x, y (after a merge) would be read as x, y, z without a word."""
    names = [str(c) for c in table.columns]
    if all(axis in names for axis in "xyz"):
        return np.column_stack([np.asarray(table[axis]) for axis in "xyz"])
    if len(names) != 3:
        raise InvalidPointsError(f"{name}: a table of {len(names)} columns without x, y, z among them "
                                 f"({', '.join(names[:6])}{', …' if len(names) > 6 else ''}): select the "
                                 'coordinates, e.g. df[["x", "y", "z"]]')
    return table


def to_rows(values: np.ndarray, pts: Points, fill):
    """Spread per-finite-point values back over the input rows (``fill`` for dropped rows)."""
    if pts.finite is None:
        return values
    out = np.full(pts.finite.shape, fill, dtype=values.dtype)
    out[pts.finite] = values
    return out


@nb.njit(cache=True, nogil=True)
def finite_bounds(points):
    """(lo, hi, number of rows holding NaN/Inf) of an (n, 3) array, over its finite rows, in one
    pass (branch-free: a row that isn't finite counts as +inf for lo and -inf for hi)."""
    lo0 = lo1 = lo2 = np.inf
    hi0 = hi1 = hi2 = -np.inf
    bad = 0
    for p in range(points.shape[0]):
        x, y, z = points[p, 0], points[p, 1], points[p, 2]
        ok = math.isfinite(x) and math.isfinite(y) and math.isfinite(z)
        bad += not ok
        lo0, hi0 = min(lo0, x if ok else np.inf), max(hi0, x if ok else -np.inf)
        lo1, hi1 = min(lo1, y if ok else np.inf), max(hi1, y if ok else -np.inf)
        lo2, hi2 = min(lo2, z if ok else np.inf), max(hi2, z if ok else -np.inf)
    return np.array([lo0, lo1, lo2]), np.array([hi0, hi1, hi2]), bad


#: Ratio of two scans' extents beyond which they are most likely in other units (1000 between
#: millimetres and metres; a Kinect frame against a building's scan stays within 100).
UNITS_RATIO = 100.0


def other_units(*spans: float) -> bool:
    """Whether scans of these extents (world units) are most likely in other units."""
    return min(spans) > 0 and max(spans) > UNITS_RATIO * min(spans)
