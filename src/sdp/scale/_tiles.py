"""Change detection in tiles: clouds larger than memory, in parallel on Dask.

The data path of :func:`sdp.detect_changes`, cut into square columns of the global lattice:

1. **bucket** (one Dask task per slice of each file): read the rows (LAS/LAZ chunks, NPY and
   PLY slices; :class:`sdp.io.PointSource`), and append each point, with its row number, to the
   bucket of its tile and of every tile whose *halo* it lies in (on disk, in ``workdir``);
2. **compare** (one task per tile): build the two fields from the tile's buckets, form the
   difference volumes and flag the tile's own points, as :func:`sdp.detect_changes` does, and
   label the tile's own change regions (:func:`sdp.change._regions.label_part`); return the changed rows
   and the labels of the tile's face nodes;
3. **regions** (here): join the tiles' labels across their faces (:func:`sdp.change._regions.join_parts`);
4. with ``decision="combined"``, **combine** (one task per tile): mark the tile's own points by
   their distance to the other epoch (the level fitted here on every tile's calibration sample,
   which the compare tasks return), then join the components of the changed cells here.

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

**Memory** (:class:`sdp.scale._budget.JobBudget`): the memory limit is the whole job's. The command takes a fixed
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
dense grids over the box (:func:`sdp.scale._budget.dense_grid_bytes`), or the points in memory (the process and
≈ 200 bytes per point: :func:`sdp.scale._budget.untiled_point_bytes`), would exceed the memory limit.

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

import os
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .._core._validate import auto_or_nonnegative, direction, integer_at_least
from ..change._combined import joined_by_regions
from ..change._coverage import footprint_covered
from ..change._detect import ChangeResult, PointChanges
from ..change._regions import Volume, describe_regions, join_parts, label_part
from ..defaults import DEFAULTS
from ..errors import InvalidOptionError
from ..fields._density import DensityField, threshold
from ..fields._lattice import BLOCK
from ..options import Cylinder, Execution, Lattice, NoiseModel, as_options
from ._budget import BYTES_PER_TILE_POINT
from ._session import Session, Tiling, first_slices, load_bucket
from ._store import FieldStore, require_zarr

__all__ = ["detect_changes_tiled", "distances_tiled", "build_field_tiled"]


def _empty_field(like: DensityField) -> DensityField:
    """A field with no point (G = 0 everywhere) on ``like``'s lattice."""
    return DensityField(like.grid, np.zeros((0, 3), np.int64), np.zeros((0, BLOCK**3), np.float32), h=like.h,
                        sigma=like.sigma, truncate=like.truncate)


class _Side(NamedTuple):
    """One direction of a tile (:func:`_tile_changes`): this epoch's field, its own points and
    their rows, which of them the density changed, the indices of those not comparable, the
    difference volume, the other epoch's records in the tile, this epoch's records in the tile
    (its halo's too) and which of them are its own."""

    field: DensityField
    points: np.ndarray
    rows: np.ndarray
    changed: np.ndarray
    unseen: np.ndarray
    volume: Volume
    other: np.ndarray
    records: np.ndarray
    own: np.ndarray


