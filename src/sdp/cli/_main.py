"""The ``sdp`` command: a thin layer over the Python API.

Each command is a ``cmd_NAME(a)`` that passes the parsed options ``a`` to one library function
(:mod:`sdp.cli`'s functions: the commands in Python) and prints what it returns (the text of
:mod:`sdp.cli._text`, or JSON), plus its parser in :func:`build_parser`. Options are checked by
:mod:`sdp._core._validate`; :func:`main` turns errors and signals into one line and an exit status, and
:func:`run` is the program (the console script and ``python -m sdp.cli``).
"""

from __future__ import annotations

import argparse
import gc
import os
import signal
import sys
import threading
import warnings

from .. import __version__
from .._core import _progress
from .._core import _validate as V
from .._core._json import dumps
from ..defaults import DEFAULTS
from ..errors import GridTooLargeError, SDPError
from ..io._cloud import ReadNotice
from ..io._output import all_or_none, defer
from ..options import Coverage, Cylinder, Execution, Lattice, NoiseModel, Outputs, Registration
from . import _actions as A
from . import _change as C
from . import _distance as D
from . import _examples as X
from . import _files as F
from . import _series as S
from ._text import action_eval_text, action_splits_text, alignment_text, frame_text, train_text, written_text
from ._warmup import first_run


def _grid_options(p):
    g = p.add_argument_group("grid (default: --voxel-size auto, sigma from the point spacing, which suits real scans)")
    g.add_argument("--voxel-size", default=DEFAULTS.voxel_size, type=V.cli_type(V.auto_or_positive),
                   help="voxel length in world units, or 'auto' (default: from the clouds' point spacing)")
    g.add_argument("--grid-size", type=V.cli_type(V.integer_at_least, 1),
                   help="the paper's level of detail: longest side / GRID_SIZE (paper: 80)")
    g.add_argument("-k", type=V.cli_type(V.finite), default=DEFAULTS.k,
                   help="threshold h = 1 + k·e^-1/2 (default 3, the paper's)")
    g.add_argument("--h", type=V.cli_type(V.positive_finite), help="threshold h given directly")
    g.add_argument("--sigma-voxels", type=V.cli_type(V.auto_or_positive), default=DEFAULTS.sigma_voxels,
                   help="sigma in voxels (default auto: 1.5 on the automatic voxel, the paper's 2 on a given one)")
    g.add_argument("--memory-limit", type=V.cli_type(V.memory_size),
                   help=X.MEMORY_HELP)


def _tile_options(p, title, *, tiled: bool = True):
    t = p.add_argument_group(title)
    if tiled:
        t.add_argument("--tiled", action="store_true", help="work in tiles even if the clouds fit in memory")
    t.add_argument("--tile-size", type=V.cli_type(V.positive_finite),
                   help="tile edge in world units (default: what a worker's share of --memory-limit holds)")
    t.add_argument("--scheduler", help="dask.distributed scheduler address, e.g. tcp://host:8786 "
                   "(default: a local cluster of --workers processes)")
    t.add_argument("--workers", type=V.cli_type(V.integer_at_least, 1),
                   help="worker processes of the local cluster (default: one per core)")
    t.add_argument("--workdir", type=V.cli_type(V.existing_folder),
                   help="folder for the tiles' buckets (shared by all workers on a cluster)")


# The flags → the option objects of sdp.options (validated once, as in Python).

def _lattice(a) -> Lattice:
    return Lattice(voxel_size=a.voxel_size, grid_size=a.grid_size, sigma_voxels=a.sigma_voxels, k=a.k, h=a.h)


def _execution(a, notify=None) -> Execution:
    return Execution(memory_limit=a.memory_limit, tiled=getattr(a, "tiled", False), tile_size=a.tile_size,
                     scheduler=a.scheduler, workers=a.workers, workdir=a.workdir, notify=notify)


def _coverage(a) -> Coverage:
    return Coverage(sensor_origin=V.sensor_origin_option("--sensor-origin", a.sensor_origin), range_noise=a.range_noise)


def _noise(a) -> NoiseModel:
    return NoiseModel(registration_error=a.registration_error, range_exponent=a.range_exponent,
                      correlation_length=a.correlation_length)


def _noise_options(p) -> None:
    """The combined decision's noise model (:class:`sdp.NoiseModel`)."""
    p.add_argument("--registration-error", metavar="E|auto", default=DEFAULTS.registration_error,
                   type=V.cli_type(V.auto_or_nonnegative),
                   help="with --decision combined: the level's systematic part as M3C2's reg (default auto: "
                        "measured on the points the density left unchanged)")
    p.add_argument("--range-exponent", metavar="P|auto", default=DEFAULTS.range_exponent,
                   type=V.cli_type(V.auto_or_exponent),
                   help="with --decision combined: the systematic part grows as range^P along the sensor's ray, "
                        "P in [0, 2] (2: a structured-light camera, 0: a laser scanner; default auto: fitted)")
    p.add_argument("--correlation-length", metavar="L", type=V.cli_type(V.positive_finite),
                   default=DEFAULTS.correlation_length,
                   help="with --decision combined: errors correlated over L (world units): a cylinder counts at "
                        "most (d/2L)^2 independent points, d = 4 sigma its diameter (default: independent)")


