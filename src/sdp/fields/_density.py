"""The density field G and its normalized form F = h − G, on a block-sparse grid.

G(x) = Σ_i exp(−‖x − p_i‖² / 2σ²) is sampled at the nodes of the global lattice of
:mod:`sdp.fields._lattice`, in the blocks of :mod:`sdp.fields._blocks` (``field.blocks``), allocated only where some
point's kernel cube (±⌈truncate·σ⌉ nodes) reaches; elsewhere G = 0. Two builds:

- ``method="exact"``: every point adds its Gaussian to each node of its kernel cube (equal to a
  brute-force sum to 1e-5, tested). About 60× slower than
- ``method="fast"`` (the default): trilinear binning of each point onto its cell's 8 nodes,
  then a separable Gaussian blur per axis over the blocks, in place: lines of blocks along the
  axis run in parallel, each block's original is kept in a small ring until the next blocks have
  read it, all-zero blocks are skipped and 64 lines are blurred per tap at once, so a build needs
  one array of blocks, not two. The blur's variance is σ² − 1/6 voxel² (binning adds 1/6 on
  average) and its amplitude keeps each point's mass: the result departs from the exact sum by
  < 1 % of the field's peak (a lone point: up to 7 % of its own peak). Points are binned 4 M per
  kernel call, one progress step each.

:func:`build_fields` builds the fields of a comparison on one lattice: the single-threaded first
parts of the builds (block marking, binning) run at once on two threads, their blurs, parallel
inside, in turn; two whole single-threaded builds at once were 1.1–1.3× slower than two
parallel builds in turn. A cloud built alone (a stream's frame, :func:`sdp.align`'s levels,
``sdp field``) marks its blocks in two halves and bins its points in two slabs of nodes along x
at once: each node's sum is taken by one thread in the points' order, so the field is the one
thread's to the bit.

Operations on G alone (no points needed): :meth:`DensityField.coarsen` gives the next level of
detail (2l, 2σ: blur by a normalized Gaussian of √3·σ, ×8, every second node; within 3 % of a
field rebuilt from the points, tested), used by :func:`sdp.align`'s pyramid;
:meth:`~DensityField.accumulate` adds another field of the same lattice and σ block by block
(allocating blocks and growing the directory as needed) and :meth:`~DensityField.scale` decays
it, for :mod:`sdp.stream._watch`; :meth:`~DensityField.footprint` projects G on the x, y plane for
:mod:`sdp.change._coverage`. A result of :mod:`sdp.fields._boolean` is a field flagged
:attr:`~DensityField.is_boolean` (G := h − F), which :meth:`~DensityField.coarsen` and
:meth:`~DensityField.accumulate` refuse. :mod:`sdp.fields._file` writes and reads the ``.sdpf`` file.

References
----------
.. [1] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
   Comparison and Applications" (method summary: ``docs/method.md`` of the shared docs).
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path

import numpy as np

from .._core._memory import check_memory
from .._core._parallel import concurrent, map_concurrently
from .._core._points import Points, as_points
from .._core._progress import bar
from .._core._validate import check_grid_options, check_threshold, finite
from ..defaults import DEFAULTS
from ..errors import IncompatibleFieldsError, InvalidOptionError, InvalidPointsError
from . import _file as fieldfile
from ._blocks import Blocks
from ._file import FORMAT_VERSION
from ._kernels import bin_trilinear, mark_blocks, splat_exact, trilinear
from ._lattice import BLOCK, Grid, check_kernel
from ._spacing import resolve_lattice

__all__ = ["DensityField", "threshold", "FORMAT_VERSION", "BOOLEAN_METHODS"]  # FORMAT_VERSION: of sdp.fields._file

#: The ``method`` of the fields :mod:`sdp.fields._boolean` returns (saved with them): they hold a combined
#: F as G := h − F, not the density of any points (:attr:`DensityField.is_boolean`).
BOOLEAN_METHODS = ("union", "intersection", "difference")

_DELTA = math.exp(-0.5)
#: Build method used by ``method="auto"``: binning + blur was faster at every size measured
#: (``benchmarks/bench_core.py``) and departs from the exact sum by < 1 % of the peak.
_AUTO_METHOD = "fast"
_CHUNK = 4_000_000  # points binned per kernel call (a progress step)
_SPLIT_POINTS = 50_000  # fewer points are marked and binned on one thread (a thread's start costs more)
_ALL = 1 << 62  # a slab holding every node


def _slabs(xyz: np.ndarray, x0: float, voxel: float) -> list[tuple[int, int]]:
    """Two slabs of nodes along x, split at a block's face near the points' median (of a sample):
    about half the binning each."""
    ix = np.floor((xyz[::64, 0] - x0) / voxel)
    mid = int(np.median(ix)) // BLOCK * BLOCK
    return [(-_ALL, mid), (mid, _ALL)]


def threshold(k: float = DEFAULTS.k) -> float:
    """The paper's threshold h = 1 + k·e^(−1/2): the density of a point with k neighbours at σ.

    Raises
    ------
    InvalidOptionError
        ``k`` not a finite number, or one that makes h ≤ 0 (no density is below it).
    """
    k = finite("k", k)
    check_threshold(k, None)
    return 1.0 + k * _DELTA


class DensityField:
    """Global density G(x) = Σ_i exp(−‖x − p_i‖² / 2σ²) of a point cloud, on a sparse grid.

    Build one with :meth:`from_points`. ``G`` is sampled at the nodes of a world-aligned grid
    of voxel length ``l`` (see :mod:`sdp.fields._lattice`), stored in blocks of 8³ nodes that exist only
    where some point's kernel reaches; elsewhere G = 0. Between nodes G is interpolated
    trilinearly. The normalized field is F = h − G (negative inside the cluster volume).

    Fields returned by the Boolean operations of :mod:`sdp.fields._boolean` are instances too, flagged
    by :attr:`is_boolean`: they store the combined F through ``G := h − F``, so queries,
    meshes, files and further Boolean operations work on them; :meth:`coarsen` and
    :meth:`accumulate`, which need the density of points, refuse them.

    Attributes
    ----------
    grid : Grid
        Voxel size, snapped origin and the box of blocks.
    blocks : Blocks
        The node values of G in blocks of 8³, their keys and the block directory
        (:class:`sdp.fields._blocks.Blocks`, local to ``grid``'s box).
    h : float
        Threshold of the normalized field F = h − G.
    sigma : float
        Kernel standard deviation in world units (σ = ``sigma_voxels`` · l).
    truncate : float
        Kernels are cut off beyond ``truncate`` · σ along each axis (a cube).
    n_points : int
        Finite points the field was built from (0 for Boolean results).
    n_dropped : int
        Rows of the input that held NaN or Inf and were left out.
    method : str
        ``"exact"``, ``"fast"``, or the Boolean operation that made the field
        (:data:`BOOLEAN_METHODS`).
    """

    def __init__(self, grid: Grid, keys: np.ndarray, blocks: np.ndarray, *, h: float, sigma: float,
                 truncate: float, n_points: int = 0, n_dropped: int = 0, method: str = "exact"):
        self.grid = grid
        self.blocks = Blocks(grid.shape_blocks, keys, blocks)
        self.h = float(h)
        self.sigma = float(sigma)
        self.truncate = float(truncate)
        self.n_points = int(n_points)
        self.n_dropped = int(n_dropped)
        self.method = method

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_points(cls, points, *, voxel_size: float | str | None = DEFAULTS.voxel_size,
                    grid_size: int | None = None, sigma_voxels: float | str = DEFAULTS.sigma_voxels,
                    k: float = DEFAULTS.k, h: float | None = None, truncate: float = DEFAULTS.truncate,
                    method: str = DEFAULTS.method, memory_limit: int | str | None = None) -> "DensityField":
        """Build the density field of a cloud in O(n).

        Parameters
        ----------
        points : array_like, shape (n, 3)
            World coordinates (float64). Rows holding NaN or Inf are dropped and counted in
            :attr:`n_dropped`. (Internally also the ``Points`` of ``sdp._core._points.as_points``,
            used as validated.)
        voxel_size : float or "auto"
            Node spacing l in world units; ``"auto"`` (the default, :data:`sdp.DEFAULTS`):
            :func:`sdp.auto_voxel_size` of the cloud, σ from its point spacing.
        grid_size : int, optional
            The paper's level of detail: the bounding box's longest side divided into
            ``grid_size`` segments (80 in the paper); wins over ``voxel_size="auto"``.
        sigma_voxels : float or "auto"
            σ in voxels; ``"auto"`` (default): 1.5 on the automatic lattice (σ is the point
            spacing's, the lattice only samples it), the paper's 2 with a given voxel or grid
            size (:func:`sdp.fields._spacing.resolve_sigma_voxels`).
        k, h : float
            Threshold h = 1 + k·e^(−1/2) (k = 3 neighbours), or ``h`` given directly.
        truncate : float
            Each kernel is cut off outside the cube |x − p|∞ ≤ truncate·σ (3σ: the cut-off
            value is e^(−4.5) ≈ 0.011 of the peak).
        method : {"auto", "exact", "fast"}
            ``"exact"`` adds every point's Gaussian to every node of its kernel cube.
            ``"fast"`` spreads each point over its cell's 8 nodes (trilinear weights), then
            blurs with a separable Gaussian of variance σ² − 1/6 voxel² (the binning adds
            1/6 voxel² on average), scaled so each point keeps the mass of its exact
            Gaussian. It departs from the exact sum by less than 1 % of the field's peak on
            the clouds tested (``tests/test_field.py`` holds it to 2 %). ``"auto"`` picks the
            method measured faster (see ``_AUTO_METHOD``).
        memory_limit : int or str, optional
            Refuse (before allocating) grids that need more; default ``$SDP_MEMORY_LIMIT`` or 4 GiB.

        Raises
        ------
        InvalidPointsError
            Not an (n, 3) array, no finite point, or zero extent with ``grid_size``.
        GridTooLargeError
            The grid would need more memory than ``memory_limit``.

        Examples
        --------
        >>> import numpy as np
        >>> from sdp import DensityField
        >>> pts = np.random.default_rng(0).random((1000, 3))
        >>> field = DensityField.from_points(pts, voxel_size=0.05)  # σ = 2 voxels, h for k = 3
        >>> field.voxel_size, round(field.sigma, 3), round(field.h, 2)
        (0.05, 0.1, 2.82)
        >>> bool(field.inside(pts).all()), bool(field.inside([[5.0, 5.0, 5.0]])[0])
        (True, False)
        """
        (field,), _ = build_fields([points], voxel_size=voxel_size, grid_size=grid_size, sigma_voxels=sigma_voxels,
                                   k=k, h=h, truncate=truncate, method=method, memory_limit=memory_limit)
        return field

    @classmethod
    def _binned(cls, cloud: Points, *, voxel_size: float, sigma_voxels: float, k: float, h: float | None,
                truncate: float, method: str, memory_limit: int | str | None, split: bool = False):
        """The first, single-threaded part of :meth:`from_points` for a validated cloud and checked
        options (:func:`build_fields`): (field, flags of the blocks written, taps), the field holding
        the exact sums (``method="exact"``, taps None) or the binned weights still to be blurred with
        ``taps`` (``"fast"``). ``split``: mark and bin on two threads (a cloud built alone), the
        field the same to the bit."""
        l = voxel_size
        if method == "auto":
            method = _AUTO_METHOD
        if method not in ("exact", "fast"):
            raise InvalidOptionError(f"method must be 'auto', 'exact' or 'fast', got {method!r}")
        if method == "fast" and sigma_voxels <= math.sqrt(1.0 / 6.0):
            raise InvalidOptionError(f"sigma of {sigma_voxels:g} voxels is below 0.41 voxels, the least the fast build "
                                     "(binning, then a blur) can make: use a larger sigma in voxels")
        rmax = truncate * sigma_voxels
        reach = check_kernel(sigma_voxels, truncate, memory_limit)
        grid = Grid.covering(cloud.lo, cloud.hi, l, reach)
        span = float(np.max(cloud.hi - cloud.lo))
        check_memory(grid.n_blocks_box * 5, f"the block directory of a {grid.shape} grid", memory_limit,
                     advice=f"the points span {span:.4g} at a voxel of {l:.4g}: remove far outliers, or use a larger "
                            "voxel size (or a smaller grid size)")
        xyz, origin, l = cloud.xyz, grid.origin, grid.voxel_size
        shape_blocks = np.asarray(grid.shape_blocks, np.int64)
        halves = split and len(xyz) >= _SPLIT_POINTS and concurrent()
        if halves:  # each half's blocks, joined: the same blocks
            half = len(xyz) // 2
            occ = np.bitwise_or(*map_concurrently(lambda part: mark_blocks(part, origin, l, reach, reach + 1,
                                                                           shape_blocks), (xyz[:half], xyz[half:])))
        else:
            occ = mark_blocks(xyz, origin, l, reach, reach + 1, shape_blocks)
        flat = np.flatnonzero(occ)
        check_memory(flat.size * BLOCK**3 * 4 + grid.n_blocks_box * 5,
                     f"{flat.size} blocks of {BLOCK}³ nodes (voxel {l:g})", memory_limit)
        keys = np.stack(np.unravel_index(flat, grid.shape_blocks), axis=1)
        field = cls(grid, keys, np.zeros((flat.size, BLOCK**3), np.float32),
                    h=threshold(k) if h is None else h, sigma=sigma_voxels * l, truncate=truncate,
                    n_points=len(cloud.xyz), n_dropped=cloud.n_dropped,
                    method=method)
        touched = np.zeros(flat.size, np.bool_)
        with bar(len(xyz), "building field") as pb:
            for s in range(0, len(xyz), _CHUNK):
                part = xyz[s:s + _CHUNK]
                if method == "exact":
                    splat_exact(part, origin, l, field.blocks.directory, field.blocks.values,
                                1.0 / (2 * sigma_voxels**2), rmax, reach)
                else:
                    slabs = _slabs(part, origin[0], l) if halves else [(-_ALL, _ALL)]
                    map_concurrently(lambda s: bin_trilinear(part, origin, l, field.blocks.directory,
                                                             field.blocks.values, touched, *s), slabs)
                pb.update(len(part))
        if method == "exact":
            return field, touched, None
        s = math.sqrt(sigma_voxels**2 - 1.0 / 6.0)
        return field, touched, _gaussian_taps(s, int(math.floor(rmax))) * np.float32(sigma_voxels / s)

    # ------------------------------------------------------------------ online updates
    def accumulate(self, other: "DensityField", *, weight: float = 1.0) -> "DensityField":
        """Add ``weight`` · G_other to this field, in place; returns ``self``.

        ``other`` must share the voxel size, σ and truncation (build it with
        ``voxel_size=self.voxel_size, sigma_voxels=self.sigma / self.voxel_size``). G is linear
        in the points, so accumulating the field of new points equals rebuilding from all the
        points, up to float32 rounding; ``weight=-1`` removes points added before (a sliding
        window). Costs O(other's blocks); new blocks go to spare rows reserved at the end (the
        store grows by half when full, so a stream of frames copies the field's blocks O(log)
        times), and the directory is rebuilt when the box must grow.

        Raises
        ------
        IncompatibleFieldsError
            Another lattice or σ, or either field is a Boolean result (:attr:`is_boolean`).
        """
        if not isinstance(other, DensityField):
            raise IncompatibleFieldsError(f"accumulate takes a DensityField (built on this one's lattice), got "
                                          f"{type(other).__name__}")
        if not (isinstance(weight, (int, float, np.integer, np.floating)) and math.isfinite(weight)):
            raise InvalidOptionError(f"weight must be a finite number, got {weight!r}")
        self._refuse_boolean("accumulate", other)
        if not (np.isclose(other.voxel_size, self.voxel_size, rtol=1e-12, atol=0)
                and np.isclose(other.sigma, self.sigma, rtol=1e-9) and other.truncate == self.truncate):
            raise IncompatibleFieldsError(
                f"can't accumulate a field of voxel {other.voxel_size:g}, σ {other.sigma:g} into one of voxel "
                f"{self.voxel_size:g}, σ {self.sigma:g}: build it with the same voxel_size and sigma_voxels")
        keys = other.global_keys
        if len(keys) == 0:
            return self
        lo = np.minimum(keys.min(axis=0), self.grid.block_origin)
        hi = np.maximum(keys.max(axis=0) + 1, self.grid.block_origin + np.asarray(self.grid.shape_blocks))
        if np.any(lo < self.grid.block_origin) or np.any(hi > self.grid.block_origin + self.grid.shape_blocks):
            grid = Grid(self.voxel_size, lo, tuple(int(v) for v in hi - lo))
            check_memory(grid.n_blocks_box * 5 + self.nbytes, f"the block directory of a {grid.shape} grid", None)
            self.blocks.move(self.grid.block_origin - lo, grid.shape_blocks)
            self.grid = grid
        rows = self.blocks.allocate(keys - self.grid.block_origin)
        self.blocks.add(rows, other.blocks.values, weight)
        self.n_points += int(round(weight * other.n_points))
        return self

    def copy(self) -> "DensityField":
        """An independent copy (node values, blocks and directory copied)."""
        out = DensityField.__new__(DensityField)
        out.__dict__.update(self.__dict__)
        out.blocks = self.blocks.copy()
        return out

    def scale(self, factor: float) -> "DensityField":
        """Multiply G by ``factor``, in place (an exponential decay: old points fade); returns ``self``.

        O(allocated nodes). Observed every frame with decay λ, a static surface's G settles at
        1/(1 − λ) times one frame's. ``factor``: a finite number (refused in one line before the
        field is touched, as :meth:`accumulate`'s ``weight``).
        """
        factor = finite("factor", factor)
        self._refuse_boolean("scale")  # a combined F scaled is no Boolean of scaled densities
        self.blocks.values *= np.float32(factor)
        return self

    @property
    def is_boolean(self) -> bool:
        """Whether the field is a result of :mod:`sdp.fields._boolean` (``method`` in :data:`BOOLEAN_METHODS`,
        also after save and load): its G is h − F of the combined volume, not a density of points."""
        return self.method in BOOLEAN_METHODS

    def _refuse_boolean(self, operation: str, *others: "DensityField") -> None:
        for f in (self, *others):
            if f.is_boolean:
                raise IncompatibleFieldsError(
                    f"{operation}() needs the density of points, and this field is the {f.method} of two fields "
                    "(it holds F as G = h - F): apply it to the fields built from points, then combine them")

    # ------------------------------------------------------------------ queries
    @property
    def voxel_size(self) -> float:
        """Node spacing l, in world units."""
        return self.grid.voxel_size

    @property
    def n_blocks(self) -> int:
        """Number of allocated blocks of 8³ nodes."""
        return len(self.blocks)

    @property
    def nbytes(self) -> int:
        """Memory held by node values (spare rows included) and the block directory, in bytes."""
        return self.blocks.nbytes

    def density(self, points) -> np.ndarray:
        """G at world positions (n, 3), by trilinear interpolation; 0 outside the grid, NaN for NaN rows."""
        return self.interpolate(self.blocks.values, points)

    def interpolate(self, values: np.ndarray, points) -> np.ndarray:
        """Trilinear interpolation at world positions of per-node ``values`` laid out like this
        field's blocks (float32, (n_blocks, 512)); nodes outside the blocks read as 0."""
        pts = _query_array(points)
        values = np.asarray(values)
        if values.shape != self.blocks.values.shape or values.dtype != np.float32:
            raise InvalidOptionError(f"values must be float32 of this field's blocks' shape "
                                     f"{self.blocks.values.shape}, got {values.dtype} {values.shape}")
        out = np.empty(len(pts))
        trilinear(pts, self.grid.origin, self.voxel_size, self.blocks.directory, values, out)
        return out

    def footprint(self, points) -> np.ndarray:
        """The density projected on the x, y plane, at each point's x, y (any z).

        G integrated along z and divided by the integral of one kernel (√(2π)·σ), from the
        nodes (Σ_z G·l / (√(2π)·σ), then bilinear in x, y): in the units of G, so one point
        adds up to 1 at its own x, y, and a point's footprint is never below its density.
        ``footprint(p) >= h`` says that the cloud sampled the column of p densely enough for
        the threshold, at any height (:func:`sdp.change._coverage.footprint_covered`).
        """
        self._refuse_boolean("footprint")  # a column's sum of h − F is no count of points
        pts = _query_array(points)
        flat = np.ascontiguousarray(pts)
        flat = np.c_[flat[:, :2], np.full(len(flat), self.grid.origin[2])]  # z at the first node of a column
        shape = self.grid.shape_blocks
        keys = self.blocks.keys
        packed = keys[:, 0] * shape[1] + keys[:, 1]
        # only the columns of blocks the queries' cells touch (a cell's far corner may be in the next one)
        cell = np.floor((flat[:, :2] - self.grid.origin[:2]) / self.voxel_size)
        ok = np.all(np.isfinite(cell), axis=1)
        first = (cell[ok].astype(np.int64) // BLOCK)
        near = np.concatenate([first + [dx, dy] for dx in (0, 1) for dy in (0, 1)])
        near = near[np.all((near >= 0) & (near < shape[:2]), axis=1)]
        rows = np.flatnonzero(np.isin(packed, near[:, 0] * shape[1] + near[:, 1], kind="table"))
        packed = packed[rows]
        along_z = self.blocks.values[rows].reshape(-1, BLOCK, BLOCK, BLOCK).sum(axis=3)
        if np.any(packed[1:] < packed[:-1]):  # built fields keep a column's blocks together; accumulated ones may not
            order = np.argsort(packed, kind="stable")
            packed, along_z = packed[order], along_z[order]
        starts = np.flatnonzero(np.r_[True, packed[1:] != packed[:-1]]) if len(packed) else np.zeros(0, np.int64)
        cols = packed[starts]
        sums = np.add.reduceat(along_z, starts, axis=0) if len(starts) else np.zeros((0, BLOCK, BLOCK), np.float32)
        sums *= np.float32(self.voxel_size / (math.sqrt(2 * math.pi) * self.sigma))
        directory = np.full((shape[0], shape[1], 1), -1, np.int32)
        directory[cols // shape[1], cols % shape[1], 0] = np.arange(len(cols), dtype=np.int32)
        values = np.repeat(sums[..., None], BLOCK, axis=3).reshape(len(cols), BLOCK**3)
        out = np.empty(len(flat))
        trilinear(flat, self.grid.origin, self.voxel_size, directory, values, out)
        return out

    def field(self, points) -> np.ndarray:
        """F = h − G at world positions: negative inside the cluster volume."""
        return self.h - self.density(points)

    def inside(self, points) -> np.ndarray:
        """Boolean mask of the positions inside the cluster volume (F < 0); False for NaN rows."""
        return self.field(points) < 0

    def with_threshold(self, *, k: float | None = None, h: float | None = None) -> "DensityField":
        """The same density with another threshold (shares the node values, no copy).

        A union or intersection moves with its operands' common threshold (F shifts alike on
        both); a difference, max(F_a, −F_b), does not: refused (:class:`~sdp.IncompatibleFieldsError`).
        """
        if (k is None) == (h is None):
            raise InvalidOptionError("give exactly one of k= and h=")
        check_threshold(k, h)
        if self.method == "difference":
            raise IncompatibleFieldsError("with_threshold() of a difference is not the difference of the fields at "
                                          "that threshold: set it on both fields, then take their difference")
        out = DensityField.__new__(DensityField)
        out.__dict__.update(self.__dict__)
        out.blocks = self.blocks.view()
        out.h = threshold(k) if h is None else float(h)
        return out

    def node_values(self, global_keys: np.ndarray) -> np.ndarray:
        """G at every node of the blocks with global block coordinates ``global_keys`` (m, 3).

        Returns float32 (m, 512); blocks this field doesn't hold read as 0. Used to combine
        two fields on one lattice without interpolation.
        """
        return self.blocks.take(np.asarray(global_keys, np.int64) - self.grid.block_origin)

    @property
    def global_keys(self) -> np.ndarray:
        """Global block coordinates (m, 3) of the allocated blocks."""
        return self.blocks.keys + self.grid.block_origin

    def to_dense(self, *, memory_limit: int | str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """G on every node of the bounding box of blocks: ``(array float32, world origin)``."""
        check_memory(int(np.prod(self.grid.shape)) * 4, f"a dense {self.grid.shape} array", memory_limit)
        dense = self.blocks.box(np.zeros(3, np.int64), np.asarray(self.grid.shape, np.int64))
        return dense, self.grid.origin

    # ------------------------------------------------------------------ derived fields
    def mesh(self, *, level: float = 0.0):
        """Iso-surface F = ``level`` (default 0: the cluster boundary) by Lewiner's marching cubes.

        See :func:`sdp.fields._surface.extract_surface`.
        """
        from ._surface import extract_surface

        return extract_surface(self, level=level)

    def coarsen(self) -> "DensityField":
        """The next level of detail: voxel 2l and σ doubled, without the points.

        A peak-1 Gaussian of σ convolved with a normalized Gaussian of s = √3·σ is
        (1/8)·(peak-1 Gaussian of 2σ); so G at 2σ is 8 × (G blurred by s), sampled at every
        second node. Exact up to the kernels' truncation and the grid's sampling.

        Raises
        ------
        IncompatibleFieldsError
            The field is a Boolean result (:attr:`is_boolean`): not a sum of Gaussians.
        """
        self._refuse_boolean("coarsen")
        l, sv = self.voxel_size, self.sigma / self.voxel_size
        s = math.sqrt(3.0) * sv
        taps = _gaussian_taps(s, int(math.floor(self.truncate * s)))
        taps *= np.float32(2.0) / taps.sum()  # normalized kernel, x2 per axis (8 in 3-D)
        # dilate the blocks by the blur's reach so the wider kernel has room
        pad = -(-(len(taps) // 2) // BLOCK)
        occ = np.zeros(np.asarray(self.grid.shape_blocks) + 2 * pad, bool)
        span = range(-pad, pad + 1)
        for dx in span:
            for dy in span:
                for dz in span:
                    idx = self.blocks.keys + pad + np.array([dx, dy, dz])
                    occ[tuple(idx.T)] = True
        grid = Grid(l, self.grid.block_origin - pad, tuple(occ.shape))
        keys = np.stack(np.nonzero(occ), axis=1)
        wide = DensityField(grid, keys, self.node_values(keys + grid.block_origin), h=self.h,
                            sigma=self.sigma, truncate=self.truncate)
        wide.blocks.blur(taps)
        # coarse block K holds coarse nodes 8K…8K+7 = fine nodes 16K…16K+14 (global)
        ckeys = np.unique(np.floor_divide(wide.global_keys, 2), axis=0)
        cgrid = Grid(2 * l, ckeys.min(axis=0), tuple(int(v) for v in np.ptp(ckeys, axis=0) + 1))
        offs = np.stack(np.unravel_index(np.arange(BLOCK**3), (BLOCK,) * 3), axis=1)
        fine = (ckeys[:, None, :] * BLOCK + offs[None]) * 2 - wide.grid.block_origin * BLOCK
        vals = wide.blocks.at_nodes(fine.reshape(-1, 3))
        return DensityField(cgrid, ckeys - cgrid.block_origin, vals.reshape(-1, BLOCK**3), h=self.h,
                            sigma=2 * self.sigma, truncate=self.truncate, n_points=self.n_points,
                            n_dropped=self.n_dropped, method=f"coarsen({self.method})")

    # ------------------------------------------------------------------ files
    def save(self, path: str | os.PathLike) -> Path:
        """Write the field to ``path`` (compressed ``.sdpf``: a zip of arrays and JSON metadata,
        :mod:`sdp.fields._file`).

        The file is written under a temporary name and renamed, so a crash never leaves a
        half-written file and an existing file is replaced only once the new one is complete.
        """
        return fieldfile.write(self, path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "DensityField":
        """Read a field written by :meth:`save` (:func:`sdp.fields._file.read`)."""
        return cls(**fieldfile.read(path))

    def __repr__(self) -> str:
        return (f"DensityField(voxel_size={self.voxel_size:g}, sigma={self.sigma:g}, h={self.h:.4g}, "
                f"blocks={self.n_blocks}, box={self.grid.shape}, n_points={self.n_points}, method={self.method!r})")


def build_fields(clouds, *, voxel_size: float | str | None = DEFAULTS.voxel_size, grid_size: int | None = None,
                 sigma_voxels: float | str = DEFAULTS.sigma_voxels, k: float = DEFAULTS.k, h: float | None = None,
                 truncate: float = DEFAULTS.truncate, method: str = DEFAULTS.method,
                 memory_limit: int | str | None = None) -> tuple[list[DensityField], list[float]]:
    """:meth:`DensityField.from_points` of each cloud, on one lattice (the voxel resolved from all
    of them, :func:`sdp.fields._spacing.resolve_lattice`): their single-threaded parts (block marking,
    binning) at once on the threads of :func:`sdp._core._parallel.map_concurrently` (a cloud alone:
    its two halves marked, its two slabs binned at once), then the parallel blurs in turn. Returns
    the fields and the seconds each took (its first part, in its own thread, plus its blur: together
    more than the wall time when the first parts overlap)."""
    check_grid_options(voxel_size=None if grid_size is not None else voxel_size, sigma_voxels=sigma_voxels, k=k,
                       h=h, truncate=truncate, memory_limit=memory_limit)  # before any work
    clouds = [c if isinstance(c, Points) else as_points(c) for c in clouds]  # Points: validated already
    voxel, sigma_voxels = resolve_lattice(clouds, voxel_size=voxel_size, grid_size=grid_size, k=k,
                                          sigma_voxels=sigma_voxels)
    options = dict(voxel_size=voxel, sigma_voxels=sigma_voxels, k=k, h=h, truncate=truncate, method=method,
                   memory_limit=memory_limit)

    def binned(cloud):
        t = time.perf_counter()
        return DensityField._binned(cloud, split=len(clouds) == 1, **options), time.perf_counter() - t

    fields, seconds = [], []
    for (field, touched, taps), t_binned in map_concurrently(binned, clouds):
        t = time.perf_counter()
        if taps is not None:
            field.blocks.blur(taps, nonzero=touched)
        fields.append(field)
        seconds.append(t_binned + time.perf_counter() - t)
    return fields, seconds


def _gaussian_taps(s: float, radius: int) -> np.ndarray:
    j = np.arange(-radius, radius + 1, dtype=np.float64)
    return np.exp(-(j**2) / (2 * s * s)).astype(np.float32)


def _query_array(points) -> np.ndarray:
    try:
        arr = np.ascontiguousarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidPointsError(f"query points: expected an (n, 3) array of numbers ({exc})") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InvalidPointsError(f"query points: expected shape (n, 3), got {arr.shape}")
    return arr
