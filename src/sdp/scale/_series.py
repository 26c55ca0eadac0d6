"""A series in tiles on Dask: the reference prepared and every epoch measured tile by tile.

:func:`sdp.series` measures each epoch against a :class:`sdp.distance.PreparedReference`. When an
epoch or the reference would not fit the memory limit (or with ``Execution(tiled=True)``), the
same numbers are made in tiles, on the buckets and Dask cluster of one
:class:`sdp.scale._session.Session` kept for the whole run (the cluster starts once, not once
per epoch):

1. **prepare** (one task per tile): the tile's own core points (given core points: those the
   tile owns; default: the reference subsampled per tile by :func:`sdp.distance._reference.subsample`
   with the whole reference's origin), with those within two cells of the tile so that the
   cells whose core points share a normal are whole, prepared against the tile's reference
   points and halo (:func:`sdp.distance._distances.tile_halo`) with the whole reference's cell
   corner; assembled in core-point order into one :class:`PreparedReference`, whose state is
   what the archive stores (an append then works unchanged);
2. **each epoch**: bucketed on the session's tiling, then one task per tile holding core points
   measures the tile's bucket at its core points (:meth:`PreparedReference.measure` on the
   tile's points and halo, the cells starting where the whole epoch's would); the rows are
   assembled in order. The epoch's buckets are removed before the next one.

Every cube of the default subsample, every cell of core points sharing a normal and every
cylinder and search along a normal that a tile's own core points read lie inside its halo, and
the buckets keep the rows' order, so the sums run in the same order as in memory: each value
equals the in-memory one bit for bit (tested), given the same scales. ``"auto"`` scales are
measured on the reference's first slice (2 M rows: the whole of a smaller reference, whose
scales then equal the in-memory ones; a larger one's may differ slightly from the scales the
in-memory run would measure on all its points); the archive records the scales used.

Cost: the Dask cluster starts once per run (a local one of two workers: about 1 s to start and
0.3 s to close here); each epoch is read and written to the buckets once (its points with their
halo), then read by its tiles. Tiles are sized for what a series task holds (about 500 bytes per
point of one cloud with its halo, :data:`_TILE_POINT_BYTES`); the halo grows with the search along
the normal (``max_distance``, twelve projection scales by default). Five epochs of 2 M points:
1.1× the in-memory time per epoch, 982 MB for all the processes (docs/benchmarks.md §13).
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from .._core._memory import check_memory, format_bytes
from .._core._memory import memory_limit as resolve_memory_limit
from .._core._points import as_points
from .._core._validate import direction
from ..defaults import DEFAULTS
from ..distance._cells import CELL, CellLists, bounds, cell_moments
from ..distance._distances import Distances, normal_sigma, search_reach, tile_halo
from ..distance._level import with_level
from ..distance._reference import PreparedReference, subsample
from ..errors import InvalidOptionError, SDPError
from ..fields._lattice import BLOCK
from ..io._cloud import Cloud, input_format
from ..io._ply import ply_is_binary
from ..io._read import header_point_count
from ..io._source import PointSource
from ..options import Cylinder, Execution
from ._budget import PROCESS_BYTES
from ._session import Session, Tiling, first_slices, load_bucket

__all__ = ["TiledSeries", "plan_series", "count_points", "POINT_BYTES", "CORE_BYTES", "PREPARE_CORE_BYTES"]

#: The values a measuring task returns per core point (as :func:`sdp.distances_tiled` packs them).
_PACKED = ("distance", "lod", "significant", "n1", "n2", "spread1", "spread2", "normal_x", "normal_y", "normal_z",
           "level", "off_axis")
_STATE = ("normal", "ref_mean", "ref_spread", "ref_count", "ref_level", "ref_across", "ref_across_var")


def _open(epoch, fmt: str | None):
    """A file as a :class:`PointSource` (LAS/LAZ, NPY, binary PLY: read in slices), an array as float64."""
    if isinstance(epoch, (str, os.PathLike)):
        try:
            return PointSource.open(epoch, format=fmt)
        except SDPError as exc:
            if "slices" in str(exc):
                raise SDPError(f"{epoch}: a series in tiles reads LAS/LAZ, NPY or binary PLY files in slices; "
                               "convert the epochs first") from None
            raise
    xyz = epoch.xyz if isinstance(epoch, Cloud) else epoch
    return np.asarray(xyz, dtype=np.float64)


#: Bytes a task holds per point of its tile and halo, one cloud at a time: the bucket read (64),
#: PreparedReference's sorted copy, cells and moments (200), the subsample's keys, sort and
#: distances (about 130), the core points' share; sizes the tiles (a compare task's is 2,400).
_TILE_POINT_BYTES = 500

#: Bytes the in-memory run needs per point of an epoch (:meth:`PreparedReference.memory_per_epoch`:
#: its sorted copy, cells and moments), and per core point when measuring and when preparing.
POINT_BYTES, CORE_BYTES, PREPARE_CORE_BYTES = 200.0, 160.0, 240.0


def count_points(epoch, fmt: str | None) -> int | None:
    """Points of an epoch without reading them (a LAS header, an NPY or binary PLY map), None for
    files that can't be read in slices (or can't be read: the in-memory run says why)."""
    if not isinstance(epoch, (str, os.PathLike)):
        return len(epoch.xyz if isinstance(epoch, Cloud) else epoch)
    try:
        kind = input_format(Path(epoch), fmt)
        if kind == "npy" and np.load(epoch, mmap_mode="r", allow_pickle=False).ndim != 2:
            return None  # a structured array: read whole
        if kind in ("las", "npy") or (kind == "ply" and ply_is_binary(epoch)):  # headers alone (PointSource.open
            return header_point_count(epoch, format=fmt)  # also decodes a LAZ point: 25 ms)
    except Exception:  # unreadable here: the in-memory run reads it, or says why it can't
        pass
    return None


def plan_series(epochs: list, *, reference: int | None, core_count: int, execution: Execution,
                format: str | None = None, align: bool = False) -> "TiledSeries | None":
    """A :class:`TiledSeries` when the epochs are measured in tiles, else None (in memory).

    Tiles are taken with ``execution.tiled``, or when the in-memory run would refuse an epoch or
    the reference: the process itself (:data:`~sdp.scale._budget.PROCESS_BYTES`) and 200 bytes per
    point of the largest epoch plus 160 per core point, or of the reference plus 240 per core
    point, above the memory limit (``core_count``: the core points
    given, counted without reading them (a file that can't be: none), or the archive's; the
    default core points, a subsample of the reference, are not known before it is read, and count
    as none). Only LAS/LAZ, NPY and binary PLY files (and arrays)
    can be read in slices: other files keep the run in memory (and are refused with
    ``tiled=True``), as does ``align`` (alignment needs each epoch whole: refused in one line
    when tiles are needed).
    """
    limit = resolve_memory_limit(execution.memory_limit)
    if execution.tiled:
        if align:
            raise InvalidOptionError("--align registers whole epochs in memory: not with --tiled (align the epochs "
                                     "first, or run without --tiled)")
        for e in epochs:  # every file readable in slices, before any work
            if count_points(e, format) is None:
                _open(e, format)  # the file's own error, or that it can't be read in slices
        return TiledSeries(execution, format=format)
    sizes = [count_points(e, format) for e in epochs]
    if None in sizes:
        return None  # a file the tiles can't slice: the in-memory run reads it (or says why it can't)
    n_max = max(sizes)
    n_ref = sizes[reference] if reference is not None else 0
    need = PROCESS_BYTES + max(POINT_BYTES * n_max + CORE_BYTES * core_count,  # the limit is the whole job's
                               POINT_BYTES * n_ref + PREPARE_CORE_BYTES * core_count)
    if need <= limit:
        return None
    if align:
        raise InvalidOptionError(f"epochs of up to {n_max:,} points need {format_bytes(need)} in memory, above the "
                                 f"memory limit of {format_bytes(limit)}; --align registers whole epochs in memory: "
                                 "give a larger --memory-limit, or align the epochs first")
    reason = (f"measuring the series in tiles on Dask: epochs of up to {n_max:,} points need {format_bytes(need)} in "
              f"memory, above the memory limit of {format_bytes(limit)}")
    # said by the tiles once taken; a refusal of theirs names the limit that runs in memory
    return TiledSeries(replace(execution, switched=(reason, need)), format=format, reason=reason)


class TiledSeries:
    """One series run's tiles: a :class:`Session` (its buckets and Dask cluster, started by
    :meth:`prepare` or the first :meth:`measure`) kept until :meth:`close` (``with`` closes it)."""

    def __init__(self, execution: Execution, *, format: str | None = None, reason: str | None = None):
        self.execution, self.format, self.reason = execution, format, reason
        self.run: Session | None = None
        self.prepared: PreparedReference | None = None
        self._keys: list | None = None  # tiles holding core points, their state on disk
        self._record: dict | None = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close(*exc)

    def close(self, *exc) -> None:
        """Stop the cluster and remove the buckets (whatever happened); :meth:`record` stays."""
        if self.run is not None:
            self._record = self.record()
        run, self.run = self.run, None
        if run is not None:
            run.__exit__(*(exc or (None, None, None)))

    def _start(self, clouds: dict, projection_scale: float, normal_scale: float, reach: float) -> None:
        halo, self.margin = tile_halo(projection_scale, normal_scale, reach)
        # the voxel only sets the tiles' granularity (blocks of 8 voxels), as sdp.distances_tiled
        self.run = Session(clouds, projection_scale / 8.0, sigma_voxels=2.0, k=DEFAULTS.k, h=None,
                           truncate=DEFAULTS.truncate, method=DEFAULTS.method, halo=halo,
                           point_bytes=_TILE_POINT_BYTES, **self.execution.tile_keywords())

    def record(self) -> dict:
        """What the run record says of the tiles: their number and edge, the reason, the seconds per step."""
        run = self.run
        if run is None and self._record is not None:  # closed
            return self._record
        out = {"tiles": len(self._keys or []), "reason": self.reason or "asked (tiled)"}
        if run is not None:
            out.update(tile_size=run.tiling.edge, budget_per_task=int(run.budget.task),
                       timings={k: round(v, 4) for k, v in run.timings.items()})
        return out

    # ------------------------------------------------------------------ the reference
    def prepare(self, reference, core_points=None, *, cylinder: Cylinder, orientation=None) -> PreparedReference:
        """The reference side at the core points (default: the reference subsampled at the projection
        scale), prepared tile by tile: equal to :meth:`PreparedReference.prepare` on the whole
        reference with the same scales (``"auto"`` ones from the reference's first slice)."""
        ref = _open(reference, self.format)
        core = None if core_points is None else _open(core_points, self.format)
        if isinstance(core, PointSource):
            core = core.read(0, core.n_rows)
        if core is not None:
            core = as_points(core, name="core points").xyz
        d, D, max_half = _scales(ref, core, cylinder, self.execution)
        towards = direction("orientation", DEFAULTS.orientation if orientation is None else orientation)
        clouds = {"reference": ref} if core is None else {"reference": ref, "core": core}
        self._start(clouds, d, D, max_half)
        run = self.run
        lo = np.asarray(run.sources["reference"].lo, np.float64)
        corner = (lo if core is None else np.minimum(lo, core.min(axis=0))) - 1e-9
        opts = dict(cylinder=Cylinder(projection_scale=d, normal_scale=D, max_distance=max_half),
                    orientation=towards, corner=corner, origin=None if core is not None else lo,
                    margin=self.margin, memory_limit=run.opts["memory_limit"])
        results = run.tasks("prepare", _prepare_tile, [(key, run.root, run.tiling, opts) for key in run.tiles], ())
        rows = np.concatenate([r[0] for r in results]) if results else np.zeros(0, np.int64)
        order = np.argsort(rows, kind="stable")
        xyz = np.concatenate([r[1] for r in results])[order] if results else np.zeros((0, 3))
        values = np.concatenate([r[2] for r in results])[order] if results else np.zeros((0, 11))
        if not len(xyz):
            raise SDPError("no core point: the reference and the core points given do not meet")
        self.prepared = PreparedReference(
            core_points=np.ascontiguousarray(xyz), normal=np.ascontiguousarray(values[:, 0:3]),
            ref_mean=np.ascontiguousarray(values[:, 3]), ref_spread=np.ascontiguousarray(values[:, 4]),
            ref_count=np.ascontiguousarray(values[:, 5]), ref_level=values[:, 6].astype(np.int8),
            ref_across=np.ascontiguousarray(values[:, 7:10]), ref_across_var=np.ascontiguousarray(values[:, 10]),
            ref_front=np.full(len(xyz), np.nan),  # tiles follow no sensor: the normals face `towards`
            projection_scale=d, normal_scale=D, max_distance=max_half, corner=corner, orientation=towards)
        return self.prepared

    # ------------------------------------------------------------------ the epochs
    def measure(self, prepared: PreparedReference, epoch, *, registration_error: float | str,
                reference: bool = False) -> tuple[Distances, int]:
        """(distances of ``epoch`` at ``prepared``'s core points, the epoch's points), tile by tile:
        equal to :meth:`PreparedReference.measure` on the whole epoch (an ``"auto"`` registration
        error measured over the whole epoch, once its tiles are in). ``reference``: the epoch is
        the reference :meth:`prepare` bucketed (not read again)."""
        t0 = time.perf_counter()
        if self.run is None:  # an append: the tiles from the first new epoch
            self._start({"epoch": _open(epoch, self.format)}, prepared.projection_scale, prepared.normal_scale,
                        prepared.max_distance)
            name = "epoch"
        elif reference:
            name = "reference"
        else:
            name = "epoch"
            self.run.add(name, _open(epoch, self.format))
        run = self.run
        if self._keys is None:
            self._keys = _write_state(prepared, run.root, run.tiling)
        scalars = prepared.state()[1]
        lo = prepared.epoch_corner(run.sources[name].lo)  # where the whole epoch's cells start
        reg = 0.0 if registration_error == "auto" else float(registration_error)
        jobs = [(key, run.root, name, lo, reg, scalars, run.opts["memory_limit"])
                for key in self._keys]
        results = run.tasks("measure", _measure_tile, jobs, ())
        m = len(prepared.core_points)
        packed = np.full((m, len(_PACKED)), np.nan)
        for rows, values in results:
            packed[rows] = values
        n_points = run.sources[name].n_rows - run.dropped.get(name, 0)
        run.drop(name)
        level = packed[:, 10].astype(np.int8)
        d = Distances(core_points=prepared.core_points, distance=packed[:, 0], lod=packed[:, 1],
                      significant=packed[:, 2] == 1, n1=packed[:, 3], n2=packed[:, 4], spread1=packed[:, 5],
                      spread2=packed[:, 6], normal=np.ascontiguousarray(packed[:, 7:10]), level=level,
                      projection_scale=prepared.projection_scale, normal_scale=prepared.normal_scale,
                      max_distance=max(prepared.max_distance, 3.0 * prepared.projection_scale / 4.0),
                      registration_error=reg,
                      orientation="towards ({:g}, {:g}, {:g})".format(*prepared.orientation),
                      timings={"total": time.perf_counter() - t0}, tiles=len(self._keys), off_axis=packed[:, 11] == 1)
        return with_level(d, registration_error), int(n_points)


def _scales(ref, core, cylinder: Cylinder, execution: Execution) -> tuple[float, float, float]:
    """(d, D, the search's half-length): ``"auto"`` ones as :meth:`PreparedReference.prepare` finds
    them, on the reference's first slice (thinned to fit the memory limit)."""
    from ..fields._spacing import resolve_lattice
    from .._core._validate import auto_or_positive

    d = auto_or_positive("projection_scale", cylinder.projection_scale)
    D = auto_or_positive("normal_scale", cylinder.normal_scale)
    L = auto_or_positive("max_distance", cylinder.max_distance)
    if d == "auto" or D == "auto":
        first = first_slices([ref])[0].xyz
        if d == "auto":  # as sdp.series: the density kernel's σ of the reference
            voxel, sigma_voxels = resolve_lattice([as_points(first)], k=DEFAULTS.k)
            d = 4.0 * sigma_voxels * voxel
        if D == "auto":  # the roughness at the core cells' centroids, as prepare
            sigma_p = d / 4.0
            step = max(1, math.ceil(400.0 * len(first) / max(resolve_memory_limit(execution.memory_limit), 1.0)))
            first = first[::step]
            cores = first[subsample(first, d)] if core is None else core
            lo = np.minimum(first.min(axis=0), cores.min(axis=0)) - 1e-9
            lists = CellLists(lo, np.maximum(first.max(axis=0), cores.max(axis=0)))
            _, starts = lists.order(cores, CELL * sigma_p)
            centroids = np.ascontiguousarray(cell_moments(lists.get(cores, CELL * sigma_p)[0], starts)[:, 1:4])
            D = 4.0 * normal_sigma(lists, first, centroids, sigma_p, "auto")
    return float(d), float(D), search_reach(L, d)


def _prepare_tile(key, root: str, tiling: Tiling, opts: dict):
    """The reference side at tile ``key``'s own core points: (their rows, xyz, (m, 11) values:
    normal, ref_mean, ref_spread, ref_count, ref_level, ref_across, ref_across_var)."""
    opts = dict(opts)
    margin, origin = opts.pop("margin"), opts.pop("origin")
    ref = load_bucket(root, "reference", key)
    if origin is None:  # given core points: the tile's bucket of them
        core = load_bucket(root, "core", key)
    else:  # the reference subsampled: whole cubes (inside the halo) choose as in the whole reference
        core = ref[subsample(ref[:, :3], opts["cylinder"].projection_scale, origin=origin)] if len(ref) else ref
    own = tiling.owns(key, core)
    if not own.any():
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 11))
    values = np.full((int(own.sum()), 11), np.nan)
    values[:, 5], values[:, 6] = 0.0, -1.0  # no reference point near: never comparable, as in memory
    if len(ref) >= 3:
        near = tiling.owns(key, core, margin)  # the cells whose core points share a normal, whole
        p = PreparedReference.prepare(np.ascontiguousarray(ref[:, :3]), np.ascontiguousarray(core[near, :3]), **opts)
        mine = own[near]
        values = np.column_stack([p.normal, p.ref_mean, p.ref_spread, p.ref_count, p.ref_level, p.ref_across,
                                  p.ref_across_var])[mine]
    return core[own, 3].astype(np.int64), np.ascontiguousarray(core[own, :3]), values.astype(np.float64)


