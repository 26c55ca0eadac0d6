"""Change detection between two clouds (the paper's Algorithm 1), with change regions.

:func:`detect_changes` works in these steps:

1. One lattice for both clouds (:func:`sdp.fields._spacing.resolve_lattice`: from the union box, or the
   voxel measured on both clouds), and both fields F_ref and F_cur on it
   (:func:`sdp.fields._density.build_fields`).
2. The difference volume D = max(F_cur, −F_ref) on the current field's blocks (outside them
   F_cur = h > 0, so the volume lies inside). The current points where the trilinear D(p) < 0
   have appeared; with the fields swapped, the reference points that disappeared. D is never
   stored (:class:`sdp.change._regions.Volume`): the kernels evaluate it node by node from both fields
   where they need it, in the same float32 arithmetic as the stored Boolean result
   (:func:`sdp.fields._boolean.difference_on_own_blocks`, which the tiled path ships), so a comparison
   allocates no field-sized array besides the two fields (touching fresh memory costs about
   0.2 ms per MB). Every point with D(p) < 0 has a negative cell corner, so the masks agree
   with the regions.
3. Coverage (:mod:`sdp.change._coverage`, :func:`judge_coverage`): each changed point becomes changed,
   unchanged or not comparable, by the other scan's rays (:mod:`sdp.change._visibility`) when its sensor
   position is known (``sensor_origin="auto"``: ``Cloud.sensor_origin``, an organized PCD's
   VIEWPOINT; or given), else by the other field's footprint. It runs before
   ``min_region_points``; not comparable points get no region, and the cluster rule does not
   promote them.
4. Regions (:mod:`sdp.change._regions`): the 6-connected components of D < 0 and their points;
   ``min_region_points`` drops strays. ``decision="cluster"`` (the paper's clustering): a
   component of the cloud's own cluster volume in which more than ``cluster_fraction`` of the
   points changed is reported changed whole; the others stay point-wise, because an object
   resting on a table shares the table's cluster, and a rule that also cleared minority
   clusters would erase it.

Steps 3 and 4 of the two directions (appeared, disappeared) are independent: they run on two
threads (:func:`sdp._core._parallel.map_concurrently`; the kernels release the GIL) when Numba has more
than one thread and a thread-safe threading layer (OpenMP, TBB), else in turn. The spacing of
the two clouds (``voxel_size="auto"``) is measured the same way, and so are the first parts of
the two builds (:func:`sdp.fields._density.build_fields` says why their blurs run in turn).

References
----------
.. [1] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
   Comparison and Applications", Algorithm 1.
.. [2] J. P. Underwood et al., "Explicit 3D change detection using ray-tracing in spherical
   coordinates", ICRA 2013 (the visibility test of ``sensor_origin=``, :mod:`sdp.change._visibility`).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from dataclasses import field as dc_field

import numpy as np

from .._core._memory import check_memory
from .._core._memory import memory_limit as memory_limit_bytes
from .._core._parallel import map_concurrently
from .._core._points import as_points, to_rows
from .._core._validate import boolean, finite, integer_at_least
from ..defaults import DEFAULTS
from ..errors import InvalidOptionError
from ..fields._density import DensityField, build_fields
from ..fields._spacing import resolve_lattice
from ..options import Coverage, Lattice, NoiseModel, as_options
from ._combined import combine_decision
from ._coverage import CHANGED, NOT_COMPARABLE, UNCHANGED, footprint_covered, states_of
from ._regions import Region, Volume, describe_regions, label_volume
from ._range_image import RangeImage
from ._visibility import (gone_only_if_seen, image_camera, rays_sent, resolve_sensor_origins, scanner_of_points,
                          sensor_band, sensor_poles, visibility_states)

#: The decisions of :func:`detect_changes` (``"density"`` is ``"point"``: the paper's, density alone).
DECISIONS = ("point", "density", "cluster", "combined")

__all__ = ["DECISIONS", "ChangeResult", "PointChanges", "detect_changes", "judge_coverage", "inside_difference",
           "region_rules"]


class PointChanges:
    """The state and region label of each point of one cloud, held as per-point arrays (in
    memory), or as the sorted rows that changed, with their labels, and the sorted rows that are
    not comparable (in tiles, whose clouds need not fit in memory). From rows, the per-point
    arrays are made on first use and kept; :meth:`rows` makes those of a slice of rows alone."""

    __slots__ = ("n", "blank", "_state", "_labels", "_changed", "_changed_labels", "_unseen")

    def __init__(self, n: int, *, state=None, labels=None, changed=None, changed_labels=None, unseen=None,
                 blank: int = 0):
        self.n = int(n)
        self.blank = int(blank)  # rows holding NaN or Inf among the n: not comparable, and no point
        self._state, self._labels = state, labels
        self._changed, self._changed_labels, self._unseen = changed, changed_labels, unseen

    @classmethod
    def of_rows(cls, n: int, changed: np.ndarray, changed_labels: np.ndarray, unseen: np.ndarray, *,
                blank: int = 0) -> PointChanges:
        return cls(n, changed=np.asarray(changed, np.int64), changed_labels=np.asarray(changed_labels, np.int32),
                   unseen=np.asarray(unseen, np.int64), blank=blank)

    @property
    def state(self) -> np.ndarray:
        if self._state is None:
            self._state, self._labels = self.rows(0, self.n)
        return self._state

    @property
    def labels(self) -> np.ndarray:
        if self._labels is None:
            self._state, self._labels = self.rows(0, self.n)
        return self._labels

    def count(self, value: int) -> int:
        """How many points are in state ``value``."""
        if self._state is not None:
            return int(np.count_nonzero(self._state == value))
        changed, unseen = int(self._changed.size), int(self._unseen.size)
        return {CHANGED: changed, NOT_COMPARABLE: unseen}.get(value, self.n - changed - unseen)

    def rows(self, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        """(state uint8, label int32) of rows ``start`` … ``stop``−1."""
        if self._state is not None:
            return self._state[start:stop], self._labels[start:stop]
        state, labels = np.full(stop - start, UNCHANGED, np.uint8), np.full(stop - start, -1, np.int32)
        i, j = np.searchsorted(self._changed, (start, stop))
        state[self._changed[i:j] - start], labels[self._changed[i:j] - start] = CHANGED, self._changed_labels[i:j]
        i, j = np.searchsorted(self._unseen, (start, stop))
        state[self._unseen[i:j] - start] = NOT_COMPARABLE
        return state, labels


@dataclass(eq=False)
class ChangeResult:
    """What changed between a reference and a current cloud: the result of
    :func:`detect_changes` (in memory) and of :func:`sdp.detect_changes_tiled` (in tiles).

    Every point is in one of three states (:mod:`sdp.change._coverage`): changed (appeared in the
    current, disappeared from the reference), not comparable (the other epoch never saw its
    place), or unchanged. Per-point arrays have one entry per input row (rows that held NaN/Inf
    are not comparable, in no region).

    A result of the tiles (``tiled``) holds the rows that changed, not per-point arrays: the
    command streams its output from those rows (:meth:`rows`), so that its memory does not grow
    with the clouds. Its per-point arrays are made on first use and kept (5 bytes per point of
    that cloud, outside the tiled job's memory limit): for clouds that fit in memory.

    Attributes
    ----------
    current_state, reference_state : ndarray of uint8 (n_current,), (n_reference,)
        The ``change`` field of each point: :data:`~sdp.UNCHANGED` (0), :data:`~sdp.CHANGED` (1:
        appeared in the current, disappeared from the reference), :data:`~sdp.NOT_COMPARABLE`
        (2: the other epoch has no density there and never saw the place: outside its footprint,
        field of view, or hidden from its sensor; and a row holding NaN or Inf, which nothing measured).
    appeared_labels, disappeared_labels : ndarray of int32 (n_current,), (n_reference,)
        The label of each point's change region in ``appeared_regions`` / ``disappeared_regions``
        (-1: none: unchanged, not comparable, or a stray dropped by ``min_region_points``).
    appeared, disappeared, current_not_comparable, reference_not_comparable : ndarray of bool
        Masks of those states (made from the states at each use).
    appeared_regions, disappeared_regions : list of Region
        Connected change regions, largest first.
    reference_field, current_field : DensityField or None
        The two fields, on one lattice (same voxel size); None in tiles (the fields are built
        tile by tile and not kept).
    tiled : bool
        Whether the clouds were compared in tiles (:func:`sdp.detect_changes_tiled`).
    n_reference, n_current : int
        Rows of each input (a stored reference: the points its field was built from), of which
        ``n_dropped_reference`` / ``n_dropped_current`` held NaN or Inf.
    voxel_size, sigma, h : float
        Parameters used.
    decision : str
        ``"point"``, ``"cluster"`` or ``"combined"`` (see :func:`detect_changes`; tiles: ``"point"`` or
        ``"combined"``).
    current_distance, current_lod, reference_distance, reference_lod : ndarray of float64 or None
        With ``decision="combined"``: each point's signed distance to the other epoch's surface
        and its level of detection at 95 % (:class:`sdp.distance._noise.SurfaceDistances`; NaN:
        nothing to measure against), measured over the whole cloud on first use (the decision
        itself measures them only next to what the density found); else None. ``summary()``
        gives the level's calibration per direction (``"level"``: σ_s, the range exponent p).
    sensor_origins : tuple of (ndarray (3,) or None)
        The reference's and the current's sensor position used (None: not known).
    coverage : dict of str to str
        How each direction decided what the other epoch saw: ``"sensor rays"``,
        ``"footprint"`` or ``"off"``, for ``"appeared"`` and ``"disappeared"``.
    range_noise : dict of str to float
        The band of each epoch's rays (``"reference"``, ``"current"``: b = range_noise·r², per
        world unit; :func:`sdp.change._visibility.sensor_band`), where its sensor is known.
    range_units : dict of str to float
        Where the default band was taken per millimetre (0.001) or centimetre (0.01): that epoch's
        points lie farther from its sensor than a depth camera sees in metres
        (:func:`sdp.change._visibility.depth_camera_units`).
    n_tiles, tile_size : int, float or None
        In tiles: the tiles compared and their edge (world units); else 0 and None.
    timings : dict of str to float
        Seconds per step. In memory: ``build_reference``, ``build_current``, ``detect`` (as the
        paper's Table I), then ``coverage`` (the visibility test with a sensor, else the
        footprint) and ``regions``; with ``voxel_size="auto"``, also ``voxel_size``; with
        ``decision="combined"``, also ``distance`` (both directions' completion by the distance). The two
        builds bin their clouds at once, and ``coverage`` and ``regions`` add up both
        directions, which run at once: on two threads when there are two cores, so these steps
        may add up to more than the wall time they took. In tiles: wall seconds of ``bucket``
        (reading included), ``compare`` and ``regions``, and summed task seconds ``read``,
        ``build_reference``, ``build_current``, ``detect``, ``label``.
    """

    _reference: PointChanges = dc_field(repr=False)
    _current: PointChanges = dc_field(repr=False)
    appeared_regions: list[Region]
    disappeared_regions: list[Region]
    voxel_size: float
    sigma: float
    h: float
    decision: str = "point"
    reference_field: DensityField | None = dc_field(default=None, repr=False)
    current_field: DensityField | None = dc_field(default=None, repr=False)
    tiled: bool = False
    n_dropped_reference: int = 0
    n_dropped_current: int = 0
    sensor_origins: tuple = (None, None)
    coverage: dict[str, str] = dc_field(default_factory=dict)
    range_noise: dict[str, float] = dc_field(default_factory=dict)
    range_units: dict[str, float] = dc_field(default_factory=dict)
    n_tiles: int = 0
    tile_size: float | None = None
    timings: dict[str, float] = dc_field(default_factory=dict)
    _distances: tuple = dc_field(default=(None, None), repr=False)  # (reference's, current's) _Distances

    current_distance = property(lambda self: self._distance_rows(1, 0))
    current_lod = property(lambda self: self._distance_rows(1, 1))
    reference_distance = property(lambda self: self._distance_rows(0, 0))
    reference_lod = property(lambda self: self._distance_rows(0, 1))

    def _distance_rows(self, cloud: int, which: int) -> np.ndarray | None:
        """The distance (``which`` 0) or lod (1) of the reference's (``cloud`` 0) or current's (1)
        rows, measured on first use; None without ``decision="combined"``."""
        d = self._distances[cloud]
        return None if d is None or d.rows is None else d.rows[which]

    @property
    def current_state(self) -> np.ndarray:
        """The ``change`` field of the current points (uint8): 0 unchanged, 1 appeared, 2 not comparable."""
        return self._current.state

    @property
    def reference_state(self) -> np.ndarray:
        """The ``change`` field of the reference points: 0 unchanged, 1 disappeared, 2 not comparable."""
        return self._reference.state

    @property
    def appeared_labels(self) -> np.ndarray:
        """Region label of each current point (int32; -1: none)."""
        return self._current.labels

    @property
    def disappeared_labels(self) -> np.ndarray:
        """Region label of each reference point (int32; -1: none)."""
        return self._reference.labels

    @property
    def appeared(self) -> np.ndarray:
        """Mask of the current points that appeared."""
        return self.current_state == CHANGED

    @property
    def disappeared(self) -> np.ndarray:
        """Mask of the reference points that disappeared."""
        return self.reference_state == CHANGED

    @property
    def current_not_comparable(self) -> np.ndarray:
        """Mask of the current points the reference never saw."""
        return self.current_state == NOT_COMPARABLE

    @property
    def reference_not_comparable(self) -> np.ndarray:
        """Mask of the reference points the current never saw."""
        return self.reference_state == NOT_COMPARABLE

    @property
    def n_reference(self) -> int:
        return self._reference.n

    @property
    def n_current(self) -> int:
        return self._current.n

    def rows(self, cloud: str, start: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
        """(state uint8, region label int32) of rows ``start`` … ``stop``−1 of the ``"reference"``
        or ``"current"`` cloud; in tiles made from the changed rows alone, without the whole
        cloud's arrays (what a streamed writer needs: :func:`sdp.write_points_streamed`)."""
        if cloud not in ("reference", "current"):
            raise InvalidOptionError(f"cloud must be 'reference' or 'current', got {cloud!r}")
        points = self._reference if cloud == "reference" else self._current
        return points.rows(max(0, int(start)), min(points.n, int(stop)))

    def summary(self) -> dict:
        """A JSON-serializable summary: counts, parameters (and tiles), sensors, coverage, timings
        and regions."""
        def origin(o):
            return None if o is None else np.asarray(o, np.float64).tolist()  # (3,), or (k, 3) scanners

        def counts(points, dropped, kind, distances=None):
            # the points compared: rows holding NaN or Inf are counted as dropped, not as points
            out = {"points": points.n - points.blank, "dropped": int(dropped), kind: points.count(CHANGED),
                   "not_comparable": points.count(NOT_COMPARABLE) - points.blank}
            if distances is not None:
                out["level"] = distances.level()
            return out

        tiles = {"tiles": self.n_tiles, "tile_size": self.tile_size} if self.tiled else {}
        reference = counts(self._reference, self.n_dropped_reference, "disappeared", self._distances[0])
        if self.coverage.get("disappeared") == "not measured":  # a field store's reference: no points to test
            reference.update(disappeared=None, not_comparable=None)
        return {"voxel_size": self.voxel_size, "sigma": self.sigma, "h": self.h, "decision": self.decision, **tiles,
                "sensor_origin": {"reference": origin(self.sensor_origins[0]),
                                  "current": origin(self.sensor_origins[1])},
                "coverage": dict(self.coverage),
                **({"range_noise": dict(self.range_noise)} if self.range_noise else {}),
                **({"range_units": dict(self.range_units)} if self.range_units else {}),
                "reference": reference,
                "current": counts(self._current, self.n_dropped_current, "appeared", self._distances[1]),
                "timings": dict(self.timings),
                "appeared_regions": [r.to_dict() for r in self.appeared_regions],
                "disappeared_regions": [r.to_dict() for r in self.disappeared_regions]}


def detect_changes(reference, current, *, lattice: Lattice | None = None, coverage: Coverage | None = None,
                   decision: str = DEFAULTS.decision, cluster_fraction: float = DEFAULTS.cluster_fraction,
                   min_region_points: int = DEFAULTS.min_region_points, regions: bool = True,
                   memory_limit: int | str | None = None, noise: NoiseModel | None = None) -> ChangeResult:
    """Points that appeared in ``current`` and disappeared from ``reference``.

    Builds F_ref and F_cur on one lattice (same voxel size), forms the difference volumes
    D = max(F_cur, −F_ref) and max(F_ref, −F_cur) at the nodes, and flags each point whose
    interpolated D is negative: it lies in its own cloud's cluster volume and outside the
    other's. A flagged point where the other epoch could not see is *not comparable*, not
    changed (:mod:`sdp.change._coverage`). Every default is :data:`sdp.DEFAULTS` (the best setting
    measured on real scans; ``grid_size=80`` is the paper's).

    Parameters
    ----------
    reference, current : array_like (n, 3) or Cloud
        World coordinates, both in the same frame (register them first), or clouds as
        :func:`sdp.read_points` returns them (they bring their sensor position and the count
        of rows their reader dropped).
    lattice : Lattice, optional
        Where the fields live (:class:`sdp.Lattice`): by default the voxel from both clouds' point
        spacing (:func:`sdp.auto_voxel_size`), because a fixed grid is too coarse on real scans;
        ``Lattice(grid_size=80)`` is the paper's (the longest side of the box holding *both*
        clouds in 80 segments).
    coverage : Coverage, optional
        Where the other scan could see (:class:`sdp.Coverage`). A flagged point the other epoch
        could not see is not comparable. With the other scan's sensor origin known (by default
        what each cloud's file records, :attr:`sdp.Cloud.sensor_origin`: an organized PCD's
        VIEWPOINT), each changed point is followed along that scan's rays
        (:func:`sdp.change._visibility.visibility_states`): a point whose place the other scan
        saw through stays a change; one whose ray the other scan saw end at the same range
        (within ``range_noise``·r²) is not a change; one the other scan could not see (hidden
        behind something nearer, or no return) is unchanged if it continues the unchanged surface
        around it (the table a moved object uncovers), else not comparable. Without a sensor, a
        changed point is not comparable when the other epoch did not sample its column (x, y at
        any height) densely enough for the threshold (:func:`sdp.footprint_covered`). It runs
        before the ``min_region_points`` filter. After :func:`sdp.align`, give the current's
        origin moved with the same matrix (two positions).
    memory_limit : int, str, optional
        As in :meth:`DensityField.from_points`.
    decision : {"point", "density", "cluster", "combined"}
        ``"point"`` (or ``"density"``, the same): Algorithm 1, each point on its own, by the
        density alone. ``"combined"``: the density's answer, or the point's distance to the
        other epoch's surface beyond a level of detection that holds on the sensor
        (:mod:`sdp.change._combined`), regions on the combined decision; the result then holds
        each point's ``distance`` and ``lod``. ``"cluster"``: the paper's clustering
        completes partly detected objects: a connected component of the cloud's own cluster
        volume (F < 0) in which more than ``cluster_fraction`` of the points changed is
        reported changed whole (its comparable points); the points of other components keep
        their own decision. (An object touching static structure shares its cluster with it
        and stays point-wise.)
    cluster_fraction : float
        Threshold of the ``"cluster"`` decision, in [0, 1); another value is refused with the
        other decisions, which would ignore it.
    min_region_points : int
        Change regions with fewer points are strays (noise, parallax at edges): their points
        are reported unchanged. Default 50; 1 keeps everything. Needs ``regions=True`` (or the
        ``"cluster"`` or ``"combined"`` decision, which find regions anyway): another value is
        refused with ``regions=False``.
    regions : bool
        Group changed points into connected regions (skip to save time).
    noise : NoiseModel, optional
        With ``decision="combined"``: the parts of the level of detection that are known
        (:class:`sdp.NoiseModel`: the systematic part, its growth with range, correlated
        errors); what is not given is measured on the pair's stable majority. Refused with
        the other decisions, which have no level.

    Returns
    -------
    ChangeResult

    Examples
    --------
    A box put on a floor: the box's points above the floor's own density appear, in one region.

    >>> import numpy as np
    >>> import sdp
    >>> rng = np.random.default_rng(0)
    >>> floor = np.c_[rng.random((4000, 2)), np.zeros(4000)]  # 1 m x 1 m
    >>> box = rng.uniform([0.4, 0.4, 0.0], [0.6, 0.6, 0.2], (500, 3))
    >>> result = sdp.detect_changes(floor, np.concatenate([floor, box]), lattice=sdp.Lattice(voxel_size=0.02))
    >>> int(result.appeared[:4000].sum()), int(result.disappeared.sum())  # the floor did not change
    (0, 0)
    >>> len(result.appeared_regions), [round(float(c), 1) for c in result.appeared_regions[0].centroid[:2]]
    (1, [0.5, 0.5])
    """
    if decision not in DECISIONS:
        raise InvalidOptionError(f"decision must be one of {', '.join(DECISIONS)}, got {decision!r}")
    given_decision, decision = decision, "point" if decision == "density" else decision
    lattice = as_options(Lattice, lattice, "lattice")
    coverage = as_options(Coverage, coverage, "coverage")
    noise = NoiseModel.of(noise, decision)
    memory_limit_bytes(memory_limit)
    min_region_points = integer_at_least("min_region_points", min_region_points, 0)
    boolean("regions", regions)
    given_fraction, cluster_fraction = cluster_fraction, finite("cluster_fraction", cluster_fraction)
    if not 0 <= cluster_fraction < 1:  # the float from here on, as min_region_points: "0.5" reached NumPy as text
        raise InvalidOptionError(f"cluster_fraction must be in [0, 1), got {given_fraction!r}")
    # options another choice leaves unused are refused, as watch refuses window without update='window'
    if cluster_fraction != DEFAULTS.cluster_fraction and decision != "cluster":
        raise InvalidOptionError(f"cluster_fraction applies to decision='cluster' only "
                                 f"(decision is {given_decision!r})")
    if min_region_points != DEFAULTS.min_region_points and not regions and decision not in ("cluster", "combined"):
        raise InvalidOptionError("min_region_points drops small regions: it applies with regions=True only "
                                 "(regions is False)")
    o_ref, o_cur = resolve_sensor_origins(coverage.sensor_origin, reference, current)
    ref = as_points(reference, name="reference")
    cur = as_points(current, name="current")
    s_ref = scanner_of_points(reference, o_ref, len(ref.xyz))  # which scanner saw each point (several)
    s_cur = scanner_of_points(current, o_cur, len(cur.xyz))
    pole_of = {id(ref): sensor_poles(reference, o_ref), id(cur): sensor_poles(current, o_cur)}  # their verticals
    timings = {}
    t = time.perf_counter()
    voxel_size, sigma_voxels = resolve_lattice([ref, cur], voxel_size=lattice.voxel_size, grid_size=lattice.grid_size,
                                               k=lattice.k, sigma_voxels=lattice.sigma_voxels)
    if lattice.automatic:
        timings["voxel_size"] = time.perf_counter() - t
    if decision == "combined":  # the distances' cells and arrays too, before any work
        from ..distance._noise import distance_bytes

        check_memory(distance_bytes((ref, cur), sigma_voxels * voxel_size),
                     f"the combined decision's distances between {len(ref.xyz):,} and {len(cur.xyz):,} points",
                     memory_limit, advice="use decision='point' (the density alone, also in tiles)")
    opts = dict(voxel_size=voxel_size, sigma_voxels=sigma_voxels, k=lattice.k, h=lattice.h,
                truncate=lattice.truncate, method=lattice.method, memory_limit=memory_limit)
    (f_ref, f_cur), (timings["build_reference"], timings["build_current"]) = build_fields([ref, cur], **opts)
    t = time.perf_counter()
    app, d_app = inside_difference(f_cur, f_ref, cur.xyz)
    dis, d_dis = inside_difference(f_ref, f_cur, ref.xyz)
    timings["detect"] = time.perf_counter() - t

    # each epoch's range image from its single sensor, built once when first needed: the other
    # direction's visibility test, and this one's check that a hider's place could be seen
    views = {id(c): _Once(lambda c=c, o=o, s=s, f=f: RangeImage.from_points(c.xyz, o, rays_sent=s,
                                                                             camera=image_camera(f, o),
                                                                             pole=pole_of[id(c)])
                          if o is not None and np.ndim(o) == 1 else None)
             for c, f, o, s in ((ref, reference, o_ref, rays_sent(reference)),
                                (cur, current, o_cur, rays_sent(current)))}
    # and the range noise of each epoch's sensor (a laser scan's is not a depth camera's)
    band = {role: sensor_band(c, coverage.range_noise, xyz=p.xyz, origin=o)
            for role, p, c, o in (("reference", ref, reference, o_ref), ("current", cur, current, o_cur))}
    noise_of = {id(ref): band["reference"][0], id(cur): band["current"][0]}
    raw = {id(ref): dis, id(cur): app}  # each epoch's points the density finds gone from the other

    def finish(job):
        """Coverage and region rules of one direction: (the points' states and labels, regions), times."""
        fld, pts, mask, d, other, other_field, other_origin, other_scan, own_origin, own_scan = job
        t = time.perf_counter()
        states = judge_coverage(pts.xyz, mask, other.xyz, other_field, other_origin, coverage=coverage.enabled,
                                range_noise=noise_of[id(other)], present=fld.inside, other_scan=other_scan,
                                image=views[id(other)].get, own_origin=own_origin, own_scan=own_scan,
                                own_image=views[id(pts)].get, own_range_noise=noise_of[id(pts)],
                                other_pole=pole_of[id(other)], own_pole=pole_of[id(pts)],
                                other_gone=raw[id(other)])
        steps = {"coverage": time.perf_counter() - t}
        t = time.perf_counter()
        unseen = states == NOT_COMPARABLE
        if decision == "combined":
            # what the density finds by itself (its regions, strays dropped): the components the
            # distance may complete (:func:`complete`)
            mask, _, region_of = region_rules(fld, d, pts.xyz, states == CHANGED, regions=True, decision="point",
                                              min_region_points=min_region_points, cluster_fraction=cluster_fraction)
            regs = []
        else:
            mask, regs, region_of = region_rules(fld, d, pts.xyz, states == CHANGED, regions=regions,
                                                 decision=decision, min_region_points=min_region_points,
                                                 cluster_fraction=cluster_fraction, blocked=unseen)
        steps["regions"] = time.perf_counter() - t
        return (states, mask, regs, region_of), steps

    jobs = [(f_cur, cur, app, d_app, ref, f_ref, o_ref, s_ref, o_cur, s_cur),
            (f_ref, ref, dis, d_dis, cur, f_cur, o_cur, s_cur, o_ref, s_ref)]
    # the two directions are independent: on two threads when there are two cores
    (appeared, steps_a), (disappeared, steps_d) = map_concurrently(finish, jobs, parallel_kernels=True)
    distances = (None, None)
    if decision == "combined":
        from ..distance._noise import pair_cells  # the distances load only for this decision

        t = time.perf_counter()
        # the distance completes what the density found (:mod:`sdp.change._combined`): both clouds
        # sorted once into the cells of 1.5σ both directions read, if either found anything
        lists = pair_cells((ref, cur), f_cur.sigma, sort=appeared[1].any() or disappeared[1].any())
        distances = (_Distances(jobs[1], disappeared[0], lists, noise), _Distances(jobs[0], appeared[0], lists, noise))

        def complete(k):
            fld, (states, found, _, found_regions) = jobs[k][0], (appeared, disappeared)[k]
            if not found.any():  # nothing to complete: no component is kept (rule 4)
                return states, found, [], np.full(len(found), -1)
            idx = np.flatnonzero(found)
            changed, regs, region_of = combine_decision(
                distances[1 - k].surface, states, directed=distances[1 - k].directed,
                present=fld.inside, found=idx, found_regions=found_regions[idx], regions=regions)
            return states, changed, regs, region_of

        appeared, disappeared = map_concurrently(complete, [0, 1], parallel_kernels=True)
        timings["distance"] = time.perf_counter() - t
    timings.update({step: steps_a[step] + steps_d[step] for step in steps_a})
    appeared, disappeared = (_point_changes(out, pts) for out, pts in ((appeared, cur), (disappeared, ref)))
    how = {"appeared": _coverage_kind(o_ref, coverage.enabled), "disappeared": _coverage_kind(o_cur, coverage.enabled)}
    return ChangeResult(_reference=disappeared[0], _current=appeared[0], appeared_regions=appeared[1],
                        disappeared_regions=disappeared[1], voxel_size=float(f_cur.voxel_size), sigma=f_cur.sigma,
                        h=f_cur.h, decision=decision, reference_field=f_ref, current_field=f_cur,
                        n_dropped_reference=f_ref.n_dropped, n_dropped_current=f_cur.n_dropped,
                        sensor_origins=(o_ref, o_cur), coverage=how, timings=timings, _distances=distances,
                        range_noise={role: band[role][0] for role, o in (("reference", o_ref), ("current", o_cur))
                                     if o is not None and coverage.enabled},
                        range_units={role: band[role][1] for role, o in (("reference", o_ref), ("current", o_cur))
                                     if o is not None and coverage.enabled and band[role][1] != 1.0})


def _point_changes(out, pts):
    """(PointChanges over the input rows, regions) of one direction's (states, changed mask,
    regions, region label per point)."""
    states, mask, regs, region_of = out
    state = to_rows(states_of(mask, states == NOT_COMPARABLE), pts, NOT_COMPARABLE)  # a NaN row: nothing measured
    labels = to_rows(np.asarray(region_of).astype(np.int32), pts, -1)
    blank = 0 if pts.finite is None else int((~pts.finite).sum())
    return PointChanges(len(state), state=state, labels=labels, blank=blank), regs


class _Distances:
    """One direction's distances to the other epoch (``decision="combined"``): the
    :class:`sdp.distance._noise.SurfaceDistances` its decision reads, made when first needed,
    and every point's distance and level over the input rows, measured on first use."""

    def __init__(self, job, states, lists, noise: NoiseModel):
        self._job, self._states, self._lists, self._noise = job, states, lists, noise
        self._surface = self._rows = None
        _, _, _, _, _, _, other_origin, _, own_origin, _ = job
        # one sensor per cloud: the noise model's range law and normals (several: neither yet)
        self.own_origin, self.other_origin = single_origin(own_origin), single_origin(other_origin)
        self.directed = self.other_origin is not None

    @property
    def surface(self):
        if self._surface is None:
            from ..distance._noise import SurfaceDistances

            fld, pts, _, _, other, *_ = self._job
            self._surface = SurfaceDistances(pts.xyz, other.xyz, sigma=fld.sigma, own_origin=self.own_origin,
                                             other_origin=self.other_origin, stable=self._states == UNCHANGED,
                                             lists=self._lists, **self._noise.arguments())
        return self._surface

    @property
    def rows(self) -> tuple[np.ndarray, np.ndarray]:
        """(distance, lod) per input row (NaN: a dropped row, or nothing to measure against)."""
        if self._rows is None:
            pd = self.surface.everywhere()
            pts = self._job[1]
            self._rows = (to_rows(pd.distance, pts, np.nan), to_rows(pd.lod, pts, np.nan))
        return self._rows

    def level(self) -> dict:
        """The level's calibration (:func:`level_summary`)."""
        return level_summary(self.surface.level, self._noise)


def level_summary(level: tuple, noise: NoiseModel) -> dict:
    """The summary's ``level`` of one direction from its calibration (p, r̃, c, σ_s): the systematic
    part σ_s (95 %: 1.96·σ_s), the range exponent p, and what of them ``noise`` gave."""
    p, r_med, scale, s = level
    given = {"given": noise.given} if noise.given else {}
    return {"systematic": s, "range_exponent": p, "median_range": r_med, "random_scale": scale, **given}


def judge_coverage(points: np.ndarray, changed: np.ndarray, other: np.ndarray | None, other_field: DensityField,
                   other_origin: np.ndarray | None, *, coverage: bool = True,
                   range_noise: float = DEFAULTS.range_noise, image=None, present=None,
                   other_scan: np.ndarray | None = None, own_origin=None, own_scan=None,
                   own_image=None, own_range_noise: float | None = None, other_pole=None,
                   own_pole=None, other_gone=None) -> np.ndarray:
    """The state (:mod:`sdp.change._coverage`) of each point of ``points`` flagged ``changed`` against
    the other epoch (its points ``other`` and field ``other_field``): by the other scan's rays
    when its origin is known (:func:`sdp.change._visibility.visibility_states`, ``present`` and
    ``image`` as there; several origins (k, 3) with ``other_scan``, the scanner of each point of
    ``other``: a point is comparable where any of them could see it), else by the other field's footprint
    (:func:`sdp.change._coverage.footprint_covered`); without ``coverage``, what the other scan could
    not see counts as changed. With the points' own sensors (``own_origin``, ``own_scan``, and the
    range image ``own_image`` or a callable returning it, their ``own_range_noise``), a hider their
    scan does not hold is gone only where those sensors could have seen its place
    (:func:`sdp.change._visibility.gone_only_if_seen`). ``other_pole`` and ``own_pole``: the
    sensors' verticals, shaped as their origins (:func:`sdp.change._visibility.sensor_poles`), or
    None. ``other_gone``: which points of ``other`` the density finds gone (a mask, or a callable
    giving it over some rows: ``gone`` of :func:`~sdp.change._visibility.visibility_states`; the
    unchanged points near them are no part of a plane test's patch)."""
    if other_origin is not None:
        present = gone_only_if_seen(present, points, own_origin, own_scan, floor=other_field.sigma, image=own_image,
                                    range_noise=range_noise if own_range_noise is None else own_range_noise,
                                    other_origin=other_origin, pole=own_pole)
        states = visibility_states(points, changed, other, other_origin, sigma=other_field.sigma,
                                   range_noise=range_noise, image=image, present=present, other_scan=other_scan,
                                   pole=other_pole, gone=other_gone, gone_reach=2.0 * other_field.truncate)
        if not coverage:
            states[states == NOT_COMPARABLE] = CHANGED
        return states
    states = np.asarray(changed, bool).astype(np.uint8)
    if coverage:
        cand = np.flatnonzero(changed)
        states[cand[~footprint_covered(points[cand], other_field)]] = NOT_COMPARABLE
    return states


def _coverage_kind(other_origin, coverage: bool) -> str:
    return "sensor rays" if other_origin is not None else ("footprint" if coverage else "off")


def inside_difference(fld: DensityField, other: DensityField, pts: np.ndarray):
    """Mask of ``pts`` (the finite points ``fld`` was built from) inside fld − other, and the
    difference volume D = max(F_fld, −F_other) < 0 on ``fld``'s blocks (D interpolated at the points)."""
    d = Volume.difference(fld, other)
    return d.negative_at(fld, pts), d


def region_rules(fld: DensityField, d: Volume, pts: np.ndarray, mask: np.ndarray, *, regions: bool,
                 decision: str, min_region_points: int, cluster_fraction: float, blocked: np.ndarray | None = None):
    """(mask, regions, region label per point) after the region-level rules of :func:`detect_changes`
    (``blocked``: points the cluster rule may not promote, the not comparable ones)."""
    if not (regions or decision == "cluster"):
        return mask, [], np.where(mask, 0, -1)
    # only the changed points' labels are used below (unchanged points end at -1, or take a
    # promoted cluster's label): label those alone, each point's label depends on it only
    changed = np.flatnonzero(mask)
    changed_pts = pts[changed]
    changed_labels, counts = label_volume(fld, d, changed_pts)
    kept = np.ones(len(changed), bool)
    if min_region_points > 1 and len(counts):
        big = np.bincount(changed_labels, minlength=len(counts)) >= min_region_points
        kept = big[np.maximum(changed_labels, 0)]
    if decision != "cluster":
        # the regions of the changed points alone (the others hold no label): the same sums in
        # the same order as over every point, at a tenth of the passes over the cloud
        regs, changed_region = describe_regions(changed_pts, np.where(kept, changed_labels, -1),
                                                counts * fld.voxel_size**3)
        mask = np.zeros(len(pts), bool)
        mask[changed[kept]] = True
        region_of = np.full(len(pts), -1, np.int64)
        region_of[changed] = changed_region
        return mask, regs, region_of
    labels = np.full(len(pts), -1, np.int64)
    labels[changed] = changed_labels
    mask = mask.copy()
    mask[changed[~kept]] = False
    mask, labels, counts = _cluster_decision(fld, pts, mask, labels, counts, cluster_fraction, blocked)
    regs, region_of = describe_regions(pts, np.where(mask, labels, -1), counts * fld.voxel_size**3)
    return mask, regs, region_of


def _cluster_decision(fld: DensityField, pts: np.ndarray, changed: np.ndarray, labels: np.ndarray,
                      counts: np.ndarray, fraction: float, blocked: np.ndarray | None):
    """Promote whole clusters (components of the cloud's own F < 0) in which more than
    ``fraction`` of the points changed; they become regions of their own."""
    clusters, cluster_nodes = label_volume(fld, Volume.inside(fld), pts)
    inside = clusters >= 0
    n = np.bincount(clusters[inside], minlength=len(cluster_nodes))
    c = np.bincount(clusters[inside], weights=changed[inside], minlength=len(cluster_nodes))
    promoted = np.zeros(len(changed), bool)
    promoted[inside] = (c > fraction * np.maximum(n, 1))[clusters[inside]]
    if blocked is not None:
        promoted &= ~blocked
    # promoted clusters are labelled after the change regions
    labels = np.where(promoted, len(counts) + clusters, labels)
    return changed | promoted, labels, np.concatenate([counts, cluster_nodes])


def single_origin(origin):
    """``origin`` if it is one sensor's position (3,) or None; None for several scanners (k, 3)."""
    return origin if origin is None or np.ndim(origin) == 1 else None


class _Once:
    """A value made by ``make()`` when first asked for (``get``), once, whichever thread asks."""

    def __init__(self, make):
        self._make, self._lock, self._value, self._made = make, threading.Lock(), None, False

    def get(self):
        with self._lock:
            if not self._made:
                self._value, self._made = self._make(), True
        return self._value
