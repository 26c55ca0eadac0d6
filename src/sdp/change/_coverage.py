"""Where two epochs can be compared: "not seen" is not "changed".

A density difference says that the other epoch has no point here. That is a change only where
the other epoch could have had one: inside its coverage. Every point of a comparison is in one
of three states (the values written in the ``change`` field of every output):

- :data:`UNCHANGED` (0): the other epoch has density here;
- :data:`CHANGED` (1): the other epoch covered this place and found it different;
- :data:`NOT_COMPARABLE` (2): the other epoch never saw this place, so nothing is known.

Coverage is decided from the other epoch's own data. With the sensor's position known
(:mod:`sdp.change._visibility`), by its rays: a place outside its field of view, or hidden from it, was
not seen. Without it (airborne and mobile scans, merged maps), by its footprint
(:func:`footprint_covered`): a place whose column (its x, y, at any height) the other epoch did
not sample densely enough for the density threshold lies outside that epoch's extent or in a
gap of its sampling. Any height, because a new building stands on ground the earlier flight
did cover: the footprint swallows no change inside the covered area. M3C2 answers NaN at
points not seen (no point of one epoch in its cylinder), and CloudCompare and PDAL leave them
out of their statistics; here they are counted, written and drawn as their own state.

The footprint (:meth:`sdp.DensityField.footprint`: G summed along z at the node columns,
× l/(√(2π)·σ), bilinear in x, y) is compared with the same h. It is never below the density,
so it only splits the changed points, and it fades at a flight's edge as the density does.

References
----------
.. [1] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
   terrestrial laser scanner: application to the Rangitikei canyon (N-Z)", ISPRS J.
   Photogramm. Remote Sens. 82, 2013 (M3C2: no distance where a cylinder holds no point).
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidOptionError

__all__ = ["UNCHANGED", "CHANGED", "NOT_COMPARABLE", "footprint_covered", "states_of"]

#: Values of the ``change`` field: unchanged, changed, not comparable.
UNCHANGED, CHANGED, NOT_COMPARABLE = 0, 1, 2


def footprint_covered(points: np.ndarray, other) -> np.ndarray:
    """Did the other epoch sample each point's column (its x, y, at any height) densely enough?

    True where the other field's density projected on the x, y plane
    (:meth:`sdp.DensityField.footprint`) reaches its threshold h: the same test as the density's
    own, on the column instead of the point. So a point the other epoch has density at is
    always covered (a footprint is never below the density), a point inside the covered area
    but above the other epoch's ground (a new roof) is covered, and the fringe beyond another
    flight's edge, where the density fades, fades from the footprint alike.

    Parameters
    ----------
    points : ndarray (n, 3) float64
        The points to test.
    other : DensityField
        The other epoch's field (the reference's for appeared points).

    Returns
    -------
    ndarray of bool (n,)
    """
    from ..fields._density import DensityField

    if not isinstance(other, DensityField):
        raise InvalidOptionError(f"footprint_covered takes the other epoch's DensityField, got {type(other).__name__}")
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0:
        return np.zeros(0, bool)
    return other.footprint(points) >= other.h


def states_of(changed: np.ndarray, not_comparable: np.ndarray) -> np.ndarray:
    """The ``change`` field (uint8: :data:`UNCHANGED`, :data:`CHANGED`, :data:`NOT_COMPARABLE`)
    of two disjoint masks."""
    out = np.asarray(changed, bool).astype(np.uint8)
    out[np.asarray(not_comparable, bool)] = NOT_COMPARABLE
    return out
