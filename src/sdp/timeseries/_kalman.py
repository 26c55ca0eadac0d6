"""Change through time at every core point: a constant-velocity Kalman filter and its
Rauch–Tung–Striebel smoother, with steps taken as they come.

State ``(d, v)``: the change since the reference and its rate. Between epochs ``dt`` apart the
change moves by ``v·dt`` and a white-noise acceleration of spectral density ``q`` perturbs both
(``Q = q·[[dt³/3, dt²/2], [dt²/2, dt]]``). Each epoch observes ``d`` with the variance of its own
level of detection, ``(lod/1.96)²`` (M3C2's LoD95 is 1.96 standard deviations), as Winiwarter
et al. [1]_ do, less the reference cylinder's part: every epoch is measured against the same
reference, so that part is one error shared by the whole series, which smoothing cannot average
away; the caller adds it once to the smoothed variance
(:func:`observation_variance`). Not-comparable epochs are skipped
(prediction only).

- **Process noise from the data**: ``q`` makes the robust spread (1.4826 × the median absolute
  value) of the standardised second differences of the observed series equal to one: the
  differences of consecutive slopes, ``(z₃−z₂)/h₂ − (z₂−z₁)/h₁``, have the variance of the three
  observations' noise plus ``q·(h₁+h₂)/3``. Pooled over the core points, the median is not moved
  by the few places that step, so a series of stable ground and steady creep gets a small ``q``
  and the smoother averages over many epochs; where nothing but noise is seen, ``q`` is a tiny
  floor that keeps the covariances positive.
- **Steps**: an observation more than ``k`` (default 4) standard deviations of its innovation
  away from the prediction, confirmed by the next epoch lying as far on the same side, is a step:
  the position's variance is raised by the innovation's square before the update, so the filter
  takes the new level at once and the smoother does not carry the step back into the epochs
  before it (an intervention, as in structural time-series models [2]_). Its epoch is recorded.
  A step too small for one epoch to show is found afterwards by all the epochs together
  (:func:`step_scan`: a line plus a step against the line, the step's epoch chosen where it
  explains most, kept beyond 16, 4σ); those points are smoothed again with the step there. A
  step found on stable ground re-levels a series that stays near zero: no change, no onset.
- Smoothed values and their standard deviations (the smoother's covariance) for ``d`` and ``v``.

The filter, the smoother and the step scan are Numba kernels that take one core point at a time
(in parallel) through its epochs, reading a copy of the block with each point's epochs side by
side; :func:`smooth` is called on blocks of core points sized from the memory limit
(:data:`BYTES_PER_VALUE`).

References
----------
.. [1] L. Winiwarter, K. Anders, D. Czerwonka-Schröder, B. Höfle, "Full four-dimensional change
   analysis of topographic point cloud time series using Kalman filtering", Earth Surface
   Dynamics 11 (2023) 593–613.
.. [2] A. C. Harvey, "Forecasting, Structural Time Series Models and the Kalman Filter",
   Cambridge University Press (1989).
.. [3] H. E. Rauch, F. Tung, C. T. Striebel, "Maximum likelihood estimates of linear dynamic
   systems", AIAA Journal 3(8) (1965) 1445–1450.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["observation_variance", "process_noise", "smooth", "kalman", "step_scan", "BYTES_PER_VALUE"]

#: Working memory of :func:`smooth` and its caller per epoch and core point, a bound: the float64
#: inputs and their transposed copies (32 B), the four float64 outputs (32 B) and as much again for
#: the columns smoothed a second time, the float32 reads and results (24 B); 320 leaves room for
#: the allocator and NumPy's temporaries.
BYTES_PER_VALUE = 320
_STEP_K = 4.0
_SCAN = 16.0  # the step scan's statistic (χ²(1) at one epoch): 4σ, 6e-5 per epoch tried


def observation_variance(lod: np.ndarray, registration_error: np.ndarray, ref_var: np.ndarray) -> np.ndarray:
    """Each epoch's own noise variance (epochs, points) from its level of detection: the level's
    standard deviation ``lod/1.96 = sqrt(ref_var + epoch_var) + registration_error`` without the
    reference's part ``ref_var``, which every epoch shares. Treated as independent, that part would
    average away over many epochs and a stable place would read as changed by its reference's
    noise; it is added once to the smoothed variance instead."""
    reg = np.asarray(registration_error, np.float64)[:, None]
    sd = np.maximum(lod.astype(np.float64) / 1.96 - reg, 0.0)
    # float32 levels: where the epoch's part is below their rounding, keep a thousandth of the whole
    own = np.maximum(sd**2 - ref_var, 1e-3 * sd**2)
    return (np.sqrt(own) + reg) ** 2


def _second_differences(z, var, t):
    """(slope differences, their noise variance, (h₁+h₂)/3) of consecutive valid triples, flattened."""
    h = np.diff(t)
    h1, h2 = h[:-1, None], h[1:, None]
    u = (z[2:] - z[1:-1]) / h2 - (z[1:-1] - z[:-2]) / h1
    noise = var[2:] / h2**2 + var[1:-1] * (1.0 / h1 + 1.0 / h2) ** 2 + var[:-2] / h1**2
    span = np.broadcast_to((h1 + h2) / 3.0, u.shape)
    ok = np.isfinite(u) & np.isfinite(noise) & (noise > 0)
    return u[ok], noise[ok], span[ok]


def process_noise(z: np.ndarray, var: np.ndarray, t: np.ndarray, *, max_samples: int = 200_000) -> float:
    """The white-noise acceleration density ``q`` (see the module docstring) of series ``z``
    (epochs, points) observed with variances ``var`` at times ``t``."""
    t = np.asarray(t, np.float64)
    if len(t) < 3:
        return 0.0
    u, noise, span = _second_differences(np.asarray(z, np.float64), np.asarray(var, np.float64), t)
    if u.size > max_samples:  # an even sample over epochs and points: the median needs no more
        step = u.size // max_samples + 1
        u, noise, span = u[::step], noise[::step], span[::step]
    floor = 1e-6 * float(np.median(noise)) / float(np.median(span)) if u.size else 0.0
    if u.size < 10:
        return floor

    def spread(q):
        return 1.4826 * np.median(np.abs(u) / np.sqrt(noise + q * span))

    if spread(0.0) <= 1.0:
        return floor
    lo, hi = 0.0, float(np.median(u**2 / span)) + floor
    while spread(hi) > 1.0:
        hi *= 4.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if spread(mid) > 1.0 else (lo, mid)
    return max(hi, floor)


def step_scan(z: np.ndarray, var: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(best step epoch, its statistic) per column: the likelihood ratio of a line plus a step at
    epoch s against the line alone (weighted least squares, weights 1/var), maximised over s with
    at least two observations on each side; χ²(1) for one s. All s at once from sums over the
    tail: with the line's residuals r, the statistic is (Σ_{k≥s} w r)² / (Σ_{k≥s} w − gᵀG⁻¹g)."""
    z = np.asarray(z, np.float64)
    t = np.asarray(t, np.float64)
    at = np.zeros(z.shape[1], np.int64)
    stat = np.zeros(z.shape[1])
    if len(t):  # each point's epochs side by side, as the kernel walks them
        _step_scan(np.ascontiguousarray(z.T), np.ascontiguousarray(np.asarray(var, np.float64).T), t - t.mean(), at,
                   stat)
    return at, stat


