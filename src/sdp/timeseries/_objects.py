"""4D objects of change and the epoch each change starts.

A core point at an epoch is *changed* when its smoothed change is significant: ``|smoothed| >
1.96·smoothed_sigma`` (the smoother's own 95 % bound). Changed (epoch, point) pairs of the same
sign are joined to their spatial neighbours at the same epoch (core points closer than
``radius``, by default 1.5 × the 90th percentile of the core points' spacing) and to themselves at the
next epoch, where both changed in one way: gradually, or by steps at the same epoch (± 1; the
steps of :mod:`sdp.timeseries._kalman`), since a step and a creep beside it, or two steps at
different epochs, are different events. The connected sets in space and time are the 4D objects
of change, like the objects-by-change of Anders et al. [1]_, here grown from every significant
pair at once instead of from seeds. Sets of fewer than ``min_points`` distinct core points are noise and are left out
(object 0): ten, or as many as cover three cylinders' footprints if the core points are denser
than the cylinders (:func:`min_object_points`: neighbouring cylinders then share their points and
their noise). An object *starts* at the first epoch at which ``min_points`` of its core points are
changed together (the first epoch with any, if it never has that many at once): a few core points
at its rim, where a change smoothed over time leaks before it happens, do not date it.

A series that fits in memory is one graph over every (epoch, point), cut into components by one
union-find (:func:`objects_in_memory`). Beyond memory the work streams over the epochs
(:func:`find_objects`): each epoch's spatial components, then the components of consecutive
epochs that share a point are joined (a union over component ids); a second pass gives every
pair its object and sums the object table. Memory: the neighbour pairs, two epochs' rows and one
id per component. Both give the same objects (tested).

The onset of a core point's change is the first epoch from which its smoothed change stays
significant for two epochs running, or the epoch of its first step (:mod:`sdp.timeseries._kalman`)
if that comes first; ``onset_kind`` says which (1: step, 2: gradual). A step with no significant
change after it is no onset.

References
----------
.. [1] K. Anders, L. Winiwarter, H. Mara, R. Lindenbergh, S. E. Vos, B. Höfle, "Fully automatic
   spatiotemporal segmentation of 3D LiDAR time series for the extraction of natural surface
   changes", ISPRS J. Photogramm. 173 (2021) 297–308.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = ["neighbour_pairs", "find_objects", "objects_in_memory", "onsets", "OBJECT_FIELDS"]

OBJECT_FIELDS = ("object_start", "object_end", "object_start_time", "object_end_time", "object_points",
                 "object_area", "object_peak_change", "object_mean_velocity")


def neighbour_pairs(xyz: np.ndarray, radius: float | None = None) -> tuple[np.ndarray, np.ndarray, float, float]:
    """(i, j, radius, area per core point): the core points' neighbour pairs within ``radius``
    (default 1.5 × the 90th percentile of the nearest-neighbour spacing: core points subsampled
    on a grid lie up to a cell and a half apart and must still touch); the area is the median
    spacing squared."""
    tree = cKDTree(xyz)
    if len(xyz) > 1:
        d, _ = tree.query(xyz[:: max(1, len(xyz) // 5000)], k=2)
        spacing, far = float(np.median(d[:, 1])), float(np.quantile(d[:, 1], 0.9))
    else:
        spacing = far = 1.0
    radius = 1.5 * far if radius is None else float(radius)
    pairs = tree.query_pairs(radius, output_type="ndarray")
    return pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64), radius, spacing * spacing


def min_object_points(xyz: np.ndarray, projection_scale: float, *, footprints: float = 3.0,
                      floor: int = 10) -> int:
    """The fewest core points of an object: ``floor``, or as many as cover ``footprints``
    cylinders (π d²/4 each) at the core points' median spacing, if more. Core points closer than
    the cylinder share their points and their noise: a cluster of them flickers together."""
    _, _, _, area = neighbour_pairs(xyz[:: max(1, len(xyz) // 200_000)], 0.0)
    area *= max(1, len(xyz) // 200_000)  # a sample's spacing is wider by the square root of the step
    return int(max(floor, math.ceil(footprints * math.pi * projection_scale**2 / 4.0 / area)))


def _components(sign: np.ndarray, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, int]:
    """Per core point, its component among the changed points of one epoch (-1: unchanged), numbered
    in the order of their first point; ``i, j``: the neighbour pairs whose changes are of one kind."""
    out = np.full(len(sign), -1, np.int64)
    return out, _epoch_labels(np.ascontiguousarray(sign, np.int8), i, j, out)


def _table(start, first, end, npts, peak, vsum, vcount, anchor, min_points, times, radius, area):
    """The object table of the roots with at least ``min_points`` core points, largest first; (table, root → id)."""
    start = np.where(start >= len(times), first, start)
    kept = np.flatnonzero(npts >= min_points)
    kept = kept[np.lexsort((anchor[kept], start[kept], -npts[kept]))]  # largest, then earliest, first
    ids = np.zeros(len(npts), np.int32)
    ids[kept] = np.arange(1, len(kept) + 1, dtype=np.int32)
    return {"object_start": start[kept].astype(np.int32), "object_end": end[kept].astype(np.int32),
            "object_start_time": times[start[kept]], "object_end_time": times[end[kept]],
            "object_points": npts[kept].astype(np.int64), "object_area": npts[kept] * area,
            "object_peak_change": peak[kept], "object_mean_velocity": vsum[kept] / np.maximum(vcount[kept], 1),
            "radius": radius, "area_per_point": area}, ids


def objects_in_memory(smoothed, sigma, velocity, xyz, times, *, min_points: int, step=None, radius=None):
    """:func:`find_objects` on a whole series in memory (epochs, points): one graph over every
    (epoch, point), one union-find; (table, object ids (epochs, points) int32)."""
    i, j, radius, area = neighbour_pairs(xyz, radius)
    E, m = smoothed.shape
    step = np.full(m, -1) if step is None else np.asarray(step)
    together = (step[i] < 0) & (step[j] < 0) | (step[i] >= 0) & (step[j] >= 0) & (np.abs(step[i] - step[j]) <= 1)
    sig = np.isfinite(smoothed) & np.isfinite(sigma) & (np.abs(smoothed) > 1.96 * sigma)
    sign = np.where(sig, np.sign(smoothed), 0).astype(np.int8)
    label = _space_time_labels(sign, i[together], j[together])
    node = np.flatnonzero(sign.reshape(-1))
    uniq, root = np.unique(label[node], return_inverse=True)
    n_roots = len(uniq)
    epoch, point = node // m, node % m
    start = np.full(n_roots, E, np.int64)
    first = np.full(n_roots, E, np.int64)
    end = np.full(n_roots, -1, np.int64)
    np.minimum.at(first, root, epoch)
    np.maximum.at(end, root, epoch)
    keys, counts = np.unique(root * E + epoch, return_counts=True)
    full = counts >= min_points
    np.minimum.at(start, keys[full] // E, keys[full] % E)
    d = smoothed.reshape(-1)[node]
    order = np.lexsort((-np.abs(d), root))
    head = np.ones(len(order), bool)
    head[1:] = root[order[1:]] != root[order[:-1]]
    peak = np.zeros(n_roots)
    peak[root[order[head]]] = d[order[head]]
    v = velocity.reshape(-1)[node]
    fv = np.isfinite(v)
    vsum = np.bincount(root[fv], v[fv], minlength=n_roots)
    vcount = np.bincount(root[fv], minlength=n_roots).astype(np.float64)
    npts = np.bincount(np.unique(root * m + point) // m, minlength=n_roots)
    anchor = np.full(n_roots, E * m, np.int64)
    np.minimum.at(anchor, root, node)
    table, ids = _table(start, first, end, npts, peak, vsum, vcount, anchor, min_points, times, radius, area)
    labels = np.zeros(E * m, np.int32)
    labels[node] = ids[root]
    return table, labels.reshape(E, m)


@nb.njit(cache=True, inline="always")
def _find(parent, a):
    while parent[a] != a:  # path halving
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@nb.njit(cache=True, inline="always")
def _union(parent, a, b):
    ra, rb = _find(parent, a), _find(parent, b)
    if ra < rb:
        parent[rb] = ra
    elif rb < ra:
        parent[ra] = rb


@nb.njit(cache=True, parallel=True)
def _space_time_labels(sign, i, j):
    """Per (epoch, point) node ``k·m + p``, the smallest node of its component: neighbours ``i[e],
    j[e]`` of one sign at one epoch, a point of one sign at consecutive epochs (a union-find; each
    epoch's own unions touch only its nodes, so the epochs run in parallel)."""
    E, m = sign.shape
    parent = np.arange(E * m)
    for k in nb.prange(E):
        base = k * m
        for e in range(len(i)):
            sa = sign[k, i[e]]
            if sa != 0 and sa == sign[k, j[e]]:
                _union(parent, base + i[e], base + j[e])
    for k in range(E - 1):
        base = k * m
        for p in range(m):
            if sign[k, p] != 0 and sign[k, p] == sign[k + 1, p]:
                _union(parent, base + p, base + m + p)
    for a in range(E * m):
        parent[a] = _find(parent, a)
    return parent


@nb.njit(cache=True)
def _epoch_labels(sign, i, j, out):
    """:func:`_components`' kernel: ``out`` filled, the number of components returned."""
    m = len(sign)
    parent = np.arange(m)
    for e in range(len(i)):
        sa = sign[i[e]]
        if sa != 0 and sa == sign[j[e]]:
            _union(parent, i[e], j[e])
    ids = np.full(m, -1, np.int64)  # root → component
    n = 0
    for p in range(m):
        if sign[p] != 0:
            r = _find(parent, p)
            if ids[r] < 0:
                ids[r] = n
                n += 1
            out[p] = ids[r]
    return n


def find_objects(read_epoch, n_epochs: int, xyz: np.ndarray, times: np.ndarray, *, min_points: int,
                 step: np.ndarray | None = None, radius: float | None = None, write=None) -> dict:
    """The 4D objects of change (see the module docstring).

    ``read_epoch(k)`` returns (smoothed, smoothed_sigma, velocity) of epoch ``k``; ``write(k,
    labels)`` receives each epoch's object ids (int32, 0: none). Returns the object table
    (:data:`OBJECT_FIELDS`, objects ordered by size, ids 1…) and the neighbourhood used.
    ``step``: each core point's step epoch (-1: none); neighbours join only if both changed
    gradually or both stepped within an epoch of each other."""
    i, j, radius, area = neighbour_pairs(xyz, radius)
    m = len(xyz)
    step = np.full(m, -1) if step is None else np.asarray(step)
    together = (step[i] < 0) & (step[j] < 0) | (step[i] >= 0) & (step[j] >= 0) & (np.abs(step[i] - step[j]) <= 1)
    i, j = i[together], j[together]

    def signs(k):
        d, s, v = read_epoch(k)
        sig = np.isfinite(d) & np.isfinite(s) & (np.abs(d) > 1.96 * s)
        return np.where(sig, np.sign(d), 0).astype(np.int8), d, v

    # pass 1: components per epoch, joined to the previous epoch's where a point stays changed
    offsets, links, sizes, prev, prev_sign = [], [], [], None, None
    total = 0
    for k in range(n_epochs):
        sign, _, _ = signs(k)
        comp, n = _components(sign, i, j)
        offsets.append(total)
        sizes.append(np.bincount(comp[comp >= 0], minlength=n))
        if prev is not None:
            both = (sign != 0) & (sign == prev_sign)
            # one row per pair of components, not per point: the memory stays with the components
            links.append(np.unique(np.c_[prev[both] + offsets[k - 1], comp[both] + total], axis=0))
        prev, prev_sign = comp, sign
        total += n
    links = np.concatenate(links) if links else np.empty((0, 2), np.int64)
    graph = coo_matrix((np.ones(len(links), np.int8), (links[:, 0], links[:, 1])), shape=(total, total))
    _, root = connected_components(graph, directed=False) if total else (0, np.empty(0, np.int64))
    n_roots = int(root.max()) + 1 if total else 0
    # a root of fewer (epoch, point) pairs than min_points has fewer distinct points: no object, and
    # its points need not be listed (the noise's many small roots would make that list grow with the epochs)
    nodes = np.bincount(root, np.concatenate(sizes), minlength=n_roots).astype(np.int64) if total else \
        np.zeros(0, np.int64)
    listed = nodes >= min_points

    # pass 2: per root, its epochs, distinct points, peak change and velocity sums
    start = np.full(n_roots, n_epochs, np.int64)  # the first epoch with min_points changed core points
    first = np.full(n_roots, n_epochs, np.int64)  # the first epoch with any
    anchor = np.full(n_roots, n_epochs * m, np.int64)  # the first (epoch, point): ties in the order
    end = np.full(n_roots, -1, np.int64)
    peak = np.zeros(n_roots)
    vsum, vcount = np.zeros(n_roots), np.zeros(n_roots)
    pairs = []
    for k in range(n_epochs):
        sign, d, v = signs(k)
        comp, _ = _components(sign, i, j)
        at = np.flatnonzero(comp >= 0)
        r = root[comp[at] + offsets[k]]
        np.minimum.at(first, r, k)
        np.minimum.at(anchor, r, k * m + at)
        np.maximum.at(end, r, k)
        born = (np.bincount(r, minlength=n_roots) >= min_points) & (start == n_epochs)
        start[born] = k
        order = np.lexsort((-np.abs(d[at]), r))
        head = np.ones(len(order), bool)
        head[1:] = r[order[1:]] != r[order[:-1]]
        cand = order[head]
        better = np.abs(d[at][cand]) > np.abs(peak[r[cand]])
        peak[r[cand][better]] = d[at][cand][better]
        fv = np.isfinite(v[at])
        np.add.at(vsum, r[fv], v[at][fv])
        np.add.at(vcount, r[fv], 1)
        pairs.append(np.unique(r[listed[r]] * m + at[listed[r]]))
        if len(pairs) > 64:
            pairs = [np.unique(np.concatenate(pairs))]
    pairs = np.unique(np.concatenate(pairs)) if pairs else np.empty(0, np.int64)
    npts = np.where(listed, np.bincount(pairs // m, minlength=n_roots), nodes) if n_roots else np.zeros(0, np.int64)
    table, ids = _table(start, first, end, npts, peak, vsum, vcount, anchor, min_points, times, radius, area)

    # pass 3: each epoch's object ids
    if write is not None:
        for k in range(n_epochs):
            sign, _, _ = signs(k)
            comp, _ = _components(sign, i, j)
            labels = np.zeros(m, np.int32)
            at = comp >= 0
            labels[at] = ids[root[comp[at] + offsets[k]]]
            write(k, labels)
    return table


def onsets(smoothed: np.ndarray, sigma: np.ndarray, step: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(onset epoch or -1, kind: 0 none, 1 step, 2 gradual) per core point of a block (epochs, points):
    the first epoch of two running with significant smoothed change, or the step before it."""
    sig = np.isfinite(smoothed) & (np.abs(smoothed) > 1.96 * sigma)
    run = sig[:-1] & sig[1:] if len(sig) > 1 else sig
    has = run.any(axis=0)
    first = np.where(has, np.argmax(run, axis=0), -1)
    stepped = (step >= 0) & (first >= 0) & (step <= first)
    onset = np.where(stepped, step, first).astype(np.int32)
    kind = np.where(stepped, 1, np.where(first >= 0, 2, 0)).astype(np.int8)
    return onset, kind
