"""Change detection on a stream of frames against a reference field that can learn and forget.

A robot keeps a model field; each frame that arrives is compared with it (Algorithm 1: the
frame's points inside frame − model have appeared), then optionally merged into it. The
model is a weighted mean of frame fields, G_model = Σ w_k·G_k / Σ w_k, held as the sum
Σ w_k·G_k with the threshold scaled by Σ w_k, so a static surface keeps one frame's density
whatever the history:

- ``update="none"``: the model is the reference, never changed;
- ``update="window"``: the mean of the reference and the last ``window − 1`` frames; a frame
  leaving the window is subtracted (the field is linear in its points), so its objects are
  forgotten;
- ``update="decay"``: exponential forgetting, weights λ^age (``decay`` = λ per frame).

A frame without a finite point (a covered or blinded sensor, a message of no points) is
yielded empty (:attr:`FrameChange.empty`) and changes nothing: nothing was seen, so nothing is
compared, and the model neither learns nor forgets (a window keeps its frames).

Each update costs the frame's own field (built once, used for detection too) plus a pass over
its blocks: time proportional to the frame, not to the history.

A camera that moves (a hand-held sensor, a robot without a pose estimate) sees a static scene
from a new pose at every frame, and every surface then looks changed. ``align=`` registers each
frame onto the reference before it is compared and merged, starting from the previous frame's
transform: GICP against the reference points (small_gicp [1], prepared once for the stream) or
the density method of :func:`sdp.align` against the reference field. ``sensor_origin=`` adds
the visibility test of :func:`sdp.detect_changes` against the reference scan's rays (its range
image built once for the stream): depth edges and surfaces the reference could not see are not
changes. The appeared points go through :func:`sdp.change._detect.judge_coverage` as in
:func:`sdp.detect_changes`: by the reference's rays when its sensor is known (read from its
file by default), else by the model's footprint.

References
----------
.. [1] K. Koide, "small_gicp: Efficient and parallel algorithms for point cloud registration",
   Journal of Open Source Software 9(100), 2024.
"""

from __future__ import annotations

import os
import time
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from dataclasses import field as dc_field

import numpy as np

from .._core._memory import check_memory
from .._core._points import as_points, to_rows
from .._core._validate import boolean, finite, integer_at_least
from ..change._coverage import CHANGED, NOT_COMPARABLE, UNCHANGED, states_of
from ..change._detect import inside_difference, judge_coverage, region_rules, single_origin
from ..change._regions import Region
from ..change._range_image import RangeImage
from ..change._visibility import (image_camera, rays_sent, resolve_sensor_origins, scanner_of_points,
                                  sensor_poles, sensor_range_noise)
from ..defaults import DEFAULTS
from ..errors import InvalidOptionError, InvalidPointsError
from ..fields._density import DensityField
from ..fields._spacing import resolve_lattice
from ..options import Coverage, Lattice, NoiseModel, Registration, as_options
from ..registration._align import GicpTarget
from ..registration._align import align as align_density
from ..registration._align import transform_points

__all__ = ["FrameChange", "watch"]


