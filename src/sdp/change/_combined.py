"""One decision from the density and the distance (``decision="combined"`` of
:func:`sdp.detect_changes`).

The density masks answer "is there matter here that the other epoch did not have?": a point is
changed when the other epoch's density at it is below h, i.e. (:mod:`sdp.distance._distances`)
when it lies more than about 2σ from the other surface. Closer than that, an object resting on
or against an old surface (a box on the table, a cup against a wall) hides in the old
surface's kernel. The distance to the other epoch's surface, with a level of detection that
holds on the sensor (:func:`sdp.distance._noise.point_distances`), answers below 2σ.

The rule, per point of one direction:

1. coverage first (:func:`sdp.change._detect.judge_coverage`): a not comparable point stays so;
2. changed if the density says so, **or** (see 4) if its distance lies beyond the level of detection
   at 99.9 % rather than 95 % (``lod × 3.29/1.96``): a scan holds about 10⁴ cells of 1.5σ, and
   at 95 % several hundred cells of a static scene would pass by chance; where the other scan's
   sensor is known, only a point *in front of* the other surface (towards that sensor) counts
   by distance: what appeared in front of an old surface stands between it and the sensor,
   while a point behind it is a place the old scan saw as empty space or could not see (the
   visibility test's business);
3. as Algorithm 1 asks of every change, the point must be matter of its own epoch: inside its
   own cluster volume (F < 0). A depth camera's "flying pixels" between a foreground edge and the
   background lie in front of the old surface but alone, below h;
4. regions on the combined decision: 26-connected components of the cells of 1.5σ holding a
   changed point. A component is kept only if the density found part of it, as its own decision
   does (in one of its regions, not a stray): the distance completes an object down to the old
   surface it stands on, it does not raise changes of its own, nor grow them from a stray. On
   the static Kinect pairs whole patches of a table come back several millimetres off (a depth
   camera's correlated errors between frames: the heavy tail the level of detection
   is calibrated to, 5 % beyond it), as far from the old surface as the lower part of a cup
   standing on it; what tells the cup is that its top stands out of the table's kernel. An
   object thinner than about 2σ lying flat stays unfound, as with the density alone.
   Components with fewer than ``min_region_points`` points are strays.

The distance and its level are kept per point (the ``distance`` and ``lod`` output fields).

References
----------
.. [1] D. Lague et al. 2013 (M3C2's level of detection); A. W. Vieira et al. (the density masks).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ._coverage import CHANGED, UNCHANGED
from ._regions import describe_regions

__all__ = ["combine_decision", "DECISION_FACTOR"]

#: The decision's level against the 95 % level of detection: z(99.9 %) / z(95 %).
DECISION_FACTOR = 3.2905 / 1.96


def combine_decision(points: np.ndarray, other: np.ndarray, states: np.ndarray, *, sigma: float,
                     voxel_size: float, own_origin=None, other_origin=None, min_region_points: int = 50,
                     regions: bool = True, present: np.ndarray | None = None, found: np.ndarray | None = None):
    """(changed mask, regions, region label per point, distance, lod) of one direction.

    ``points``/``other``: the finite points of this epoch and of the other; ``states``: their
    states after the density test and coverage (:mod:`sdp.change._coverage`); ``present``: the
    points inside their own epoch's cluster volume (F < 0), the only ones the distance may mark;
    ``found``: the points the density's own decision keeps (its regions of ``min_region_points``,
    default every point it marks), the only ones that keep a component (rule 4)."""
    from ..distance._noise import point_distances  # the distances load only for this decision

    pd = point_distances(points, other, sigma=sigma, own_origin=own_origin, other_origin=other_origin,
                         stable=states == UNCHANGED)
    beyond = DECISION_FACTOR * pd.lod
    with np.errstate(invalid="ignore"):
        far = pd.distance > beyond if other_origin is not None else np.abs(pd.distance) > beyond
    if present is not None:  # matter of its own epoch (F < 0), as Algorithm 1 asks of a change
        far &= present
    changed = (states == CHANGED) | ((states == UNCHANGED) & far)
    labels, counts = _cell_components(pd.cells, pd.cell_index, changed)
    if len(counts):  # the distance completes what the density found (rule 4)
        seeded = np.zeros(len(counts), bool)
        seeded[labels[(states == CHANGED) if found is None else found]] = True
        changed &= seeded[np.maximum(labels, 0)]
        if min_region_points > 1:
            changed &= counts[np.maximum(labels, 0)] >= min_region_points
        labels = np.where(changed, labels, -1)
    if regions:
        regs, region_of = describe_regions(points, labels, counts, voxel_size)
    else:
        regs, region_of = [], np.where(changed, 0, -1)
    return changed, regs, region_of, pd.distance, pd.lod


def _cell_components(cells: np.ndarray, cell_index: np.ndarray, changed: np.ndarray):
    """(label per point, -1 if not changed; points per component) of the 26-connected cells that
    hold a changed point."""
    labels = np.full(len(cells), -1, np.int64)
    hit = np.unique(cells[changed])
    if hit.size == 0:
        return labels, np.zeros(0, np.int64)
    pairs = cKDTree(cell_index[hit]).query_pairs(1.8, output_type="ndarray")  # √3 < 1.8 < 2
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(hit.size, hit.size))
    n, comp = connected_components(graph, directed=False)
    of_cell = np.full(len(cell_index), -1, np.int64)
    of_cell[hit] = comp
    labels[changed] = of_cell[cells[changed]]
    return labels, np.bincount(labels[changed], minlength=n)
