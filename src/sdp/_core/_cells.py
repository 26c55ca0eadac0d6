"""One spatial hash of cubic cells, shared by the k-th neighbour distances of
:mod:`sdp.fields._spacing`, the cell moments of :mod:`sdp.distance._distances` and the cube
grouping of :mod:`sdp.change._planes`.

A cell ``(ix, iy, iz)``, each index in ``[0, 2**21)``, packs into one int64 key (:func:`cell_key`:
21 bits per axis, 63 in all, so a key is never negative and ``-1`` marks a free slot). A table
is an int64 array of ``2**bits`` keys, open addressing with linear probing, kept at most half
full (:func:`table_bits`); a key's first slot is its Fibonacci hash (:func:`slot`): the key times
``⌊2⁶⁴/φ⌋`` (wrapping), top ``bits`` bits. The multiplication mixes all three packed axes
into the top bits, so that neighbouring cells along any axis spread over the table, and a
lookup costs one multiply and a shift [1]_. What a slot points to is the caller's: the last point of a cell's
linked list (:func:`linked_cells`), a cell's run in a counting sort (:func:`hashed_sort`),
a group's number (the cube grouping of :mod:`sdp.change._planes`).

Each caller keeps its own cell coordinates (how it rounds a point into a cell) and its own use
of the table; only the packing, the hash, the probing and the table builders live here.

The kernels are inlined into their callers' compiled code, and Numba's cache checks only the
caller's own source file: after editing this module, touch the callers (or clear their
``__pycache__``) so that their cached kernels are compiled again.

References
----------
.. [1] D. E. Knuth, *The Art of Computer Programming*, Vol. 3, *Sorting and Searching*, 2nd ed.,
   §6.4 (multiplicative hashing, the golden ratio; open addressing with linear probing), 1998.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

__all__ = ["BITS", "MAX_INDEX", "cell_key", "cell_keys", "table_bits", "slot", "probe", "find", "find_cell",
           "linked_cells", "key_table", "table_row", "hashed_sort"]

BITS = 21  # bits per axis in a key: three of them fill an int64 but its sign bit
MAX_INDEX = 1 << BITS  # cell indices per axis: 0 … MAX_INDEX − 1
_MIN_BITS = 6  # the smallest table: 64 slots
_GOLDEN = -7046029254386353131  # ⌊2⁶⁴/φ⌋ = 0x9E3779B97F4A7C15 as a signed int64 (the product wraps)


@nb.njit(cache=True, inline="always")
def cell_key(ix, iy, iz):
    """The int64 key of cell (ix, iy, iz), each in ``[0, MAX_INDEX)`` (not checked: see
    :func:`find_cell`); keys of distinct cells differ, and sort as (ix, iy, iz)."""
    return (ix << (2 * BITS)) | (iy << BITS) | iz


@nb.njit(cache=True, nogil=True)
def cell_keys(cells):
    """:func:`cell_key` of each row of ``cells`` (n, 3) int64."""
    out = np.empty(cells.shape[0], np.int64)
    for i in range(cells.shape[0]):
        out[i] = cell_key(cells[i, 0], cells[i, 1], cells[i, 2])
    return out


@nb.njit(cache=True)
def table_bits(slots):
    """log2 of the table size for ``slots`` slots: the smallest power of two ≥ ``slots``, at least
    64 (a table for ``c`` cells at most half full: ``table_bits(2 * c)``)."""
    bits = _MIN_BITS
    while (1 << bits) < slots:
        bits += 1
    return bits


@nb.njit(cache=True, inline="always")
def slot(key, shift, mask):
    """First slot of ``key`` in a table of ``2**bits`` slots (``shift = 64 − bits``, ``mask =
    2**bits − 1``): Fibonacci hashing, the top ``bits`` bits of key × ⌊2⁶⁴/φ⌋."""
    return ((key * _GOLDEN) >> shift) & mask


@nb.njit(cache=True, inline="always")
def probe(keys, key, shift, mask):
    """The slot holding ``key`` in the table ``keys``, or the free slot (``keys[s] < 0``) where it
    would go. Reads only ``keys[:mask + 1]`` (a table may carry its values after its keys)."""
    s = slot(key, shift, mask)
    while True:
        stored = keys[s]
        if stored == key or stored < 0:
            return s
        s = (s + 1) & mask


@nb.njit(cache=True, inline="always")
def find(keys, key, shift, mask):
    """The slot holding ``key`` in the table ``keys``, -1 if it is absent."""
    s = probe(keys, key, shift, mask)
    return s if keys[s] == key else -1


@nb.njit(cache=True, inline="always")
def find_cell(keys, ix, iy, iz, shift, mask):
    """The slot of cell (ix, iy, iz), -1 if it is absent or outside ``[0, MAX_INDEX)`` on an axis."""
    if ix < 0 or iy < 0 or iz < 0 or ix >= MAX_INDEX or iy >= MAX_INDEX or iz >= MAX_INDEX:
        return -1
    return find(keys, cell_key(ix, iy, iz), shift, mask)


@nb.njit(cache=True, nogil=True)
def linked_cells(points, lo, c, bits):
    """Points in cells of side ``c`` from ``lo`` (cell ``⌊(p − lo)·(1/c)⌋``, within
    ``[0, MAX_INDEX)`` on each axis), as linked lists, in one pass.

    Returns ``keys`` (2**bits,) int64, the table of the cells' keys (-1: free slot); ``heads``
    (2**bits,) int32, the last point of each used slot's cell; ``next`` (n,) int32, the previous
    point of the same cell (-1: none), so a cell's points come last first; the number of cells;
    and the number of points placed (n). When the table gets half full the build stops: ``next``
    comes back empty and the count is the point it stopped at (rebuild with more bits).
    """
    n = points.shape[0]
    cap = 1 << bits
    mask = cap - 1
    shift = 64 - bits
    keys = np.full(cap, -1, np.int64)
    heads = np.empty(cap, np.int32)
    nxt = np.empty(n, np.int32)
    cells = 0
    inv = 1.0 / c
    last_key = -1
    s = -1
    for i in range(n):
        key = cell_key(int(math.floor((points[i, 0] - lo[0]) * inv)), int(math.floor((points[i, 1] - lo[1]) * inv)),
                       int(math.floor((points[i, 2] - lo[2]) * inv)))
        if key != last_key:  # scans are ordered: consecutive points often share a cell
            s = probe(keys, key, shift, mask)
            if keys[s] < 0:
                if 2 * cells >= cap:
                    return keys, heads, nxt[:0], cells, i
                keys[s] = key
                heads[s] = -1
                cells += 1
            last_key = key
        nxt[i] = heads[s]
        heads[s] = i
    return keys, heads, nxt, cells, n


@nb.njit(cache=True, nogil=True)
def key_table(keys):
    """Table of the distinct ``keys`` (m,): one int64 array of 2 × 2**bits, the slots' keys
    (-1: free) then each slot's row in ``keys`` (read by :func:`table_row`)."""
    bits = table_bits(2 * keys.shape[0])
    cap = 1 << bits
    table = np.full(2 * cap, -1, np.int64)
    shift, mask = 64 - bits, cap - 1
    for r in range(keys.shape[0]):
        s = probe(table, keys[r], shift, mask)
        table[s] = keys[r]
        table[cap + s] = r
    return table


