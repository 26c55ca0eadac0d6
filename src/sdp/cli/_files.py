"""The other commands as functions, files in, files out: ``sdp build``, ``mesh``, ``bool``,
``info``, ``align``, ``watch``, ``eval`` and ``render``."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .._core import _validate as V
from ..defaults import DEFAULTS
from ..errors import GridTooLargeError, SDPError
from ..io._output import all_or_none, check_format, check_outputs
from ..io._cloud import input_format
from ..io._read import read_points
from ..options import Coverage, Execution, Lattice, NoiseModel, Registration, as_options
from . import _text as report
from ._common import align_clouds, is_field, is_store, pictures, read_input, same_frame, sensor_origins

__all__ = ["build_field_file", "mesh_file", "combine_files", "describe_file", "align_files", "watch_folder",
           "Evaluation", "evaluate_files", "render_file"]


def _no_lattice(lattice: Lattice) -> None:
    """Refuse a lattice given with a field, whose own lattice wins (it would be ignored)."""
    if lattice != Lattice():
        raise SDPError("a field sets the lattice (voxel, σ, h): give no --voxel-size, --sigma-voxels, -k, --h or "
                       "--grid-size with it")


def _lattice(clouds, lattice: Lattice, memory_limit, like=None) -> dict:
    """``DensityField.from_points`` options: ``lattice`` (``auto``: from all ``clouds``' point
    spacing), or the lattice, σ and h of the field ``like`` so results can be combined."""
    from .._core._points import as_points
    from ..fields._spacing import resolve_lattice

    if like is not None:
        _no_lattice(lattice)
        return dict(voxel_size=like.voxel_size, sigma_voxels=like.sigma / like.voxel_size, h=like.h,
                    truncate=like.truncate, memory_limit=memory_limit)
    kw = lattice.keywords()
    kw["voxel_size"], kw["sigma_voxels"] = resolve_lattice(
        [as_points(c) for c in clouds], voxel_size=kw.pop("voxel_size", "auto"), grid_size=kw.pop("grid_size", None),
        k=lattice.k, sigma_voxels=lattice.sigma_voxels)
    return dict(kw, memory_limit=memory_limit)


@contextmanager
def _blocks_budget(clouds, format, memory_limit, advice: str):
    """Yield what the fields' blocks may take of the memory limit: the limit is the whole job's, so
    the process and the points of the cloud files ``clouds`` come first (counted from the files'
    headers where they have one, before reading), refused at once when they alone exceed it
    (``advice`` says what to do), the blocks in what is left (``sdp build``, ``mesh``, ``bool``)."""
    from .._core._memory import format_bytes
    from .._core._memory import memory_limit as limit
    from ..scale._budget import check_process_fits, untiled_point_bytes
    from ..scale._series import count_points

    cap = limit(memory_limit)
    counts = [count_points(c, format) for c in clouds if not is_field(c)]
    n = None if None in counts else sum(counts)
    held = untiled_point_bytes(n or 0)
    what = "the process itself" if not n else f"{n:,} points in memory with the process"
    check_process_fits(cap)  # the points are not what to change
    if held >= cap:
        raise GridTooLargeError(f"{', '.join(map(str, clouds))}: {what} need about {format_bytes(held)}, above the "
                                f"memory limit of {format_bytes(cap)}: {advice}, or raise the memory limit "
                                "(--memory-limit, $SDP_MEMORY_LIMIT)")
    try:
        yield cap - held
    except GridTooLargeError as exc:  # its limit was what the points and the process leave
        raise GridTooLargeError(f"{exc} (the {format_bytes(cap)} limit less {format_bytes(held)} for {what})") \
            from None


def _check_surface(fld, level: float, memory_limit, what: str) -> None:
    """Refuse, before marching cubes, a surface of ``fld`` that the memory limit can't hold with
    the process and the field (``sdp mesh``, ``sdp bool`` to a mesh)."""
    from .._core._memory import memory_limit as limit
    from ..fields._surface import check_surface, surface_bytes
    from ..scale._budget import PROCESS_BYTES

    check_surface(PROCESS_BYTES + fld.nbytes + surface_bytes(fld, level=level), limit(memory_limit), what)


def _left_out(path, name: str, n: int) -> str:
    """Why an NPZ's array ``name`` is not a per-point field (its length is not the points'), or ""."""
    if Path(path).suffix.lower() != ".npz":
        return ""
    with np.load(path, allow_pickle=False) as z:
        if name not in z.files or not z[name].ndim:
            return ""
        return f"; its array {name!r} holds {len(z[name]):,} values for {n:,} points"


def _field_or_points(path, format):
    """A field file loaded, or a cloud file's points (n, 3)."""
    from ..fields._density import DensityField

    return DensityField.load(path) if is_field(path) else read_points(path, format=format, fields=False).xyz