@dataclass
class FrameChange:
    """What appeared in one frame, relative to the model before that frame.

    Attributes
    ----------
    index : int
        Position of the frame in the stream (0 = first frame after the reference).
    name : str
        The frame's name (its file name from the command line), else its index.
    appeared : ndarray of bool
        One flag per row of the frame (False for NaN rows).
    not_comparable : ndarray of bool
        Rows where the reference could not see (outside its footprint or field of view, or
        hidden from its sensor): neither appeared nor unchanged (:mod:`sdp.change._coverage`);
        also rows holding NaN or Inf (no return), which nothing measured.
    regions : list of Region
        Connected appeared regions, largest first.
    appeared_labels : ndarray of int32
        The label of each row's region in ``regions`` (-1: none), as
        :attr:`sdp.ChangeResult.appeared_labels`.
    latency : float
        Seconds from receiving the frame to the answer, model update included.
    timings : dict of str to float
        Seconds per step: ``build``, ``detect``, ``regions``, ``update`` (and ``align`` with
        ``align=``).
    transform : ndarray (4, 4) or None
        With ``align=``: the rigid transform that mapped the frame onto the reference (its
        points were compared and merged after it); None otherwise.
    empty : bool
        The frame held no finite point: nothing was compared and the model did not change.
    overlap : float or None
        With ``align=``: the share of the frame's finite points inside the model after the
        registration. A registration refines an overlap it starts from: a frame that shares
        (almost) nothing with the model gets a pose that is a guess (``sdp watch`` says so below 5 %).
    pose_kept : bool
        With ``align="density"``: the frame's registration ended with less of it inside the model
        than it started from (:attr:`sdp.Alignment.diverged`), and the previous frame's pose was
        kept (``sdp watch`` says so).
    """

    index: int
    name: str
    appeared: np.ndarray
    not_comparable: np.ndarray
    regions: list[Region]
    appeared_labels: np.ndarray
    latency: float
    timings: dict[str, float] = dc_field(default_factory=dict)
    transform: np.ndarray | None = None
    empty: bool = False
    overlap: float | None = None
    pose_kept: bool = False

    @property
    def n_appeared(self) -> int:
        return int(self.appeared.sum())

    @property
    def state(self) -> np.ndarray:
        """The ``change`` field of the frame's rows (uint8): 0 unchanged, 1 appeared, 2 not comparable."""
        return states_of(self.appeared, self.not_comparable)

    def summary(self) -> dict:
        return {"index": self.index, "name": self.name, "points": int(self.appeared.size),
                "appeared": self.n_appeared, "not_comparable": int(self.not_comparable.sum()),
                "latency": self.latency, "timings": dict(self.timings),
                "transform": None if self.transform is None else self.transform.tolist(), "empty": self.empty,
                "overlap": self.overlap, "pose_kept": self.pose_kept,
                "regions": [{"n_points": r.n_points, "centroid": r.centroid.tolist(), "size": r.size.tolist()}
                            for r in self.regions]}