def _registration(a) -> Registration | None:
    V.check_alignment_options(a.align, fix_horizontal=a.fix_horizontal, align_class=a.align_class)
    return None if a.align is None else Registration(method=a.align, fix_horizontal=a.fix_horizontal,
                                                     align_class=a.align_class)


#: ``--quiet``: print nothing but errors and the JSON that was asked for (set by :func:`main`).
_quiet = False


def _say(message: str) -> None:
    """A notice on stderr (the switch to tiles), unless ``--quiet``."""
    if not _quiet:
        print(f"sdp: {message}", file=sys.stderr)


def _notices(show):
    """``warnings.showwarning`` that prints a reader's :class:`~sdp.io._cloud.ReadNotice` as one
    ``sdp:`` line, as :func:`_say` does (Python's form takes two lines and names sdp's source),
    and hands other warnings to ``show``."""
    def shown(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, ReadNotice):
            _say(str(message))
        else:
            show(message, category, filename, lineno, file, line)
    return shown


def _print(text: str) -> None:
    """``text`` on stdout, flushed: before the outputs are committed, so a full stdout fails the
    command (nothing written); a reader that has gone (``| head``) is not a failure, and the
    rest is dropped."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # the interpreter's last flush too
    except OSError as exc:
        # a series archive or field store is committed before its summary (sdp.io._output.commit_point): say so
        raise SDPError(f"standard output: {exc.strerror or exc}" + (
            "; the archive or field store was written before it (see `sdp info`), the other outputs were not"
            if _finished
            else "")) from None


def _line(text: str) -> None:
    """A line of a command's text on stdout (flushed: commands that stream print as they go), unless ``--quiet``."""
    if not _quiet:
        _print(text)


def _show(text: str, summary=None, as_json: bool = False) -> int:
    """Print ``text`` (not with ``--quiet``), or ``summary`` as JSON (``--json``, and ``sdp info``,
    whose answer is JSON: also with ``--quiet``); exit status 0."""
    if as_json:
        _print(dumps(summary))
    elif text:
        _line(text)
    return 0


# Each command: the parsed options → one call of sdp.cli's functions → print (its text, or JSON).

def cmd_change(a):
    r = C.compare_files(a.reference, a.current, output=a.output, format=a.format,
                        outputs=Outputs(both=a.both, png=a.png, html=a.html, report=a.report, aligned=a.aligned_output),
                        lattice=_lattice(a), coverage=_coverage(a),
                        align=_registration(a), execution=_execution(a, None if a.json else _say),
                        decision=a.decision, min_region_points=a.min_region_points, topic=a.topic, noise=_noise(a))
    how = set((r.summary.get("coverage") or {}).values())
    if a.range_noise != DEFAULTS.range_noise and how == {"footprint"}:  # known only once the files are read
        _say(f"--range-noise {a.range_noise} was not used: neither file records where its sensor stood (coverage "
             "by footprint); give --sensor-origin")
    return _show(r.summary_text(), r.summary, a.json)


def cmd_distance(a):
    r = D.distance_files(a.reference, a.current, output=a.output, core_points=a.core_points,
                         outputs=Outputs(png=a.png, report=a.report, field_names=a.field_names), format=a.format,
                         cylinder=Cylinder(projection_scale=a.projection_scale, normal_scale=a.normal_scale,
                                           max_distance=a.max_distance),
                         registration_error=a.registration_error, orientation=a.orientation,
                         sensor_origin=a.sensor_origin, align=_registration(a),
                         execution=_execution(a, None if a.json else _say))
    s = r.summary
    if a.max_distance not in (None, "auto") and float(a.max_distance) < s["max_distance"]:
        _say(f"--max-distance {a.max_distance} is shorter than the cylinder itself (0.75 d, the kernel's cut): "
             f"searched ±{s['max_distance']:.4g} along the normal")
    if s.get("nearest_reference", float("inf")) < s["normal_scale"] / 2:  # near the points, yet no normal: too small
        _say(f"no core point has a normal: fewer than three reference points lie within D/2 = "
             f"{s['normal_scale'] / 2:.4g} of each; give a --normal-scale (and --projection-scale) above the "
             f"points' spacing")
    elif s["core_points"] and not s["comparable"]:  # every row NaN: most likely core points off the clouds
        _say(f"no core point has a distance: no epoch's points lie within the cylinders (d = "
             f"{s['projection_scale']:.4g}, ±{s['max_distance']:.4g} along the normal) of any of them; are the "
             f"core points on the clouds, in the same frame?")
    return _show(r.summary_text(), s, a.json)


def cmd_build(a):
    built = F.build_field_file(a.cloud, output=a.output, format=a.format, lattice=_lattice(a),
                               execution=_execution(a, _say))
    return _show(written_text(built, a.output))


def cmd_info(a):
    from ..timeseries._archive import is_series

    if is_series(a.file):  # a series archive: its summary (sdp.cli._series.describe_series)
        return _show("", S.describe_series(a.file), as_json=True)
    return _show("", F.describe_file(a.file, format=a.format), as_json=True)


def _epoch_output(text: str) -> tuple[str, str]:
    k, sep, path = text.partition(":")
    if not sep or not path:
        raise SDPError(f"--epoch-output wants K:FILE (an epoch index and a file), got {text!r}")
    return k, path


