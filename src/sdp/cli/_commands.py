"""Each ``sdp`` command as a Python function: files in, files out, one call.

The command line (:mod:`sdp.cli`) parses its options, calls one function of this module and
prints what it returns (the text of :mod:`sdp.cli._text`, or JSON); Python users call the same
functions and get the same files, decisions and errors. The main one is :func:`compare_files`
(``sdp change``): it decides by itself, before any work, whether two clouds are compared in
memory (:func:`sdp.detect_changes`) or in tiles on Dask (:func:`sdp.detect_changes_tiled`),
exactly as the command does (:func:`plan_change`), and writes the labelled clouds.

Every function checks its options (:mod:`sdp._core._validate`) and its outputs
(:func:`sdp.io.check_outputs`) before it reads anything, and writes all its outputs or none
(:func:`sdp.io.all_or_none`). Error messages name options as the command line spells them
(``--align-class`` for ``align_class=``).

References
----------
.. [1] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
   Comparison and Applications", Algorithm 1.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from . import _text as report
from .._core import _validate as V
from .._core._memory import format_bytes
from ..defaults import DEFAULTS
from ..options import Coverage, Cylinder, Execution, Lattice, Outputs, Registration
from ..errors import SDPError
from ..io._output import all_or_none, check_outputs
from ..io._read import read_points

__all__ = ["ChangePlan", "FileComparison", "plan_change", "compare_files", "FileDistances", "distance_files",
           "build_field_file", "mesh_file", "combine_files", "describe_file", "align_files", "watch_folder",
           "Evaluation", "evaluate_files", "render_file", "train_actions", "predict_actions", "stream_actions",
           "evaluate_actions", "disappeared_path"]


def _is_store(path) -> bool:
    return Path(path).suffix.lower() == ".zarr"


def _is_field(path) -> bool:
    return Path(path).suffix.lower() == ".sdpf"


def disappeared_path(output) -> Path:
    """Where ``both=True`` writes the reference's labelled points: ``OUT_disappeared.EXT`` beside ``OUT.EXT``."""
    out = Path(output)
    return out.with_name(out.stem + "_disappeared" + out.suffix)


