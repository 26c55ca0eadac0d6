"""The shared spatial hash of cubic cells (sdp._core._cells)."""

import math

import numpy as np
import pytest

from sdp._core import _cells as C

TOP = C.MAX_INDEX - 1


def walk(heads, nxt, s):
    """The points of the linked list starting at slot ``s``."""
    out, p = [], heads[s]
    while p >= 0:
        out.append(int(p))
        p = nxt[p]
    return out


def cells_of(points, lo, c):
    inv = 1.0 / c
    return np.floor((points - lo) * inv).astype(np.int64)


def test_keys_pack_the_three_indices_up_to_the_21_bit_limit():
    assert C.BITS == 21 and C.MAX_INDEX == 2**21
    assert C.cell_key(0, 0, 0) == 0
    assert C.cell_key(TOP, TOP, TOP) == 2**63 - 1  # the largest int64: never negative, never -1
    assert C.cell_key(1, 0, 0) == 2**42 and C.cell_key(0, 1, 0) == 2**21 and C.cell_key(0, 0, 1) == 1
    edge = np.array([[i, j, k] for i in (0, 1, TOP - 1, TOP) for j in (0, 1, TOP - 1, TOP)
                     for k in (0, 1, TOP - 1, TOP)], np.int64)
    keys = C.cell_keys(edge)
    assert len(np.unique(keys)) == len(edge) and (keys >= 0).all()
    # keys sort as the cells do, lexicographically
    assert np.array_equal(np.argsort(keys, kind="stable"), np.lexsort(edge.T[::-1]))
    # and each unpacks to its cell
    mask = C.MAX_INDEX - 1
    assert np.array_equal(np.c_[keys >> 42, (keys >> 21) & mask, keys & mask], edge)


def test_table_sizes():
    assert C.table_bits(0) == 6 and C.table_bits(64) == 6 and C.table_bits(65) == 7
    assert C.table_bits(2 * 1000) == 11 and C.table_bits(2.5 * 1000.5) == 12


def test_slots_spread_neighbouring_cells():
    bits = 10
    keys = C.cell_keys(np.array([[i, j, k] for i in range(8) for j in range(8) for k in range(8)], np.int64))
    slots = np.array([C.slot(k, 64 - bits, (1 << bits) - 1) for k in keys])
    assert ((0 <= slots) & (slots < 1 << bits)).all()
    assert len(np.unique(slots)) > 0.5 * len(keys)  # 512 cells into 1024 slots: few collide


def test_every_point_is_found_in_its_cell(rng):
    points = np.r_[rng.uniform(0, 1, (3000, 3)), np.repeat(rng.uniform(0, 1, (50, 3)), 4, axis=0)]
    lo, c = points.min(axis=0), 0.07
    keys, heads, nxt, n_cells, done = C.linked_cells(points, lo, c, 12)
    assert done == len(points) and len(nxt) == len(points)
    cells = cells_of(points, lo, c)
    assert n_cells == len(np.unique(cells, axis=0)) == (keys >= 0).sum()
    bits = int(math.log2(len(keys)))
    seen = np.zeros(len(points), int)
    for key_cell in np.unique(cells, axis=0):
        s = C.find_cell(keys, *key_cell, 64 - bits, len(keys) - 1)
        assert s >= 0 and keys[s] == C.cell_key(*key_cell)
        members = walk(heads, nxt, s)
        assert members == sorted(members, reverse=True)  # a cell's points come last first
        assert (cells[members] == key_cell).all()
        seen[members] += 1
    assert (seen == 1).all()  # every point in exactly one list: its cell's