def _tile_of(tiling: Tiling, xyz: np.ndarray) -> np.ndarray:
    """(m, 2) keys of the tiles owning ``xyz`` (:meth:`Tiling.owns`' test, so every point has one)."""
    n = tiling.blocks * BLOCK
    keys = np.empty((len(xyz), 2), np.int64)
    for a in range(2):
        u = xyz[:, a] / tiling.voxel_size
        k = np.floor(u / n).astype(np.int64)
        k -= u < k * n  # u / n rounded up to the next tile
        k += u >= (k + 1) * n
        keys[:, a] = k
    return keys


def _write_state(prepared: PreparedReference, root: str, tiling: Tiling) -> list:
    """Each tile's core points' state, on disk for its measuring tasks; the tiles holding core points."""
    folder = Path(root, "state")
    folder.mkdir(exist_ok=True)
    keys = _tile_of(tiling, prepared.core_points)
    order = np.lexsort((keys[:, 1], keys[:, 0]))
    sorted_keys = keys[order]
    cut = np.flatnonzero(np.any(np.diff(sorted_keys, axis=0) != 0, axis=1)) + 1
    out = []
    for part in np.split(order, cut):
        rows = np.sort(part)
        key = (int(keys[rows[0], 0]), int(keys[rows[0], 1]))
        np.savez(folder / f"{key[0]}_{key[1]}.npz", rows=rows, core_points=prepared.core_points[rows],
                 **{name: getattr(prepared, name)[rows] for name in _STATE})
        out.append(key)
    return out