# --- sdp change ----------------------------------------------------------------------------------

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
    """

    tiled: bool
    reason: str | None = None
    voxel_size: float | None = None
    sigma_voxels: float | None = None
    sources: list | None = None


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
    when two dense float32 grids over the clouds' box (:func:`sdp.scale._tiles.dense_grid_bytes`), or
    the points themselves (:func:`sdp.scale._tiles.untiled_point_bytes`), would exceed the memory
    limit (:func:`sdp._core._memory.memory_limit`). Only LAS/LAZ, NPY and binary PLY files can be read
    in slices, and only the point decision with footprint coverage runs in tiles: other
    files, ``grid_size``, ``align``, ``decision="cluster"`` or a given sensor position keep
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
    from ..scale._tiles import dense_grid_bytes, sampled_lattice, untiled_point_bytes

    outputs = Outputs() if outputs is None else outputs
    lattice = Lattice() if lattice is None else lattice
    coverage = Coverage() if coverage is None else coverage
    execution = Execution() if execution is None else execution
    both, tiled, align = outputs.both, execution.tiled, Registration.of(align)
    if _is_store(reference):  # a stored reference field: its lattice, σ, h and tiles
        from ..scale._store import FieldStore

        sources = [FieldStore.open(reference), PointSource.open(current, format=format)]
        if both:
            raise SDPError("--both needs the reference points; a .zarr field store only tells what appeared")
        return ChangePlan(tiled=True, voxel_size=sources[0].voxel_size,
                          sigma_voxels=sources[0].sigma / sources[0].voxel_size, sources=sources)
    streamed = all((format or FORMATS.get(Path(f).suffix.lower())) in ("las", "npy", "ply")
                   for f in (reference, current))
    # tiles follow no rays: a given sensor keeps the comparison in memory
    given_sensor = not (isinstance(coverage.sensor_origin, str) and coverage.sensor_origin in ("auto", "none"))
    if not tiled and (not streamed or lattice.grid_size is not None or align or decision != "point" or given_sensor):
        return ChangePlan(tiled=False)
    if tiled:
        V.check_tiled_options(grid_size=lattice.grid_size, align=align, sensor_origin=coverage.sensor_origin,
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
    grids = 2 * dense_grid_bytes(lo, hi, voxel, sigma_voxels=sigma_voxels)
    points = untiled_point_bytes(sum(s.n_rows for s in sources))
    cap = limit(execution.memory_limit)
    if not (tiled or max(grids, points) > cap):
        return ChangePlan(tiled=False)
    if output is not None and Path(output).suffix.lower() not in (".las", ".laz"):  # the tiles stream LAS/LAZ
        raise SDPError(f"{output}: the clouds are compared in tiles (two dense grids would need "
                       f"{format_bytes(grids)}, above the memory limit of {format_bytes(cap)}), whose "
                       "output streams to LAS/LAZ: give -o OUT.laz, or a larger --memory-limit")
    reason = None if tiled else (f"comparing in tiles on Dask: dense grids of {format_bytes(grids)} or the points "
                                 f"in memory ({format_bytes(points)} with the process) exceed the memory limit of "
                                 f"{format_bytes(cap)}")
    if reason and outputs.pictures:  # the pictures need every point in memory
        raise SDPError(f"--png/--html/--report are made in memory, but dense grids of {format_bytes(grids)} "
                       f"exceed the memory limit of {format_bytes(cap)}: give a larger --memory-limit or no pictures")
    return ChangePlan(tiled=True, reason=reason, voxel_size=float(voxel), sigma_voxels=sigma_voxels, sources=sources)


def compare_files(reference, current, *, output, outputs: Outputs | None = None, format: str | None = None,
                  lattice: Lattice | None = None, coverage: Coverage | None = None,
                  align: Registration | str | None = None, execution: Execution | None = None,
                  decision: str = DEFAULTS.decision,
                  min_region_points: int = DEFAULTS.min_region_points) -> FileComparison:
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
        Point-cloud files (PCD, PLY, LAS/LAZ, XYZ/TXT/CSV, NPY/NPZ; ``format`` overrides the
        extension). ``reference`` may be a ``.zarr`` field store (:func:`build_field_file`):
        compared in tiles, what appeared only.
    output : path-like
        The labelled current cloud (.ply, .las, .laz, .npz; tiles write LAS/LAZ).
    outputs : Outputs, optional
        What else to write (:class:`sdp.Outputs`): ``both``, the reference's points labelled
        as disappeared, to :func:`disappeared_path`; ``png`` and ``html``, pictures of the
        appeared points (:func:`sdp.render_changes`, :func:`sdp.render_changes_html`);
        ``report``, one self-contained HTML page (:func:`sdp.change_report`: summary,
        parameters and why, maps of both directions, region sizes, the region table with
        thumbnails, a 3-D view; in memory only, refused with tiles); ``aligned``, the current's
        points where the alignment moved them (default: its own coordinates).
    lattice, decision, min_region_points
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
    outputs = Outputs() if outputs is None else outputs
    lattice = Lattice() if lattice is None else lattice
    coverage = Coverage() if coverage is None else coverage
    execution = Execution() if execution is None else execution
    align = Registration.of(align)
    out = Path(output)
    check_outputs([out, disappeared_path(out) if outputs.both else None, outputs.png, outputs.html, outputs.report],
                  [reference, current])
    _check_picture_extras(png=outputs.png, html=outputs.html, report=outputs.report)
    V.integer_at_least("min_region_points", min_region_points, 0)
    if execution.tiled and not _is_store(reference):
        V.check_tiled_options(grid_size=lattice.grid_size, align=align, sensor_origin=coverage.sensor_origin,
                              decision=decision, pictures=outputs.pictures)
    plan = plan_change(reference, current, output=out, format=format, outputs=outputs, lattice=lattice,
                       coverage=coverage, align=align, decision=decision, execution=execution)
    if plan.reason and execution.notify is not None:
        execution.notify(plan.reason)
    with all_or_none():
        if plan.tiled:
            return _compare_tiled(plan, reference, current, out, both=outputs.both,
                                  min_region_points=min_region_points, lattice=lattice, execution=execution)
        return _compare_in_memory(reference, current, out, outputs=outputs, format=format, lattice=lattice,
                                  coverage=coverage, align=align, memory_limit=execution.memory_limit,
                                  detect=dict(decision=decision, min_region_points=min_region_points))


def _compare_in_memory(reference, current, out: Path, *, outputs: Outputs, format, lattice: Lattice,
                       coverage: Coverage, align: Registration | None, memory_limit, detect: dict) -> FileComparison:
    from ..change._detect import detect_changes

    t0 = time.perf_counter()
    ref, cur = read_points(reference, format=format), read_points(current, format=format)
    t_read = time.perf_counter() - t0
    _check_in_memory(len(ref.xyz) + len(cur.xyz), memory_limit)
    alignment, moved = None, cur
    if align:
        alignment = _align_clouds(ref, cur, (reference, current), align)
        moved = cur.transformed(alignment.matrix)  # the current scan's sensor moves with it
    origin = _sensor_origins(coverage.sensor_origin, (reference, ref), (current, moved), alignment)
    r = detect_changes(ref, moved, lattice=lattice, coverage=replace(coverage, sensor_origin=origin),
                       memory_limit=memory_limit, **detect)
    out_xyz = moved.xyz if outputs.aligned else cur.xyz
    both, png, html, report = outputs.both, outputs.png, outputs.html, outputs.report
    jobs = [(out, cur, out_xyz, r.current_state, r.appeared_labels, r.current_field, moved.xyz)]
    if both:
        jobs.append((disappeared_path(out), ref, ref.xyz, r.reference_state, r.disappeared_labels,
                     r.reference_field, ref.xyz))
    outputs = _write_labelled(jobs, inputs=(reference, current))
    outputs += _pictures(png, html, out_xyz, r.current_state, f"appeared in {Path(current).name}",
                         regions=r.appeared_regions if out_xyz is moved.xyz else ())  # boxes in the moved frame
    summary = r.summary()
    summary["timings"]["read"] = t_read
    if alignment is not None:
        summary["alignment"] = alignment.summary()
        summary["timings"]["align"] = alignment.seconds
    if report:
        outputs.append(str(report))
    summary["outputs"] = outputs
    if report:
        from ..viz._report import change_report

        t = time.perf_counter()
        given = coverage.sensor_origin
        options = dict(voxel_size=lattice.voxel_size, grid_size=lattice.grid_size, sigma_voxels=lattice.sigma_voxels,
                       k=lattice.k, h=lattice.h, decision=detect["decision"],
                       min_region_points=detect["min_region_points"], range_noise=coverage.range_noise,
                       sensor_origin=given if isinstance(given, str) else given.tolist())
        change_report(report, r, ref.xyz, moved.xyz, summary=summary, options=options,
                      names=(Path(reference).name, Path(current).name))
        summary["timings"]["report"] = time.perf_counter() - t
    return FileComparison(str(reference), str(current), r, summary, tiled=False, alignment=alignment, outputs=outputs)


def _check_in_memory(n_points: int, memory_limit) -> None:
    """Refuse, before any field is built, a comparison in memory that would exceed the memory
    limit as a whole (:func:`sdp.scale._tiles.untiled_point_bytes`), with the smallest limit that holds it."""
    from ..errors import GridTooLargeError
    from .._core._memory import memory_limit as limit
    from ..scale._tiles import untiled_point_bytes

    need, cap = untiled_point_bytes(n_points), limit(memory_limit)
    if need > cap:
        raise GridTooLargeError(
            f"comparing {n_points:,} points in memory needs about {format_bytes(need)}, above the memory limit "
            f"of {format_bytes(cap)}: give --memory-limit {math.ceil(need / 2**20)}MB or more (LAS/LAZ, NPY or "
            "binary PLY files with the point decision are compared in tiles instead)")


def _write_labelled(jobs, inputs) -> list[str]:
    """Write each (path, cloud, xyz, state, region, field, xyz the field saw) as a labelled cloud:
    ``change`` (0 unchanged, 1 changed, 2 not comparable), ``region``, ``G`` and ``F``."""
    from ..io._output import write_points

    written = []
    for path, cloud, xyz, state, region, fld, seen in jobs:
        fields = {"change": state, "region": region.astype(np.int32),
                  "G": fld.density(seen).astype(np.float32), "F": fld.field(seen).astype(np.float32)}
        write_points(path, xyz, fields, like=cloud, inputs=inputs)
        written.append(str(path))
    return written


def _compare_tiled(plan: ChangePlan, reference, current, out: Path, *, both, min_region_points,
                   lattice: Lattice, execution: Execution) -> FileComparison:
    from ..io._source import write_points_streamed
    from ..scale._tiles import detect_changes_tiled

    lattice = replace(lattice, voxel_size=plan.voxel_size, sigma_voxels=plan.sigma_voxels)  # as sampled
    r = detect_changes_tiled(*plan.sources, lattice=lattice, min_region_points=min_region_points, execution=execution)
    jobs = [(out, plan.sources[1], "current")]
    if both:
        jobs.append((disappeared_path(out), plan.sources[0], "reference"))
    t = time.perf_counter()
    outputs = []
    for path, src, cloud in jobs:
        def fields_of(start, stop, cloud=cloud):  # from the result's rows: no per-point array of the whole cloud
            change, region = r.rows(cloud, start, stop)
            return {"change": change, "region": region}

        outputs.append(str(write_points_streamed(path, src, fields_of, inputs=(reference, current))))
    summary = r.summary()
    summary["timings"]["write"] = time.perf_counter() - t
    summary["outputs"] = outputs
    return FileComparison(str(reference), str(current), r, summary, tiled=True, outputs=outputs)


def _sensor_origins(choice, ref_scan, cur_scan, alignment=None):
    """``sensor_origin=`` of :func:`sdp.detect_changes` from a checked ``--sensor-origin``
    (:func:`sdp._core._validate.sensor_origin_option`): ``auto``/``none`` as they are, ``viewpoint``
    as ``auto`` once both files (name, Cloud) record a position, a position for both scans
    (the current's moved by ``alignment``)."""
    if isinstance(choice, str):
        if choice == "viewpoint":
            for name, c in (ref_scan, cur_scan):
                if c.sensor_origin is None:
                    raise SDPError(f"{name}: the file records no sensor position (organized PCD files do); "
                                   "give --sensor-origin X,Y,Z or auto")
            return "auto"
        return choice
    cur_xyz = choice if alignment is None else alignment.apply(np.array([choice]))[0]
    return np.array([choice, cur_xyz], dtype=np.float64)


def _align_clouds(ref, cur, names, registration: Registration):
    """:func:`sdp.align` of the current Cloud onto the reference (a Cloud, or a DensityField),
    estimated on the points of the registration's LAS classes of both when given."""
    from ..registration._align import align
    from ..fields._density import DensityField

    ref_xyz = ref if isinstance(ref, DensityField) else ref.xyz
    cur_xyz = cur.xyz
    classes, align_class = registration.classes, registration.align_class
    if classes is not None:
        if isinstance(ref, DensityField):
            raise SDPError("--align-class needs the reference's points, not a field")
        picked = []
        for cloud, name in zip((ref, cur), names, strict=True):
            if "classification" not in cloud.fields:
                raise SDPError(f"{name}: no 'classification' field for --align-class (LAS/LAZ files have one)")
            keep = np.isin(cloud.fields["classification"], classes)
            if keep.sum() < 3:
                shown = align_class if isinstance(align_class, str) else ",".join(map(str, classes))
                raise SDPError(f"{name}: {int(keep.sum())} points of class {shown}: too few to align on")
            picked.append(cloud.xyz[keep])
        ref_xyz, cur_xyz = picked
    return align(ref_xyz, cur_xyz, method=registration.method, fix_horizontal=registration.fix_horizontal)


def _check_picture_extras(*, png=None, html=None, report=None) -> None:
    """Before any work: the extras the asked-for pictures need (one-line :class:`sdp.MissingDependencyError`)."""
    from ..errors import require

    if png:
        require("matplotlib", "plots", "--png (a PNG)")
    if html:
        require("plotly", "plots", "--html (an HTML view)")
    if report:
        from ..viz._report import require_extras

        require_extras()


def _pictures(png, html, xyz, changed, title, regions=()) -> list[str]:
    """Write the ``png`` / ``html`` pictures of changed points that were asked for (a map outlines ``regions``)."""
    if not (png or html):
        return []
    from ..viz._render import render_changes, render_changes_html

    written = []
    if png:
        render_changes(png, xyz, changed, title=title, regions=regions)
        written.append(str(png))
    if html:
        render_changes_html(html, xyz, changed, title=title)
        written.append(str(html))
    return written


# --- sdp distance ------------------------------------------------------------------------------

@dataclass
class FileDistances:
    """What :func:`distance_files` measured and wrote."""

    reference: str
    current: str
    result: object  # sdp.Distances
    summary: dict
    alignment: object = None
    outputs: list = field(default_factory=list)

    def summary_text(self) -> str:
        return report.distance_text(self.summary, self.reference, self.current)


def distance_files(reference, current, *, output, core_points=None, outputs: Outputs | None = None,
                   format: str | None = None, cylinder: Cylinder | None = None,
                   registration_error: float | str = "auto", orientation=None,
                   sensor_origin=DEFAULTS.sensor_origin, align: Registration | str | None = None,
                   execution: Execution | None = None) -> FileDistances:
    """Signed distances from the reference to the current along the normal, with M3C2's level of
    detection, written per core point: ``sdp distance`` as a function.

    The output holds the core points (default: every reference point, M3C2's epoch 1) with the
    fields of :data:`sdp.distance._distances.DISTANCE_FIELDS` (``distance``, ``lod``, ``significant``,
    ``n1``, ``n2``, ``spread1``, ``spread2``, ``normal_x/y/z``; NaN distance where an epoch has
    no points near: not comparable). LAS/LAZ output of LAS/LAZ core points keeps every input
    dimension.

    Parameters
    ----------
    reference, current : path-like
        Point-cloud files (``format`` overrides the extension).
    output : path-like
        The core points with their distances (.ply, .las, .laz, .npz).
    core_points : path-like, optional
        A cloud file of core points (any format sdp reads).
    outputs : Outputs, optional
        ``png``: a map (or view) of the significant distances and their histogram
        (:func:`sdp.render_distances`); ``report``: one self-contained HTML page
        (:func:`sdp.distance_report`: summary, parameters and why, the map and histogram, a
        3-D view). In memory only (refused with tiles).
    cylinder, orientation, sensor_origin
        As in :func:`sdp.distances` (``sensor_origin`` also takes ``"viewpoint"`` and ``"X,Y,Z"``,
        as :func:`compare_files`).
    registration_error : float or "auto"
        M3C2's registration error; ``"auto"``: the alignment's RMS residual with ``align``, else 0.
    align : Registration, "density" or "gicp", optional
        Register the current onto the reference first, as :func:`compare_files`; the distances are
        between the aligned epochs.
    execution : Execution, optional
        The memory limit and the tiles: ``tiled`` measures in tiles on Dask
        (:func:`sdp.distances_tiled`: every reference row, normals along ``orientation``, LAS/LAZ
        output streamed from the reference), as it does by itself when the in-memory work would
        exceed the memory limit (``notify`` gets one line saying so).

    Returns
    -------
    FileDistances

    Raises
    ------
    SDPError
        Bad options, outputs that can't be written or would overwrite an input, unreadable files.

    References
    ----------
    .. [1] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
       terrestrial laser scanner", ISPRS J. Photogramm. 82 (2013) (M3C2).
    """
    from ..distance._distances import distances
    from ..io._output import write_points

    outputs = Outputs() if outputs is None else outputs
    cylinder = Cylinder() if cylinder is None else cylinder
    execution = Execution() if execution is None else execution
    align = Registration.of(align)
    png, report, memory_limit = outputs.png, outputs.report, execution.memory_limit
    out = Path(output)
    check_outputs([out, png, report], [reference, current, core_points])
    _check_picture_extras(png=png, report=report)
    V.auto_or_nonnegative("--registration-error", registration_error)
    sensor = V.sensor_origin_option("--sensor-origin", sensor_origin)
    if orientation is not None:
        orientation = V.sensor_origin_option("--orientation", orientation)
        if isinstance(orientation, str):
            raise SDPError(f"--orientation must be X,Y,Z, got {orientation!r}")
    if _distances_in_tiles(reference, current, output, format=format, execution=execution, core_points=core_points,
                           align=align, png=png, report=report):
        return _distance_tiled(reference, current, out, format=format, registration_error=registration_error,
                               orientation=orientation, cylinder=cylinder, execution=execution)
    with all_or_none():
        t0 = time.perf_counter()
        ref, cur = read_points(reference, format=format), read_points(current, format=format)
        core = None if core_points is None else read_points(core_points, format=format)
        t_read = time.perf_counter() - t0
        alignment, moved = None, cur
        if align:
            alignment = _align_clouds(ref, cur, (reference, current), align)
            moved = cur.transformed(alignment.matrix)
        reg = V.auto_or_nonnegative("--registration-error", registration_error)
        if reg == "auto":
            reg = float(alignment.rmse) if alignment is not None and np.isfinite(alignment.rmse) else 0.0
        origin = _sensor_origins(sensor, (reference, ref), (current, moved), alignment)
        d = distances(ref, moved, core_points=core, cylinder=cylinder, registration_error=reg,
                      orientation=orientation, sensor_origin=origin, memory_limit=memory_limit)
        like = core if core is not None else ref
        like = like if like.n_dropped == 0 else None  # rows were dropped: the input's dimensions no longer line up
        write_points(out, d.core_points, d.fields(), like=like, inputs=(reference, current, core_points))
        outputs = [str(out)]
        if png:
            from ..viz._render import render_distances

            render_distances(png, d.core_points, d.distance, d.significant, d.lod,
                             title=f"{Path(reference).name} → {Path(current).name}: signed distance")
            outputs.append(str(png))
        summary = d.summary()
        summary["timings"]["read"] = round(t_read, 4)
        if alignment is not None:
            summary["alignment"] = alignment.summary()
        if report:
            from ..viz._report import distance_report

            outputs.append(str(report))
            summary["outputs"] = outputs
            t = time.perf_counter()
            distance_report(report, d, summary=summary, names=(Path(reference).name, Path(current).name),
                            options=dict(projection_scale=cylinder.projection_scale,
                                         normal_scale=cylinder.normal_scale, max_distance=cylinder.max_distance,
                                         registration_error=registration_error, orientation=orientation,
                                         sensor_origin=sensor_origin))
            summary["timings"]["report"] = round(time.perf_counter() - t, 4)
    summary["outputs"] = outputs
    return FileDistances(str(reference), str(current), d, summary, alignment, outputs)


def _distances_in_tiles(reference, current, output, *, format, execution: Execution, core_points, align, png,
                        report=None) -> bool:
    """Whether :func:`distance_files` measures in tiles: asked, or the in-memory work (about
    450 bytes per reference point and 200 per current point) would exceed the memory limit."""
    from .._core._memory import memory_limit as limit
    from ..io._source import PointSource

    tiled, notify = execution.tiled, execution.notify
    try:
        n_ref, n_cur = (PointSource.open(f, format=format).n_rows for f in (reference, current))
    except SDPError:
        if tiled:
            raise SDPError("--tiled reads LAS/LAZ, NPY or binary PLY files in slices; "
                           "convert the clouds first") from None
        return False
    need, cap = 450.0 * n_ref + 200.0 * n_cur, limit(execution.memory_limit)
    if not (tiled or need > cap):
        return False
    for option, given in (("--core-points", core_points), ("--align", align), ("--png", png), ("--report", report)):
        if given:
            raise SDPError(f"{option} is not available in tiles (the in-memory work would need "
                           f"{format_bytes(need)}; the memory limit is {format_bytes(cap)})")
    if Path(output).suffix.lower() not in (".las", ".laz"):
        raise SDPError(f"{output}: distances in tiles stream to LAS/LAZ: give -o OUT.laz")
    if not tiled and notify is not None:
        notify(f"measuring in tiles on Dask: the in-memory work would need {format_bytes(need)}, above the "
               f"memory limit of {format_bytes(cap)}")
    return True


def _distance_tiled(reference, current, out: Path, *, format, registration_error, orientation, cylinder: Cylinder,
                    execution: Execution) -> FileDistances:
    from ..io._source import PointSource, write_points_streamed
    from ..scale._tiles import distances_tiled

    reg = V.auto_or_nonnegative("--registration-error", registration_error)
    with all_or_none():
        d = distances_tiled(reference, current, cylinder=cylinder, registration_error=0.0 if reg == "auto" else reg,
                            orientation=orientation, execution=execution)
        fields = d.fields()
        write_points_streamed(out, PointSource.open(reference, format=format),
                              lambda a, b: {k: v[a:b] for k, v in fields.items()}, inputs=(reference, current))
    summary = d.summary()
    summary["outputs"] = [str(out)]
    return FileDistances(str(reference), str(current), d, summary, None, [str(out)])


# --- fields: sdp build, mesh, bool, info ---------------------------------------------------------

def _lattice(clouds, lattice: Lattice, memory_limit, like=None) -> dict:
    """``DensityField.from_points`` options: ``lattice`` (``auto``: from all ``clouds``' point
    spacing), or the lattice, σ and h of the field ``like`` so results can be combined."""
    from .._core._points import as_points
    from ..fields._spacing import resolve_lattice

    if like is not None:
        return dict(voxel_size=like.voxel_size, sigma_voxels=like.sigma / like.voxel_size, h=like.h,
                    truncate=like.truncate, memory_limit=memory_limit)
    kw = lattice.keywords()
    kw["voxel_size"], kw["sigma_voxels"] = resolve_lattice(
        [as_points(c) for c in clouds], voxel_size=kw.pop("voxel_size", "auto"), grid_size=kw.pop("grid_size", None),
        k=lattice.k, sigma_voxels=lattice.sigma_voxels)
    return dict(kw, memory_limit=memory_limit)


def _field_or_points(path, format):
    """A field file loaded, or a cloud file's points (n, 3)."""
    from ..fields._density import DensityField

    return DensityField.load(path) if _is_field(path) else read_points(path, format=format).xyz


def _field(path, format, lattice: Lattice, memory_limit):
    """A field file loaded, or a cloud file's field built on ``lattice``."""
    from ..fields._density import DensityField

    x = _field_or_points(path, format)
    return x if isinstance(x, DensityField) else DensityField.from_points(x, **_lattice([x], lattice, memory_limit))


def build_field_file(cloud, *, output, format: str | None = None, lattice: Lattice | None = None,
                     execution: Execution | None = None):
    """Build the density field of a cloud file and save it (``sdp build``).

    ``output`` ``.sdpf``: :meth:`DensityField.from_points` in memory on ``lattice``,
    :meth:`DensityField.save`; ``.zarr``: a :class:`~sdp.FieldStore` built in tiles
    (:func:`sdp.build_field_tiled` with ``execution``, the file read in slices,
    ``voxel_size="auto"`` from its first slice). Returns the field or store.
    """
    lattice = Lattice() if lattice is None else lattice
    execution = Execution() if execution is None else execution
    check_outputs([output], [cloud])
    if not _is_store(output):
        fld = _field(cloud, format, lattice, execution.memory_limit)
        _save_field(fld, output, inputs=(cloud,))
        return fld
    from ..io._source import PointSource
    from ..scale._tiles import build_field_tiled, sampled_lattice

    source = PointSource.open(cloud, format=format)
    voxel, sigma_voxels = sampled_lattice([source], voxel_size=lattice.voxel_size, k=lattice.k,
                                          sigma_voxels=lattice.sigma_voxels)
    return build_field_tiled(source, output, lattice=replace(lattice, voxel_size=voxel, sigma_voxels=sigma_voxels),
                             execution=execution)


def _save_field(fld, path, inputs):
    from ..io._output import refuse_overwrite

    refuse_overwrite(path, inputs)
    fld.save(path)


def mesh_file(path, *, output, level: float = 0.0, format: str | None = None, lattice: Lattice | None = None,
              memory_limit=None):
    """Write the iso-surface F = ``level`` of a field (``.sdpf``), field store (``.zarr``) or
    cloud file (built on ``lattice``) as PLY/OBJ/STL (``sdp mesh``); returns the Mesh."""
    from .._core._memory import memory_limit as limit
    from ..io._output import write_mesh

    lattice = Lattice() if lattice is None else lattice
    check_outputs([output], [path])
    limit(memory_limit)
    if _is_store(path):
        from ..scale._store import FieldStore

        mesh = FieldStore.open(path).mesh(level=level)
    else:
        mesh = _field(path, format, lattice, memory_limit).mesh(level=level)
    write_mesh(output, mesh, inputs=(path,))
    return mesh


def combine_files(operation: str, a, b, *, output, format: str | None = None, lattice: Lattice | None = None,
                  memory_limit=None):
    """Union, intersection or difference of two fields or clouds, saved (``sdp bool``).

    A cloud is built on the lattice of the other operand when that is a field, else both
    clouds on ``lattice`` (``auto``: one voxel from both). ``output`` ``.sdpf``: the field; ``.ply``/``.obj``/``.stl``:
    its surface (returns the Mesh); ``.zarr``: two field stores combined tile by tile.
    """
    from .._core._memory import memory_limit as limit
    from ..fields import _boolean as boolean
    from ..fields._density import DensityField
    from ..io._output import write_mesh

    if operation not in ("union", "intersection", "difference"):
        raise SDPError(f"operation must be union, intersection or difference, got {operation!r}")
    lattice = Lattice() if lattice is None else lattice
    check_outputs([output], [a, b])
    limit(memory_limit)
    if _is_store(output):
        from ..scale._store import FieldStore

        if not (_is_store(a) and _is_store(b)):
            raise SDPError("a .zarr output combines two .zarr field stores (build them with sdp build -o X.zarr)")
        return FieldStore.open(a).combine(FieldStore.open(b), operation, output)
    items = [_field_or_points(p, format) for p in (a, b)]
    like = next((x for x in items if isinstance(x, DensityField)), None)
    kw = _lattice(items, lattice, memory_limit, like)  # clouds are built on a given field's lattice, else on one from both
    fa, fb = (x if isinstance(x, DensityField) else DensityField.from_points(x, **kw) for x in items)
    result = getattr(boolean, operation)(fa, fb)
    if _is_field(output):
        _save_field(result, output, inputs=(a, b))
        return result
    mesh = result.mesh()
    write_mesh(output, mesh, inputs=(a, b))
    return mesh


def describe_file(path, *, format: str | None = None) -> dict:
    """What ``sdp info`` prints: kind, size and parameters of a cloud, field (``.sdpf``) or field store."""
    from ..fields._density import DensityField

    if _is_store(path):
        from ..scale._store import FieldStore

        st = FieldStore.open(path)
        return {"kind": "field store", "voxel_size": st.voxel_size, "sigma": st.sigma, "h": st.h,
                "tiles": len(st.tiles), "tile_blocks": st.tile_blocks, "blocks": st.n_blocks, "n_points": st.n_points}
    if _is_field(path):
        f = DensityField.load(path)
        return {"kind": "field", "voxel_size": f.voxel_size, "sigma": f.sigma, "h": f.h, "blocks": f.n_blocks,
                "box_nodes": list(f.grid.shape), "origin": f.grid.origin.tolist(), "n_points": f.n_points,
                "method": f.method, "megabytes": f.nbytes / 2**20}
    c = read_points(path, format=format)
    return {"kind": "cloud", "points": len(c), "dropped_non_finite": c.n_dropped,
            "min": c.xyz.min(0).tolist(), "max": c.xyz.max(0).tolist(), "fields": sorted(c.fields)}


# --- sdp align, watch --------------------------------------------------------------------------

def align_files(reference, current, *, output, method: str = DEFAULTS.align_method, fix_horizontal: bool = False,
                align_class=None, format: str | None = None):
    """Estimate the rigid transform that moves ``current`` onto ``reference`` (a cloud, or a
    field ``.sdpf`` for ``method="density"``) and write it as a 4x4 text matrix for
    ``numpy.loadtxt`` (``sdp align REFERENCE CURRENT``: the reference first, as in every
    command); ``fix_horizontal`` and ``align_class`` as in :func:`compare_files`. Returns the
    :class:`~sdp.Alignment`."""
    from ..fields._density import DensityField
    from ..io._output import atomic_path, refuse_overwrite

    check_outputs([output], [reference, current])
    refuse_overwrite(output, (reference, current))
    registration = Registration(method=method, fix_horizontal=fix_horizontal, align_class=align_class)
    ref = DensityField.load(reference) if _is_field(reference) else read_points(reference, format=format)
    al = _align_clouds(ref, read_points(current, format=format), (reference, current), registration)
    with atomic_path(output) as tmp:
        np.savetxt(tmp, al.matrix, fmt="%.12g", header=f"sdp align {current} onto {reference} ({method})")
    return al


def watch_folder(reference, frames, *, format: str | None = None, lattice: Lattice | None = None,
                 update: str = DEFAULTS.update, window: int = DEFAULTS.window, decay: float = DEFAULTS.decay,
                 min_region_points: int = DEFAULTS.min_region_points, align: Registration | str | None = None,
                 coverage: Coverage | None = None) -> Iterator:
    """:func:`sdp.watch` over the point-cloud files of a folder, in natural name order (``sdp watch``).

    ``reference`` is a cloud file or a field (``.sdpf``); ``coverage`` as in
    :func:`compare_files` (its ``sensor_origin`` is the reference's). The folder and the reference are checked and read
    now; the frames are read one by one as the returned iterator of :class:`~sdp.FrameChange`
    (named after their files) advances.
    """
    import re

    from ..io._cloud import FORMATS
    from ..stream._watch import watch

    folder = Path(frames)
    if not folder.is_dir():
        raise SDPError(f"{folder}: not a folder of frames")
    paths = sorted((p for p in folder.iterdir() if p.suffix.lower() in FORMATS and p.is_file()),
                   key=lambda p: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)])
    if not paths:
        raise SDPError(f"{folder}: no point-cloud files ({', '.join(sorted(FORMATS))})")
    coverage = Coverage() if coverage is None else coverage
    choice = coverage.sensor_origin
    if _is_field(reference):
        from ..fields._density import DensityField

        if not (isinstance(choice, str) and choice in ("auto", "none")):
            raise SDPError("--sensor-origin follows the reference's rays: give the reference cloud, not a field")
        ref, origin = DensityField.load(reference), None
    else:
        ref = read_points(reference, format=format)
        origin = _sensor_origins(choice, (reference, ref), (reference, ref))
        origin = origin[0] if isinstance(origin, np.ndarray) else origin
    stream = ((p.name, read_points(p, format=format)) for p in paths)
    return watch(ref, stream, lattice=lattice, update=update, window=window, decay=decay,
                 min_region_points=min_region_points, align=align, coverage=replace(coverage, sensor_origin=origin))