def _field(path, format, lattice: Lattice, memory_limit):
    """A field file loaded, or a cloud file's field built on ``lattice``."""
    from ..fields._density import DensityField

    if is_field(path):
        _no_lattice(lattice)
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
    lattice = as_options(Lattice, lattice, "lattice")
    execution = as_options(Execution, execution, "execution")
    check_outputs([output], [cloud])
    check_format(output, "field")
    if not is_store(output):
        execution.say_in_memory("a .zarr output")
        with _blocks_budget([cloud], format, execution.memory_limit,
                            "build a field store in tiles (-o FIELD.zarr)") as blocks:
            fld = _field(cloud, format, lattice, blocks)
        _save_field(fld, output, inputs=(cloud,))
        return fld
    from ..io._source import PointSource
    from ..scale._session import sampled_lattice
    from ..scale._tiles import build_field_tiled

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

    lattice = as_options(Lattice, lattice, "lattice")
    check_outputs([output], [path])
    check_format(output, "mesh")
    limit(memory_limit)
    if is_store(path):
        from ..scale._store import FieldStore

        _no_lattice(lattice)
        mesh = FieldStore.open(path).mesh(level=level, memory_limit=memory_limit)
    else:
        with _blocks_budget([path], format, memory_limit, "use a larger --voxel-size") as blocks:
            fld = _field(path, format, lattice, blocks)
        _check_surface(fld, level, memory_limit, f"{path}: its surface")
        mesh = fld.mesh(level=level)
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
    lattice = as_options(Lattice, lattice, "lattice")
    check_outputs([output], [a, b])
    check_format(output, "field", "mesh")
    limit(memory_limit)
    if is_store(output):
        from ..scale._store import FieldStore

        if not (is_store(a) and is_store(b)):
            raise SDPError("a .zarr output combines two .zarr field stores (build them with sdp build -o X.zarr)")
        _no_lattice(lattice)  # the stores' lattice wins: one given would be ignored
        return FieldStore.open(a).combine(FieldStore.open(b), operation, output)
    if is_store(a) or is_store(b):
        raise SDPError(f"{a if is_store(a) else b}: a .zarr field store combines with another one into a .zarr "
                       f"output (-o X.zarr); with a cloud or a .sdpf field, give the cloud it was built from")
    with _blocks_budget([a, b], format, memory_limit, "use a larger --voxel-size") as blocks:
        items = [_field_or_points(p, format) for p in (a, b)]
        like = next((x for x in items if isinstance(x, DensityField)), None)
        kw = _lattice(items, lattice, blocks, like)  # clouds are built on a given field's lattice, else on one from both
        fa, fb = (x if isinstance(x, DensityField) else DensityField.from_points(x, **kw) for x in items)
        result = getattr(boolean, operation)(fa, fb)
    if is_field(output):
        _save_field(result, output, inputs=(a, b))
        return result
    from ..errors import SurfaceError

    del items, like, fa, fb  # the operands: the surface is the result's alone
    _check_surface(result, 0.0, memory_limit, f"the surface of the {operation}")
    try:
        mesh = result.mesh()
    except SurfaceError:  # no --level here: the volume itself is empty (a difference of a cloud with itself)
        raise SurfaceError(f"the {operation} holds no volume (F ≥ 0 everywhere): there is no surface to write; "
                           "write the field (-o OUT.sdpf) to keep it") from None
    write_mesh(output, mesh, inputs=(a, b))
    return mesh


