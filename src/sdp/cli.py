"""The ``sdp`` command: a thin layer over the Python API (one library call per command)."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np

from . import __version__, _progress
from . import validate as V
from .defaults import DEFAULTS
from .errors import SDPError
from .io import all_or_none, check_outputs, read_points

EXAMPLES_CHANGE = """  sdp change ref.pcd cur.pcd -o changes.ply                  appeared points of cur.pcd
  sdp change ref.laz cur.laz -o out.laz --both --voxel-size 0.1
  sdp change ref.ply cur.ply -o out.ply --grid-size 80        the paper's parameters
  sdp change ref.pcd cur.pcd -o out.ply --json                summary as JSON
  sdp change ref.pcd rescan.pcd -o out.ply --align density    register the rescan first
  sdp change ref.ply cur.ply -o out.ply --sensor-origin 0,0,0   the sensor stood there (PCD: read from the file)
  sdp change a.laz b.laz -o out.laz --voxel-size 0.1 --memory-limit 2GB   any size: tiles on Dask
  sdp change a.laz b.laz -o out.laz --voxel-size 0.1 --scheduler tcp://host:8786   on a cluster
"""

EXAMPLES_BOOL = """  sdp bool difference cur.sdpf ref.sdpf -o new.sdpf          what cur has and ref lacks
  sdp bool union a.pcd b.pcd -o both.ply                      surface of the union (auto voxel from both)
  sdp bool intersection a.sdpf b.ply -o common.stl            b is built on a's lattice
"""
EXAMPLES_ALIGN = """  sdp align rescan.pcd reference.pcd -o T.txt               density-based, coarse to fine
  sdp align rescan.pcd reference.pcd -o T.txt --method gicp  small_gicp (extra: align)
  sdp change reference.pcd rescan.pcd -o out.ply --align density   align, then compare
"""
EXAMPLES_WATCH = """  sdp watch empty_room.pcd frames/                         each frame against a sliding window
  sdp watch first.pcd frames/ --align gicp                  a hand-held camera: register each frame first
  sdp watch first.ply frames/ --sensor-origin 0,0,0         the sensor's rays (a PCD's VIEWPOINT is read by itself)
  sdp watch map.sdpf frames/ --update none --json           against a fixed reference field
"""
EXAMPLES_ACTION = """  sdp action eval ../shared/data/msr_action3d --json          the cross-subject protocol
  sdp action train ../shared/data/msr_action3d -o model.npz --subjects 1,3,5,7,9
  sdp action predict model.npz a05_s02_e01_sdepth.mat
"""
EXAMPLES_EVAL = """  sdp eval changes.ply truth.ply                              field 'change' of both
  sdp eval demo-output/current_labelled.ply demo-output/current_labelled.ply --truth-field truth
  sdp eval changes.las scan_labels.las --truth-field classification --json
"""
EXAMPLES_RENDER = """  sdp render changes.ply --png changes.png                    'change' field: changed in vermillion
  sdp render changes.laz --html changes.html --field change   interactive, opens in a browser
  sdp render scan.sdpf --png slices.png                       three slices of F = h - G
