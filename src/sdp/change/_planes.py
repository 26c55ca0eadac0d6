"""The plane test: does a point the other scan could not judge continue the unchanged surface?

A hidden or unobserved point is explained, not a change, when it continues the unchanged
surface around it: it lies on the least-squares plane of its nearest unchanged neighbours (Hoppe
et al. [1]), and that patch is flat. That is the table a moved object uncovers, or the border of a
field of view that moved. Points in one cube share the patch nearest to their mean (one
neighbour query per cube, by :func:`sdp._core._kdtree.k_nearest`).

What left is no evidence of what stayed: the patch leaves out the unchanged points near a point
the density finds gone from the other epoch. An unchanged verdict rests on the other epoch's
points within the kernel's support (truncate·σ), a gone point's verdict on this epoch's points
within the same reach; within twice that reach the two verdicts share their evidence. There an
unchanged point may be a new object's face where it passes through the surface of the object it
replaced (the density cannot tell two surfaces apart within about 2σ), or the foot of a moved
object beside its table: a patch of them explained a new object's hidden faces as unchanged
(put behind the old one's front) and failed on the uncovered table beside them
(docs/benchmarks.md §11).

References
----------
.. [1] H. Hoppe, T. DeRose, T. Duchamp, J. McDonald, W. Stuetzle, "Surface reconstruction from
   unorganized points", SIGGRAPH 1992.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .._core._cells import BITS, MAX_INDEX, cell_key, find_cell, linked_cells, probe, table_bits
from .._core._kdtree import k_nearest
from .._core._points import finite_bounds
from ._coverage import CHANGED, UNCHANGED

__all__ = ["explain_by_planes"]


def explain_by_planes(points, changed, states, unseen, *, plane_points, plane_stride, plane_distance,
                       plane_flatness, plane_bin, gone=None, gone_reach: float = 0.0) -> np.ndarray:
    """``states`` with the ``unseen`` points that continue the unchanged surface made unchanged: on
    its plane, and for a point the other scan says nothing of (not comparable: outside its view,
    or hidden behind what is still there) also within the patch's reach (twice its spread of its
    centre). Farther, the plane would be extrapolated over ground never seen; a point the other
    scan saw changed (a gone hider, a free ray) is judged by the plane alone, as a moved object's
    uncovered table. ``gone``: the other epoch's points the density finds gone (g, 3), or a
    callable returning them; the unchanged points within ``gone_reach`` of one are no part of a
    patch."""
    static = _every_nth_unchanged(points, changed, max(1, int(plane_stride)))
    if len(unseen) and gone is not None:
        gone = np.ascontiguousarray(gone() if callable(gone) else gone, np.float64).reshape(-1, 3)
        if len(gone) and len(static):
            static = static[~near_any(static, gone, gone_reach)]
    if len(unseen) and len(static) >= 3:
        on_plane, within = _on_unchanged_plane(np.take(points, unseen, axis=0), static,
                                               k=min(int(plane_points), len(static)), distance=plane_distance,
                                               flatness=plane_flatness, bin_size=plane_bin)
        states[unseen[on_plane & (within | (states[unseen] == CHANGED))]] = UNCHANGED
    return states


def near_any(points: np.ndarray, others: np.ndarray, reach: float) -> np.ndarray:
    """Which ``points`` lie within ``reach`` of a point of ``others`` (both (n, 3) float64, finite,
    non-empty). ``others`` in cells of side ``reach`` (:func:`sdp._core._cells.linked_cells`): a
    point's neighbours within reach lie in its cell's 27; a second table of the cells next to an
    occupied one answers most points with one lookup."""
    (lo_p, hi_p, _), (lo_o, hi_o, _) = finite_bounds(points), finite_bounds(others)  # NumPy's axis=0 is slower
    lo = np.minimum(lo_p, lo_o) - reach  # every neighbour's index ≥ 0
    span = (np.maximum(hi_p, hi_o) - lo) / reach if reach > 0 else np.inf
    if not np.all(span < MAX_INDEX - 2):  # cells too many to key: not expected of a scan at its own σ
        return np.linalg.norm(points - others[k_nearest(others, points, 1)[:, 0]], axis=1) <= reach
    bits = table_bits(max(len(others) // 4, 1))
    while True:
        keys, heads, nxt, cells, _ = linked_cells(others, lo, reach, bits)
        if len(nxt):
            return _near_any(keys, heads, nxt, others, points, lo, reach, cells)
        bits += 2  # the table got half full: more cells than guessed


@nb.njit(cache=True, nogil=True)
def _near_any(keys, heads, nxt, others, points, lo, c, cells):
    """:func:`near_any`'s kernel over the cell lists of ``others`` (side ``c`` from ``lo``)."""
    mask, shift = keys.shape[0] - 1, 64 - int(round(math.log2(keys.shape[0])))
    low = (1 << BITS) - 1
    # the cells next to an occupied one (itself included): a point in none of them has no neighbour
    bits = table_bits(2 * 27 * cells)
    ring = np.full(1 << bits, -1, np.int64)
    rmask, rshift = (1 << bits) - 1, 64 - bits
    for s in range(keys.shape[0]):
        key = keys[s]
        if key >= 0:
            ix, iy, iz = key >> (2 * BITS), (key >> BITS) & low, key & low
            for dx in range(-1, 2):
                for dy in range(-1, 2):
                    for dz in range(-1, 2):
                        k = cell_key(ix + dx, iy + dy, iz + dz)
                        ring[probe(ring, k, rshift, rmask)] = k
    inv, r2 = 1.0 / c, c * c
    out = np.zeros(points.shape[0], np.bool_)
    for i in range(points.shape[0]):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        cx, cy, cz = int(math.floor((x - lo[0]) * inv)), int(math.floor((y - lo[1]) * inv)), \
            int(math.floor((z - lo[2]) * inv))
        k = cell_key(cx, cy, cz)
        if ring[probe(ring, k, rshift, rmask)] != k:
            continue
        for ix in range(cx - 1, cx + 2):
            for iy in range(cy - 1, cy + 2):
                for iz in range(cz - 1, cz + 2):
                    s = find_cell(keys, ix, iy, iz, shift, mask)
                    p = heads[s] if s >= 0 else -1
                    while p >= 0 and not out[i]:
                        dx, dy, dz = others[p, 0] - x, others[p, 1] - y, others[p, 2] - z
                        out[i] = dx * dx + dy * dy + dz * dz <= r2
                        p = nxt[p]
    return out