def describe_file(path, *, format: str | None = None) -> dict:
    """What ``sdp info`` prints: kind, size and parameters of a cloud, field (``.sdpf``) or field store."""
    from ..fields._density import DensityField

    if is_store(path):
        from ..scale._store import FieldStore

        st = FieldStore.open(path)
        return {"kind": "field store", "voxel_size": st.voxel_size, "sigma": st.sigma, "h": st.h,
                "tiles": len(st.tiles), "tile_blocks": st.tile_blocks, "blocks": st.n_blocks, "n_points": st.n_points}
    if is_field(path):
        f = DensityField.load(path)
        return {"kind": "field", "voxel_size": f.voxel_size, "sigma": f.sigma, "h": f.h, "blocks": f.n_blocks,
                "box_nodes": list(f.grid.shape), "origin": f.grid.origin.tolist(), "n_points": f.n_points,
                "method": f.method, "megabytes": f.nbytes / 2**20}
    from ..io._bag import bag_topics, is_bag

    if is_bag(path):  # a ROS bag: its point-cloud topics
        return {"kind": "ROS bag", "pointcloud2_topics": bag_topics(path)}
    c = read_points(path, format=format)
    info = {"kind": "cloud", "points": len(c), "dropped_non_finite": c.n_dropped,
            "min": c.xyz.min(0).tolist(), "max": c.xyz.max(0).tolist(), "fields": sorted(c.fields)}
    if c.sensor_origins is not None:
        info["sensors"] = c.sensor_origins.tolist()
    if c.image is not None:  # an organized frame: its image, and the camera its returns fit (or none)
        from .._core._pinhole import fit_camera

        camera = None if c.sensor_origin is None else fit_camera(c.xyz, c.pixels, c.image, c.sensor_origin)
        info["image"] = {"height": int(c.image[0]), "width": int(c.image[1]),
                         "pinhole": camera.describe() if camera is not None else None}
    if input_format(Path(path), format) == "e57":  # each scan's pose and grid, the points it kept
        from ..io._e57 import e57_scans

        scans = e57_scans(path)
        kept = np.bincount(np.asarray(c.fields["scan"], np.int64), minlength=len(scans))
        info["scans"] = [{**s, "kept": int(kept[s["scan"]])} for s in scans]
    return info


#: Outputs a 4x4 text matrix is not: binary point clouds, fields, meshes, pictures, pages.
_NOT_TEXT = (".ply", ".pcd", ".las", ".laz", ".npy", ".npz", ".e57", ".bag", ".sdpf", ".zarr", ".obj", ".stl", ".png",
             ".html")


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
    suffix = Path(output).suffix.lower()
    if suffix in _NOT_TEXT:
        raise SDPError(f"{output}: the transform is written as a 4x4 text matrix, not as {suffix}: give -o T.txt "
                       "(--aligned-output of sdp change writes the moved scan)")
    registration = Registration(method=method, fix_horizontal=fix_horizontal, align_class=align_class)
    ref = DensityField.load(reference) if is_field(reference) else read_points(reference, format=format)
    al = align_clouds(ref, read_points(current, format=format), (reference, current), registration)
    with atomic_path(output) as tmp:
        np.savetxt(tmp, al.matrix, fmt="%.12g", header=f"sdp align {current} onto {reference} ({method})")
    return al


def frame_files(folder) -> tuple[list[Path], list[Path]]:
    """(the frames of a folder, in natural name order, the files left out): the point-cloud files of
    its most common format. A recording's folder often holds its frames beside text of the same
    readers' formats (poses, timestamps, notes), which would be read as frames of a few points."""
    from collections import Counter

    from ..io._cloud import FORMATS, natural_key

    files = [p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in FORMATS]
    counts = Counter(p.suffix.lower() for p in files)
    if len(counts) > 1:
        (first, n), (_, m) = counts.most_common(2)
        if n == m:
            each = ", ".join(f"{k}: {v}" for k, v in sorted(counts.items()))
            raise SDPError(f"{folder}: holds as many {first} files as of another format ({each}): give a folder of "
                           "one format")
    kind = counts.most_common(1)[0][0] if counts else None
    frames = sorted((p for p in files if p.suffix.lower() == kind), key=natural_key)
    return frames, sorted(p for p in files if p.suffix.lower() != kind)


