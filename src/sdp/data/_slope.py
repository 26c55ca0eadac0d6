"""A simulated slope scanned many times, with known change: the truth for series of epochs.

A rough slope (a plane rising ``slope`` per unit of x, with bumps of a few centimetres) is
sampled afresh at every epoch (uniform random positions, noise along z of ``noise``) and moved by
a small rigid registration error (a translation of ``registration`` standard deviation per axis
and a tilt of a few hundredths of a degree). On it: a *creeping* disk moving along the slope's
normal at ``creep_rate`` per epoch time unit from the first epoch, and a *step* disk moving by
``step`` at epoch ``step_epoch``; everywhere else the ground is stable. :meth:`SlopeSeries.truth`
gives the true signed displacement along the plane's normal (the sign of M3C2 with normals up)
at any core point and epoch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SlopeSeries", "slope_series"]


@dataclass
class SlopeSeries:
    """Epochs of a simulated slope and its truth (see :func:`slope_series`)."""

    epochs: list  # (n, 3) float64 arrays
    times: np.ndarray
    size: float
    slope: float
    creep_centre: tuple
    creep_radius: float
    creep_rate: float
    step_centre: tuple
    step_radius: float
    step: float
    step_epoch: int
    noise: float
    registration: float

    @property
    def normal(self) -> np.ndarray:
        """The plane's unit normal (pointing up)."""
        n = np.array([-self.slope, 0.0, 1.0])
        return n / np.linalg.norm(n)

    def zone(self, xyz: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Per point: 1 creeping, 2 step, 0 stable, -1 within ``margin`` of a zone's edge (neither)."""
        out = np.zeros(len(xyz), np.int8)
        for label, centre, radius in ((1, self.creep_centre, self.creep_radius), (2, self.step_centre,
                                                                                    self.step_radius)):
            r = np.hypot(xyz[:, 0] - centre[0], xyz[:, 1] - centre[1])
            out[(r < radius + margin) & (out == 0)] = -1
            out[r < radius - margin] = label
        return out

    def truth(self, xyz: np.ndarray) -> np.ndarray:
        """(epochs, points): the true displacement along the normal of each core point at each epoch."""
        z = self.zone(xyz)
        t = self.times - self.times[0]
        out = np.zeros((len(t), len(xyz)))
        out[:, z == 1] = (self.creep_rate * t)[:, None]
        out[self.step_epoch:, z == 2] = self.step
        return out


def _surface(x, y, slope):
    return slope * x + 0.03 * np.sin(1.3 * x) * np.cos(0.9 * y) + 0.02 * np.sin(3.1 * y + 0.5 * x)


def slope_series(n_epochs: int = 25, points: int = 100_000, *, size: float = 20.0, noise: float = 0.004,
                 registration: float = 0.001, creep_rate: float = -0.002, step: float = 0.03,
                 step_epoch: int | None = None, seed: int = 0) -> SlopeSeries:
    """Epochs of a simulated slope with a creeping disk, a step and stable ground (module docstring).

    Parameters
    ----------
    n_epochs, points : int
        Epochs, points per epoch (times 0, 1, …).
    size : float
        The square's side (world units, metres).
    noise : float
        Standard deviation of each point's z.
    registration : float
        Standard deviation of each epoch's translation per axis (its tilt: registration / size rad).
    creep_rate : float
        The creeping disk's displacement along the normal per time unit.
    step, step_epoch : float, int
        The step disk's displacement and the epoch it happens (default: the middle epoch).

    Returns
    -------
    SlopeSeries
    """
    rng = np.random.default_rng(seed)
    step_epoch = n_epochs // 2 if step_epoch is None else step_epoch
    s = SlopeSeries(epochs=[], times=np.arange(n_epochs, dtype=np.float64), size=size, slope=0.3,
                    creep_centre=(0.3 * size, 0.5 * size), creep_radius=0.15 * size, creep_rate=creep_rate,
                    step_centre=(0.72 * size, 0.5 * size), step_radius=0.12 * size, step=step, step_epoch=step_epoch,
                    noise=noise, registration=registration)
    n = s.normal
    for k in range(n_epochs):
        xy = rng.uniform(0.0, size, (points, 2))
        xyz = np.c_[xy, _surface(xy[:, 0], xy[:, 1], s.slope)]
        xyz += s.truth(xyz)[k][:, None] * n[None, :]
        xyz[:, 2] += noise * rng.standard_normal(points)
        if k:  # the reference defines the frame; the others are registered onto it with a small error
            angle = rng.normal(0.0, registration / size, 3)
            cx, cy, cz = np.cos(angle)
            sx, sy, sz = np.sin(angle)
            rot = (np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]]) @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
                   @ np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]))
            centre = xyz.mean(axis=0)
            xyz = (xyz - centre) @ rot.T + centre + rng.normal(0.0, registration, 3)
        s.epochs.append(xyz)
    return s