@nb.njit(cache=True, parallel=True)
def _step_scan(z, var, tc, at, stat):
    """:func:`step_scan`'s kernel on (points, epochs) arrays, centred times ``tc``: fills ``at``, ``stat``."""
    m, E = z.shape
    for j in nb.prange(m):
        s0 = s1 = s2 = z0 = z1 = 0.0
        n_ok = 0
        for k in range(E):
            if np.isfinite(z[j, k]) and np.isfinite(var[j, k]) and var[j, k] > 0:
                w = 1.0 / var[j, k]
                s0 += w
                s1 += w * tc[k]
                s2 += w * tc[k] * tc[k]
                z0 += w * z[j, k]
                z1 += w * tc[k] * z[j, k]
                n_ok += 1
        det = s0 * s2 - s1 * s1
        if not det > 1e-300 * max(s0 * s2, 1e-300):
            continue
        a, b = (s2 * z0 - s1 * z1) / det, (s0 * z1 - s1 * z0) / det
        num = g0 = g1 = 0.0
        count = 0
        best, best_at = 0.0, 0
        for k in range(E - 1, 0, -1):  # the tail sums Σ_{k≥s}; s = 0 is no step
            if np.isfinite(z[j, k]) and np.isfinite(var[j, k]) and var[j, k] > 0:
                w = 1.0 / var[j, k]
                num += w * (z[j, k] - a - b * tc[k])
                g0 += w
                g1 += w * tc[k]
                count += 1
            den = g0 - (s2 * g0 * g0 - 2 * s1 * g0 * g1 + s0 * g1 * g1) / det
            if count >= 2 and count <= n_ok - 2 and den > 1e-12 * max(g0, 1e-300):
                value = num * num / den
                if value > 0 and value >= best:  # ties: the earliest epoch (none found: 0)
                    best, best_at = value, k
        at[j] = best_at
        stat[j] = best


