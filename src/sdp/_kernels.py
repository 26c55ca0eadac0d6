"""Numba kernels on block-sparse grids (private).

Storage, shared by every kernel: ``directory`` is an int32 array over the grid's box of blocks
(-1 = block not allocated, else its row in ``blocks``); ``blocks`` is float32 of shape
(m, 512), node (x, y, z) of a block at column ``x*64 + y*8 + z``; ``keys`` (m, 3) int64 holds
each block's position in the directory. Node coordinates ``u`` are float64 grid units
(``(p - origin) / l``). Every kernel is compiled once and cached on disk (``cache=True``).
"""

from __future__ import annotations

import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor

# Parallel kernels run on Numba's OpenMP layer. By default its idle workers spin before they
# sleep, and on a machine whose cores are busy with other jobs a spinning worker is descheduled:
# each parallel kernel then waited ~10 ms for it (measured on 2 shared cores; 0.01 ms when
# workers sleep). Set before OpenMP starts; an explicit OMP_WAIT_POLICY is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba as nb  # noqa: E402
import numpy as np  # noqa: E402

B = 8  # must equal grid.BLOCK
B2 = B * B
B3 = B * B * B


def map_concurrently(fn, items, *, parallel_kernels: bool = False) -> list:
    """``[fn(x) for x in items]``, the items at once on several threads when Numba may use more
    than one thread (``NUMBA_NUM_THREADS``: the cores by default, 1 on the Dask workers of
    :mod:`sdp.tiles`): the kernels release the GIL (``nogil=True``), so independent pieces of
    work (the two directions of a comparison, the spacing of two clouds) overlap. The calling
    thread takes the first item; the others go to a pool of threads kept for the process
    (starting threads per call delayed the second piece by up to 4 ms of a 6 ms job). Called
    from a pool thread, the items run in turn. ``parallel_kernels``: ``fn`` also calls parallel
    kernels; they may run from two threads at once only on a thread-safe Numba threading layer
    (OpenMP, TBB; not the fallback "workqueue"), else the items run in turn."""
    items = list(items)
    if len(items) < 2 or nb.config.NUMBA_NUM_THREADS < 2 or getattr(_in_pool, "yes", False):
        return [fn(x) for x in items]
    if parallel_kernels:
        try:
            safe = nb.threading_layer() in ("omp", "tbb")
        except ValueError:  # no parallel kernel has run yet: the layer is not chosen
            safe = False
        if not safe:
            return [fn(x) for x in items]
    futures = [_pool().submit(fn, x) for x in items[1:]]
    try:
        first = fn(items[0])
    except BaseException:
        for f in futures:
            f.cancel()
        raise
    return [first, *(f.result() for f in futures)]


_in_pool = threading.local()  # .yes in the pool's threads
_pool_lock = threading.Lock()
_pool_executor: ThreadPoolExecutor | None = None


def _pool() -> ThreadPoolExecutor:
    global _pool_executor
    with _pool_lock:
        if _pool_executor is None:
            _pool_executor = ThreadPoolExecutor(max(nb.config.NUMBA_NUM_THREADS - 1, 1), "sdp",
                                                initializer=lambda: setattr(_in_pool, "yes", True))
        return _pool_executor


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
def bin_trilinear(points, origin, voxel, directory, blocks, touched):
    """Add each point's unit weight to its cell's 8 nodes, split by trilinear weights, and flag
    the blocks written in ``touched`` (the others stay all zero).

    Weights are computed in float64 and rounded to float32 before they are added (a float32
    sum, no round trip through float64 per node).
    """
    for p in range(points.shape[0]):
        x = (points[p, 0] - origin[0]) / voxel
        y = (points[p, 1] - origin[1]) / voxel
        z = (points[p, 2] - origin[2]) / voxel
        ix, iy, iz = int(math.floor(x)), int(math.floor(y)), int(math.floor(z))
        fx, fy, fz = x - ix, y - iy, z - iz
        gx, gy, gz = 1.0 - fx, 1.0 - fy, 1.0 - fz
        if (ix & 7) < 7 and (iy & 7) < 7 and (iz & 7) < 7:  # the cell lies in one block
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
    d0, d1, d2 = directory.shape
    dlen = directory.shape[axis]
    n1 = d1 if axis == 0 else d0  # the other two axes, in order
    n2 = d1 if axis == 2 else d2
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


@nb.njit(cache=True, nogil=True)
def _find(parent, i):
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


# ---------------------------------------------------------------------------- volumes (sdp.regions)
# A volume (sdp.regions.Volume) is the set of nodes of field a's blocks where
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


@nb.njit(cache=True, nogil=True)
def volume_masks(a_keys, a_blocks, ha, b_blocks, b_directory, shift, hb):
    """Per block of a, per line of 8 nodes along z (columns 8j … 8j+7): bit z set where v < 0,
    that is where A > ha and B < hb (the sign of a float32 difference is exact)."""
    fa_h, fb_h = np.float32(ha), np.float32(hb)
    masks = np.zeros((a_blocks.shape[0], B2), np.uint8)
    for blk in range(a_blocks.shape[0]):
        j = _partner(a_keys, blk, b_directory, shift)
        if j < 0 and not fb_h > 0:
            continue  # v >= -hb >= 0 throughout
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