def cmd_series(a):
    options = dict(core_points=a.core_points, reference=a.reference, registration_error=a.registration_error,
                   align=_registration(a), format=a.format, topic=a.topic,
                   orientation=None if a.orientation is None else V.sensor_origin_option("--orientation", a.orientation))
    given = (a.projection_scale, a.normal_scale, a.max_distance)
    if not a.append or given != (DEFAULTS.projection_scale, DEFAULTS.normal_scale, DEFAULTS.max_distance):
        options["cylinder"] = Cylinder(projection_scale=a.projection_scale, normal_scale=a.normal_scale,
                                       max_distance=a.max_distance)
    if isinstance(options["orientation"], str):
        raise SDPError(f"--orientation must be X,Y,Z, got {a.orientation!r}")
    if a.points is not None and a.points_output is None:  # options that would be ignored
        raise SDPError("--points chooses the core points of --points-output: give --points-output FILE.csv too")
    if a.field_names != DEFAULTS.field_names and not (a.epoch_output or a.points_output):
        raise SDPError("--field-names names the exports' fields: give --epoch-output or --points-output too")
    r = S.series_files(a.epochs, output=a.output, append=a.append, times=a.times, options=options,
                       execution=_execution(a, None if a.json else _say),
                       outputs=Outputs(report=a.report, field_names=a.field_names),
                       exports={"epochs": [_epoch_output(e) for e in a.epoch_output or []],
                                "points": None if a.points_output is None else (a.points_output, a.points)})
    return _show(r.summary_text(), r.summary, a.json)


def cmd_mesh(a):
    mesh = F.mesh_file(a.input, output=a.output, level=a.level, format=a.format, lattice=_lattice(a),
                       memory_limit=a.memory_limit)
    return _show(written_text(mesh, a.output))


def cmd_bool(a):
    result = F.combine_files(a.operation, a.a, a.b, output=a.output, format=a.format, lattice=_lattice(a),
                             memory_limit=a.memory_limit)
    return _show(written_text(result, a.output))


def cmd_align(a):
    al = F.align_files(a.reference, a.current, output=a.output, method=a.method, fix_horizontal=a.fix_horizontal,
                       align_class=a.align_class, format=a.format)
    return _show(f"{alignment_text(al.summary())}\nwrote {a.output}", al.summary(), a.json)


def cmd_watch(a):
    from ..io._bag import is_bag

    if os.path.isdir(a.frames) and not is_bag(a.frames):  # frames of one format: say what is left out
        skipped = F.frame_files(a.frames)[1]
        if skipped:
            _say(f"{a.frames}: {len(skipped)} file(s) of other formats left out, not frames: "
                 f"{', '.join(p.name for p in skipped[:5])}{' …' if len(skipped) > 5 else ''}")
    try:
        frames = F.watch_folder(a.reference, a.frames, format=a.format, lattice=Lattice(voxel_size=a.voxel_size),
                                update=a.update, window=a.window, decay=a.decay,
                                min_region_points=a.min_region_points, align=a.align, coverage=_coverage(a),
                                topic=a.topic, decision=a.decision, noise=_noise(a))
        for r in frames:  # a line per frame, as it comes (the frames are compared as they are iterated)
            if a.json:  # JSON Lines: a reader takes each frame as it comes
                _print(dumps(r.summary(), indent=None))
            else:
                _line(frame_text(r))
    except GridTooLargeError as exc:  # its advice named options sdp watch has not
        raise GridTooLargeError(str(exc).replace("(--memory-limit, $SDP_MEMORY_LIMIT)", "($SDP_MEMORY_LIMIT)")
                                .replace("a larger voxel size (or a smaller grid size)", "a larger --voxel-size")) \
            from None
    return 0


def cmd_action(a):
    if a.action_command == "train":
        model, cv, n = A.train_actions(a.data_dir, output=a.output, subjects=a.subjects, workers=a.workers)
        return _show(train_text(model, cv, n, a.output))
    if a.action_command == "predict" and a.stream is not None:
        for frame, label in A.stream_actions(a.model, a.stream, window=a.window, every=a.every):
            _line(f"frame {frame}: a{label:02d}")  # as it comes
        return 0
    if a.action_command == "predict":
        return _show("\n".join(f"{path}: a{label:02d}" for path, label in A.predict_actions(a.model, a.sequences)))
    s = A.evaluate_actions(a.data_dir, splits=a.splits, workers=a.workers)
    return _show((action_splits_text if a.splits == "all" else action_eval_text)(s), s, a.json)


def cmd_eval(a):
    e = F.evaluate_files(a.predicted, a.truth, predicted_field=a.predicted_field, truth_field=a.truth_field,
                         format=a.format)
    return _show(e.summary_text(), e.scores, a.json)


def cmd_render(a):
    written = F.render_file(a.file, png=a.png, html=a.html, field=a.field, format=a.format)
    return _show("\n".join(f"wrote {w}" for w in written))


def cmd_demo(a):
    from ..data._demo import run_demo

    run_demo(a.output, seed=a.seed, echo=_line)
    return 0


def cmd_warmup(a):
    from ._warmup import warmup

    return _show(f"kernels compiled and cached ({sum(warmup(echo=None if a.quiet else _line).values()):.0f} s)")