def _tile_changes(key, root: str, tiling: Tiling, opts: dict, store: str | None, every: bool, out: dict):
    """Fields of both epochs in one tile and, per direction, its own points' density decision
    (footprint coverage): ``{kind: _Side}``, a direction without points of its own left out
    unless ``every`` (the regions need the halo's part of a difference volume). Times go to
    ``out``."""
    t0 = time.perf_counter()
    recs = {e: load_bucket(root, e, key) for e in ("reference", "current")}
    out["read"] = out.get("read", 0.0) + time.perf_counter() - t0
    fields = {}
    for e, rec in recs.items():
        t = time.perf_counter()
        if e == "reference" and store is not None:
            # the stored blocks of this run's tile and one block around it (the run's tiles need not be
            # the store's: its memory budget may cut smaller ones), enough to interpolate anywhere in it
            lo = np.asarray(key, np.int64) * tiling.blocks - 1
            fields[e] = FieldStore.open(store).read(lo, lo + tiling.blocks + 2)
        else:
            fields[e] = DensityField.from_points(rec[:, :3], **opts) if len(rec) else None
        out[f"build_{e}"] = out.get(f"build_{e}", 0.0) + time.perf_counter() - t
    t = time.perf_counter()
    found = {}
    for e, other, kind in (("current", "reference", "appeared"), ("reference", "current", "disappeared")):
        fld, rec = fields[e], recs[e]
        own = np.zeros(len(rec), bool) if fld is None else tiling.owns(key, rec)
        if fld is None or len(rec) == 0 or (not own.any() and not every):
            continue  # no points of this epoch here (a stored reference has none): no difference volume
        pts = np.ascontiguousarray(rec[own, :3])
        d = Volume.difference(fld, fields[other] or _empty_field(fld))  # evaluated where needed, never stored
        mask = d.negative_at(fld, pts) if len(pts) else np.zeros(0, bool)
        cand = np.flatnonzero(mask)
        unseen = cand if fields[other] is None else cand[~footprint_covered(pts[cand], fields[other])]
        mask[unseen] = False
        found[kind] = _Side(fld, pts, rec[own, 3].astype(np.int64), mask, unseen, d, recs[other], rec, own)
    out["detect"] = out.get("detect", 0.0) + time.perf_counter() - t
    return found


def _compare_tile(key, root: str, tiling: Tiling, opts: dict, store: str | None, regions: bool = True,
                  cells: tuple | None = None, correlation: float | None = None) -> dict:
    """Fields of both epochs in one tile, its own changed rows and its own not comparable rows
    (outside the other field's footprint; see the module docstring), and with ``regions`` the
    components of the difference volume in the tile (:func:`sdp.change._regions.label_part`: what the
    regions across tiles are joined from). With ``store`` (a :class:`FieldStore` path) the
    reference field is read from it. With ``cells`` (the corners of the combined decision's
    cells), also each direction's calibration sample (``"<kind> sample"``:
    :meth:`sdp.distance._noise.SurfaceDistances.calibration_sample`; ``correlation``: the noise
    model's correlation length)."""
    out = {"read": 0.0, "build_reference": 0.0, "build_current": 0.0, "label": 0.0, "detect": 0.0, "distance": 0.0}
    blocks_lo = np.asarray(key, np.int64) * tiling.blocks
    states = _tile_changes(key, root, tiling, opts, store, regions, out)
    for kind in ("appeared", "disappeared"):
        out[kind] = (np.zeros(0, np.int64), np.zeros((0, 3)), None, np.zeros(0, np.int64))
        out[f"{kind} sample"] = (np.zeros(0),) * 3
        if kind not in states:
            continue
        side = states[kind]
        if cells is not None:
            t1 = time.perf_counter()
            surface = _surface(side, cells, correlation=correlation)
            if surface is not None:
                out[f"{kind} sample"] = surface[0].calibration_sample()
            out["distance"] += time.perf_counter() - t1
        changed = side.changed
        part = None
        if regions:
            t1 = time.perf_counter()
            part = label_part(side.field, side.volume, side.points[changed], blocks_lo,
                              blocks_lo + tiling.blocks)  # the regions span tiles
            out["label"] += time.perf_counter() - t1
        out[kind] = (side.rows[changed], side.points[changed], part, side.rows[side.unseen])
    return out


def _surface(side: _Side, cells: tuple, level: tuple | None = None, correlation: float | None = None):
    """(:class:`sdp.distance._noise.SurfaceDistances` of one direction's points in a tile, the
    stable mask): ``side`` is :func:`_tile_changes`' entry. Its points are all of this epoch's
    in the tile, the halo's too, so that a cell across the tile's edge has the centroid it has
    in memory (a point's distance is read at its cell's); stable are the tile's own points the
    density left unchanged. The cells start at ``cells[0]`` (the clouds' corner, as in memory:
    one cell lattice for every tile). None if nothing is stable or the other epoch has too few
    points here."""
    from ..distance._cells import CellLists
    from ..distance._noise import SurfaceDistances

    unchanged = ~side.changed
    unchanged[side.unseen] = False
    if not unchanged.any() or len(side.other) < 3:
        return None
    stable = np.zeros(len(side.records), bool)
    stable[np.flatnonzero(side.own)[unchanged]] = True
    return SurfaceDistances(np.ascontiguousarray(side.records[:, :3]), np.ascontiguousarray(side.other[:, :3]),
                            sigma=side.field.sigma, stable=stable, lists=CellLists(*cells), level=level,
                            correlation_length=correlation), stable


