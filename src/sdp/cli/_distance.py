"""``sdp distance`` as a function: signed distances with their level of detection, files to files.

References
----------
.. [1] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
   terrestrial laser scanner", ISPRS J. Photogramm. 82 (2013) (M3C2).
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
from ..distance._names import rename_fields
from ..errors import SDPError
from ..io._output import all_or_none, check_format, check_outputs
from ..io._read import read_points
from ..options import Cylinder, Execution, Outputs, Registration, as_options
from . import _text as report
from ._common import align_clouds, alignment_summary, check_picture_extras, sensor_origins

__all__ = ["FileDistances", "distance_files"]


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


#: Names of normals a points file may carry (PLY's, PCL's, PDAL's, CloudCompare's), in lower case.
_NORMAL_NAMES = {"nx", "ny", "nz", "normal_x", "normal_y", "normal_z", "normalx", "normaly", "normalz"}


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
        3-D view). In memory only (refused with tiles). ``field_names``: the output's names of the
        fields (``"cloudcompare"``, ``"pdal"``: as those tools' M3C2 name them).
    cylinder, orientation, sensor_origin
        As in :func:`sdp.distances` (``sensor_origin`` also takes ``"viewpoint"`` and ``"X,Y,Z"``,
        as :func:`compare_files`).
    registration_error : float or "auto"
        M3C2's registration error; ``"auto"``: measured on the stable part of the core points
        (after the alignment with ``align``; :mod:`sdp.distance._level`).
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

    outputs = as_options(Outputs, outputs, "outputs").only("sdp distance", "png", "report", "field_names")
    cylinder = as_options(Cylinder, cylinder, "cylinder")
    execution = as_options(Execution, execution, "execution")
    align = Registration.of(align)
    png, report, memory_limit = outputs.png, outputs.report, execution.memory_limit
    out = Path(output)
    check_outputs([out, png, report], [reference, current, core_points])
    check_format(out, "points")
    check_picture_extras(png=png, report=report)
    V.auto_or_nonnegative("--registration-error", registration_error)
    sensor = V.sensor_origin_option("--sensor-origin", sensor_origin)
    if orientation is not None:
        orientation = V.direction("--orientation", orientation)
    V.check_orientation(orientation, sensor_given=not (isinstance(sensor, str) and sensor in ("auto", "none")),
                        names=("--orientation", "--sensor-origin"))
    tiles = _distances_in_tiles(reference, current, output, format=format, execution=execution,
                                core_points=core_points, align=align, png=png, report=report, sensor=sensor)
    if tiles is not None:
        return _distance_tiled(reference, current, out, format=format, registration_error=registration_error,
                               orientation=orientation, cylinder=cylinder, execution=tiles,
                               field_names=outputs.field_names)
    execution.say_in_memory()
    with all_or_none():
        t0 = time.perf_counter()
        ref, cur = read_points(reference, format=format), read_points(current, format=format)
        core = None if core_points is None else read_points(core_points, format=format)
        t_read = time.perf_counter() - t0
        alignment, moved = None, cur
        if align:
            alignment = align_clouds(ref, cur, (reference, current), align)
            moved = cur.transformed(alignment.matrix)
        reg = V.auto_or_nonnegative("--registration-error", registration_error)
        origin = sensor_origins(sensor, (reference, ref), (current, moved), alignment)
        d = distances(ref, moved, core_points=core, cylinder=cylinder, registration_error=reg,
                      orientation=orientation, sensor_origin=origin, memory_limit=memory_limit)
        like = core if core is not None else ref  # its rows dropped (NaN, an E57's invalid returns) with their fields
        fields = rename_fields(d.fields(), outputs.field_names, path=out)
        write_points(out, d.core_points, fields, like=like, inputs=(reference, current, core_points))
        outputs = [str(out)]
        if png:
            from ..viz._render import render_distances

            render_distances(png, d.core_points, d.distance, d.significant, d.lod,
                             title=f"{Path(reference).name} → {Path(current).name}: signed distance")
            outputs.append(str(png))
        summary = d.summary()
        summary["core_points_dropped"] = int((core if core is not None else ref).n_dropped)  # NaN/Inf rows of the file
        if summary["core_points"] and summary["no_normal"] == summary["core_points"]:
            # no normal anywhere: core points off the clouds, or a normal scale below the points' spacing
            from scipy.spatial import cKDTree

            sample = d.core_points[np.isfinite(d.core_points).all(axis=1)][:: max(1, summary["core_points"] // 200)]
            summary["nearest_reference"] = float(np.median(cKDTree(ref.xyz).query(sample)[0]))
        given = [k for k in (like.fields if like is not None else {}) if k.lower() in _NORMAL_NAMES and k not in fields]
        if given:  # kept as input dimensions, beside the normals measured along: say which is which
            summary["input_normals"] = given
        summary["timings"]["read"] = round(t_read, 4)
        if alignment is not None:
            summary["alignment"] = alignment_summary(alignment, align)
        if report:
            from ..viz._report import distance_report

            outputs.append(str(report))
            summary["outputs"] = outputs
            distance_report(report, d, summary=summary, names=(Path(reference).name, Path(current).name),
                            options=dict(projection_scale=cylinder.projection_scale,
                                         normal_scale=cylinder.normal_scale, max_distance=cylinder.max_distance,
                                         registration_error=registration_error, orientation=orientation,
                                         sensor_origin=sensor_origin), timings=summary["timings"])
    summary["outputs"] = outputs
    return FileDistances(str(reference), str(current), d, summary, alignment, outputs)


def _distances_in_tiles(reference, current, output, *, format, execution: Execution, core_points, align, png,
                        report=None, sensor=None) -> Execution | None:
    """How :func:`distance_files` measures in tiles (``execution``, with why and what the work
    would need in memory when not asked: :attr:`sdp.Execution.switched`), or None: in memory.
    Tiles are taken when asked, or when the in-memory work (the process itself, about 450 bytes
    per reference point and 200 per current point) would exceed the memory limit, which is the
    whole job's as in every command."""
    from .._core._memory import memory_limit as limit
    from ..errors import GridTooLargeError
    from ..io._cloud import input_format
    from ..io._read import header_point_count
    from ..io._source import PointSource
    from ..scale._budget import PROCESS_BYTES

    tiled = execution.tiled
    for f in (reference, current):  # a missing or unknown file says so, not that tiles can't read it
        input_format(Path(f), format)
    cap = limit(execution.memory_limit)
    try:
        n_ref, n_cur = (PointSource.open(f, format=format).n_rows for f in (reference, current))
    except SDPError:
        if tiled:
            raise SDPError("--tiled reads LAS/LAZ, NPY or binary PLY files in slices; "
                           "convert the clouds first") from None
        n_ref, n_cur = (header_point_count(f, format=format) for f in (reference, current))
        need = None if n_ref is None or n_cur is None else PROCESS_BYTES + 450.0 * n_ref + 200.0 * n_cur
        if need is not None and need > cap:  # in memory only, and too large: refused before reading
            raise GridTooLargeError(f"measuring {n_ref:,} against {n_cur:,} points in memory needs about "
                                    f"{format_bytes(need)}, above the memory limit of {format_bytes(cap)}: give "
                                    f"--memory-limit {math.ceil(need / 2**20)}MB or more (LAS/LAZ, NPY or binary "
                                    "PLY files are measured in tiles instead)")
        return None
    need = PROCESS_BYTES + 450.0 * n_ref + 200.0 * n_cur
    if not (tiled or need > cap):
        return None
    given_sensor = not (sensor is None or (isinstance(sensor, str) and sensor in ("auto", "none")))
    for option, given in (("--core-points", core_points), ("--align", align), ("--png", png), ("--report", report),
                          ("--sensor-origin", given_sensor)):  # tiles follow no sensor: its normals would be lost
        if given:
            why = ("with --tiled" if tiled else f"in tiles (the in-memory work would need {format_bytes(need)} with "
                                                f"the process; the memory limit is {format_bytes(cap)})")
            raise SDPError(f"{option} is not available {why}")
    if Path(output).suffix.lower() not in (".las", ".laz"):
        raise SDPError(f"{output}: distances in tiles stream to LAS/LAZ: give -o OUT.laz")
    if tiled:
        return execution
    # said by the tiles once taken; a refusal of theirs names the limit that runs in memory
    return replace(execution, switched=(f"measuring in tiles on Dask: the in-memory work would need "
                                        f"{format_bytes(need)} with the process, above the memory limit of "
                                        f"{format_bytes(cap)}", need))


def _distance_tiled(reference, current, out: Path, *, format, registration_error, orientation, cylinder: Cylinder,
                    execution: Execution, field_names: str = DEFAULTS.field_names) -> FileDistances:
    from ..io._source import PointSource, write_points_streamed
    from ..scale._tiles import distances_tiled

    reg = V.auto_or_nonnegative("--registration-error", registration_error)
    with all_or_none():
        d = distances_tiled(reference, current, cylinder=cylinder, registration_error=reg,
                            orientation=orientation, execution=execution)
        fields = rename_fields(d.fields(), field_names, path=out)
        write_points_streamed(out, PointSource.open(reference, format=format),
                              lambda a, b: {k: v[a:b] for k, v in fields.items()}, inputs=(reference, current))
    summary = d.summary()
    summary["outputs"] = [str(out)]
    return FileDistances(str(reference), str(current), d, summary, None, [str(out)])

