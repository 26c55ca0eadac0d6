"""Where an epoch's sensor could not see the place measured, there is no distance.

M3C2's cylinder takes whatever points of the other epoch lie in it, and its search along the
normal finds the other epoch's surface wherever it lies. Neither asks whether that epoch's sensor
saw the place: a face turned away from the other scanner gets the points of the faces it did
see, where a cylinder straddles an edge, and the mean of an object's far side, centimetres to
decimetres off (a parked car's far face scanned from its other side: 1,011 of 1,080 core points
"significant" on a static street); where an epoch has no points in the cylinder at the core point
(:attr:`sdp.Distances.level` 1: found farther along the normal) the place may have been emptied,
or merely hidden, or outside the field of view. Where the sensor is known (a PCD's VIEWPOINT, an
E57 scan's pose), its rays tell, as they do for the change masks (:mod:`sdp.change._visibility`,
the same range image and band): a place is seen when the ray through it returns at its range (the
same surface) or beyond it (seen free), or returns nothing inside the field of view (free space,
as the masks take it); it is not seen when every return near its ray is nearer (hidden), or when
it lies outside the field of view or beyond the sensor's reach.

The place is where the epoch's surface was measured: the core point moved along the normal by
that epoch's mean offset in its cylinder (level 0), so a surface that moved towards the sensor,
hiding the old place, is measured where it now is and stays comparable. Where an epoch was found
only farther along the normal (level 1), the place is the core point itself (was it emptied, or
hidden?), unless the normal faces the core points' own sensor and the surface was found in front
of the core point, on the side that sensor saw it from, nearer than anything the reference held
along the normal there (:attr:`sdp.distance.PreparedReference.ref_front`): it is new, hides the
place itself (a balcony built before a wall, a door opened towards the scanner, a deposit on a
slope) and is measured where it stands: it is that epoch's own returns, which its sensor saw. A
surface found in front that the reference held as well (a ledge, a canopy, seen from elsewhere)
says nothing of the hidden place: no distance there.
With several scanners (a multi-scan E57), a place is seen when any scanner of that epoch saw it.
Places not seen get no distance (NaN: not comparable, as M3C2's places without points), so they
are neither significant nor counted in the level's calibration.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..change._range_image import RangeImage, sees
from ..change._visibility import image_camera, rays_sent, scanner_of_points, sensor_poles, sensor_range_noise
from ..defaults import DEFAULTS
from ._cells import CELL, RADIUS

__all__ = ["front_start", "not_seen", "without_unseen"]


def front_start(ref_mean: np.ndarray, sigma: float) -> np.ndarray:
    """Where to look for what the reference held in front of its core points: beyond its own
    surface (``ref_mean`` along the normal, NaN: the core point), the cylinder's half-length
    (RADIUS·σ_p) and the cells its search bridges (1.5 cells)."""
    return np.nan_to_num(np.asarray(ref_mean, np.float64)) + (RADIUS + 1.5 * CELL) * sigma


def without_unseen(d, cloud, xyz: np.ndarray, origins: np.ndarray | None, *, sigma: float, along=None,
                   facing: bool = False, free_ahead=None):
    """``d`` (:class:`sdp.Distances`) with no distance at the core points whose measured place
    the scan ``cloud`` (an array or a :class:`sdp.Cloud`; its finite points ``xyz``; its sensors
    ``origins``: (3,), or (k, 3) with the Cloud's :attr:`~sdp.Cloud.scan`, or None) could not
    see; ``d`` itself when nothing changes.

    The place is where that epoch's surface was measured, ``along`` (m,) from the core point
    along the normal (its cylinder's mean offset; NaN or None: the core point), where both
    epochs answered at the core point (level 0); the core point itself where an epoch was found
    only farther along the normal (level 1): was the place emptied, or hidden? ``facing``: the
    normals face the core points' own sensor, so a scanner behind the surface (on the other side
    of its normal) saw its back, not the place: a wall's far face is no measurement of
    its near one; and a surface found farther in front of the core point (``along`` > 0, level 1),
    nearer than ``free_ahead`` (m,) (how far in front the reference held nothing; NaN: unknown),
    is new: it is the epoch's own returns, measured where it stands, whatever the place behind it
    (module docstring)."""
    measured = np.flatnonzero(np.isfinite(d.distance))
    if origins is None or measured.size == 0:
        return d
    scan = None
    if np.ndim(origins) == 2:  # several scanners: the cloud says which saw each point
        scan = scanner_of_points(cloud, origins, len(getattr(cloud, "xyz", cloud)))
        if len(scan) != len(xyz):  # rows with NaN were dropped from xyz
            scan = scan[np.isfinite(cloud.xyz).all(axis=1)]
    offset = np.zeros(measured.size) if along is None else np.asarray(along, np.float64)[measured]
    new = np.zeros(measured.size, bool)
    if facing and free_ahead is not None:  # found farther in front, where the reference held nothing
        with np.errstate(invalid="ignore"):
            new = (d.level[measured] == 1) & (offset > 0) & (offset < np.asarray(free_ahead, np.float64)[measured])
    # a new surface is the epoch's own returns, which its sensor saw: only the other places are asked
    asked = measured[~new]
    offset = np.where((d.level[asked] == 0) & np.isfinite(offset[~new]), offset[~new], 0.0)
    places = d.core_points[asked] + offset[:, None] * d.normal[asked]
    hidden = asked[not_seen(places, xyz, origins, scan, sigma=sigma,
                            normals=d.normal[asked] if facing else None,
                            range_noise=sensor_range_noise(cloud, DEFAULTS.range_noise, xyz=xyz, origin=origins),
                            rays=rays_sent(cloud), camera=image_camera(cloud, origins),
                            poles=sensor_poles(cloud, origins))]
    if hidden.size == 0:
        return d
    distance, lod, level = d.distance.copy(), d.lod.copy(), d.level.copy()
    distance[hidden] = lod[hidden] = np.nan
    level[hidden] = -1
    return dataclasses.replace(d, distance=distance, lod=lod, significant=np.abs(distance) > lod, level=level,
                               not_seen=d.not_seen + int(hidden.size))


def not_seen(points: np.ndarray, cloud: np.ndarray, origins: np.ndarray, scan: np.ndarray | None, *,
             sigma: float, normals: np.ndarray | None = None, range_noise: float = DEFAULTS.range_noise,
             rays: bool = True, camera=None, poles: np.ndarray | None = None) -> np.ndarray:
    """Which of ``points`` the scan ``cloud`` could not see from ``origins`` (one position (3,),
    or k positions (k, 3) with ``scan``, each point of ``cloud``'s scanner): hidden from every
    scanner, or outside every field of view (module docstring), or with ``normals`` (each
    place's surface normal, facing its own sensor) behind every scanner's back. The band around
    a return is the change masks' (``range_noise``·r², at least σ); ``rays``: the scan sent every
    ray of its view (:func:`sdp.change._visibility.rays_sent`), as the change masks ask; ``camera``:
    the pinhole of one camera's organized frame (:func:`sdp.change._visibility.image_camera`);
    ``poles``: each scanner's vertical, shaped as ``origins`` (:func:`sdp.change._visibility.sensor_poles`),
    or None."""
    unseen = np.ones(len(points), bool)
    if len(points) == 0:
        return unseen
    origins = np.asarray(origins, np.float64)
    verticals = [None] * len(origins.reshape(-1, 3)) if poles is None else np.reshape(poles, (-1, 3))
    for j, origin in enumerate(origins.reshape(-1, 3)):
        mine = cloud if origins.ndim == 1 else cloud[scan == j]
        todo = np.flatnonzero(unseen)
        if len(mine) == 0 or len(todo) == 0:
            continue
        query = np.take(points, todo, axis=0)
        image = RangeImage.from_points(mine, origin, rays_sent=rays, camera=camera if origins.ndim == 1 else None,
                                       pole=verticals[j])
        seen = sees(image, query, range_noise=range_noise, floor=sigma)
        if normals is not None:  # a scanner behind the surface saw its other side
            seen &= np.einsum("ij,ij->i", origin - query, normals[todo]) > 0
        unseen[todo] = ~seen
    return unseen