def _distance_marks(key, root: str, tiling: Tiling, opts: dict, cells: tuple, levels: dict,
                    correlation: float | None = None) -> dict:
    """The combined decision's distance in one tile (:mod:`sdp.change._combined`, rules 2 and 3):
    per direction, the rows and points of its own points that the density left unchanged, that
    lie inside their own cluster volume and whose distance to the other epoch's surface is
    beyond the level of detection at 99.9 % (either side: tiles follow no sensor), the level
    ``levels[kind]`` calibrated on every tile's sample."""
    from ..change._combined import DECISION_FACTOR

    out = {"distance": 0.0}
    states = _tile_changes(key, root, tiling, opts, None, False, out)
    t = time.perf_counter()
    for kind in ("appeared", "disappeared"):
        out[kind] = (np.zeros(0, np.int64), np.zeros((0, 3)))
        surface = _surface(states[kind], cells, levels[kind], correlation) if kind in states else None
        if surface is None:
            continue
        sd, stable = surface
        fld, rec = states[kind].field, states[kind].records
        idx = np.flatnonzero(stable)
        dist, lod = sd.at(idx)
        with np.errstate(invalid="ignore"):
            far = idx[np.abs(dist) > DECISION_FACTOR * lod]
        far = far[fld.inside(rec[far, :3])]  # matter of its own epoch (F < 0), as Algorithm 1 asks of a change
        out[kind] = (rec[far, 3].astype(np.int64), np.ascontiguousarray(rec[far, :3]))
    out["distance"] = time.perf_counter() - t
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
    regs, region_of = describe_regions(xyz, labels, counts * voxel_size**3)
    return rows, region_of, regs


class _Level(NamedTuple):
    """One direction's level of the combined decision in tiles, for the summary: the tiles keep no
    per-point distance (``rows`` None)."""

    calibration: tuple
    noise: NoiseModel
    rows: None = None

    def level(self) -> dict:
        from ..change._detect import level_summary

        return level_summary(self.calibration, self.noise)


def _check_cell_span(lo, hi, cell: float, what: str, advice: str) -> None:
    """Refuse, before any tile is read, cells of ``cell`` placed from the clouds' corner ``lo``
    (so that every tile's cells are memory's) that ``hi`` puts more than 2**21 cells away: the
    cells' keys hold 21 bits per axis (:mod:`sdp._core._cells`)."""
    from .._core._cells import BITS, MAX_INDEX

    span = float(np.max(np.asarray(hi, np.float64) - np.asarray(lo, np.float64)))
    if span / cell >= MAX_INDEX - 4:
        raise InvalidOptionError(f"{what} places cells of {cell:g} from the clouds' corner, and the clouds span "
                                 f"{span:g} units, more than 2**{BITS} such cells: {advice}")


#: The halo of the combined decision's tiles, in σ: the other epoch's normals reach 4σ from a
#: cell's centroid (2σ_n, σ_n = 2σ), the centroid lies up to a cell (1.5σ) from the point, and the
#: cells read around them add up to a cell on each side.
_COMBINED_HALO = 9.0