def test_absent_and_off_grid_cells_are_not_found(rng):
    points = rng.uniform(0, 1, (500, 3))
    lo, c = np.zeros(3), 0.1
    keys, heads, nxt, _, _ = C.linked_cells(points, lo, c, 8)
    shift, mask = 64 - 8, len(keys) - 1
    present = {tuple(v) for v in cells_of(points, lo, c)}
    for cell in [(10, 0, 0), (0, 11, 3), (50, 50, 50), (TOP, TOP, TOP), (TOP, 0, 0)]:
        assert cell not in present and C.find_cell(keys, *cell, shift, mask) == -1
    for cell in [(-1, 0, 0), (0, -1, 0), (0, 0, -1), (C.MAX_INDEX, 0, 0), (0, C.MAX_INDEX, 0), (0, 0, C.MAX_INDEX)]:
        assert C.find_cell(keys, *cell, shift, mask) == -1  # off the grid: never looked up
    assert C.find(keys, C.cell_key(9, 9, 9) + 12345, shift, mask) == -1


def test_collisions_many_cells_in_a_small_table():
    bits = 6  # 64 slots
    shift, mask = 64 - bits, (1 << bits) - 1
    # cells at the 21-bit limits whose keys all start at the same slot: each probe walks past the others
    candidates = np.array([[TOP - i, j, TOP - k] for i in range(8) for j in range(8) for k in range(64)], np.int64)
    keys = C.cell_keys(candidates)
    home = np.array([C.slot(k, shift, mask) for k in keys])
    same = candidates[home == np.bincount(home).argmax()][:20]
    assert len(same) >= 10
    table = C.key_table(C.cell_keys(same))
    assert len(table) == 2 * 64  # 20 cells: 40 slots → 64
    for row, cell in enumerate(same):
        assert C.table_row(table, *cell, shift) == row
    assert C.table_row(table, TOP, TOP, TOP - 1000, shift) == -1
    # 31 cells fill a 64-slot table to just under half: the probes wrap around its end
    many = candidates[:31]
    table = C.key_table(C.cell_keys(many))
    assert len(table) == 2 * 64
    assert [C.table_row(table, *cell, shift) for cell in many] == list(range(31))


def test_a_half_full_table_stops_the_build():
    # 100 cells along x, 3 points each, in a 64-slot table: it stops at the 33rd cell's first point
    points = np.repeat(np.c_[np.arange(100) + 0.5, np.full(100, 0.5), np.full(100, 0.5)], 3, axis=0)
    keys, heads, nxt, n_cells, done = C.linked_cells(points, np.zeros(3), 1.0, 6)
    assert len(nxt) == 0 and n_cells == 32 and done == 32 * 3
    keys, heads, nxt, n_cells, done = C.linked_cells(points, np.zeros(3), 1.0, C.table_bits(2.5 * 100))
    assert len(nxt) == len(points) and n_cells == 100 and done == len(points)


@pytest.mark.parametrize("n, spread", [(2000, 6), (3000, 1000)])  # few cells; a cell per point (the table grows)
def test_hashed_sort_groups_every_cell_in_input_order(rng, n, spread):
    cells = rng.integers(0, spread, (n, 3)).astype(np.int64)
    cells[::7] = [TOP, 0, TOP]
    points = cells + rng.uniform(0.01, 0.99, cells.shape)
    order, starts, table = C.hashed_sort(points, np.zeros(3), 1.0)
    assert sorted(order) == list(range(n))
    unique = np.unique(cells, axis=0)
    assert len(starts) == len(unique) + 1 and starts[0] == 0 and starts[-1] == n
    shift = 64 - int(math.log2(len(table) // 2))
    seen = set()
    for row in range(len(starts) - 1):
        members = order[starts[row]:starts[row + 1]]
        assert (np.diff(members) > 0).all()  # stable: a cell's points in input order
        cell = cells[members[0]]
        assert (cells[members] == cell).all() and C.table_row(table, *cell, shift) == row
        seen.add(tuple(cell))
    assert len(seen) == len(unique)
    assert C.table_row(table, TOP, TOP, TOP, shift) == -1
    order, starts, table = C.hashed_sort(np.zeros((0, 3)), np.zeros(3), 1.0)
    assert len(order) == 0 and list(starts) == [0] and (table == -1).all()