# --- sdp eval, render --------------------------------------------------------------------------

@dataclass
class Evaluation:
    """Scores of predicted change labels against truth (:func:`evaluate_files`).

    Attributes
    ----------
    scores : dict
        :func:`sdp.scores` (what ``sdp eval --json`` prints).
    points, predicted, true : int
        Points compared, points predicted changed, truly changed points among the comparable.
    """

    scores: dict
    points: int
    predicted: int
    true: int

    def summary_text(self) -> str:
        """The three lines ``sdp eval`` prints."""
        return report.evaluation_text(self)


def evaluate_files(predicted, truth, *, predicted_field: str = "change", truth_field: str = "change",
                   format: str | None = None) -> Evaluation:
    """Kappa, precision, recall, IoU … of the labels of one file against another's (``sdp eval``).

    ``predicted_field="change"`` (sdp's field): 1 is changed and 2 not comparable (left out);
    any other field, and ``truth_field``: nonzero is changed. Both files hold the same points
    in the same order.
    """
    from ..change._coverage import CHANGED, NOT_COMPARABLE
    from ..change._metrics import scores

    values = []
    for path, name in ((predicted, predicted_field), (truth, truth_field)):
        c = read_points(path, format=format)
        if name not in c.fields:
            raise SDPError(f"{path}: no per-point field {name!r} (fields: {', '.join(sorted(c.fields)) or 'none'})")
        values.append(np.asarray(c.fields[name]))
    if len(values[0]) != len(values[1]):
        raise SDPError(f"{predicted} has {len(values[0]):,} points and {truth} {len(values[1]):,}: "
                       "they must be the same points in the same order")
    if predicted_field == "change":  # sdp's field: 1 changed, 2 not comparable (scored apart)
        changed, comparable = values[0] == CHANGED, values[0] != NOT_COMPARABLE
    else:  # any other field: nonzero is changed
        changed, comparable = values[0] != 0, None
    true = values[1] != 0
    sc = scores(true, changed, comparable=comparable)
    comparable = np.ones(len(true), bool) if comparable is None else comparable
    return Evaluation(sc, len(true), int(changed.sum()), int(true[comparable].sum()))