def _combined_regions(density, marked, found, cells: tuple, cell: float, regions: bool):
    """Rows, region labels and regions of one kind of change under the combined decision
    (:func:`sdp.change._combined.combine_decision`'s rule 4) from the tiles' pieces: ``density``
    (rows, points) the density changed (comparable), ``marked`` (rows, points) the distance
    changed, ``found`` (rows, region labels) of the density's own regions. The 26-connected
    components of the cells of ``cell`` (from ``cells[0]``, the clouds' corner; ``cells[1]`` their
    far corner) holding a changed point, found as in memory (:func:`sdp.distance._noise._components`),
    are kept where they hold a found row, those holding one density region joined
    (:func:`sdp.change._combined.joined_by_regions`)."""
    from ..distance._cells import CellLists
    from ..distance._noise import _components

    rows = np.concatenate([p[0] for p in density] + [p[0] for p in marked])
    xyz = np.concatenate([p[1] for p in density] + [p[1] for p in marked]).reshape(-1, 3)
    order = np.argsort(rows, kind="stable")
    rows, xyz = rows[order], np.ascontiguousarray(xyz[order])
    found_rows, found_regions = found
    if len(rows) == 0 or len(found_rows) == 0:
        return rows[:0], np.zeros(0, np.int64), []
    ordered, starts, table, dims, _, by_cell = CellLists(*cells).get(xyz, cell)
    n_cells = len(starts) - 1
    index = np.floor((ordered[starts[:-1]] - cells[0]) / cell).astype(np.int64)  # as the table's keys
    component = _components(table, dims, index, np.ones(n_cells, bool))[0]
    of_point = np.empty(len(rows), np.int64)
    of_point[by_cell] = np.repeat(np.arange(n_cells), np.diff(starts))
    at = np.searchsorted(rows, found_rows)  # every found row is a density row
    kept, found_components = np.unique(component[of_point[at]], return_inverse=True)
    joined = joined_by_regions(found_components.ravel(), found_regions, len(kept))
    of_kept = np.full(component.max() + 1, -1, np.int64)
    of_kept[kept] = joined
    labels = of_kept[component[of_point]]
    keep = labels >= 0
    rows, xyz, labels = rows[keep], xyz[keep], labels[keep]
    if not regions:
        return rows, np.zeros(len(rows), np.int64), []
    of_cell = of_kept[component]
    cells_of = np.bincount(of_cell[of_cell >= 0], minlength=joined.max() + 1)  # a region's volume, as in memory
    regs, region_of = describe_regions(xyz, labels, cells_of * cell**3)
    return rows, region_of, regs


