"""Numba kernels of the block-sparse grid (:mod:`sdp.fields._density`, :mod:`sdp.fields._blocks`): block marking,
trilinear binning, the exact splat, the separable blur, block addition, trilinear queries and
gathers of node values.

Storage (:class:`sdp.fields._blocks.Blocks`): ``directory`` is an int32 array over the grid's box of
blocks (-1 = block not allocated, else its row in ``blocks``); ``blocks`` is float32 of shape
(m, 512), node (x, y, z) of a block at column ``x*64 + y*8 + z``; ``keys`` (m, 3) int64 holds
each block's position in the directory. Node coordinates ``u`` are float64 grid units
(``(p - origin) / l``). Every kernel is compiled once and cached on disk (``cache=True``).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .._core import _parallel  # noqa: F401  (how OpenMP's workers wait: set before a parallel kernel runs)
from ._lattice import BLOCK as B

B2 = B * B
B3 = B * B * B


@nb.njit(cache=True, nogil=True)
def mark_blocks(points, origin, voxel, lo_off, hi_off, shape_blocks):
    """Occupancy (uint8, directory-shaped) of blocks holding nodes floor(u)-lo_off … floor(u)+hi_off,
    u = (points - origin) / voxel the points' grid units (computed on the fly, not stored).

    Along one axis the blocks reached from a node depend only on its block and its position
    in the block, and take one of at most four ranges (the lowest block reached is one of two,
    as is the highest). A first pass records, per block holding points, which of the 4³
    combinations its points use (a 64-bit mask); a second marks the ranges of each recorded
    combination once, instead of once per point.
    """
    lo_min = -lo_off // B  # lowest block offset reached from position 0 of a block: it or one above
    hi_min = hi_off // B  # highest block offset reached from position 0: it or one above
    axis_code = np.empty(B, np.int64)  # per position in a block: (lowest, highest) block reached
    for r in range(B):
        axis_code[r] = ((r - lo_off) // B - lo_min) * 2 + ((r + hi_off) // B - hi_min)
    codes = np.zeros((shape_blocks[0], shape_blocks[1], shape_blocks[2]), np.uint64)
    for p in range(points.shape[0]):
        ix = int(math.floor((points[p, 0] - origin[0]) / voxel))
        iy = int(math.floor((points[p, 1] - origin[1]) / voxel))
        iz = int(math.floor((points[p, 2] - origin[2]) / voxel))
        code = axis_code[ix & 7] * 16 + axis_code[iy & 7] * 4 + axis_code[iz & 7]
        codes[ix >> 3, iy >> 3, iz >> 3] |= np.uint64(1) << np.uint64(code)
    occ = np.zeros((shape_blocks[0], shape_blocks[1], shape_blocks[2]), np.uint8)
    for bx in range(shape_blocks[0]):
        for by in range(shape_blocks[1]):
            for bz in range(shape_blocks[2]):
                mask = codes[bx, by, bz]
                if mask == 0:
                    continue
                for code in range(64):
                    if not (mask >> np.uint64(code)) & np.uint64(1):
                        continue
                    cx, cy, cz = code >> 4, (code >> 2) & 3, code & 3
                    for x in range(bx + lo_min + (cx >> 1), bx + hi_min + (cx & 1) + 1):
                        for y in range(by + lo_min + (cy >> 1), by + hi_min + (cy & 1) + 1):
                            for z in range(bz + lo_min + (cz >> 1), bz + hi_min + (cz & 1) + 1):
                                occ[x, y, z] = 1
    return occ


@nb.njit(cache=True, nogil=True)
def bin_trilinear(points, origin, voxel, directory, blocks, touched, x_lo, x_hi):
    """Add each point's unit weight to its cell's 8 nodes, split by trilinear weights, and flag
    the blocks written in ``touched`` (the others stay all zero); only the nodes of x index in
    [``x_lo``, ``x_hi``) (multiples of the block's side, or beyond the grid: all of them).

    Two calls on disjoint slabs may run at once on one field: each node's sum is then taken by
    one of them, in the points' order, so the field is the same to the bit as one call's.
    Weights are computed in float64 and rounded to float32 before they are added (a float32
    sum, no round trip through float64 per node).
    """
    for p in range(points.shape[0]):
        x = (points[p, 0] - origin[0]) / voxel
        ix = int(math.floor(x))
        if ix + 1 < x_lo or ix >= x_hi:  # neither of its cell's x nodes in the slab
            continue
        y = (points[p, 1] - origin[1]) / voxel
        z = (points[p, 2] - origin[2]) / voxel
        iy, iz = int(math.floor(y)), int(math.floor(z))
        fx, fy, fz = x - ix, y - iy, z - iz
        gx, gy, gz = 1.0 - fx, 1.0 - fy, 1.0 - fz
        if (ix & 7) < 7 and (iy & 7) < 7 and (iz & 7) < 7:  # the cell lies in one block (so in the slab)
            blk = directory[ix >> 3, iy >> 3, iz >> 3]
            touched[blk] = True
            out = blocks[blk]
            n = (ix & 7) * B2 + (iy & 7) * B + (iz & 7)
            out[n] += np.float32(gx * gy * gz)
            out[n + 1] += np.float32(gx * gy * fz)
            out[n + B] += np.float32(gx * fy * gz)
            out[n + B + 1] += np.float32(gx * fy * fz)
            out[n + B2] += np.float32(fx * gy * gz)
            out[n + B2 + 1] += np.float32(fx * gy * fz)
            out[n + B2 + B] += np.float32(fx * fy * gz)
            out[n + B2 + B + 1] += np.float32(fx * fy * fz)
            continue
        for a in range(2):
            wx = fx if a else gx
            nx = ix + a
            if nx < x_lo or nx >= x_hi:
                continue
            for b in range(2):
                wy = fy if b else gy
                ny = iy + b
                for c in range(2):
                    wz = fz if c else gz
                    nz = iz + c
                    blk = directory[nx >> 3, ny >> 3, nz >> 3]
                    touched[blk] = True
                    blocks[blk, (nx & 7) * B2 + (ny & 7) * B + (nz & 7)] += np.float32(wx * wy * wz)


@nb.njit(cache=True, nogil=True)
def splat_exact(points, origin, voxel, directory, blocks, inv_two_s2, rmax, reach):
    """Add exp(-d²/2σ²) of every point to every node within the cube |d|∞ <= rmax (grid units)."""
    n_t = 2 * reach + 2
    wx = np.empty(n_t)
    wy = np.empty(n_t)
    wz = np.empty(n_t)
    for p in range(points.shape[0]):
        x = (points[p, 0] - origin[0]) / voxel
        y = (points[p, 1] - origin[1]) / voxel
        z = (points[p, 2] - origin[2]) / voxel
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


@nb.njit(cache=True, nogil=True)
def nonzero_blocks(blocks):
    """Per block: does it hold any nonzero value?"""
    out = np.zeros(blocks.shape[0], np.bool_)
    for b in range(blocks.shape[0]):
        for n in range(B3):
            if blocks[b, n] != 0.0:
                out[b] = True
                break
    return out


@nb.njit(cache=True, inline="always")
def _along(directory, axis, k, i1, i2):
    """The directory entry at position k along ``axis`` of the line (i1, i2) of the other two axes."""
    if axis == 0:
        return directory[k, i1, i2]
    if axis == 1:
        return directory[i1, k, i2]
    return directory[i1, i2, k]


@nb.njit(cache=True, inline="always")
def _lines(directory, axis):
    """(blocks along ``axis``, and the directory's other two sizes in order): the lines of a pass."""
    d0, d1, d2 = directory.shape
    return directory.shape[axis], (d1 if axis == 0 else d0), (d1 if axis == 2 else d2)


@nb.njit(parallel=True, cache=True)
def blur_pass(blocks, nonzero, directory, axis, taps):
    """One separable pass, in place: ``taps`` (odd length) along ``axis``, rotating the block layout.

    The pass reads each block with the blurred axis as its first (slowest) index, column
    ``a*64 + b*8 + c``, and writes it rotated, column ``b*64 + c*8 + a``: the next axis comes
    first. Three passes along x, y, z therefore start and end in the usual layout, and every
    pass convolves along the first index, with each tap updating a block's 64 lines at once.

    The lines of blocks along ``axis`` run in parallel; along a line, each block's original
    values are copied to a small ring before the block is overwritten, so the blocks after it
    read them there (no second array: the pass touches no fresh memory). Nodes of blocks that
    are not allocated read as 0. ``nonzero`` flags the blocks that may hold a nonzero value
    (a block not flagged must hold zeros): unflagged blocks are not read, and are left as they
    are when no source reaches them; the flags are updated for the output.
    """
    r = (taps.shape[0] - 1) // 2
    nbr = (r + B - 1) // B
    ring_len = nbr + 1
    dlen, n1, n2 = _lines(directory, axis)
    for line in nb.prange(n1 * n2):
        i1, i2 = line // n2, line % n2
        ring = np.empty((ring_len, B3), np.float32)  # originals of the blocks k - nbr … k
        ring_ok = np.zeros(ring_len, np.bool_)
        neigh = np.empty(2 * nbr + 1, np.int64)  # per offset j: -1 no source; j <= 0 in the ring; j > 0 its row
        acc = np.empty(B3, np.float32)
        for k in range(dlen):
            blk = _along(directory, axis, k, i1, i2)
            slot = k % ring_len
            ring_ok[slot] = blk >= 0 and nonzero[blk]
            if ring_ok[slot]:
                ring[slot, :] = blocks[blk]
            if blk < 0:
                continue
            any_src = False
            for j in range(-nbr, nbr + 1):
                kk = k + j
                if j <= 0:
                    ok = kk >= 0 and ring_ok[kk % ring_len]
                    neigh[j + nbr] = 0 if ok else -1
                else:
                    nb_blk = _along(directory, axis, kk, i1, i2) if kk < dlen else -1
                    ok = nb_blk >= 0 and nonzero[nb_blk]
                    neigh[j + nbr] = nb_blk if ok else -1
                any_src = any_src or ok
            if not any_src:
                continue  # all zero, and stays so
            acc[:] = 0.0
            for a in range(B):
                for t in range(taps.shape[0]):
                    s = a + t - r + nbr * B
                    j = s // B - nbr
                    if neigh[j + nbr] < 0:
                        continue
                    inp = ring[(k + j) % ring_len] if j <= 0 else blocks[neigh[j + nbr]]
                    w = taps[t]
                    ls = (s % B) * B2
                    for li in range(B2):
                        acc[a * B2 + li] += w * inp[ls + li]
            out = blocks[blk]
            for a in range(B):
                for li in range(B2):
                    out[li * B + a] = acc[a * B2 + li]
            nonzero[blk] = True


#: Taps of the blur's unrolled kernel (:func:`blur_pass_short`): a radius of 4 nodes, the default
#: σ of 1.5 voxels cut at 3σ; shorter taps are padded with zeros (adding 0·x leaves a sum as it is).
SHORT_TAPS = 9


@nb.njit(cache=True, inline="always")
def _convolve_short(pad, w, out):
    """out[l·8 + a] = Σ_t w[t]·pad[(a + t)·64 + l] for a < 8, l < 64, t < 9, added in the order of t
    as :func:`blur_pass` adds them, written rotated as it writes them. The nine taps are unrolled
    and the indices unsigned (no negative-index wrap-around): each row of 64 lanes vectorizes with
    its sums held in registers, where a loop over the taps kept them in memory."""
    w0, w1, w2, w3, w4, w5, w6, w7, w8 = w[0], w[1], w[2], w[3], w[4], w[5], w[6], w[7], w[8]
    lanes, b = np.uint64(B2), np.uint64(B)
    for a in range(b):
        base = a * lanes
        for li in range(lanes):
            i = base + li
            s = np.float32(0.0)
            s += w0 * pad[i]
            s += w1 * pad[i + lanes]
            s += w2 * pad[i + np.uint64(2) * lanes]
            s += w3 * pad[i + np.uint64(3) * lanes]
            s += w4 * pad[i + np.uint64(4) * lanes]
            s += w5 * pad[i + np.uint64(5) * lanes]
            s += w6 * pad[i + np.uint64(6) * lanes]
            s += w7 * pad[i + np.uint64(7) * lanes]
            s += w8 * pad[i + np.uint64(8) * lanes]
            out[li * b + a] = s


@nb.njit(parallel=True, cache=True)
def blur_pass_short(blocks, nonzero, directory, axis, taps):
    """:func:`blur_pass` for taps of at most :data:`SHORT_TAPS` (odd length), with the same sums
    node by node (bit for bit; the taps beyond the given ones are 0, and a finite sum plus 0·x is
    that sum): each block's input planes (the 4 before it along ``axis``, its own 8, the 4 after;
    0 where no source) are copied into one contiguous strip, then convolved with the nine taps
    unrolled (:func:`_convolve_short`), whose sums stay in registers where a loop over the taps
    keeps them in memory."""
    r = SHORT_TAPS // 2
    w = np.zeros(SHORT_TAPS, np.float32)
    off = r - (taps.shape[0] - 1) // 2
    for t in range(taps.shape[0]):
        w[off + t] = taps[t]
    dlen, n1, n2 = _lines(directory, axis)
    for line in nb.prange(n1 * n2):
        i1, i2 = line // n2, line % n2
        ring = np.empty((2, B3), np.float32)  # originals of the blocks k - 1 and k
        ring_ok = np.zeros(2, np.bool_)
        pad = np.empty((B + 2 * r) * B2, np.float32)  # input planes 8k - 4 … 8k + 11, 64 lanes each
        for k in range(dlen):
            blk = _along(directory, axis, k, i1, i2)
            slot = k % 2
            ring_ok[slot] = blk >= 0 and nonzero[blk]
            if ring_ok[slot]:
                ring[slot, :] = blocks[blk]
            if blk < 0:
                continue
            prev_ok = k > 0 and ring_ok[1 - slot]
            nxt = _along(directory, axis, k + 1, i1, i2) if k + 1 < dlen else -1
            next_ok = nxt >= 0 and nonzero[nxt]
            if not (prev_ok or ring_ok[slot] or next_ok):
                continue  # all zero, and stays so
            # planes 4 … 7 of the block before, its own 0 … 7, 0 … 3 of the next
            if prev_ok:
                pad[:r * B2] = ring[1 - slot, (B - r) * B2:]
            else:
                pad[:r * B2] = 0.0
            if ring_ok[slot]:
                pad[r * B2:(r + B) * B2] = ring[slot]
            else:
                pad[r * B2:(r + B) * B2] = 0.0
            if next_ok:
                pad[(r + B) * B2:] = blocks[nxt, :r * B2]
            else:
                pad[(r + B) * B2:] = 0.0
            _convolve_short(pad, w, blocks[blk])
            nonzero[blk] = True


@nb.njit(parallel=True, cache=True)
def add_blocks(dst, rows, src, weight):
    """dst[rows[i]] += weight · src[i] in float32, for every block i of src (rows distinct)."""
    w = np.float32(weight)
    for i in nb.prange(src.shape[0]):
        out = dst[rows[i]]
        inp = src[i]
        for n in range(B3):
            out[n] += w * inp[n]


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
        if ix >= 0 and iy >= 0 and iz >= 0 and (ix & 7) < 7 and (iy & 7) < 7 and (iz & 7) < 7:
            # the cell lies in one block (inside the grid): one lookup, same sum as below
            blk = directory[ix >> 3, iy >> 3, iz >> 3]
            if blk >= 0:
                row = blocks[blk]
                n = (ix & 7) * B2 + (iy & 7) * B + (iz & 7)
                gx, gy, gz = 1.0 - fx, 1.0 - fy, 1.0 - fz
                acc += gx * gy * gz * row[n]
                acc += gx * gy * fz * row[n + 1]
                acc += gx * fy * gz * row[n + B]
                acc += gx * fy * fz * row[n + B + 1]
                acc += fx * gy * gz * row[n + B2]
                acc += fx * gy * fz * row[n + B2 + 1]
                acc += fx * fy * gz * row[n + B2 + B]
                acc += fx * fy * fz * row[n + B2 + B + 1]
            out[p] = acc
            continue
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


@nb.njit(cache=True, nogil=True)
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


@nb.njit(cache=True, nogil=True)
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