"""


def _grid_options(p):
    g = p.add_argument_group("grid (default: --voxel-size auto, sigma from the point spacing, which suits real scans)")
    g.add_argument("--voxel-size", default=DEFAULTS.voxel_size, type=V.cli_type(V.auto_or_positive),
                   help="voxel length in world units, or 'auto' (default: from the clouds' point spacing)")
    g.add_argument("--grid-size", type=V.cli_type(V.integer_at_least, 1),
                   help="the paper's level of detail: longest side / GRID_SIZE (paper: 80)")
    g.add_argument("-k", type=V.cli_type(V.finite), default=DEFAULTS.k,
                   help="threshold h = 1 + k·e^-1/2 (default 3, the paper's)")
    g.add_argument("--h", type=V.cli_type(V.positive_finite), help="threshold h given directly")
    g.add_argument("--sigma-voxels", type=V.cli_type(V.positive_finite), default=DEFAULTS.sigma_voxels,
                   help="sigma in voxels (default 2, the paper's)")
    g.add_argument("--memory-limit", type=V.cli_type(V.memory_size),
                   help="refuse grids needing more (e.g. 2GB; default $SDP_MEMORY_LIMIT or 4GiB)")


def _tile_options(p, title, *, tiled: bool = True):
    t = p.add_argument_group(title)
    if tiled:
        t.add_argument("--tiled", action="store_true", help="work in tiles even if the clouds fit in memory")
    t.add_argument("--tile-size", type=V.cli_type(V.positive_finite),
                   help="tile edge in world units (default: ~2M points per tile)")
    t.add_argument("--scheduler", help="dask.distributed scheduler address, e.g. tcp://host:8786 "
                   "(default: a local cluster of --workers processes)")
    t.add_argument("--workers", type=V.cli_type(V.integer_at_least, 1),
                   help="worker processes of the local cluster (default: one per core)")
    t.add_argument("--workdir", type=V.cli_type(V.existing_folder),
                   help="folder for the tiles' buckets (shared by all workers on a cluster)")


def _tile_kwargs(a) -> dict:
    return dict(sigma_voxels=a.sigma_voxels, k=a.k, h=a.h, tile_size=a.tile_size, memory_limit=a.memory_limit,
                scheduler=a.scheduler, workers=a.workers, workdir=a.workdir)


def _sampled_voxel(a, sources) -> float:
    """``--voxel-size``, or ``auto`` from the first chunk of each source (clouds too large to read whole)."""
    from .tiles import sampled_voxel_size

    return sampled_voxel_size(sources, voxel_size=_voxel(a), k=a.k, sigma_voxels=a.sigma_voxels)


def _is_store(path) -> bool:
    return Path(path).suffix.lower() == ".zarr"


def _voxel(a) -> float | str:
    if a.voxel_size == "auto":
        return "auto"
    try:
        return float(a.voxel_size)
    except ValueError:
        raise SDPError(f"--voxel-size must be a number or 'auto', got {a.voxel_size!r}") from None


def _grid_kwargs(a):
    size = {"grid_size": a.grid_size} if a.grid_size is not None else {"voxel_size": _voxel(a)}
    return dict(size, k=a.k, h=a.h, sigma_voxels=a.sigma_voxels, memory_limit=a.memory_limit)


def cmd_change(a):
    from .change import detect_changes

    out = Path(a.output)
    check_outputs([out, _disappeared_path(out) if a.both else None, a.png, a.html], [a.reference, a.current])
    tiled = _tiled_voxel(a)
    if tiled is not None:
        return _change_tiled(a, tiled)
    t0 = time.perf_counter()
    ref, cur = read_points(a.reference, format=a.format), read_points(a.current, format=a.format)
    t_read = time.perf_counter() - t0
    alignment, moved = None, cur
    if (a.fix_horizontal or a.align_class) and not a.align:
        raise SDPError("--fix-horizontal and --align-class choose how to align: give --align density too")
    if a.align:
        alignment = _align(a, ref, cur, method=a.align)
        moved = cur.transformed(alignment.matrix)  # the current scan's sensor moves with it
    r = detect_changes(ref, moved, decision=a.decision, min_region_points=a.min_region_points,
                       sensor_origin=_sensor_origin(a, (a.reference, ref), (a.current, moved), alignment),
                       range_noise=a.range_noise, **_grid_kwargs(a))
    out_xyz = moved.xyz if a.aligned_output else cur.xyz
    jobs = [(out, cur, out_xyz, r.current_state, r.appeared_region, r.current_field, moved.xyz)]
    if a.both:
        jobs.append((_disappeared_path(out), ref, ref.xyz, r.reference_state, r.disappeared_region,
                     r.reference_field, ref.xyz))
    outputs = _write_labelled(a, jobs)
    outputs += _pictures(a, out_xyz, r.current_state, f"appeared in {Path(a.current).name}")
    summary = r.summary()
    summary["timings"]["read"] = t_read
    if alignment is not None:
        summary["alignment"] = alignment.summary()
        summary["timings"]["align"] = alignment.seconds
    summary["outputs"] = outputs
    _report(a, summary)
    return 0


def _disappeared_path(out: Path) -> Path:
    return out.with_name(out.stem + "_disappeared" + out.suffix)


def _write_labelled(a, jobs) -> list[str]:
    """Write each (path, cloud, xyz, state, region, field, xyz the field saw) as a labelled cloud:
    ``change`` (0 unchanged, 1 changed, 2 not comparable), ``region``, ``G`` and ``F``."""
    from .io import write_points

    written = []
    for path, cloud, xyz, state, region, fld, seen in jobs:
        fields = {"change": state, "region": region.astype(np.int32),
                  "G": fld.density(seen).astype(np.float32), "F": fld.field(seen).astype(np.float32)}
        write_points(path, xyz, fields, like=cloud, inputs=(a.reference, a.current))
        written.append(str(path))
    return written


def _sensor_origin(a, ref_scan, cur_scan, alignment=None):
    """``sensor_origin=`` of :func:`sdp.detect_changes` from ``--sensor-origin``: ``auto`` what
    the files say, ``viewpoint`` the same but required, ``none`` no sensor, ``X,Y,Z`` one
    position (the current's moved by ``alignment``)."""
    choice = a.sensor_origin
    if choice in ("auto", "none"):
        return choice
    if choice == "viewpoint":
        for name, c in (ref_scan, cur_scan):
            if c.sensor_origin is None:
                raise SDPError(f"{name}: the file records no sensor position (organized PCD files do); "
                               "give --sensor-origin X,Y,Z or auto")
        return "auto"
    try:
        xyz = [float(v) for v in choice.split(",")]
    except ValueError:
        xyz = []
    if len(xyz) != 3 or not np.isfinite(xyz).all():
        raise SDPError(f"--sensor-origin must be auto, none, viewpoint or X,Y,Z (finite numbers), got {choice!r}")
    cur_xyz = xyz if alignment is None else alignment.apply(np.array([xyz]))[0]
    return np.array([xyz, cur_xyz], dtype=np.float64)


def _tiled_voxel(a) -> float | None:
    """The voxel size of a tiled comparison when ``--tiled`` is given or the clouds need it, else None.

    Tiles are taken when the two dense grids over the clouds' box, or the points themselves,
    would exceed the memory limit; only LAS/LAZ, NPY and binary PLY can be read in slices.
    """
    from .grid import memory_limit
    from .io import FORMATS, PointSource
    from .tiles import dense_grid_bytes, untiled_point_bytes

    if _is_store(a.reference):  # a stored reference field: its lattice, σ, h and tiles
        from .store import FieldStore

        a.tiled, a.sources = True, [FieldStore.open(a.reference), PointSource.open(a.current, format=a.format)]
        if a.both:
            raise SDPError("--both needs the reference points; a .zarr field store only tells what appeared")
        return a.sources[0].voxel_size
    streamed = all((a.format or FORMATS.get(Path(f).suffix.lower())) in ("las", "npy", "ply")
                   for f in (a.reference, a.current))
    given_sensor = a.sensor_origin not in ("auto", "none")  # the tiles follow no rays
    if not a.tiled and (not streamed or a.grid_size is not None or a.align or a.decision != "point" or given_sensor):
        return None
    if a.tiled:
        for flag, bad in (("--grid-size", a.grid_size is not None), ("--align", a.align),
                          ("--sensor-origin", given_sensor),
                          ("--decision cluster", a.decision != "point"), ("--png/--html", a.png or a.html)):
            if bad:
                raise SDPError(f"{flag} is not available with --tiled")
        if not streamed:
            raise SDPError("--tiled reads LAS/LAZ, NPY or binary PLY files in slices; convert the clouds first")
    try:
        sources = [PointSource.open(f, format=a.format) for f in (a.reference, a.current)]
    except SDPError:
        if a.tiled:
            raise
        return None  # ASCII PLY and the like: the in-memory path reads them (or reports the error)
    voxel = _sampled_voxel(a, sources)
    lo = np.minimum(sources[0].lo, sources[1].lo)
    hi = np.maximum(sources[0].hi, sources[1].hi)
    grids = 2 * dense_grid_bytes(lo, hi, voxel, sigma_voxels=a.sigma_voxels)
    points = untiled_point_bytes(sum(s.n_rows for s in sources))
    cap = memory_limit(a.memory_limit)
    if a.tiled or max(grids, points) > cap:
        if Path(a.output).suffix.lower() not in (".las", ".laz"):  # before any work: the tiles stream LAS/LAZ
            raise SDPError(f"{a.output}: the clouds are compared in tiles (two dense grids would need "
                           f"{V.format_bytes(grids)}, above the memory limit of {V.format_bytes(cap)}), whose "
                           "output streams to LAS/LAZ: give -o OUT.laz, or a larger --memory-limit")
        if not a.tiled and not a.json:
            print(f"sdp: comparing in tiles on Dask: dense grids of {V.format_bytes(grids)} and points of "
                  f"{V.format_bytes(points)} exceed the memory limit of {V.format_bytes(cap)}", file=sys.stderr)
        a.sources = sources
        return float(voxel)
    return None


def _change_tiled(a, voxel: float):
    from .io import write_points_streamed
    from .tiles import detect_changes_tiled

    r = detect_changes_tiled(*a.sources, voxel_size=voxel, min_region_points=a.min_region_points, **_tile_kwargs(a))
    from .coverage import CHANGED, NOT_COMPARABLE

    out = Path(a.output)
    jobs = [(out, a.sources[1], r.appeared_rows, r.appeared_region, r.current_not_comparable_rows)]
    if a.both:
        jobs.append((_disappeared_path(out), a.sources[0], r.disappeared_rows, r.disappeared_region,
                     r.reference_not_comparable_rows))
    t = time.perf_counter()
    outputs = []
    for path, src, rows, region, unseen in jobs:
        def fields_of(start, stop, rows=rows, region=region, unseen=unseen):
            i, j = np.searchsorted(rows, (start, stop))
            change, label = np.zeros(stop - start, np.uint8), np.full(stop - start, -1, np.int32)
            change[rows[i:j] - start], label[rows[i:j] - start] = CHANGED, region[i:j]
            i, j = np.searchsorted(unseen, (start, stop))
            change[unseen[i:j] - start] = NOT_COMPARABLE
            return {"change": change, "region": label}

        outputs.append(str(write_points_streamed(path, src, fields_of, inputs=(a.reference, a.current))))
    summary = r.summary()
    summary["timings"]["write"] = time.perf_counter() - t
    summary["outputs"] = outputs
    _report(a, summary)
    return 0


def _report(a, s):
    """Print a change summary: JSON with ``--json``, else a table."""
    if a.json:
        print(json.dumps(s, indent=2))
        return
    for role, name, kind in (("reference", a.reference, "disappeared"), ("current", a.current, "appeared")):
        c = s[role]
        print(f"{role:<10} {name}: {c['points']:,} points ({c['dropped']:,} dropped), {c[kind]:,} {kind}, "
              f"{c['not_comparable']:,} not comparable")
    if "alignment" in s:
        print(_alignment_text(s["alignment"]))
    print(f"voxel {s['voxel_size']:.4g}, sigma {s['sigma']:.4g}, h {s['h']:.4f}, decision {s['decision']}"
          + (f", {s['tiles']} tiles of {s['tile_size']:.4g}" if "tiles" in s else ""))
    print(_coverage_text(s))
    for kind in ("appeared", "disappeared"):
        regs = s[f"{kind}_regions"]
        if regs:
            print(f"\n{kind} regions ({len(regs)}; largest 10):")
            print(f"  {'#':>3} {'points':>8}  {'centroid':>30}  {'size':>26}")
            for g in regs[:10]:
                c = " ".join(f"{v:9.3f}" for v in g["centroid"])
                size = " ".join(f"{hi - lo:8.3f}" for lo, hi in zip(g["bbox_min"], g["bbox_max"], strict=True))
                print(f"  {g['label']:>3} {g['n_points']:>8,}  {c}  {size}")
    print("\ntime (ms): " + ", ".join(f"{k} {v * 1e3:.1f}" for k, v in s["timings"].items()))
    for o in s.get("outputs", []):
        print(f"wrote {o}")


def _coverage_text(s) -> str:
    """One line: how each direction decided what the other scan saw (sensor rays or footprint)."""
    origins = s.get("sensor_origin", {})

    def one(kind, other):
        how = s["coverage"][kind]
        if how == "sensor rays":
            o = ", ".join(f"{v:.4g}" for v in origins[other])
            return f"{kind}: the {other}'s sensor rays (origin {o})"
        return f"{kind}: the {other}'s footprint (no sensor position known)" if how == "footprint" else f"{kind}: off"
    return "coverage: " + "; ".join((one("appeared", "reference"), one("disappeared", "current")))


def _lattice(a, clouds, like=None) -> dict:
    """``DensityField.from_points`` options: the grid options (``auto``: from all ``clouds``'
    point spacing), or the lattice, σ and h of the field ``like`` so results can be combined."""
    from ._points import as_points
    from .params import resolve_voxel_size

    if like is not None:
        return dict(voxel_size=like.voxel_size, sigma_voxels=like.sigma / like.voxel_size, h=like.h,
                    truncate=like.truncate, memory_limit=a.memory_limit)
    kw = _grid_kwargs(a)
    kw["voxel_size"] = resolve_voxel_size([as_points(c) for c in clouds], voxel_size=kw.pop("voxel_size", "auto"),
                                          grid_size=kw.pop("grid_size", None), k=a.k, sigma_voxels=a.sigma_voxels)
    return kw


def _is_field(path) -> bool:
    return Path(path).suffix.lower() == ".sdpf"


def _field(path, a):
    """A field file loaded, or a cloud file's field built with the grid options."""
    from .field import DensityField

    if _is_field(path):
        return DensityField.load(path)
    xyz = read_points(path, format=a.format).xyz
    return DensityField.from_points(xyz, **_lattice(a, [xyz]))


def _field_or_points(path, a):
    """A field file loaded, or a cloud file's points (n, 3)."""
    from .field import DensityField

    return DensityField.load(path) if _is_field(path) else read_points(path, format=a.format).xyz


def _save_field(field, path, inputs):
    from .io import refuse_overwrite

    refuse_overwrite(path, inputs)
    field.save(path)
    print(f"{field!r}\nwrote {path}")


def _pictures(a, xyz, changed, title) -> list[str]:
    """Write the ``--png`` / ``--html`` pictures of changed points that were asked for."""
    from .render import render_changes, render_changes_html

    written = []
    for path, render in ((a.png, render_changes), (getattr(a, "html", None), render_changes_html)):
        if path:
            render(path, xyz, changed, title=title)
            written.append(path)
    return written


def _align_options(p):
    p.add_argument("--fix-horizontal", action="store_true",
                   help="density alignment: estimate only the vertical shift and the tilts (z up); for epochs of "
                        "nearly flat terrain")
    p.add_argument("--align-class", metavar="C[,C...]",
                   help="estimate the transform on the points of these LAS classes of both scans (e.g. 2: ground), "
                        "then move the whole current scan")


def _alignment_text(al) -> str:
    t = " ".join(f"{v:.4f}" for v in al["translation"])
    return (f"aligned current onto reference ({al['method']}): rotation {al['rotation_degrees']:.3f}°, "
            f"translation [{t}], inside the reference's volume {al['inside_before']:.1%} → {al['inside_after']:.1%}, "
            f"residual {al['rmse']:.4g} (RMS), {al['seconds']:.2f} s")


def _align(a, ref, cur, *, method: str):
    """sdp.align of the current Cloud onto the reference (a Cloud, or a DensityField) with the
    options --fix-horizontal and --align-class."""
    from .align import align
    from .field import DensityField

    if a.fix_horizontal and method != "density":
        raise SDPError("--fix-horizontal works with the density alignment only")
    ref_xyz = ref if isinstance(ref, DensityField) else ref.xyz
    cur_xyz = cur.xyz
    if a.align_class:
        try:
            classes = [int(c) for c in a.align_class.split(",")]
        except ValueError:
            raise SDPError(f"--align-class takes LAS class numbers such as 2 or 2,9, got {a.align_class!r}") from None
        if isinstance(ref, DensityField):
            raise SDPError("--align-class needs the reference's points, not a field")
        picked = []
        for cloud, name in ((ref, a.reference), (cur, a.current)):
            if "classification" not in cloud.fields:
                raise SDPError(f"{name}: no 'classification' field for --align-class (LAS/LAZ files have one)")
            keep = np.isin(cloud.fields["classification"], classes)
            if keep.sum() < 3:
                raise SDPError(f"{name}: {int(keep.sum())} points of class {a.align_class}: too few to align on")
            picked.append(cloud.xyz[keep])
        ref_xyz, cur_xyz = picked
    return align(ref_xyz, cur_xyz, method=method, fix_horizontal=a.fix_horizontal)


def cmd_align(a):
    from .field import DensityField
    from .io import atomic_path, refuse_overwrite

    check_outputs([a.output], [a.current, a.reference])
    refuse_overwrite(a.output, (a.current, a.reference))
    ref = DensityField.load(a.reference) if _is_field(a.reference) else read_points(a.reference, format=a.format)
    al = _align(a, ref, read_points(a.current, format=a.format), method=a.method)
    with atomic_path(a.output) as tmp:
        np.savetxt(tmp, al.matrix, fmt="%.12g", header=f"sdp align {a.current} onto {a.reference} ({a.method})")
    if a.json:
        print(json.dumps(al.summary(), indent=2))
    else:
        print(f"{_alignment_text(al.summary())}\nwrote {a.output}")
    return 0


def cmd_watch(a):
    import re

    from .io import FORMATS
    from .online import watch

    folder = Path(a.frames)
    if not folder.is_dir():
        raise SDPError(f"{folder}: not a folder of frames")
    paths = sorted((p for p in folder.iterdir() if p.suffix.lower() in FORMATS and p.is_file()),
                   key=lambda p: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)])
    if not paths:
        raise SDPError(f"{folder}: no point-cloud files ({', '.join(sorted(FORMATS))})")
    if _is_field(a.reference):
        from .field import DensityField

        if a.sensor_origin not in ("auto", "none"):
            raise SDPError("--sensor-origin follows the reference's rays: give the reference cloud, not a field")
        ref, origin = DensityField.load(a.reference), None
    else:
        ref = read_points(a.reference, format=a.format)
        origin = _sensor_origin(a, (a.reference, ref), (a.reference, ref))
        origin = origin[0] if isinstance(origin, np.ndarray) else origin
    frames = ((p.name, read_points(p, format=a.format)) for p in paths)
    reports = []
    for r in watch(ref, frames, voxel_size=_voxel(a), update=a.update, window=a.window, decay=a.decay,
                   min_region_points=a.min_region_points, align=a.align, sensor_origin=origin,
                   range_noise=a.range_noise):
        s = r.summary()
        reports.append(s)
        if not a.json:
            where = "; ".join(f"{g['n_points']:,} at ({', '.join(f'{v:.2f}' for v in g['centroid'])})"
                              for g in s["regions"][:3])
            print(f"{r.name}: {s['points']:,} points, {r.n_appeared:,} appeared in {len(r.regions)} regions, "
                  f"{s['not_comparable']:,} not comparable ({r.latency * 1e3:.1f} ms){': ' + where if where else ''}")
    if a.json:
        print(json.dumps(reports, indent=2))
    return 0