def _align_options(p):
    p.add_argument("--fix-horizontal", action="store_true",
                   help="density alignment: estimate only the vertical shift and the tilts (z up); for epochs of "
                        "nearly flat terrain")
    p.add_argument("--align-class", metavar="C[,C...]",
                   help="estimate the transform on the points of these LAS classes of both scans (e.g. 2: ground), "
                        "then move the whole current scan")


def _command(sub, name, func, help, examples):
    """A subcommand whose help ends with its examples, kept as written."""
    p = sub.add_parser(name, help=help, epilog="examples:\n" + examples,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.set_defaults(func=func)
    return p


class _Parser(argparse.ArgumentParser):
    """argparse with its errors on one line (``sdp: error: ...``, status 2), pointing at ``--help``."""

    def error(self, message: str):
        self.exit(2, f"sdp: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="sdp", description="Compare point clouds through spatial density patterns.")
    p.add_argument("--version", action="version", version=f"sdp {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    c = _command(sub, "change", cmd_change, "appeared (and disappeared) points between two clouds", X.CHANGE)
    c.add_argument("reference")
    c.add_argument("current")
    c.add_argument("-o", "--output", required=True, help="labelled current cloud (.ply, .las, .laz, .npz)")
    c.add_argument("--both", action="store_true",
                   help="also write the disappeared reference points (OUTPUT_disappeared)")
    c.add_argument("--decision", choices=("point", "density", "cluster", "combined"), default=DEFAULTS.decision,
                   help="point or density (the same: Algorithm 1 per point, by density), cluster (the paper's "
                        "clustering) or combined (density or the distance beyond its level of detection; "
                        "writes the distance and lod fields)")
    c.add_argument("--min-region-points", type=V.cli_type(V.integer_at_least, 0), default=DEFAULTS.min_region_points,
                   help="drop change regions with fewer points (default 50: smaller ones are noise and depth edges)")
    _noise_options(c)
    c.add_argument("--png", help="write a picture of the appeared points")
    c.add_argument("--html", help="write an interactive 3D view (needs the html extra: plotly)")
    c.add_argument("--report", help=X.REPORT_HELP)
    c.add_argument("--json", action="store_true", help="print the summary as JSON")
    c.add_argument("--topic", metavar="TOPIC[:N]", help="a ROS bag input: the PointCloud2 message of TOPIC to compare "
                   "(its first, or its N-th from 0; -1 the last)")
    c.add_argument("--align", choices=("density", "gicp"), help="register CURRENT onto REFERENCE first")
    c.add_argument("--aligned-output", action="store_true", help="write CURRENT's aligned coordinates (with --align)")
    _align_options(c)
    c.add_argument("--sensor-origin", metavar="auto|none|viewpoint|X,Y,Z", default=DEFAULTS.sensor_origin,
                   help="test changes along the sensor's rays (sdp.change._visibility). auto (default): where a file "
                        "records it (organized PCD: VIEWPOINT), as it lifts kappa on Kinect pairs from 0.67 to 0.85; "
                        "viewpoint: the same, required; none: density and footprint only; X,Y,Z: one position")
    c.add_argument("--range-noise", type=V.cli_type(V.nonnegative_finite), default=DEFAULTS.range_noise,
                   help="with a sensor: same range within RANGE_NOISE·r² (default 0.015, a Kinect's depth noise; "
                        "E57 and LAS/LAZ files: a laser's, the kernel's σ at any range)")
    _tile_options(c, "large clouds: tiles on Dask (taken by itself when the grids or points exceed --memory-limit, "
                     "or when REFERENCE is a .zarr field store; outputs LAS/LAZ with 'change' and 'region')")

    ds = _command(sub, "distance", cmd_distance, "signed distance along the normal, its level of detection and "
                  "significance (M3C2's answer)", X.DISTANCE)
    for name in ("reference", "current"):
        ds.add_argument(name)
    ds.add_argument("-o", "--output", required=True, help="core points with distance, lod, significant, n1, n2, "
                    "spread1, spread2, normal_x/y/z (.ply, .las, .laz, .npz)")
    ds.add_argument("--core-points", help="where to measure (a cloud file; default: every reference point)")
    for flag, default, what in (
            ("--projection-scale", DEFAULTS.projection_scale, "M3C2's d, the cylinder's diameter (4 sigma)"),
            ("--normal-scale", DEFAULTS.normal_scale, "M3C2's D, the normal's diameter (2d, up to 4d when rough)"),
            ("--max-distance", DEFAULTS.max_distance, "how far along the normal an epoch is looked for (12d)")):
        ds.add_argument(flag, type=V.cli_type(V.auto_or_positive), default=default, help=f"{what}; default auto")
    ds.add_argument("--registration-error", default="auto", type=V.cli_type(V.auto_or_nonnegative),
                    help="added to the level of detection (default auto: measured on the stable part, after "
                         "--align if given; 0 below 100 stable places)")
    ds.add_argument("--orientation", metavar="X,Y,Z", help="normals point this way without a sensor (default 0,0,1)")
    ds.add_argument("--sensor-origin", metavar="auto|none|viewpoint|X,Y,Z", default=DEFAULTS.sensor_origin,
                    help="normals point towards the sensor (auto: where a file records it)")
    ds.add_argument("--field-names", choices=("sdp", "cloudcompare", "pdal"), default=DEFAULTS.field_names,
                    help="name the output's fields as sdp (default), CloudCompare's M3C2 or PDAL's filters.m3c2 do")
    ds.add_argument("--png", help="map of the significant distances and their histogram")
    ds.add_argument("--report", help=X.REPORT_HELP)
    ds.add_argument("--json", action="store_true", help="print the summary as JSON")
    ds.add_argument("--align", choices=("density", "gicp"), help="register CURRENT onto REFERENCE first")
    _align_options(ds)
    ds.add_argument("--memory-limit", type=V.cli_type(V.memory_size),
                    help=X.MEMORY_HELP)
    _tile_options(ds, "large clouds: tiles on Dask (taken by itself beyond --memory-limit; output LAS/LAZ)")

    se = _command(sub, "series", cmd_series, "many epochs against one reference: distances, smoothed change, "
                  "velocity and 4D objects of change in one archive, appended epoch by epoch", X.SERIES)
    se.add_argument("epochs", nargs="+", help="the epochs' files (or ROS bags, with --topic), in time order")
    se.add_argument("-o", "--output", required=True, help="the archive (.zarr folder)")
    se.add_argument("--append", action="store_true", help="add EPOCHS to the archive: only they are measured, "
                    "with its reference, core points and options")
    se.add_argument("--times", help="T1,T2,...: numbers or ISO dates (default: the files' own: LAS GPS time or "
                    "creation date, E57 acquisition start, a bag's first header.stamp; else the index)")
    se.add_argument("--topic", help="epochs that are ROS bags: the sensor_msgs/PointCloud2 topic whose messages, moved "
                    "into map or odom with /tf, make the epoch, each one a scan position (the scans extra)")
    se.add_argument("--core-points", help="where to measure (a cloud file; default: the reference subsampled at the "
                    "projection scale)")
    se.add_argument("--reference", type=V.cli_type(V.integer_at_least, 0), help="index of the reference epoch "
                    "(default 0)")
    for flag, default, what in (
            ("--projection-scale", DEFAULTS.projection_scale, "M3C2's d, the cylinder's diameter (from the reference)"),
            ("--normal-scale", DEFAULTS.normal_scale, "M3C2's D, the normal's diameter (2d, up to 4d when rough)"),
            ("--max-distance", DEFAULTS.max_distance, "how far along the normal an epoch is looked for (12d)")):
        se.add_argument(flag, type=V.cli_type(V.auto_or_positive), default=default, help=f"{what}; default auto")
    se.add_argument("--registration-error", type=V.cli_type(V.auto_or_nonnegative),
                    help="added to each epoch's level of detection (default auto: measured on each epoch's "
                         "stable part, after --align if given; an append keeps the archive's)")
    se.add_argument("--orientation", metavar="X,Y,Z", help="normals point this way (default 0,0,1)")
    se.add_argument("--align", choices=("density", "gicp"), help="register each epoch onto the reference first")
    _align_options(se)
    se.add_argument("--memory-limit", type=V.cli_type(V.memory_size),
                    help=X.MEMORY_HELP + "; epochs are read one at a time")
    _tile_options(se, "epochs beyond memory: tiles on Dask (taken by themselves beyond --memory-limit)")
    se.add_argument("--report", help="one HTML page: maps of change and velocity, the largest objects' series, "
                    "the object table, the parameters (needs the plots extra)")
    se.add_argument("--epoch-output", action="append", metavar="K:FILE",
                    help="epoch K's distances, smoothed change, velocity and object per core point (.las, .laz, "
                         ".ply, .npz); repeatable")
    se.add_argument("--points-output", metavar="FILE", help="per-point series (.csv or .parquet)")
    se.add_argument("--field-names", choices=("sdp", "cloudcompare", "pdal"), default=DEFAULTS.field_names,
                    help="name the exports' distance, uncertainty, significance and normal as sdp (default), "
                         "CloudCompare's M3C2 or PDAL's filters.m3c2 do")
    se.add_argument("--points", metavar="I,J,...", help="core points of --points-output (default: the peak of "
                    "each of the five largest objects)")
    se.add_argument("--json", action="store_true", help="print the summary as JSON")

    b = _command(sub, "build", cmd_build, "density field of a cloud, saved (.sdpf; a .zarr store in tiles)", X.BUILD)
    b.add_argument("cloud")
    b.add_argument("-o", "--output", required=True, help=".sdpf (in memory) or .zarr (a field store, built in tiles)")
    _tile_options(b, "field stores (.zarr output)", tiled=False)

    i = _command(sub, "info", cmd_info, "describe a cloud or a field file", "  sdp info scan.laz\n  sdp info scan.sdpf")
    i.add_argument("file", help="a cloud, a field (.sdpf), a field store or a series archive (.zarr)")

    m = _command(sub, "mesh", cmd_mesh, "iso-surface of a field or cloud (Lewiner marching cubes)", X.MESH)
    m.add_argument("input", help="a field (.sdpf), a field store (.zarr: tile by tile) or a cloud")
    m.add_argument("-o", "--output", required=True, help=".ply, .obj or .stl")
    m.add_argument("--level", type=V.cli_type(V.finite), default=0.0, help="level of F = h - G (0: the boundary)")

    o = _command(sub, "bool", cmd_bool, "union, intersection or difference of two fields or clouds", X.BOOL)
    o.add_argument("operation", choices=("union", "intersection", "difference"))
    o.add_argument("a", help="field (.sdpf), field store (.zarr) or cloud")
    o.add_argument("b", help="field (.sdpf), field store (.zarr) or cloud")
    o.add_argument("-o", "--output", required=True,
                   help=".sdpf (the field), .zarr (of two field stores, tile by tile) or .ply/.obj/.stl (its surface)")

    al = _command(sub, "align", cmd_align, "rigid transform mapping CURRENT onto REFERENCE (4x4 text)", X.ALIGN)
    al.add_argument("reference", help="cloud, or field (.sdpf) for --method density")
    al.add_argument("current", help="the cloud to move onto REFERENCE")
    al.add_argument("-o", "--output", required=True, help="text file with the 4x4 matrix")
    al.add_argument("--method", choices=("density", "gicp"), default=DEFAULTS.align_method,
                    help="density: maximise the reference's density, coarse to fine; gicp: small_gicp")
    _align_options(al)
    al.add_argument("--json", action="store_true", help="print the result as JSON")

    w = _command(sub, "watch", cmd_watch, "compare each frame of a folder, in order, with a model that learns", X.WATCH)
    w.add_argument("reference", help="cloud or field (.sdpf) of the scene before the frames")
    w.add_argument("frames", help="folder of frames, processed in natural name order, or a ROS bag (with --topic)")
    w.add_argument("--topic", help="the sensor_msgs/PointCloud2 topic of a ROS 1 or ROS 2 bag (the scans extra)")
    w.add_argument("--update", choices=("none", "window", "decay"), default=DEFAULTS.update,
                   help="how the model learns the frames (default window: learns the last frames, forgets the rest)")
    w.add_argument("--window", type=V.cli_type(V.integer_at_least, 1),
                   help=f"frames in the model for --update window, reference included (default {DEFAULTS.window})")
    w.add_argument("--decay", type=V.cli_type(V.finite),
                   help=f"per-frame forgetting factor for --update decay (default {DEFAULTS.decay})")
    w.add_argument("--min-region-points", type=V.cli_type(V.integer_at_least, 0), default=DEFAULTS.min_region_points,
                   help="drop appeared regions with fewer points (default 50)")
    w.add_argument("--voxel-size", default=DEFAULTS.voxel_size, type=V.cli_type(V.auto_or_positive),
                   help="voxel of a reference cloud, or 'auto' (default)")
    w.add_argument("--align", choices=("gicp", "density"),
                   help="register each frame onto the reference first (a moving camera): gicp (small_gicp, "
                        "needs a reference cloud) or density")
    w.add_argument("--sensor-origin", metavar="auto|none|viewpoint|X,Y,Z", default=DEFAULTS.sensor_origin,
                   help="test changes along the reference's rays (sdp.change._visibility): auto (default) where its "
                        "file "
                        "records the sensor (organized PCD), viewpoint the same but required, none, or X,Y,Z")
    w.add_argument("--range-noise", type=V.cli_type(V.nonnegative_finite), default=DEFAULTS.range_noise,
                   help="with a sensor: same range within RANGE_NOISE·r² (default 0.015, a Kinect; "
                        "E57 and LAS/LAZ: a laser's)")
    w.add_argument("--decision", choices=("point", "density", "combined"), default=DEFAULTS.decision,
                   help="point / density (the density alone, default) or combined (also the distance to the "
                        "reference's surface beyond its level of detection, completing what the density found)")
    _noise_options(w)
    w.add_argument("--json", action="store_true",
                   help="print each frame's summary as it comes, one JSON object a line (JSON Lines)")

    act = _command(sub, "action", cmd_action, "recognise human actions in depth sequences (MSR Action3D)", X.ACTION)
    asub = act.add_subparsers(dest="action_command", required=True)
    t = asub.add_parser("train", help="fit a classifier on a folder of aXX_sYY_eZZ sequences")
    t.add_argument("data_dir")
    t.add_argument("-o", "--output", required=True, help="model file (.npz)")
    t.add_argument("--subjects", help="comma-separated subjects to train on (default: all)")
    pr = asub.add_parser("predict", help="action label of each sequence")
    pr.add_argument("model")
    pr.add_argument("sequences", nargs="*", help=".mat or .bin depth sequences")
    pr.add_argument("--stream", metavar="FRAMES",
                    help="a folder of .npy depth frames, in natural name order (or a sequence file, replayed)")
    pr.add_argument("--window", type=V.cli_type(V.integer_at_least, 2), default=DEFAULTS.action_window,
                    help=f"frames used (default {DEFAULTS.action_window})")
    pr.add_argument("--every", type=V.cli_type(V.integer_at_least, 1), default=DEFAULTS.action_every,
                    help=f"say it each N frames ({DEFAULTS.action_every})")
    ev = asub.add_parser("eval", help="the cross-subject protocol: accuracy on AS1, AS2, AS3 and all")
    ev.add_argument("data_dir")
    ev.add_argument("--json", action="store_true", help="print the accuracies (fractions) and timings as JSON")
    ev.add_argument("--splits", choices=("standard", "all"), default="standard",
                    help="standard: train on subjects 1,3,5,7,9 (default); all: every five-subject training set "
                         "(252), the mean, spread and the standard split's place")
    for q, more in ((t, ""), (ev, " (and, with --splits all, sharing the splits)")):
        q.add_argument("--workers", type=V.cli_type(V.integer_at_least, 1), default=os.cpu_count() or 1,
                       help=f"processes reading sequences{more}")

    e = _command(sub, "eval", cmd_eval, "kappa, precision, recall, … of predicted change labels against truth", X.EVAL)
    e.add_argument("predicted", help="cloud with the predicted labels (e.g. the output of sdp change)")
    e.add_argument("truth", help="cloud with the true labels, same points in the same order")
    e.add_argument("--predicted-field", default="change",
                   help="field of PREDICTED (default change: 1 changed, 2 not comparable, left out; region: an id "
                        "from 0 is changed, -1 not; other fields: nonzero is changed)")
    e.add_argument("--truth-field", default="change", help="field of TRUTH (nonzero: changed; default change)")
    e.add_argument("--json", action="store_true", help="print the scores as JSON")

    r = _command(sub, "render", cmd_render, "picture of a labelled cloud (vermillion: changed) or slices of a field",
                 X.RENDER)
    r.add_argument("file", help="cloud with a label field, or a field (.sdpf)")
    r.add_argument("--png", help="picture (three views of a cloud; three slices of a field)")
    r.add_argument("--html", help="interactive 3D view of a cloud (needs the html extra: plotly)")
    r.add_argument("--field",
                   help="per-point field of a cloud to colour by (default change: 1 changed, 2 not comparable, "
                        "grey); another field: nonzero drawn as changed, NaN grey")

    for q in (c, ds, se, b, i, m, o, al, w, e, r):
        q.add_argument("--format", help="input format, overriding the extension (pcd, ply, las, text, npy, npz, e57)")
    for q in (c, b, m, o):
        _grid_options(q)

    d = _command(sub, "demo", cmd_demo, "change detection on a simulated office scan; write results", X.DEMO)
    d.add_argument("-o", "--output", default="demo-output", help="folder for the outputs (default demo-output)")
    d.add_argument("--seed", type=int, default=0, help="the simulation's random seed (default 0)")
    wu = _command(sub, "warmup", cmd_warmup, "compile every kernel now (make install does)", "  sdp warmup")
    with_json = (c, ds, se, al, w, ev, e)
    for q in (c, ds, se, b, i, m, o, al, w, t, pr, ev, e, r, d, wu):
        q.add_argument("-q", "--quiet", action="store_true",
                       help="print nothing but errors"
                            + (" (and the JSON that --json asks for)" if q in with_json else "")
                            + ": no summary, progress bar or notice")
    return p


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread so that ``finally`` blocks and context managers clean up
    (temporary outputs, the tiles' work folder, the Dask cluster) before the process ends."""


#: The signal that ended the command (SIGINT or SIGTERM), if one did. A library calling back into
#: Python (lazrs writing LAZ) turns the exception a handler raises into its own error: the
#: signal, not the exception, says the command was interrupted.
_signalled: int | None = None
#: The command has committed its outputs or ended: a signal now comes too late to stop anything.
_finished = False


def _finish() -> None:
    global _finished
    _finished = True


def _on_signal(signum, frame):
    global _signalled
    if _finished:
        return
    _signalled = signum
    signal.signal(signum, signal.SIG_IGN)  # a second one must not cut the clean-up short
    if defer(_stop):  # taken by another thread during a commit: it completes first (then the signal comes too late)
        return
    _stop()


def _stop() -> None:
    """Raise the exception of the signal that came, unless the command has committed its outputs:
    before the commit, as a library may have swallowed the one the handler raised (a destructor's,
    reported as "Exception ignored in …") and the command gone on."""
    if _signalled is not None and not _finished:
        raise KeyboardInterrupt() if _signalled == signal.SIGINT else _Terminated()


def _unraisable(previous):
    """``sys.unraisablehook`` without the report of the signal's exception swallowed by a destructor
    (:func:`_stop` acts on the signal)."""
    def hook(unraisable):
        if _signalled is None or not isinstance(unraisable.exc_value, (KeyboardInterrupt, _Terminated)):
            previous(unraisable)

    return hook


def _one_line(exc: BaseException) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return lines[0] if lines else type(exc).__name__


def _error(exc: BaseException) -> int | None:
    """The one line on stderr and the exit status of a command that raised ``exc`` (None: a bug,
    whose traceback is shown)."""
    if _signalled is not None or isinstance(exc, (KeyboardInterrupt, _Terminated)):
        term = _signalled == signal.SIGTERM or isinstance(exc, _Terminated)
        print(f"sdp: {'terminated' if term else 'interrupted'}", file=sys.stderr)
        return 128 + (signal.SIGTERM if term else signal.SIGINT)
    if isinstance(exc, BrokenPipeError):  # output piped into head & co.
        sys.stderr.close()
        return 0
    if isinstance(exc, (SDPError, ValueError)):
        message = _one_line(exc)
    elif isinstance(exc, MemoryError):
        message = ("out of memory: use a larger --voxel-size, or a --memory-limit the machine has free (sdp then "
                   "refuses, or compares in tiles, before allocating)")
    elif isinstance(exc, OSError):  # a disk full, a file vanishing: said in one line
        message = f"{exc.filename + ': ' if exc.filename else ''}{exc.strerror or _one_line(exc)}"
    else:
        return None
    print(f"sdp: error: {message}", file=sys.stderr)
    return 2


def _dash_values(parser: argparse.ArgumentParser, argv: list[str]) -> list[str]:
    """``argv`` with an option's value that starts with a dash attached to it (``--memory-limit
    -5GB`` → ``--memory-limit=-5GB``, ``--orientation -1,0,0``): argparse takes such a value for
    another option and says the option "expected one argument"; attached, the value is checked
    and refused or used as any other."""
    takes_value, options = set(), set()
    stack = [parser]
    while stack:
        p = stack.pop()
        for action in p._actions:
            options.update(action.option_strings)
            if action.option_strings and action.nargs not in (0, "?", "*"):
                takes_value.update(action.option_strings)
            if isinstance(action, argparse._SubParsersAction):
                stack.extend(action.choices.values())
    out = []
    for token in argv:
        if out and out[-1] in takes_value and token.startswith("-") and token not in options and token != "--":
            out[-1] = f"{out[-1]}={token}"
        else:
            out.append(token)
    return out


def _once(parser: argparse.ArgumentParser, argv: list[str]) -> None:
    """Refuse an option given twice (``-o a.ply -o b.ply``): argparse keeps the last silently.
    Options that collect (``--epoch-output``) may repeat."""
    sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
    command = next((t for t in argv if not t.startswith("-")), None)
    if sub is None or command not in sub.choices:
        return
    cmd = sub.choices[command]
    strings = cmd._option_string_actions
    seen: dict[str, str] = {}
    for i, token in enumerate(argv):
        if token == "--":
            break
        name = token.split("=", 1)[0]
        if not name.startswith("-") or name in ("-", "--"):
            continue
        found = [o for o in strings if o == name] or [o for o in strings if o.startswith("--") and o.startswith(name)]
        if len(found) != 1:
            continue  # not an option, or an ambiguous prefix: argparse says so
        action = strings[found[0]]
        if isinstance(action, (argparse._AppendAction, argparse._CountAction, argparse._HelpAction)):
            continue
        shown = token if "=" in token or action.nargs == 0 or i + 1 == len(argv) else f"{token} {argv[i + 1]}"
        if action.dest in seen:
            cmd.error(f"{found[0]} given twice ({seen[action.dest]}, {shown}): give it once")
        seen[action.dest] = shown


def main(argv=None, *, restore_signals: bool = True) -> int:
    """Run the ``sdp`` command line ``argv`` (default ``sys.argv[1:]``); returns the exit status.

    Ctrl-C and SIGTERM end a command with 130 or 143 and nothing written; once its outputs are
    committed, they are ignored (with ``restore_signals=False``, as :func:`run` calls it, until
    the process ends; else the previous handlers are put back)."""
    global _quiet, _signalled, _finished
    parser = build_parser()
    argv = _dash_values(parser, list(sys.argv[1:] if argv is None else argv))
    _once(parser, argv)
    args = parser.parse_args(argv)
    quiet = getattr(args, "quiet", False)
    _progress.enable(not (quiet or getattr(args, "json", False)))
    in_main = threading.current_thread() is threading.main_thread()
    _quiet, _signalled, _finished = quiet, None, False
    previous = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)} if in_main else {}
    unraisable, sys.unraisablehook = sys.unraisablehook, _unraisable(sys.unraisablehook)
    try:
        # a command writes all its outputs or none; with --quiet, warnings (not errors) are not shown
        with all_or_none(on_commit=_finish, stop=_stop), warnings.catch_warnings():
            if quiet:
                warnings.simplefilter("ignore")
            warnings.showwarning = _notices(warnings.showwarning)  # put back as it was when the block ends
            with first_run(args.command, quiet=quiet):
                return args.func(args)
    except BaseException as exc:
        status = _error(exc)
        if status is None:
            raise
        return status
    finally:
        _quiet, _finished = False, True
        sys.unraisablehook = unraisable
        for s, handler in previous.items() if restore_signals else ():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)


def run() -> None:
    """The ``sdp`` program: :func:`main` on ``sys.argv``, then exit with its status.

    The garbage collector is tuned for a program that loads Numba, whose type registries (some
    125,000 objects, alive until the end) dominate the heap: full collections run a tenth as often
    (every 100 collections of the middle generation instead of 10), and before the interpreter
    shuts down the objects still alive are put out of the collector's reach (:func:`gc.freeze`),
    so the collections of the shutdown do not traverse them again and again. Together 0.25–0.3 s
    of every command that runs a kernel (measured on ``sdp change`` with a Kinect pair: full
    collections 0.06–0.07 s, shutdown 0.2 s, a quarter of the command). Cyclic garbage is still
    collected while the command runs. Nothing is lost at exit: every output is written and closed
    by then, the streams are flushed and ``atexit`` handlers run as before, and the memory goes
    back to the system with the process (Python never promised to finalize objects still alive
    at exit).
    """
    young, middle, _ = gc.get_threshold()
    gc.set_threshold(young, middle, 100)
    try:
        status = main(restore_signals=False)
    finally:
        gc.freeze()
    if status == 0:  # everything written: a Ctrl-C from now on changes nothing. Ignored, not handled, as the
        # interpreter's shutdown puts the default action back for signals a Python function handles
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, signal.SIG_IGN)
    sys.exit(status)

