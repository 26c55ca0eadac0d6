"""Change detection in tiles: clouds larger than memory, in parallel on Dask.

The data path of :func:`sdp.detect_changes`, cut into square columns of the global lattice:

1. **bucket** (one Dask task per slice of each file): read the rows (LAS/LAZ chunks, NPY and
   PLY slices; :class:`sdp.io.PointSource`), and append each point, with its row number, to the
   bucket of its tile and of every tile whose *halo* it lies in (on disk, in ``workdir``);
2. **compare** (one task per tile): build the two fields from the tile's buckets, form the
   difference volumes and flag the tile's own points, as :func:`sdp.detect_changes` does, and
   label the tile's own change regions (:func:`sdp.change._regions.label_part`); return the changed rows
   and the labels of the tile's face nodes;
3. **regions** (here): join the tiles' labels across their faces (:func:`sdp.change._regions.join_parts`).

Tiles are square columns of ``T × T`` blocks (all z) of the global lattice. A tile's points plus
its halo of ``ceil(truncate·σ) + 3`` voxels (kernel reach, binning, interpolation, margin) hold
every point whose kernel reaches the nodes a tile point is interpolated from, so each tile's
decisions equal the untiled run's (tested on a scene whose objects straddle tile corners, and on
objects over 100+ tiles).

- **Bucket**: one task per 8 M rows of each file. :class:`~sdp.io.PointSource` reads row slices
  (LAS/LAZ by seeking the LAZ chunk table, NPY and binary PLY through memory maps); each finite
  point goes, with its row number, to the bucket file of its tile and of every tile whose halo
  holds it. A task's first write to each bucket truncates it, so a task run again after its
  worker died writes its rows once.
- **Compare**: both fields from the tile's buckets (rows in file order, so the sums run in the
  same order as untiled), D and the masks of the tile's own points as in :mod:`sdp.change._detect`, the
  footprint of the other field (the halo holds every kernel that reaches a column), and the
  tile's part of the change regions (:mod:`sdp.change._regions` explains the join over face nodes). A
  task returns the changed rows and points and their labels, not the blocks.
- The first task that fails for good stops the run (the others are cancelled); Dask workers
  that die running one task more often than the scheduler allows raise
  :class:`~sdp.WorkerLostError`. A scheduler that does not answer within 10 s is an error, not
  a hang. Local workers ignore SIGINT: the client ends the run, and removes the work folder.

**Memory** (:class:`JobBudget`): the memory limit is the whole job's. The command takes a fixed
share: its process, counted as 256 MiB (measured 220 MiB), and the streamed output's chunk. Not
counted: the changed rows and the face nodes while the regions are joined (≈ 48 bytes per changed
point), and the result, which holds rows, not per-point arrays (:class:`sdp.ChangeResult`: 12
bytes per changed point, 8 per not comparable one), from which the output is streamed
(:meth:`sdp.ChangeResult.rows`); its per-point arrays (5 bytes per point of a cloud) are made
only when a caller asks for them, outside the limit, which the command never does. The rest is
split over the workers (a local cluster's, or a remote scheduler's worker threads, counted when
connecting), and each worker's share less its own process (256 MiB, measured 210 MiB) is one
task's. A tile
holds what that share holds at ≈ 1.2 KB per point and epoch, its halo included, at the clouds'
mean density. Tiles that share cannot hold (a limit below the processes themselves, or a given
``--tile-size``) are refused before any cluster starts, with the smallest limit that works.
:func:`sdp.io.write_points_streamed` writes the output chunk by chunk (LAS/LAZ keeps every input
dimension). ``sdp change`` takes this path by itself (:func:`sdp.plan_change`) when two
dense grids over the box (:func:`dense_grid_bytes`), or the points in memory (the process and
≈ 200 bytes per point: :func:`untiled_point_bytes`), would exceed the memory limit.

Tasks run on a Dask local cluster (one single-threaded worker process per core, Numba at one
thread each) by default, or on any ``dask.distributed`` cluster given its scheduler address;
``workdir`` must then be on a file system every worker can reach, and so must the input files.

References
----------
.. [1] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
   Comparison and Applications", Algorithm 1.
.. [2] Dask Development Team, "Dask: Library for dynamic task scheduling", https://dask.org.
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import signal
import tempfile
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._core._memory import check_memory, format_bytes
from .._core._memory import memory_limit as _memory_limit
from .._core._progress import bar
from .._core._validate import (
    check_grid_options,
    check_tile_options,
    integer_at_least,
    nonnegative_finite,
    positive_finite,
)
from ..change._coverage import footprint_covered
from ..change._detect import ChangeResult, PointChanges
from ..change._regions import Volume, describe_regions, join_parts, label_part
from ..defaults import DEFAULTS
from ..errors import GridTooLargeError, InvalidOptionError, InvalidPointsError, SDPError, WorkerLostError, require
from ..fields._density import DensityField, threshold
from ..fields._lattice import BLOCK, check_kernel, check_lattice, kernel_reach
from ..io._source import PointSource
from ..options import Cylinder, Execution, Lattice
from . import _kernels as K
from ._store import FieldStore, require_zarr

__all__ = ["detect_changes_tiled", "build_field_tiled", "distances_tiled", "first_slices",
           "dense_grid_bytes", "untiled_point_bytes", "sampled_lattice"]

_PART_ROWS = 8_000_000  # rows read by one bucketing task
_BYTES_PER_ROW_READ = 600  # a decoded row in a bucketing task: record, x y z, tile keys, sort, bucket record
_BYTES_PER_TILE_POINT = 1200  # a point of one epoch in a compare task: bucket record, its share of two fields
# (blocks, blur buffer, difference), masks: the 100 M-point benchmark peaked at 3.4 GiB (client and 2 workers)
# with 1.2 M points per tile and epoch


def dense_grid_bytes(lo, hi, voxel_size: float, *, sigma_voxels: float = 2.0, truncate: float = 3.0) -> int:
    """Bytes of one float32 dense grid over the box [lo, hi] with its kernel margin: the size
    at which :func:`detect_changes_tiled` is worth its overhead (``sdp change`` switches when
    two of them exceed the memory limit)."""
    reach = kernel_reach(sigma_voxels, truncate)
    nodes = np.floor((np.asarray(hi, float) - np.asarray(lo, float)) / positive_finite("voxel_size", voxel_size))
    return int(np.prod(nodes + 2 * reach + 2) * 4)


#: Resident bytes of ``sdp change`` in memory, per point of both clouds: float64 x, y, z, the file
#: records, the fields' share, masks, labels and the output's records (measured: 1.26 GiB at the peak
#: for two LAZ clouds of 2.9 M and 3 M points at 1 m voxels, the process itself included).
_BYTES_PER_POINT_IN_MEMORY = 200
#: The in-memory command's process before any data: the interpreter, NumPy, SciPy and Numba's kernels
#: (measured: 197 MiB after a small comparison).
PROCESS_BYTES = 224 * 2**20


def untiled_point_bytes(n_points: int) -> int:
    """Bytes the in-memory comparison of ``n_points`` (both clouds) holds at its peak, the process
    itself included (the fields' blocks are checked against the memory limit when allocated)."""
    return PROCESS_BYTES + int(n_points) * _BYTES_PER_POINT_IN_MEMORY


@dataclass(frozen=True)
class _Tiling:
    """Square columns of ``blocks`` × ``blocks`` lattice blocks, with a halo (world units)."""

    voxel_size: float
    blocks: int
    halo: float

    @property
    def edge(self) -> float:
        return self.blocks * BLOCK * self.voxel_size

    def owns(self, key, xyz: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Mask of the points whose cell, floor(p / l), lies in tile ``key``'s blocks (x, y), or
        within ``margin`` (world units) of them."""
        n = self.blocks * BLOCK
        m = margin / self.voxel_size
        u = xyz[:, 0] / self.voxel_size
        v = xyz[:, 1] / self.voxel_size
        return ((u >= key[0] * n - m) & (u < (key[0] + 1) * n + m) & (v >= key[1] * n - m)
                & (v < (key[1] + 1) * n + m))


def _bucket_part(source: PointSource, epoch: str, start: int, stop: int, part: int, tiling: _Tiling,
                 root: str, chunk_rows: int) -> tuple[dict, int, float]:
    """Bucket rows start … stop−1 of ``source``, ``chunk_rows`` at a time; returns ({tile: count},
    rows dropped, seconds reading)."""
    counts: dict[tuple[int, int], int] = {}
    dropped, t_read = 0, 0.0
    chunks = source.chunks(chunk_rows, start, stop)
    while True:
        t = time.perf_counter()
        item = next(chunks, None)
        t_read += time.perf_counter() - t
        if item is None:
            break
        first, xyz = item
        i0, j0, nj, sizes, records, n_bad = K.tile_buckets(xyz, first, tiling.voxel_size, tiling.blocks * BLOCK,
                                                            tiling.halo)
        dropped += n_bad
        ends = np.cumsum(sizes)
        for b in np.flatnonzero(sizes):
            key = (int(i0 + b // nj), int(j0 + b % nj))
            path = Path(root, epoch, f"{key[0]}_{key[1]}")
            path.mkdir(exist_ok=True)  # not its parents: a run that ended removed them, and stays removed
            # the task's first write to a bucket truncates it: a task run again (its worker died) writes
            # its rows once
            with open(path / f"{part:06d}.bin", "ab" if key in counts else "wb") as f:
                records[ends[b] - sizes[b]:ends[b]].tofile(f)
            counts[key] = counts.get(key, 0) + int(sizes[b])
    return counts, dropped, t_read


def _load(root: str, epoch: str, key) -> np.ndarray:
    """Bucket of tile ``key``: (m, 4) float64 rows x, y, z, row number, in row order."""
    folder = Path(root, epoch, f"{key[0]}_{key[1]}")
    if not folder.is_dir():
        return np.zeros((0, 4))
    return np.concatenate([np.fromfile(p, np.float64).reshape(-1, 4) for p in sorted(folder.iterdir())])


def _empty_field(like: DensityField) -> DensityField:
    """A field with no point (G = 0 everywhere) on ``like``'s lattice."""
    return DensityField(like.grid, np.zeros((0, 3), np.int64), np.zeros((0, BLOCK**3), np.float32), h=like.h,
                        sigma=like.sigma, truncate=like.truncate)


def _compare_tile(key, root: str, tiling: _Tiling, opts: dict, store: str | None, regions: bool = True) -> dict:
    """Fields of both epochs in one tile, its own changed rows and its own not comparable rows
    (outside the other field's footprint; see the module docstring), and with ``regions`` the
    components of the difference volume in the tile (:func:`sdp.change._regions.label_part`: what the
    regions across tiles are joined from). With ``store`` (a :class:`FieldStore` path) the
    reference field is read from it."""
    t0 = time.perf_counter()
    recs = {e: _load(root, e, key) for e in ("reference", "current")}
    out = {"read": time.perf_counter() - t0, "build_reference": 0.0, "build_current": 0.0, "label": 0.0}
    fields = {}
    for e, rec in recs.items():
        t = time.perf_counter()
        if e == "reference" and store is not None:
            fields[e] = FieldStore.open(store).tile_field(key)
        else:
            fields[e] = DensityField.from_points(rec[:, :3], **opts) if len(rec) else None
        out[f"build_{e}"] = time.perf_counter() - t
    t = time.perf_counter()
    blocks_lo = np.asarray(key, np.int64) * tiling.blocks
    for e, other, kind in (("current", "reference", "appeared"), ("reference", "current", "disappeared")):
        fld, rec = fields[e], recs[e]
        own = np.zeros(len(rec), bool) if fld is None else tiling.owns(key, rec)
        out[kind] = (np.zeros(0, np.int64), np.zeros((0, 3)), None, np.zeros(0, np.int64))
        if fld is None or len(rec) == 0 or (not own.any() and not regions):
            continue  # no points of this epoch here (a stored reference has none): no difference volume
        pts = np.ascontiguousarray(rec[own, :3])
        d = Volume.difference(fld, fields[other] or _empty_field(fld))  # evaluated where needed, never stored
        mask = d.negative_at(fld, pts) if len(pts) else np.zeros(0, bool)
        rows = rec[own, 3].astype(np.int64)
        cand = np.flatnonzero(mask)
        unseen = cand if fields[other] is None else cand[~footprint_covered(pts[cand], fields[other])]
        mask[unseen] = False
        part = None
        if regions:
            t1 = time.perf_counter()
            part = label_part(fld, d, pts[mask], blocks_lo, blocks_lo + tiling.blocks)  # the regions span tiles
            out["label"] += time.perf_counter() - t1
        out[kind] = (rows[mask], pts[mask], part, rows[unseen])
    out["detect"] = time.perf_counter() - t - out["label"]
    return out


def _regions(parts, voxel_size: float, min_region_points: int, regions: bool):
    """Rows, region labels and regions of one kind of change from the tiles' pieces: the tiles'
    components joined across their faces (:func:`sdp.change._regions.join_parts`)."""
    rows = np.concatenate([p[0] for p in parts])
    order = np.argsort(rows, kind="stable")
    rows, xyz = rows[order], np.concatenate([p[1] for p in parts])[order]
    if not regions or len(rows) == 0:
        return rows, np.zeros(len(rows), np.int64), []
    joined, counts = join_parts([p[2] for p in parts if p[2] is not None])
    joined = iter(joined)
    labels = np.concatenate([next(joined) if p[2] is not None else np.full(len(p[0]), -1, np.int64)
                             for p in parts])[order]
    if min_region_points > 1 and len(counts):
        big = (np.bincount(labels, minlength=len(counts)) >= min_region_points)[labels]
        rows, xyz, labels = rows[big], xyz[big], labels[big]
    regs, region_of = describe_regions(xyz, labels, counts, voxel_size)
    return rows, region_of, regs


def detect_changes_tiled(reference, current, *, lattice: Lattice | None = None,
                         min_region_points: int = DEFAULTS.min_region_points, regions: bool = True,
                         execution: Execution | None = None) -> ChangeResult:
    """:func:`sdp.detect_changes` (point decision, footprint coverage) in tiles, for clouds of any size.

    Every default is :data:`sdp.DEFAULTS`, as for :func:`sdp.detect_changes`. Points outside the
    other epoch's footprint (:func:`sdp.change._coverage.footprint_covered`) are not comparable; the
    tiles follow no sensor rays.

    Parameters
    ----------
    reference : path-like, PointSource, array_like (n, 3) or FieldStore
        Files are read in slices (LAS/LAZ, NPY, binary PLY; other formats are read once and
        spilled to ``workdir``); arrays are spilled to ``workdir`` as NPY. A
        :class:`~sdp.FieldStore` (e.g. from :func:`build_field_tiled`) is compared tile by
        tile without its points: only what appeared is found, on the store's lattice,
        σ, threshold and tiles.
    current : path-like, PointSource or array_like (n, 3)
        As ``reference``.
    lattice : Lattice, optional
        As in :func:`sdp.detect_changes` (no ``grid_size``: the tiles need the voxel before
        reading the points). ``voxel_size="auto"`` is measured on the first slice of each
        cloud; the lattice is the store's when ``reference`` is one.
    min_region_points, regions
        As in :func:`sdp.detect_changes`; regions span tiles.
    execution : Execution, optional
        The tiles (:class:`sdp.Execution`): ``tile_size`` in world units (rounded up to whole
        blocks of 8 voxels; default about ``tile_points`` points of the larger cloud per tile,
        from its mean density in x, y; default ``tile_points``: what one task's share of the
        memory limit holds, ≈ 1.2 KB per point and epoch, 230 k points with 2 GiB and 2
        workers). ``memory_limit`` is the whole job's, shared as :class:`JobBudget` says: this
        process's share, then each worker's (of a local cluster, or each thread of the
        scheduler's workers: a task at once each), which less the worker process itself sets the
        tile size and the rows decoded at a time; tiles that need more are refused before any
        work, with the smallest limit that would hold them. ``scheduler``: None, a Dask local
        cluster of ``workers`` processes (default: the cores); ``"tcp://host:8786"``, that
        ``dask.distributed`` scheduler; ``"synchronous"`` or ``"threads"``, Dask's local
        schedulers in this process (debugging, tests). ``workdir``: where the buckets go
        (default: the system's temporary folder), removed afterwards; on a cluster it must be
        shared by all workers.

    Returns
    -------
    ChangeResult
        With ``tiled`` True: the rows that changed, from which the per-point arrays are made on
        first use (``reference_field`` and ``current_field`` are None). With a stored
        reference, only what appeared: every reference point is unchanged.
    """
    lattice, execution = _tiled_options(lattice, execution)
    integer_at_least("min_region_points", min_region_points, 0)
    k, h = lattice.k, lattice.h
    voxel_size, sigma_voxels, truncate = lattice.voxel_size, lattice.sigma_voxels, lattice.truncate
    tiles = execution.tile_keywords()
    store = reference if isinstance(reference, FieldStore) else None
    if store is not None:
        voxel_size, truncate, h = store.voxel_size, store.truncate, store.h
        sigma_voxels = store.sigma / store.voxel_size
        tiles["tile_size"] = store.tile_blocks * BLOCK * store.voxel_size
    clouds = {"current": current} if store is not None else {"reference": reference, "current": current}
    with _Session(clouds, voxel_size, sigma_voxels=sigma_voxels, k=k, h=h, truncate=truncate, method=lattice.method,
                  **tiles) as run:
        jobs = [(key, run.root, run.tiling, run.opts, store and str(store.path), regions) for key in run.tiles]
        results = run.tasks("compare", _compare_tile, jobs,
                            ("read", "build_reference", "build_current", "detect", "label"))
        t = time.perf_counter()
        out = {kind: _regions([r[kind] for r in results], run.voxel_size, min_region_points, regions)
               for kind in ("appeared", "disappeared")}
        unseen = {kind: np.sort(np.concatenate([r[kind][3] for r in results])) for kind in ("appeared", "disappeared")}
        run.timings["regions"] = time.perf_counter() - t
    n_ref = run.sources["reference"].n_rows if store is None else store.n_points
    points = {kind: PointChanges.of_rows(n, *out[kind][:2], unseen[kind])
              for kind, n in (("appeared", run.sources["current"].n_rows), ("disappeared", n_ref))}
    return ChangeResult(_reference=points["disappeared"], _current=points["appeared"],
                        appeared_regions=out["appeared"][2], disappeared_regions=out["disappeared"][2],
                        voxel_size=run.voxel_size, sigma=run.sigma_voxels * run.voxel_size,
                        h=threshold(k) if h is None else float(h), decision="point", tiled=True,
                        n_dropped_reference=run.dropped.get("reference", 0), n_dropped_current=run.dropped["current"],
                        coverage={"appeared": "footprint", "disappeared": "footprint"}, n_tiles=len(run.tiles),
                        tile_size=run.tiling.edge, timings=run.timings)


def distances_tiled(reference, current, *, cylinder: Cylinder | None = None,
                    registration_error: float = DEFAULTS.registration_error, orientation=None,
                    execution: Execution | None = None):
    """:func:`sdp.distances` in tiles, for clouds of any size: every reference row a core point.

    Each tile measures its own reference points from its buckets, which hold every point within
    a halo of the longest search (``max_distance`` + the cylinder and normal reach + two cells);
    the cells start at the clouds' common corner, so with the same scales each distance equals
    :func:`sdp.distances`' (tested). ``"auto"`` scales come from the first slice of each cloud
    (the tiles need them before the points); normals point along ``orientation`` (+z: the tiles
    follow no sensor). Parameters as in :func:`sdp.distances` and :func:`detect_changes_tiled`.

    Returns
    -------
    Distances
        One row per reference row, in row order (rows that held NaN/Inf: NaN, not comparable).
    """
    from ..distance._distances import Distances, distances, search_reach, tile_halo

    cylinder = Cylinder() if cylinder is None else cylinder
    execution = Execution() if execution is None else execution
    reg = nonnegative_finite("registration_error", registration_error)
    t0 = time.perf_counter()
    d, D = cylinder.projection_scale, cylinder.normal_scale
    if d == "auto" or D == "auto":  # from the first slice of each cloud, as the tiled change detection
        firsts = first_slices([reference, current])
        sample = firsts[0].xyz[:: max(1, len(firsts[0].xyz) // 20_000)]
        probe = distances(*firsts, core_points=sample, cylinder=cylinder, sensor_origin=None, orientation=orientation,
                          memory_limit=execution.memory_limit)
        d, D = probe.projection_scale, probe.normal_scale
    sigma_p = d / 4.0
    reach = search_reach(cylinder.max_distance, d)
    halo, margin = tile_halo(d, D, reach)
    with _Session({"reference": reference, "current": current}, sigma_p / 2.0, sigma_voxels=2.0, k=DEFAULTS.k,
                  h=None, truncate=DEFAULTS.truncate, method=DEFAULTS.method, halo=halo,
                  **execution.tile_keywords()) as run:
        opts = dict(cylinder=Cylinder(projection_scale=d, normal_scale=D, max_distance=reach),
                    registration_error=reg, orientation=orientation, corner=run.lo - 1e-9, margin=margin,
                    memory_limit=run.opts["memory_limit"])
        results = run.tasks("distances", _distance_tile, [(key, run.root, run.tiling, opts) for key in run.tiles],
                            ())
    n = run.sources["reference"].n_rows
    xyz, packed = np.full((n, 3), np.nan), np.full((n, 11), np.nan)
    for rows, pts, values in results:
        xyz[rows], packed[rows] = pts, values
    level = np.where(np.isnan(packed[:, 10]), -1, packed[:, 10]).astype(np.int8)
    timings = dict(run.timings, total=time.perf_counter() - t0)
    return Distances(core_points=xyz, distance=packed[:, 0], lod=packed[:, 1], significant=packed[:, 2] == 1,
                     n1=packed[:, 3], n2=packed[:, 4], spread1=packed[:, 5], spread2=packed[:, 6],
                     normal=np.ascontiguousarray(packed[:, 7:10]), level=level, projection_scale=d, normal_scale=D,
                     max_distance=max(reach, 3.0 * sigma_p), registration_error=reg,
                     orientation="towards (0, 0, 1)" if orientation is None else f"towards {tuple(orientation)}",
                     timings=timings, tiles=len(run.tiles))


def _distance_tile(key, root: str, tiling: _Tiling, opts: dict):
    """The distances of tile ``key``'s own reference rows: (rows, xyz, (m, 11) values)."""
    from ..distance._distances import distances

    opts = dict(opts)
    margin = opts.pop("margin")
    ref, cur = _load(root, "reference", key), _load(root, "current", key)
    own = tiling.owns(key, ref)
    if not own.any():
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 11))
    values = np.full((int(own.sum()), 11), np.nan)
    if len(cur) >= 3 and len(ref) >= 3:
        near = tiling.owns(key, ref, margin)
        d = distances(ref[:, :3], cur[:, :3], core_points=ref[near, :3], sensor_origin=None, **opts)
        mine = own[near]
        f = d.fields()
        cols = [f[name] for name in ("distance", "lod", "significant", "n1", "n2", "spread1", "spread2",
                                     "normal_x", "normal_y", "normal_z")]
        values = np.column_stack([*cols, d.level])[mine].astype(np.float64)
        values[values[:, 10] < 0, 10] = np.nan
    return ref[own, 3].astype(np.int64), np.ascontiguousarray(ref[own, :3]), values


def build_field_tiled(cloud, path: str | os.PathLike, *, lattice: Lattice | None = None,
                      execution: Execution | None = None) -> FieldStore:
    """The density field of a cloud of any size, built tile by tile into a :class:`FieldStore`.

    Same parameters as :func:`detect_changes_tiled` (one cloud); ``path`` is the store to
    write (a folder, conventionally ``*.zarr``). Each tile's blocks equal those of
    :meth:`DensityField.from_points` on the whole cloud.
    """
    lattice, execution = _tiled_options(lattice, execution)
    require_zarr()  # before any work
    k, h, truncate = lattice.k, lattice.h, lattice.truncate
    with _Session({"cloud": cloud}, lattice.voxel_size, sigma_voxels=lattice.sigma_voxels, k=k, h=h,
                  truncate=truncate, method=lattice.method, **execution.tile_keywords()) as run:
        store = FieldStore.create(path, voxel_size=run.voxel_size, sigma=run.sigma_voxels * run.voxel_size,
                                  truncate=truncate, h=threshold(k) if h is None else float(h),
                                  tile_blocks=run.tiling.blocks,
                                  inputs=(cloud,) if isinstance(cloud, (str, Path)) else ())
        try:
            jobs = [(key, run.root, run.tiling, run.opts, str(store.path)) for key in run.tiles]
            counts = run.tasks("build", _build_tile, jobs, ())
            store.set_counts(sum(counts), run.dropped["cloud"])
        except BaseException:  # no half-built store left behind (a failed tile, Ctrl-C, SIGTERM)
            shutil.rmtree(store.path, ignore_errors=True)
            raise
    return store


def _tiled_options(lattice: Lattice | None, execution: Execution | None) -> tuple[Lattice, Execution]:
    """The options of a tiled function, with their defaults; a ``grid_size`` refused (the tiles need
    the voxel before they read the points)."""
    lattice = Lattice() if lattice is None else lattice
    if lattice.grid_size is not None:
        raise InvalidOptionError("grid_size is not available in tiles: give a voxel size or 'auto'")
    return lattice, Execution() if execution is None else execution


def _build_tile(key, root: str, tiling: _Tiling, opts: dict, store: str) -> int:
    """Build tile ``key``'s field from its bucket and store its own blocks; returns its own points."""
    rec = _load(root, "cloud", key)
    FieldStore.open(store).write_tile(key, DensityField.from_points(rec[:, :3], **opts))
    return int(tiling.owns(key, rec).sum())


#: Resident memory of the processes themselves, before any data (measured here: 220 MiB for the
#: command with NumPy, Numba's kernels, Dask's client and the local scheduler; 210 MiB for a Dask
#: worker that has run a tile), and of the streamed output in the command (a chunk of LAS records
#: read, its labelled copy and the LAZ encoder's buffers).
CLIENT_BYTES = 256 * 2**20
WORKER_BYTES = 256 * 2**20
WRITE_BYTES = 2_000_000 * 120


def _mb(nbytes: float) -> str:
    """A size in whole MB, rounded up, as ``--memory-limit`` reads it."""
    return f"{math.ceil(nbytes / 2**20)}MB"


@dataclass(frozen=True)
class JobBudget:
    """How one memory limit is shared by the processes of a tiled run: the command (``client``:
    its process and the streamed output; not counted: the changed rows and the face nodes of the
    regions, ≈ 48 bytes per changed point, and the result's rows, which the command never turns
    into per-point arrays) and each of ``workers`` (its process and one task's
    data); with ``separate=False`` the tasks run in the command's own process (Dask's local
    schedulers), ``workers`` of them at once."""

    limit: int
    workers: int
    separate: bool = True

    @property
    def client(self) -> int:
        """The command's share: its process and the streamed output's chunk."""
        return CLIENT_BYTES + WRITE_BYTES

    @property
    def worker(self) -> int:
        """The memory of one worker: what the command leaves, over the workers."""
        return (self.limit - self.client) // self.workers

    @property
    def task(self) -> int:
        """The data one task may hold: a worker's share less the worker process itself."""
        return self.worker - (WORKER_BYTES if self.separate else 0)

    @property
    def task_budget(self) -> str:
        """What :attr:`task` is, for messages."""
        itself = f", less {format_bytes(WORKER_BYTES)} for the worker itself" if self.separate else ""
        return (f"a task's share of the memory limit of {format_bytes(self.limit)} (less {format_bytes(self.client)} "
                f"for the command, over {self.workers} worker(s){itself})")

    def parts(self) -> str:
        """Who takes what, for messages."""
        each = (f"each of {self.workers} Dask worker(s) {format_bytes(WORKER_BYTES)} plus its tile" if self.separate
                else f"each of {self.workers} task(s) its tile")
        return f"the command itself takes {format_bytes(self.client)} and {each}"

    def smallest(self, task_bytes: float) -> int:
        """The smallest limit under which a task may hold ``task_bytes``."""
        return int(self.client + self.workers * (task_bytes + (WORKER_BYTES if self.separate else 0)))


def _check_tile_points(tiling: _Tiling, sources: dict, plan: JobBudget, *, given: bool) -> None:
    """Refuse, before any task runs, tiles whose points (with their halo, at the clouds' mean
    density) would need more than a task's share of the memory limit."""
    need = 2 * _tile_points(tiling, sources) * _BYTES_PER_TILE_POINT
    if need <= plan.task:
        return
    points = f"about {_tile_points(tiling, sources):,} points per epoch with their halo"
    if given and plan.task > 0:
        raise GridTooLargeError(f"tiles of {tiling.edge:.4g} ({points}) would need {format_bytes(need)}, above "
                                f"{plan.task_budget} of {format_bytes(plan.task)}: give a smaller --tile-size, or "
                                f"--memory-limit {_mb(plan.smallest(need))} or more")
    raise GridTooLargeError(f"the memory limit of {format_bytes(plan.limit)} can't hold this job: {plan.parts()}, and "
                            f"{'these' if given else 'the smallest'} tiles (edge {tiling.edge:.4g}, {points}) need "
                            f"{format_bytes(need)}; give --memory-limit {_mb(plan.smallest(need))} or more")


def _tile_points(tiling: _Tiling, sources: dict) -> int:
    """Points of the denser cloud in one tile and its halo, at its mean density in x, y (at most all of them)."""
    return min(max(s.n_rows for s in sources.values()),
               int(math.ceil(_density(sources) * (tiling.edge + 2 * tiling.halo) ** 2)))


def _density(sources: dict) -> float:
    lo = np.min([s.lo for s in sources.values()], axis=0)
    hi = np.max([s.hi for s in sources.values()], axis=0)
    area = max(float(np.prod(hi[:2] - lo[:2])), 1e-12)
    return max(s.n_rows for s in sources.values()) / area


class _Session:
    """Workdir, Dask cluster and bucketed clouds of one tiled run; ``with`` closes them."""

    def __init__(self, clouds: dict, voxel_size, *, sigma_voxels, k, h, truncate, method, tile_size, tile_points,
                 memory_limit, scheduler, workers, workdir, halo: float | None = None):
        check_grid_options(voxel_size=voxel_size, sigma_voxels=sigma_voxels, k=k, h=h, truncate=truncate,
                           memory_limit=memory_limit)
        check_tile_options(tile_size=tile_size, tile_points=tile_points, workers=workers, workdir=workdir,
                           scheduler=scheduler)
        _dask("dask" if scheduler in ("synchronous", "threads") else "dask.distributed")  # before any work
        # "auto": the tiles need the lattice before the points
        voxel_size, sigma_voxels = sampled_lattice(list(clouds.values()), voxel_size=voxel_size or "auto", k=k,
                                                   sigma_voxels=sigma_voxels)
        self.voxel_size, self.sigma_voxels = float(voxel_size), float(sigma_voxels)
        workers = workers or os.cpu_count() or 1
        in_process = scheduler in ("synchronous", "threads")
        self.root = tempfile.mkdtemp(prefix="sdp-tiles-", dir=workdir)
        self.timings: dict[str, float] = {}
        self.executor = self.cluster = None
        try:
            if not (scheduler is None or in_process):  # a cluster of its own: its workers share the limit,
                self.executor, self.cluster = _connect(scheduler, workers)  # one task per thread at once
                workers = max(1, sum(self.executor.nthreads().values()))
            plan = JobBudget(_memory_limit(memory_limit), 1 if scheduler == "synchronous" else workers,
                             separate=not in_process)
            share, budget = plan.task, plan.task_budget
            if tile_points is None:  # what a task's share holds (none: the smallest tiles, refused below)
                tile_points = max(0, share // (2 * _BYTES_PER_TILE_POINT))
            self.sources = {e: _source(c, self.root, e) for e, c in clouds.items()}
            lo = np.min([src.lo for src in self.sources.values()], axis=0)
            hi = np.max([src.hi for src in self.sources.values()], axis=0)
            # with no share left, the reach alone is checked here and the tiles are refused below
            reach = check_kernel(sigma_voxels, truncate, share if share > 0 else 2**62, budget=budget)
            check_lattice(lo, hi, self.voxel_size, reach)
            self.lo = lo
            self.tiling = _tiling(self.sources, self.voxel_size, tile_size, tile_points, sigma_voxels, truncate, halo)
            _check_tile_points(self.tiling, self.sources, plan, given=tile_size is not None)
            self.opts = dict(voxel_size=self.voxel_size, sigma_voxels=sigma_voxels, k=k, h=h, truncate=truncate,
                             method=method, memory_limit=share)
            chunk_rows = int(min(2_000_000, max(10_000, share // (4 * _BYTES_PER_ROW_READ))))
            _check_tile_directory(self.tiling, lo, hi, reach, share, budget)
            for e in self.sources:
                Path(self.root, e).mkdir()
            if self.executor is None:
                self.executor, self.cluster = _connect(scheduler, workers)
            jobs = [(src, e, s, s + _PART_ROWS, i, self.tiling, self.root, chunk_rows)
                    for e, src in self.sources.items() for i, s in enumerate(range(0, src.n_rows, _PART_ROWS))]
            done = self.tasks("bucket", _bucket_part, jobs, (), unit="slice")
        except BaseException:
            self.__exit__()
            raise
        self.budget = plan
        self.timings["read"] = sum(d[2] for d in done)
        self.dropped = {e: sum(d[1] for d, j in zip(done, jobs, strict=True) if j[1] == e) for e in self.sources}
        self.tiles = sorted({key for d in done for key in d[0]})

    def tasks(self, step: str, func, jobs: list, summed: tuple, unit: str = "tile") -> list:
        """Run the jobs; time the step (wall) and sum the tasks' own timings named ``summed``;
        the progress bar counts ``unit`` (a tile, a slice of a file)."""
        t = time.perf_counter()
        results = _run(self.executor, func, jobs, {"bucket": "reading and tiling"}.get(step, f"{step} tiles"), unit)
        self.timings[step] = time.perf_counter() - t
        for name in summed:
            self.timings[name] = self.timings.get(name, 0.0) + sum(r[name] for r in results)
        return results

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        """Close the client and the local cluster, and remove the work folder whatever happens
        (an error, Ctrl-C, SIGTERM turned into an exception by ``sdp``'s ``main``)."""
        try:
            if getattr(self, "executor", None) is not None and not isinstance(self.executor, str):
                self.executor.close()
        finally:
            try:
                if getattr(self, "cluster", None) is not None:
                    self.cluster.close()  # stops the workers: nothing writes into the buckets any more
            finally:
                shutil.rmtree(self.root, ignore_errors=True)


def sampled_lattice(clouds: list, *, voxel_size: float | str = DEFAULTS.voxel_size, k: float = DEFAULTS.k,
                    sigma_voxels: float | str = DEFAULTS.sigma_voxels) -> tuple[float, float]:
    """(voxel, σ in voxels) as :func:`sdp.fields._spacing.resolve_lattice`, ``"auto"`` measured on the
    first slice of each cloud (a path, :class:`~sdp.io.PointSource` or array): clouds too large
    to read whole."""
    from ..fields._spacing import resolve_lattice

    if not isinstance(voxel_size, str):
        return resolve_lattice([], voxel_size=voxel_size, sigma_voxels=sigma_voxels)
    return resolve_lattice(first_slices(clouds), voxel_size=voxel_size, k=k, sigma_voxels=sigma_voxels)


def first_slices(clouds: list) -> list:
    """The first slice of each cloud (a path, :class:`~sdp.io.PointSource` or array), validated:
    what the tiles measure spacing and scales on before they read the points."""
    from .._core._points import as_points

    firsts = []
    for c in clouds:
        if isinstance(c, (str, os.PathLike)):
            c = PointSource.open(c)
        firsts.append(as_points(next(c.chunks())[1] if isinstance(c, PointSource) else c))
    return firsts


def _source(s, root: str, epoch: str) -> PointSource:
    if isinstance(s, PointSource):
        return s
    if isinstance(s, (str, os.PathLike)):
        return PointSource.open(s, spill_dir=root)
    xyz = np.asarray(s, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InvalidPointsError(f"{epoch} points must be an (n, 3) array, got shape {xyz.shape}")
    path = Path(root, f"{epoch}.npy")
    np.save(path, xyz)
    return PointSource.open(path)


def _tiling(sources: dict, voxel_size: float, tile_size: float | None, tile_points: int, sigma_voxels: float,
            truncate: float, halo: float | None = None) -> _Tiling:
    if halo is None:
        halo = (math.ceil(truncate * sigma_voxels) + 3) * voxel_size  # kernel reach + binning + interpolation + margin
    cell = BLOCK * voxel_size
    if tile_size is None:  # tile_points in the tile and its halo at the mean density: whole blocks, rounded down
        blocks = math.floor((math.sqrt(tile_points / max(_density(sources), 1e-12)) - 2 * halo) / cell)
    else:
        blocks = math.ceil(tile_size / cell)
    blocks = max(1, blocks, math.ceil(2 * halo / cell))
    return _Tiling(voxel_size, blocks, halo)


def _check_tile_directory(tiling: _Tiling, lo, hi, reach: int, share: int, budget: str) -> None:
    """Refuse, before any task runs, tiles whose block directory alone exceeds a task's share of
    the memory limit (a voxel far below the point spacing: 1e-9 for metres)."""
    span = (tiling.edge + 2 * tiling.halo) / tiling.voxel_size + 2 * reach + 2 * BLOCK
    z = (float(hi[2]) - float(lo[2])) / tiling.voxel_size + 2 * reach + 2 * BLOCK
    check_memory((span / BLOCK) ** 2 * (z / BLOCK) * 5, f"the block directory of one tile (voxel "
                 f"{tiling.voxel_size:g}, tile edge {tiling.edge:.4g})", share, budget=budget)


#: Seconds to wait for a ``dask.distributed`` scheduler to answer.
CONNECT_TIMEOUT = 10


#: Run in each local worker process as it starts (a Dask preload): Ctrl-C in a terminal reaches the
#: whole process group, and the client, not each worker, ends the run (a worker would print a
#: KeyboardInterrupt traceback); the client closes the cluster on its way out.
_WORKER_PRELOAD = """
import signal, threading
if threading.current_thread() is threading.main_thread():
    signal.signal(signal.SIGINT, signal.SIG_IGN)
"""


def _dask(module: str):
    """``dask`` or ``dask.distributed`` (the ``tiles`` extra), or a one-line :class:`~sdp.MissingDependencyError`."""
    return require(module, "tiles", "the tiled path (Dask)")


def _connect(scheduler: str | None, workers: int):
    """(executor, cluster): a distributed ``Client`` (and the local cluster it drives), or the
    name of a Dask local scheduler."""
    if scheduler in ("synchronous", "threads"):
        return scheduler, None
    distributed = _dask("dask.distributed")
    Client, LocalCluster = distributed.Client, distributed.LocalCluster

    if scheduler is None:  # the tasks bound their own memory (``share``): no pausing by distributed
        with _sigint_deferred() as interrupted:  # a cluster half started can't be closed
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, memory_limit=0,
                                   dashboard_address=":0", env={"NUMBA_NUM_THREADS": "1"},  # a core per worker
                                   silence_logs=logging.ERROR,  # no warnings about tasks cancelled on Ctrl-C
                                   preload=[_WORKER_PRELOAD])
            try:
                client = Client(cluster)
            except BaseException:
                cluster.close()
                raise
        if interrupted():
            client.close()
            cluster.close()
            raise KeyboardInterrupt
        return client, cluster
    try:
        return Client(scheduler, timeout=CONNECT_TIMEOUT), None
    except (OSError, TimeoutError, ValueError) as exc:  # refused, unreachable, or not an address
        reason = str(exc).splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise SDPError(f"can't reach the Dask scheduler at {scheduler} within {CONNECT_TIMEOUT} s ({reason}); "
                       "start it (dask scheduler) or check the address") from None


@contextmanager
def _sigint_deferred():
    """Hold Ctrl-C back in the block (main thread only), and tell afterwards whether it came."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: False
        return
    hits = []
    previous = signal.signal(signal.SIGINT, lambda *_: hits.append(True))
    try:
        yield lambda: bool(hits)
    finally:
        signal.signal(signal.SIGINT, previous)


#: Retries of a task that raised (a shared file system's passing error); a task whose worker died
#: is rescheduled by Dask itself, up to its scheduler's ``allowed-failures``.
TASK_RETRIES = 1


def _run(executor, func, jobs: list, what: str, unit: str = "tile") -> list:
    """func(*job) for every job, in order, on a distributed ``Client`` or a local Dask scheduler (its name).

    The first task that fails for good stops the run: the others are cancelled and its error
    is raised (a worker lost more often than the scheduler allows: :class:`WorkerLostError`).
    """
    if not jobs:
        return []
    if isinstance(executor, str):
        dask = _dask("dask")

        return list(dask.compute(*[dask.delayed(func, pure=False)(*job) for job in jobs], scheduler=executor))
    distributed = _dask("dask.distributed")

    futures = executor.map(func, *zip(*jobs, strict=True), pure=False, retries=TASK_RETRIES)
    try:
        with bar(len(futures), what, unit=unit) as pb:
            for future in distributed.as_completed(futures):
                if future.status == "error":
                    future.result()  # raises the task's error: no waiting for the other tasks
                pb.update(1)
        return executor.gather(futures)
    except distributed.KilledWorker as exc:
        worker = getattr(exc.args[1], "address", "?") if len(exc.args) > 1 else "?"
        tries = exc.args[2] + 1 if len(exc.args) > 2 else 1
        raise WorkerLostError(f"{what}: the Dask workers running one task died {tries} time(s) (the last: {worker}); "
                              "the run was stopped: check the workers' memory and logs") from None
    finally:
        executor.cancel([f for f in futures if not f.done()])