def cmd_action(a):
    from . import actions

    if a.action_command == "train":
        check_outputs([a.output], [a.data_dir])
        rows = actions.list_sequences(a.data_dir)
        if a.subjects:
            try:
                wanted = {int(v) for v in a.subjects.split(",")}
            except ValueError:
                raise SDPError(f"--subjects takes subject numbers such as 1,3,5, got {a.subjects!r}") from None
            rows = [r for r in rows if r[2] in wanted]
        x = actions.describe_sequences([r[0] for r in rows], workers=a.workers)
        model, cv = actions.train(x, np.array([r[1] for r in rows]), np.array([r[2] for r in rows]))
        model.save(a.output)
        print(f"{len(rows)} sequences, {len(model.classes)} actions; alpha {model.alpha:g}, "
              f"leave-one-subject-out accuracy {cv:.3f}\nwrote {a.output}")
    elif a.action_command == "predict":
        model = actions.ActionModel.load(a.model)
        for path in a.sequences:
            label = model.predict(actions.sequence_descriptor(actions.read_sequence(path)))[0]
            print(f"{path}: a{int(label):02d}")
    else:
        t0 = time.perf_counter()
        r = actions.evaluate_protocol(a.data_dir, workers=a.workers)
        r["timings"]["total"] = time.perf_counter() - t0
        summary = dict(r["accuracy"], cv=r["cv_accuracy"], alpha=r["alpha"], timings=r["timings"],
                       sequences=r["sequences"])
        if a.json:
            print(json.dumps(summary, indent=2))
        else:
            for name, acc in r["accuracy"].items():
                cv = r["cv_accuracy"].get(name)
                print(f"{name:8s} {acc:.3f}" + (f"   (cross-validated on training subjects {cv:.3f})" if cv else ""))
            print("time (s): " + ", ".join(f"{k} {v:.1f}" for k, v in r["timings"].items()))
    return 0


