"""How much each place changed: a signed distance along the surface normal, its level of
detection and a significance flag, from the density kernels of the two epochs.

M3C2 [1]_ answers "by how much, and is it more than the noise?" with a k-d tree, a normal per
core point and a cylinder search. The same answer falls out of the density field's kernel:
the Gaussian that builds G, centred on a core point, weights each epoch's points around it,
and their weighted moments are what M3C2 needs.

- **Normal**: the eigenvector of the smallest eigenvalue of the reference's kernel-weighted
  covariance at the normal scale (the current's where the reference has no points), oriented
  towards the sensor when it is known, else along ``orientation`` (default +z, as M3C2). The
  core points of one cell (of the moments below) share one normal, taken at their centroid.
- **Distance**: along that normal, each epoch's kernel-weighted mean offset in a cylinder
  around the core point: weight ``exp(−r²/2σ_p²)`` of the distance ``r`` to the axis, radius
  and half-length cut at 3σ_p (the kernel's truncation). Where an epoch has too few points
  there — fewer than two effective points, or less weight than two points on the rim of M3C2's
  cylinder (radius d/2 = 2σ_p): a few points near the cut tell where the surface lies off the
  axis, not at it — (it moved farther than the kernel reaches), the nearest of its cells on the normal's
  line within ``max_distance`` is found and the same cylinder, moved there, answers (twice
  recentred on the mean it finds): a displacement of any size is measured at the kernel's own
  resolution, and the nearest surface answers, not a mean of all surfaces on the line.
  ``distance = mean₂ − mean₁``: positive where the current lies on the normal's side (M3C2's
  sign).
- **Off the axis** (M3C2's step edge, Lague et al. [1]_): M3C2 assumes each epoch's surface
  crosses the cylinder's axis. Where the current's surface has gone (a door swung open, the floor
  under a pallet set down) its cylinder may still catch another surface at its rim (the frame, the
  pallet's sides) and read a small, significant distance. The cylinder's sums also give each
  epoch's weighted centroid across the axis; where the current's lies farther from the
  reference's than a half-disc's centroid (0.80σ_p) plus their sampling noise (:func:`off_axis`)
  there is no corresponding surface: no distance, counted as ``off_axis``. A surface cut by an
  edge in both epochs (a table's) gives both the same centroid and is measured. The combined
  decision's per-point offsets (:mod:`sdp.distance._noise`) are not tested so: they measure each
  point against the other epoch alone, within 3σ, where the density decides beyond 2σ.
- **Moments on cells** (:mod:`sdp.distance._cells`): each epoch's points are summed once, in O(n), into cubic cells of
  1.5σ_p (count, centroid, scatter); a cylinder reads at most 5³ cells and gives each cell's
  points the weight of its centroid (their offsets and spread along the normal stay exact), so
  a query costs the same however dense the cloud is. A counting sort over the box of cells
  orders them (beyond 2²⁵ cells, a sort by cell key and the spatial hash of
  :mod:`sdp._core._cells`); the search along a normal's line goes in steps of half a cell until
  the line passes an occupied cell or one of its 26 neighbours. The cells start at the corner of
  the reference and core points, the current's whole cells lower where it reaches lower, so
  every epoch compared with one reference is cut into the same cells.
- **Uncertainty**: ``spread`` = the weighted standard deviation along the normal, ``n`` = the
  effective number of points ``(Σw)²/Σw²`` (the count of an equivalent uniform cylinder), and
  M3C2's level of detection ``lod = 1.96·(√(spread₁²/n₁ + spread₂²/n₂) + registration_error)``;
  ``significant = |distance| > lod``. The registration error is measured on the stable part
  of the places unless given (:mod:`sdp.distance._level`: M3C2's ``reg = 0`` promises 5 % and
  gives 56–83 % on static real pairs).

Scales: a Gaussian of σ gives as many effective points as a disk of radius 2σ, so the
projection scale ``d`` (M3C2's cylinder *diameter*) is ``4σ_p`` and the normal scale ``D``
(the normal sphere's diameter) is ``4σ_n``. With ``"auto"``, σ_p is the density kernel's own σ
(σ = 1.5 × the 90th percentile of the 3rd-neighbour spacing, :func:`sdp.auto_voxel_size`), so a
cylinder holds about 28 points of a surface sampled like the cloud; ``D = 2d``, enlarged to
20× the roughness found at that scale (Lague et al.'s rule that the normal scale be 20–25× the
roughness, so that roughness does not tilt the normals) up to ``4d``. CloudCompare's M3C2
plugin has a "Guess params" button and advises reading the article before trusting it; here
the guess is the spacing the density kernel already measures, checked by Lague's roughness rule
(the scales used are in the summary).

The binary change masks of :func:`sdp.detect_changes` and this distance agree where both apply:
a current point is "appeared" when the reference's density at it is below h. For a reference
surface of peak density G₀ at distance δ along the normal, G_ref ≈ G₀·exp(−δ²/2s²) with
s² = σ² + spread², so the point is appeared when ``|δ| > s·√(2 ln(G₀/h))``: about 2σ on a
plane sampled as densely as the automatic σ assumes (``benchmarks/bench_distance.py`` moves a
plane step by step: none appeared at 1.5σ, all at 2.5σ, the formula said 2.1σ). G₀ grows with the
surface's sampling density, and the threshold with it: a box sampled four times as densely as the
room around it appears from about 3.5σ (an exploratory run: 0 % of its face at 3σ, 77 % at 3.5σ).

In tiles (:func:`sdp.distances_tiled`, on the buckets and Dask session of :mod:`sdp.scale._tiles`) each
tile measures its own reference points from buckets with a halo of the longest search plus the
cylinder's and the normal's reach and whole cells (:func:`tile_halo`); core points just outside
the tile are measured too, so that the cells whose points share a normal are whole, and the
cells start at the whole reference's corner: the numbers equal the in-memory ones.

References
----------
.. [1] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
   terrestrial laser scanner: application to the Rangitikei canyon (N-Z)", ISPRS Journal of
   Photogrammetry and Remote Sensing 82 (2013) 10–26.
.. [2] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
   Comparison and Applications" (the Gaussian kernel, σ = 2 voxels).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numba as nb
import numpy as np
import numpy.typing as npt

from .._core._cells import BITS, MAX_INDEX
from .._core._kdtree import k_nearest
from .._core._memory import check_memory
from .._core._memory import memory_limit as grid_memory_limit
from .._core._points import as_points
from .._core._validate import auto_or_nonnegative, auto_or_positive, check_orientation, direction
from ..change._visibility import resolve_sensor_origins, scanner_of_points
from ..defaults import DEFAULTS
from ..errors import InvalidOptionError, InvalidPointsError
from ..fields._spacing import resolve_lattice
from ..options import Cylinder, as_options
from ._cells import CELL, DENSE_CELLS, NORMAL_REACH, RADIUS, CellLists, cell_moments
from ._level import with_level
from ._seen import front_start, without_unseen

__all__ = ["Distances", "distances", "search_reach", "cells_below", "normal_sigma", "tile_halo", "DISTANCE_FIELDS"]

#: The per-point outputs, in the order files store them.
DISTANCE_FIELDS = ("distance", "lod", "significant", "n1", "n2", "spread1", "spread2",
                   "normal_x", "normal_y", "normal_z")

_ROUGHNESS_RATIO = 20.0  # Lague et al.: normal scale ≥ 20–25 × the roughness
_MAX_NORMAL_FACTOR = 4.0  # the roughness rule may enlarge D up to this many projection scales
_HALF_DISC = math.sqrt(2.0 / math.pi)  # a half-disc's weighted centroid from the axis, in σ_p (off_axis)
#: The least level of detection per unit of the core point's coordinates: 2⁻⁴⁶, 64 float64 roundings
#: of them (the offsets are means of differences of coordinates that large: two noiseless scans of
#: one plane at UTM's 5e6 m differ by 5e-10 m, half a rounding); 71 nm there.
_RESOLUTION = 2.0**-46



@dataclass
class Distances:
    """Per core point: how far the current lies from the reference along the normal, and whether
    that is more than the noise (see :func:`distances`).

    Attributes
    ----------
    core_points : ndarray (m, 3) float64
        Where the distances were measured.
    distance : ndarray (m,) float64
        Signed distance ``mean₂ − mean₁`` along ``normal``; NaN (not comparable) where no normal
        could be fitted (fewer than three reference points within ``normal_scale / 2``), where an
        epoch has fewer than two effective points in the longest cylinder or less weight than two
        points on its rim (:mod:`sdp.distance._seen`), where its sensor could not see the place
        (``not_seen``), or where the current's surface lies off the cylinder's axis (``off_axis``).
    lod : ndarray (m,) float64
        Level of detection at 95 % (M3C2's LoD95), NaN where ``distance`` is.
    significant : ndarray (m,) bool
        ``|distance| > lod`` (False where not comparable).
    n1, n2 : ndarray (m,) float64
        Effective numbers of reference and current points, ``(Σw)²/Σw²``.
    spread1, spread2 : ndarray (m,) float64
        Weighted standard deviation of the epochs' points along the normal.
    normal : ndarray (m, 3) float64
        Unit normals, oriented as described in :func:`distances`.
    level : ndarray (m,) int8
        0: both epochs answered in the cylinder at the core point; 1: one was found farther along
        the normal; -1: no distance.
    projection_scale, normal_scale, max_distance, registration_error : float
        The parameters used (M3C2's terms: diameters d and D, the cylinder's half-length, ``reg``).
    registration_source : str
        Where ``registration_error`` came from: ``"given"``; with ``registration_error="auto"``,
        ``"measured on the stable part"``, or ``"M3C2's 0: fewer than 100 stable places"``.
    not_seen : int
        Core points without a distance because an epoch was found only farther along the normal
        and its sensor could not see the core point (:mod:`sdp.distance._seen`).
    off_axis : ndarray (m,) bool or None
        Core points without a distance because the current's surface only touches the cylinder
        off its axis (at its rim: a door swung open inside its frame; :func:`off_axis`): its
        weighted centroid across the axis lies farther from the reference's than a half-disc's
        (0.80σ_p) plus 1.96 times their sampling noise. None: not tested (an archive's reference that did not keep its centroid).
    orientation : str
        How the normals were oriented.
    timings : dict of str to float
        Seconds per step.
    tiles : int
        Tiles the work was cut into (:func:`sdp.distances_tiled`); 0: in memory.
    mean1 : ndarray (m,) float64 or None
        Offset of the reference's weighted mean from the core point along ``normal`` (where
        the reference surface lies): a point's own distance to it is ``(p − core)·normal −
        mean1`` (:mod:`sdp.distance._noise`); None in tiles.
    """

    core_points: np.ndarray
    distance: np.ndarray
    lod: np.ndarray
    significant: np.ndarray
    n1: np.ndarray
    n2: np.ndarray
    spread1: np.ndarray
    spread2: np.ndarray
    normal: np.ndarray
    level: np.ndarray
    projection_scale: float
    normal_scale: float
    max_distance: float
    registration_error: float
    orientation: str
    timings: dict = field(default_factory=dict)
    tiles: int = 0
    mean1: np.ndarray | None = field(default=None, repr=False)
    registration_source: str = "given"
    not_seen: int = 0
    off_axis: np.ndarray | None = field(default=None, repr=False)

    @property
    def comparable(self) -> np.ndarray:
        """Core points with a distance (both epochs have points in the cylinder)."""
        return np.isfinite(self.distance)

    def fields(self) -> dict[str, np.ndarray]:
        """The per-point outputs by name (:data:`DISTANCE_FIELDS`), as files store them."""
        out = {name: getattr(self, name) for name in DISTANCE_FIELDS[:7]}
        out["significant"] = self.significant.astype(np.uint8)
        for i, axis in enumerate("xyz"):
            out[f"normal_{axis}"] = self.normal[:, i]
        return out

    def summary(self) -> dict:
        """Counts, the distribution of the distances and the parameters, as plain numbers."""
        ok = self.comparable
        d, sig = self.distance[ok], self.significant[ok]
        # rows given without a position (NaN, Inf) are counted as dropped, not as core points
        blank = int((~np.isfinite(self.core_points).all(axis=1)).sum()) if self.core_points.size else 0

        def q(values, p):
            return float(np.quantile(values, p)) if values.size else float("nan")

        return {
            "core_points": int(len(self.distance)) - blank,
            "core_points_dropped": blank,
            "comparable": int(ok.sum()),
            "not_comparable": int((~ok).sum()) - blank,
            "not_seen": self.not_seen,
            "off_axis": 0 if self.off_axis is None else int(self.off_axis.sum()),
            "no_normal": int((np.isnan(self.normal).any(axis=1) & np.isfinite(self.core_points).all(axis=1)).sum()),
            "significant": int(sig.sum()),
            "significant_positive": int((sig & (d > 0)).sum()),
            "significant_negative": int((sig & (d < 0)).sum()),
            "median_distance": q(d, 0.5),
            "median_abs_distance": q(np.abs(d), 0.5),
            "distance_p05": q(d, 0.05),
            "distance_p95": q(d, 0.95),
            "median_lod": q(self.lod[ok], 0.5),
            "projection_scale": self.projection_scale,
            "normal_scale": self.normal_scale,
            "max_distance": self.max_distance,
            "registration_error": self.registration_error,
            "registration_source": self.registration_source,
            "orientation": self.orientation,
            "tiles": self.tiles,
            "timings": {k: round(v, 4) for k, v in self.timings.items()},
        }


def distances(reference, current, *, core_points=None, cylinder: Cylinder | None = None,
              registration_error: float | str = DEFAULTS.registration_error,
              orientation: npt.ArrayLike | None = None, sensor_origin=DEFAULTS.sensor_origin,
              memory_limit=None, corner: npt.ArrayLike | None = None) -> Distances:
    """Signed distance from the reference to the current along the local normal, with M3C2's
    level of detection, at every core point.

    Parameters
    ----------
    reference, current : array_like (n, 3) or :class:`sdp.io.Cloud`
        The two epochs, in one frame (align them first: :func:`sdp.align`).
    core_points : array_like (m, 3), Cloud, ``"reference"`` or ``"current"``, optional
        Where to measure; default every reference point (M3C2's epoch 1). Rows holding NaN or
        Inf stay in the results, without a distance (NaN, ``level`` -1).
    cylinder : Cylinder, optional
        M3C2's scales (:class:`sdp.Cylinder`, world units): the projection scale ``d`` (the
        cylinder's diameter; its Gaussian has σ_p = d/4; ``"auto"``: the density kernel's σ from
        the point spacing), the normal scale ``D`` (diameter, σ_n = D/4; ``"auto"``: 2d,
        enlarged to 20× the roughness at that scale, at most 4d) and how far along the normal
        an epoch is looked for (``"auto"``: 48σ_p = 12d).
    registration_error : float or "auto"
        Added to the level of detection before the 1.96 factor (M3C2's ``reg``), world units,
        e.g. the residual of an alignment on ground known to be stable. ``"auto"`` (default):
        measured on the data, the smallest for which at most 5 % of the stable part of the
        core points (distances within 2σ_p) lies beyond the level (:mod:`sdp.distance._level`; a
        shift of the whole scene by less than 2σ_p reads as a registration error where the scene
        is alike throughout, as changed on its smooth parts where the rest is rough).
    orientation : array_like (3,), optional
        Direction the normals point to where the sensor is unknown; default +z.
    sensor_origin : "auto", None or array_like
        As :func:`sdp.detect_changes`: where known, normals point towards the sensor of the
        core points' epoch (the reference's for the default core points).
    memory_limit : int, str or None
        As :func:`sdp.detect_changes` (``$SDP_MEMORY_LIMIT``, else 4 GiB): checked against an
        estimate of what the sorted clouds, their cells and the outputs need, before any work.
    corner : array_like (3,), optional
        Where the cells start: a point below every reference and core point in x, y and z
        (default: just below their lowest corner); the current's cells start whole cells lower
        where it reaches lower. Parts of a larger cloud given the same corner (the tiles of
        :func:`sdp.distances_tiled`), and epochs against one reference (:func:`sdp.series`),
        are cut into the same cells.

    Returns
    -------
    Distances

    Raises
    ------
    InvalidPointsError, InvalidOptionError
        Bad clouds or options (checked before any work).
    GridTooLargeError
        The work would need more than the memory limit.

    References
    ----------
    .. [1] Lague et al. 2013 (M3C2, the level of detection); Vieira et al. (the kernel).

    Examples
    --------
    >>> import numpy as np, sdp
    >>> rng = np.random.default_rng(0)
    >>> ground = np.c_[rng.uniform(0, 10, (20000, 2)), 0.01 * rng.standard_normal(20000)]
    >>> raised = ground.copy()
    >>> raised[np.hypot(*(ground[:, :2] - 5).T) < 2, 2] += 0.05  # a disc raised 5 cm, the rest stable
    >>> d = sdp.distances(ground, raised, cylinder=sdp.Cylinder(projection_scale=0.5))
    >>> disc = np.hypot(*(d.core_points[:, :2] - 5).T) < 1.5
    >>> print(round(float(np.median(d.distance[disc])), 3), bool(d.significant[disc].mean() > 0.99))
    0.05 True

    A whole scene moved reads as a registration error (``"auto"``); give 0 for M3C2's level:

    >>> shifted = sdp.distances(ground, ground + [0, 0, 0.05], cylinder=sdp.Cylinder(projection_scale=0.5),
    ...                         registration_error=0)
    >>> bool(shifted.significant.mean() > 0.99)
    True
    """
    t0 = time.perf_counter()
    ref, cur = as_points(reference, name="reference"), as_points(current, name="current")
    for pts, name in ((ref, "reference"), (cur, "current")):
        if len(pts.xyz) < 3:
            raise InvalidPointsError(f"the {name} has {len(pts.xyz)} point(s): a surface normal and a spread need "
                                     "at least 3")
    cylinder = as_options(Cylinder, cylinder, "cylinder")
    d_opt = auto_or_positive("projection_scale", cylinder.projection_scale)
    D_opt = auto_or_positive("normal_scale", cylinder.normal_scale)
    L_opt = auto_or_positive("max_distance", cylinder.max_distance)
    reg = auto_or_nonnegative("registration_error", registration_error)
    grid_memory_limit(memory_limit)  # readable and positive, before any work
    towards = direction("orientation", DEFAULTS.orientation if orientation is None else orientation)
    origins = resolve_sensor_origins(sensor_origin, reference, current)
    for cloud, o in zip((reference, current), origins):  # several scanners need each point's, before any work
        if np.ndim(o) == 2:
            scanner_of_points(cloud, o, len(getattr(cloud, "xyz", cloud)))
    # core points given with NaN rows (an array, or an epoch's own rows): which rows were measured,
    # so that the results keep one row per row given, whichever way the core points were named
    given_rows = None
    if core_points is None or (isinstance(core_points, str) and core_points == "reference"):
        core, sensor, given_rows = ref.xyz, _sensor_per_point(origins[0], reference, ref.xyz), ref.finite
    elif isinstance(core_points, str):
        if core_points != "current":
            raise InvalidOptionError(f"core_points must be points, 'reference' or 'current', got {core_points!r}")
        core, sensor, given_rows = cur.xyz, _sensor_per_point(origins[1], current, cur.xyz), cur.finite
    else:
        given = as_points(core_points, name="core points")
        core, given_rows = given.xyz, given.finite
        sensor = _sensor_per_point(origins[0], reference, ref.xyz, core)
    # the core points' own sensor, given or read from their file ("auto"), sets their normals
    from_file = isinstance(sensor_origin, str) and sensor_origin == "auto"
    if orientation is not None and sensor is not None and from_file:
        raise InvalidOptionError("orientation points the normals where no sensor is known, and the core points' "
                                 "file records theirs (a PCD's VIEWPOINT, an E57's poses), which the normals face: "
                                 "give sensor_origin=None (--sensor-origin none) to orient them by orientation")
    check_orientation(orientation, sensor_given=sensor is not None and not from_file)
    timings = {"validate": time.perf_counter() - t0}

    t = time.perf_counter()
    sigma_p = _projection_sigma(ref, cur, d_opt)
    max_half = search_reach(L_opt, 4.0 * sigma_p)
    # the reference's cells start at its corner, the current's whole cells lower where it reaches lower:
    # every epoch measured against one reference is cut into the same cells (sdp.series equals this)
    lo = cell_corner(np.minimum(ref.lo, core.min(axis=0)), corner)
    cur_lo = cells_below(lo, cur.lo, CELL * sigma_p)
    hi = np.maximum(np.maximum(ref.hi, cur.hi), core.max(axis=0))
    clouds = np.maximum(ref.hi, cur.hi) - np.minimum(ref.lo, cur.lo)
    if np.max(hi - lo) / (CELL * sigma_p) >= MAX_INDEX - 4 > np.max(clouds) / (CELL * sigma_p):
        raise InvalidPointsError(f"the core points reach {np.max(hi - lo):g} units across, the clouds "
                                 f"{np.max(clouds):g}: give core points on or near the clouds")
    # per cloud point: a sorted copy, its permutation and cell (8 × 5 B) and its cell's moments
    # at two cell sizes (at most 2 × 80 B); per core point: its copy, normal and results (≈ 30 × 8 B);
    # the dense cell tables (4 B per cell of the box, for the cells of three clouds)
    box_cells = min(float(np.prod((hi - lo) // (CELL * sigma_p) + 1)), DENSE_CELLS)
    need = 200.0 * (len(ref.xyz) + len(cur.xyz)) + 240.0 * len(core) + 3 * 4.0 * box_cells
    check_memory(need, f"distances between {len(ref.xyz):,} and {len(cur.xyz):,} points at {len(core):,} core points",
                 memory_limit, advice="measure at fewer core points (core_points=), or compare in tiles")
    timings["scales"] = time.perf_counter() - t

    if D_opt != "auto" and np.max(hi - lo) / (D_opt / 4.0) >= MAX_INDEX - 4:  # its cells are a quarter of it
        raise InvalidOptionError(f"the clouds span {np.max(hi - lo):g} units, more than 2**{BITS} cells of "
                                 f"normal_scale / 4 = {D_opt / 4:g}: give a larger normal_scale, or compare in tiles")
    lists = CellLists(lo, hi)
    cur_lists = lists if np.array_equal(cur_lo, lo) else CellLists(cur_lo, hi)
    t = time.perf_counter()
    # queries in cell order: neighbouring queries then read the same cells while they are cached,
    # and the core points of a cell share one normal, taken at their centroid
    order, starts, core_sorted, centroids = _core_cells(lists, core, sigma_p)
    per_cell = np.diff(starts)
    sigma_n = normal_sigma(lists, ref.xyz, centroids, sigma_p, D_opt)
    normal, _ = lists.normals(ref.xyz, centroids, sigma_n)
    missing = ~np.isfinite(normal[:, 0])
    if missing.any():  # no reference point near: the current's surface gives the direction
        normal[missing] = cur_lists.normals(cur.xyz, centroids[missing], sigma_n)[0]
    normal = np.repeat(normal, per_cell, axis=0)
    if sensor is not None:  # one position (3,), or each core point's own scanner (m, 3)
        facing = (sensor[order] if sensor.ndim == 2 else sensor[None, :]) - core_sorted
        flip = np.einsum("ij,ij->i", normal, facing) < 0
        how = "towards the sensor" if sensor.ndim == 1 else "towards each point's scanner"
    else:
        flip = normal @ towards < 0
        how = f"towards ({towards[0]:g}, {towards[1]:g}, {towards[2]:g})"
    normal[flip] *= -1.0
    timings["normals"] = time.perf_counter() - t

    t = time.perf_counter()
    stats = [lists.cylinder(ref.xyz, core_sorted, normal, sigma_p, max_half),
             cur_lists.cylinder(cur.xyz, core_sorted, normal, sigma_p, max_half)]
    timings["cylinders"] = time.perf_counter() - t

    reach = max(max_half, 3.0 * sigma_p)
    m = len(order)
    dist, lod, n1, n2, s1, s2 = (np.empty(m) for _ in range(6))
    out_normal, level, off = np.empty((m, 3)), np.empty(m, np.int8), np.empty(m, np.bool_)
    _results(order, stats[0], stats[1], normal, 0.0 if reg == "auto" else reg, reach, sigma_p, core_sorted, dist, lod,
             n1, n2, s1, s2, out_normal, level, off)
    normal = out_normal
    mean1 = np.full(m, np.nan)
    mean1[order] = stats[0][0]
    # a copy: core is the caller's own array (the reference, or core_points=) where it was finite float64,
    # and the results are the caller's to edit (shift to a local datum) without editing the input
    d = Distances(core_points=core.copy(), distance=dist, lod=lod, significant=np.abs(dist) > lod,
                  n1=n1, n2=n2, spread1=s1, spread2=s2, normal=normal, level=level,
                  projection_scale=4.0 * sigma_p, normal_scale=4.0 * sigma_n, max_distance=reach,
                  registration_error=0.0 if reg == "auto" else reg, orientation=how, timings=timings, mean1=mean1,
                  off_axis=off)
    t = time.perf_counter()
    # where an epoch's sensor could not see the place measured, there is no distance
    # (sdp.distance._seen); the reference saw its own points
    facing = sensor is not None  # the normals face the core points' own sensor
    free = None
    if facing and origins[1] is not None:  # what the reference held in front, where the current was found so
        free = np.full(m, np.nan)
        ahead = np.flatnonzero((d.level == 1) & (mean1 + d.distance > 0))
        if ahead.size:
            free[ahead] = lists.free_ahead(ref.xyz, np.ascontiguousarray(core[ahead]),
                                           np.ascontiguousarray(d.normal[ahead]), sigma_p,
                                           front_start(mean1[ahead], sigma_p), max_half)
    d = without_unseen(d, current, cur.xyz, origins[1], sigma=sigma_p, along=mean1 + d.distance, facing=facing,
                       free_ahead=free)
    if core is not ref.xyz:
        d = without_unseen(d, reference, ref.xyz, origins[0], sigma=sigma_p, along=mean1, facing=facing)
    timings["not_seen"] = time.perf_counter() - t
    d = with_level(d, reg)
    if given_rows is not None:
        d = _on_given_rows(d, given_rows)
    timings["total"] = time.perf_counter() - t0
    return d


def _on_given_rows(d: Distances, rows: np.ndarray) -> Distances:
    """``d`` measured at the finite core points ``rows`` (mask) of those given, spread over every
    row given: a row holding NaN or Inf gets no distance (NaN, level -1), so that results stay
    aligned with the caller's core points."""
    import dataclasses

    def spread(values, fill):
        out = np.full((len(rows),) + values.shape[1:], fill, values.dtype)
        out[rows] = values
        return out

    arrays = {name: spread(getattr(d, name), np.nan) for name in ("core_points", "distance", "lod", "n1", "n2",
                                                                  "spread1", "spread2", "normal")}
    return dataclasses.replace(d, **arrays, significant=spread(d.significant, False), level=spread(d.level, -1),
                               mean1=None if d.mean1 is None else spread(d.mean1, np.nan),
                               off_axis=None if d.off_axis is None else spread(d.off_axis, False))


def auto_scales(reference, current, *, cylinder: Cylinder | None = None) -> tuple[float, float]:
    """(projection scale, normal scale) as :func:`distances` chooses them at the reference's own
    points (its default core points), ``"auto"`` parts measured, given ones kept: what the tiles
    take from the first slice of each cloud, so that where that slice is the whole cloud they
    equal the run in memory."""
    ref, cur = as_points(reference, name="reference"), as_points(current, name="current")
    cylinder = as_options(Cylinder, cylinder, "cylinder")
    d_opt = auto_or_positive("projection_scale", cylinder.projection_scale)
    D_opt = auto_or_positive("normal_scale", cylinder.normal_scale)
    sigma_p = _projection_sigma(ref, cur, d_opt)
    lists = CellLists(cell_corner(ref.lo), np.maximum(ref.hi, cur.hi))
    centroids = _core_cells(lists, ref.xyz, sigma_p)[3]
    return 4.0 * sigma_p, 4.0 * normal_sigma(lists, ref.xyz, centroids, sigma_p, D_opt)


def _projection_sigma(ref, cur, projection_scale) -> float:
    """σ_p: a quarter of ``projection_scale``, or for ``"auto"`` the density kernel's σ."""
    if projection_scale != "auto":
        return projection_scale / 4.0
    voxel, sigma_voxels = resolve_lattice([ref, cur], k=DEFAULTS.k)
    return sigma_voxels * voxel


def _core_cells(lists: "CellLists", core: np.ndarray, sigma_p: float):
    """(permutation into cell order, each cell's first row, the core points in that order, each
    cell's centroid) of the core points in the cylinders' cells."""
    order, starts = lists.order(core, CELL * sigma_p)
    core_sorted = lists.get(core, CELL * sigma_p)[0]
    return order, starts, core_sorted, np.ascontiguousarray(cell_moments(core_sorted, starts)[:, 1:4])


def cells_below(corner: np.ndarray, lowest: np.ndarray, cell: float) -> np.ndarray:
    """``corner`` moved down by whole cells of ``cell`` until it lies below ``lowest``: the same
    cells, reaching lower."""
    shift = np.ceil(np.maximum(np.asarray(corner) - np.asarray(lowest) + 1e-9, 0.0) / cell)
    return corner - shift * cell


def cell_corner(lowest: np.ndarray, corner=None) -> np.ndarray:
    """Where the cells start: just below ``lowest`` (the reference's and the core points' lowest
    corner), or at ``corner`` if given (finite and below it: a tile gives the whole cloud's)."""
    lo = np.asarray(lowest, np.float64) - 1e-9
    if corner is None:
        return lo
    try:
        given = np.asarray(corner, np.float64)
    except (TypeError, ValueError):
        given = np.full(1, np.nan)
    if given.shape != (3,):
        raise InvalidOptionError(f"corner must be three numbers x, y, z, got {corner!r}")
    corner = given
    if not (np.isfinite(corner).all() and (corner <= lo).all()):
        raise InvalidOptionError(f"corner {corner} must be finite and below every reference and core point "
                                 f"(lowest {lo})")
    return corner


def search_reach(max_distance: float | str, projection_scale: float) -> float:
    """How far along the normal an epoch is looked for: ``max_distance``, or for ``"auto"``
    12 projection scales (48σ_p)."""
    return 12.0 * projection_scale if max_distance == "auto" else float(max_distance)


def tile_halo(projection_scale: float, normal_scale: float, reach: float) -> tuple[float, float]:
    """(halo, margin) of a tile that measures its own core points as the whole cloud would:
    ``margin``: core points this close to the tile are measured too, so that the cells whose
    points share a normal are whole; ``halo``: every point a query of those reads (the search
    along the normal, the cylinder's radius, the normal's reach) plus whole cells around them."""
    sigma_p, sigma_n = projection_scale / 4.0, normal_scale / 4.0
    margin = 2.0 * CELL * sigma_p
    cell = max(CELL * sigma_p, sigma_n)
    halo = (max(reach, RADIUS * sigma_p) + RADIUS * sigma_p + NORMAL_REACH * sigma_n
            + 4.0 * cell * math.sqrt(3.0) + margin)
    return halo, margin


def normal_sigma(lists: "CellLists", ref_xyz: np.ndarray, centroids: np.ndarray, sigma_p: float, normal_scale) -> float:
    """σ of the normals' Gaussian: a quarter of ``normal_scale``, or with ``"auto"`` twice the
    projection's σ, widened on rough surfaces (the reference's roughness at a sample of the core
    cells' centroids) up to :data:`_MAX_NORMAL_FACTOR` × σ_p."""
    if normal_scale != "auto":
        return normal_scale / 4.0
    sigma_n = 2.0 * sigma_p
    sample = centroids[:: max(1, len(centroids) // 2000)]
    _, rough = lists.normals(ref_xyz, sample, sigma_n)
    rough = rough[np.isfinite(rough)]
    if rough.size:
        sigma_n = min(max(sigma_n, _ROUGHNESS_RATIO * float(np.median(rough)) / 4.0), _MAX_NORMAL_FACTOR * sigma_p)
    return sigma_n


@nb.njit(cache=True, inline="always")
def off_axis(l1, v1, l2, v2, sigma):
    """Whether the current's surface only touches the cylinder off its axis (M3C2's step edge):
    its weighted centroid across the axis, ``l2`` (3), lies farther than
    ``√(2/π)·σ_p + 1.96·√(v₁ + v₂)`` from the reference's, ``l1``.

    M3C2 assumes that each epoch's surface crosses the cylinder's axis. A surface that does, sampled
    evenly, has its centroid across the axis at the axis up to its sampling noise: the variance of
    a weighted mean position, ``v = (Σw|a − L|² / Σw) / n_eff`` with ``n_eff = (Σw)² / Σw²`` (Kish's
    effective count; summed over both directions across), measured on the points, so that a clumped
    or lined sampling widens it. The two epochs' centroids are independent, their
    difference has variance ``v₁ + v₂``, and 1.96·√(v₁ + v₂) bounds its length at 95 % or more
    whatever its shape (exactly, all of it along one direction; spread evenly, the 95 % point of
    its length is 1.73·√(v₁ + v₂)). The epochs are compared with each other, not with the axis: a
    surface cut by an edge (a table's) gives both epochs the same part of the disc and the same
    centroid, and stays measured. Beyond the noise, √(2/π)·σ_p = 0.80σ_p, the centroid of a
    half-disc under the Gaussian weight: a surface ending at ``a`` past the axis has its centroid
    λ(a/σ_p)·σ_p out (λ the inverse Mills ratio: 0.80 at a = 0, 1.0 at 0.3σ_p, 2.4 at 2σ_p),
    so the bound is where the current's surface stops reaching the axis: one that only touches the
    rim (a door frame around a door swung open, a pallet's sides around the floor it stands on)
    lies 2σ_p or more out, and a reference half-disc whose other half the current fills (0.80σ_p
    plus noise) stays measured. Within about σ_p of a step the cylinder straddles it at its own
    resolution: a side along the normal at ``a`` pulls the centroid in to ``a`` (a pallet's side is
    caught from 1.3σ_p in the tests' scene, a floor's edge alone from about 0.25σ_p). NaN (an old
    archive's reference, which did not keep its centroid) never counts as off the axis."""
    dx, dy, dz = l2[0] - l1[0], l2[1] - l1[1], l2[2] - l1[2]
    bound = _HALF_DISC * sigma + 1.96 * math.sqrt(v1 + v2)
    return dx * dx + dy * dy + dz * dz > bound * bound


@nb.njit(cache=True, nogil=True, parallel=True)
def _results(order, ref, cur, normal, reg, reach, sigma, core, dist, lod, n1, n2, s1, s2, out_normal, level, off):
    """The outputs, back in the core points' input order (``order``: sorted row → input row), in
    one pass: distance = mean₂ − mean₁ and M3C2's level of detection; NaN (level -1) where an
    epoch had no points or the two lie farther apart than ``reach``, and where the current's
    surface lies off the cylinder's axis (:func:`off_axis`, ``off`` True there). The level is at
    least what the arithmetic resolves at the core point's coordinates (``core``, sorted as the
    stats: :data:`_RESOLUTION` of their magnitude), so that noiseless data (a level of 0) does not
    call rounding significant."""
    m1, sp1, c1, k1, l1, v1 = ref
    m2, sp2, c2, k2, l2, v2 = cur
    for i in nb.prange(order.shape[0]):
        j = order[i]
        d = m2[i] - m1[i]
        n1[j], n2[j], s1[j], s2[j] = c1[i], c2[i], sp1[i], sp2[i]
        for a in range(3):
            out_normal[j, a] = normal[i, a]
        near = abs(d) <= reach and np.isfinite(normal[i, 0])
        off[j] = near and off_axis(l1[i], v1[i], l2[i], v2[i], sigma)
        if near and not off[j]:
            dist[j] = d
            size = max(1.0, abs(core[i, 0]), abs(core[i, 1]), abs(core[i, 2]))
            lod[j] = max(1.96 * (math.sqrt(sp1[i] ** 2 / c1[i] + sp2[i] ** 2 / c2[i]) + reg), _RESOLUTION * size)
            level[j] = max(k1[i], k2[i])
        else:
            dist[j] = lod[j] = np.nan
            level[j] = -1


def _sensor_per_point(origins, cloud, xyz: np.ndarray, core: np.ndarray | None = None) -> np.ndarray | None:
    """The sensor the normals face: one position (3,), or with several scanners (k, 3) each
    point's own (m, 3), the scanner of ``cloud``'s points (:attr:`sdp.Cloud.scan`), or for other
    ``core`` points that of their nearest point of ``cloud``."""
    if origins is None or np.ndim(origins) == 1:
        return None if origins is None else np.asarray(origins, np.float64)
    scan = scanner_of_points(cloud, origins, len(xyz))
    if core is not None:
        scan = scan[k_nearest(xyz, core, 1)[:, 0]]
    return np.asarray(origins, np.float64)[scan]
