"""Change through time at every core point: a constant-velocity Kalman filter and a fixed-lag
Rauch–Tung–Striebel smoother, with steps taken as they come.

State ``(d, v)``: the change since the reference and its rate. Between epochs ``dt`` apart the
change moves by ``v·dt`` and a white-noise acceleration of spectral density ``q`` perturbs both
(``Q = q·[[dt³/3, dt²/2], [dt²/2, dt]]``). Each epoch observes ``d`` with the variance of its own
level of detection, ``(lod/1.96)²`` (M3C2's LoD95 is 1.96 standard deviations), as Winiwarter
et al. [1]_ do, less the reference cylinder's part: every epoch is measured against the same
reference, so that part is one error shared by the whole series, which smoothing cannot average
away; the caller adds it once to the smoothed variance (:func:`observation_variance`).
Not-comparable epochs are skipped (prediction only).

- **Process noise from the data**: ``q`` makes the robust spread (1.4826 × the median absolute
  value) of the standardised second differences of the observed series equal to one: the
  differences of consecutive slopes, ``(z₃−z₂)/h₂ − (z₂−z₁)/h₁``, have the variance of the three
  observations' noise plus ``q·(h₁+h₂)/3``. Pooled over the core points, the median is not moved
  by the few places that step, so a series of stable ground and steady creep gets a small ``q``
  and the smoother averages over many epochs; where nothing but noise is seen, ``q`` is a tiny
  floor that keeps the covariances positive.
- **Steps**: an observation more than ``k`` (default 4) standard deviations of its innovation
  away from the prediction, confirmed by the next comparable epoch (within the lag, so that an
  append decides as the full run does) lying as far on the same side, is a step:
  the position's variance is raised by the innovation's square before the update, so the filter
  takes the new level at once and the smoother does not carry the step back into the epochs
  before it (an intervention, as in structural time-series models [2]_). Its epoch is recorded.
  Not confirmed, it is an outlier (a person, a parked car, a splash of rain): its variance is
  raised by the innovation's square, so it hardly moves the series. Without a next observation
  (the newest epochs, or none comparable within the lag) it counts as a step, which a later epoch
  confirms or revises. A confirmed jump that the next epoch carries on from as far again (in
  proportion to the time since the observation before the jump: nearer that than the jump's own
  level) is a change of rate: a steady
  change faster than the noise, which a step at every epoch would leave with no rate at all. The
  rate's variance is then raised by that rate's square too, so the filter learns it; its epoch is
  no step (the onset is gradual). Where the level's prediction is wider than one epoch's noise
  (extrapolated across a gap at a rate few epochs told), the innovation alone cannot see a step:
  the pair of epochs is then judged by a likelihood ratio [5]_ (:func:`_level_shift`), and a
  level shift that explains them better than an outlier or a change of rate is a step.
- **The reference is pinned**: its distance to itself is exactly 0, an observation of variance 0,
  so the smoothed change there is 0 ± 0 (the reference's shared part is not added to it).
- **The rate starts at 0 ± one of the point's noise deviations per typical time step** (the
  series' median interval, not the next one: epochs an hour apart do not make a rate of 24 deviations
  a day plausible) at its first
  observation (the change itself starts diffuse). A diffuse rate is set by the second epoch, so a
  step right after the reference would read as a rate, and the third epoch, predicted twice as
  far, as another step.
- **Fixed lag** [3]_ [4]_: epoch ``k`` is smoothed with the epochs up to ``k + lag`` (all of
  them for the last ``lag``). A smoother over the whole series would change every epoch when one
  is added; with a lag, an epoch is final once ``lag`` more have come, so appending an epoch
  filters on from the state saved ``lag`` epochs back and rewrites ``lag + 1`` rows, and the
  result is that of a run over all the epochs. The smoother's memory is the lag: a velocity is
  the slope of about ``lag`` epochs around it at most.
- Smoothed values and their standard deviations (the smoother's covariance) for ``d`` and ``v``.

The filter and the smoother are a Numba kernel that takes one core point at a time (in parallel)
through its epochs, reading a copy of the block with each point's epochs side by side; callers
size blocks of core points from the memory limit (:data:`BYTES_PER_VALUE`).

References
----------
.. [1] L. Winiwarter, K. Anders, D. Czerwonka-Schröder, B. Höfle, "Full four-dimensional change
   analysis of topographic point cloud time series using Kalman filtering", Earth Surface
   Dynamics 11 (2023) 593–613.
.. [2] A. C. Harvey, "Forecasting, Structural Time Series Models and the Kalman Filter",
   Cambridge University Press (1989).
.. [3] H. E. Rauch, F. Tung, C. T. Striebel, "Maximum likelihood estimates of linear dynamic
   systems", AIAA Journal 3(8) (1965) 1445–1450.
.. [4] S. Särkkä, "Bayesian Filtering and Smoothing", Cambridge University Press (2013), ch. 8
   (fixed-lag smoothing).
.. [5] A. S. Willsky, H. L. Jones, "A generalized likelihood ratio approach to the detection and
   estimation of jumps in linear systems", IEEE Trans. Automatic Control 21(1) (1976) 108–112.
"""

