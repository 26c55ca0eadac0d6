"""Block-sparse storage of node values: blocks of 8³ nodes, their keys and a dense directory.

The encoding of a field, apart from its geometry (:class:`sdp.fields._lattice.Grid`: voxel, origin and box
of blocks), as OpenVDB's leaves [1]: node values are float32 in blocks of ``BLOCK**3`` nodes
(2 KiB), allocated only where needed; a dense int32 *directory* over the box of blocks maps a
block's position to its row (-1: not allocated), an O(1) lookup at 1/128 byte per box node
(a 500³ box costs 1 MB). City-scale scenes never need one directory for the whole box: they are
cut into tiles (:mod:`sdp.scale._tiles`), each with its own. There is no separate dense path: on small
grids every block is simply allocated, so the numbers are the same by construction.
:class:`Blocks` holds the values, keys and directory and the operations on them (rows of keys,
allocation, gathers, the blur).
Positions here are *local* block coordinates (0 … ``shape - 1``); the grid's ``block_origin``
makes them global. :class:`sdp.DensityField` holds one :class:`Blocks` (``field.blocks``); the
Numba kernels of :mod:`sdp.fields._kernels` and :mod:`sdp.fields._volume_kernels` take its three arrays.

References
----------
.. [1] K. Museth, "VDB: High-resolution sparse volumes with dynamic topology",
   ACM Trans. Graph. 32(3), 2013.
"""

from __future__ import annotations

import numpy as np

from ._kernels import SHORT_TAPS, add_blocks, blur_pass, blur_pass_short, gather_box, node_values, nonzero_blocks
from ._lattice import BLOCK

__all__ = ["Blocks"]


