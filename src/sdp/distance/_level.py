"""The level of detection's systematic part, measured on the data when it is not given.

M3C2's level of detection ``lod = 1.96·(√(s₁²/n₁ + s₂²/n₂) + reg)`` [1]_ promises that a
surface that did not move lies beyond it in 5 % of the places. Its random part assumes the n
points of a cylinder carry independent errors, and ``reg`` (registration, calibration) is left to
the user. Real sensors break the first assumption and users rarely know the second: on static
real pairs with ``reg = 0`` the random part alone gives levels of 0.3 mm on a Kinect (69–83 % of
the core points "significant" after GICP, where errors are correlated over the matcher's window
and common to whole frames [2]_) and 4 cm on the Toronto ALS ground (56 %, after alignment: strip
adjustment and GNSS errors are common to whole swaths).

``registration_error="auto"`` therefore measures ``reg`` where it shows: the smallest ``reg ≥ 0``
for which at most 5 % of the *stable part* of the scene lies beyond the level, that is the
(k+1)-th largest of ``|d|/1.96 − √(s₁²/n₁ + s₂²/n₂)`` over it, k = ⌊5 % of it⌋ (the same rule as
the combined decision's systematic part, :mod:`sdp.distance._noise`). The stable part is what
neither the density test nor the noise would call a change:

- **within the density test's reach**: ``|d| ≤ 2σ_p``, σ_p the cylinder's kernel (a quarter of the
  projection scale; by default the density kernel's own σ). A surface is "changed" for the
  density test once the other epoch's surface lies beyond ``s·√(2 ln(G₀/h))`` of it, about 2σ on
  a surface sampled as densely as the automatic σ assumes (:mod:`sdp.distance._distances`). No
  statistic of the scene decides this bound, so a change that covers most of a scene (a growing
  plant, a slope sliding by more than 2σ_p) stays outside it, measured against the noise of what
  did not move;
- **not an outlier of the noise there**: the standardised distance ``d/√(s₁²/n₁ + s₂²/n₂)``
  within five robust standard deviations (1.4826 × the median absolute deviation [3]_) of its
  median, over the places within reach. Beyond that bound a Gaussian keeps 6·10⁻⁷ of its places
  and a Laplace-tailed one 0.6 %, so it drops changes smaller than the kernel (a step of a few
  noise σ over a part of the scene), not the stable surface's tails. Standardised, because
  each place has its own random part (a laser's spread grows with range and incidence).

Where the random part alone already keeps 5 % of the stable part within the level, ``reg = 0``:
the level is never lowered below M3C2's. Where the stable part holds fewer than 100 places (a
handful of chosen core points, or a scene that all moved), ``reg = 0`` too: a 5 % share read from
n places has a standard error of √(0.05·0.95/n), 2.2 % at 100, the level's own tolerance.

What this cannot tell: a shift smaller than 2σ_p of the whole scene (a registration error, or
a real subsidence of every place by less than the kernel) reads as a registration error where
the scene is alike throughout; where it stands out of the noise of the scene's smooth parts and
not of its rough ones (flat ground among trees and roofs), those smooth parts fall outside the
stable part and read as changed instead (Toronto's ALS tile against itself raised by 5 cm: 0
measured, 10.7 % significant). Give
``reg`` as a number (e.g. the residual of an alignment on ground known to be stable) where that
matters. Where a sensor's noise exceeds 2σ_p (a depth camera far from its subject, seen with a
kernel set by the nearer points' spacing) the stable part is cut at 2σ_p and the level is too low
there. A depth camera's tail is heavier than five robust standard deviations allow (4–7 % of a
static Kinect pair's places beyond it, most within a metre of the camera): the level promises 5 %
and gives 7.9–13.1 % there (``benchmarks/bench_level.py``), against 17–30 % with ``reg = 0``.

References
----------
.. [1] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
   terrestrial laser scanner", ISPRS J. 82 (2013) (the level of detection and ``reg``).
.. [2] K. Khoshelham, S. O. Elberink, "Accuracy and resolution of Kinect depth data for indoor
   mapping applications", Sensors 12 (2012) 1437–1454.
.. [3] P. J. Rousseeuw, C. Croux, "Alternatives to the median absolute deviation", J. Am. Stat.
   Assoc. 88 (1993) 1273–1283 (1.4826 × MAD: a Gaussian's standard deviation).
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["LEVEL_Z", "SHARE", "STABLE_REACH", "MIN_STABLE", "stable_part", "measured_registration_error", "with_level",
           "systematic"]

LEVEL_Z = 1.96  # two-sided 95 %: the level of detection's promise
SHARE = 0.05  # share of the stable part beyond the level
STABLE_REACH = 2.0  # σ_p: a surface nearer the other epoch's is unchanged for the density test
ROBUST_BOUND = 5.0  # robust standard deviations of the standardised distances: what moved within reach
MIN_STABLE = 100  # places the 5 % quantile is read from: its standard error √(0.05·0.95/n) is 2.2 % at 100
_SAMPLE = 200_000  # places read for the quantile: a 5 % share to about ±0.05 %


def stable_part(distance: np.ndarray, random_sd: np.ndarray, sigma_p: float) -> np.ndarray:
    """The places within the density test's reach, ``|distance| ≤ 2σ_p``, whose distance in units
    of its own random part is within five robust standard deviations of the median there
    (module docstring)."""
    with np.errstate(invalid="ignore"):
        near = np.flatnonzero((np.abs(distance) <= STABLE_REACH * sigma_p) & (random_sd > 0))
    out = np.zeros(distance.shape, bool)
    if near.size:
        z = distance[near] / random_sd[near]
        dev = np.abs(z - np.median(z))
        out[near[dev <= ROBUST_BOUND * 1.4826 * np.median(dev)]] = True
    return out


def measured_registration_error(distance: np.ndarray, random_sd: np.ndarray, sigma_p: float) -> float | None:
    """The smallest ``reg ≥ 0`` with at most 5 % of the stable part (:func:`stable_part`) beyond
    ``1.96·(random_sd + reg)`` (``random_sd``: each place's √(s₁²/n₁ + s₂²/n₂)); None where the
    stable part holds fewer than 100 places, too few to tell a 5 % share within ±2 %."""
    step = max(1, distance.size // _SAMPLE)  # a regular sample: the places are in no particular order
    distance, random_sd = distance[::step], random_sd[::step]
    keep = stable_part(distance, random_sd, sigma_p)
    excess = np.abs(distance[keep]) / LEVEL_Z - random_sd[keep]
    if excess.size < MIN_STABLE:  # too few to read a 5 % share from
        return None
    k = int(SHARE * excess.size)
    return max(0.0, float(np.partition(excess, excess.size - 1 - k)[excess.size - 1 - k]))


def with_level(d, registration_error):
    """``d`` (:class:`sdp.Distances` measured with ``reg = 0``) with ``registration_error``
    measured on its stable part; ``d`` itself for a given number (the kernels added it)."""
    if registration_error != "auto":
        return d
    reg = measured_registration_error(d.distance, d.lod / LEVEL_Z, d.projection_scale / 4.0)
    if reg is None:
        return dataclasses.replace(d, registration_source=f"M3C2's 0: fewer than {MIN_STABLE} stable places")
    lod = d.lod + LEVEL_Z * reg
    return dataclasses.replace(d, lod=lod, significant=np.abs(d.distance) > lod, registration_error=reg,
                               registration_source="measured on the stable part")


def systematic(absd: np.ndarray, random: np.ndarray, g: np.ndarray) -> float:
    """Smallest σ_s ≥ 0 for which at most 5 % of the stable points lie beyond
    1.96·√(random + (σ_s·g)²). A point lies beyond it while σ_s < s_i =
    √((|d|/1.96)² − random)/g, so σ_s is the (k+1)-th largest s_i, k = ⌊5 % of the points⌋."""
    if absd.size == 0:
        return 0.0
    with np.errstate(invalid="ignore"):
        s_i = np.sqrt(np.maximum((absd / LEVEL_Z) ** 2 - random, 0.0)) / g
    k = int(SHARE * absd.size)
    # most s_i are 0 (points within their random part alone), and NumPy's selection slows down
    # about twentyfold on so many ties: select among the rest (NaN, if any, stays the largest)
    rest = s_i[~(s_i <= 0.0)]
    if k >= rest.size:
        return 0.0
    return float(np.partition(rest, rest.size - 1 - k)[rest.size - 1 - k])