@nb.njit(parallel=True, cache=True)
def volume_at(points, origin, voxel, a_directory, a_keys, a_blocks, ha, b_blocks, b_directory, shift, hb, out):
    """out[p] = trilinear interpolation of v at world position points[p] (finite), as
    :func:`trilinear` interpolates an array of v on a's blocks: nodes outside a's blocks and
    points outside the grid read as 0."""
    fa_h, fb_h = np.float32(ha), np.float32(hb)
    d0, d1, d2 = a_directory.shape
    for p in nb.prange(points.shape[0]):
        x = (points[p, 0] - origin[0]) / voxel
        y = (points[p, 1] - origin[1]) / voxel
        z = (points[p, 2] - origin[2]) / voxel
        ix, iy, iz = int(math.floor(x)), int(math.floor(y)), int(math.floor(z))
        fx, fy, fz = x - ix, y - iy, z - iz
        acc = 0.0
        if ix >= 0 and iy >= 0 and iz >= 0 and (ix & 7) < 7 and (iy & 7) < 7 and (iz & 7) < 7 and \
                ix < d0 * B and iy < d1 * B and iz < d2 * B:
            # the cell lies in one block: one lookup in each field, the same sum as below
            blk = a_directory[ix >> 3, iy >> 3, iz >> 3]
            if blk >= 0:
                j = _partner(a_keys, blk, b_directory, shift)
                n = (ix & 7) * B2 + (iy & 7) * B + (iz & 7)
                for a in range(2):
                    wx = fx if a else 1.0 - fx
                    for b in range(2):
                        wy = fy if b else 1.0 - fy
                        for c in range(2):
                            wz = fz if c else 1.0 - fz
                            acc += wx * wy * wz * _volume_value(a_blocks, fa_h, b_blocks, j, fb_h, blk,
                                                                n + a * B2 + b * B + c)
            out[p] = acc
            continue
        for a in range(2):
            nx = ix + a
            if nx < 0 or nx >= d0 * B:
                continue
            wx = fx if a else 1.0 - fx
            for b in range(2):
                ny = iy + b
                if ny < 0 or ny >= d1 * B:
                    continue
                wy = fy if b else 1.0 - fy
                for c in range(2):
                    nz = iz + c
                    if nz < 0 or nz >= d2 * B:
                        continue
                    blk = a_directory[nx >> 3, ny >> 3, nz >> 3]
                    if blk < 0:
                        continue
                    wz = fz if c else 1.0 - fz
                    v = _volume_value(a_blocks, fa_h, b_blocks, _partner(a_keys, blk, b_directory, shift), fb_h,
                                      blk, (nx & 7) * B2 + (ny & 7) * B + (nz & 7))
                    acc += wx * wy * wz * v
        out[p] = acc


@nb.njit(cache=True, inline="always")
def _runs_of(mk, out):
    """The runs of consecutive set bits of ``mk``, as masks, into ``out`` (low bits first); returns
    their number."""
    n = 0
    while mk:
        run = ((mk + (mk & -mk)) ^ mk) & mk  # adding the lowest set bit clears the lowest run
        out[n] = run
        n += 1
        mk &= ~run
    return n


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
def _union(parent, a, b):
    ra = _find(parent, a)
    rb = _find(parent, b)
    if ra != rb:
        parent[max(ra, rb)] = min(ra, rb)


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
    scratch = np.empty(B, np.int64)
    for s in range(n_active):
        for j in range(B2):
            first[s * B2 + j + 1] = first[s * B2 + j] + _runs_of(np.int64(masks[active[s], j]), scratch)
    run_mask = np.empty(first[-1], np.int64)
    for s in range(n_active):
        for j in range(B2):
            _runs_of(np.int64(masks[active[s], j]), run_mask[first[s * B2 + j]:])
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
                _union(parent, r0, first[t * B2 + j + 1] - 1)  # the last run of that line
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
                            _union(parent, r, q)
    labels = np.full((n_active, B3), -1, np.int32)
    root_label = np.full(run_mask.shape[0], -1, np.int64)
    node_counts = np.zeros(run_mask.shape[0], np.int64)
    count = 0
    for s in range(n_active):
        for j in range(B2):
            for r in range(first[s * B2 + j], first[s * B2 + j + 1]):
                root = _find(parent, r)
                if root_label[root] < 0:
                    root_label[root] = count
                    count += 1
                for z in range(B):
                    if run_mask[r] >> z & 1:
                        labels[s, j * B + z] = root_label[root]
                        node_counts[root_label[root]] += 1
    return slot, labels, node_counts[:count]


@nb.njit(parallel=True, cache=True)
def corner_labels(u, directory, slot, labels, a_keys, a_blocks, ha, b_blocks, b_directory, shift, hb):
    """For each point, the label of the cell corner with the lowest v among labelled corners.

    ``slot`` and ``labels`` as returned by :func:`label_nodes`; -1 where no corner of the
    point's cell carries a label.
    """
    fa_h, fb_h = np.float32(ha), np.float32(hb)
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
                    if blk < 0 or slot[blk] < 0:
                        continue
                    i = (nx & 7) * B2 + (ny & 7) * B + (nz & 7)
                    if labels[slot[blk], i] < 0:
                        continue
                    v = _volume_value(a_blocks, fa_h, b_blocks, _partner(a_keys, blk, b_directory, shift), fb_h,
                                      blk, i)
                    if v < best:
                        best = v
                        out[p] = labels[slot[blk], i]
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


# ---------------------------------------------------------------------------- tiles (sdp.tiles)
@nb.njit(cache=True, nogil=True)
def scaled_xyz(X, Y, Z, scale, offset):
    """LAS integer coordinates → float64 world (n, 3): X·scale + offset, as laspy computes it."""
    out = np.empty((X.shape[0], 3))
    for p in range(X.shape[0]):
        out[p, 0] = X[p] * scale[0] + offset[0]
        out[p, 1] = Y[p] * scale[1] + offset[1]
        out[p, 2] = Z[p] * scale[2] + offset[2]
    return out


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