def smooth(z: np.ndarray, var: np.ndarray, t: np.ndarray, q: float, *, step_k: float = _STEP_K,
           scan: float = _SCAN, scale: float | None = None):
    """The smoother of :func:`kalman` with steps found twice: by the filter's innovations, then by
    :func:`step_scan` where a step too small for one epoch to show is seen by all of them (its
    statistic beyond ``scan``); those points are smoothed again with a step there. Same returns
    as :func:`kalman`."""
    sm, vel, ssd, vsd, step = kalman(z, var, t, q, step_k=step_k, scale=scale)
    if len(t) < 5 or not scan:
        return sm, vel, ssd, vsd, step
    at, stat = step_scan(z, var, t)
    todo = np.flatnonzero((stat > scan) & (step < 0))
    if todo.size:
        again = kalman(z[:, todo], var[:, todo], t, q, step_k=step_k, forced=at[todo], scale=scale)
        for out, new in zip((sm, vel, ssd, vsd), again[:4]):
            out[:, todo] = new
        step[todo] = np.where((again[4] >= 0) & (again[4] < at[todo]), again[4], at[todo])
    return sm, vel, ssd, vsd, step


def kalman(z: np.ndarray, var: np.ndarray, t: np.ndarray, q: float, *, step_k: float = _STEP_K, forced=None,
           scale: float | None = None):
    """Kalman filter and RTS smoother of each column of ``z`` (epochs, points).

    Parameters
    ----------
    z, var : ndarray (E, m)
        Observed change and its variance (NaN: no observation).
    t : ndarray (E,)
        Epoch times, increasing.
    q : float
        Process noise density (:func:`process_noise`).
    step_k : float
        Innovations beyond this many standard deviations, confirmed by the next epoch, are steps.
    forced : ndarray (m,) int, optional
        An epoch per point where a step is taken whatever its innovation (-1: none).
    scale : float, optional
        The noise's typical standard deviation, which sets the width of the diffuse start
        (default: from these columns; give one value for every block of a series, so that blocks
        give the numbers of the whole).

    Returns
    -------
    (smoothed, velocity, smoothed_sigma, velocity_sigma) : ndarray (E, m) float64
    step : ndarray (m,) int32
        The epoch of each point's first step, -1 if none.
    """
    z = np.ascontiguousarray(z, np.float64)
    var = np.ascontiguousarray(var, np.float64)
    t = np.asarray(t, np.float64)
    E, m = z.shape
    if scale is None:
        ok = np.isfinite(z) & np.isfinite(var) & (var > 0)
        scale = float(np.sqrt(np.median(var[ok]))) if ok.any() else 1.0
    dt0 = float(np.median(np.diff(t))) if E > 1 else 1.0
    # a diffuse start, 1000 noise deviations wide: wider, and the smoother's 2×2 inverse loses its digits
    big_d, big_v = (1e3 * scale) ** 2, (1e3 * scale / dt0) ** 2
    forced = np.full(m, -1, np.int64) if forced is None else np.asarray(forced, np.int64)
    out = np.empty((4, E, m))
    step = np.full(m, -1, np.int32)
    # the inputs with each point's epochs side by side, as the kernel reads them
    _kalman_columns(np.ascontiguousarray(z.T), np.ascontiguousarray(var.T), t, float(q), float(step_k), forced,
                    big_d, big_v, out, step)
    return out[0], out[1], out[2], out[3], step