def watch(reference, frames: Iterable, *, lattice: Lattice | None = None, update: str = DEFAULTS.update,
          window: int | None = None, decay: float | None = None,
          min_region_points: int = DEFAULTS.min_region_points, regions: bool = True,
          align: Registration | str | None = None, coverage: Coverage | None = None,
          decision: str = DEFAULTS.decision, noise: NoiseModel | None = None) -> Iterator[FrameChange]:
    """Compare each frame of a stream with a model of the scene, in order; yield as they come.

    Every default is :data:`sdp.DEFAULTS`, as for :func:`sdp.detect_changes` and ``sdp watch``.

    Parameters
    ----------
    reference : array_like (n, 3), Cloud or DensityField
        The scene before the stream: points (a :func:`sdp.read_points` cloud brings its sensor
        position), or a field (its lattice, σ and h are used).
    frames : iterable
        Arrays (m, 3) or clouds, or ``(name, array)`` pairs; consumed lazily.
    lattice : Lattice, optional
        Lattice of the reference points (:class:`sdp.Lattice`; default: the voxel from their
        point spacing, :func:`sdp.auto_voxel_size`); a reference field brings its own.
    update : {"window", "none", "decay"}
        How the model learns (see the module docstring); default ``"window"``.
    window : int, optional
        Frames in the model (the reference counts as one) for ``update="window"`` (default
        ``DEFAULTS.window``); refused with another update, where it would be ignored.
    decay : float, optional
        λ in (0, 1) for ``update="decay"`` (default ``DEFAULTS.decay``); refused with another update.
    min_region_points : int
        Appeared regions with fewer points are dropped (noise); default 50.
    regions : bool
        Group appeared points into regions (skip for the lowest latency).
    align : Registration, "density" or "gicp", optional
        Register each frame onto the reference first (see the module docstring), starting
        from the previous frame's transform (the method only: no ``fix_horizontal`` or
        ``align_class`` in a stream): ``"gicp"`` needs reference points (not a field) and the
        ``align`` extra, downsamples both at σ and pairs points up to 4σ apart, after a first pass at 4σ
        and 16σ (:class:`sdp.registration._align.GicpTarget`); ``"density"``
        is :func:`sdp.align` on the reference field. None: the frames are already in the
        reference's frame (a fixed camera, or poses applied by the caller).
    coverage : Coverage, optional
        Tell what the model could not see (:class:`sdp.Coverage`): with the reference scan's
        sensor position (reference points only; by default what a reference read from a file
        says, an organized PCD's VIEWPOINT), the visibility test of :func:`sdp.detect_changes`
        against the reference's rays: an appeared point the reference saw at the same range is
        not a change, one it could not see is not comparable; without one, a frame point whose
        column the model did not sample densely enough is not comparable (its footprint).
    decision : {"point", "density", "combined"}
        As in :func:`sdp.detect_changes`: ``"combined"`` completes what the density finds in a
        frame with the distance to the reference's surface (reference points only).
    noise : NoiseModel, optional
        With ``decision="combined"``, as in :func:`sdp.detect_changes`.

    Yields
    ------
    FrameChange
    """
    if isinstance(frames, (str, bytes, os.PathLike)):  # iterated, a folder's name would be frames of one letter
        raise InvalidOptionError(f"frames must be points, not a path ({os.fsdecode(frames)!r}): for a folder's files "
                                 "use sdp.cli.watch_folder(reference, folder), or the command sdp watch REF FOLDER")
    lattice = as_options(Lattice, lattice, "lattice")
    coverage = as_options(Coverage, coverage, "coverage")
    registration = Registration.of(align)
    if update not in ("none", "window", "decay"):
        raise InvalidOptionError(f"update must be 'none', 'window' or 'decay', got {update!r}")
    for name, value, mode in (("window", window, "window"), ("decay", decay, "decay")):
        if value is not None and update != mode:  # it would be ignored
            raise InvalidOptionError(f"{name} applies to update={mode!r} only (update is {update!r})")
    window = DEFAULTS.window if window is None else window
    decay = DEFAULTS.decay if decay is None else decay
    if update == "window":  # a whole number of frames: "3" compared as text, 2.5 frames kept as 2.5
        window = integer_at_least("window", window, 1)
    if update == "decay":  # the number checked, used: "0.5" as text failed at its first frame
        decay = finite("decay", decay)
        if not 0 < decay < 1:
            raise InvalidOptionError("decay must be in (0, 1)")
    if registration is not None and (registration.fix_horizontal or registration.classes is not None):
        raise InvalidOptionError("a stream aligns its frames by the method alone: no fix_horizontal or align_class")
    align = None if registration is None else registration.method
    min_region_points = integer_at_least("min_region_points", min_region_points, 0)
    regions = boolean("regions", regions)  # as detect_changes: a string "no" would read as True
    if decision not in ("point", "density", "combined"):
        raise InvalidOptionError(f"decision must be 'point', 'density' or 'combined' in a stream, got {decision!r}")
    if min_region_points != DEFAULTS.min_region_points and not regions and decision != "combined":
        raise InvalidOptionError("min_region_points drops small regions: it applies with regions=True only "
                                 "(as in sdp.detect_changes)")
    noise = NoiseModel.of(noise, decision)
    is_field = isinstance(reference, DensityField)
    origin = pts = None
    if is_field:
        if align == "gicp" or coverage.given or decision == "combined":
            raise InvalidOptionError("align='gicp', a sensor position and decision='combined' need the reference "
                                     "points, not a field")
        base, ref = reference, None
    else:
        origin = resolve_sensor_origins(coverage.sensor_origin, reference, None)[0]
        pts = as_points(reference, name="reference")
        ref = pts.xyz
        l, sv = resolve_lattice([pts], voxel_size=lattice.voxel_size, grid_size=lattice.grid_size, k=lattice.k,
                                sigma_voxels=lattice.sigma_voxels)
        base = DensityField.from_points(pts, voxel_size=l, sigma_voxels=sv, k=lattice.k, h=lattice.h,
                                        truncate=lattice.truncate, method=lattice.method)
    h, opts = base.h, dict(voxel_size=base.voxel_size, sigma_voxels=base.sigma / base.voxel_size,
                           truncate=base.truncate, h=base.h)
    model = base if update == "none" else base.copy()
    weight, history = 1.0, deque([base])
    target = None if align != "gicp" else GicpTarget(ref, resolution=base.sigma, max_distance=4 * base.sigma)
    scan = None if is_field else scanner_of_points(reference, origin, len(ref))  # several scanners: each point's
    pole = None if is_field else sensor_poles(reference, origin)  # the scanners' verticals, where known
    image = None if origin is None or np.ndim(origin) == 2 else \
        RangeImage.from_points(ref, origin, rays_sent=rays_sent(reference), camera=image_camera(reference, origin),
                               pole=pole)
    band = sensor_range_noise(reference, coverage.range_noise, xyz=ref, origin=origin)  # a laser's, a camera's
    matrix = None if align is None else np.eye(4)
    kept_rows = {}

    def reference_rows(rows: slice) -> np.ndarray:  # the same rows every frame: gathered once
        key = rows.indices(len(ref))
        if key not in kept_rows:
            kept_rows[key] = np.ascontiguousarray(ref[rows])
        return kept_rows[key]

    try:
        frames = iter(frames)
    except TypeError:
        raise InvalidOptionError(f"frames must be an iterable of point arrays or clouds (or (name, points) pairs), "
                                 f"got {type(frames).__name__}") from None
    for index, item in enumerate(frames):
        if isinstance(item, tuple) and len(item) != 2:
            raise InvalidOptionError(f"frame {index}: a frame is points, or a (name, points) pair; got a tuple of "
                                     f"{len(item)}")
        name, given = item if isinstance(item, tuple) else (str(index), item)
        t0 = time.perf_counter()
        timings = {}
        try:
            cur = as_points(given, name=f"frame {name}")
        except InvalidPointsError:
            rows = _rows_if_empty(given)
            if rows is None:  # not an array of points at all
                raise
            yield FrameChange(index=index, name=name, appeared=np.zeros(rows, bool),
                              not_comparable=np.ones(rows, bool), regions=[],
                              appeared_labels=np.full(rows, -1, np.int32), latency=time.perf_counter() - t0,
                              transform=matrix, empty=True)
            continue
        pose_kept = False
        if align is not None:  # from the previous frame's pose: the sensor moved little since
            t = time.perf_counter()
            if target is not None:
                matrix = target.register(cur.xyz, matrix)
            else:
                found = align_density(base, cur.xyz, init=matrix)
                matrix, pose_kept = found.matrix, found.diverged
            cur = cur.moved(transform_points(matrix, cur.xyz))
            timings["align"] = time.perf_counter() - t
        try:
            frame = DensityField.from_points(cur, **opts)
        except InvalidPointsError as exc:  # coordinates the lattice can't place (a corrupt frame): say which
            raise InvalidPointsError(f"frame {name}: {exc}") from None
        t1 = time.perf_counter()
        seen = model.with_threshold(h=h * weight)
        mask, d = inside_difference(frame, seen, cur.xyz)
        overlap = None if align is None else float(np.mean(~mask)) if len(mask) else 0.0  # inside the model
        choice = coverage.sensor_origin  # the frame's own sensor: what it could see, its range law
        choice = "auto" if isinstance(choice, str) and choice == "viewpoint" else choice
        own = single_origin(resolve_sensor_origins(choice, None, given)[1])
        own_pole = sensor_poles(given, own)
        if own is not None and matrix is not None:
            own = transform_points(matrix, own[None, :])[0]
            own_pole = None if own_pole is None else matrix[:3, :3] @ own_pole
        # the model's footprint, or the reference's rays (imaged once)
        states = judge_coverage(cur.xyz, mask, ref, seen, origin, coverage=coverage.enabled,
                                range_noise=band, image=image, present=frame.inside, other_scan=scan,
                                other_pole=pole, own_origin=own, own_pole=own_pole,
                                own_range_noise=sensor_range_noise(given, coverage.range_noise, xyz=cur.xyz,
                                                                   origin=own),
                                other_gone=lambda rows: inside_difference(base, frame, reference_rows(rows))[0])
        mask, unseen = states == CHANGED, states == NOT_COMPARABLE
        t2 = time.perf_counter()
        labels = np.full(len(mask), -1, np.int32)
        if regions or decision == "combined":  # point-wise decision: only the appeared points need a region
            idx = np.flatnonzero(mask)
            kept, regs, labels[idx] = region_rules(frame, d, cur.xyz[idx], np.ones(len(idx), bool), regions=True,
                                                   decision="point", min_region_points=min_region_points,
                                                   cluster_fraction=0.5)
            mask[idx] = kept
        else:
            regs = []
        if decision == "combined" and mask.any():  # the distance completes what the density kept
            mask, regs, region_of = _complete(cur, pts, states, mask, labels, frame, own_origin=own,
                                              other_origin=single_origin(origin), regions=regions, noise=noise)
            labels = region_of.astype(np.int32)
        t3 = time.perf_counter()
        if update == "decay":
            model.scale(decay).accumulate(frame)
            weight = decay * weight + 1
        elif update == "window":
            if len(history) == 1:  # the first frame tells what a window of them will hold: refused before it grows
                from .._core._memory import format_bytes

                check_memory(window * frame.nbytes + model.nbytes, f"a window of {window} frames' fields (the first "
                             f"{format_bytes(frame.nbytes)})", None,
                             advice="give a smaller window, or update='decay' (one field, however many frames)")
            model.accumulate(frame)
            history.append(frame)
            if len(history) > window:
                model.accumulate(history.popleft(), weight=-1)
            weight = float(len(history))
        t4 = time.perf_counter()
        timings.update(build=t1 - t0 - timings.get("align", 0.0), detect=t2 - t1, regions=t3 - t2, update=t4 - t3)
        yield FrameChange(index=index, name=name, appeared=to_rows(mask, cur, False),
                          not_comparable=to_rows(unseen, cur, True), regions=regs,
                          appeared_labels=to_rows(labels, cur, -1), latency=t4 - t0, timings=timings,
                          transform=matrix, overlap=overlap, pose_kept=pose_kept)