def cmd_build(a):
    check_outputs([a.output], [a.cloud])
    if not _is_store(a.output):
        _save_field(_field(a.cloud, a), a.output, inputs=(a.cloud,))
        return 0
    from .io import PointSource
    from .tiles import build_field_tiled

    source = PointSource.open(a.cloud, format=a.format)
    store = build_field_tiled(source, a.output, voxel_size=_sampled_voxel(a, [source]), **_tile_kwargs(a))
    print(f"{store!r}\nwrote {a.output}")
    return 0


def cmd_info(a):
    from .field import DensityField

    if _is_store(a.file):
        from .store import FieldStore

        st = FieldStore.open(a.file)
        info = {"kind": "field store", "voxel_size": st.voxel_size, "sigma": st.sigma, "h": st.h,
                "tiles": len(st.tiles), "tile_blocks": st.tile_blocks, "blocks": st.n_blocks, "n_points": st.n_points}
    elif _is_field(a.file):
        f = DensityField.load(a.file)
        info = {"kind": "field", "voxel_size": f.voxel_size, "sigma": f.sigma, "h": f.h, "blocks": f.n_blocks,
                "box_nodes": list(f.grid.shape), "origin": f.grid.origin.tolist(), "n_points": f.n_points,
                "method": f.method, "megabytes": f.nbytes / 2**20}
    else:
        c = read_points(a.file, format=a.format)
        info = {"kind": "cloud", "points": len(c), "dropped_non_finite": c.n_dropped,
                "min": c.xyz.min(0).tolist(), "max": c.xyz.max(0).tolist(), "fields": sorted(c.fields)}
    print(json.dumps(info, indent=2))
    return 0


