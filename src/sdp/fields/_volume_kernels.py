"""Numba kernels of difference volumes and their regions (:mod:`sdp.change._regions`, :mod:`sdp.fields._boolean`):
the stored difference max(F_a, −F_b), the same value node by node without storing it (masks of
negative nodes, trilinear values at points), union-find over runs of negative nodes, the label of
each point's cell, and per-label point statistics.

Block storage as in :mod:`sdp.fields._kernels` (``keys``, ``blocks``, ``directory``). Every kernel is
compiled once and cached on disk (``cache=True``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .._core import _parallel  # noqa: F401  (how OpenMP's workers wait: set before a parallel kernel runs)
from .._core._disjoint import find, union
from ._lattice import BLOCK as B

B2 = B * B
B3 = B * B * B


# ---------------------------------------------------------------------------- volumes (sdp.regions)
# A volume (sdp.change._regions.Volume) is the set of nodes of field a's blocks where
# v = max(ha − A, B − hb) < 0; its kernels take (a_keys, a_blocks, ha, b_blocks, b_directory, shift,
# hb). With B the other field's G (its block found through ``b_directory`` at a's key + ``shift``;
# 0 where it holds none), v is the difference max(F_a, −F_b), computed node by node in float32
# exactly as :func:`difference_blocks` stores it, without storing it; with no B (hb = inf), F_a.
@nb.njit(cache=True, inline="always")
def _partner(a_keys, blk, b_directory, shift):
    """Row in b of the block at a's block ``blk`` (-1: b holds none)."""
    k0, k1, k2 = a_keys[blk, 0] + shift[0], a_keys[blk, 1] + shift[1], a_keys[blk, 2] + shift[2]
    d = b_directory.shape
    if 0 <= k0 < d[0] and 0 <= k1 < d[1] and 0 <= k2 < d[2]:
        return b_directory[k0, k1, k2]
    return -1


@nb.njit(cache=True, inline="always")
def _volume_value(a_blocks, fa_h, b_blocks, j, fb_h, blk, n):
    """v at node ``n`` of a's block ``blk`` (``j``: its partner in b), float32 like difference_blocks."""
    if j >= 0:
        return max(fa_h - a_blocks[blk, n], b_blocks[j, n] - fb_h)
    return max(fa_h - a_blocks[blk, n], -fb_h)


@nb.njit(parallel=True, cache=True)
def volume_masks(a_keys, a_blocks, ha, b_blocks, b_directory, shift, hb):
    """Per block of a, per line of 8 nodes along z (columns 8j … 8j+7): bit z set where v < 0,
    that is where A > ha and B < hb (the sign of a float32 difference is exact)."""
    fa_h, fb_h = np.float32(ha), np.float32(hb)
    masks = np.zeros((a_blocks.shape[0], B2), np.uint8)
    for blk in nb.prange(a_blocks.shape[0]):
        j = _partner(a_keys, blk, b_directory, shift)
        if j < 0 and not fb_h > 0:
            continue  # v >= -hb >= 0 throughout
        above = 0
        for n in range(B3):  # a count, not a search: it vectorizes
            above += a_blocks[blk, n] > fa_h
        if above == 0:
            continue  # A <= ha throughout (most blocks of the halo): v >= 0
        for line in range(B2):
            mk = 0
            if j >= 0:
                for z in range(B):
                    n = line * B + z
                    mk |= ((a_blocks[blk, n] > fa_h) & (b_blocks[j, n] < fb_h)) << z
            else:
                for z in range(B):
                    mk |= (a_blocks[blk, line * B + z] > fa_h) << z
            masks[blk, line] = mk
    return masks


@nb.njit(cache=True, nogil=True)
def _partners(a_keys, b_directory, shift):
    """Row in b of each of a's blocks (-1: b holds none)."""
    out = np.empty(a_keys.shape[0], np.int64)
    for blk in range(a_keys.shape[0]):
        out[blk] = _partner(a_keys, blk, b_directory, shift)
    return out


