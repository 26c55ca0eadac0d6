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
import os
import re
from dataclasses import dataclass

import numpy as np

from ..errors import GridTooLargeError, InvalidOptionError, InvalidPointsError
from .._core._validate import check_lattice, format_bytes, integer_at_least, positive_finite

__all__ = ["BLOCK", "Grid", "voxel_size_for_grid_size", "memory_limit", "parse_bytes", "check_memory",
           "MIN_MEMORY_LIMIT"]

#: Edge length of a block, in nodes (blocks hold ``BLOCK**3`` float32 values, 2 KiB).
BLOCK = 8

_DEFAULT_MEMORY_LIMIT = 4 * 2**30
_UNITS = {"": 1, "b": 1, "k": 2**10, "kb": 2**10, "kib": 2**10, "m": 2**20, "mb": 2**20,
          "mib": 2**20, "g": 2**30, "gb": 2**30, "gib": 2**30, "t": 2**40, "tb": 2**40, "tib": 2**40}


#: Smallest memory limit accepted: a smaller one is almost surely a size given without its unit.
MIN_MEMORY_LIMIT = 2**20


def parse_bytes(value: int | float | str) -> int:
    """Parse a memory size such as ``2GB``, ``512MiB`` or ``1e9`` into bytes (binary units).

    Raises
    ------
    InvalidOptionError
        Not a positive finite size in a known unit.
    """
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        if not (value > 0 and math.isfinite(value)):
            raise InvalidOptionError(f"a memory limit must be a positive size such as 2GB, got {value!r}")
        return int(value)
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?|[0-9]+\.)\s*([a-zA-Z]*)\s*", str(value))
    if not match or match.group(2).lower() not in _UNITS:
        raise InvalidOptionError(f"can't read memory size {value!r}: use e.g. 2GB, 512MB or a number of bytes")
    return parse_bytes(float(match.group(1)) * _UNITS[match.group(2).lower()])


def memory_limit(limit: int | float | str | None = None) -> int:
    """The memory limit in bytes: ``limit`` if given, else ``$SDP_MEMORY_LIMIT``, else 4 GiB.

    Raises
    ------
    InvalidOptionError
        Unreadable, not positive, or, given as text (the command line, ``$SDP_MEMORY_LIMIT``),
        below 1 MB (:data:`MIN_MEMORY_LIMIT`: most likely a size without its unit).
    """
    source = "the memory limit"
    if limit is None:
        env = os.environ.get("SDP_MEMORY_LIMIT")
        limit, source = (_DEFAULT_MEMORY_LIMIT, source) if env is None else (env, "$SDP_MEMORY_LIMIT")
    try:
        cap = parse_bytes(limit)
    except InvalidOptionError as exc:
        if source == "the memory limit":
            raise
        raise InvalidOptionError(f"{source}: {exc}") from None
    if cap < MIN_MEMORY_LIMIT and isinstance(limit, str):  # numbers (Python) are bytes, taken as given
        raise InvalidOptionError(f"{source} {limit!r} is {format_bytes(cap)}, below the minimum of "
                                 f"{format_bytes(MIN_MEMORY_LIMIT)}: give a size with its unit, e.g. 2GB")
    return cap


def check_memory(nbytes: float, what: str, limit: int | float | str | None, *,
                 advice: str = "use a larger voxel size (or a smaller grid size)",
                 budget: str = "the memory limit") -> None:
    """Raise :class:`GridTooLargeError` if ``nbytes`` exceeds the memory limit.

    The message gives both sizes in human units and says what to change: ``advice``, or
    raising the memory limit (``--memory-limit`` on the command line, ``memory_limit=`` in
    Python, ``$SDP_MEMORY_LIMIT`` for both). ``budget`` names what ``limit`` is (a worker's
    share of the memory limit, for the tiles).
    """
    cap = memory_limit(limit)
    if not nbytes <= cap:
        raise GridTooLargeError(
            f"{what} would need {format_bytes(nbytes)}, above {budget} of {format_bytes(cap)}: "
            f"{advice}, or raise the memory limit ($SDP_MEMORY_LIMIT)")


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