def _on_unchanged_plane(query: np.ndarray, static: np.ndarray, *, k: int, distance: float, flatness: float,
                        bin_size: float) -> tuple[np.ndarray, np.ndarray]:
    """(Does each query point lie on the least-squares plane of the ``k`` static points nearest to
    it, the patch being flat (RMS off-plane deviation < ``flatness``) and the point within
    ``distance`` of the plane? Does it lie within the patch's reach, twice its spread of its
    centre?) Query points sharing a cube of side ``bin_size`` share one patch: the one nearest to
    their mean (one neighbour query per cube, not per point)."""
    inverse, centres = _cube_means(query, bin_size)
    mean, normal, rms, spread = _plane_fits(static, k_nearest(static, centres, k))
    within = np.linalg.norm(query - mean[inverse], axis=1) <= 2.0 * spread[inverse]
    return _on_planes(query, inverse, mean, normal, rms, distance, flatness), within


def _cube_means(query: np.ndarray, bin_size: float) -> tuple[np.ndarray, np.ndarray]:
    """(cube of each point, mean point of each cube) of the cubes of side ``bin_size`` holding
    ``query`` (cube ``⌊p / bin_size⌋``); cubes numbered in the order their first point comes,
    means summed in row order (as ``np.bincount``)."""
    inverse, centres = _group_means(query, bin_size)
    if len(inverse) < len(query):  # cubes too many to pack into a key: not expected of a scan at its own σ
        _, first, inverse = np.unique(np.floor(query / bin_size).astype(np.int64), axis=0, return_index=True,
                                      return_inverse=True)
        number = np.empty(len(first), np.int64)
        number[np.argsort(first)] = np.arange(len(first))
        inverse = number[inverse.ravel()]
        centres = np.stack([np.bincount(inverse, weights=query[:, d]) for d in range(3)], axis=1)
        centres /= np.bincount(inverse)[:, None]
    return inverse, centres


@nb.njit(cache=True, nogil=True)
def _group_means(query, bin_size):
    """(group of each row, mean row of each group) of the rows of ``query`` sharing a cube
    ``⌊p / bin_size⌋``: groups numbered by their first row, sums in row order. The cubes are
    counted from the lowest on each axis and hashed (:mod:`sdp._core._cells`); where they span
    ``MAX_INDEX`` or more on an axis, nothing (empty arrays)."""
    n = query.shape[0]
    cells = np.empty((n, 3), np.int64)
    lo = np.zeros(3, np.int64)
    hi = np.zeros(3, np.int64)
    for i in range(n):
        for d in range(3):
            c = int(math.floor(query[i, d] / bin_size))
            cells[i, d] = c
            if i == 0 or c < lo[d]:
                lo[d] = c
            if i == 0 or c > hi[d]:
                hi[d] = c
    for d in range(3):
        if hi[d] - lo[d] >= MAX_INDEX:
            return np.empty(0, np.int64), np.empty((0, 3))
    bits = table_bits(2 * n)
    cap = 1 << bits
    shift, mask = 64 - bits, cap - 1
    keys = np.full(cap, -1, np.int64)
    slot_group = np.empty(cap, np.int64)
    inverse = np.empty(n, np.int64)
    sums = np.zeros((n, 3))
    counts = np.zeros(n, np.int64)
    groups = 0
    last_key = -1
    g = -1
    for i in range(n):
        key = cell_key(cells[i, 0] - lo[0], cells[i, 1] - lo[1], cells[i, 2] - lo[2])
        if key != last_key:  # scans are ordered: consecutive points often share a cube
            s = probe(keys, key, shift, mask)
            if keys[s] < 0:
                keys[s] = key
                slot_group[s] = groups
                groups += 1
            g = slot_group[s]
            last_key = key
        inverse[i] = g
        counts[g] += 1
        sums[g, 0] += query[i, 0]
        sums[g, 1] += query[i, 1]
        sums[g, 2] += query[i, 2]
    centres = np.empty((groups, 3))
    for g in range(groups):
        for d in range(3):
            centres[g, d] = sums[g, d] / counts[g]
    return inverse, centres


