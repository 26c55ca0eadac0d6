"""Where an epoch's sensor could not see a core point, the distance there is not measured.

M3C2's search along the normal finds the other epoch's surface wherever it lies; where that epoch
has no points in the cylinder at the core point (:attr:`sdp.Distances.level` 1: found farther
along the normal) the place may have been emptied, or merely not seen by that epoch's sensor:
hidden behind something nearer, or outside its field of view. A distance to whatever surface lies
farther along the normal is then no measurement of that place, and M3C2 has no way to tell.
Where the sensor is known (a PCD's VIEWPOINT, an E57 scan's pose), its rays tell, as they do for
the change masks (:mod:`sdp.change._visibility`, the same range image and band): a place is seen
when the ray through it returns at its range (the same surface) or beyond it (seen free), or
returns nothing inside the field of view (free space, as the masks take it); it is not seen when
every return near its ray is nearer (hidden), or when it lies outside the field of view or beyond
the sensor's reach. With several scanners (a multi-scan E57), a place is seen when any scanner of
that epoch saw it. Places not seen get no distance (NaN: not comparable, as M3C2's places without
points), so they are neither significant nor counted in the level's calibration.

On the three static mOSD pairs this leaves 2,831, 3,440 and 0 of the 2,831, 5,648 and 6,358 places
found farther along the normal without a distance (``benchmarks/bench_level.py``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..change._visibility import HIDDEN, UNOBSERVED, RangeImage, scanner_of_points
from ..defaults import DEFAULTS

__all__ = ["not_seen", "without_unseen"]


def without_unseen(d, cloud, xyz: np.ndarray, origins: np.ndarray | None, *, sigma: float):
    """``d`` (:class:`sdp.Distances`) with no distance at the core points found only farther
    along the normal (level 1) that the scan ``cloud`` (an array or a :class:`sdp.Cloud`; its
    finite points ``xyz``; its sensors ``origins``: (3,), or (k, 3) with the Cloud's
    :attr:`~sdp.Cloud.scan`, or None) could not see; ``d`` itself when nothing changes."""
    far = np.flatnonzero(d.level == 1)
    if origins is None or far.size == 0:
        return d
    scan = None
    if np.ndim(origins) == 2:  # several scanners: the cloud says which saw each point
        scan = scanner_of_points(cloud, origins, len(cloud.xyz))
        if len(scan) != len(xyz):  # rows with NaN were dropped from xyz
            scan = scan[np.isfinite(cloud.xyz).all(axis=1)]
    hidden = far[not_seen(d.core_points[far], xyz, origins, scan, sigma=sigma)]
    if hidden.size == 0:
        return d
    distance, lod, level = d.distance.copy(), d.lod.copy(), d.level.copy()
    distance[hidden] = lod[hidden] = np.nan
    level[hidden] = -1
    return dataclasses.replace(d, distance=distance, lod=lod, significant=np.abs(distance) > lod, level=level,
                               not_seen=d.not_seen + int(hidden.size))


def not_seen(points: np.ndarray, cloud: np.ndarray, origins: np.ndarray, scan: np.ndarray | None, *,
             sigma: float) -> np.ndarray:
    """Which of ``points`` the scan ``cloud`` could not see from ``origins`` (one position (3,),
    or k positions (k, 3) with ``scan``, each point of ``cloud``'s scanner): hidden from every
    scanner, or outside every field of view (module docstring). The band around a return is
    the change masks' (``DEFAULTS.range_noise``·r², at least σ)."""
    unseen = np.ones(len(points), bool)
    if len(points) == 0:
        return unseen
    origins = np.asarray(origins, np.float64)
    for j, origin in enumerate(origins.reshape(-1, 3)):
        mine = cloud if origins.ndim == 1 else cloud[scan == j]
        todo = np.flatnonzero(unseen)
        if len(mine) == 0 or len(todo) == 0:
            continue
        image = RangeImage.from_points(mine, origin)
        query = np.take(points, todo, axis=0)
        cls = image.classify(query, range_noise=DEFAULTS.range_noise, floor=sigma)
        hidden = cls == HIDDEN
        outside = cls == UNOBSERVED
        outside[outside] = ~image.in_view(query[outside])
        unseen[todo] = hidden | outside
    return unseen
