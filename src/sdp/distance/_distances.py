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
- **Moments on cells**: each epoch's points are summed once, in O(n), into cubic cells of
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

from .._core._cells import BITS, MAX_INDEX, hashed_sort, table_row
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
from ._level import with_level
from ._seen import without_unseen

__all__ = ["Distances", "distances", "search_reach", "cells_below", "normal_sigma", "tile_halo", "DISTANCE_FIELDS"]

#: The per-point outputs, in the order files store them.
DISTANCE_FIELDS = ("distance", "lod", "significant", "n1", "n2", "spread1", "spread2",
                   "normal_x", "normal_y", "normal_z")

_MIN_POINTS = 2.0  # effective points an epoch needs in the cylinder: a spread needs two
# and as much weight as two points on the rim of M3C2's cylinder (radius d/2 = 2σ_p): a few points
# near the cut (3σ_p) weigh alike, so their effective count is full while they tell where the
# surface lies off the axis, not at it (on a normal tilted by 1°, 2 cm at 1 m)
_MIN_WEIGHT = 2.0 * math.exp(-2.0)
_NORMAL_REACH = 2.0  # normal kernels cut at 2σ_n: the covariance's direction is settled by then
_ROUGHNESS_RATIO = 20.0  # Lague et al.: normal scale ≥ 20–25 × the roughness
_MAX_NORMAL_FACTOR = 4.0  # the roughness rule may enlarge D up to this many projection scales
_DENSE_CELLS = 2**25  # boxes of up to this many cells are sorted by counting (4 bytes per cell)
_RADIUS = 3.0  # cylinder cut, in σ_p: the density kernel's truncation
_CELL = 1.5  # cells of the cylinders' moments, in σ_p


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
        points on its rim (:mod:`sdp.distance._seen`), or where its sensor could not see the place
        (``not_seen``).
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
    towards = np.array([0.0, 0.0, 1.0]) if orientation is None else direction("orientation", orientation)
    origins = resolve_sensor_origins(sensor_origin, reference, current)
    for cloud, o in zip((reference, current), origins):  # several scanners need each point's, before any work
        if np.ndim(o) == 2:
            scanner_of_points(cloud, o, len(getattr(cloud, "xyz", cloud)))
    given_rows = None  # core points given with NaN rows: which rows were measured
    if core_points is None or (isinstance(core_points, str) and core_points == "reference"):
        core, sensor = ref.xyz, _sensor_per_point(origins[0], reference, ref.xyz)
    elif isinstance(core_points, str):
        if core_points != "current":
            raise InvalidOptionError(f"core_points must be points, 'reference' or 'current', got {core_points!r}")
        core, sensor = cur.xyz, _sensor_per_point(origins[1], current, cur.xyz)
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
    cur_lo = cells_below(lo, cur.lo, _CELL * sigma_p)
    hi = np.maximum(np.maximum(ref.hi, cur.hi), core.max(axis=0))
    clouds = np.maximum(ref.hi, cur.hi) - np.minimum(ref.lo, cur.lo)
    if np.max(hi - lo) / (_CELL * sigma_p) >= MAX_INDEX - 4 > np.max(clouds) / (_CELL * sigma_p):
        raise InvalidPointsError(f"the core points reach {np.max(hi - lo):g} units across, the clouds "
                                 f"{np.max(clouds):g}: give core points on or near the clouds")
    # per cloud point: a sorted copy, its permutation and cell (8 × 5 B) and its cell's moments
    # at two cell sizes (at most 2 × 80 B); per core point: its copy, normal and results (≈ 30 × 8 B);
    # the dense cell tables (4 B per cell of the box, for the cells of three clouds)
    box_cells = min(float(np.prod((hi - lo) // (_CELL * sigma_p) + 1)), _DENSE_CELLS)
    need = 200.0 * (len(ref.xyz) + len(cur.xyz)) + 240.0 * len(core) + 3 * 4.0 * box_cells
    check_memory(need, f"distances between {len(ref.xyz):,} and {len(cur.xyz):,} points at {len(core):,} core points",
                 memory_limit, advice="measure at fewer core points (core_points=), or compare in tiles")
    timings["scales"] = time.perf_counter() - t

    if D_opt != "auto" and np.max(hi - lo) / (D_opt / 4.0) >= MAX_INDEX - 4:  # its cells are a quarter of it
        raise InvalidOptionError(f"the clouds span {np.max(hi - lo):g} units, more than 2**{BITS} cells of "
                                 f"normal_scale / 4 = {D_opt / 4:g}: give a larger normal_scale, or compare in tiles")
    lists = _CellLists(lo, hi)
    cur_lists = lists if np.array_equal(cur_lo, lo) else _CellLists(cur_lo, hi)
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
    out_normal, level = np.empty((m, 3)), np.empty(m, np.int8)
    _results(order, stats[0], stats[1], normal, 0.0 if reg == "auto" else reg, reach, dist, lod, n1, n2, s1, s2,
             out_normal, level)
    normal = out_normal
    mean1 = np.full(m, np.nan)
    mean1[order] = stats[0][0]
    d = Distances(core_points=core, distance=dist, lod=lod, significant=np.abs(dist) > lod,
                  n1=n1, n2=n2, spread1=s1, spread2=s2, normal=normal, level=level,
                  projection_scale=4.0 * sigma_p, normal_scale=4.0 * sigma_n, max_distance=reach,
                  registration_error=0.0 if reg == "auto" else reg, orientation=how, timings=timings, mean1=mean1)
    t = time.perf_counter()
    # where an epoch's sensor could not see the place measured, there is no distance
    # (sdp.distance._seen); the reference saw its own points
    facing = sensor is not None  # the normals face the core points' own sensor
    d = without_unseen(d, current, cur.xyz, origins[1], sigma=sigma_p, along=mean1 + d.distance, facing=facing)
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
                               mean1=None if d.mean1 is None else spread(d.mean1, np.nan))


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
    lists = _CellLists(cell_corner(ref.lo), np.maximum(ref.hi, cur.hi))
    centroids = _core_cells(lists, ref.xyz, sigma_p)[3]
    return 4.0 * sigma_p, 4.0 * normal_sigma(lists, ref.xyz, centroids, sigma_p, D_opt)


def _projection_sigma(ref, cur, projection_scale) -> float:
    """σ_p: a quarter of ``projection_scale``, or for ``"auto"`` the density kernel's σ."""
    if projection_scale != "auto":
        return projection_scale / 4.0
    voxel, sigma_voxels = resolve_lattice([ref, cur], k=DEFAULTS.k)
    return sigma_voxels * voxel


def _core_cells(lists: "_CellLists", core: np.ndarray, sigma_p: float):
    """(permutation into cell order, each cell's first row, the core points in that order, each
    cell's centroid) of the core points in the cylinders' cells."""
    order, starts = lists.order(core, _CELL * sigma_p)
    core_sorted = lists.get(core, _CELL * sigma_p)[0]
    return order, starts, core_sorted, np.ascontiguousarray(_cell_moments(core_sorted, starts)[:, 1:4])


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
    margin = 2.0 * _CELL * sigma_p
    cell = max(_CELL * sigma_p, sigma_n)
    halo = (max(reach, _RADIUS * sigma_p) + _RADIUS * sigma_p + _NORMAL_REACH * sigma_n
            + 4.0 * cell * math.sqrt(3.0) + margin)
    return halo, margin


def normal_sigma(lists: "_CellLists", ref_xyz: np.ndarray, centroids: np.ndarray, sigma_p: float, normal_scale) -> float:
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


class _CellLists:
    """Each cloud's points sorted into cubic cells of one size, built once per (cloud, size)."""

    def __init__(self, lo, hi):
        self.lo = np.asarray(lo, np.float64)
        self.extent = np.asarray(hi, np.float64) - self.lo
        self._cache: dict = {}

    def order(self, xyz, cell):
        """(permutation that sorts ``xyz`` by cell, start of each cell's run in that order)."""
        entry = self.get(xyz, cell)
        return entry[5], entry[1]

    def get(self, xyz: np.ndarray, cell: float, *, point_cells: bool = False):
        """(points sorted by cell, start of each occupied cell's run, cell table, its box of
        cells (the first cell's index, then the box's size) or zeros for a hash table, cell
        size, the sorting permutation).

        A cell's index is floor((p − lo) / cell) in both tables, so the cells do not depend on
        which table holds them; the dense box spans the points' own cells only (a tile of a
        large cloud, whose cells start at the whole cloud's corner, gets a small box).
        ``point_cells``: each point's run is wanted too (:meth:`point_cells`): the counting
        sort writes it as it goes, in order, where a pass afterwards would scatter it."""
        key = (id(xyz), cell)
        if key not in self._cache:
            if np.max(self.extent) / cell >= MAX_INDEX - 4:
                raise InvalidOptionError(f"the clouds span {np.max(self.extent):g} units, more than 2**{BITS} cells "
                                         f"of {cell:g}: give a larger projection_scale, or compare in tiles")
            first, last = _index_box(xyz, self.lo, cell)
            size = last - first + 1
            if np.prod(size.astype(float)) <= _DENSE_CELLS:  # a counting sort over the box of cells
                dims = np.r_[size, first]
                linear = np.empty(len(xyz), np.int32)  # at most 2**25 cells
                _box_cells(xyz, self.lo, cell, dims, linear)
                runs = np.empty(len(xyz) if point_cells else 0, np.int64)
                order, starts, table, ordered = _counting_sort(xyz, linear, int(np.prod(size)), runs)
                if point_cells:
                    self._cache[("cells", *key)] = runs
            else:
                order, starts, table = hashed_sort(xyz, self.lo, cell)
                dims = np.zeros(6, np.int64)
                ordered = _gather(xyz, order)
            self._cache[key] = (ordered, starts, table, dims, cell, order)
        return self._cache[key]

    def point_cells(self, xyz: np.ndarray, cell: float) -> np.ndarray:
        """Each point's cell: its run in :meth:`get`'s order (int64)."""
        key = ("cells", id(xyz), cell)
        if key not in self._cache:
            _, starts, _, _, _, order = self.get(xyz, cell, point_cells=True)
            if key not in self._cache:  # sorted before, or by hashing
                self._cache[key] = _runs_of(order, starts)
        return self._cache[key]

    def normals(self, xyz, queries, sigma, cell=None):
        """(unit normals (m, 3), NaN where fewer than 3 points; roughness = √λ_min).

        From the moments of cells of σ (count, centroid, scatter), each cell weighted by the
        Gaussian at its centroid: a few dozen cells per query instead of hundreds of points,
        and the direction of a covariance does not need each point's own weight. ``cell``:
        cells of another size instead (those of the cylinders, already sorted: no second sort
        where few queries are made)."""
        normal = np.empty((len(queries), 3))
        rough = np.empty(len(queries))
        _normals(*self.moments(xyz, sigma if cell is None else cell), self.lo, np.ascontiguousarray(queries), sigma,
                 _NORMAL_REACH * sigma, normal, rough)
        return normal, rough

    def moments(self, xyz, cell):
        """(one row of count, centroid, scatter per occupied cell of ``xyz``; the cell table, its
        box of cells, the cell size), built once per cloud and cell size."""
        pts, starts, table, rows, cell, _ = self.get(xyz, cell)
        key = ("moments", id(xyz), cell)
        if key not in self._cache:
            self._cache[key] = _cell_moments(pts, starts)
        return self._cache[key], table, rows, cell

    def cylinder(self, xyz, queries, normals, sigma, max_half):
        """(weighted mean offset, spread, effective count, level) of ``xyz`` in the cylinders:
        level 0 around the core point; level 1 around the nearest cell of ``xyz`` on the normal's
        line within ``max_half``, where the first found too few points."""
        half = _RADIUS * sigma
        out = self._cylinders(xyz, queries, normals, sigma, half)
        level = np.where(_enough(out), 0, -1)
        todo = np.flatnonzero(level < 0)
        if todo.size and max_half > half:
            q, n = queries[todo], normals[todo]
            _, _, table, dims, cell, _ = self.get(xyz, _CELL * sigma)
            t = np.empty(todo.size)
            _nearest_along(table, dims, cell, self.lo, q, n, max_half, t)
            found = np.flatnonzero(np.isfinite(t))
            q, n, t = q[found], n[found], t[found]
            for _ in range(2):  # move the cylinder onto the surface found: twice settles it
                fine = self._cylinders(xyz, np.ascontiguousarray(q + t[:, None] * n), n, sigma, half)
                ok = fine[:, 2] >= _MIN_POINTS  # a first cylinder beside the surface moves onto it
                t = np.where(ok, t + np.nan_to_num(fine[:, 0]), t)
            fine[:, 0] = t
            keep = _enough(fine) & (np.abs(t) <= max_half)
            out[todo[found[keep]]] = fine[keep]
            level[todo[found[keep]]] = 1
        out[level < 0, :2] = np.nan
        return out[:, 0], out[:, 1], out[:, 2], level

    def _cylinders(self, xyz, queries, normals, sigma, half):
        """(mean offset, spread, effective count, weight) per cylinder; no mean nor spread
        where too few points answer."""
        out = np.empty((len(queries), 4))
        _cylinders(*self.moments(xyz, _CELL * sigma), self.lo, np.ascontiguousarray(queries),
                   np.ascontiguousarray(normals), sigma, _RADIUS * sigma, half, out)
        out[out[:, 2] < _MIN_POINTS, :2] = np.nan
        return out


def _enough(out: np.ndarray) -> np.ndarray:
    """The cylinders (rows of :meth:`_CellLists._cylinders`) that measure: as many effective points
    as a spread needs, as much weight as two points on M3C2's rim."""
    return (out[:, 2] >= _MIN_POINTS) & (out[:, 3] >= _MIN_WEIGHT)


def _index_box(xyz, lo, cell):
    """(first, last) cell index per axis of the points, as the kernels index them: from the
    points' corners, since ⌊(x − lo) / cell⌋ never decreases with x (one serial pass: a parallel
    reduction waits for every core, and a series decodes its next epoch on them meanwhile)."""
    low, high = bounds(xyz)
    return (np.floor((low - lo) / cell).astype(np.int64), np.floor((high - lo) / cell).astype(np.int64))


@nb.njit(cache=True, nogil=True)
def bounds(xyz):
    """(lowest, highest) corner of the points, in one pass."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in range(xyz.shape[0]):
        for a in range(3):
            lo[a] = min(lo[a], xyz[i, a])
            hi[a] = max(hi[a], xyz[i, a])
    return lo, hi


@nb.njit(cache=True, nogil=True, parallel=True)
def _box_cells(xyz, lo, cell, dims, linear):
    """Each point's cell as a row of the box of ``dims[:3]`` cells from cell ``dims[3:]``."""
    for i in nb.prange(xyz.shape[0]):
        ix = min(max(int(math.floor((xyz[i, 0] - lo[0]) / cell)) - dims[3], 0), dims[0] - 1)
        iy = min(max(int(math.floor((xyz[i, 1] - lo[1]) / cell)) - dims[4], 0), dims[1] - 1)
        iz = min(max(int(math.floor((xyz[i, 2] - lo[2]) / cell)) - dims[5], 0), dims[2] - 1)
        linear[i] = (ix * dims[1] + iy) * dims[2] + iz


@nb.njit(cache=True, nogil=True)
def _counting_sort(xyz, linear, total, run_of):
    """Points sorted by cell in O(n + cells): (permutation, start of each occupied cell's run,
    dense table cell → run (-1: empty), the points in that order), ``linear``: each point's
    cell in a box of ``total`` cells (:func:`_box_cells`); ``run_of``, unless empty: each
    point's run."""
    n = xyz.shape[0]
    table = np.zeros(total, np.int32)
    for i in range(n):
        table[linear[i]] += 1
    starts = np.empty(n + 1, np.int64)
    runs = 0
    at = 0
    for c in range(total):  # counts → first slot of each cell; the table then maps cell → run
        k = table[c]
        if k:
            starts[runs] = at
            table[c] = runs
            runs += 1
            at += k
        else:
            table[c] = -1
    starts[runs] = n
    fill = starts[:runs].copy()
    order = np.empty(n, np.int64)
    ordered = np.empty_like(xyz)
    keep = run_of.shape[0] == n
    for i in range(n):
        r = table[linear[i]]
        if keep:
            run_of[i] = r
        j = fill[r]
        order[j] = i
        for a in range(3):
            ordered[j, a] = xyz[i, a]
        fill[r] = j + 1
    return order, starts[: runs + 1].copy(), table, ordered


@nb.njit(cache=True, nogil=True)
def _runs_of(order, starts):
    """Each point's run of a sort by cell (permutation ``order``, runs ``starts``)."""
    out = np.empty(order.shape[0], np.int64)
    for k in range(starts.shape[0] - 1):
        for j in range(starts[k], starts[k + 1]):
            out[order[j]] = k
    return out


@nb.njit(cache=True, nogil=True, parallel=True)
def _results(order, ref, cur, normal, reg, reach, dist, lod, n1, n2, s1, s2, out_normal, level):
    """The outputs, back in the core points' input order (``order``: sorted row → input row), in
    one pass: distance = mean₂ − mean₁ and M3C2's level of detection; NaN (level -1) where an
    epoch had no points or the two lie farther apart than ``reach``."""
    m1, sp1, c1, k1 = ref
    m2, sp2, c2, k2 = cur
    for i in nb.prange(order.shape[0]):
        j = order[i]
        d = m2[i] - m1[i]
        n1[j], n2[j], s1[j], s2[j] = c1[i], c2[i], sp1[i], sp2[i]
        for a in range(3):
            out_normal[j, a] = normal[i, a]
        if abs(d) <= reach and np.isfinite(normal[i, 0]):
            dist[j] = d
            lod[j] = 1.96 * (math.sqrt(sp1[i] ** 2 / c1[i] + sp2[i] ** 2 / c2[i]) + reg)
            level[j] = max(k1[i], k2[i])
        else:
            dist[j] = lod[j] = np.nan
            level[j] = -1


@nb.njit(cache=True, nogil=True, parallel=True)
def _gather(values, index):
    """``values[index]`` on all threads (a permutation of a scan touches memory at random)."""
    out = np.empty((index.shape[0],) + values.shape[1:], values.dtype)
    for i in nb.prange(index.shape[0]):
        out[i] = values[index[i]]
    return out


@nb.njit(cache=True, inline="always")
def rows_around(table, dims, shift, x, y, z, rows):
    """The rows of the 27 cells around cell (x, y, z), -1 where empty, into ``rows`` (27,): in a
    dense table (``dims``: the box's size, then its first cell) or a hash table (``dims`` zeros:
    :func:`sdp._core._cells.key_table`). The table's kind is tested once, outside the loops: a
    hash probe's loop beside a dense lookup in one loop body made the dense lookups ten times
    slower."""
    k = 0
    if dims[0] > 0:
        for dx in range(-1, 2):
            ix = x + dx - dims[3]
            for dy in range(-1, 2):
                iy = y + dy - dims[4]
                for dz in range(-1, 2):
                    iz = z + dz - dims[5]
                    if ix < 0 or iy < 0 or iz < 0 or ix >= dims[0] or iy >= dims[1] or iz >= dims[2]:
                        rows[k] = -1
                    else:
                        rows[k] = table[(ix * dims[1] + iy) * dims[2] + iz]
                    k += 1
    else:
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    rows[k] = table_row(table, x + dx, y + dy, z + dz, shift)
                    k += 1


@nb.njit(cache=True, inline="always")
def _cell_box(qx, qy, qz, ex, ey, ez, lo, cell):
    """First and last cell index per axis of the box (q ± e)."""
    return (int(math.floor((qx - ex - lo[0]) / cell)), int(math.floor((qx + ex - lo[0]) / cell)),
            int(math.floor((qy - ey - lo[1]) / cell)), int(math.floor((qy + ey - lo[1]) / cell)),
            int(math.floor((qz - ez - lo[2]) / cell)), int(math.floor((qz + ez - lo[2]) / cell)))


@nb.njit(cache=True, inline="always")
def _smallest_eigenvector(a00, a01, a02, a11, a12, a22):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3×3 matrix, and that eigenvalue
    (closed form: the trigonometric solution of the characteristic cubic, then the largest cross
    product of two rows of A − λI)."""
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    p = math.sqrt(p2 / 6.0)
    if p < 1e-300:
        return 0.0, 0.0, 1.0, q
    b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
    b01, b02, b12 = a01 / p, a02 / p, a12 / p
    r = (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)) / 2.0
    r = min(1.0, max(-1.0, r))
    lam = q + 2.0 * p * math.cos(math.acos(r) / 3.0 + 2.0 * math.pi / 3.0)
    r0 = (a00 - lam, a01, a02)
    r1 = (a01, a11 - lam, a12)
    r2 = (a02, a12, a22 - lam)
    best, bx, by, bz = -1.0, 0.0, 0.0, 1.0
    for u, v in ((r0, r1), (r0, r2), (r1, r2)):
        cx = u[1] * v[2] - u[2] * v[1]
        cy = u[2] * v[0] - u[0] * v[2]
        cz = u[0] * v[1] - u[1] * v[0]
        nn = cx * cx + cy * cy + cz * cz
        if nn > best:
            best, bx, by, bz = nn, cx, cy, cz
    s = math.sqrt(best)
    return bx / s, by / s, bz / s, lam


@nb.njit(cache=True, nogil=True)
def _cell_moments(pts, starts):
    """Per cell of a sorted cloud, one row: point count, centroid (3), scatter about the centroid
    (xx, xy, xz, yy, yz, zz); one row per cell keeps a query's reads to a cache line or two."""
    c = starts.shape[0] - 1
    m = np.zeros((c, 10))
    for r in range(c):
        a, b = starts[r], starts[r + 1]
        m[r, 0] = b - a
        for j in range(a, b):
            for k in range(3):
                m[r, 1 + k] += pts[j, k]
        for k in range(3):
            m[r, 1 + k] /= b - a
        for j in range(a, b):
            dx, dy, dz = pts[j, 0] - m[r, 1], pts[j, 1] - m[r, 2], pts[j, 2] - m[r, 3]
            m[r, 4] += dx * dx
            m[r, 5] += dx * dy
            m[r, 6] += dx * dz
            m[r, 7] += dy * dy
            m[r, 8] += dy * dz
            m[r, 9] += dz * dz
    return m


@nb.njit(cache=True, inline="always")
def _normal_cell(cells, r, qx, qy, qz, r2max, inv2s2, acc):
    """``acc`` (points, weight, weighted sums of the offsets and of their products) with cell row
    ``r`` added if its centroid lies within reach, each point weighted by the Gaussian at it."""
    dx, dy, dz = cells[r, 1] - qx, cells[r, 2] - qy, cells[r, 3] - qz
    d2 = dx * dx + dy * dy + dz * dz
    if d2 > r2max:
        return acc
    npts, w, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz = acc
    g = math.exp(-d2 * inv2s2)
    n = cells[r, 0]
    gn = g * n
    return (npts + n, w + gn, sx + gn * dx, sy + gn * dy, sz + gn * dz,
            sxx + g * cells[r, 4] + gn * dx * dx, sxy + g * cells[r, 5] + gn * dx * dy,
            sxz + g * cells[r, 6] + gn * dx * dz, syy + g * cells[r, 7] + gn * dy * dy,
            syz + g * cells[r, 8] + gn * dy * dz, szz + g * cells[r, 9] + gn * dz * dz)


@nb.njit(cache=True, nogil=True, parallel=True)
def _normals(cells, table, dims, cell, lo, queries, sigma, reach, normal, rough):
    inv2s2 = 0.5 / (sigma * sigma)
    r2max = reach * reach
    shift = 64 - int(round(math.log2(max(table.shape[0] // 2, 1))))  # hash tables only
    for i in nb.prange(queries.shape[0]):
        qx, qy, qz = queries[i, 0], queries[i, 1], queries[i, 2]
        x0, x1, y0, y1, z0, z1 = _cell_box(qx, qy, qz, reach, reach, reach, lo, cell)
        acc = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if dims[0] > 0:  # a dense table: the box clipped to it once, each column's cells read in a row
            x0, x1 = max(x0 - dims[3], 0), min(x1 - dims[3], dims[0] - 1)
            y0, y1 = max(y0 - dims[4], 0), min(y1 - dims[4], dims[1] - 1)
            z0, z1 = max(z0 - dims[5], 0), min(z1 - dims[5], dims[2] - 1)
            for ix in range(x0, x1 + 1):
                for iy in range(y0, y1 + 1):
                    column = (ix * dims[1] + iy) * dims[2]
                    for c in range(column + z0, column + z1 + 1):
                        r = table[c]
                        if r >= 0:
                            acc = _normal_cell(cells, r, qx, qy, qz, r2max, inv2s2, acc)
        else:
            for ix in range(x0, x1 + 1):
                for iy in range(y0, y1 + 1):
                    for iz in range(z0, z1 + 1):
                        r = table_row(table, ix, iy, iz, shift)
                        if r >= 0:
                            acc = _normal_cell(cells, r, qx, qy, qz, r2max, inv2s2, acc)
        npts, w, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz = acc
        if npts < 3:
            normal[i, 0] = normal[i, 1] = normal[i, 2] = np.nan
            rough[i] = np.nan
            continue
        mx, my, mz = sx / w, sy / w, sz / w
        nx, ny, nz, lam = _smallest_eigenvector(sxx / w - mx * mx, sxy / w - mx * my, sxz / w - mx * mz,
                                                syy / w - my * my, syz / w - my * mz, szz / w - mz * mz)
        normal[i, 0], normal[i, 1], normal[i, 2] = nx, ny, nz
        rough[i] = math.sqrt(max(lam, 0.0))


@nb.njit(cache=True, nogil=True, parallel=True)
def _nearest_along(table, dims, cell, lo, queries, normals, reach, out):
    """Per query: the signed offset t, nearest to 0 with |t| ≤ ``reach``, at which the line
    ``q + t·n`` passes an occupied cell or one of its 26 neighbours (steps of half a cell, both
    ways at once; the neighbours bridge the gaps of a sparse surface); NaN if none."""
    shift = 64 - int(round(math.log2(max(table.shape[0] // 2, 1))))  # hash tables only
    step = 0.5 * cell
    for i in nb.prange(queries.shape[0]):
        rows = np.empty(27, np.int64)
        out[i] = np.nan
        s = step
        while s <= reach and np.isnan(out[i]):
            for sign in (1.0, -1.0):
                t = sign * s
                cx = int(math.floor((queries[i, 0] + t * normals[i, 0] - lo[0]) / cell))
                cy = int(math.floor((queries[i, 1] + t * normals[i, 1] - lo[1]) / cell))
                cz = int(math.floor((queries[i, 2] + t * normals[i, 2] - lo[2]) / cell))
                rows_around(table, dims, shift, cx, cy, cz, rows)
                if rows.max() >= 0:
                    out[i] = t
                    break
            s += step


@nb.njit(cache=True, inline="always")
def _cylinder_cell(cells, r, qx, qy, qz, nx, ny, nz, half, r2max, inv2s2, w, w2, st, stt):
    """The sums of a cylinder (weight, squared weight, weighted offset and its square) with cell
    row ``r`` added if its centroid lies in the cylinder."""
    dx, dy, dz = cells[r, 1] - qx, cells[r, 2] - qy, cells[r, 3] - qz
    t = dx * nx + dy * ny + dz * nz
    if t > half or t < -half:
        return w, w2, st, stt
    r2 = dx * dx + dy * dy + dz * dz - t * t
    if r2 > r2max:
        return w, w2, st, stt
    g = math.exp(-r2 * inv2s2)
    n = cells[r, 0]
    along = (nx * (cells[r, 4] * nx + cells[r, 5] * ny + cells[r, 6] * nz)
             + ny * (cells[r, 5] * nx + cells[r, 7] * ny + cells[r, 8] * nz)
             + nz * (cells[r, 6] * nx + cells[r, 8] * ny + cells[r, 9] * nz))
    return w + g * n, w2 + g * g * n, st + g * n * t, stt + g * (n * t * t + along)


@nb.njit(cache=True, nogil=True, parallel=True)
def _cylinders(cells, table, dims, cell, lo, queries, normals, sigma, radius, half, out):
    """Per query: kernel-weighted mean offset along its normal, spread and effective count of the
    cells whose centroid lies within ``radius`` of its axis and ``half`` along it; each cell's
    points share the weight of its centroid, their offsets and spread are exact (the cell's
    centroid and scatter)."""
    inv2s2 = 0.5 / (sigma * sigma)
    r2max = radius * radius
    shift = 64 - int(round(math.log2(max(table.shape[0] // 2, 1))))  # hash tables only
    for i in nb.prange(queries.shape[0]):
        qx, qy, qz = queries[i, 0], queries[i, 1], queries[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        w = w2 = st = stt = 0.0
        if not np.isfinite(nx):
            out[i, 0] = out[i, 1] = np.nan
            out[i, 2] = out[i, 3] = 0.0
            continue
        ex = half * abs(nx) + radius * math.sqrt(max(0.0, 1.0 - nx * nx))
        ey = half * abs(ny) + radius * math.sqrt(max(0.0, 1.0 - ny * ny))
        ez = half * abs(nz) + radius * math.sqrt(max(0.0, 1.0 - nz * nz))
        x0, x1, y0, y1, z0, z1 = _cell_box(qx, qy, qz, ex, ey, ez, lo, cell)
        if dims[0] > 0:
            # a dense table: the box clipped to it once, each column's cells read in a row (most
            # of a box's cells are empty, so the per-cell index arithmetic was most of the time)
            x0, x1 = max(x0 - dims[3], 0), min(x1 - dims[3], dims[0] - 1)
            y0, y1 = max(y0 - dims[4], 0), min(y1 - dims[4], dims[1] - 1)
            z0, z1 = max(z0 - dims[5], 0), min(z1 - dims[5], dims[2] - 1)
            for ix in range(x0, x1 + 1):
                for iy in range(y0, y1 + 1):
                    column = (ix * dims[1] + iy) * dims[2]
                    for c in range(column + z0, column + z1 + 1):
                        r = table[c]
                        if r >= 0:
                            w, w2, st, stt = _cylinder_cell(cells, r, qx, qy, qz, nx, ny, nz, half, r2max, inv2s2,
                                                            w, w2, st, stt)
        else:
            for ix in range(x0, x1 + 1):
                for iy in range(y0, y1 + 1):
                    for iz in range(z0, z1 + 1):
                        r = table_row(table, ix, iy, iz, shift)
                        if r >= 0:
                            w, w2, st, stt = _cylinder_cell(cells, r, qx, qy, qz, nx, ny, nz, half, r2max, inv2s2,
                                                            w, w2, st, stt)
        out[i, 3] = w
        if w <= 0.0:
            out[i, 0] = out[i, 1] = np.nan
            out[i, 2] = 0.0
            continue
        m = st / w
        n_eff = w * w / w2
        var = max(stt / w - m * m, 0.0)
        if n_eff > 1.0:
            var *= n_eff / (n_eff - 1.0)
        out[i, 0] = m
        out[i, 1] = math.sqrt(var)
        out[i, 2] = n_eff


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