@nb.njit(cache=True, nogil=True)
def _every_nth_unchanged(points, changed, stride):
    """Every ``stride``-th row of ``points`` not ``changed`` (the first, the stride-th, …), in one
    pass into room for every row's share."""
    out = np.empty(((changed.shape[0] + stride - 1) // stride, 3))
    j = 0
    m = 0
    for i in range(changed.shape[0]):
        if not changed[i]:
            if j == 0:
                out[m, 0], out[m, 1], out[m, 2] = points[i, 0], points[i, 1], points[i, 2]
                m += 1
            j += 1
            if j == stride:
                j = 0
    return out[:m]


@nb.njit(cache=True, nogil=True)
def _on_planes(query, inverse, mean, normal, rms, distance, flatness):
    """Per query point: its cube's patch is flat (RMS < ``flatness``) and the point lies within
    ``distance`` of the patch's plane."""
    out = np.empty(query.shape[0], np.bool_)
    for i in range(query.shape[0]):
        g = inverse[i]
        off = abs((query[i, 0] - mean[g, 0]) * normal[g, 0] + (query[i, 1] - mean[g, 1]) * normal[g, 1]
                  + (query[i, 2] - mean[g, 2]) * normal[g, 2])
        out[i] = rms[g] < flatness and off < distance
    return out

@nb.njit(cache=True, nogil=True)
def _plane_fits(static, idx):
    """Least-squares plane of each patch ``static[idx[i]]``: its mean, unit normal (eigenvector of
    the covariance's smallest eigenvalue λ, closed form for symmetric 3×3 matrices), RMS
    deviation sqrt(λ) (inf for a patch without a plane: all points equal) and spread (the RMS
    distance of its points from their mean: how far the patch reaches)."""
    m, k = idx.shape
    mean = np.zeros((m, 3))
    normal = np.zeros((m, 3))
    rms = np.full(m, np.inf)
    spread = np.zeros(m)
    for i in range(m):
        mx = my = mz = 0.0
        for j in range(k):
            s = idx[i, j]
            mx += static[s, 0]
            my += static[s, 1]
            mz += static[s, 2]
        mx /= k
        my /= k
        mz /= k
        mean[i, 0], mean[i, 1], mean[i, 2] = mx, my, mz
        a00 = a01 = a02 = a11 = a12 = a22 = 0.0
        for j in range(k):
            s = idx[i, j]
            x = static[s, 0] - mx
            y = static[s, 1] - my
            z = static[s, 2] - mz
            a00 += x * x
            a01 += x * y
            a02 += x * z
            a11 += y * y
            a12 += y * z
            a22 += z * z
        a00 /= k
        a01 /= k
        a02 /= k
        a11 /= k
        a12 /= k
        a22 /= k
        spread[i] = math.sqrt(a00 + a11 + a22)
        # smallest eigenvalue: trigonometric solution of the characteristic cubic
        q = (a00 + a11 + a22) / 3.0
        p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)
        if not p2 > 1e-24 * q * q or q == 0.0:
            continue  # isotropic patch, or one point repeated: no plane
        p = math.sqrt(p2 / 6.0)
        b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
        b01, b02, b12 = a01 / p, a02 / p, a12 / p
        det = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
        lam = q + 2.0 * p * math.cos(math.acos(min(1.0, max(-1.0, det / 2.0))) / 3.0 + 2.0 * math.pi / 3.0)
        # its eigenvector: the longest cross product of two rows of A − λI
        r0x, r0y, r0z = a00 - lam, a01, a02
        r1x, r1y, r1z = a01, a11 - lam, a12
        r2x, r2y, r2z = a02, a12, a22 - lam
        best = 0.0
        for c in range(3):
            if c == 0:
                ux, uy, uz, vx, vy, vz = r0x, r0y, r0z, r1x, r1y, r1z
            elif c == 1:
                ux, uy, uz, vx, vy, vz = r0x, r0y, r0z, r2x, r2y, r2z
            else:
                ux, uy, uz, vx, vy, vz = r1x, r1y, r1z, r2x, r2y, r2z
            cx, cy, cz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
            nn = cx * cx + cy * cy + cz * cz
            if nn > best:
                best = nn
                normal[i, 0], normal[i, 1], normal[i, 2] = cx, cy, cz
        if best > 0.0:
            f = 1.0 / math.sqrt(best)
            normal[i, 0] *= f
            normal[i, 1] *= f
            normal[i, 2] *= f
            rms[i] = math.sqrt(max(lam, 0.0))
    return mean, normal, rms, spread