def cmd_mesh(a):
    check_outputs([a.output], [a.input])
    if _is_store(a.input):
        from .store import FieldStore

        mesh = FieldStore.open(a.input).mesh(level=a.level)
    else:
        mesh = _field(a.input, a).mesh(level=a.level)
    _write_mesh(a.output, mesh, inputs=(a.input,))
    return 0


def _write_mesh(path, mesh, inputs):
    from .io import write_mesh

    write_mesh(path, mesh, inputs=inputs)
    print(f"{len(mesh.vertices):,} vertices, {len(mesh.faces):,} triangles, area {mesh.area:.4g}\nwrote {path}")


def cmd_bool(a):
    from . import boolean
    from .field import DensityField

    check_outputs([a.output], [a.a, a.b])
    if _is_store(a.output):
        from .store import FieldStore

        if not (_is_store(a.a) and _is_store(a.b)):
            raise SDPError("a .zarr output combines two .zarr field stores (build them with sdp build -o X.zarr)")
        out = FieldStore.open(a.a).combine(FieldStore.open(a.b), a.operation, a.output)
        print(f"{out!r}\nwrote {a.output}")
        return 0
    items = [_field_or_points(p, a) for p in (a.a, a.b)]
    like = next((x for x in items if isinstance(x, DensityField)), None)
    kw = _lattice(a, items, like)  # clouds are built on a given field's lattice, else on one from both
    fa, fb = (x if isinstance(x, DensityField) else DensityField.from_points(x, **kw) for x in items)
    result = getattr(boolean, a.operation)(fa, fb)
    if _is_field(a.output):
        _save_field(result, a.output, inputs=(a.a, a.b))
    else:
        _write_mesh(a.output, result.mesh(), inputs=(a.a, a.b))
    return 0


