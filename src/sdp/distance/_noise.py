"""A level of detection that holds on real sensors, and the distance of every point of a cloud
to the other epoch's surface.

M3C2's level of detection ``1.96·(√(s₁²/n₁ + s₂²/n₂) + reg)`` (:func:`sdp.distances`) assumes
that the n points of a cylinder carry independent errors. Real sensors do not: a structured-light
depth camera matches a window of pixels, so neighbouring points share one depth error, its
calibration and quantisation errors are common to whole frames, and its depth error grows
about as z² (the disparity step is fixed, depth ∝ 1/disparity). On the static Kinect pairs of
the mOSD set, the distances of the unchanged majority have a median of 0.15 mm but a 95th
percentile of 1–2 mm: about 14 % of them are "significant" where the level promises 5 %.

:func:`point_distances` measures, for each point, its own signed offset from the other epoch's
surface (the other epoch's kernel-weighted mean along the normal, in the cylinder of
:func:`sdp.distances` at the centroid of the point's cell of 1.5σ_p: one query per cell, about
20 times fewer than per point on a Kinect frame), and models its variance in three parts:

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
  against log range over ten range bins of the stable majority, where the sensor is known,
  else 0;
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

import time
from dataclasses import dataclass, field

import numpy as np

from ..errors import InvalidOptionError
from ..options import Cylinder
from ._distances import distances

__all__ = ["PointDistances", "point_distances", "LEVEL_Z"]

LEVEL_Z = 1.96  # two-sided 95 %: the level of detection's promise
_SHARE = 0.05  # share of the stable majority beyond the level
_CELL = 1.5  # points share the distance of their cell of 1.5σ_p
_MAX_EXPONENT = 2.0  # a structured-light camera's σ_z ∝ z²; nothing grows faster
_CALIBRATION_POINTS = 20_000  # the 5 % quantile to about ±0.3 %


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
    if registration_error != "auto" and not (np.isscalar(registration_error)
                                             and np.isfinite(registration_error) and registration_error >= 0):
        raise InvalidOptionError(f"registration_error must be 'auto' or a number >= 0, got {registration_error!r}")
    if range_exponent != "auto" and not (np.isscalar(range_exponent) and 0 <= range_exponent <= _MAX_EXPONENT):
        raise InvalidOptionError(f"range_exponent must be 'auto' or in [0, 2], got {range_exponent!r}")
    if correlation_length is not None and not (np.isscalar(correlation_length) and correlation_length > 0):
        raise InvalidOptionError(f"correlation_length must be a length > 0, got {correlation_length!r}")
    t0 = time.perf_counter()
    points = np.asarray(points, np.float64)
    n = len(points)
    c = _CELL * sigma
    lo = points.min(axis=0) if n else np.zeros(3)
    ijk = np.floor((points - lo) / c).astype(np.int64)
    dims = ijk.max(axis=0) + 1 if n else np.ones(3, np.int64)
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]
    uniq, inv, count = np.unique(key, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    m = len(uniq)
    cell_index = np.stack([uniq // (dims[1] * dims[2]), (uniq // dims[2]) % dims[1], uniq % dims[2]], axis=1)
    centroid = np.empty((m, 3))
    for a in range(3):
        centroid[:, a] = np.bincount(inv, points[:, a], m) / count
    timings = {"cells": time.perf_counter() - t0}
    nan = np.full(n, np.nan)
    if n < 3 or len(other) < 3:
        return PointDistances(nan, nan.copy(), inv, cell_index, c, 0.0, float("nan"), timings)

    t = time.perf_counter()
    origins = None if other_origin is None else np.stack([np.asarray(other_origin, np.float64)] * 2)
    # only the other epoch's cylinder is read (its mean, spread and count): the cells' centroids
    # stand in for this epoch's points, which saves sorting them; D = 2d, the automatic normal
    # scale before its roughness check (a sampled pass of its own); the other surface is looked
    # for within the cylinder's own half-length 3σ, no farther: beyond about 2σ the density
    # decides (:mod:`sdp.change._combined`)
    d = distances(other, centroid, core_points=centroid,
                  cylinder=Cylinder(projection_scale=4.0 * sigma, normal_scale=8.0 * sigma, max_distance=3.0 * sigma),
                  sensor_origin=origins)
    timings["distances"] = time.perf_counter() - t

    t = time.perf_counter()
    n_corr = np.inf if correlation_length is None else (2.0 * sigma / float(correlation_length)) ** 2
    normal = d.normal[inv]
    # each point's own offset from the other surface (the kernel mean of the other epoch in the
    # cylinder of its cell's centroid): an object's points against an old surface are not
    # averaged with that surface's, as the cylinder's own mean would
    dist = np.einsum("ij,ij->i", points - centroid[inv], normal) - d.mean1[inv]
    # one point of an unchanged surface scatters about the other epoch's mean as that epoch's own
    # points do: s₁²(1 + 1/n₁'); the other epoch's cylinder holds no new object, so an object
    # next to the point does not widen its level
    with np.errstate(invalid="ignore", divide="ignore"):
        random = (d.spread1**2 * (1.0 + 1.0 / np.minimum(d.n1, n_corr)))[inv]
    ok = np.isfinite(dist) & np.isfinite(random)
    calib = ok & (np.ones(n, bool) if stable is None else np.asarray(stable, bool))
    # a quantile and a slope: a regular sample of the stable points tells them as well as all do
    idx = np.flatnonzero(calib)
    if idx.size > _CALIBRATION_POINTS:
        calib = np.zeros(n, bool)
        calib[idx[:: idx.size // _CALIBRATION_POINTS]] = True
    if own_origin is not None:
        r = np.maximum(np.linalg.norm(points - np.asarray(own_origin, np.float64), axis=1), 1e-9)
    else:
        r = np.ones(n)
    if range_exponent == "auto":
        p = _fit_exponent(dist[calib], r[calib]) if own_origin is not None else 0.0
    else:
        p = float(range_exponent)
    r_med = float(np.median(r[calib])) if calib.any() else 1.0
    g = (r / r_med) ** p
    scale = 1.0
    if registration_error == "auto":
        s = _systematic(np.abs(dist[calib]), random[calib], g[calib])
        if s == 0.0 and calib.any():  # fewer than 5 % beyond the random part alone: scaled down to 5 %
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.abs(dist[calib]) / (LEVEL_Z * np.sqrt(random[calib]))
            scale = min(1.0, float(np.quantile(ratio, 1.0 - _SHARE))) ** 2
    else:
        s = float(registration_error) / LEVEL_Z
    lod = LEVEL_Z * np.sqrt(scale * random + (s * g) ** 2)
    timings["level"] = time.perf_counter() - t
    return PointDistances(np.where(ok, dist, np.nan), np.where(ok, lod, np.nan), inv, cell_index, c,
                          float(p), float(s), timings)


def _fit_exponent(dist: np.ndarray, r: np.ndarray) -> float:
    """Slope of log median |distance| against log median range over ten range bins (clipped to
    [0, 2]); 0 when the ranges hardly vary."""
    a = np.abs(dist)
    keep = a > 0
    a, r = a[keep], r[keep]
    if a.size < 100 or np.quantile(r, 0.9) < 1.2 * np.quantile(r, 0.1):
        return 0.0
    edges = np.quantile(r, np.linspace(0, 1, 11))
    b = np.clip(np.searchsorted(edges, r, side="right") - 1, 0, 9)
    x = np.array([np.log(np.median(r[b == i])) for i in range(10) if np.any(b == i)])
    y = np.array([np.log(np.median(a[b == i])) for i in range(10) if np.any(b == i)])
    if x.size < 3:
        return 0.0
    return float(np.clip(np.polyfit(x, y, 1)[0], 0.0, _MAX_EXPONENT))


def _systematic(absd: np.ndarray, random: np.ndarray, g: np.ndarray) -> float:
    """Smallest σ_s ≥ 0 for which at most 5 % of the stable points lie beyond
    1.96·√(random + (σ_s·g)²) (bisection: the share falls as σ_s grows)."""
    if absd.size == 0:
        return 0.0

    def share(s):
        return np.count_nonzero(absd > LEVEL_Z * np.sqrt(random + (s * g) ** 2)) / absd.size

    if share(0.0) <= _SHARE:
        return 0.0
    lo, hi = 0.0, float(np.max(absd / g)) / LEVEL_Z + 1e-12
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if share(mid) > _SHARE else (lo, mid)
    return hi