def _measure_tile(key, root: str, name: str, lo: np.ndarray, reg: float, scalars: dict, memory_limit):
    """Tile ``key``'s core points measured on its bucket of epoch ``name``: (rows, (m, 12) values)."""
    t0 = time.perf_counter()
    with np.load(Path(root, "state", f"{key[0]}_{key[1]}.npz")) as f:
        state = {k: f[k] for k in f.files}
    rows = state.pop("rows")
    prepared = PreparedReference.from_state(state, scalars)
    rec = load_bucket(root, name, key)
    check_memory(prepared.memory_per_epoch(len(rec)), f"a tile of {len(rec):,} points of an epoch", memory_limit,
                 advice="give a smaller --tile-size")
    if not len(rec):  # no point of the epoch near: what the cylinders give for none
        values = np.full((len(rows), len(_PACKED)), np.nan)
        values[:, 2], values[:, 3], values[:, 4] = 0.0, prepared.ref_count, 0.0
        values[:, 5], values[:, 7:10], values[:, 10], values[:, 11] = prepared.ref_spread, prepared.normal, -1.0, 0.0
        return rows, values
    xyz = np.ascontiguousarray(rec[:, :3])
    d = prepared._measure(xyz, lo, bounds(xyz)[1], reg, t0)
    f = d.fields()
    values = np.column_stack([f[n] for n in _PACKED[:10]] + [d.level, d.off_axis]).astype(np.float64)
    return rows, values