@nb.njit(parallel=True, cache=True)
def volume_at(points, origin, voxel, a_directory, a_keys, a_blocks, ha, b_blocks, b_directory, shift, hb, out,
              signs):
    """out[p] = trilinear interpolation of v at world position points[p] (finite), as
    :func:`trilinear` interpolates an array of v on a's blocks: nodes outside a's blocks and
    points outside the grid read as 0.

    With ``signs``, only the sign of out[p] is kept where it is decided early: a point whose cell
    lies in one block with B > hb at all 8 corners has v > 0 at each, so its interpolation is
    positive, and gets 1.0 without reading A (most points of a comparison: unchanged ones)."""
    fa_h, fb_h = np.float32(ha), np.float32(hb)
    partner = _partners(a_keys, b_directory, shift)
    d0, d1, d2 = a_directory.shape
    for p in nb.prange(points.shape[0]):
        x = (points[p, 0] - origin[0]) / voxel
        y = (points[p, 1] - origin[1]) / voxel
        z = (points[p, 2] - origin[2]) / voxel
        ix, iy, iz = int(math.floor(x)), int(math.floor(y)), int(math.floor(z))
        fx, fy, fz = x - ix, y - iy, z - iz
        gx, gy, gz = 1.0 - fx, 1.0 - fy, 1.0 - fz
        if ix >= 0 and iy >= 0 and iz >= 0 and (ix & 7) < 7 and (iy & 7) < 7 and (iz & 7) < 7 and \
                ix < d0 * B and iy < d1 * B and iz < d2 * B:
            # the cell lies in one block (as (7/8)³ of the cells do): one lookup in each field, the
            # sum below unrolled in the same order
            blk = a_directory[ix >> 3, iy >> 3, iz >> 3]
            if blk < 0:
                out[p] = 0.0
                continue
            j = partner[blk]
            n = (ix & 7) * B2 + (iy & 7) * B + (iz & 7)
            if j >= 0:
                bb = b_blocks[j]
                b0, b1, b2, b3 = bb[n] - fb_h, bb[n + 1] - fb_h, bb[n + B] - fb_h, bb[n + B + 1] - fb_h
                b4, b5 = bb[n + B2] - fb_h, bb[n + B2 + 1] - fb_h
                b6, b7 = bb[n + B2 + B] - fb_h, bb[n + B2 + B + 1] - fb_h
                if signs and min(b0, b1, b2, b3, b4, b5, b6, b7) > 0:
                    out[p] = 1.0
                    continue
            else:
                b0 = b1 = b2 = b3 = b4 = b5 = b6 = b7 = -fb_h
            ab = a_blocks[blk]
            acc = 0.0
            acc += gx * gy * gz * max(fa_h - ab[n], b0)
            acc += gx * gy * fz * max(fa_h - ab[n + 1], b1)
            acc += gx * fy * gz * max(fa_h - ab[n + B], b2)
            acc += gx * fy * fz * max(fa_h - ab[n + B + 1], b3)
            acc += fx * gy * gz * max(fa_h - ab[n + B2], b4)
            acc += fx * gy * fz * max(fa_h - ab[n + B2 + 1], b5)
            acc += fx * fy * gz * max(fa_h - ab[n + B2 + B], b6)
            acc += fx * fy * fz * max(fa_h - ab[n + B2 + B + 1], b7)
            out[p] = acc
            continue
        acc = 0.0
        if ix >= 0 and iy >= 0 and iz >= 0 and ix + 1 < d0 * B and iy + 1 < d1 * B and iz + 1 < d2 * B:
            # the cell lies across blocks inside the grid (a third of a scan's points): per axis, the
            # blocks and offsets of its two nodes once, then the corners in the order below, no checks
            bx0, bx1, ox0, ox1 = ix >> 3, (ix + 1) >> 3, (ix & 7) * B2, ((ix + 1) & 7) * B2
            by0, by1, oy0, oy1 = iy >> 3, (iy + 1) >> 3, (iy & 7) * B, ((iy + 1) & 7) * B
            bz0, bz1, oz0, oz1 = iz >> 3, (iz + 1) >> 3, iz & 7, (iz + 1) & 7
            for a in range(2):
                bx, ox, wx = (bx1, ox1, fx) if a else (bx0, ox0, gx)
                for b in range(2):
                    by, oy, wy = (by1, oy1, fy) if b else (by0, oy0, gy)
                    for c in range(2):
                        bz, oz, wz = (bz1, oz1, fz) if c else (bz0, oz0, gz)
                        blk = a_directory[bx, by, bz]
                        if blk >= 0:
                            acc += wx * wy * wz * _volume_value(a_blocks, fa_h, b_blocks, partner[blk], fb_h, blk,
                                                                ox + oy + oz)
            out[p] = acc
            continue
        for a in range(2):
            nx = ix + a
            if nx < 0 or nx >= d0 * B:
                continue
            wx = fx if a else gx
            for b in range(2):
                ny = iy + b
                if ny < 0 or ny >= d1 * B:
                    continue
                wy = fy if b else gy
                for c in range(2):
                    nz = iz + c
                    if nz < 0 or nz >= d2 * B:
                        continue
                    blk = a_directory[nx >> 3, ny >> 3, nz >> 3]
                    if blk < 0:
                        continue
                    wz = fz if c else gz
                    v = _volume_value(a_blocks, fa_h, b_blocks, partner[blk], fb_h, blk,
                                      (nx & 7) * B2 + (ny & 7) * B + (nz & 7))
                    acc += wx * wy * wz * v
        out[p] = acc


