"""Numba kernel of :class:`sdp.io.PointSource`: LAS integer coordinates to world coordinates.

Compiled once and cached on disk (``cache=True``).
"""

from __future__ import annotations

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def scaled_xyz(X, Y, Z, scale, offset):
    """LAS integer coordinates → float64 world (n, 3): X·scale + offset, as laspy computes it."""
    out = np.empty((X.shape[0], 3))
    for p in range(X.shape[0]):
        out[p, 0] = X[p] * scale[0] + offset[0]
        out[p, 1] = Y[p] * scale[1] + offset[1]
        out[p, 2] = Z[p] * scale[2] + offset[2]
    return out
