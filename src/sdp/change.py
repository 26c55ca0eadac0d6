"""Change detection between two clouds (the paper's Algorithm 1), with change regions.

References
----------
.. [1] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
   Comparison and Applications", Algorithm 1.
.. [2] J. P. Underwood et al., "Explicit 3D change detection using ray-tracing in spherical
   coordinates", ICRA 2013 (the visibility test of ``sensor_origin=``, :mod:`sdp.visibility`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from dataclasses import field as dc_field

import numpy as np
import numpy.typing as npt

from ._kernels import map_concurrently
from ._points import Points, as_points
from .field import DensityField, build_fields
from .grid import voxel_size_for_grid_size
from .params import auto_voxel_size_of
from .regions import Region, Volume, describe_regions, label_volume
from .visibility import as_sensor_origins, explained_by_visibility

__all__ = ["ChangeResult", "detect_changes"]


@dataclass
class ChangeResult:
    """What changed between a reference and a current cloud.

    Attributes
    ----------
    appeared : ndarray of bool (n_current,)
        Current points inside the difference volume current − reference (one per input row;
        rows that held NaN/Inf are False).
    disappeared : ndarray of bool (n_reference,)
        Reference points inside reference − current.
    appeared_regions, disappeared_regions : list of Region
        Connected change regions, largest first.
    appeared_region, disappeared_region : ndarray of int64
        Region label of each point (-1: unchanged).
    reference_field, current_field : DensityField
        The two fields, on one lattice (same voxel size).
    timings : dict of str to float
        Seconds per step: ``build_reference``, ``build_current``, ``detect`` (as the paper's
        Table I), then ``regions``; with ``voxel_size="auto"``, also ``voxel_size``; with
        ``sensor_origin=``, also ``visibility``. The two builds bin their clouds at once, and
        ``regions`` and ``visibility`` add up both directions, which run at once: on two threads
        when there are two cores, so these steps may add up to more than the wall time they took.
    voxel_size, h : float
        Parameters used.
    decision : str
        ``"point"`` or ``"cluster"`` (see :func:`detect_changes`).
    """

    appeared: np.ndarray
    disappeared: np.ndarray
    appeared_regions: list[Region]
    disappeared_regions: list[Region]
    appeared_region: np.ndarray
    disappeared_region: np.ndarray
    reference_field: DensityField
    current_field: DensityField
    voxel_size: float
    h: float
    decision: str
    timings: dict[str, float] = dc_field(default_factory=dict)

    def summary(self) -> dict:
        """A JSON-serializable summary: counts, parameters, timings and regions."""
        return {"voxel_size": self.voxel_size, "sigma": self.current_field.sigma, "h": self.h,
                "decision": self.decision,
                "reference": {"points": int(self.disappeared.size), "dropped": self.reference_field.n_dropped,
                              "disappeared": int(self.disappeared.sum())},
                "current": {"points": int(self.appeared.size), "dropped": self.current_field.n_dropped,
                            "appeared": int(self.appeared.sum())},
                "timings": dict(self.timings),
                "appeared_regions": [r.to_dict() for r in self.appeared_regions],
                "disappeared_regions": [r.to_dict() for r in self.disappeared_regions]}


def detect_changes(reference, current, *, grid_size: int | None = None, voxel_size: float | str | None = None,
                   sigma_voxels: float = 2.0, k: float = 3, h: float | None = None, truncate: float = 3.0,
                   method: str = "auto", decision: str = "point", cluster_fraction: float = 0.5,
                   min_region_points: int = 1, regions: bool = True,
                   memory_limit: int | str | None = None, sensor_origin: npt.ArrayLike | None = None,
                   range_noise: float = 0.015) -> ChangeResult:
    """Points that appeared in ``current`` and disappeared from ``reference``.

    Builds F_ref and F_cur on one lattice (same voxel size), forms the difference volumes
    D = max(F_cur, −F_ref) and max(F_ref, −F_cur) at the nodes, and flags each point whose
    interpolated D is negative: it lies in its own cloud's cluster volume and outside the
    other's.

    Parameters
    ----------
    reference, current : array_like (n, 3)
        World coordinates; both in the same frame (register them first).
    grid_size : int, optional
        The paper's parameterization: the longest side of the box holding *both* clouds
        divided into ``grid_size`` segments. The default when ``voxel_size`` is not given: 80.
    voxel_size : float or "auto", optional
        Voxel length in world units, or ``"auto"`` for :func:`sdp.auto_voxel_size` of both
        clouds (recommended for real scans).
    sigma_voxels, k, h, truncate, method, memory_limit
        As in :meth:`DensityField.from_points`.
    decision : {"point", "cluster"}
        ``"point"``: Algorithm 1, each point on its own. ``"cluster"``: the paper's clustering
        completes partly detected objects: a connected component of the cloud's own cluster
        volume (F < 0) in which more than ``cluster_fraction`` of the points changed is
        reported changed whole; the points of other components keep their own decision. (An
        object touching static structure shares its cluster with it and stays point-wise.)
    cluster_fraction : float
        Threshold of the ``"cluster"`` decision, in [0, 1).
    min_region_points : int
        Change regions with fewer points are strays (noise, parallax at edges): their points
        are reported unchanged. 1 keeps everything. Needs ``regions=True``.
    regions : bool
        Group changed points into connected regions (skip to save time).
    sensor_origin : array_like (3,) or (2, 3), optional
        Where the sensor stood, in the clouds' frame: one position for both scans, or the
        reference's and the current's (e.g. :attr:`sdp.io.Cloud.sensor_origin`, a PCD file's
        VIEWPOINT; after :func:`sdp.align`, move the current's origin with the same matrix).
        Adds the visibility test of :mod:`sdp.visibility`: an appeared point stays a change if
        the reference's rays passed through its place, or if the reference could not see its
        place (hidden behind something nearer, or no return) and it does not continue the
        unchanged surface around it; a point whose ray the reference saw end at the same range
        is not a change. Disappeared points are tested against the current scan's view. This
        removes the surface a moved object uncovers and depth noise along the rays; it runs
        before the ``min_region_points`` filter. None (default): the density test alone.
    range_noise : float
        With ``sensor_origin``: "the same range" is within ``range_noise``·r² world units at
        range r, and at least σ (for metres: 0.015 m⁻¹, 1.5 cm at 1 m, covers a Kinect's depth
        noise and steps and its drift between frames).

    Returns
    -------
    ChangeResult
    """
    if decision not in ("point", "cluster"):
        raise ValueError(f"decision must be 'point' or 'cluster', got {decision!r}")
    origins = None if sensor_origin is None else as_sensor_origins(sensor_origin)
    if not (range_noise >= 0 and np.isfinite(range_noise)):
        raise ValueError(f"range_noise must be a finite number >= 0, got {range_noise!r}")
    ref = as_points(reference, name="reference")
    cur = as_points(current, name="current")
    timings = {}
    if voxel_size is None and grid_size is None:
        grid_size = 80
    if isinstance(voxel_size, str):
        if voxel_size != "auto":
            raise ValueError(f"voxel_size must be a length or 'auto', got {voxel_size!r}")
        t = time.perf_counter()
        voxel_size = auto_voxel_size_of([ref, cur], k=int(round(k)), sigma_voxels=sigma_voxels)  # validated once
        timings["voxel_size"] = time.perf_counter() - t
    elif grid_size is not None:
        if voxel_size is not None:
            raise ValueError("give grid_size= or voxel_size=, not both")
        voxel_size = voxel_size_for_grid_size(np.minimum(ref.lo, cur.lo), np.maximum(ref.hi, cur.hi), grid_size)
    opts = dict(voxel_size=voxel_size, sigma_voxels=sigma_voxels, k=k, h=h, truncate=truncate, method=method,
                memory_limit=memory_limit)
    (f_ref, f_cur), (timings["build_reference"], timings["build_current"]) = build_fields([ref, cur], **opts)
    t = time.perf_counter()
    app, d_app = _inside_difference(f_cur, f_ref, cur.xyz)
    dis, d_dis = _inside_difference(f_ref, f_cur, ref.xyz)
    timings["detect"] = time.perf_counter() - t
    o_ref, o_cur = (None, None) if origins is None else origins

    def finish(job):
        """Visibility test and region rules of one direction: (rows, regions, region of rows), times."""
        fld, pts, mask, d, other, other_origin = job
        steps = {}
        if other_origin is not None:
            t = time.perf_counter()
            mask = mask & ~explained_by_visibility(pts.xyz, mask, other.xyz, other_origin, sigma=fld.sigma,
                                                   range_noise=range_noise)
            steps["visibility"] = time.perf_counter() - t
        t = time.perf_counter()
        mask, regs, region_of = _regions(fld, d, pts.xyz, mask, regions=regions, decision=decision,
                                         min_region_points=min_region_points, cluster_fraction=cluster_fraction)
        steps["regions"] = time.perf_counter() - t
        return (_to_rows(mask, pts, False), regs, _to_rows(region_of, pts, -1)), steps

    # the two directions are independent: on two threads when there are two cores
    (appeared, steps_a), (disappeared, steps_d) = map_concurrently(
        finish, [(f_cur, cur, app, d_app, ref, o_ref), (f_ref, ref, dis, d_dis, cur, o_cur)], parallel_kernels=True)
    timings.update({step: steps_a[step] + steps_d[step] for step in steps_a})
    return ChangeResult(appeared=appeared[0], disappeared=disappeared[0], appeared_regions=appeared[1],
                        disappeared_regions=disappeared[1], appeared_region=appeared[2],
                        disappeared_region=disappeared[2],
                        reference_field=f_ref, current_field=f_cur, voxel_size=float(voxel_size), h=f_cur.h,
                        decision=decision, timings=timings)


def _inside_difference(fld: DensityField, other: DensityField, pts: np.ndarray):
    """Mask of ``pts`` (the finite points ``fld`` was built from) inside fld − other, and the
    difference volume D = max(F_fld, −F_other) < 0 on ``fld``'s blocks (D interpolated at the points)."""
    d = Volume.difference(fld, other)
    return d.at(fld, pts) < 0, d


def _regions(fld: DensityField, d: Volume, pts: np.ndarray, mask: np.ndarray, *, regions: bool,
             decision: str, min_region_points: int, cluster_fraction: float):
    """(mask, regions, region label per point) after the region-level rules of :func:`detect_changes`."""
    if not (regions or decision == "cluster"):
        return mask, [], np.where(mask, 0, -1)
    # only the changed points' labels are used below (unchanged points end at -1, or take a
    # promoted cluster's label): label those alone, each point's label depends on it only
    changed = np.flatnonzero(mask)
    labels = np.full(len(pts), -1, np.int64)
    labels[changed], counts = label_volume(fld, d, pts[changed])
    if min_region_points > 1 and len(counts):
        big = np.bincount(labels[mask], minlength=len(counts)) >= min_region_points
        mask = mask & big[np.maximum(labels, 0)]
    if decision == "cluster":
        mask, labels, counts = _cluster_decision(fld, pts, mask, labels, counts, cluster_fraction)
    regs, region_of = describe_regions(pts, np.where(mask, labels, -1), counts, fld.voxel_size)
    return mask, regs, region_of


def _cluster_decision(fld: DensityField, pts: np.ndarray, changed: np.ndarray, labels: np.ndarray,
                      counts: np.ndarray, fraction: float):
    """Promote whole clusters (components of the cloud's own F < 0) in which more than
    ``fraction`` of the points changed; they become regions of their own."""
    clusters, cluster_nodes = label_volume(fld, Volume.inside(fld), pts)
    inside = clusters >= 0
    n = np.bincount(clusters[inside], minlength=len(cluster_nodes))
    c = np.bincount(clusters[inside], weights=changed[inside], minlength=len(cluster_nodes))
    promoted = np.zeros(len(changed), bool)
    promoted[inside] = (c > fraction * np.maximum(n, 1))[clusters[inside]]
    # promoted clusters are labelled after the change regions
    labels = np.where(promoted, len(counts) + clusters, labels)
    return changed | promoted, labels, np.concatenate([counts, cluster_nodes])


def _to_rows(values: np.ndarray, pts: Points, fill):
    """Spread per-finite-point values back over the input rows (``fill`` for dropped rows)."""
    if pts.finite is None:
        return values
    out = np.full(pts.finite.shape, fill, dtype=values.dtype)
    out[pts.finite] = values
    return out