def cmd_eval(a):
    from .coverage import CHANGED, NOT_COMPARABLE
    from .metrics import scores

    values = []
    for path, name in ((a.predicted, a.predicted_field), (a.truth, a.truth_field)):
        c = read_points(path, format=a.format)
        if name not in c.fields:
            raise SDPError(f"{path}: no per-point field {name!r} (fields: {', '.join(sorted(c.fields)) or 'none'})")
        values.append(np.asarray(c.fields[name]))
    if len(values[0]) != len(values[1]):
        raise SDPError(f"{a.predicted} has {len(values[0]):,} points and {a.truth} {len(values[1]):,}: "
                       "they must be the same points in the same order")
    if a.predicted_field == "change":  # sdp's field: 1 changed, 2 not comparable (scored apart)
        predicted, comparable = values[0] == CHANGED, values[0] != NOT_COMPARABLE
    else:  # any other field: nonzero is changed
        predicted, comparable = values[0] != 0, None
    truth = values[1] != 0
    sc = scores(truth, predicted, comparable=comparable)
    comparable = np.ones(len(truth), bool) if comparable is None else comparable
    if a.json:
        print(json.dumps(sc, indent=2))
    else:
        print(f"{len(truth):,} points ({sc['not_comparable']:,} not comparable, left out); changed: "
              f"predicted {predicted.sum():,}, true {truth[comparable].sum():,} of the comparable")
        print("  ".join(f"{k} {v:.4f}" for k, v in sc.items() if isinstance(v, float)))
        print("  ".join(f"{k} {v:,}" for k, v in sc.items() if isinstance(v, int)))
    return 0


def cmd_render(a):
    if not (a.png or a.html):
        raise SDPError("nothing to write: give --png OUT.png and/or --html OUT.html")
    check_outputs([a.png, a.html], [a.file])
    if _is_field(a.file):
        from .field import DensityField
        from .render import render_field

        if a.html:
            raise SDPError("--html draws clouds; for a field use --png (slices), or `sdp mesh` for its surface")
        render_field(a.png, DensityField.load(a.file))
        written = [a.png]
    else:
        c = read_points(a.file, format=a.format)
        if a.field not in c.fields:
            raise SDPError(f"{a.file}: no per-point field {a.field!r} to colour by "
                           f"(fields: {', '.join(sorted(c.fields)) or 'none'}); choose one with --field")
        values = np.asarray(c.fields[a.field])
        if a.field == "change":  # sdp's field: 0 unchanged, 1 changed, 2 not comparable
            state, what = values.astype(np.uint8), "changed vermillion, not comparable grey"
        else:
            state, what = values != 0, f"{a.field} ≠ 0 in vermillion"
        written = _pictures(a, c.xyz, state, f"{Path(a.file).name}: {what}")
    print("\n".join(f"wrote {w}" for w in written))
    return 0


