"""The world-aligned sparse grid: voxel size, snapped origin, blocks, and memory limits.

Node ``i`` (a triple of integers) of every grid with voxel length ``l`` sits at world position
``i * l``: the lattice is global, so two fields built with the same ``l`` share their nodes and
combine without resampling. A :class:`Grid` covers a box of *blocks* of ``BLOCK**3`` nodes;
its ``origin`` is the world position of its first node, an integer multiple of ``BLOCK * l``
kept as exact integers (``block_origin``, int64 global block coordinates) so that coordinates
10⁶ m from zero (UTM) keep sub-micrometre precision: points are converted to grid units as
``(p - origin) / l`` in float64. (How far from the origin a voxel may go: :mod:`sdp._core._validate`.)

The voxel ``l`` comes from one of three parameterizations, all resolved in one place
(:func:`sdp.fields._spacing.resolve_lattice`, which the tiled path feeds with the first slice of each
file): ``grid_size=N``, the paper's (the longest side of the box over N, σ = 2 voxels);
``voxel_size=`` a length in world units (σ = 2 voxels); ``voxel_size="auto"``, the default
(σ = 1.5 × the 90th percentile of the k-th neighbour distance, k = the threshold's 3, sampled at
``sigma_voxels="auto"`` = 1.5 voxels: the lattice only samples a σ the data set).

Memory is checked against one limit (:func:`memory_limit`: ``memory_limit=``,
``$SDP_MEMORY_LIMIT``, else 4 GiB) before anything is allocated: first the block directory,
then the blocks. Refusals give both sizes in human units (``12.3 MB``; binary units, as
:func:`parse_bytes` reads them).

References
----------
.. [1] K. Museth, "VDB: High-resolution sparse volumes with dynamic topology",
   ACM Trans. Graph. 32(3), 2013 (block-sparse storage).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .._core._memory import check_memory
from .._core._validate import integer_at_least, positive_finite
from ..errors import InvalidOptionError, InvalidPointsError

__all__ = ["BLOCK", "Grid", "voxel_size_for_grid_size", "check_lattice", "check_kernel", "kernel_reach",
           "MAX_GRID_UNITS"]

#: Edge length of a block, in nodes (blocks hold ``BLOCK**3`` float32 values, 2 KiB).
BLOCK = 8


#: Largest |coordinate| / voxel size accepted: beyond 2**40 voxels from the origin, float64 keeps
#: less than 2**-12 of a voxel, and the grid's integer node and block coordinates near their limits.
MAX_GRID_UNITS = 2.0**40


_MAX_REACH = 2**16  # kernel reach in voxels (truncate·σ): far beyond any memory limit already


def kernel_reach(sigma_voxels: float, truncate: float = 3.0) -> int:
    """⌈truncate·σ⌉, the kernel's reach in nodes, refusing one beyond 2**16 voxels (an
    :class:`InvalidOptionError`: such a σ is a mistake long before memory runs out)."""
    rmax = positive_finite("truncate", truncate) * positive_finite("sigma_voxels", sigma_voxels)
    if not rmax <= _MAX_REACH:
        raise InvalidOptionError(f"a kernel of sigma {sigma_voxels:g} voxels cut off at {truncate:g} sigma reaches "
                                 f"{rmax:.3g} voxels, more than {_MAX_REACH:,}: use a smaller sigma in voxels (and "
                                 "a larger voxel size)")
    return int(math.ceil(rmax))


def check_kernel(sigma_voxels: float, truncate: float, memory_limit=None, *, budget: str = "the memory limit") -> int:
    """The kernel's reach in nodes, ⌈truncate·σ⌉, once one point's kernel fits the memory limit.

    Raises
    ------
    GridTooLargeError
        The blocks under a single point's kernel cube alone exceed the limit (e.g. σ of 1000 voxels).
    """

    rmax = float(truncate) * float(sigma_voxels)
    kernel_reach(sigma_voxels, truncate)
    blocks = math.ceil((2 * rmax + 1) / BLOCK) ** 3
    check_memory(blocks * BLOCK**3 * 4, f"the kernel of one point (σ = {sigma_voxels:g} voxels, reaching "
                 f"{rmax:.4g} voxels each way)", memory_limit, advice="use a smaller sigma in voxels", budget=budget)
    return int(math.ceil(rmax))


def check_lattice(lo, hi, voxel_size: float, reach: int = 0) -> None:
    """Refuse a voxel size whose grid over the box [lo, hi] can't be placed in float64 and int64.

    Points are converted to grid units as ``(p − origin) / l``; more than :data:`MAX_GRID_UNITS`
    (2**40) voxels from the world origin, float64 keeps less than 1/4096 of a voxel and change
    masks would change silently; a voxel so large that the grid's corners overflow float64
    (e.g. 1e308) can't be placed at all.

    Raises
    ------
    InvalidPointsError
        The coordinates are too far from the origin for this voxel size.
    InvalidOptionError
        The voxel size is too large to place the grid's nodes.
    """

    l = float(voxel_size)
    span = float(np.max(np.abs(np.r_[np.asarray(lo, float), np.asarray(hi, float)])))
    if not math.isfinite(span):
        raise InvalidPointsError("the cloud's bounds are not finite")
    units = span / l
    if not units <= MAX_GRID_UNITS:
        raise InvalidPointsError(
            f"coordinates up to {span:.6g} are {units:.3g} voxels of {l:g} from the origin, beyond 2**40 "
            f"(≈{MAX_GRID_UNITS:.3g}): float64 can't place points within a voxel there; subtract an offset "
            "(e.g. the cloud's minimum) or use a larger voxel size")
    corner = (units + reach + 2 * BLOCK) * l * BLOCK  # the farthest node and block corner, in world units
    try:
        placed = math.isfinite(corner) and math.isfinite((reach * l) ** 2 + corner**2)
    except OverflowError:  # Python's float power raises where NumPy's would give inf
        placed = False
    if not placed:
        raise InvalidOptionError(f"voxel size {l:g} is too large: the grid's nodes would lie beyond the range of "
                                 "floating-point numbers; use a voxel size near the cloud's point spacing")



def voxel_size_for_grid_size(lo: np.ndarray, hi: np.ndarray, grid_size: int) -> float:
    """The paper's parameterization: the box's longest side divided into ``grid_size`` segments."""
    grid_size = integer_at_least("grid_size", grid_size, 1)
    extent = float(np.max(np.asarray(hi) - np.asarray(lo)))
    if not extent > 0:
        raise InvalidPointsError(
            "the cloud has zero extent (a single point, or all points equal): a grid size can't set a "
            "voxel length from it; give a voxel size in world units instead")
    return extent / grid_size


@dataclass(frozen=True)
class Grid:
    """A box of blocks on the global lattice of voxel length ``voxel_size``.

    Attributes
    ----------
    voxel_size : float
        Node spacing ``l``, in world units.
    block_origin : ndarray of int64, shape (3,)
        Global block coordinates of the first block; the world origin is
        ``block_origin * BLOCK * voxel_size``.
    shape_blocks : tuple of int
        Number of blocks along x, y, z.
    """

    voxel_size: float
    block_origin: np.ndarray
    shape_blocks: tuple[int, int, int]

    @property
    def origin(self) -> np.ndarray:
        """World coordinates (float64) of node (0, 0, 0)."""
        return self.block_origin.astype(np.float64) * (BLOCK * self.voxel_size)

    @property
    def shape(self) -> tuple[int, int, int]:
        """Number of nodes along x, y, z of the bounding box of blocks."""
        return tuple(int(s) * BLOCK for s in self.shape_blocks)

    def to_grid_units(self, points: np.ndarray) -> np.ndarray:
        """World coordinates → continuous node coordinates ``(p - origin) / l`` (float64)."""
        return (np.asarray(points, dtype=np.float64) - self.origin) / self.voxel_size

    def to_world(self, nodes: np.ndarray) -> np.ndarray:
        """Continuous node coordinates → world coordinates."""
        return np.asarray(nodes, dtype=np.float64) * self.voxel_size + self.origin

    @classmethod
    def covering(cls, lo: np.ndarray, hi: np.ndarray, voxel_size: float, reach: int) -> "Grid":
        """The smallest grid whose blocks hold every node within ``reach`` nodes of the box [lo, hi]."""
        voxel_size = positive_finite("voxel_size", voxel_size)
        check_lattice(lo, hi, voxel_size, reach)
        first = np.floor(np.asarray(lo) / voxel_size).astype(np.int64) - reach
        last = np.floor(np.asarray(hi) / voxel_size).astype(np.int64) + 1 + reach
        b0 = np.floor_divide(first, BLOCK)
        b1 = np.floor_divide(last, BLOCK)
        return cls(float(voxel_size), b0, tuple(int(v) for v in (b1 - b0 + 1)))

    @property
    def n_blocks_box(self) -> int:
        """Number of blocks in the bounding box (the size of the block directory)."""
        return math.prod(int(v) for v in self.shape_blocks)  # Python ints: no int64 wrap-around on huge boxes