@nb.njit(cache=True, nogil=True)
def _neighbour_block(directory, keys, blk, axis):
    k0, k1, k2 = keys[blk, 0], keys[blk, 1], keys[blk, 2]
    if axis == 0:
        k0 -= 1
    elif axis == 1:
        k1 -= 1
    else:
        k2 -= 1
    if k0 < 0 or k1 < 0 or k2 < 0:
        return -1
    return directory[k0, k1, k2]


@nb.njit(cache=True, nogil=True)
def label_nodes(masks, directory, keys):
    """6-connected components of the nodes set in ``masks`` ((m, 64) uint8, :func:`volume_masks`).

    Union-find runs over runs, not nodes: the negative nodes of a line of 8 along z split into
    runs of consecutive nodes (3–4 nodes each on change volumes of Kinect pairs); a run joins the
    runs it overlaps in the line before it along y and along x, and along z the run that ends
    the same line in the block below. Only blocks holding a negative node take part.
    Components are numbered in the order of their first node (blocks in row order, nodes in
    column order). Returns ``slot`` (m,) int64, each block's row in ``labels`` (-1: no negative
    node); ``labels`` (rows, 512) int32, the component of each negative node of those blocks (-1
    elsewhere); and the number of nodes of each component.
    """
    m = masks.shape[0]
    slot = np.full(m, -1, np.int64)
    n_active = 0
    for blk in range(m):
        for j in range(B2):
            if masks[blk, j]:
                slot[blk] = n_active
                n_active += 1
                break
    active = np.empty(n_active, np.int64)  # block of each slot
    for blk in range(m):
        if slot[blk] >= 0:
            active[slot[blk]] = blk
    # the runs of line j of slot s are first[s*64 + j] … first[s*64 + j + 1] - 1
    first = np.zeros(n_active * B2 + 1, np.int64)
    for s in range(n_active):
        for j in range(B2):
            mk = np.int64(masks[active[s], j])
            first[s * B2 + j + 1] = first[s * B2 + j] + _popcount8(mk & ~(mk << 1))  # a run starts at each
    run_mask = np.empty(first[-1], np.int64)
    for s in range(n_active):
        for j in range(B2):
            mk = np.int64(masks[active[s], j])
            i = first[s * B2 + j]
            while mk:
                run = ((mk + (mk & -mk)) ^ mk) & mk  # adding the lowest set bit clears the lowest run
                run_mask[i] = run
                i += 1
                mk &= ~run
    parent = np.arange(run_mask.shape[0])
    below = np.empty(3, np.int64)  # slot of the block before along x, y, z (-1: none)
    for s in range(n_active):
        for axis in range(3):
            nb_blk = _neighbour_block(directory, keys, active[s], axis)
            below[axis] = slot[nb_blk] if nb_blk >= 0 else -1
        for j in range(B2):
            r0, r1 = first[s * B2 + j], first[s * B2 + j + 1]
            if r0 == r1:
                continue
            t = below[2]
            if run_mask[r0] & 1 and t >= 0 and masks[active[t], j] & 128:
                union(parent, r0, first[t * B2 + j + 1] - 1)  # the last run of that line
            for axis in range(2):  # x, then y: the line before, in this block or the block below
                stride = B if axis == 0 else 1
                if (j // stride) % B > 0:
                    t, jj = s, j - stride
                else:
                    t, jj = below[axis], j + (B - 1) * stride
                if t < 0 or not masks[active[t], jj]:
                    continue
                for r in range(r0, r1):
                    for q in range(first[t * B2 + jj], first[t * B2 + jj + 1]):
                        if run_mask[r] & run_mask[q]:
                            union(parent, r, q)
    labels = np.empty((n_active, B3), np.int32)  # each line written whole below, while it is in cache
    root_label = np.full(run_mask.shape[0], -1, np.int64)
    node_counts = np.zeros(run_mask.shape[0], np.int64)
    count = 0
    for s in range(n_active):
        row = labels[s]
        for j in range(B2):
            for z in range(B):
                row[j * B + z] = -1
            for r in range(first[s * B2 + j], first[s * B2 + j + 1]):
                root = find(parent, r)
                if root_label[root] < 0:
                    root_label[root] = count
                    count += 1
                g = root_label[root]
                mk = run_mask[r]
                for z in range(B):
                    if mk >> z & 1:
                        row[j * B + z] = g
                node_counts[g] += _popcount8(mk)
    return slot, labels, node_counts[:count]


@nb.njit(cache=True, inline="always")
def _popcount8(mk):
    """Set bits of the low byte of ``mk``."""
    n = 0
    for z in range(B):
        n += mk >> z & 1
    return n


@nb.njit(parallel=True, cache=True)
def corner_labels(u, directory, slot, labels, a_keys, a_blocks, ha, b_blocks, b_directory, shift, hb):
    """For each point, the label of the cell corner with the lowest v among labelled corners.

    ``slot`` and ``labels`` as returned by :func:`label_nodes`; -1 where no corner of the
    point's cell carries a label.
    """
    fa_h, fb_h = np.float32(ha), np.float32(hb)
    partner = _partners(a_keys, b_directory, shift)
    d0, d1, d2 = directory.shape
    out = np.full(u.shape[0], -1, np.int64)
    for p in nb.prange(u.shape[0]):
        best = np.inf
        ix, iy, iz = int(math.floor(u[p, 0])), int(math.floor(u[p, 1])), int(math.floor(u[p, 2]))
        for a in range(2):
            nx = ix + a
            if nx < 0 or nx >= d0 * B:
                continue
            for b in range(2):
                ny = iy + b
                if ny < 0 or ny >= d1 * B:
                    continue
                for c in range(2):
                    nz = iz + c
                    if nz < 0 or nz >= d2 * B:
                        continue
                    blk = directory[nx >> 3, ny >> 3, nz >> 3]
                    if blk < 0 or slot[blk] < 0:
                        continue
                    i = (nx & 7) * B2 + (ny & 7) * B + (nz & 7)
                    label = labels[slot[blk], i]
                    if label < 0:
                        continue
                    v = _volume_value(a_blocks, fa_h, b_blocks, partner[blk], fb_h, blk, i)
                    if v < best:
                        best = v
                        out[p] = label
    return out


@nb.njit(parallel=True, cache=True)
def difference_blocks(a_blocks, a_keys, ha, b_blocks, b_directory, b_shift, hb):
    """max(F_a, −F_b) at the nodes of a's blocks, with F = h − G (float32, like a_blocks).

    Block i of a sits at position a_keys[i] + b_shift of b's directory (one shared lattice);
    where b holds no block, G_b = 0.
    """
    out = np.empty(a_blocks.shape, np.float32)
    d = b_directory.shape
    fa_h, fb_h = np.float32(ha), np.float32(hb)
    for i in nb.prange(a_blocks.shape[0]):
        k0, k1, k2 = a_keys[i, 0] + b_shift[0], a_keys[i, 1] + b_shift[1], a_keys[i, 2] + b_shift[2]
        j = -1
        if 0 <= k0 < d[0] and 0 <= k1 < d[1] and 0 <= k2 < d[2]:
            j = b_directory[k0, k1, k2]
        if j >= 0:
            for n in range(B3):
                out[i, n] = max(fa_h - a_blocks[i, n], b_blocks[j, n] - fb_h)
        else:
            for n in range(B3):
                out[i, n] = max(fa_h - a_blocks[i, n], -fb_h)
    return out


@nb.njit(cache=True, nogil=True)
def group_stats(points, labels, n_labels):
    """Count, coordinate sums, minima and maxima of the points of each label (-1 skipped)."""
    count = np.zeros(n_labels, np.int64)
    sums = np.zeros((n_labels, 3))
    lo = np.full((n_labels, 3), np.inf)
    hi = np.full((n_labels, 3), -np.inf)
    for p in range(points.shape[0]):
        g = labels[p]
        if g < 0:
            continue
        count[g] += 1
        for d in range(3):
            v = points[p, d]
            sums[g, d] += v
            lo[g, d] = min(lo[g, d], v)
            hi[g, d] = max(hi[g, d], v)
    return count, sums, lo, hi



@nb.njit(cache=True, inline="always")
def _before(k0, k1, k2, n, first):
    """(k0, k1, k2, n) comes before ``first`` (4,) in lexicographic order."""
    if k0 != first[0]:
        return k0 < first[0]
    if k1 != first[1]:
        return k1 < first[1]
    if k2 != first[2]:
        return k2 < first[2]
    return n < first[3]


@nb.njit(cache=True, inline="always")
def _on_low_face(keys, s, n, lo):
    """Is node ``n`` of block ``s`` on the part's −x or −y face (its first block along x or y)?"""
    return (keys[s, 0] == lo[0] and n // B2 == 0) or (keys[s, 1] == lo[1] and (n // B) % B == 0)


@nb.njit(cache=True, nogil=True)
def part_summary(lab, own, keys, lo, n_labels):
    """One pass over the labels of a part's blocks (:func:`sdp.change._regions.label_part`).

    ``lab`` (m, 512) int32 labels of the part's blocks with a negative node (-1 elsewhere), ``own``
    (m,) whether a block is the part's own, ``keys`` (m, 3) their global keys (any order), ``lo``
    the part's first block along x and y. Returns the own nodes of each label, each label's first
    own node (key x, y, z, node; int64 max where none) and the shared nodes (own nodes on the −x/−y
    faces, every node beyond the +x/+y faces) as global node coordinates (f, 3) with their labels (f,).
    """
    counts = np.zeros(n_labels, np.int64)
    first = np.full((n_labels, 4), np.iinfo(np.int64).max, np.int64)
    n_shared = 0
    for s in range(lab.shape[0]):
        for n in range(B3):
            g = lab[s, n]
            if g < 0:
                continue
            if own[s]:
                counts[g] += 1
                if _before(keys[s, 0], keys[s, 1], keys[s, 2], n, first[g]):
                    first[g, 0], first[g, 1], first[g, 2], first[g, 3] = keys[s, 0], keys[s, 1], keys[s, 2], n
                if _on_low_face(keys, s, n, lo):
                    n_shared += 1
            else:
                n_shared += 1
    nodes = np.empty((n_shared, 3), np.int64)
    labels = np.empty(n_shared, np.int64)
    i = 0
    for s in range(lab.shape[0]):
        for n in range(B3):
            g = lab[s, n]
            if g < 0:
                continue
            if own[s] and not _on_low_face(keys, s, n, lo):
                continue
            nodes[i, 0] = keys[s, 0] * B + n // B2
            nodes[i, 1] = keys[s, 1] * B + (n // B) % B
            nodes[i, 2] = keys[s, 2] * B + n % B
            labels[i] = g
            i += 1
    return counts, first, nodes, labels