@nb.njit(cache=True, inline="always")
def table_row(table, ix, iy, iz, shift):
    """Row of cell (ix, iy, iz) in a :func:`key_table` (``shift = 64 − bits``), -1 if absent."""
    cap = table.shape[0] // 2
    s = find_cell(table, ix, iy, iz, shift, cap - 1)
    return table[cap + s] if s >= 0 else -1


@nb.njit(cache=True, nogil=True)
def hashed_sort(points, lo, c):
    """Points sorted by cell (``⌊(p − lo)/c⌋``, within ``[0, MAX_INDEX)`` on each axis) in O(n):
    a counting sort over a hash table of the occupied cells, the runs in the order their cells
    are first met (a scan's order keeps neighbouring cells near).

    Returns the stable sorting permutation, the start of each cell's run and the end
    (cells + 1,), and the :func:`key_table` of the cells in the order of their runs. The table
    starts for n/8 cells and is built again, four times larger, when it gets half full."""
    n = points.shape[0]
    bits = table_bits(max(n // 4, 1))
    run = np.empty(n, np.int64)
    while True:
        cap = 1 << bits
        mask, shift = cap - 1, 64 - bits
        table = np.full(2 * cap, -1, np.int64)
        runs = 0
        last_key = -1
        r = -1
        full = False
        for i in range(n):
            key = cell_key(int(math.floor((points[i, 0] - lo[0]) / c)), int(math.floor((points[i, 1] - lo[1]) / c)),
                           int(math.floor((points[i, 2] - lo[2]) / c)))
            if key != last_key:  # scans are ordered: consecutive points often share a cell
                s = probe(table, key, shift, mask)
                if table[s] < 0:
                    if 2 * (runs + 1) > cap:
                        full = True
                        break
                    table[s] = key
                    table[cap + s] = runs
                    runs += 1
                r = table[cap + s]
                last_key = key
            run[i] = r
        if not full:
            break
        bits += 2
    starts = np.zeros(runs + 1, np.int64)
    for i in range(n):
        starts[run[i] + 1] += 1
    for k in range(runs):
        starts[k + 1] += starts[k]
    fill = starts[:runs].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[run[i]]] = i
        fill[run[i]] += 1
    return order, starts, table