def cmd_demo(a):
    from .change import detect_changes
    from .io import write_mesh, write_points
    from .metrics import scores
    from .render import render_changes
    from .scene import INSERTED, office_scene

    out = Path(a.output)
    out.mkdir(parents=True, exist_ok=True)
    print("Simulating a Kinect-like depth sensor in an office (ray casting, occlusion, depth noise):")
    s = office_scene(seed=a.seed)
    print(f"  reference scan {len(s.reference):,} points; current scan {len(s.current):,} points with "
          f"{len(INSERTED)} inserted objects ({s.appeared_truth.sum():,} points on them)")
    r = detect_changes(s.reference, s.current, sensor_origin=s.camera)  # the defaults; the camera is known
    sc = scores(s.appeared_truth, r.appeared, comparable=~r.current_not_comparable)
    every = scores(s.appeared_truth, r.appeared)["kappa"]
    paper = detect_changes(s.reference, s.current, grid_size=80, sensor_origin=None, coverage=False,
                           min_region_points=1)
    kp = scores(s.appeared_truth, paper.appeared)["kappa"]
    print(f"\nchange detection (the defaults: voxel {r.voxel_size * 1000:.1f} mm from the point spacing, "
          f"the camera's rays):")
    print(f"  appeared points {r.appeared.sum():,}; not comparable {sc['not_comparable']:,} (the reference's "
          "camera could not see there)")
    print(f"  on the comparable points: kappa {sc['kappa']:.3f}, precision {sc['precision']:.3f}, "
          f"recall {sc['recall']:.3f}, IoU {sc['iou']:.3f}")
    print(f"  on every point (not comparable as unchanged): kappa {every:.3f}; the paper's 80³ grid: kappa {kp:.3f}")
    print("  time (ms): " + ", ".join(f"{k} {v * 1e3:.1f}" for k, v in r.timings.items()))
    print(f"  {len(r.appeared_regions)} change regions:")
    for g in r.appeared_regions:
        objs = s.object_of_current[r.appeared_region == g.label]
        best = np.bincount(objs[objs >= 0], minlength=len(INSERTED)).argmax() if (objs >= 0).any() else -1
        name = INSERTED[best].name if best >= 0 else "(no inserted object)"
        print(f"    {g.n_points:6,} points at ({', '.join(f'{v:.2f}' for v in g.centroid)}) "
              f"size {' x '.join(f'{v:.2f}' for v in g.size)} m  ~ {name}")
    print(f"  disappeared points {r.disappeared.sum():,}: the surfaces the new objects now hide")
    write_points(out / "reference.ply", s.reference)
    write_points(out / "current_labelled.ply", s.current,
                 {"change": r.current_state, "truth": s.appeared_truth.astype(np.uint8),
                  "region": r.appeared_region.astype(np.int32),
                  "F": r.current_field.field(s.current).astype(np.float32)})
    write_mesh(out / "current_cluster_volume.ply", r.current_field.mesh())
    render_changes(out / "changes.png", s.current, r.current_state,
                   title=f"sdp demo: appeared points vermillion, not comparable grey (kappa {sc['kappa']:.3f} "
                         "vs. ground truth on the comparable points)")
    print(f"\nwrote {out}/reference.ply, current_labelled.ply, current_cluster_volume.ply, changes.png")
    return 0


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

    c = _command(sub, "change", cmd_change, "appeared (and disappeared) points between two clouds", EXAMPLES_CHANGE)
    c.add_argument("reference")
    c.add_argument("current")
    c.add_argument("-o", "--output", required=True, help="labelled current cloud (.ply, .las, .laz, .npz)")
    c.add_argument("--both", action="store_true",
                   help="also write the disappeared reference points (OUTPUT_disappeared)")
    c.add_argument("--decision", choices=("point", "cluster"), default=DEFAULTS.decision,
                   help="point (default: Algorithm 1 per point) or cluster (the paper's clustering)")
    c.add_argument("--min-region-points", type=V.cli_type(V.integer_at_least, 0), default=DEFAULTS.min_region_points,
                   help="drop change regions with fewer points (default 50: smaller ones are noise and depth edges)")
    c.add_argument("--png", help="write a picture of the appeared points")
    c.add_argument("--html", help="write an interactive 3D view (needs the html extra: plotly)")
    c.add_argument("--json", action="store_true", help="print the summary as JSON")
    c.add_argument("--align", choices=("density", "gicp"), help="register CURRENT onto REFERENCE first")
    c.add_argument("--aligned-output", action="store_true", help="write CURRENT's aligned coordinates (with --align)")
    _align_options(c)
    c.add_argument("--sensor-origin", metavar="auto|none|viewpoint|X,Y,Z", default=DEFAULTS.sensor_origin,
                   help="test changes along the sensor's rays (sdp.visibility). auto (default): where a file "
                        "records it (organized PCD: VIEWPOINT), as it lifts kappa on Kinect pairs from 0.67 to 0.85; "
                        "viewpoint: the same, required; none: density and footprint only; X,Y,Z: one position")
    c.add_argument("--range-noise", type=V.cli_type(V.nonnegative_finite), default=DEFAULTS.range_noise,
                   help="with a sensor: same range within RANGE_NOISE·r² (default 0.015, a Kinect's depth noise)")
    _tile_options(c, "large clouds: tiles on Dask (taken by itself when the grids or points exceed --memory-limit, "
                     "or when REFERENCE is a .zarr field store; outputs LAS/LAZ with 'change' and 'region')")

    b = _command(sub, "build", cmd_build, "build a density field and save it (.sdpf, or a .zarr store in tiles)",
                 "  sdp build scan.pcd -o scan.sdpf --voxel-size 0.01\n"
                 "  sdp build city.laz -o city.zarr --voxel-size 0.1        any size: tiles on Dask, on disk")
    b.add_argument("cloud")
    b.add_argument("-o", "--output", required=True, help=".sdpf (in memory) or .zarr (a field store, built in tiles)")
    _tile_options(b, "field stores (.zarr output)", tiled=False)

    i = _command(sub, "info", cmd_info, "describe a cloud or a field file", "  sdp info scan.laz\n  sdp info scan.sdpf")
    i.add_argument("file")

    m = _command(sub, "mesh", cmd_mesh, "iso-surface of a field or cloud (Lewiner marching cubes)",
                 "  sdp mesh scan.sdpf -o surface.ply\n  sdp mesh scan.pcd -o surface.obj --level 0")
    m.add_argument("input")
    m.add_argument("-o", "--output", required=True, help=".ply, .obj or .stl")
    m.add_argument("--level", type=V.cli_type(V.finite), default=0.0,
                   help="level of F = h - G (0: the cluster boundary)")

    o = _command(sub, "bool", cmd_bool, "union, intersection or difference of two fields or clouds",
                 EXAMPLES_BOOL)
    o.add_argument("operation", choices=("union", "intersection", "difference"))
    o.add_argument("a", help="field (.sdpf) or cloud")
    o.add_argument("b", help="field (.sdpf) or cloud")
    o.add_argument("-o", "--output", required=True, help=".sdpf (the field) or .ply/.obj/.stl (its surface)")

    al = _command(sub, "align", cmd_align, "rigid transform mapping CURRENT onto REFERENCE (4x4, numpy.loadtxt)",
                  EXAMPLES_ALIGN)
    al.add_argument("current")
    al.add_argument("reference", help="cloud, or field (.sdpf) for --method density")
    al.add_argument("-o", "--output", required=True, help="text file with the 4x4 matrix")
    al.add_argument("--method", choices=("density", "gicp"), default="density",
                    help="density: maximise the reference's density, coarse to fine; gicp: small_gicp")
    _align_options(al)
    al.add_argument("--json", action="store_true", help="print the result as JSON")

    w = _command(sub, "watch", cmd_watch, "compare each frame of a folder, in order, with a model that learns",
                 EXAMPLES_WATCH)
    w.add_argument("reference", help="cloud or field (.sdpf) of the scene before the frames")
    w.add_argument("frames", help="folder of frames, processed in natural name order")
    w.add_argument("--update", choices=("none", "window", "decay"), default=DEFAULTS.update,
                   help="how the model learns the frames (default window: learns the last frames, forgets the rest)")
    w.add_argument("--window", type=V.cli_type(V.integer_at_least, 1), default=DEFAULTS.window,
                   help="frames in the model, reference included (default 10)")
    w.add_argument("--decay", type=float, default=DEFAULTS.decay, help="per-frame forgetting factor for --update decay")
    w.add_argument("--min-region-points", type=V.cli_type(V.integer_at_least, 0), default=DEFAULTS.min_region_points,
                   help="drop appeared regions with fewer points (default 50)")
    w.add_argument("--voxel-size", default=DEFAULTS.voxel_size, type=V.cli_type(V.auto_or_positive),
                   help="voxel of a reference cloud, or 'auto' (default)")
    w.add_argument("--align", choices=("gicp", "density"),
                   help="register each frame onto the reference first (a moving camera): gicp (small_gicp, "
                        "needs a reference cloud) or density")
    w.add_argument("--sensor-origin", metavar="auto|none|viewpoint|X,Y,Z", default=DEFAULTS.sensor_origin,
                   help="test changes along the reference's rays (sdp.visibility): auto (default) where its file "
                        "records the sensor (organized PCD), viewpoint the same but required, none, or X,Y,Z")
    w.add_argument("--range-noise", type=V.cli_type(V.nonnegative_finite), default=DEFAULTS.range_noise,
                   help="with a sensor: same range within RANGE_NOISE·r² (default 0.015, a Kinect)")
    w.add_argument("--json", action="store_true", help="print one summary per frame as JSON")

    act = _command(sub, "action", cmd_action, "recognise human actions in depth sequences (MSR Action3D)",
                   EXAMPLES_ACTION)
    asub = act.add_subparsers(dest="action_command", required=True)
    t = asub.add_parser("train", help="fit a classifier on a folder of aXX_sYY_eZZ sequences")
    t.add_argument("data_dir")
    t.add_argument("-o", "--output", required=True, help="model file (.npz)")
    t.add_argument("--subjects", help="comma-separated subjects to train on (default: all)")
    pr = asub.add_parser("predict", help="action label of each sequence")
    pr.add_argument("model")
    pr.add_argument("sequences", nargs="+", help=".mat or .bin depth sequences")
    ev = asub.add_parser("eval", help="the cross-subject protocol: accuracy on AS1, AS2, AS3 and all")
    ev.add_argument("data_dir")
    ev.add_argument("--json", action="store_true", help="print the accuracies (fractions) and timings as JSON")
    for q in (t, ev):
        q.add_argument("--workers", type=V.cli_type(V.integer_at_least, 1), default=os.cpu_count() or 1,
                       help="processes reading sequences")

    e = _command(sub, "eval", cmd_eval, "kappa, precision, recall, … of predicted change labels against truth",
                 EXAMPLES_EVAL)
    e.add_argument("predicted", help="cloud with the predicted labels (e.g. the output of sdp change)")
    e.add_argument("truth", help="cloud with the true labels, same points in the same order")
    e.add_argument("--predicted-field", default="change",
                   help="field of PREDICTED (default change: 1 changed, 2 not comparable, left out; other fields: "
                        "nonzero is changed)")
    e.add_argument("--truth-field", default="change", help="field of TRUTH (nonzero: changed; default change)")
    e.add_argument("--json", action="store_true", help="print the scores as JSON")

    r = _command(sub, "render", cmd_render, "picture of a labelled cloud (red: changed) or slices of a field",
                 EXAMPLES_RENDER)
    r.add_argument("file", help="cloud with a label field, or a field (.sdpf)")
    r.add_argument("--png", help="picture (three views of a cloud; three slices of a field)")
    r.add_argument("--html", help="interactive 3D view of a cloud (needs the html extra: plotly)")
    r.add_argument("--field", default="change",
                   help="per-point field whose nonzero points are drawn as changed (default change)")

    for q in (c, b, i, m, o, al, w, e, r):
        q.add_argument("--format", help="input format, overriding the extension (pcd, ply, las, text, npy, npz)")
    for q in (c, b, m, o):
        _grid_options(q)

    d = _command(sub, "demo", cmd_demo, "run change detection on a simulated office scan; write results",
                 "  sdp demo -o demo-output")
    d.add_argument("-o", "--output", default="demo-output")
    d.add_argument("--seed", type=int, default=0)
    for q in (c, b, i, m, o, al, w, e, r, d):
        q.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    return p


class _Terminated(BaseException):
    """SIGTERM, raised in the main thread so that ``finally`` blocks and context managers clean up
    (temporary outputs, the tiles' work folder, the Dask cluster) before the process ends."""


def _on_sigterm(signum, frame):
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a second one must not cut the clean-up short
    raise _Terminated()


def _one_line(exc: BaseException) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return lines[0] if lines else type(exc).__name__


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    _progress.enable(not (getattr(args, "quiet", False) or getattr(args, "json", False)))
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if in_main else None
    try:
        with all_or_none():  # a command writes all its outputs or none
            return args.func(args)
    except (SDPError, ValueError) as exc:
        print(f"sdp: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except MemoryError:
        print("sdp: error: out of memory: use a larger --voxel-size or a lower --memory-limit", file=sys.stderr)
        return 2
    except BrokenPipeError:  # output piped into head & co.
        sys.stderr.close()
        return 0
    except OSError as exc:  # a disk full, a file vanishing: said in one line
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"sdp: error: {where}{exc.strerror or _one_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sdp: interrupted", file=sys.stderr)
        return 130
    except _Terminated:
        print("sdp: terminated", file=sys.stderr)
        return 128 + signal.SIGTERM
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)


if __name__ == "__main__":
    sys.exit(main())