def render_file(path, *, png=None, html=None, field: str = "change", format: str | None = None) -> list[str]:
    """Pictures of a labelled cloud (points whose ``field`` is nonzero in vermillion; sdp's
    ``change``: not comparable grey) or PNG slices of a field ``.sdpf`` (``sdp render``);
    returns the files written."""
    if not (png or html):
        raise SDPError("nothing to write: give --png OUT.png and/or --html OUT.html")
    check_outputs([png, html], [path])
    if _is_field(path):
        from ..fields._density import DensityField
        from ..viz._render import render_field

        if html:
            raise SDPError("--html draws clouds; for a field use --png (slices), or `sdp mesh` for its surface")
        render_field(png, DensityField.load(path))
        return [str(png)]
    c = read_points(path, format=format)
    if field not in c.fields:
        raise SDPError(f"{path}: no per-point field {field!r} to colour by "
                       f"(fields: {', '.join(sorted(c.fields)) or 'none'}); choose one with --field")
    values = np.asarray(c.fields[field])
    if field == "change":  # sdp's field: 0 unchanged, 1 changed, 2 not comparable
        state, what = values.astype(np.uint8), "changed vermillion, not comparable grey"
    else:
        state, what = values != 0, f"{field} ≠ 0 in vermillion"
    with all_or_none():
        return _pictures(png, html, c.xyz, state, f"{Path(path).name}: {what}")