@nb.njit(cache=True, parallel=True)
def _kalman_columns(z, var, t, q, step_k, forced, big_d, big_v, out, step):
    """The filter and smoother of :func:`kalman` on (points, epochs) arrays, one core point per
    iteration (its epochs in a scratch of ten values per epoch)."""
    m, E = z.shape
    for j in nb.prange(m):
        xp = np.empty((E, 2))  # predictions
        Pp = np.empty((E, 3))  # their covariances: 00, 01, 11
        xf = np.empty((E, 2))
        Pf = np.empty((E, 3))
        x0, x1 = 0.0, 0.0
        p00, p01, p11 = big_d, 0.0, big_v
        seen = False
        for k in range(E):
            if k:
                h = t[k] - t[k - 1]
                x0 = x0 + h * x1
                p00, p01, p11 = (p00 + 2 * h * p01 + h * h * p11 + q * h**3 / 3.0,
                                 p01 + h * p11 + q * h * h / 2.0, p11 + q * h)
                if forced[j] == k:
                    p00 = p00 + big_d
            ok = np.isfinite(z[j, k]) and np.isfinite(var[j, k]) and var[j, k] > 0
            seen = seen or ok
            nu = z[j, k] - x0 if ok else 0.0
            s = p00 + var[j, k] if ok else np.inf
            if ok and 0 < k < E - 1:
                ok2 = np.isfinite(z[j, k + 1]) and np.isfinite(var[j, k + 1]) and var[j, k + 1] > 0
                if ok2:
                    h = t[k + 1] - t[k]
                    nu2 = z[j, k + 1] - (x0 + h * x1)
                    s2 = p00 + 2 * h * p01 + h * h * p11 + var[j, k + 1]
                    if (abs(nu) > step_k * np.sqrt(s) and abs(nu2) > step_k * np.sqrt(s2)
                            and np.sign(nu) == np.sign(nu2)):
                        p00 = p00 + nu * nu
                        s = s + nu * nu
                        if step[j] < 0:
                            step[j] = k
            xp[k, 0], xp[k, 1] = x0, x1
            Pp[k, 0], Pp[k, 1], Pp[k, 2] = p00, p01, p11
            g0, g1 = p00 / s, p01 / s  # gain (0 where there is no observation: s = inf)
            x0, x1 = x0 + g0 * nu, x1 + g1 * nu
            p00, p01, p11 = p00 - g0 * p00, p01 - g0 * p01, p11 - g1 * p01
            xf[k, 0], xf[k, 1] = x0, x1
            Pf[k, 0], Pf[k, 1], Pf[k, 2] = p00, p01, p11
        if not seen:
            out[:, :, j] = np.nan
            continue
        # Rauch–Tung–Striebel: back from the last epoch
        s0, s1 = x0, x1
        q00, q01, q11 = p00, p01, p11
        out[0, E - 1, j], out[1, E - 1, j] = s0, s1
        out[2, E - 1, j], out[3, E - 1, j] = np.sqrt(max(q00, 0.0)), np.sqrt(max(q11, 0.0))
        for k in range(E - 2, -1, -1):
            h = t[k + 1] - t[k]
            f00, f01, f11 = Pf[k, 0], Pf[k, 1], Pf[k, 2]
            # C = Pf F' Pp⁻¹ with F = [[1, h], [0, 1]]
            a00, a01, a10, a11 = f00 + h * f01, f01, f01 + h * f11, f11
            b00, b01, b11 = Pp[k + 1, 0], Pp[k + 1, 1], Pp[k + 1, 2]
            det = b00 * b11 - b01 * b01
            i00, i01, i11 = b11 / det, -b01 / det, b00 / det
            c00, c01 = a00 * i00 + a01 * i01, a00 * i01 + a01 * i11
            c10, c11 = a10 * i00 + a11 * i01, a10 * i01 + a11 * i11
            e0, e1 = s0 - xp[k + 1, 0], s1 - xp[k + 1, 1]
            s0, s1 = xf[k, 0] + c00 * e0 + c01 * e1, xf[k, 1] + c10 * e0 + c11 * e1
            d00, d01, d11 = q00 - b00, q01 - b01, q11 - b11
            # P = Pf + C D C'
            t00, t01 = c00 * d00 + c01 * d01, c00 * d01 + c01 * d11
            t10, t11 = c10 * d00 + c11 * d01, c10 * d01 + c11 * d11
            q00 = f00 + t00 * c00 + t01 * c01
            q01 = f01 + t00 * c10 + t01 * c11
            q11 = f11 + t10 * c10 + t11 * c11
            out[0, k, j], out[1, k, j] = s0, s1
            out[2, k, j], out[3, k, j] = np.sqrt(max(q00, 0.0)), np.sqrt(max(q11, 0.0))
