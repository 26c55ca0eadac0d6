"""Numba kernel of :mod:`sdp.scale._tiles`: bucketing points into the tiles (and halos) that hold them.

Compiled once and cached on disk (``cache=True``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True, nogil=True)
def tile_buckets(xyz, first_row, voxel, tile_nodes, halo):
    """Group finite points into the buckets of the tiles whose core or halo holds them.

    A point's core tile is ``floor(floor(p / voxel) / tile_nodes)`` in x and y; it also joins
    the neighbouring tile on each side it lies within ``halo`` (world units) of. Returns
    ``(i0, j0, nj, counts, records, n_dropped)``: bucket ``b`` is tile ``(i0 + b // nj,
    j0 + b % nj)`` and holds ``counts[b]`` consecutive rows of ``records`` (m, 4): x, y, z, row
    number (``first_row`` + index), in row order; ``n_dropped`` points had NaN/Inf. A counting
    sort: two passes, no comparison sort.
    """
    n = xyz.shape[0]
    edge = tile_nodes * voxel
    ti = np.empty(n, np.int64)
    tj = np.empty(n, np.int64)
    flags = np.zeros(n, np.uint8)  # bits: near low x, near high x, near low y, near high y; 16: not finite
    lo_i, lo_j, hi_i, hi_j = 1 << 62, 1 << 62, -(1 << 62), -(1 << 62)
    bad = 0
    for p in range(n):
        x, y, z = xyz[p, 0], xyz[p, 1], xyz[p, 2]
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            flags[p] = 16
            bad += 1
            continue
        a = int(math.floor(x / voxel)) // tile_nodes
        b = int(math.floor(y / voxel)) // tile_nodes
        ti[p], tj[p] = a, b
        fx, fy = x - a * edge, y - b * edge
        flags[p] = (fx < halo) | ((fx >= edge - halo) << 1) | ((fy < halo) << 2) | ((fy >= edge - halo) << 3)
        lo_i, hi_i, lo_j, hi_j = min(lo_i, a), max(hi_i, a), min(lo_j, b), max(hi_j, b)
    if hi_i < lo_i:
        return 0, 0, 1, np.zeros(0, np.int64), np.zeros((0, 4)), bad
    i0, j0 = lo_i - 1, lo_j - 1
    ni, nj = hi_i - lo_i + 3, hi_j - lo_j + 3
    ids = np.empty(4, np.int64)
    counts = np.zeros(ni * nj, np.int64)
    for p in range(n):
        for k in range(_bucket_ids(flags[p], ti[p] - i0, tj[p] - j0, nj, ids)):
            counts[ids[k]] += 1
    start = np.zeros(ni * nj, np.int64)
    for b in range(1, ni * nj):
        start[b] = start[b - 1] + counts[b - 1]
    records = np.empty((start[-1] + counts[-1], 4))
    for p in range(n):
        for k in range(_bucket_ids(flags[p], ti[p] - i0, tj[p] - j0, nj, ids)):
            r = start[ids[k]]
            records[r, 0], records[r, 1], records[r, 2], records[r, 3] = xyz[p, 0], xyz[p, 1], xyz[p, 2], first_row + p
            start[ids[k]] = r + 1
    return i0, j0, nj, counts, records, bad


@nb.njit(cache=True, inline="always")
def _bucket_ids(f, a, b, nj, ids):
    """Buckets (ids[:k], returns k) of a point in local tile (a, b) with halo flags ``f``."""
    if f & 16:
        return 0
    k = 0
    for di in range(-1, 2):
        if (di == -1 and not f & 1) or (di == 1 and not f & 2):
            continue
        for dj in range(-1, 2):
            if (dj == -1 and not f & 4) or (dj == 1 and not f & 8):
                continue
            ids[k] = (a + di) * nj + (b + dj)
            k += 1
    return k
