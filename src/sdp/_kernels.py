"""Numba kernels on block-sparse grids (private).

Storage, shared by every kernel: ``directory`` is an int32 array over the grid's box of blocks
(-1 = block not allocated, else its row in ``blocks``); ``blocks`` is float32 of shape
(m, 512), node (x, y, z) of a block at column ``x*64 + y*8 + z``; ``keys`` (m, 3) int64 holds
each block's position in the directory. Node coordinates ``u`` are float64 grid units
(``(p - origin) / l``). Every kernel is compiled once and cached on disk (``cache=True``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

B = 8  # must equal grid.BLOCK
B2 = B * B
B3 = B * B * B


@nb.njit(cache=True)
def finite_bounds(points):
    """(lo, hi, number of rows holding NaN/Inf) of an (n, 3) array, over its finite rows, in one pass."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    bad = 0
    for p in range(points.shape[0]):
        x, y, z = points[p, 0], points[p, 1], points[p, 2]
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            bad += 1
            continue
        lo[0] = min(lo[0], x)
        lo[1] = min(lo[1], y)
        lo[2] = min(lo[2], z)
        hi[0] = max(hi[0], x)
        hi[1] = max(hi[1], y)
        hi[2] = max(hi[2], z)
    return lo, hi, bad


@nb.njit(parallel=True, cache=True)
def mark_blocks(u, lo_off, hi_off, shape_blocks):
    """Occupancy (uint8, directory-shaped) of blocks holding nodes floor(u)-lo_off … floor(u)+hi_off.

    Threads may write the same 1 to one cell at once, which is harmless.
    """
    occ = np.zeros((shape_blocks[0], shape_blocks[1], shape_blocks[2]), np.uint8)
    for p in nb.prange(u.shape[0]):
        i0 = int(math.floor(u[p, 0]))
        i1 = int(math.floor(u[p, 1]))
        i2 = int(math.floor(u[p, 2]))
        for bx in range((i0 - lo_off) // B, (i0 + hi_off) // B + 1):
            for by in range((i1 - lo_off) // B, (i1 + hi_off) // B + 1):
                for bz in range((i2 - lo_off) // B, (i2 + hi_off) // B + 1):
                    occ[bx, by, bz] = 1
    return occ


@nb.njit(cache=True)
def bin_trilinear(u, directory, blocks):
    """Add each point's unit weight to its cell's 8 nodes, split by trilinear weights."""
    for p in range(u.shape[0]):
        x, y, z = u[p, 0], u[p, 1], u[p, 2]
        ix, iy, iz = int(math.floor(x)), int(math.floor(y)), int(math.floor(z))
        fx, fy, fz = x - ix, y - iy, z - iz
        for a in range(2):
            wx = fx if a else 1.0 - fx
            nx = ix + a
            for b in range(2):
                wy = fy if b else 1.0 - fy
                ny = iy + b
                for c in range(2):
                    wz = fz if c else 1.0 - fz
                    nz = iz + c
                    blk = directory[nx >> 3, ny >> 3, nz >> 3]
                    blocks[blk, (nx & 7) * B2 + (ny & 7) * B + (nz & 7)] += wx * wy * wz


@nb.njit(cache=True)
def splat_exact(u, directory, blocks, inv_two_s2, rmax, reach):
    """Add exp(-d²/2σ²) of every point to every node within the cube |d|∞ <= rmax (grid units)."""
    n_t = 2 * reach + 2
    wx = np.empty(n_t)
    wy = np.empty(n_t)
    wz = np.empty(n_t)
    for p in range(u.shape[0]):
        x, y, z = u[p, 0], u[p, 1], u[p, 2]
        fx = int(math.floor(x)) - reach
        fy = int(math.floor(y)) - reach
        fz = int(math.floor(z)) - reach
        for t in range(n_t):
            d = fx + t - x
            wx[t] = math.exp(-d * d * inv_two_s2) if abs(d) <= rmax else 0.0
            d = fy + t - y
            wy[t] = math.exp(-d * d * inv_two_s2) if abs(d) <= rmax else 0.0
            d = fz + t - z
            wz[t] = math.exp(-d * d * inv_two_s2) if abs(d) <= rmax else 0.0
        for tx in range(n_t):
            if wx[tx] == 0.0:
                continue
            nx = fx + tx
            for ty in range(n_t):
                w2 = wx[tx] * wy[ty]
                if w2 == 0.0:
                    continue
                ny = fy + ty
                for tz in range(n_t):
                    w = w2 * wz[tz]
                    if w == 0.0:
                        continue
                    nz = fz + tz
                    blk = directory[nx >> 3, ny >> 3, nz >> 3]
                    blocks[blk, (nx & 7) * B2 + (ny & 7) * B + (nz & 7)] += w


@nb.njit(parallel=True, cache=True)
def nonzero_blocks(blocks):
    """Per block: does it hold any nonzero value?"""
    out = np.zeros(blocks.shape[0], np.bool_)
    for b in nb.prange(blocks.shape[0]):
        for n in range(B3):
            if blocks[b, n] != 0.0:
                out[b] = True
                break
    return out


@nb.njit(parallel=True, cache=True)
def blur_pass(src, src_nonzero, dst, dst_nonzero, directory, keys, axis, taps):
    """One separable pass: dst = src convolved with ``taps`` (odd length) along ``axis``.

    Nodes of blocks that are not allocated read as 0; output is written for every allocated
    block. Source blocks flagged all-zero in ``src_nonzero`` are skipped; ``dst_nonzero``
    receives the flags of the output. Each tap updates all 64 lines of a block at once.
    """
    r = (taps.shape[0] - 1) // 2
    nbr = (r + B - 1) // B
    dlen = directory.shape[axis]
    for b in nb.prange(keys.shape[0]):
        neigh = np.empty(2 * nbr + 1, np.int64)
        any_src = False
        for j in range(-nbr, nbr + 1):
            k0, k1, k2 = keys[b, 0], keys[b, 1], keys[b, 2]
            if axis == 0:
                k0 += j
            elif axis == 1:
                k1 += j
            else:
                k2 += j
            ka = k0 if axis == 0 else (k1 if axis == 1 else k2)
            nb_blk = directory[k0, k1, k2] if 0 <= ka < dlen else -1
            if nb_blk >= 0 and not src_nonzero[nb_blk]:
                nb_blk = -1
            neigh[j + nbr] = nb_blk
            any_src = any_src or nb_blk >= 0
        out = dst[b]
        out[:] = 0.0
        dst_nonzero[b] = any_src
        if not any_src:
            continue
        for x in range(B):
            for k in range(taps.shape[0]):
                s = x + k - r + nbr * B
                sb = neigh[s // B]
                if sb < 0:
                    continue
                ls = s % B
                w = taps[k]
                inp = src[sb]
                if axis == 0:
                    for li in range(B2):
                        out[x * B2 + li] += w * inp[ls * B2 + li]
                elif axis == 1:
                    for a in range(B):
                        for z in range(B):
                            out[a * B2 + x * B + z] += w * inp[a * B2 + ls * B + z]
                else:
                    for a in range(B):
                        for y in range(B):
                            out[a * B2 + y * B + x] += w * inp[a * B2 + y * B + ls]


@nb.njit(parallel=True, cache=True)
def trilinear(points, origin, voxel, directory, blocks, out):
    """out[p] = trilinear interpolation of the node values at world position points[p];
    0 outside the grid, NaN for NaN input. Grid units are (p - origin) / voxel."""
    d0, d1, d2 = directory.shape
    n0, n1, n2 = d0 * B, d1 * B, d2 * B
    for p in nb.prange(points.shape[0]):
        x = (points[p, 0] - origin[0]) / voxel
        y = (points[p, 1] - origin[1]) / voxel
        z = (points[p, 2] - origin[2]) / voxel
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            out[p] = np.nan
            continue
        if x <= -1.0 or y <= -1.0 or z <= -1.0 or x >= n0 or y >= n1 or z >= n2:
            out[p] = 0.0
            continue
        ix, iy, iz = int(math.floor(x)), int(math.floor(y)), int(math.floor(z))
        fx, fy, fz = x - ix, y - iy, z - iz
        acc = 0.0
        for a in range(2):
            nx = ix + a
            if nx < 0 or nx >= n0:
                continue
            wx = fx if a else 1.0 - fx
            for b in range(2):
                ny = iy + b
                if ny < 0 or ny >= n1:
                    continue
                wy = fy if b else 1.0 - fy
                for c in range(2):
                    nz = iz + c
                    if nz < 0 or nz >= n2:
                        continue
                    blk = directory[nx >> 3, ny >> 3, nz >> 3]
                    if blk < 0:
                        continue
                    wz = fz if c else 1.0 - fz
                    acc += wx * wy * wz * blocks[blk, (nx & 7) * B2 + (ny & 7) * B + (nz & 7)]
        out[p] = acc


@nb.njit(parallel=True, cache=True)
def trilinear_gradient(points, origin, voxel, directory, blocks, val, grad):
    """val[p], grad[p] = the trilinear interpolant and its gradient (per world unit) at
    world position points[p]; 0 outside the grid or where blocks are missing."""
    d0, d1, d2 = directory.shape
    n0, n1, n2 = d0 * B, d1 * B, d2 * B
    for p in nb.prange(points.shape[0]):
        x = (points[p, 0] - origin[0]) / voxel
        y = (points[p, 1] - origin[1]) / voxel
        z = (points[p, 2] - origin[2]) / voxel
        val[p], grad[p, 0], grad[p, 1], grad[p, 2] = 0.0, 0.0, 0.0, 0.0
        if not (x > 0.0 and y > 0.0 and z > 0.0 and x < n0 - 1 and y < n1 - 1 and z < n2 - 1):
            continue  # also NaN
        ix, iy, iz = int(x), int(y), int(z)
        fx, fy, fz = x - ix, y - iy, z - iz
        for a in range(2):
            wx, dx = (fx, 1.0) if a else (1.0 - fx, -1.0)
            for b in range(2):
                wy, dy = (fy, 1.0) if b else (1.0 - fy, -1.0)
                for c in range(2):
                    nx, ny, nz = ix + a, iy + b, iz + c
                    blk = directory[nx >> 3, ny >> 3, nz >> 3]
                    if blk < 0:
                        continue
                    v = blocks[blk, (nx & 7) * B2 + (ny & 7) * B + (nz & 7)]
                    wz, dz = (fz, 1.0) if c else (1.0 - fz, -1.0)
                    val[p] += wx * wy * wz * v
                    grad[p, 0] += dx * wy * wz * v / voxel
                    grad[p, 1] += wx * dy * wz * v / voxel
                    grad[p, 2] += wx * wy * dz * v / voxel


@nb.njit(cache=True)
def node_values(nodes, directory, blocks):
    """Values at integer node coordinates (k, 3); 0 where no block is allocated."""
    d0, d1, d2 = directory.shape
    out = np.zeros(nodes.shape[0], np.float32)
    for p in range(nodes.shape[0]):
        nx, ny, nz = nodes[p, 0], nodes[p, 1], nodes[p, 2]
        if 0 <= nx < d0 * B and 0 <= ny < d1 * B and 0 <= nz < d2 * B:
            blk = directory[nx >> 3, ny >> 3, nz >> 3]
            if blk >= 0:
                out[p] = blocks[blk, (nx & 7) * B2 + (ny & 7) * B + (nz & 7)]
    return out


@nb.njit(cache=True)
def gather_box(directory, blocks, lo, shape):
    """Dense float32 copy of the nodes lo … lo+shape-1 (0 where nothing is allocated)."""
    out = np.zeros((shape[0], shape[1], shape[2]), np.float32)
    d0, d1, d2 = directory.shape
    for i in range(shape[0]):
        nx = lo[0] + i
        if nx < 0 or nx >= d0 * B:
            continue
        for j in range(shape[1]):
            ny = lo[1] + j
            if ny < 0 or ny >= d1 * B:
                continue
            for k in range(shape[2]):
                nz = lo[2] + k
                if nz < 0 or nz >= d2 * B:
                    continue
                blk = directory[nx >> 3, ny >> 3, nz >> 3]
                if blk >= 0:
                    out[i, j, k] = blocks[blk, (nx & 7) * B2 + (ny & 7) * B + (nz & 7)]
    return out


@nb.njit(cache=True)
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@nb.njit(parallel=True, cache=True)
def _negative_blocks(values):
    out = np.zeros(values.shape[0], np.bool_)
    for b in nb.prange(values.shape[0]):
        for n in range(B3):
            if values[b, n] < 0:
                out[b] = True
                break
    return out


@nb.njit(cache=True)
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


@nb.njit(cache=True)
def _union(parent, a, b):
    ra = _find(parent, a)
    rb = _find(parent, b)
    if ra != rb:
        parent[max(ra, rb)] = min(ra, rb)


@nb.njit(cache=True)
def label_nodes(values, directory, keys):
    """6-connected components of the nodes where ``values`` (m, 512) is negative.

    Union-find over the blocks that hold a negative node only. Returns (labels (m, 512)
    int32, -1 elsewhere, number of components).
    """
    m = values.shape[0]
    active = _negative_blocks(values)
    slot = np.full(m, -1, np.int64)  # block -> its row among the active blocks
    n_active = 0
    for blk in range(m):
        if active[blk]:
            slot[blk] = n_active
            n_active += 1
    parent = np.arange(n_active * B3)
    strides = (B2, B, 1)
    for blk in range(m):
        if slot[blk] < 0:
            continue
        base = slot[blk] * B3
        for axis in range(3):
            stride = strides[axis]
            nb_blk = _neighbour_block(directory, keys, blk, axis)
            nb_base = slot[nb_blk] * B3 if nb_blk >= 0 else -1
            for n in range(B3):
                if values[blk, n] >= 0:
                    continue
                if (n // stride) % B > 0:
                    if values[blk, n - stride] < 0:
                        _union(parent, base + n, base + n - stride)
                elif nb_base >= 0 and values[nb_blk, n + (B - 1) * stride] < 0:
                    _union(parent, base + n, nb_base + n + (B - 1) * stride)
    labels = np.full((m, B3), -1, np.int32)
    root_label = np.full(n_active * B3, -1, np.int64)
    count = 0
    for blk in range(m):
        if slot[blk] < 0:
            continue
        for n in range(B3):
            if values[blk, n] < 0:
                root = _find(parent, slot[blk] * B3 + n)
                if root_label[root] < 0:
                    root_label[root] = count
                    count += 1
                labels[blk, n] = root_label[root]
    return labels, count


@nb.njit(parallel=True, cache=True)
def corner_labels(u, directory, labels, values):
    """For each point, the label of the cell corner with the lowest value among labelled corners.

    -1 where no corner of the point's cell carries a label.
    """
    d0, d1, d2 = directory.shape
    out = np.full(u.shape[0], -1, np.int64)
    for p in nb.prange(u.shape[0]):
        best = np.inf
        ix, iy, iz = int(math.floor(u[p, 0])), int(math.floor(u[p, 1])), int(math.floor(u[p, 2]))
        for a in range(2):
            nx = ix + a
            for b in range(2):
                ny = iy + b
                for c in range(2):
                    nz = iz + c
                    if nx < 0 or ny < 0 or nz < 0 or nx >= d0 * B or ny >= d1 * B or nz >= d2 * B:
                        continue
                    blk = directory[nx >> 3, ny >> 3, nz >> 3]
                    if blk < 0:
                        continue
                    i = (nx & 7) * B2 + (ny & 7) * B + (nz & 7)
                    if labels[blk, i] >= 0 and values[blk, i] < best:
                        best = values[blk, i]
                        out[p] = labels[blk, i]
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
        for n in range(B3):
            gb = b_blocks[j, n] if j >= 0 else np.float32(0.0)
            out[i, n] = max(fa_h - a_blocks[i, n], gb - fb_h)
    return out


@nb.njit(cache=True)
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