def watch_folder(reference, frames, *, format: str | None = None, lattice: Lattice | None = None,
                 update: str = DEFAULTS.update, window: int | None = None, decay: float | None = None,
                 min_region_points: int = DEFAULTS.min_region_points, align: Registration | str | None = None,
                 coverage: Coverage | None = None, topic: str | None = None, decision: str = DEFAULTS.decision,
                 noise: NoiseModel | None = None) -> Iterator:
    """:func:`sdp.watch` over the point-cloud files of a folder, in natural name order, or over
    the ``sensor_msgs/PointCloud2`` messages of a ROS bag's ``topic`` (:func:`sdp.io._bag.bag_frames`,
    the ``scans`` extra), in the order recorded (``sdp watch``).

    ``reference`` is a cloud file, a field (``.sdpf``) or a ROS bag's message on ``topic``
    (``TOPIC``: its first, ``TOPIC:N``: its N-th; the frames are then every message on ``TOPIC``,
    the reference's among them if it is the same bag); ``coverage`` as in
    :func:`compare_files` (its ``sensor_origin`` is the reference's); ``decision`` and ``noise`` as in
    :func:`sdp.watch`. The folder and the reference are checked and read
    now; the frames are read one by one as the returned iterator of :class:`~sdp.FrameChange`
    (named after their files) advances.
    """
    from ..io._cloud import FORMATS
    from ..stream._watch import watch

    from ..io._bag import bag_frames, is_bag, split_topic, topic_needed

    noise = NoiseModel.of(noise, decision)
    folder = Path(frames)
    bag = is_bag(folder)
    if bag and topic is None:
        raise topic_needed(folder)
    if topic is not None and not bag and not is_bag(reference):
        raise SDPError(f"{folder}: --topic reads a ROS bag (a .bag file, or a ROS 2 bag folder with metadata.yaml)")
    if bag and is_bag(reference) and format is not None:  # it would be ignored: the messages carry their layout
        raise SDPError("--format reads point-cloud files, not a ROS bag's messages (PointCloud2 says its own layout)")
    if bag and not is_bag(reference) and ":" in topic:  # every message is a frame: no N to pick
        raise SDPError(f"--topic {topic!r}: sdp watch reads every message of the bag; give TOPIC (TOPIC:N picks "
                       "the reference's message when the reference is a bag too)")
    if not bag and not folder.is_dir():
        raise SDPError(f"{folder}: not a folder of frames nor a ROS bag")
    paths = [] if bag else frame_files(folder)[0]
    if not bag and not paths:
        raise SDPError(f"{folder}: no point-cloud files ({', '.join(sorted(FORMATS))})")
    coverage = as_options(Coverage, coverage, "coverage")
    choice = coverage.sensor_origin
    if is_field(reference):
        from ..fields._density import DensityField

        if not (isinstance(choice, str) and choice in ("auto", "none")):
            raise SDPError("--sensor-origin follows the reference's rays: give the reference cloud, not a field")
        _no_lattice(as_options(Lattice, lattice, "lattice"))
        ref, origin = DensityField.load(reference), None
    else:  # a bag's message (--topic TOPIC: its first, TOPIC:N its N-th) or a cloud file
        ref = read_input(reference, format=format, topic=topic if is_bag(reference) else None)
        origin = sensor_origins(choice, (reference, ref), (reference, ref))
        origin = origin[0] if isinstance(origin, np.ndarray) else origin
    # an empty frame (a blinded sensor) is the stream's to report, not an error
    stream = bag_frames(folder, split_topic(topic)[0]) if bag else (
        (p.name, read_points(p, format=format, allow_empty=True)) for p in paths)
    if bag:
        stream = _bag_stream(ref, stream, f"{reference} ({topic})", f"{folder} ({split_topic(topic)[0]})",
                             one_frame=align is None)
    return watch(ref, stream, lattice=lattice, update=update, window=window, decay=decay,
                 min_region_points=min_region_points, align=align, coverage=replace(coverage, sensor_origin=origin),
                 decision=decision, noise=noise)