# --- sdp action --------------------------------------------------------------------------------

def train_actions(data_dir, *, output, subjects=None, workers: int = os.cpu_count() or 1):
    """Fit an action classifier on a folder of ``aXX_sYY_eZZ`` depth sequences and save it
    (``sdp action train``); ``subjects``: "1,3,5" or numbers to train on (default all).
    Returns (model, cross-validated accuracy, sequences used)."""
    from ..actions import _actions as actions

    check_outputs([output], [data_dir])
    rows = actions.list_sequences(data_dir)
    if subjects:
        try:
            wanted = {int(v) for v in (subjects.split(",") if isinstance(subjects, str) else subjects)}
        except ValueError:
            raise SDPError(f"--subjects takes subject numbers such as 1,3,5, got {subjects!r}") from None
        rows = [r for r in rows if r[2] in wanted]
    x = actions.describe_sequences([r[0] for r in rows], workers=workers)
    model, cv = actions.train(x, np.array([r[1] for r in rows]), np.array([r[2] for r in rows]))
    model.save(output)
    return model, cv, len(rows)


def predict_actions(model, sequences) -> list[tuple[str, int]]:
    """(sequence, action label) of each depth-sequence file, by a saved model (``sdp action predict``)."""
    from ..actions import _actions as actions

    if not sequences:
        raise SDPError("sdp action predict needs depth sequences, or --stream FRAMES")
    m = actions.ActionModel.load(model)
    return [(str(p), int(m.predict(actions.sequence_descriptor(actions.read_sequence(p)))[0])) for p in sequences]


def stream_actions(model, source, *, window: int = DEFAULTS.action_window, every: int = DEFAULTS.action_every):
    """(frame number from 1, action label) at each report of an :class:`sdp.actions._actions.ActionStream`
    over the frames of ``source`` (``sdp action predict MODEL --stream SOURCE``)."""
    from ..actions import _actions as actions

    stream = actions.ActionStream(actions.ActionModel.load(model), window=window, every=every,
                                  min_frames=min(10, window))
    for frame in actions.read_frames(source):
        label = stream.push(frame)
        if label is not None:
            yield stream.n_frames, label


def evaluate_actions(data_dir, *, workers: int = os.cpu_count() or 1) -> dict:
    """The cross-subject protocol (:func:`sdp.actions._actions.evaluate_protocol`) as ``sdp action eval
    --json`` prints it: accuracy per subset (fractions), ``cv``, ``alpha``, ``timings``, ``sequences``."""
    from ..actions import _actions as actions

    t0 = time.perf_counter()
    r = actions.evaluate_protocol(data_dir, workers=workers)
    r["timings"]["total"] = time.perf_counter() - t0
    return dict(r["accuracy"], cv=r["cv_accuracy"], alpha=r["alpha"], timings=r["timings"], sequences=r["sequences"])