from __future__ import annotations

import numba as nb
import numpy as np

__all__ = ["observation_variance", "process_noise", "kalman", "FilterState", "BYTES_PER_VALUE"]

#: Working memory of :func:`kalman` and its caller per epoch and core point, a bound: the float64
#: inputs and their transposed copies (32 B), the four float64 outputs (32 B), the kernel's
#: scratch (80 B), the float32 reads and results (24 B); 320 leaves room for NumPy's temporaries.
BYTES_PER_VALUE = 320
_STEP_K = 4.0
#: The rate's standard deviation at a point's first observation, in the point's noise deviations
#: per typical (median) time step. A diffuse rate would take a step right after the first epoch for a rate (two
#: epochs cannot tell them apart, and the third is then predicted twice as far); one deviation
#: per step is what one epoch can resolve, and a few epochs outweigh it.
_RATE_PRIOR = 1.0


def observation_variance(lod: np.ndarray, registration_error: np.ndarray, ref_var: np.ndarray) -> np.ndarray:
    """Each epoch's own noise variance (epochs, points) from its level of detection: the level's
    standard deviation ``lod/1.96 = sqrt(ref_var + epoch_var) + registration_error`` without the
    reference's part ``ref_var``, which every epoch shares. Treated as independent, that part would
    average away over many epochs and a stable place would read as changed by its reference's
    noise; it is added once to the smoothed variance instead."""
    lod = np.asarray(lod)
    out = np.empty(lod.shape, np.float64)
    _own_variance(lod.reshape(len(lod), -1), np.asarray(registration_error, np.float64),
                  np.broadcast_to(np.asarray(ref_var, np.float64), lod.shape[1:]).reshape(-1),
                  out.reshape(len(lod), -1))
    return out


@nb.njit(cache=True, nogil=True)
def _own_variance(lod, reg, ref_var, out):
    """:func:`observation_variance`'s kernel (one pass: the epochs' rows are large)."""
    for e in range(lod.shape[0]):
        r = reg[e]
        for p in range(lod.shape[1]):
            sd = lod[e, p] / 1.96 - r
            if sd < 0.0:  # NaN stays NaN: a missing level
                sd = 0.0
            # float32 levels: where the epoch's part is below their rounding, keep a thousandth of the whole
            own, floor = sd * sd - ref_var[p], 1e-3 * sd * sd
            if own < floor:  # NaN stays NaN, as with np.maximum
                own = floor
            v = np.sqrt(own) + r
            out[e, p] = v * v


def _second_differences(z, var, t):
    """(slope differences, their noise variance, (h₁+h₂)/3, the triple's first epoch) of consecutive
    valid triples, flattened."""
    h = np.diff(t)
    h1, h2 = h[:-1, None], h[1:, None]
    u = (z[2:] - z[1:-1]) / h2 - (z[1:-1] - z[:-2]) / h1
    noise = var[2:] / h2**2 + var[1:-1] * (1.0 / h1 + 1.0 / h2) ** 2 + var[:-2] / h1**2
    span = np.broadcast_to((h1 + h2) / 3.0, u.shape)
    ok = np.isfinite(u) & np.isfinite(noise) & (noise > 0)
    return u[ok], noise[ok], span[ok], np.nonzero(ok)[0]


