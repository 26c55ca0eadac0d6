"""The reference side of the signed distances, prepared once and measured against many epochs.

:func:`sdp.distances` computes, for one pair, the core points' cells, their normals and the
reference's kernel-weighted position in each cylinder, then the current's. In a series every
epoch is measured against the same reference at the same core points, so all of that reference
side is computed once (:meth:`PreparedReference.prepare`) and each epoch costs only its own
cells and cylinders (:meth:`PreparedReference.measure`): O(n) to sum the epoch into cells, O(1)
per core point. The prepared state is a few arrays per core point (:meth:`~PreparedReference.state`),
so a series archive stores it and an epoch appended later is measured exactly as in the full run.

The cells start at the reference's corner and an epoch reaching below it moves the corner down by
whole cells, so every epoch is cut into the same cells, as :func:`sdp.distances` does for a pair:
each epoch's numbers are those of :func:`sdp.distances` on that pair with the same scales (tested).

References
----------
.. [1] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
   terrestrial laser scanner", ISPRS J. Photogramm. 82 (2013) (M3C2, the level of detection).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from .._core._memory import check_memory
from .._core._points import as_points
from .._core._validate import auto_or_nonnegative, auto_or_positive, direction
from ..change._visibility import resolve_sensor_origins
from ..defaults import DEFAULTS
from ..errors import InvalidOptionError, InvalidPointsError
from ..fields._spacing import resolve_lattice
from ..options import Cylinder, as_options
from ._cells import CELL, RADIUS, CellLists, cell_moments
from ._distances import Distances, _results, cell_corner, cells_below, normal_sigma, search_reach
from ._level import with_level
from ._seen import front_start, without_unseen

__all__ = ["PreparedReference"]

#: The arrays of :meth:`PreparedReference.state`, per core point (in the core points' order).
STATE_ARRAYS = ("core_points", "normal", "ref_mean", "ref_spread", "ref_count", "ref_level", "ref_across",
                "ref_across_var", "ref_front")


@dataclass
class PreparedReference:
    """The reference epoch's side of :func:`sdp.distances` at fixed core points.

    Attributes
    ----------
    core_points, normal : ndarray (m, 3) float64
        Where distances are measured and the unit normals there (NaN where the reference has no
        points near: never comparable).
    ref_mean, ref_spread, ref_count : ndarray (m,) float64
        The reference's kernel-weighted offset along the normal, spread and effective count.
    ref_level : ndarray (m,) int8
        0: the reference answered in the cylinder at the core point; 1: farther along the normal.
    ref_across, ref_across_var : ndarray (m, 3), (m,) float64
        The reference's weighted centroid across the cylinder's axis and its variance, which an
        epoch's is compared with (:func:`sdp.distance._distances.off_axis`); NaN where not
        kept (an archive written before them: no place is then found off the axis).
    ref_front : ndarray (m,) float64
        How far along the normal in front of each core point the reference held nothing
        (:meth:`sdp.distance._cells.CellLists.free_ahead`; inf: nothing within the search's
        reach), where the normals face its sensors; NaN otherwise (and in an archive written
        before it). An epoch's surface found farther in front, nearer than this, is new there and
        measured where it stands (:mod:`sdp.distance._seen`).
    projection_scale, normal_scale, max_distance : float
        The scales used (M3C2's d, D and the search's half-length).
    corner : ndarray (3,) float64
        Where the cells start.
    orientation : ndarray (3,) float64
        The direction the normals were turned towards.
    """

    core_points: np.ndarray
    normal: np.ndarray
    ref_mean: np.ndarray
    ref_spread: np.ndarray
    ref_count: np.ndarray
    ref_level: np.ndarray
    ref_across: np.ndarray
    ref_across_var: np.ndarray
    ref_front: np.ndarray
    projection_scale: float
    normal_scale: float
    max_distance: float
    corner: np.ndarray
    orientation: np.ndarray
    #: The normals face the reference's sensors (prepared with ``sensor``): a surface an epoch holds
    #: farther in front of a core point is then measured where it stands (:mod:`sdp.distance._seen`).
    faces_sensor: bool = False
    #: The core points sorted by cell, their arrays in that order and their upper corner, made at
    #: the first epoch: each core point's numbers do not depend on the order, which only keeps the
    #: cylinders' reads of neighbouring cells close in memory, so a series sorts them once, not
    #: once per epoch.
    _sorted: tuple | None = field(default=None, repr=False, compare=False)

    @classmethod
    def prepare(cls, reference, core_points=None, *, cylinder: Cylinder | None = None, orientation=None,
                memory_limit=None, corner=None, sensor=None) -> "PreparedReference":
        """Cells, normals and the reference's cylinders at the core points (default: every reference point).

        ``cylinder`` as in :func:`sdp.distances`, except that ``"auto"`` scales come from the
        reference alone (they must not depend on epochs not seen yet). ``corner``: where the
        cells start (default just below the reference and core points), as in
        :func:`sdp.distances`: the tiles of one reference (:mod:`sdp.scale._series`) give the
        whole reference's, so their cells, and numbers, are those of the whole. ``sensor``: the
        position (3,) the normals face, or each core point's scanner's (m, 3), as
        :func:`sdp.distances` turns them where the reference's file records its sensors; else
        they face ``orientation`` (default +z)."""
        ref = as_points(reference, name="reference")
        if len(ref.xyz) < 3:
            raise InvalidPointsError(f"the reference has {len(ref.xyz)} point(s): a surface normal and a spread "
                                     "need at least 3")
        cylinder = as_options(Cylinder, cylinder, "cylinder")
        d_opt = auto_or_positive("projection_scale", cylinder.projection_scale)
        D_opt = auto_or_positive("normal_scale", cylinder.normal_scale)
        L_opt = auto_or_positive("max_distance", cylinder.max_distance)
        towards = direction("orientation", DEFAULTS.orientation if orientation is None else orientation)
        core = ref.xyz if core_points is None else as_points(core_points, name="core points").xyz
        if d_opt == "auto":
            voxel, sigma_voxels = resolve_lattice([ref], k=3.0)
            sigma_p = sigma_voxels * voxel
        else:
            sigma_p = d_opt / 4.0
        max_half = search_reach(L_opt, 4.0 * sigma_p)
        lo = cell_corner(np.minimum(ref.lo, core.min(axis=0)), corner)
        hi = np.maximum(ref.hi, core.max(axis=0))
        check_memory(200.0 * len(ref.xyz) + 240.0 * len(core),
                     f"the reference's {len(ref.xyz):,} points at {len(core):,} core points", memory_limit,
                     advice="measure at fewer core points")
        lists = CellLists(lo, hi)
        order, starts = lists.order(core, CELL * sigma_p)
        core_sorted = lists.get(core, CELL * sigma_p)[0]
        centroids = np.ascontiguousarray(cell_moments(core_sorted, starts)[:, 1:4])
        sigma_n = normal_sigma(lists, ref.xyz, centroids, sigma_p, D_opt)
        normal, _ = lists.normals(ref.xyz, centroids, sigma_n)
        normal = np.repeat(normal, np.diff(starts), axis=0)
        if sensor is None:
            normal[normal @ towards < 0] *= -1.0
        else:  # as sdp.distances: towards the sensor, or each core point's own scanner
            sensor = np.asarray(sensor, np.float64)
            facing = (sensor[order] if sensor.ndim == 2 else sensor[None, :]) - core_sorted
            normal[np.einsum("ij,ij->i", normal, facing) < 0] *= -1.0
        m1, s1, c1, k1, l1, v1 = lists.cylinder(ref.xyz, core_sorted, normal, sigma_p, max_half)
        front = np.full(len(core_sorted), np.nan)
        if sensor is not None:  # the normals face the sensors: what the reference held in front of each core point
            front = lists.free_ahead(ref.xyz, core_sorted, normal, sigma_p, front_start(m1, sigma_p), max_half)
        back = np.empty_like(order)
        back[order] = np.arange(len(order))

        def unsort(a):
            return np.ascontiguousarray(a[back])

        # a private copy (core may be the caller's own array); each epoch's results get theirs (_measure)
        return cls(core_points=np.array(core, np.float64, order="C"), normal=unsort(normal), ref_mean=unsort(m1),
                   ref_spread=unsort(s1), ref_count=unsort(c1), ref_level=unsort(k1).astype(np.int8),
                   ref_across=unsort(l1), ref_across_var=unsort(v1), ref_front=unsort(front),
                   projection_scale=4.0 * sigma_p, normal_scale=4.0 * sigma_n, max_distance=max_half,
                   corner=lo, orientation=towards, faces_sensor=sensor is not None)

    # ------------------------------------------------------------------ state
    def state(self) -> tuple[dict[str, np.ndarray], dict]:
        """(arrays per core point, scalars): everything :meth:`measure` needs, for an archive."""
        arrays = {name: getattr(self, name) for name in STATE_ARRAYS}
        scalars = {"projection_scale": self.projection_scale, "normal_scale": self.normal_scale,
                   "max_distance": self.max_distance, "corner": [float(v) for v in self.corner],
                   "orientation": [float(v) for v in self.orientation], "faces_sensor": self.faces_sensor}
        return arrays, scalars

    @classmethod
    def from_state(cls, arrays: dict, scalars: dict) -> "PreparedReference":
        """The object :meth:`state` described (a state without the reference's centroid across
        the axis, an archive's from before it: NaN, no place off the axis)."""
        m = len(arrays["core_points"])
        arrays = {"ref_across": np.full((m, 3), np.nan), "ref_across_var": np.full(m, np.nan),
                  "ref_front": np.full(m, np.nan), **arrays}
        return cls(**{name: np.ascontiguousarray(arrays[name]) for name in STATE_ARRAYS},
                   projection_scale=float(scalars["projection_scale"]), normal_scale=float(scalars["normal_scale"]),
                   max_distance=float(scalars["max_distance"]), corner=np.asarray(scalars["corner"], np.float64),
                   orientation=np.asarray(scalars["orientation"], np.float64),
                   faces_sensor=bool(scalars.get("faces_sensor", False)))

    def memory_per_epoch(self, n_points: int) -> float:
        """Bytes :meth:`measure` needs for an epoch of ``n_points`` (its cells and the outputs)."""
        return 200.0 * n_points + 160.0 * len(self.core_points)

    # ------------------------------------------------------------------ one epoch
    def measure(self, current, *, registration_error: float | str = "auto", memory_limit=None) -> Distances:
        """Distances from the reference to ``current`` at the core points, as :func:`sdp.distances`
        (``registration_error``: a number, or ``"auto"``: measured on the stable part; a
        :class:`sdp.Cloud` that knows its sensors: no distance where they could not see the place
        measured, :mod:`sdp.distance._seen`)."""
        t0 = time.perf_counter()
        cur = as_points(current, name="epoch")
        if len(cur.xyz) < 3:
            raise InvalidPointsError(f"an epoch has {len(cur.xyz)} point(s): a spread needs at least 3")
        reg = auto_or_nonnegative("registration_error", registration_error)
        check_memory(self.memory_per_epoch(len(cur.xyz)), f"an epoch of {len(cur.xyz):,} points", memory_limit,
                     advice="measure at fewer core points")
        d = self._measure(cur.xyz, self.epoch_corner(cur.lo), cur.hi, 0.0 if reg == "auto" else reg, t0)
        origins = resolve_sensor_origins("auto", None, current)[1]  # what the epoch's file says, else None
        d = without_unseen(d, current, cur.xyz, origins, sigma=self.projection_scale / 4.0,
                           along=self.ref_mean + d.distance, facing=self.faces_sensor, free_ahead=self.ref_front)
        return with_level(d, reg)

    def epoch_corner(self, lowest) -> np.ndarray:
        """Where an epoch's cells start: the reference's corner, whole cells lower where the epoch's
        ``lowest`` point reaches lower."""
        return cells_below(self.corner, np.asarray(lowest, np.float64), CELL * self.projection_scale / 4.0)

    def _measure(self, xyz: np.ndarray, lo: np.ndarray, highest: np.ndarray, reg: float, t0: float) -> Distances:
        """:meth:`measure` of finite points ``xyz`` (any number from 1; ``highest`` their upper
        corner) on cells from ``lo``."""
        sigma_p = self.projection_scale / 4.0
        cell = CELL * sigma_p
        core = self.core_points
        core_hi = core.max(axis=0) if self._sorted is None else self._sorted[4]
        hi = np.maximum(np.maximum(highest, core_hi), lo + cell)
        lists = CellLists(lo, hi)
        if self._sorted is None:
            order, _ = lists.order(core, cell)
            self._sorted = (order, lists.get(core, cell)[0], np.ascontiguousarray(self.normal[order]),
                            tuple(np.ascontiguousarray(a[order]) for a in (self.ref_mean, self.ref_spread,
                                                                           self.ref_count,
                                                                           self.ref_level.astype(np.int64),
                                                                           self.ref_across, self.ref_across_var)),
                            core_hi)
        order, queries, normal, ref, _ = self._sorted
        cur_stats = lists.cylinder(xyz, queries, normal, sigma_p, self.max_distance)
        reach = max(self.max_distance, RADIUS * sigma_p)
        m = len(order)
        dist, lod, n1, n2, s1, s2 = (np.empty(m) for _ in range(6))
        out_normal, level, off = np.empty((m, 3)), np.empty(m, np.int8), np.empty(m, np.bool_)
        _results(order, ref, cur_stats, normal, reg, reach, sigma_p, queries, dist, lod, n1, n2, s1, s2, out_normal,
                 level, off)
        how = "towards ({:g}, {:g}, {:g})".format(*self.orientation)
        return Distances(core_points=core.copy(), distance=dist, lod=lod, significant=np.abs(dist) > lod,
                         n1=n1, n2=n2, spread1=s1, spread2=s2, normal=out_normal, level=level,
                         projection_scale=self.projection_scale, normal_scale=self.normal_scale, max_distance=reach,
                         registration_error=reg, orientation=how, timings={"total": time.perf_counter() - t0},
                         off_axis=off)


def subsample(xyz: np.ndarray, spacing: float, *, origin=None) -> np.ndarray:
    """Rows of ``xyz``, one per occupied cube of ``spacing`` (the point nearest its cell's
    centroid, the first in input order on ties), in input order: core points at a given spacing.
    The cubes start at ``origin`` (default the lowest corner of ``xyz``; a tile gives the whole
    cloud's, so that its whole cubes choose as the whole cloud does)."""
    if not (math.isfinite(spacing) and spacing > 0):
        raise InvalidOptionError(f"core point spacing must be positive, got {spacing!r}")
    origin = xyz.min(axis=0) if origin is None else np.asarray(origin, np.float64)
    cells = np.floor((xyz - origin) / spacing).astype(np.int64)
    low, span = cells.min(axis=0), np.ptp(cells, axis=0).astype(np.float64) + 1
    if float(np.prod(span)) < 2.0**62:  # one int64 key per cube: a 1-D sort, several times faster than rows'
        cells -= low
        key = (cells[:, 0] * int(span[1]) + cells[:, 1]) * int(span[2]) + cells[:, 2]
        _, inverse = np.unique(key, return_inverse=True)
    else:
        _, inverse = np.unique(cells, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    # the cubes' numbering does not matter: each cube's sums and its nearest point are the same
    k = inverse.max() + 1
    counts = np.bincount(inverse, minlength=k).astype(np.float64)
    mean = np.stack([np.bincount(inverse, xyz[:, a], minlength=k) for a in range(3)], axis=1) / counts[:, None]
    d2 = ((xyz - mean[inverse]) ** 2).sum(axis=1)
    order = np.lexsort((d2, inverse))  # stable: ties in input order
    first = np.ones(len(order), bool)
    first[1:] = inverse[order[1:]] != inverse[order[:-1]]
    return np.sort(order[first])
