"""``sdp change`` as a function: :func:`compare_files` and the plan it makes before any work.

:func:`compare_files` decides by itself, before any work, whether two clouds are compared in
memory (:func:`sdp.detect_changes`) or in tiles on Dask (:func:`sdp.detect_changes_tiled`),
exactly as the command does (:func:`plan_change`), and writes the labelled clouds. It checks its
options and its outputs (:func:`sdp.io.check_outputs`) before it reads anything and writes all
its outputs or none (:func:`sdp.io.all_or_none`). Error messages name options as the command line
spells them (``--align-class`` for ``align_class=``).

References
----------
.. [1] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
   Comparison and Applications", Algorithm 1.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .._core import _validate as V
from .._core._memory import format_bytes
from ..defaults import DEFAULTS
from ..errors import SDPError
from ..io._output import all_or_none, check_format, check_outputs
from ..options import Coverage, Execution, Lattice, NoiseModel, Outputs, Registration, as_options
from . import _text as report
from ..io._bag import bag_path, is_bag, topic_needed
from ._common import (align_clouds, alignment_summary, check_picture_extras, disappeared_path, is_store, pictures,
                      read_input, same_frame, sensor_origins)

__all__ = ["ChangePlan", "FileComparison", "plan_change", "compare_files"]


@dataclass
class ChangePlan:
    """How :func:`compare_files` compares two files: in memory or in tiles (:func:`plan_change`).

    Attributes
    ----------
    tiled : bool
        True: :func:`sdp.detect_changes_tiled` on Dask; False: :func:`sdp.detect_changes`.
    reason : str or None
        Why tiles were taken without being asked for (the grids or points exceed the memory
        limit); None when they were asked for, or when the comparison runs in memory.
    voxel_size, sigma_voxels : float or None
        The tiled run's voxel and σ in voxels (in memory, :func:`sdp.detect_changes` decides them).
    sources : list or None
        What the tiled run reads: (reference, current) as :class:`~sdp.io.PointSource`, the
        reference possibly a :class:`~sdp.FieldStore`.
    in_memory : float or None
        With ``reason``: the memory limit (bytes) under which the comparison would run in memory
        (the dense grids or the points with the process), named by a refusal of the tiles when
        it is below their own minimum.
    """

    tiled: bool
    reason: str | None = None
    voxel_size: float | None = None
    sigma_voxels: float | None = None
    sources: list | None = None
    in_memory: float | None = None


@dataclass
class FileComparison:
    """What :func:`compare_files` found and wrote.

    Attributes
    ----------
    reference, current : str
        The two files, as given.
    result : ChangeResult
        The library's result (:func:`sdp.detect_changes`, or :func:`sdp.detect_changes_tiled`:
        ``result.tiled``).
    summary : dict
        JSON-serializable: ``result.summary()`` with the reading (or writing) time, the
        alignment, and ``outputs``; what ``sdp change --json`` prints.
    tiled : bool
        Whether the clouds were compared in tiles.
    alignment : Alignment or None
        With ``align=``: the transform that moved the current scan onto the reference.
    outputs : list of str
        The files written.
    """

    reference: str
    current: str
    result: object
    summary: dict
    tiled: bool = False
    alignment: object = None
    outputs: list[str] = field(default_factory=list)

    def summary_text(self) -> str:
        """The table ``sdp change`` prints: counts, alignment, parameters, coverage, regions, times, files."""
        return report.change_text(self.summary, self.reference, self.current)


def plan_change(reference, current, *, output=None, format: str | None = None, outputs: Outputs | None = None,
                lattice: Lattice | None = None, coverage: Coverage | None = None,
                align: Registration | str | None = None, decision: str = DEFAULTS.decision,
                execution: Execution | None = None) -> ChangePlan:
    """Decide, before any work, whether :func:`compare_files` works in memory or in tiles.

    Tiles are taken when ``execution.tiled`` is True, when ``reference`` is a ``.zarr`` field store, or
    when two dense float32 grids over the clouds' box (:func:`sdp.scale._budget.dense_grid_bytes`), or
    the points themselves (:func:`sdp.scale._budget.untiled_point_bytes`), would exceed the memory
    limit (:func:`sdp._core._memory.memory_limit`). Only LAS/LAZ, NPY and binary PLY files can be read
    in slices, and only the point and combined decisions with footprint coverage run in tiles:
    other files, ``grid_size``, ``align``, ``decision="cluster"`` or a given sensor position keep
    the comparison in memory (and are refused with ``tiled=True``). With ``voxel_size="auto"``
    the voxel is measured on the first slice of each file.

    Parameters
    ----------
    reference, current, format, outputs, lattice, coverage, align, decision, execution
        As in :func:`compare_files` (pictures and reports are made in memory only: refused when
        tiles are taken).
    output : path-like, optional
        Checked here only to be LAS/LAZ when tiles are taken (they stream their output).

    Returns
    -------
    ChangePlan

    Raises
    ------
    SDPError
        An option the tiles do not have with ``tiled=True``, files that can't be read in
        slices, ``both`` with a field store, or an output that is not LAS/LAZ for tiles.
    """
    from .._core._memory import memory_limit as limit
    from ..io._cloud import FORMATS
    from ..io._source import PointSource
    from ..fields._lattice import check_lattice
    from ..scale._budget import dense_grid_bytes, untiled_point_bytes
    from ..scale._session import sampled_lattice

    outputs = as_options(Outputs, outputs, "outputs")
    lattice = as_options(Lattice, lattice, "lattice")
    coverage = as_options(Coverage, coverage, "coverage")
    execution = as_options(Execution, execution, "execution")
    both, tiled, align = outputs.both, execution.tiled, Registration.of(align)
    if is_store(reference):  # a stored reference field: its lattice, σ, h and tiles
        from ..scale._store import FieldStore

        why = "with a .zarr field store as the reference (compared in tiles)"
        V.check_tiled_options(grid_size=lattice.grid_size, align=align, sensor_origin=coverage.sensor_origin,
                              range_noise=coverage.range_noise,
                              decision=decision, pictures=outputs.pictures, why=why)
        if lattice != Lattice():
            raise SDPError("the lattice (voxel, σ, k, h) is the field store's: give no --voxel-size, --sigma-voxels, "
                           "-k, --h or --grid-size with it")
        if output is not None and Path(output).suffix.lower() not in (".las", ".laz"):
            raise SDPError(f"{output}: the comparison {why} streams its output to LAS/LAZ: give -o OUT.laz")
        sources = [FieldStore.open(reference), PointSource.open(current, format=format)]
        if both:
            raise SDPError("--both needs the reference points; a .zarr field store only tells what appeared")
        return ChangePlan(tiled=True, voxel_size=sources[0].voxel_size,
                          sigma_voxels=sources[0].sigma / sources[0].voxel_size, sources=sources)
    streamed = all((format or FORMATS.get(Path(f).suffix.lower())) in ("las", "npy", "ply")
                   for f in (reference, current))
    # tiles follow no rays: a given sensor (or its range noise) keeps the comparison in memory
    given_sensor = not (isinstance(coverage.sensor_origin, str) and coverage.sensor_origin in ("auto", "none"))
    rays = given_sensor or coverage.range_noise != DEFAULTS.range_noise  # the sensor's rays asked for
    if not tiled and (not streamed or lattice.grid_size is not None or align or decision == "cluster" or rays):
        return ChangePlan(tiled=False)
    if tiled:
        V.check_tiled_options(grid_size=lattice.grid_size, align=align, sensor_origin=coverage.sensor_origin,
                              range_noise=coverage.range_noise,
                              decision=decision, pictures=outputs.pictures)
        if not streamed:
            raise SDPError("--tiled reads LAS/LAZ, NPY or binary PLY files in slices; convert the clouds first")
    try:
        sources = [PointSource.open(f, format=format) for f in (reference, current)]
    except SDPError:
        if tiled:
            raise
        return ChangePlan(tiled=False)  # ASCII PLY and the like: the in-memory path reads them (or reports the error)
    voxel, sigma_voxels = sampled_lattice(sources, voxel_size=lattice.voxel_size, k=lattice.k,
                                          sigma_voxels=lattice.sigma_voxels)
    lo = np.minimum(sources[0].lo, sources[1].lo)
    hi = np.maximum(sources[0].hi, sources[1].hi)
    check_lattice(lo, hi, voxel)  # before the grids' size: a lattice that can't be placed says so
    grids = 2 * dense_grid_bytes(lo, hi, voxel, sigma_voxels=sigma_voxels)
    points = untiled_point_bytes(sum(s.n_rows for s in sources))
    cap = limit(execution.memory_limit)
    if not (tiled or max(grids, points) > cap):
        return ChangePlan(tiled=False)
    if output is not None and Path(output).suffix.lower() not in (".las", ".laz"):  # the tiles stream LAS/LAZ
        if tiled:
            raise SDPError(f"{output}: --tiled streams its output to LAS/LAZ: give -o OUT.laz")
        raise SDPError(f"{output}: the clouds are compared in tiles (two dense grids would need "
                       f"{format_bytes(grids)}, above the memory limit of {format_bytes(cap)}), whose "
                       "output streams to LAS/LAZ: give -o OUT.laz, or a larger --memory-limit")
    reason = None if tiled else (f"comparing in tiles on Dask: dense grids of {format_bytes(grids)} or the points "
                                 f"in memory ({format_bytes(points)} with the process) exceed the memory limit of "
                                 f"{format_bytes(cap)}")
    if reason and outputs.pictures:  # the pictures need every point in memory
        raise SDPError(f"--png/--html/--report are made in memory, but dense grids of {format_bytes(grids)} "
                       f"exceed the memory limit of {format_bytes(cap)}: give a larger --memory-limit or no pictures")
    return ChangePlan(tiled=True, reason=reason, voxel_size=float(voxel), sigma_voxels=sigma_voxels, sources=sources,
                      in_memory=max(grids, points) if reason else None)


def compare_files(reference, current, *, output, outputs: Outputs | None = None, format: str | None = None,
                  lattice: Lattice | None = None, coverage: Coverage | None = None,
                  align: Registration | str | None = None, execution: Execution | None = None,
                  decision: str = DEFAULTS.decision, min_region_points: int = DEFAULTS.min_region_points,
                  topic: str | None = None, noise: NoiseModel | None = None) -> FileComparison:
    """Compare two point-cloud files and write the labelled clouds: ``sdp change`` as a function.

    The clouds are compared in memory (:func:`sdp.detect_changes`) or, when they need more
    than the memory limit, in tiles on Dask (:func:`sdp.detect_changes_tiled`): the choice of
    :func:`plan_change`, made before any work, exactly as the command makes it. The output
    holds every point of ``current`` with the fields ``change`` (0 unchanged, 1 appeared,
    2 not comparable, :mod:`sdp.change._coverage`) and ``region`` (-1: none), in memory also ``G``
    and ``F`` (the density and F = h − G at the point); LAS/LAZ output of LAS/LAZ input keeps
    every input dimension. Every default is :data:`sdp.DEFAULTS`.

    Parameters
    ----------
    reference, current : path-like
        Point-cloud files (PCD, PLY, LAS/LAZ, XYZ/TXT/CSV, NPY/NPZ, E57; ``format`` overrides the
        extension), or ROS bags with ``topic``. ``reference`` may be a ``.zarr`` field store
        (:func:`sdp.build_field_tiled`, ``sdp build -o FIELD.zarr``): compared in tiles, what
        appeared only.
    output : path-like
        The labelled current cloud (.ply, .las, .laz, .npz; tiles write LAS/LAZ).
    outputs : Outputs, optional
        What else to write (:class:`sdp.Outputs`): ``both``, the reference's points labelled
        as disappeared, to :func:`disappeared_path`; ``png`` and ``html``, pictures of the
        appeared points (:func:`sdp.render_changes`, :func:`sdp.render_changes_html`; with
        ``both``, the disappeared points' beside them, named as :func:`disappeared_path` says);
        ``report``, one self-contained HTML page (:func:`sdp.change_report`: summary,
        parameters and why, maps of both directions, region sizes, the region table with
        thumbnails, a 3-D view; in memory only, refused with tiles); ``aligned``, the current's
        points where the alignment moved them (default: its own coordinates).
    lattice, decision, min_region_points, noise
        As in :func:`sdp.detect_changes`.
    coverage : Coverage, optional
        As in :func:`sdp.detect_changes`; ``sensor_origin="viewpoint"`` is ``"auto"`` refusing
        files that record no sensor position. A given position is the reference's; with
        ``align`` the current's is moved with its scan.
    align : Registration, "density" or "gicp", optional
        Register ``current`` onto ``reference`` first (:class:`sdp.Registration`,
        :func:`sdp.align`).
    execution : Execution, optional
        The memory limit and the tiles (:class:`sdp.Execution`): ``tiled`` compares in tiles
        even if the clouds fit in memory; ``notify`` is called with one line when the
        comparison switches to tiles by itself (``sdp change`` prints it on stderr).
    topic : str, optional
        With a ROS bag (a ``.bag`` file, or a ROS 2 bag folder) as an input: its
        ``sensor_msgs/PointCloud2`` topic, ``TOPIC`` (its first message) or ``TOPIC:N`` (its N-th,
        from 0; negative from the end).

    Returns
    -------
    FileComparison
        ``summary`` (what ``--json`` prints), ``summary_text()`` (the table), the files written.

    Raises
    ------
    SDPError
        Bad options, outputs that can't be written or would overwrite an input, unreadable
        files (one-line messages; nothing is written).

    References
    ----------
    .. [1] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
       Comparison and Applications", Algorithm 1.
    .. [2] J. P. Underwood et al., "Explicit 3D change detection using ray-tracing in spherical
       coordinates", ICRA 2013 (``sensor_origin``).

    Examples
    --------
    >>> r = sdp.compare_files("ref.laz", "cur.laz", output="changes.laz",
    ...                       outputs=sdp.Outputs(both=True))  # doctest: +SKIP
    >>> print(r.summary_text()); r.tiled, r.summary["current"]["appeared"]  # doctest: +SKIP
    """
    outputs = as_options(Outputs, outputs, "outputs").only("sdp change", "both", "png", "html", "report", "aligned")
    lattice = as_options(Lattice, lattice, "lattice")
    coverage = as_options(Coverage, coverage, "coverage")
    execution = as_options(Execution, execution, "execution")
    noise = NoiseModel.of(noise, decision)
    align = Registration.of(align)
    if outputs.aligned and align is None:  # nothing moved: the option would be ignored
        raise SDPError("--aligned-output (outputs.aligned) writes the aligned coordinates: give --align too")
    out = Path(output)
    beside = [disappeared_path(f) for f in (out, outputs.png, outputs.html) if f is not None] if outputs.both else []
    check_outputs([out, *beside, outputs.png, outputs.html, outputs.report], [reference, current])
    check_format(out, "points")
    check_picture_extras(png=outputs.png, html=outputs.html, report=outputs.report)
    V.integer_at_least("min_region_points", min_region_points, 0)
    bags = [is_bag(f) for f in (reference, current)]
    if topic is not None and not any(bags):
        raise SDPError("--topic reads a ROS bag (a .bag file, or a ROS 2 bag folder with metadata.yaml)")
    if any(bags) and topic is None:  # before the same-message check, which would name no message
        raise topic_needed(reference if bags[0] else current)
    bag, other = (reference, current) if bags[0] else (current, reference)
    if bags[0] != bags[1] and not Path(other).exists() and str(other).split(":")[0] == topic.split(":")[0]:
        # `sdp change BAG --topic T:0 T:1`: the second message parsed as the current file (ROS names hold no colon)
        raise SDPError(f"{other}: no such file; --topic names one message for both inputs: compare the messages of "
                       f"{bag} with sdp watch BAG BAG --topic {topic} (that message against every one), or give "
                       "each its own file")
    if all(bags) and bag_path(reference) == bag_path(current):  # a ROS 2 bag's folder and its .db3 are one bag
        raise SDPError(f"{reference}: the reference and the current would be the same message ({topic}): compare a "
                       "bag's messages with sdp watch BAG_OR_REFERENCE BAG --topic TOPIC, or give each its own file")
    if any(bags) and execution.tiled:
        raise SDPError("--tiled reads LAS/LAZ, NPY or binary PLY files in slices, not ROS bags")
    if all(bags) and format is not None:  # it would be ignored: a bag's messages carry their own layout
        raise SDPError("--format reads point-cloud files, not a ROS bag's messages (PointCloud2 says its own layout)")
    if execution.tiled and not is_store(reference):
        V.check_tiled_options(grid_size=lattice.grid_size, align=align, sensor_origin=coverage.sensor_origin,
                              range_noise=coverage.range_noise,
                              decision=decision, pictures=outputs.pictures)
    plan = plan_change(reference, current, output=out, format=format, outputs=outputs, lattice=lattice,
                       coverage=coverage, align=align, decision=decision, execution=execution)
    if plan.reason:  # said by the tiles once taken; a refusal of theirs names the limit that runs in memory
        execution = replace(execution, switched=(plan.reason, plan.in_memory))
    with all_or_none():
        if plan.tiled:
            return _compare_tiled(plan, reference, current, out, both=outputs.both,
                                  min_region_points=min_region_points, lattice=lattice, execution=execution,
                                  decision=decision, noise=noise)
        execution.say_in_memory()
        return _compare_in_memory(reference, current, out, outputs=outputs, format=format, lattice=lattice,
                                  coverage=coverage, align=align, memory_limit=execution.memory_limit,
                                  detect=dict(decision=decision, min_region_points=min_region_points, noise=noise),
                                  topic=topic)


def _compare_in_memory(reference, current, out: Path, *, outputs: Outputs, format, lattice: Lattice,
                       coverage: Coverage, align: Registration | None, memory_limit, detect: dict,
                       topic: str | None = None) -> FileComparison:
    from ..change._detect import detect_changes
    from ..io._read import header_point_count

    t0 = time.perf_counter()
    announced = [header_point_count(f, format=format) for f in (reference, current)]
    if all(n is not None for n in announced):  # before reading: a file too large is not loaded first
        _check_in_memory(sum(announced), memory_limit)
    ref, cur = (read_input(f, format=format, topic=topic) for f in (reference, current))
    t_read = time.perf_counter() - t0
    _check_in_memory(len(ref.xyz) + len(cur.xyz), memory_limit)
    names = [f"{f} ({topic})" if is_bag(f) else str(f) for f in (reference, current)]  # which message
    alignment, moved = None, cur
    if align:  # registered, the current is moved into the reference's frame
        alignment = align_clouds(ref, cur, (reference, current), align)
        moved = cur.transformed(alignment.matrix)  # the current scan's sensor moves with it
    else:
        same_frame(ref, cur, names)
    origin = sensor_origins(coverage.sensor_origin, (reference, ref), (current, moved), alignment)
    r = detect_changes(ref, moved, lattice=lattice, coverage=replace(coverage, sensor_origin=origin),
                       memory_limit=memory_limit, **detect)
    out_xyz = moved.xyz if outputs.aligned else cur.xyz
    both, png, html, report = outputs.both, outputs.png, outputs.html, outputs.report
    # each scan's density at its own points, once: written as G and F, and counted where F ≥ 0
    g_cur, g_ref = r.current_field.density(moved.xyz), r.reference_field.density(ref.xyz)
    jobs = [(out, cur, out_xyz, r.current_state, r.appeared_labels, g_cur, r.current_field.h,
             (r.current_distance, r.current_lod))]
    if both:
        jobs.append((disappeared_path(out), ref, ref.xyz, r.reference_state, r.disappeared_labels,
                     g_ref, r.reference_field.h, (r.reference_distance, r.reference_lod)))
    outputs = _write_labelled(jobs, inputs=(reference, current))
    outputs += pictures(png, html, out_xyz, r.current_state, f"appeared in {Path(current).name}",
                         regions=r.appeared_regions if out_xyz is moved.xyz else ())  # boxes in the moved frame
    if both:  # the reference's own pictures, beside them as its points are
        outputs += pictures(png and disappeared_path(png), html and disappeared_path(html), ref.xyz, r.reference_state,
                            f"disappeared from {Path(reference).name}", regions=r.disappeared_regions)
    summary = r.summary()
    summary["timings"]["read"] = t_read
    for role, c in (("reference", ref), ("current", cur)):
        if c.frame is not None:  # a bag message's header.frame_id: the coverage line says why no sensor is known
            summary[role]["frame"] = c.frame
        if c.tf is not None:  # what the bag's /tf did with it
            summary[role]["tf"] = c.tf
    # a point outside its own cluster volume (F ≥ 0: sparser than the lattice assumes) can't be changed
    for role, g, fld in (("reference", g_ref, r.reference_field), ("current", g_cur, r.current_field)):
        summary[role]["outside_own_volume"] = int((g <= fld.h).sum())
    from .._core._points import other_units  # Numba's module: not at the command's start

    spans = [float(np.max(np.ptp(c.xyz, axis=0))) if len(c.xyz) else 0.0 for c in (ref, moved)]
    if other_units(*spans):  # a scan in millimetres against one in metres
        summary["extents"] = spans
    if alignment is not None:
        summary["alignment"] = alignment_summary(alignment, align)
        summary["timings"]["align"] = alignment.seconds
    if report:
        outputs.append(str(report))
    summary["outputs"] = outputs
    summary["inputs"] = names  # before the report: its JSON is the summary --json prints
    if report:
        from ..change._visibility import sensor_range_noise
        from ..viz._report import change_report

        given = coverage.sensor_origin
        options = dict(voxel_size=lattice.voxel_size, grid_size=lattice.grid_size, sigma_voxels=lattice.sigma_voxels,
                       k=lattice.k, h=lattice.h, decision=detect["decision"],
                       min_region_points=detect["min_region_points"],
                       range_noise=max(sensor_range_noise(c, coverage.range_noise) for c in (ref, cur)),
                       **detect["noise"].given,
                       sensor_origin=given if isinstance(given, str) else given.tolist())
        change_report(report, r, ref.xyz, moved.xyz, summary=summary, options=options, timings=summary["timings"],
                      names=tuple(Path(f).name + (f" ({topic})" if is_bag(f) else "") for f in (reference, current)))
    return FileComparison(*names, r, summary, tiled=False, alignment=alignment, outputs=outputs)


def _check_in_memory(n_points: int, memory_limit) -> None:
    """Refuse, before any field is built, a comparison in memory that would exceed the memory
    limit as a whole (:func:`sdp.scale._budget.untiled_point_bytes`), with the smallest limit that holds it."""
    from .._core._memory import memory_limit as limit
    from ..errors import GridTooLargeError
    from ..scale._budget import untiled_point_bytes

    need, cap = untiled_point_bytes(n_points), limit(memory_limit)
    if need > cap:
        raise GridTooLargeError(
            f"comparing {n_points:,} points in memory needs about {format_bytes(need)}, above the memory limit "
            f"of {format_bytes(cap)}: give --memory-limit {math.ceil(need / 2**20)}MB or more (LAS/LAZ, NPY or "
            "binary PLY files with the point or combined decision are compared in tiles instead)")


def _write_labelled(jobs, inputs) -> list[str]:
    """Write each (path, cloud, xyz, state, region, its density G at its points, its field's h) as a
    labelled cloud: ``change`` (0 unchanged, 1 changed, 2 not comparable), ``region``, ``G`` and
    ``F`` = h − G; with the combined decision also ``distance`` and ``lod`` (NaN: nothing to measure
    against)."""
    from ..io._output import write_points

    written = []
    for path, cloud, xyz, state, region, g, h, (dist, lod) in jobs:
        fields = {"change": state, "region": region.astype(np.int32),
                  "G": g.astype(np.float32), "F": (h - g).astype(np.float32)}
        if dist is not None:
            fields.update(distance=dist.astype(np.float32), lod=lod.astype(np.float32))
        write_points(path, xyz, fields, like=cloud, inputs=inputs)
        written.append(str(path))
    return written


def _compare_tiled(plan: ChangePlan, reference, current, out: Path, *, both, min_region_points,
                   lattice: Lattice, execution: Execution, decision: str = DEFAULTS.decision,
                   noise: NoiseModel | None = None) -> FileComparison:
    from ..io._source import write_points_streamed
    from ..scale._tiles import detect_changes_tiled

    lattice = replace(lattice, voxel_size=plan.voxel_size, sigma_voxels=plan.sigma_voxels)  # as sampled
    r = detect_changes_tiled(*plan.sources, lattice=lattice, decision=decision, min_region_points=min_region_points,
                             execution=execution, noise=noise)
    jobs = [(out, plan.sources[1], "current")]
    if both:
        jobs.append((disappeared_path(out), plan.sources[0], "reference"))
    t = time.perf_counter()
    outputs = []
    for path, src, cloud in jobs:
        def fields_of(start, stop, cloud=cloud):  # from the result's rows: no per-point array of the whole cloud
            change, region = r.rows(cloud, start, stop)
            return {"change": change, "region": region}

        # an earlier output's G, F, distance and lod would not match the change written now
        outputs.append(str(write_points_streamed(path, src, fields_of, inputs=(reference, current),
                                                 drop=("G", "F", "distance", "lod"))))
    summary = r.summary()
    summary["timings"]["write"] = time.perf_counter() - t
    summary["outputs"] = outputs
    return FileComparison(str(reference), str(current), r, summary, tiled=True, outputs=outputs)

