"""Validation of point arrays: every public entry point goes through :func:`as_points`."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from . import _kernels as K
from .errors import InvalidPointsError


class Points(NamedTuple):
    """A validated cloud: finite rows as C-contiguous float64, and what was dropped."""

    xyz: np.ndarray
    finite: np.ndarray | None  # None when every input row was finite, else the mask of kept rows
    lo: np.ndarray
    hi: np.ndarray
    dropped_before: int = 0  # rows the file reader dropped already (a Cloud's n_dropped)

    @property
    def n_dropped(self) -> int:
        return self.dropped_before + (0 if self.finite is None else int((~self.finite).sum()))


def as_points(points, *, name: str = "points") -> Points:
    """Validate an (n, 3) array-like of world coordinates, or a :class:`sdp.io.Cloud`.

    Rows with a NaN or infinite coordinate are dropped (sensors mark missing returns that
    way); :attr:`Points.finite` then holds the mask of the rows kept, so callers can report
    the count and map results back to the input rows. A cloud read from a file brings the
    count of rows its reader dropped.

    Raises
    ------
    InvalidPointsError
        If the array is not (n, 3) numeric, or holds no finite row.
    """
    before = 0
    if hasattr(points, "xyz") and hasattr(points, "n_dropped"):  # a Cloud from sdp.read_points
        points, before = points.xyz, int(points.n_dropped)
    try:
        arr = np.ascontiguousarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidPointsError(f"{name}: expected an (n, 3) array of numbers ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidPointsError(f"{name}: expected an (n, 3) array of x, y, z coordinates, got shape {arr.shape}")
    lo, hi, bad = K.finite_bounds(arr)
    finite = None
    if bad:
        finite = np.isfinite(arr).all(axis=1)
        arr = np.ascontiguousarray(arr[finite])
    if arr.shape[0] == 0:
        what = "is empty" if finite is None else f"has no finite point (all {finite.size} rows hold NaN or Inf)"
        raise InvalidPointsError(f"{name} {what}: nothing to build a density field from")
    return Points(arr, finite, lo, hi, before)