class Blocks:
    """Node values in blocks of 8³ over a box of blocks (see the module docstring).

    Attributes
    ----------
    values : ndarray of float32, shape (m, 512)
        The node values of each block; node (x, y, z) of a block at column ``x*64 + y*8 + z``.
    keys : ndarray of int64, shape (m, 3)
        Each block's position in the box (local block coordinates).
    directory : ndarray of int32, shape ``shape``
        Row of the block at each position of the box, -1 where none is allocated.
    """

    def __init__(self, shape: tuple[int, int, int], keys: np.ndarray, values: np.ndarray):
        self.keys = np.ascontiguousarray(keys, dtype=np.int64).reshape(-1, 3)
        self.values = np.ascontiguousarray(values, dtype=np.float32).reshape(-1, BLOCK**3)
        self._spare = None  # when set, values is its first rows (room to grow: see allocate)
        self.directory = _directory(self.keys, shape)

    def __len__(self) -> int:
        return len(self.keys)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Number of blocks of the box along x, y, z (the directory's shape)."""
        return self.directory.shape

    @property
    def nbytes(self) -> int:
        """Memory held by the node values (spare rows included), the keys and the directory, in bytes."""
        values = self._spare if self._spare is not None and self.values.base is self._spare else self.values
        return values.nbytes + self.directory.nbytes + self.keys.nbytes

    def copy(self) -> "Blocks":
        """An independent copy (values, keys and directory copied; no spare rows)."""
        out = Blocks.__new__(Blocks)
        out.values, out.keys, out.directory = self.values.copy(), self.keys.copy(), self.directory.copy()
        out._spare = None
        return out

    def view(self) -> "Blocks":
        """Another holder of the same arrays: writes into the values show in both; a later
        allocation or move rebinds the arrays of one holder only."""
        out = Blocks.__new__(Blocks)
        out.__dict__.update(self.__dict__)
        return out

    # ------------------------------------------------------------------ lookups
    def rows(self, keys: np.ndarray) -> np.ndarray:
        """Row (int64) of the block at each local position ``keys`` (m, 3); -1 where none is
        allocated or the position lies outside the box."""
        local = np.asarray(keys, np.int64)
        ok = np.all((local >= 0) & (local < np.asarray(self.shape)), axis=1)
        idx = np.full(len(local), -1, np.int64)
        idx[ok] = self.directory[tuple(local[ok].T)]
        return idx

    def take(self, keys: np.ndarray) -> np.ndarray:
        """Values (float32 (m, 512)) of the blocks at local positions ``keys``; 0 for blocks not held."""
        idx = self.rows(keys)
        out = np.zeros((len(idx), BLOCK**3), np.float32)
        have = idx >= 0
        out[have] = self.values[idx[have]]
        return out

    def at_nodes(self, nodes: np.ndarray) -> np.ndarray:
        """Values (float32) at integer node coordinates (k, 3) of the box; 0 where nothing is allocated."""
        return node_values(nodes, self.directory, self.values)

    def box(self, lo: np.ndarray, shape: np.ndarray) -> np.ndarray:
        """Dense float32 copy of the nodes ``lo`` … ``lo + shape - 1`` (int64 3-vectors; 0 where
        nothing is allocated, also outside the box)."""
        return gather_box(self.directory, self.values, lo, shape)

    def nonzero(self) -> np.ndarray:
        """Flags of the blocks that hold a nonzero value."""
        return nonzero_blocks(self.values)

    # ------------------------------------------------------------------ changes in place
    def blur(self, taps: np.ndarray, *, nonzero: np.ndarray | None = None) -> None:
        """Convolve the node values in place with ``taps`` along x, y and z (separable; nodes of
        blocks not allocated read as 0). ``nonzero``: flags of the blocks that may hold a nonzero
        value (default: :meth:`nonzero`)."""
        nonzero = self.nonzero() if nonzero is None else nonzero
        kernel = blur_pass_short if len(taps) <= SHORT_TAPS else blur_pass  # the same sums; the first unrolled
        for axis in range(3):
            kernel(self.values, nonzero, self.directory, axis, taps)

    def move(self, offset: np.ndarray, shape: tuple[int, int, int]) -> None:
        """Put the blocks into a new box of ``shape`` blocks, at their positions + ``offset``."""
        self.keys = self.keys + np.asarray(offset, np.int64)
        self.directory = _directory(self.keys, shape)

    def allocate(self, keys: np.ndarray) -> np.ndarray:
        """Rows (int64) of the blocks at local positions ``keys`` (inside the box, distinct),
        all-zero blocks appended for those not held yet, in the order given. New blocks go to
        spare rows reserved at the end: the values grow by half when full, so a stream of
        allocations copies them O(log) times."""
        local = np.asarray(keys, np.int64)
        rows = self.directory[tuple(local.T)].astype(np.int64)
        new = rows < 0
        if new.any():
            rows[new] = len(self.keys) + np.arange(new.sum())
            self.directory[tuple(local[new].T)] = rows[new]
            self.keys = np.concatenate([self.keys, local[new]])
            self._append_zeros(int(new.sum()))
        return rows

    def add(self, rows: np.ndarray, src: np.ndarray, weight: float = 1.0) -> None:
        """``self.values[rows[i]] += weight · src[i]`` in float32, for every block i of ``src``
        (float32 (k, 512); ``rows`` distinct, from :meth:`allocate`)."""
        add_blocks(self.values, rows, src, weight)

    def _append_zeros(self, count: int) -> None:
        """Append ``count`` all-zero blocks, in the spare rows when there is room."""
        n = len(self.values)
        spare = self._spare
        if spare is None or self.values.base is not spare or len(spare) < n + count:
            spare = np.empty((n + count + (n + count) // 2, BLOCK**3), np.float32)
            spare[:n] = self.values
            self._spare = spare
        spare[n:n + count] = 0.0
        self.values = spare[:n + count]


def _directory(keys: np.ndarray, shape) -> np.ndarray:
    directory = np.full(shape, -1, np.int32)
    if len(keys):
        directory[tuple(keys.T)] = np.arange(len(keys), dtype=np.int32)
    return directory
