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
   Every component holds part of one of the density's regions, so none is a stray, and
   components holding parts of one density region are one region: the density's volume joins
   points farther apart than two cells (a sparse scan's edge of a roof), which the cells'
   components do not, and the combined decision keeps every point the density's decision keeps.

Because of rule 4 the distance matters only in components that hold what the density found:
they are grown from its cells outwards, ring by ring, and the distance is measured at those
cells and at the sample that calibrates the level (:class:`sdp.distance._noise.SurfaceDistances`),
not across the scene: a pair where the density finds nothing costs no distance at all. The
distance and its level are kept per point (the ``distance`` and ``lod`` output fields), measured
over the whole cloud when first read.

References
----------
.. [1] D. Lague et al. 2013 (M3C2's level of detection); A. W. Vieira et al. (the density masks).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numba as nb
import numpy as np

from .._core._disjoint import find, union
from ._coverage import CHANGED, UNCHANGED
from ._regions import describe_regions

if TYPE_CHECKING:
    from ..distance._noise import SurfaceDistances

__all__ = ["combine_decision", "joined_by_regions", "DECISION_FACTOR"]

#: The decision's level against the 95 % level of detection: z(99.9 %) / z(95 %).
DECISION_FACTOR = 3.2905 / 1.96


def combine_decision(sd: SurfaceDistances, states: np.ndarray, *, directed: bool,
                     present, found: np.ndarray, found_regions: np.ndarray, regions: bool = True):
    """(changed mask, regions, region label per point) of one direction.

    ``sd``: the distances of this epoch's finite points to the other epoch
    (:class:`sdp.distance._noise.SurfaceDistances`); ``states``: their states after the density
    test and coverage (:mod:`sdp.change._coverage`); ``directed``: the other scan's sensor is
    known, so only a point in front of the other surface counts by distance; ``present(points)``:
    which points lie inside their own epoch's cluster volume (F < 0), the only ones the distance
    may mark; ``found``: the points the density's own decision keeps (its regions of
    ``min_region_points``), the only ones that keep a component (rule 4), and ``found_regions``
    their regions there.

    The components are grown from the cells of ``found`` outwards, cell ring by cell ring, so
    that the distance is measured only at the cells next to what the density found (and at the
    sample that calibrates the level), not across the whole scene."""
    n = len(states)
    density = states == CHANGED
    marked = np.zeros(n, bool)  # unchanged by density, changed by distance (rules 2 and 3)
    in_component = np.zeros(len(sd.cell_index), bool)

    def grow(rows):
        """Mark the points of cells ``rows`` that the distance changes; the cells holding a change."""
        every = sd.points_of(rows)
        idx = every[states[every] == UNCHANGED]
        if idx.size:
            d, lod = sd.at(idx)
            beyond = DECISION_FACTOR * lod
            with np.errstate(invalid="ignore"):
                far = d > beyond if directed else np.abs(d) > beyond
            far_idx = idx[far]
            if far_idx.size:  # matter of its own epoch (F < 0), as Algorithm 1 asks of a change
                marked[far_idx[present(sd.points[far_idx])]] = True
        return sd.cells_of(every[density[every] | marked[every]])

    frontier = sd.cells_of(found)
    visited = np.zeros(len(sd.cell_index), bool)
    visited[frontier] = True
    grow(frontier)
    while frontier.size:
        in_component[frontier] = True
        frontier = grow(sd.neighbours(frontier, visited))
    changed = (density | marked) & in_component[sd.cells]
    if not regions:
        return changed, [], np.where(changed, 0, -1)
    idx = np.flatnonzero(changed)
    # every cell of the components holds a change (a seed's cell holds a kept point, a cell
    # joins only holding a change): the components of the changed cells are theirs
    of_cell, n_components = sd.components(in_component)
    joined = joined_by_regions(of_cell[sd.cells[found]], found_regions, n_components)
    labels = np.full(n, -1, np.int64)
    labels[idx] = joined[of_cell[sd.cells[idx]]]
    # a region's volume: its cells of 1.5σ (the density's nodes do not hold what the distance adds)
    cells = np.bincount(joined[of_cell[in_component]], minlength=joined.max() + 1 if joined.size else 0)
    regs, region_of = describe_regions(sd.points, labels, cells * sd.cell_size**3)
    return changed, regs, region_of


def joined_by_regions(components: np.ndarray, regions: np.ndarray, n: int) -> np.ndarray:
    """The region (0, 1, … in the order of the components) of each of ``n`` components, from
    the component and the density's region of each point the density's decision keeps: the
    components holding points of one density region are one region (rule 4)."""
    regions = np.asarray(regions, np.int64)
    out = np.empty(n, np.int64)
    _joined(np.asarray(components, np.int64), regions, int(regions.max()) + 1 if regions.size else 0, out)
    return out


@nb.njit(cache=True, nogil=True)
def _joined(components, regions, m, out):
    """:func:`joined_by_regions`' kernel: each region's components in one set (-1: in no region),
    the sets numbered by their first component."""
    n = out.shape[0]
    parent = np.arange(n)
    first = np.full(m, -1, np.int64)  # a component of each region
    for i in range(components.shape[0]):
        g = regions[i]
        if g >= 0:
            if first[g] < 0:
                first[g] = components[i]
            else:
                union(parent, first[g], components[i])
    ids = np.full(n, -1, np.int64)
    k = 0
    for c in range(n):
        r = find(parent, c)  # the set's first component: met before any other of its set
        if ids[r] < 0:
            ids[r] = k
            k += 1
        out[c] = ids[r]
