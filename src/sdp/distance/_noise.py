"""A level of detection that holds on real sensors, and the distance of every point of a cloud
to the other epoch's surface.

M3C2's level of detection ``1.96·(√(s₁²/n₁ + s₂²/n₂) + reg)`` (:func:`sdp.distances`) assumes
that the n points of a cylinder carry independent errors. Real sensors do not: a structured-light
depth camera matches a window of pixels, so neighbouring points share one depth error, its
calibration and quantisation errors are common to whole frames, and its depth error grows
about as z² (the disparity step is fixed, depth ∝ 1/disparity). On the static Kinect pairs of
the mOSD set, the distances of the unchanged majority have a median of 0.15 mm but a 95th
percentile of 1–2 mm: about 14 % of them are "significant" where the level promises 5 %.

:class:`SurfaceDistances` (:func:`point_distances` for every point at once) measures, for each
point, its own signed offset from the other epoch's surface (the other epoch's kernel-weighted
mean along the normal, in the cylinder of :func:`sdp.distances` at the centroid of the point's
cell of 1.5σ_p: one query per cell, about 20 times fewer than per point on a Kinect frame), and
models its variance in three parts:

- **random**: one point of an unchanged surface scatters about the other epoch's mean as that
  epoch's own points do, ``s₁²(1 + 1/n₁')``, s₁ the other epoch's spread along the normal in
  the cylinder (which holds no new object: an object beside the point does not widen its
  level) and ``n₁' = min(n₁, (2σ_p/ℓ)²)`` when errors are known to be correlated over a length
  ℓ (``correlation_length``: about one independent sample per ℓ² of the cylinder's area
  π(2σ_p)², Bretherton et al.'s effective count of correlated data). By default ``n₁' = n₁``
  and what correlation adds shows in the systematic part, which is measured, not assumed (a
  Kinect's window of correlated pixels depends on its matcher);
- **range-dependent**: ``(σ_s·g(r))²`` with ``g(r) = (r/r̃)^p`` along the sensor's ray, r̃
  the median range; ``p`` (``range_exponent``) is 2 for a structured-light camera and 0 for a
  laser scanner; ``"auto"`` fits it (clipped to [0, 2]) as the slope of log median |distance|
  against log range over ten range bins (of equal counts) of the stable majority, where the
  sensor is known, else 0;
- **systematic** (registration, calibration, correlated errors): σ_s is what the data say when
  ``registration_error="auto"``: the smallest σ_s for which no more than 5 % of the stable
  majority (the points the density test left unchanged) lies beyond the level. This is the
  robust spread of the distances over the stable majority, taken at the level the LoD promises
  rather than at the median, because Kinect distances are heavy-tailed (a Gaussian scale from
  their median would promise 5 % and deliver 14 %); up to 5 % of the "stable" points may be
  changes the density missed without moving it. A given number is M3C2's ``reg`` instead
  (σ_s = reg/1.96, e.g. the alignment's residual), nothing estimated.
- **the random part's scale**, with ``"auto"`` too: where fewer than 5 % of the stable majority
  lie beyond the random part alone (σ_s = 0), the random part is scaled down (factor c ≤ 1) until
  5 % do. s₁ is the spread of the other epoch across the whole cylinder, which holds the
  surface's curvature there (a laser scan of a building or a slope: edges, mouldings, waves of a
  few σ_p), while a point near the cylinder's axis does not carry it: the spreads alone then
  promise 5 % and give less (2.6–2.9 % on the DLUT re-scans; 0.2 % on waves of 10σ_p in
  ``tests/test_combined.py``). The stable majority measures the level's scale as it measures
  the systematic part; never up (that is σ_s's part).

``lod = 1.96·√(c·random + (σ_s·g(r))²)``. A moved surface shifts the distances of the majority
only if it *is* the majority; a whole scene offset by a registration error is then
(rightly) within the level.

The stable majority is read at a regular sample of the cells (at most 1,024 cells, at most
20,000 of their stable points; about 10,000 on a Kinect frame: a 5 % share to about ±0.5 %;
each direction of a pair measures its own sample), so the level is known before
any other cell is measured; a decision that needs the distance near a few objects only
(:mod:`sdp.change._combined`) measures those cells and the sample, not the whole scene.

References
----------
.. [1] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
   terrestrial laser scanner", ISPRS J. 82 (2013) (the level of detection).
.. [2] K. Khoshelham, S. O. Elberink, "Accuracy and resolution of Kinect depth data for indoor
   mapping applications", Sensors 12 (2012) 1437–1454 (σ_z ∝ z², the disparity step).
.. [3] C. S. Bretherton et al., "The effective number of spatial degrees of freedom of a
   time-varying field", J. Climate 12 (1999) (effective count of correlated samples).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numba as nb
import numpy as np

from .._core._parallel import map_concurrently
from ..errors import InvalidOptionError
from ._cells import DENSE_CELLS, CellLists, bounds, rows_around
from ._level import LEVEL_Z, SHARE, systematic

__all__ = ["PointDistances", "SurfaceDistances", "point_distances", "pair_cells", "distance_bytes", "LEVEL_Z"]

CELL = 1.5  # points share the distance of their cell of 1.5σ_p
_MAX_EXPONENT = 2.0  # a structured-light camera's σ_z ∝ z²; nothing grows faster
_CALIBRATION_POINTS = 20_000  # the 5 % quantile to about ±0.3 %
_CALIBRATION_CELLS = 1024  # the cells they come from: a regular sample of the scene, no larger than the share's
# ±0.5 % needs (measuring it is most of what the combined decision adds to the density's time)


@dataclass
class PointDistances:
    """Per point of a cloud: its signed distance to the other epoch's surface and the
    level of detection (see :func:`point_distances`).

    Attributes
    ----------
    distance, lod : ndarray (n,) float64
        Each point's signed offset from the other epoch's surface along the normal (positive:
        in front of it, towards the other scan's sensor when known, else +z) and its level at
        95 %; NaN where the other epoch has nothing to measure against.
    cells : ndarray (n,) int64
        Each point's cell (row of the cells' arrays).
    cell_index : ndarray (m, 3) int64
        Integer coordinates of each cell (cells of ``cell_size``).
    cell_size, range_exponent, systematic : float
        The cells' edge, the exponent p of g(r) and σ_s (at the median range).
    timings : dict of str to float
    """

    distance: np.ndarray
    lod: np.ndarray
    cells: np.ndarray
    cell_index: np.ndarray
    cell_size: float
    range_exponent: float
    systematic: float
    timings: dict = field(default_factory=dict)

    @property
    def significant(self) -> np.ndarray:
        """``|distance| > lod`` (False where not comparable)."""
        with np.errstate(invalid="ignore"):
            return np.abs(self.distance) > self.lod


def point_distances(points: np.ndarray, other: np.ndarray, *, sigma: float, own_origin=None, other_origin=None,
                    stable: np.ndarray | None = None, registration_error: float | str = "auto",
                    range_exponent: float | str = "auto", correlation_length: float | None = None) -> PointDistances:
    """Signed offset of each point of ``points`` from the surface of ``other``, with a level of
    detection that holds on real sensors (module docstring).

    Parameters
    ----------
    points, other : ndarray (n, 3), (k, 3) float64
        Finite world coordinates of the two epochs, in one frame.
    sigma : float
        The density kernel's σ: the projection scale is 4σ (as :func:`sdp.distances`).
    own_origin, other_origin : ndarray (3,) or None
        The sensors of ``points`` and of ``other``: ranges are taken from ``own_origin``,
        normals point towards ``other_origin`` (else +z).
    stable : ndarray (n,) bool, optional
        The majority that did not change (e.g. what the density test left unchanged); default
        every point.
    registration_error : "auto" or float
        ``"auto"``: σ_s from the stable majority; a number: M3C2's ``reg`` (σ_s = reg/1.96).
    range_exponent : "auto" or float
        p of g(r) = (r/r̃)^p, in [0, 2]; ``"auto"``: fitted where ``own_origin`` is known, else 0.
    correlation_length : float, optional
        ℓ, the length over which errors are correlated (world units); default none known.

    Returns
    -------
    PointDistances
    """
    return SurfaceDistances(points, other, sigma=sigma, own_origin=own_origin, other_origin=other_origin,
                            stable=stable, registration_error=registration_error, range_exponent=range_exponent,
                            correlation_length=correlation_length).everywhere()


def distance_bytes(clouds, sigma: float) -> float:
    """Memory the distances of a pair need (:class:`SurfaceDistances` both ways; ``clouds``: the
    two epochs' :class:`sdp._core._points.Points`): per point, its sorted copy, permutation and cell
    (40 B), its cell's moments (at most 80 B), its distance, variance and range (24 B) and the
    decision's masks (16 B); per cloud, the dense table of cells (4 B per cell of the box, at
    most 2**25 cells)."""
    lo = np.minimum(clouds[0].lo, clouds[1].lo)
    hi = np.maximum(clouds[0].hi, clouds[1].hi)
    box = float(np.prod((hi - lo) // (CELL * sigma) + 1))
    return 160.0 * (len(clouds[0].xyz) + len(clouds[1].xyz)) + 2 * 4.0 * min(box, DENSE_CELLS)


def pair_cells(clouds, sigma: float, *, sort: bool = False) -> CellLists:
    """The cells of 1.5σ that both epochs of a pair share (:class:`SurfaceDistances` ``lists``):
    ``clouds``, the two epochs' :class:`sdp._core._points.Points`; each cloud is sorted into
    them once, for both directions (``sort``: now, both at once, rather than when first read)."""
    lists = CellLists(np.minimum(clouds[0].lo, clouds[1].lo) - 1e-9, np.maximum(clouds[0].hi, clouds[1].hi))
    if sort:
        map_concurrently(lambda c: (lists.point_cells(c.xyz, CELL * sigma), lists.moments(c.xyz, CELL * sigma)),
                         clouds, parallel_kernels=True)
    return lists


class SurfaceDistances:
    """Each point's signed distance to the other epoch's surface and its level of detection
    (module docstring), measured cell by cell when asked: :meth:`at` for some points,
    :meth:`everywhere` for all. A decision that needs the distance near a few objects only
    (:mod:`sdp.change._combined`) reads the other epoch's cylinders at those cells and at the
    sample of the stable majority that calibrates the level, not at every cell.

    Parameters are those of :func:`point_distances`; ``lists``: the cells the two epochs are
    sorted into (:func:`pair_cells`; default their own); ``level``: (p, r̃, c, σ_s) calibrated
    elsewhere (:func:`fit_level`: the tiles' samples together), else on this sample.

    Attributes
    ----------
    cells : ndarray (n,) int64
        Each point's cell (row of ``cell_index``).
    cell_index : ndarray (m, 3) int64
        Integer coordinates of each cell of ``cell_size`` (1.5σ).
    """

    def __init__(self, points: np.ndarray, other: np.ndarray, *, sigma: float, own_origin=None, other_origin=None,
                 stable: np.ndarray | None = None, registration_error: float | str = "auto",
                 range_exponent: float | str = "auto", correlation_length: float | None = None,
                 lists: CellLists | None = None, level: tuple | None = None):
        if registration_error != "auto" and not (np.isscalar(registration_error)
                                                 and np.isfinite(registration_error) and registration_error >= 0):
            raise InvalidOptionError(f"registration_error must be 'auto' or a number >= 0, got {registration_error!r}")
        if range_exponent != "auto" and not (np.isscalar(range_exponent) and 0 <= range_exponent <= _MAX_EXPONENT):
            raise InvalidOptionError(f"range_exponent must be 'auto' or in [0, 2], got {range_exponent!r}")
        if correlation_length is not None and not (isinstance(correlation_length, (int, float, np.integer, np.floating))
                                                   and correlation_length > 0):
            raise InvalidOptionError(f"correlation_length must be a length > 0, got {correlation_length!r}")
        t0 = time.perf_counter()
        self.points = np.ascontiguousarray(points, np.float64)
        self.other = np.ascontiguousarray(other, np.float64)
        self.sigma = float(sigma)
        self.cell_size = c = CELL * sigma
        self._own_origin = None if own_origin is None else np.asarray(own_origin, np.float64)
        self._other_origin = None if other_origin is None else np.asarray(other_origin, np.float64)
        self._stable = None if stable is None else np.asarray(stable, bool)
        self._options = (registration_error, range_exponent, correlation_length)
        n = len(self.points)
        if lists is None:
            lo, hi = bounds(self.points) if n else (np.zeros(3), np.zeros(3))
            if len(self.other):
                lo_o, hi_o = bounds(self.other)
                lo, hi = np.minimum(lo, lo_o), np.maximum(hi, hi_o)
            lists = CellLists(lo - 1e-9, hi)
        self._lists = lists
        # the cylinders' own cells of 1.5σ: this epoch's points grouped by counting, the centroids
        # read off the cells' moments
        if n:
            self.cells = lists.point_cells(self.points, c)
            ordered, self._starts, self._table, self._dims, _, self._order = lists.get(self.points, c)
            m = len(self._starts) - 1
            self._centroid, self.cell_index = np.empty((m, 3)), np.empty((m, 3), np.int64)
            _cells_of(ordered, self._starts, lists.moments(self.points, c)[0], lists.lo, c, self._centroid,
                      self.cell_index)
        else:
            self._starts, self._order = np.zeros(1, np.int64), np.zeros(0, np.int64)
            self._centroid, self.cells, self.cell_index = np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 3), np.int64)
            self._table, self._dims = np.full(128, -1, np.int64), np.zeros(6, np.int64)
        m = len(self._starts) - 1
        self._measured = np.zeros(m, bool)
        self._scratch = np.zeros(m, bool)  # all False between calls of _distinct
        self._dist, self._random, self._r = np.full(n, np.nan), np.full(n, np.nan), np.ones(n)
        self._comparable = n >= 3 and len(self.other) >= 3
        self._level = level  # (p, r̃, c, σ_s) given, or once calibrated
        self._everywhere = None
        self.timings = {"cells": time.perf_counter() - t0}

    def points_of(self, rows: np.ndarray) -> np.ndarray:
        """The points (indices) of the cells ``rows``."""
        return _points_of(self._order, self._starts, np.asarray(rows, np.int64))

    def neighbours(self, rows: np.ndarray, visited: np.ndarray) -> np.ndarray:
        """The occupied cells among the 26 neighbours of the cells ``rows`` that are not
        ``visited`` (m,) bool, which they then are."""
        return _neighbours(self._table, self._dims, self.cell_index, np.asarray(rows, np.int64), visited)

    def components(self, hit: np.ndarray) -> tuple[np.ndarray, int]:
        """(label of each cell, -1 where not ``hit``; the number of components) of the
        26-connected components of the cells ``hit`` (m,) bool."""
        return _components(self._table, self._dims, self.cell_index, np.asarray(hit, bool))

    def cells_of(self, idx: np.ndarray) -> np.ndarray:
        """The distinct cells of the points ``idx``, in the order first met."""
        return _distinct(self.cells, np.asarray(idx, np.int64), self._scratch)

    def at(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(distance, lod) of the points ``idx``, their cells measured if not yet (NaN: nothing
        to measure against)."""
        idx = np.asarray(idx, np.int64)
        self._measure(self.cells_of(idx))
        lod = np.empty(len(idx))
        _level(self._random, self._r, idx, *self.level, lod)
        return self._dist[idx], lod

    @property
    def level(self) -> tuple[float, float, float, float]:
        """(p, r̃, c, σ_s) of ``lod = 1.96·√(c·random + (σ_s·(r/r̃)^p)²)``, calibrated on a sample
        of the stable majority on first use."""
        if self._level is None:
            self._level = self._calibrate()
        return self._level

    def everywhere(self) -> PointDistances:
        """Every point's distance and level."""
        if self._everywhere is None:
            self._measure(np.arange(len(self._measured)))
            idx = np.arange(len(self.points))
            p, _, _, s = self.level
            lod = np.empty(len(idx))
            _level(self._random, self._r, idx, *self.level, lod)
            self._everywhere = PointDistances(self._dist.copy(), lod, self.cells, self.cell_index, self.cell_size,
                                              float(p), float(s), dict(self.timings))
        return self._everywhere

    def _measure(self, rows: np.ndarray) -> None:
        """The other epoch's normal and cylinder at the centroid of each cell ``rows`` not yet
        measured, and the offsets, random variances and ranges of their points."""
        rows = rows[~self._measured[rows]]
        if rows.size == 0 or not self._comparable:
            return
        t = time.perf_counter()
        self._measured[rows] = True
        lists, sigma, other = self._lists, self.sigma, self.other
        centroid = np.ascontiguousarray(self._centroid[rows])
        # D = 2d, the automatic normal scale before its roughness check, from the cylinders' own
        # cells; the other surface is looked for within the cylinder's half-length 3σ, no
        # farther: beyond about 2σ the density decides (:mod:`sdp.change._combined`)
        sigma_n = 2.0 * sigma
        normal, _ = lists.normals(other, centroid, sigma_n, cell=self.cell_size)
        missing = ~np.isfinite(normal[:, 0])
        if missing.any():  # none of the other epoch near: this epoch's surface gives the direction
            normal[missing] = lists.normals(self.points, np.ascontiguousarray(centroid[missing]), sigma_n,
                                            cell=self.cell_size)[0]
        if self._other_origin is not None:
            flip = np.einsum("ij,ij->i", normal, self._other_origin - centroid) < 0
        else:
            flip = normal[:, 2] < 0
        normal[flip] *= -1.0
        mean1, spread1, n1 = lists.cylinder(other, centroid, normal, sigma, 3.0 * sigma)[:3]
        corr = self._options[2]
        n_corr = np.inf if corr is None else np.float64(2.0 * sigma / float(corr)) ** 2  # inf, not OverflowError
        # one point of an unchanged surface scatters about the other epoch's mean as that epoch's
        # own points do: s₁²(1 + 1/n₁'); the other epoch's cylinder holds no new object, so an
        # object next to the point does not widen its level
        with np.errstate(invalid="ignore", divide="ignore"):
            random = spread1**2 * (1.0 + 1.0 / np.minimum(n1, n_corr))
        # each point's own offset from the other surface (the kernel mean of the other epoch in the
        # cylinder of its cell's centroid): an object's points against an old surface are not
        # averaged with that surface's, as the cylinder's own mean would
        origin = np.zeros(3) if self._own_origin is None else self._own_origin
        _per_point(self.points, self._order, self._starts, rows, centroid, normal, mean1, random, origin,
                   self._own_origin is not None, self._dist, self._random, self._r)
        self.timings["distances"] = self.timings.get("distances", 0.0) + time.perf_counter() - t

    def calibration_sample(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(distance, random variance, range) of the stable points of a regular sample of the
        cells (at most ``_CALIBRATION_CELLS`` cells, ``_CALIBRATION_POINTS`` points), which
        :func:`fit_level` calibrates the level on."""
        m = len(self._measured)
        sample = np.arange(0, m, max(1, m // _CALIBRATION_CELLS))
        self._measure(sample)
        idx = self.points_of(sample)
        calib = idx[np.isfinite(self._dist[idx]) & (True if self._stable is None else self._stable[idx])]
        # a quantile and a slope: a regular sample of the stable points tells them as well as all do
        calib = thinned(np.sort(calib))
        return self._dist[calib], self._random[calib], self._r[calib]

    def _calibrate(self) -> tuple[float, float, float, float]:
        """(p, r̃, c, σ_s) from a regular sample of the cells, their stable points."""
        t = time.perf_counter()
        registration_error, range_exponent, _ = self._options
        level = fit_level(*self.calibration_sample(), registration_error=registration_error,
                          range_exponent=range_exponent, ranged=self._own_origin is not None)
        self.timings["level"] = time.perf_counter() - t
        return level


def thinned(values: np.ndarray) -> np.ndarray:
    """A regular sample of at most about ``_CALIBRATION_POINTS`` of ``values``."""
    return values[:: values.size // _CALIBRATION_POINTS] if values.size > _CALIBRATION_POINTS else values


def fit_level(dist: np.ndarray, random: np.ndarray, r: np.ndarray, *, registration_error="auto",
              range_exponent="auto", ranged: bool = False) -> tuple[float, float, float, float]:
    """(p, r̃, c, σ_s) of the level (module docstring) from stable points' distances, random
    variances and ranges (``ranged``: the ranges are along a known sensor's rays)."""
    if range_exponent == "auto":
        p = _fit_exponent(dist, r) if ranged else 0.0
    else:
        p = float(range_exponent)
    r_med = float(np.median(r)) if r.size else 1.0
    scale = 1.0
    if registration_error == "auto":
        s = systematic(np.abs(dist), random, (r / r_med) ** p)
        if s == 0.0 and dist.size:  # fewer than 5 % beyond the random part alone: scaled down to 5 %
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.abs(dist) / (LEVEL_Z * np.sqrt(random))
            scale = min(1.0, float(np.quantile(ratio, 1.0 - SHARE))) ** 2
    else:
        s = float(registration_error) / LEVEL_Z
    return float(p), r_med, scale, float(s)


@nb.njit(cache=True, nogil=True)
def _cells_of(ordered, starts, moments, lo, c, centroid, cell_index):
    """From a counting sort into cells of ``c`` (points ``ordered``, runs ``starts``) and the
    cells' ``moments``: each cell's centroid and integer index."""
    for k in range(starts.shape[0] - 1):
        for a in range(3):
            centroid[k, a] = moments[k, 1 + a]
            cell_index[k, a] = int(math.floor((ordered[starts[k], a] - lo[a]) / c))


@nb.njit(cache=True, nogil=True)
def _distinct(cells, idx, seen):
    """The distinct ``cells[idx]`` in the order first met (``seen``: all False, left so)."""
    out = np.empty(idx.shape[0], np.int64)
    m = 0
    for i in idx:
        c = cells[i]
        if not seen[c]:
            seen[c] = True
            out[m] = c
            m += 1
    for k in range(m):
        seen[out[k]] = False
    return out[:m]


@nb.njit(cache=True, nogil=True)
def _points_of(order, starts, rows):
    """The points of the cells ``rows`` (a counting sort's permutation and runs)."""
    total = 0
    for k in rows:
        total += starts[k + 1] - starts[k]
    out = np.empty(total, np.int64)
    at = 0
    for k in rows:
        for j in range(starts[k], starts[k + 1]):
            out[at] = order[j]
            at += 1
    return out


@nb.njit(cache=True, nogil=True)
def _neighbours(table, dims, cell_index, rows, visited):
    """Occupied, not yet ``visited`` cells among the 26 neighbours of ``rows`` (marked visited)."""
    shift = 64 - int(round(math.log2(max(table.shape[0] // 2, 1))))  # hash tables only
    out = np.empty(26 * rows.shape[0], np.int64)
    around = np.empty(27, np.int64)
    found = 0
    for k in rows:
        rows_around(table, dims, shift, cell_index[k, 0], cell_index[k, 1], cell_index[k, 2], around)
        for r in around:
            if r >= 0 and not visited[r]:
                visited[r] = True
                out[found] = r
                found += 1
    return out[:found]


@nb.njit(cache=True, nogil=True)
def _components(table, dims, cell_index, hit):
    """26-connected components of the ``hit`` cells, by depth-first search over the table."""
    shift = 64 - int(round(math.log2(max(table.shape[0] // 2, 1))))  # hash tables only
    label = np.full(hit.shape[0], -1, np.int64)
    stack = np.empty(hit.shape[0], np.int64)
    around = np.empty(27, np.int64)
    n = 0
    for start in range(hit.shape[0]):
        if not hit[start] or label[start] >= 0:
            continue
        label[start] = n
        stack[0] = start
        top = 1
        while top:
            top -= 1
            k = stack[top]
            rows_around(table, dims, shift, cell_index[k, 0], cell_index[k, 1], cell_index[k, 2], around)
            for r in around:
                if r >= 0 and hit[r] and label[r] < 0:
                    label[r] = n
                    stack[top] = r
                    top += 1
        n += 1
    return label, n


@nb.njit(cache=True, nogil=True, parallel=True)
def _per_point(points, order, starts, rows, centroid, normal, mean1, random_of_cell, origin, ranged,
               dist, random, r):
    """For the points of cells ``rows`` (``centroid``, ``normal``, ``mean1``, ``random_of_cell``:
    one row per cell of ``rows``): each point's offset along its cell's normal from the other
    epoch's mean, its random variance, its range from ``origin`` (if ``ranged``); NaN offset and
    variance where either is unknown."""
    for q in nb.prange(rows.shape[0]):
        k = rows[q]
        v = random_of_cell[q]
        for j in range(starts[k], starts[k + 1]):
            i = order[j]
            d = -mean1[q]
            for a in range(3):
                d += (points[i, a] - centroid[q, a]) * normal[q, a]
            if np.isfinite(d) and np.isfinite(v):
                dist[i], random[i] = d, v
            else:
                dist[i] = random[i] = np.nan
            if ranged:
                s = 0.0
                for a in range(3):
                    s += (points[i, a] - origin[a]) ** 2
                r[i] = max(math.sqrt(s), 1e-9)


@nb.njit(cache=True, nogil=True, parallel=True)
def _level(random, r, idx, p, r_med, scale, s, lod):
    """``lod = 1.96·√(c·random + (σ_s·(r/r̃)^p)²)`` at the points ``idx`` (NaN where ``random`` is)."""
    for q in nb.prange(idx.shape[0]):
        i = idx[q]
        g = (r[i] / r_med) ** p if p != 0.0 else 1.0
        lod[q] = LEVEL_Z * math.sqrt(scale * random[i] + (s * g) ** 2)


def _fit_exponent(dist: np.ndarray, r: np.ndarray) -> float:
    """Slope of log median |distance| against log median range over ten range bins of equal
    counts (clipped to [0, 2]); 0 when the ranges hardly vary."""
    a = np.abs(dist)
    keep = a > 0
    a, r = a[keep], r[keep]
    if a.size < 100:
        return 0.0
    q = r.size // 10  # ten bins of q points (the at most 9 farthest left out)
    p10, p90 = int(0.1 * (r.size - 1)), int(0.9 * (r.size - 1))
    # the bins need only their members, not their order: a partition at their edges (a third
    # of a sort's time, which was most of the calibration's)
    by_range = np.argpartition(r, np.unique([p10, p90, *range(q, min(10 * q, r.size - 1) + 1, q)]))
    r, a = r[by_range], a[by_range]
    if r[p90] < 1.2 * r[p10]:
        return 0.0
    x = np.log(np.median(r[: 10 * q].reshape(10, q), axis=1))
    y = np.log(np.median(a[: 10 * q].reshape(10, q), axis=1))
    return float(np.clip(np.polyfit(x, y, 1)[0], 0.0, _MAX_EXPONENT))