def _bag_stream(ref, stream, ref_name: str, bag_name: str, *, one_frame: bool):
    """The frames of a bag's ``stream``, each refused (:func:`same_frame`, with ``one_frame``) if it
    names another frame than ``ref``; what the bag's /tf did with them said once (a ReadNotice)."""
    from ..io._cloud import notice

    said = set()
    for name, cloud in stream:
        if one_frame and getattr(ref, "frame", None) is not None:  # a field names none
            same_frame(ref, cloud, (ref_name, f"{bag_name} frame {name}"))
        if cloud.tf is not None and cloud.tf not in said:
            said.add(cloud.tf)
            notice(f"{bag_name}: frames {cloud.tf} (from frame {name})")
        yield name, cloud


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
    ``"region"`` (sdp's too): a region's id (0, 1, …) is changed, -1 not; any other field, and
    ``truth_field``: nonzero is changed. Both files hold the same points
    in the same order.
    """
    from ..change._coverage import CHANGED, NOT_COMPARABLE, UNCHANGED
    from ..change._metrics import scores

    values, clouds = [], []
    for path, name in ((predicted, predicted_field), (truth, truth_field)):
        c = read_points(path, format=format)
        if name not in c.fields:
            raise SDPError(f"{path}: no per-point field {name!r} (fields: {', '.join(sorted(c.fields)) or 'none'})"
                           + _left_out(path, name, len(c.xyz) + c.n_dropped))
        v = np.asarray(c.fields[name])
        if v.ndim != 1:
            raise SDPError(f"{path}: field {name!r} holds {v.shape[1:]} values per point; give a field of one label "
                           "per point")
        if v.dtype.kind not in "biuf":
            raise SDPError(f"{path}: field {name!r} holds {v.dtype} values, not numeric labels")
        if v.dtype.kind == "f" and not np.isfinite(v).all():
            raise SDPError(f"{path}: field {name!r} has {int((~np.isfinite(v)).sum()):,} labels that are not numbers "
                           "(NaN or infinite)")
        if name == "change" and not np.isin(v, (UNCHANGED, CHANGED, NOT_COMPARABLE)).all():  # sdp's three states
            raise SDPError(f"{path}: field 'change' holds values other than 0 (unchanged), 1 (changed) and 2 (not "
                           f"comparable), e.g. {v[~np.isin(v, (0, 1, 2))][0].item()!r}")
        values.append(v)
        clouds.append(c)
    if len(values[0]) != len(values[1]):
        raise SDPError(f"{predicted} has {len(values[0]):,} points and {truth} {len(values[1]):,}: "
                       "they must be the same points in the same order")
    _check_same_points(clouds[0], clouds[1])
    if predicted_field == "change":  # sdp's field: 1 changed, 2 not comparable (scored apart)
        changed, comparable = values[0] == CHANGED, values[0] != NOT_COMPARABLE
    elif predicted_field == "region":  # sdp's field: a region's id (from 0), -1 none
        changed, comparable = values[0] >= 0, None
    else:  # any other field: nonzero is changed
        changed, comparable = values[0] != 0, None
    true = values[1] != 0
    sc = scores(true, changed, comparable=comparable)
    comparable = np.ones(len(true), bool) if comparable is None else comparable
    return Evaluation(sc, len(true), int(changed.sum()), int(true[comparable].sum()))


def _check_same_points(a, b) -> None:
    """Refuse two files whose points differ by more than their files' rounding: LAS keeps 1 mm
    (or its own scale), PLY and PCD float32 (a relative 6e-8), so a point may move by that much
    between a file and its labelled copy."""
    scale = max(float(np.abs(a.xyz).max()), float(np.abs(b.xyz).max()))
    tolerance = 1e-3 + 1e-6 * scale
    gap = np.abs(a.xyz - b.xyz).max(axis=1)
    worst = int(np.argmax(gap))
    if gap[worst] > tolerance:
        raise SDPError(f"{a.path} and {b.path} are not the same points in the same order (point {worst:,} is "
                       f"{gap[worst]:.4g} apart; {int((gap > tolerance).sum()):,} points differ)")


def render_file(path, *, png=None, html=None, field: str | None = None, format: str | None = None) -> list[str]:
    """Pictures of a labelled cloud (points whose ``field`` is nonzero in vermillion, NaN grey: no
    value; sdp's ``change``, the default: not comparable grey) or PNG slices of a field ``.sdpf``
    (``sdp render``; no ``field`` then); returns the files written. A ``.zarr`` store is refused."""
    if not (png or html):
        raise SDPError("nothing to write: give --png OUT.png and/or --html OUT.html")
    V.picture_path("png", png)
    V.picture_path("html", html)
    if is_store(path):  # read whole, a field store may not fit in memory: its surface is what shows it
        from ..timeseries._archive import is_series

        raise SDPError(f"{path}: a series archive is not rendered; `sdp series --report` draws one" if is_series(path)
                       else f"{path}: a field store (.zarr) is not rendered; `sdp mesh {path} -o SURFACE.ply` writes "
                            f"its surface, tile by tile")
    check_outputs([png, html], [path])
    if is_field(path):
        from ..fields._density import DensityField
        from ..viz._render import render_field

        if html:
            raise SDPError("--html draws clouds; for a field use --png (slices), or `sdp mesh` for its surface")
        if field is not None:
            raise SDPError(f"--field colours a cloud's points by one of their fields; a field ({path}) is drawn as "
                           f"slices of its density: give no --field")
        render_field(png, DensityField.load(path))
        return [str(png)]
    c = read_points(path, format=format)
    field = "change" if field is None else field
    if field not in c.fields:
        raise SDPError(f"{path}: no per-point field {field!r} to colour by "
                       f"(fields: {', '.join(sorted(c.fields)) or 'none'}); choose one with --field")
    values = np.asarray(c.fields[field])
    if field == "change":  # sdp's field: 0 unchanged, 1 changed, 2 not comparable
        state, what = values.astype(np.uint8), "changed vermillion, not comparable grey"
    else:  # NaN (no value: nothing measured there) is not comparable, not "≠ 0"
        state = np.where(values != 0, np.uint8(1), np.uint8(0))
        if values.dtype.kind == "f":
            state[~np.isfinite(values)] = 2
        what = f"{field} ≠ 0 in vermillion, NaN grey"
    with all_or_none():
        return pictures(png, html, c.xyz, state, f"{Path(path).name}: {what}")