def process_noise(z: np.ndarray, var: np.ndarray, t: np.ndarray, *, max_samples: int = 200_000) -> float:
    """The white-noise acceleration density ``q`` (see the module docstring) of series ``z``
    (epochs, points) observed with variances ``var`` at times ``t``: the median over the triples of
    consecutive epochs of each triple's own ``q`` (the one for which its slope differences spread as
    their noise says, :func:`_triple_noise`; the lower of the two middle ones for an even count), so
    that one epoch unlike the others (snow, a misregistered scan), which enters three triples at
    every core point, moves it no more than a minority of triples can."""
    t = np.asarray(t, np.float64)
    if len(t) < 3:
        return 0.0
    u, noise, span, triple = _second_differences(np.asarray(z, np.float64), np.asarray(var, np.float64), t)
    if u.size > max_samples:  # an even sample over epochs and points: the median needs no more
        step = u.size // max_samples + 1
        u, noise, span, triple = u[::step], noise[::step], span[::step], triple[::step]
    floor = 1e-6 * float(np.median(noise)) / float(np.median(span)) if u.size else 0.0
    if u.size < 10:
        return floor
    starts = np.flatnonzero(np.r_[True, triple[1:] != triple[:-1]])  # triples in order (row-major flattening)
    ends = np.r_[starts[1:], u.size]
    each = [_triple_noise(u[a:b], noise[a:b], span[a:b], floor) for a, b in zip(starts, ends) if b - a >= 10]
    if not each:
        return _triple_noise(u, noise, span, floor)
    return float(np.sort(each)[(len(each) - 1) // 2])  # the lower median: one epoch in 3 of 6 triples moves it not


def _triple_noise(u, noise, span, floor: float) -> float:
    """The ``q`` for which the slope differences ``u`` spread (1.4826 × their median absolute
    value over their deviation) as their noise and the process say, at least ``floor``."""

    def spread(q):
        return 1.4826 * np.median(np.abs(u) / np.sqrt(noise + q * span))

    if spread(0.0) <= 1.0:
        return floor
    hi = float(np.median(u**2 / span)) + floor
    while spread(hi) > 1.0:
        hi *= 4.0
    return max(_root(lambda q: spread(q) - 1.0, 0.0, hi), floor)


def _root(f, lo: float, hi: float, *, rtol: float = 1e-12, most: int = 100) -> float:
    """The root of a continuous ``f`` with ``f(lo) > 0 >= f(hi)``, by the Illinois variant of
    false position (M. Dowell, P. Jarratt, BIT 11 (1971) 168–174): a dozen evaluations where
    bisection needs 60 (each one here a median over up to 200,000 values)."""
    f_lo, f_hi = f(lo), f(hi)
    side = 0
    for _ in range(most):
        if f_hi == 0.0 or hi - lo <= rtol * hi:
            break
        mid = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
        if not lo < mid < hi:
            mid = 0.5 * (lo + hi)
        f_mid = f(mid)
        if f_mid > 0.0:
            lo, f_lo = mid, f_mid
            f_hi = f_hi * 0.5 if side == 1 else f_hi
            side = 1
        else:
            hi, f_hi = mid, f_mid
            f_lo = f_lo * 0.5 if side == -1 else f_lo
            side = -1
    return hi


@nb.njit(cache=True, inline="always")
def _level_shift(d2, nu, x1, p00, p01, p11, s, h, before, q, var2, step_k):
    """The level shift at an epoch judged with the next comparable one ``h`` later (0.0: none):
    the generalised likelihood ratio of a jump in a linear system (Willsky and Jones [5]_) on the
    pair of innovations. Predicted from the state before the epoch, the pair ``(nu, nu + d2 −
    h·x1)`` has the covariance of the two predictions plus their noise; each alternative explains
    it along its own direction ``a``: a level shift ``(1, 1)``, an outlier at either epoch ``(1,
    0)`` or ``(0, 1)``, a change of rate from the observation ``before`` earlier ``(before, before
    + h)``. The shift's estimate is returned when its statistic ``(a'S⁻¹ν)² / a'S⁻¹a`` is beyond
    ``step_k²`` and above every other's: a jump across a long gap whose prediction was wide with
    the rate's uncertainty, with the epochs on both sides at their own level, is a step."""
    nu2 = nu + d2 - h * x1
    s12 = p00 + h * p01
    s22 = p00 + 2 * h * p01 + h * h * p11 + q * h**3 / 3.0 + var2
    det = s * s22 - s12 * s12
    if not det > 0.0:
        return 0.0
    i11, i12, i22 = s22 / det, -s12 / det, s / det
    b1, b2 = i11 * nu + i12 * nu2, i12 * nu + i22 * nu2  # S⁻¹ν
    best = -1.0
    for a1, a2 in ((1.0, 0.0), (0.0, 1.0), (before, before + h)):
        num = a1 * b1 + a2 * b2
        den = a1 * a1 * i11 + 2 * a1 * a2 * i12 + a2 * a2 * i22
        if den > 0.0 and num * num / den > best:
            best = num * num / den
    num, den = b1 + b2, i11 + 2 * i12 + i22
    if not den > 0.0 or num * num / den <= max(best, step_k * step_k):
        return 0.0
    return num / den


class FilterState:
    """Each core point's filter after one epoch (``epoch``; -1: before the first), which a later
    run filters on from: the state ``(d, v)``, its covariance (00, 01, 11) and the time of the last
    observation (NaN: none) in ``x`` (m, 6), the first epoch observed (``seen``, a large number if
    none) and of the first step (``step``, -1)."""

    def __init__(self, epoch: int, x: np.ndarray, seen: np.ndarray, step: np.ndarray):
        self.epoch, self.x, self.seen, self.step = int(epoch), x, seen, step

    @classmethod
    def start(cls, m: int) -> "FilterState":
        x = np.zeros((m, 6))
        x[:, 5] = np.nan
        return cls(-1, x, np.full(m, 2**62, np.int64), np.full(m, -1, np.int32))

    def columns(self, a: int, b: int) -> "FilterState":
        return FilterState(self.epoch, self.x[a:b], self.seen[a:b], self.step[a:b])


def kalman(z: np.ndarray, var: np.ndarray, t: np.ndarray, q: float, *, lag: int, scale: float, dt: float,
           state: FilterState | None = None, step_k: float = _STEP_K, reference: int | None = None):
    """Kalman filter and fixed-lag RTS smoother of each column of ``z``.

    Parameters
    ----------
    z, var : ndarray (W, m)
        Observed change and its variance (NaN: no observation) at the epochs after
        ``state.epoch``, up to the last of the series.
    t : ndarray (E,)
        All the epochs' times, increasing (``E = state.epoch + 1 + W``).
    q : float
        Process noise density (:func:`process_noise`).
    lag : int
        Epochs smoothed with those up to ``lag`` after them; the last ``lag`` with all that follow.
    scale, dt : float
        The noise's typical standard deviation, which sets the width of the diffuse start, and the
        typical time step (the rate's start at a point first observed at the newest epoch); a run
        and its appends give the same values for every block.
    state : FilterState, optional
        The filter after epoch ``state.epoch`` (default: before the first epoch).
    step_k : float
        Innovations beyond this many standard deviations, confirmed by the next epoch, are steps.
    reference : int, optional
        The reference epoch (among all ``E``): its distance to itself is exactly 0, an observation
        of variance 0 (``var`` is not read there), so the change there is 0 ± 0. None: no epoch is.

    Returns
    -------
    (smoothed, velocity, smoothed_sigma, velocity_sigma) : ndarray (R, m) float64
        Rows ``r0 = max(state.epoch, 0)`` to ``E - 1``: the saved epoch's row is final now.
    step : ndarray (m,) int32
        The epoch of each point's first step up to the last epoch, -1 if none.
    saved : FilterState
        The filter after epoch ``E - 1 - lag``, from which the next run (one more epoch or more)
        filters on.
    """
    z = np.ascontiguousarray(z, np.float64)
    var = np.ascontiguousarray(var, np.float64)
    t = np.asarray(t, np.float64)
    W, m = z.shape
    state = FilterState.start(m) if state is None else state
    E = state.epoch + 1 + W
    if len(t) != E:
        raise ValueError(f"{len(t)} times for {E} epochs")
    # the change starts diffuse, 1000 noise deviations wide: wider, and the smoother's 2×2 inverse
    # loses its digits (the rate's start is set at each point's first observation, _one_point)
    big_d = (1e3 * scale) ** 2
    r0 = max(state.epoch, 0)
    out = np.empty((4, E - r0, m))
    keep = E - 1 - lag
    x_out = state.x.copy()
    seen = state.seen.copy()
    step = state.step.copy()
    # the inputs with each point's epochs side by side, as the kernel reads them
    _fixed_lag(np.ascontiguousarray(z.T), np.ascontiguousarray(var.T), t, float(q), float(step_k), big_d, float(dt),
               int(lag), state.epoch, np.ascontiguousarray(state.x), keep, x_out, seen, step, out,
               -1 if reference is None else int(reference))
    if keep > state.epoch:
        saved = FilterState(keep, x_out, np.where(seen <= keep, seen, 2**62), np.where(step <= keep, step, -1)
                            .astype(np.int32))
    else:  # too few epochs yet to move the saved state
        saved = state
    return out[0], out[1], out[2], out[3], step, saved


@nb.njit(cache=True, parallel=True)
def _fixed_lag(z, var, t, q, step_k, big_d, dt, lag, f, x_in, keep, x_out, seen, step, out, ref):
    """:func:`kalman`'s kernel on (points, epochs) arrays, one core point per iteration (its epochs
    in a scratch of ten values per epoch): filtered on from epoch ``f`` (state ``x_in``), the state
    after epoch ``keep`` written to ``x_out``, rows from ``max(f, 0)`` smoothed into ``out``."""
    m, W = z.shape
    E = f + 1 + W
    base = max(f, 0)  # epoch of the scratch's first row
    R = E - base
    per = 64  # points per task: the scratch allocated once for them
    for block in nb.prange((m + per - 1) // per):
        xp = np.empty((R, 2))  # predictions
        Pp = np.empty((R, 3))  # their covariances: 00, 01, 11
        xf = np.empty((R, 2))
        Pf = np.empty((R, 3))
        for j in range(block * per, min(m, block * per + per)):
            _one_point(z, var, t, q, step_k, big_d, dt, lag, f, x_in, keep, x_out, seen, step, out, j, E, base,
                       xp, Pp, xf, Pf, ref)


@nb.njit(cache=True, inline="always")
def _one_point(z, var, t, q, step_k, big_d, dt, lag, f, x_in, keep, x_out, seen, step, out, j, E, base,
               xp, Pp, xf, Pf, ref):
    """:func:`_fixed_lag` for core point ``j`` in the scratch ``xp, Pp, xf, Pf``."""
    last_seen = np.nan  # the time of the last observation
    if f >= 0:
        x0, x1 = x_in[j, 0], x_in[j, 1]
        p00, p01, p11 = x_in[j, 2], x_in[j, 3], x_in[j, 4]
        last_seen = x_in[j, 5]
        xf[0, 0], xf[0, 1] = x0, x1
        Pf[0, 0], Pf[0, 1], Pf[0, 2] = p00, p01, p11
    else:
        x0, x1 = 0.0, 0.0
        p00, p01, p11 = big_d, 0.0, 0.0
    W = z.shape[1]
    for k in range(f + 1, E):
        w = k - f - 1  # column of the inputs
        r = k - base  # row of the scratch
        if k:
            h = t[k] - t[k - 1]
            x0 = x0 + h * x1
            p00, p01, p11 = (p00 + 2 * h * p01 + h * h * p11 + q * h**3 / 3.0,
                             p01 + h * p11 + q * h * h / 2.0, p11 + q * h)
        pinned = k == ref and np.isfinite(z[j, w])  # the reference against itself: exactly 0, variance 0
        ok = pinned or (np.isfinite(z[j, w]) and np.isfinite(var[j, w]) and var[j, w] > 0)
        if ok and seen[j] > k:
            seen[j] = k
            # the first observation: the change diffuse, its rate 0 ± _RATE_PRIOR of the point's
            # noise deviations (this epoch's or the next one's, the larger) per typical time step
            v = var[j, w] if np.isfinite(var[j, w]) and var[j, w] > 0 else 0.0
            if k < E - 1 and np.isfinite(var[j, w + 1]) and var[j, w + 1] > v:
                v = var[j, w + 1]
            x0, x1 = 0.0, 0.0
            p00, p01, p11 = big_d, 0.0, _RATE_PRIOR * _RATE_PRIOR * v / (dt * dt)
        nu = z[j, w] - x0 if ok else 0.0
        s = p00 + (0.0 if pinned else var[j, w]) if ok else np.inf
        if ok and k > 0:
            # the next comparable epoch within the lag, so that an append decides as the full run
            nxt = -1
            for w2 in range(w + 1, min(w + lag, W - 1) + 1):
                if np.isfinite(z[j, w2]) and np.isfinite(var[j, w2]) and var[j, w2] > 0:
                    nxt = w2
                    break
            shift = 0.0
            if nxt >= 0 and not pinned and p00 > var[j, w]:
                # the level predicted less well than one epoch measures it (extrapolated at an uncertain
                # rate across a gap): the innovation alone cannot tell a step, the pair of epochs can
                shift = _level_shift(z[j, nxt] - z[j, w], nu, x1, p00, p01, p11, s, t[f + 1 + nxt] - t[k],
                                     t[k] - (last_seen if np.isfinite(last_seen) else t[k - 1]),
                                     q, 0.0 if f + 1 + nxt == ref else var[j, nxt], step_k)
            jump = abs(nu) > step_k * np.sqrt(s)
            is_step = jump and (nxt < 0 or pinned)
            ramp = False
            if jump and not is_step:
                # beyond step_k deviations: a step if the next comparable epoch lies as far on the
                # same side, an outlier if it does not (the observation weighs as if its variance
                # held the innovation); without one (the newest epochs, or none comparable) it
                # counts as a step until one comes
                h = t[f + 1 + nxt] - t[k]
                nu2 = z[j, nxt] - (x0 + h * x1)
                s2 = p00 + 2 * h * p01 + h * h * p11 + var[j, nxt]
                is_step = abs(nu2) > step_k * np.sqrt(s2) and np.sign(nu) == np.sign(nu2)
                if is_step:
                    # a step stays at its new level; a change of rate goes on from it as far again
                    # (in proportion to the time since the observation before) by the next epoch:
                    # whichever the next epoch lies nearer to. A ramp (a steady change faster than
                    # the noise) opens the rate's variance by its square too, so the filter learns it
                    d2 = z[j, nxt] - z[j, w]
                    before = t[k] - (last_seen if np.isfinite(last_seen) else t[k - 1])
                    ramp = np.sign(d2) == np.sign(nu) and abs(d2) > 0.5 * abs(nu) * h / before
                    if ramp:
                        p11 = p11 + (d2 / h) ** 2
                elif shift == 0.0:
                    s = s + nu * nu
            if shift != 0.0 and not is_step:
                # not seen by the innovation alone, or judged an outlier by the next epoch as far
                # out, but the two epochs together are a level shift: a step across a gap the
                # rate was extrapolated over
                is_step = True
                nu_open = max(nu * nu, shift * shift)
                p00 = p00 + nu_open
                s = s + nu_open
                if step[j] < 0:
                    step[j] = k
            elif is_step:
                p00 = p00 + nu * nu
                s = s + nu * nu
                if step[j] < 0 and not ramp:  # a ramp's start is an onset of the gradual kind
                    step[j] = k
        xp[r, 0], xp[r, 1] = x0, x1
        Pp[r, 0], Pp[r, 1], Pp[r, 2] = p00, p01, p11
        g0, g1 = p00 / s, p01 / s  # gain (0 where there is no observation: s = inf)
        x0, x1 = x0 + g0 * nu, x1 + g1 * nu
        p00, p01, p11 = p00 - g0 * p00, p01 - g0 * p01, p11 - g1 * p01
        xf[r, 0], xf[r, 1] = x0, x1
        Pf[r, 0], Pf[r, 1], Pf[r, 2] = p00, p01, p11
        if ok:
            last_seen = t[k]
        if k == keep:
            x_out[j, 0], x_out[j, 1] = x0, x1
            x_out[j, 2], x_out[j, 3], x_out[j, 4] = p00, p01, p11
            x_out[j, 5] = last_seen
    # rows final now (each smoothed from lag epochs on), then the last ones from the last epoch
    last = E - 1
    for row in range(base, E):
        end = min(row + lag, last)
        if row + lag < last or row == max(base, last - lag):
            _rts(t, xp, Pp, xf, Pf, base, end, row, seen[j], out, j)
        if row + lag >= last:
            break


@nb.njit(cache=True, inline="always")
def _rts(t, xp, Pp, xf, Pf, base, end, stop, seen, out, j):
    """Rauch–Tung–Striebel back from epoch ``end`` to ``stop``: rows ``stop`` (and, from the last
    epoch, every row down to it) of ``out``; NaN where nothing was observed up to ``end``."""
    last = out.shape[1] + base - 1
    if seen > end:
        for k in range(stop, end + 1 if end == last else stop + 1):
            for a in range(4):
                out[a, k - base, j] = np.nan
        return
    r = end - base
    s0, s1 = xf[r, 0], xf[r, 1]
    q00, q01, q11 = Pf[r, 0], Pf[r, 1], Pf[r, 2]
    if end == last:
        out[0, r, j], out[1, r, j] = s0, s1
        out[2, r, j], out[3, r, j] = np.sqrt(max(q00, 0.0)), np.sqrt(max(q11, 0.0))
    for k in range(end - 1, stop - 1, -1):
        r = k - base
        h = t[k + 1] - t[k]
        f00, f01, f11 = Pf[r, 0], Pf[r, 1], Pf[r, 2]
        # C = Pf F' Pp⁻¹ with F = [[1, h], [0, 1]]
        a00, a01, a10, a11 = f00 + h * f01, f01, f01 + h * f11, f11
        b00, b01, b11 = Pp[r + 1, 0], Pp[r + 1, 1], Pp[r + 1, 2]
        det = b00 * b11 - b01 * b01
        if det > 1e-12 * b00 * b11:
            i00, i01, i11 = b11 / det, -b01 / det, b00 / det
        else:  # rank one (the level pinned at the reference, no process noise): the pseudo-inverse B / tr(B)²
            tr2 = (b00 + b11) ** 2
            i00, i01, i11 = (b00 / tr2, b01 / tr2, b11 / tr2) if tr2 > 0.0 else (0.0, 0.0, 0.0)
        c00, c01 = a00 * i00 + a01 * i01, a00 * i01 + a01 * i11
        c10, c11 = a10 * i00 + a11 * i01, a10 * i01 + a11 * i11
        e0, e1 = s0 - xp[r + 1, 0], s1 - xp[r + 1, 1]
        s0, s1 = xf[r, 0] + c00 * e0 + c01 * e1, xf[r, 1] + c10 * e0 + c11 * e1
        d00, d01, d11 = q00 - b00, q01 - b01, q11 - b11
        # P = Pf + C D C'
        t00, t01 = c00 * d00 + c01 * d01, c00 * d01 + c01 * d11
        t10, t11 = c10 * d00 + c11 * d01, c10 * d01 + c11 * d11
        q00 = f00 + t00 * c00 + t01 * c01
        q01 = f01 + t00 * c10 + t01 * c11
        q11 = f11 + t10 * c10 + t11 * c11
        if end == last or k == stop:
            out[0, r, j], out[1, r, j] = s0, s1
            out[2, r, j], out[3, r, j] = np.sqrt(max(q00, 0.0)), np.sqrt(max(q11, 0.0))