def detect_changes_tiled(reference, current, *, lattice: Lattice | None = None, decision: str = DEFAULTS.decision,
                         min_region_points: int = DEFAULTS.min_region_points, regions: bool = True,
                         execution: Execution | None = None, noise: NoiseModel | None = None) -> ChangeResult:
    """:func:`sdp.detect_changes` (footprint coverage) in tiles, for clouds of any size.

    Every default is :data:`sdp.DEFAULTS`, as for :func:`sdp.detect_changes`. Points outside the
    other epoch's footprint (:func:`sdp.change._coverage.footprint_covered`) are not comparable; the
    tiles follow no sensor rays.

    ``decision="combined"`` (:mod:`sdp.change._combined`) takes a second pass over the tiles: each
    marks its own points that the density left unchanged whose distance to the other epoch's
    surface lies beyond the level of detection at 99.9 % (either side of it: no sensor tells the
    front), inside their own cluster volume; here the components of the changed cells of 1.5σ
    are joined across the tiles and kept where they hold a point of the density's own regions,
    as in memory. One level per direction is fitted on every tile's calibration sample together
    (:func:`sdp.distance._noise.fit_level`; one tile holding the whole scene gives the in-memory
    sample, so memory's states; several tiles, a larger sample of the same scene), and the
    tiles' halo grows to 9σ, the reach of the other epoch's normals and cylinders. The result
    holds no per-point distance: ``sdp change`` writes none in tiles.

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
    decision : {"point", "density", "combined"}
        As in :func:`sdp.detect_changes` (``"cluster"`` is refused: memory only); ``"combined"``
        as above, refused with a stored reference (no points to measure distances to).
    min_region_points, regions, noise
        As in :func:`sdp.detect_changes`; regions span tiles. No sensor: the level does not
        grow with range.
    execution : Execution, optional
        The tiles (:class:`sdp.Execution`): ``tile_size`` in world units (rounded up to whole
        blocks of 8 voxels; default about ``tile_points`` points of the larger cloud per tile,
        from its mean density in x, y; default ``tile_points``: what one task's share of the
        memory limit holds, ≈ 1.2 KB per point and epoch, 230 k points with 2 GiB and 2
        workers). ``memory_limit`` is the whole job's, shared as :class:`sdp.scale._budget.JobBudget` says: this
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
    min_region_points = integer_at_least("min_region_points", min_region_points, 0)
    if decision not in ("point", "density", "combined"):
        raise InvalidOptionError(f"decision={decision!r} is not available in tiles: 'point' or 'combined'")
    noise = NoiseModel.of(noise, decision)
    combined = decision == "combined"
    if combined and isinstance(reference, FieldStore):
        raise InvalidOptionError("decision='combined' measures distances to the reference's points: a field store "
                                 "has none")
    k, h = lattice.k, lattice.h
    voxel_size, sigma_voxels, truncate = lattice.voxel_size, lattice.sigma_voxels, lattice.truncate
    tiles = execution.tile_keywords()
    store = reference if isinstance(reference, FieldStore) else None
    if store is not None:
        voxel_size, truncate, h = store.voxel_size, store.truncate, store.h
        sigma_voxels = store.sigma / store.voxel_size
        tiles["tile_size"] = store.tile_blocks * BLOCK * store.voxel_size
    clouds = {"current": current} if store is not None else {"reference": reference, "current": current}
    # the combined decision's tasks also hold each epoch's distances: 160 B per point
    # (sdp.distance._noise.distance_bytes)
    extra = dict(halo_sigmas=_COMBINED_HALO, point_bytes=2 * BYTES_PER_TILE_POINT + 2 * 160) if combined else {}
    with Session(clouds, voxel_size, sigma_voxels=sigma_voxels, k=k, h=h, truncate=truncate, method=lattice.method,
                  **tiles, **extra) as run:
        # the combined decision's cells of 1.5σ from the clouds' corner, as pair_cells places them in memory
        cells = (run.lo - 1e-9, run.hi) if combined else None
        if combined:
            _check_cell_span(*cells, 1.5 * run.sigma_voxels * run.voxel_size, "decision='combined' in tiles",
                             "use decision='point' (tiles have no such limit), or a larger voxel")
        jobs = [(key, run.root, run.tiling, run.opts, store and str(store.path), regions or combined, cells,
                 noise.correlation_length) for key in run.tiles]
        steps = ("read", "build_reference", "build_current", "detect") + (("distance",) if combined else ())
        results = run.tasks("compare", _compare_tile, jobs, steps + ("label",))
        t = time.perf_counter()
        out = {kind: _regions([r[kind] for r in results], run.voxel_size, min_region_points, regions or combined)
               for kind in ("appeared", "disappeared")}
        unseen = {kind: np.sort(np.concatenate([r[kind][3] for r in results])) for kind in ("appeared", "disappeared")}
        run.timings["regions"] = time.perf_counter() - t
        if combined:
            from ..distance._noise import CELL, fit_level, thinned

            # one level per direction, from every tile's sample in tile order (one tile: the in-memory sample)
            levels = {kind: fit_level(*(thinned(np.concatenate([r[f"{kind} sample"][a] for r in results]))
                                        for a in range(3)), registration_error=noise.registration_error,
                                      range_exponent=noise.range_exponent)
                      for kind in ("appeared", "disappeared")}
            marks = run.tasks("combine", _distance_marks,
                              [(key, run.root, run.tiling, run.opts, cells, levels, noise.correlation_length)
                               for key in run.tiles], steps)
            t = time.perf_counter()
            sigma = run.sigma_voxels * run.voxel_size
            out = {kind: _combined_regions([r[kind][:2] for r in results], [m[kind] for m in marks], out[kind][:2],
                                           cells, CELL * sigma, regions)
                   for kind in ("appeared", "disappeared")}
            run.timings["regions"] += time.perf_counter() - t
    levels = (_Level(levels["disappeared"], noise), _Level(levels["appeared"], noise)) if combined else (None, None)
    n_ref = run.sources["reference"].n_rows if store is None else store.n_points
    # rows holding NaN or Inf: nothing measured them, not comparable as in memory
    unseen = {kind: np.union1d(unseen[kind], run.dropped_rows.get(name, np.zeros(0, np.int64)))
              for kind, name in (("appeared", "current"), ("disappeared", "reference"))}
    points = {kind: PointChanges.of_rows(n, *out[kind][:2], unseen[kind],
                                         blank=len(run.dropped_rows.get(name, ())))
              for kind, n, name in (("appeared", run.sources["current"].n_rows, "current"),
                                    ("disappeared", n_ref, "reference"))}
    return ChangeResult(_reference=points["disappeared"], _current=points["appeared"],
                        appeared_regions=out["appeared"][2], disappeared_regions=out["disappeared"][2],
                        voxel_size=run.voxel_size, sigma=run.sigma_voxels * run.voxel_size,
                        h=threshold(k) if h is None else float(h), decision="combined" if combined else "point",
                        tiled=True,
                        n_dropped_reference=run.dropped.get("reference", 0), n_dropped_current=run.dropped["current"],
                        # a stored reference has no points to find disappeared: not measured, not none
                        coverage={"appeared": "footprint",
                                  "disappeared": "footprint" if store is None else "not measured"},
                        n_tiles=len(run.tiles),
                        tile_size=run.tiling.edge, timings=run.timings, _distances=levels)


def distances_tiled(reference, current, *, cylinder: Cylinder | None = None,
                    registration_error: float | str = DEFAULTS.registration_error, orientation=None,
                    execution: Execution | None = None):
    """:func:`sdp.distances` in tiles, for clouds of any size: every reference row a core point.

    Each tile measures its own reference points from its buckets, which hold every point within
    a halo of the longest search (``max_distance`` + the cylinder and normal reach + two cells);
    the cells start at the reference's corner, as in memory, so with the same scales each distance equals
    :func:`sdp.distances`' (tested). ``"auto"`` scales come from the first slice of each cloud
    (the tiles need them before the points), measured as in memory (:func:`sdp.distance._distances.auto_scales`):
    where that slice is the whole cloud, the same scales; normals point along ``orientation`` (+z: the tiles
    follow no sensor); an ``"auto"`` registration error is measured over the whole cloud once the
    tiles are in. Parameters as in :func:`sdp.distances` and :func:`detect_changes_tiled`.

    Returns
    -------
    Distances
        One row per reference row, in row order (rows that held NaN/Inf: NaN, not comparable).
    """
    from ..distance._distances import Distances, auto_scales, search_reach, tile_halo
    from ..distance._level import with_level

    cylinder = as_options(Cylinder, cylinder, "cylinder")
    execution = as_options(Execution, execution, "execution")
    reg_opt = auto_or_nonnegative("registration_error", registration_error)
    reg = 0.0 if reg_opt == "auto" else reg_opt
    towards = direction("orientation", DEFAULTS.orientation if orientation is None else orientation)  # before any work
    t0 = time.perf_counter()
    d, D = cylinder.projection_scale, cylinder.normal_scale
    if d == "auto" or D == "auto":  # from the first slice of each cloud, as the tiled change detection
        d, D = auto_scales(*first_slices([reference, current]), cylinder=cylinder)
    sigma_p = d / 4.0
    reach = search_reach(cylinder.max_distance, d)
    halo, margin = tile_halo(d, D, reach)
    with Session({"reference": reference, "current": current}, sigma_p / 2.0, sigma_voxels=2.0, k=DEFAULTS.k,
                  h=None, truncate=DEFAULTS.truncate, method=DEFAULTS.method, halo=halo,
                  **execution.tile_keywords()) as run:
        corner = np.asarray(run.sources["reference"].lo) - 1e-9
        _check_cell_span(corner, run.hi, min(1.5 * sigma_p, D / 4.0), "distances in tiles",
                         "give a larger projection scale, or measure parts of the clouds apart")
        opts = dict(cylinder=Cylinder(projection_scale=d, normal_scale=D, max_distance=reach),
                    registration_error=reg, orientation=orientation, corner=corner,
                    margin=margin,
                    memory_limit=run.opts["memory_limit"])
        results = run.tasks("distances", _distance_tile, [(key, run.root, run.tiling, opts) for key in run.tiles],
                            ())
    n = run.sources["reference"].n_rows
    xyz, packed = np.full((n, 3), np.nan), np.full((n, 12), np.nan)
    for rows, pts, values in results:
        xyz[rows], packed[rows] = pts, values
    level = np.where(np.isnan(packed[:, 10]), -1, packed[:, 10]).astype(np.int8)
    timings = dict(run.timings, total=time.perf_counter() - t0)
    measured = Distances(core_points=xyz, distance=packed[:, 0], lod=packed[:, 1], significant=packed[:, 2] == 1,
                         n1=packed[:, 3], n2=packed[:, 4], spread1=packed[:, 5], spread2=packed[:, 6],
                         normal=np.ascontiguousarray(packed[:, 7:10]), level=level, projection_scale=d,
                         normal_scale=D, max_distance=max(reach, 3.0 * sigma_p), registration_error=reg,
                         orientation="towards ({:g}, {:g}, {:g})".format(*towards),
                         timings=timings, tiles=len(run.tiles), off_axis=packed[:, 11] == 1)
    return with_level(measured, reg_opt)


def _distance_tile(key, root: str, tiling: Tiling, opts: dict):
    """The distances of tile ``key``'s own reference rows: (rows, xyz, (m, 12) values: the fields, the
    level, off the axis)."""
    from ..distance._distances import distances

    opts = dict(opts)
    margin = opts.pop("margin")
    ref, cur = load_bucket(root, "reference", key), load_bucket(root, "current", key)
    own = tiling.owns(key, ref)
    if not own.any():
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 12))
    values = np.full((int(own.sum()), 12), np.nan)
    if len(cur) >= 3 and len(ref) >= 3:
        near = tiling.owns(key, ref, margin)
        d = distances(ref[:, :3], cur[:, :3], core_points=ref[near, :3], sensor_origin=None, **opts)
        mine = own[near]
        f = d.fields()
        cols = [f[name] for name in ("distance", "lod", "significant", "n1", "n2", "spread1", "spread2",
                                     "normal_x", "normal_y", "normal_z")]
        values = np.column_stack([*cols, d.level, d.off_axis])[mine].astype(np.float64)
        values[values[:, 10] < 0, 10] = np.nan
    return ref[own, 3].astype(np.int64), np.ascontiguousarray(ref[own, :3]), values


def build_field_tiled(cloud, path: str | os.PathLike, *, lattice: Lattice | None = None,
                      execution: Execution | None = None) -> FieldStore:
    """The density field of a cloud of any size, built tile by tile into a :class:`FieldStore`.

    Same parameters as :func:`detect_changes_tiled` (one cloud); ``path`` is the store to
    write (a folder, conventionally ``*.zarr``), written under a temporary name and renamed into
    place when complete (:meth:`FieldStore.commit`): a run that fails or is stopped leaves what was
    at ``path``. Each tile's blocks equal those of :meth:`DensityField.from_points` on the whole cloud.
    """
    lattice, execution = _tiled_options(lattice, execution)
    require_zarr()  # before any work
    k, h, truncate = lattice.k, lattice.h, lattice.truncate
    with Session({"cloud": cloud}, lattice.voxel_size, sigma_voxels=lattice.sigma_voxels, k=k, h=h,
                  truncate=truncate, method=lattice.method, **execution.tile_keywords()) as run:
        store = FieldStore.create(path, voxel_size=run.voxel_size, sigma=run.sigma_voxels * run.voxel_size,
                                  truncate=truncate, h=threshold(k) if h is None else float(h),
                                  tile_blocks=run.tiling.blocks,
                                  inputs=(cloud,) if isinstance(cloud, (str, Path)) else ())
        try:
            jobs = [(key, run.root, run.tiling, run.opts, str(store.path)) for key in run.tiles]
            counts = run.tasks("build", _build_tile, jobs, ())
            store.set_counts(sum(counts), run.dropped["cloud"])
        except BaseException:  # no half-built store left behind (a failed tile, Ctrl-C, SIGTERM), the old one kept
            store.discard()
            raise
        return store.commit()  # only now is a store already at ``path`` replaced


def _tiled_options(lattice: Lattice | None, execution: Execution | None) -> tuple[Lattice, Execution]:
    """The options of a tiled function, with their defaults; a ``grid_size`` refused (the tiles need
    the voxel before they read the points)."""
    lattice = as_options(Lattice, lattice, "lattice")
    if lattice.grid_size is not None:
        raise InvalidOptionError("grid_size is not available in tiles: give a voxel size or 'auto'")
    return lattice, as_options(Execution, execution, "execution")


def _build_tile(key, root: str, tiling: Tiling, opts: dict, store: str) -> int:
    """Build tile ``key``'s field from its bucket and store its own blocks; returns its own points."""
    rec = load_bucket(root, "cloud", key)
    FieldStore._open(store).write_tile(key, DensityField.from_points(rec[:, :3], **opts))  # not committed yet
    return int(tiling.owns(key, rec).sum())