def _rows_if_empty(given) -> int | None:
    """The number of rows of a frame that is an (n, 3) array (or cloud) without a finite row, else None."""
    xyz = given.xyz if hasattr(given, "xyz") and hasattr(given, "n_dropped") else given
    try:
        arr = np.asarray(xyz, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if arr.ndim != 2 or arr.shape[1] != 3 or np.isfinite(arr).all(axis=1).any():
        return None
    return len(arr)


def _complete(cur, ref, states, found, found_labels, frame: DensityField, *, own_origin, other_origin,
              regions: bool, noise: NoiseModel):
    """:func:`sdp.change._combined.combine_decision` of a frame's points (``cur``) against the
    reference points (``ref``), from the density's ``states``, the points it keeps (``found``) and
    their regions (``found_labels``)."""
    from ..change._combined import combine_decision
    from ..distance._noise import SurfaceDistances, distance_bytes, pair_cells

    check_memory(distance_bytes((ref, cur), frame.sigma), f"the combined decision's distances for a frame of "
                 f"{len(cur.xyz):,} points", None, advice="use decision='point'")
    # the frame's cells change with every frame, so both are sorted again (the reference too)
    lists = pair_cells((ref, cur), frame.sigma, sort=True)
    sd = SurfaceDistances(cur.xyz, ref.xyz, sigma=frame.sigma, own_origin=own_origin, other_origin=other_origin,
                          stable=states == UNCHANGED, lists=lists, **noise.arguments())
    idx = np.flatnonzero(found)
    return combine_decision(sd, states, directed=other_origin is not None,
                            present=frame.inside, found=idx, found_regions=found_labels[idx], regions=regions)

