"""Many epochs against one reference: distances per epoch, appended, smoothed, grouped into objects.

:func:`series` measures every epoch against the reference at fixed core points, reusing the
reference's cells, normals and cylinders (:class:`sdp.distance.PreparedReference`): an epoch
costs reading it, summing it into cells and one cylinder per core point, and one write of its
row to the archive (:mod:`sdp.timeseries._archive`). Epochs are read one at a time, so the memory
is one epoch and the reference side whatever the number of epochs. With ``append=True`` only
the new epochs are measured, against the reference state stored in the archive, so the rows
equal those of a full run over all the epochs (tested bit for bit). Then, in blocks of core
points sized from the memory limit, the fixed-lag Kalman smoother (:mod:`sdp.timeseries._kalman`),
and epoch by epoch the onsets and the 4D objects (:mod:`sdp.timeseries._objects`): a full run
from the first epoch, an append from the state the archive saved ``lag`` epochs back (the
filter, the tracked objects, the inputs since), so that it rewrites ``lag + 1`` rows and the
result is that of a full run. The process noise comes from the first 2ⁿ epochs (all three of
three; :func:`_noise_epochs`): an append that reaches the next power of two estimates it again and
runs over the whole series.

Times: ``times`` (numbers, or ISO dates: velocities are then per day), else each file's own
(:func:`sdp.io._time.file_time`: LAS GPS time or creation date, E57 acquisition start, a ROS bag's first
``header.stamp``), else the
epochs' index; the archive records which.

References
----------
.. [1] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
   terrestrial laser scanner", ISPRS J. Photogramm. 82 (2013) (M3C2).
.. [2] L. Winiwarter et al., "Full four-dimensional change analysis of topographic point cloud
   time series using Kalman filtering", Earth Surf. Dynam. 11 (2023) 593–613.
.. [3] K. Anders et al., "Fully automatic spatiotemporal segmentation of 3D LiDAR time series
   for the extraction of natural surface changes", ISPRS J. Photogramm. 173 (2021) 297–308.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import math
import os
import re
import time
import warnings
from pathlib import Path

import numpy as np

from .._core._memory import check_memory
from .._core._memory import memory_limit as resolve_memory_limit
from .._core._points import as_points
from .._core._validate import auto_or_nonnegative, auto_or_positive, boolean, integer_at_least
from ..defaults import DEFAULTS
from ..distance._distances import _sensor_per_point
from ..distance._level import LEVEL_Z
from ..distance._reference import PreparedReference, subsample
from ..errors import InvalidOptionError, InvalidPointsError, SDPError
from ..fields._spacing import resolve_lattice
from ..io._bag import bag_epoch, topic_needed
from ..io._cloud import Cloud, is_bag
from ..io._output import check_outputs
from ..io._read import read_points
from ..io._time import file_time
from ..options import Cylinder, Execution, Registration, as_options
from ..scale._budget import PROCESS_BYTES, check_process_fits
from ..scale._series import CORE_BYTES, POINT_BYTES, count_points, plan_series
from . import _archive as A
from ._kalman import BYTES_PER_VALUE, FilterState, kalman, observation_variance, process_noise
from ._objects import OBJECT_FIELDS, Tracker, min_object_points

__all__ = ["series", "SERIES_FIELDS"]

#: The per-(epoch, point) arrays of an archive.
SERIES_FIELDS = ("distance", "lod", "significant", "smoothed", "velocity", "smoothed_sigma", "velocity_sigma",
                 "object")
_EPOCH_DIMS = ("epoch", "point")
#: Memory per point of an epoch measured while the next is read (:data:`sdp.scale._series.POINT_BYTES`)
#: and the next one's reading (its coordinates and the reader's buffers).
_AHEAD_BYTES = POINT_BYTES + 64.0
_DERIVED_EPOCHS = 16  # epochs per chunk of the smoothed arrays: an append rewrites lag + 1 rows (16 by default)


def _version() -> str:
    from .. import __version__

    return __version__


# ------------------------------------------------------------------ times
def _parse_time(value) -> tuple[float, str]:
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        if not math.isfinite(float(value)):
            raise InvalidOptionError(f"time {value!r} is not finite")
        return float(value), "number"
    if isinstance(value, _dt.datetime) and value.tzinfo is not None:  # NumPy keeps no zone: in UTC
        value = value.astimezone(_dt.timezone.utc).replace(tzinfo=None)
    if isinstance(value, (_dt.date, np.datetime64)):
        value = str(np.datetime64(value))
    text = str(value).strip()
    if not text or text.lower() == "nat":
        raise InvalidOptionError("a time is empty (two commas, or one at an end?): give one per epoch")
    try:
        number = float(text)
    except ValueError:
        pass
    else:
        if math.isfinite(number):
            return number, "number"
    # a zone (Z, +02:00) is taken off here and applied: NumPy applies it too, but warns that it
    # represents none
    zone = _ZONE.search(text) if re.search("[T ]", text, re.IGNORECASE) else None  # after a time only
    shift = 0
    if zone:
        text = text[:zone.start()]
        if zone.group(2):
            shift = (1 if zone.group(2) == "+" else -1) * (int(zone.group(3)) * 60 + int(zone.group(4) or 0))
    try:
        with warnings.catch_warnings():  # a zone left in the text (+2h) is not one of ours: refused
            warnings.simplefilter("error", UserWarning)
            # at its own unit, then microseconds: a fraction of a second is kept (float days hold microseconds)
            stamp = np.datetime64(text).astype("datetime64[us]") - np.timedelta64(shift, "m")
    except (ValueError, UserWarning):
        raise InvalidOptionError(f"time {value!r} is neither a number nor an ISO date (2024-05-01, "
                                 "2024-05-01T12:00 or 2024-05-01T12:00:00.5+02:00)") from None
    return float((stamp - np.datetime64("1970-01-01T00:00:00", "us")).astype(np.int64)) / 86_400e6, "date"


_ZONE = re.compile(r"(Z|([+-])(\d\d):?(\d\d)?)$", re.IGNORECASE)  # an ISO time's zone: Z, +02, +0200, +02:00


def parse_times(values) -> tuple[np.ndarray, str]:
    """(times as float64, "number" or "date": days since 1970-01-01) of numbers or ISO dates."""
    if isinstance(values, str):
        values = [v for v in values.split(",")]
    parsed = [_parse_time(v) for v in values]
    kinds = {k for _, k in parsed}
    if len(kinds) > 1:
        raise InvalidOptionError("times mix numbers and dates: give all as numbers or all as ISO dates")
    return np.array([t for t, _ in parsed], np.float64), kinds.pop() if kinds else "number"


def _resolve_times(epochs, times, *, start_index: int = 0, topic: str | None = None):
    """(times, kind, source, note) of the epochs: given, from the files, else their index; ``note``
    says why the files' own times were not used where some record one (None otherwise)."""
    if times is not None:
        t, kind = parse_times(times)
        if len(t) != len(epochs):
            raise InvalidOptionError(f"{len(t)} time(s) for {len(epochs)} epoch(s)")
        return t, kind, "given", None
    found = [file_time(e, topic=topic) for e in epochs]
    stamps = [f[0] for f in found if f is not None]
    if found and len(stamps) == len(found) and len(set(stamps)) == len(found):
        return np.array(stamps), "date", f"file ({', '.join(sorted({f[1] for f in found}))})", None
    note = None
    if stamps:  # some files are dated: say why their dates were not used
        undated = [_name(e, k) for k, (e, f) in enumerate(zip(epochs, found)) if f is None]
        if undated:
            note = (f"{len(stamps)} of {len(found)} files record a time, not {', '.join(undated[:3])}"
                    f"{' …' if len(undated) > 3 else ''}: the epochs are numbered (give --times to date them)")
        else:
            twice = next(x for x in stamps if stamps.count(x) > 1)
            note = (f"two files record the same time {A.show_time(twice, 'date')}: the epochs are numbered (give "
                    f"--times to date them)")
    return np.arange(start_index, start_index + len(epochs), dtype=np.float64), "number", "index", note


# ------------------------------------------------------------------ inputs
def _name(epoch, k: int) -> str:
    return str(epoch) if isinstance(epoch, (str, os.PathLike)) else f"array {k}"


@contextlib.contextmanager
def _naming(name: str):
    """A point error raised inside (too few points, none finite) says which epoch it is about."""
    try:
        yield
    except InvalidPointsError as e:
        raise InvalidPointsError(f"{name}: {e}") from None


def _load(epoch, fmt, topic: str | None = None, limit=None):
    """An epoch's cloud: a file read, a ROS bag's messages on ``topic`` merged (refused beyond
    ``limit`` before they are read), or the array or cloud given."""
    if isinstance(epoch, (str, os.PathLike)):
        if topic is not None and is_bag(epoch):
            return bag_epoch(epoch, topic, memory_limit=limit)
        return read_points(epoch, format=fmt, fields=False)
    return epoch


def _check_bags(epochs, topic: str | None, tiled: bool) -> None:
    """Refuse, before any work, ``topic`` without a bag among ``epochs``, a bag without ``topic`` (listing
    its topics), a message number (``TOPIC:N``) and tiles."""
    bags = [e for e in epochs if isinstance(e, (str, os.PathLike)) and is_bag(e)]
    if topic is not None and not bags:
        raise InvalidOptionError("--topic reads a ROS bag epoch (a .bag file, or a ROS 2 bag folder with "
                                 "metadata.yaml); no epoch is one")
    if bags and topic is None:
        raise topic_needed(bags[0])
    if bags and ":" in topic:  # sdp change's TOPIC:N picks a message; an epoch is all of them
        raise InvalidOptionError(f"--topic {topic!r}: a bag epoch is every message of the topic; give TOPIC, not "
                                 "TOPIC:N")
    if bags and tiled:
        raise InvalidOptionError(f"{bags[0]}: a ROS bag epoch is read whole, in memory: not with --tiled")


def _xyz(cloud) -> np.ndarray:
    return cloud.xyz if isinstance(cloud, Cloud) else as_points(cloud, name="epoch").xyz


def _core_name(core_points) -> str:
    return str(core_points) if isinstance(core_points, (str, os.PathLike)) else "given as an array"


def _core_xyz(cloud) -> tuple[np.ndarray, int]:
    """(the core points' finite rows, how many rows were left out for holding NaN or Inf)."""
    if isinstance(cloud, Cloud):
        return cloud.xyz, int(cloud.n_dropped)
    pts = as_points(cloud, name="core points")
    return pts.xyz, 0 if pts.finite is None else int((~pts.finite).sum())


def _same(a, b) -> bool:
    if isinstance(a, (int, float)) and isinstance(b, (int, float)):
        return math.isclose(float(a), float(b), rel_tol=1e-12, abs_tol=0.0)
    return a == b


def _check_append(archive: dict, given: dict, core_points, path: Path) -> None:
    """Refuse, in one line, options that differ from the archive's (repeating them is fine)."""
    for name, value in given.items():
        if value is None:
            continue
        kept, used = archive["given"].get(name), archive["used"].get(name)
        if not (_same(value, kept) or _same(value, used)):
            # named for both the command (--projection-scale) and Python (projection_scale)
            raise InvalidOptionError(f"{name.replace('_', ' ')} {value} differs from the archive's {kept} ({path}): "
                                     "an append keeps the archive's options")


def _aligned_on_stable_part(prepared, ref_xyz, cloud, xyz, registration, *, registration_error, memory_limit):
    """(the epoch aligned onto the reference, its points, its distances, the alignment's record):
    aligned on all its points, measured, then aligned again, from there, on its points away from
    the core points whose change was significant, and measured again (twice: the second round's
    stable part is the one the better alignment tells). Every point of an epoch
    pulls a rigid alignment, a creeping slope's too: 5 % of a facade creeping 14 mm moved the
    whole epoch by 0.8 mm, epoch after epoch, and the still facade read as change; a survey
    registers its epochs on their stable part (CloudCompare's ICP on a chosen subset, for one), which
    the first measurement tells here."""
    from ..registration._align import align as align_clouds  # SciPy's spatial module: only to align

    def measured(matrix):
        moved = cloud.transformed(matrix) if isinstance(cloud, Cloud) else None  # its sensors move with it
        pts = moved.xyz if moved is not None else xyz @ matrix[:3, :3].T + matrix[:3, 3]
        return moved if moved is not None else pts, pts, prepared.measure(
            moved if moved is not None else pts, registration_error=registration_error, memory_limit=memory_limit)

    options = dict(method=registration.method, fix_horizontal=registration.fix_horizontal)
    al = align_clouds(ref_xyz, xyz, **options)
    moved, pts, d = measured(al.matrix)
    record = {"matrix": al.matrix.tolist(), "rmse": float(al.rmse)}
    for _ in range(_STABLE_ROUNDS):
        changed = prepared.core_points[d.significant]
        if not len(changed):
            break
        # the epoch's points farther than a projection scale from every significant core point
        # (cells of that size: a point's own and its 26 neighbours')
        stable = ~_near(pts, changed, prepared.projection_scale)
        if stable.sum() < max(_MIN_STABLE, _STABLE_SHARE * len(pts)):
            break
        al = align_clouds(ref_xyz, xyz[stable], init=al.matrix, **options)
        moved, pts, d = measured(al.matrix)
        record = {"matrix": al.matrix.tolist(), "rmse": float(al.rmse), "stable_points": int(stable.sum())}
    return moved, pts, d, record


_STABLE_ROUNDS = 2  # alignments on the stable part, each on the part its predecessor's distances tell
_MIN_STABLE = 1_000  # points an alignment on the stable part needs at least, and
_STABLE_SHARE = 0.2  # the share of the epoch: less, and the first alignment stays


def _near(points: np.ndarray, centres: np.ndarray, size: float) -> np.ndarray:
    """Which ``points`` lie in a cube of side ``size`` holding one of ``centres`` or beside one
    (cubes ⌊p / size⌋ compared as rows of three integers: no packing to overflow)."""
    def rows(cells):
        return np.ascontiguousarray(cells).view([("x", np.int64), ("y", np.int64), ("z", np.int64)]).ravel()

    offsets = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    around = np.floor(centres / size).astype(np.int64)[:, None, :] + offsets[None]
    marked = np.unique(rows(around.reshape(-1, 3)))
    own = rows(np.floor(points / size).astype(np.int64))
    at = np.minimum(np.searchsorted(marked, own), len(marked) - 1)
    return marked[at] == own


def _read_ahead(epochs, fmt, *, skip: int, fits, tiled: bool, topic: str | None = None, limit=None):
    """Each epoch's points in turn (None for the epoch ``skip``, which the caller holds, and for
    every epoch with ``tiled``), the next file read on a thread while the caller measures this one
    when ``fits(its point count)``: the cylinders' kernels release the GIL and a file's decoding
    does for much of its time, so the reading overlaps the measuring (less so for LAZ, whose
    decompression keeps both cores busy by itself). Two epochs are then in memory at once."""
    from concurrent.futures import ThreadPoolExecutor

    def read(k):
        return None if tiled or k == skip else _load(epochs[k], fmt, topic, limit)

    def ahead(k):
        if tiled or k >= len(epochs) or k == skip or not isinstance(epochs[k], (str, os.PathLike)):
            return False
        n = count_points(epochs[k], fmt)
        return n is not None and fits(n)

    with ThreadPoolExecutor(1, thread_name_prefix="sdp-read") as pool:
        pending = None
        try:
            for k in range(len(epochs)):
                cloud = pending.result() if pending is not None else read(k)
                pending = pool.submit(read, k + 1) if ahead(k + 1) else None
                yield cloud
                del cloud
        finally:
            if pending is not None:
                pending.cancel()


# ------------------------------------------------------------------ the run
def series(epochs, *, output, append: bool = False, times=None, core_points=None, reference: int | None = None,
           cylinder: Cylinder | None = None, registration_error: float | str | None = None,
           align: Registration | str | None = None, orientation=None, execution: Execution | None = None,
           format: str | None = None, topic: str | None = None):
    """Signed distances of many epochs against one reference at fixed core points, in one Zarr
    archive, with their smoothed change, velocity, onsets and 4D objects of change.

    Parameters
    ----------
    epochs : sequence of path-like, array_like (n, 3) or Cloud
        The epochs in time order (files are read one at a time).
    output : path-like
        The archive (a ``.zarr`` folder), written all or nothing; replaced unless ``append``.
    append : bool
        Add ``epochs`` to the archive ``output``: only they are measured, against its reference,
        core points and parameters; the result equals a full run over all the epochs.
    times : sequence of numbers or ISO date strings, or "T1,T2,…", optional
        The epochs' times (strictly increasing; an append's come after the archive's last).
        Default: each file's recorded time (LAS GPS time or creation date, E57 acquisition start),
        else the epochs' index.
    core_points : path-like or array_like (m, 3), optional
        Where to measure; default the reference subsampled at the projection scale (one point per
        cube of d, the one nearest its cell's centroid). Stored in the archive (``x``, ``y``,
        ``z``); rows holding NaN or Inf are left out, and the archive's record says how many.
    reference : int, optional
        Index of the reference epoch among ``epochs`` (default 0, the first).
    cylinder : Cylinder, optional
        M3C2's scales as in :func:`sdp.distances` (``"auto"`` from the reference alone).
    registration_error : float or "auto", optional
        Added to each epoch's level of detection (M3C2's ``reg``). ``"auto"`` (default): measured
        on each epoch's stable part, after the alignment with ``align``
        (:mod:`sdp.distance._level`); the archive's ``registration_error`` (``epoch``) holds it.
    align : Registration, "density" or "gicp", optional
        Register each epoch onto the reference first.
    orientation : array_like (3,), optional
        Direction the normals point to (default +z).
    execution : Execution, optional
        The memory limit (an epoch, the reference side and the smoother's blocks are sized from it)
        and the tiles: with ``tiled`` True, or when an epoch or the reference would not fit the
        limit, the reference is prepared and every epoch measured in tiles on Dask
        (:mod:`sdp.scale._series`: the same numbers; ``"auto"`` scales from the reference's first
        slice; not with ``align``).
    format : str, optional
        Input format overriding the files' extensions.
    topic : str, optional
        The ``sensor_msgs/PointCloud2`` topic of the epochs that are ROS bags: each bag is one
        epoch, every message on the topic moved into ``map`` or ``odom`` with its ``/tf`` and
        merged, each message a scan position (:func:`sdp.io._bag.bag_epoch`); its time, unless
        given, the first message's ``header.stamp``. Needed when an epoch is a bag, refused otherwise.

    Returns
    -------
    xarray.Dataset
        The archive, opened (:func:`sdp.open_series`).

    Raises
    ------
    SDPError
        Bad options, epochs or times (before any work), an append whose options differ from the
        archive's, an epoch time already in the archive.

    References
    ----------
    .. [1] Lague et al. 2013 (M3C2); Winiwarter et al. 2023 (Kalman smoothing of change series);
       Anders et al. 2021 (4D objects by change).

    Examples
    --------
    >>> import numpy as np, sdp, tempfile, os
    >>> rng = np.random.default_rng(1)
    >>> ground = lambda dz: np.c_[rng.uniform(0, 4, (4000, 2)), dz + 0.002 * rng.standard_normal(4000)]
    >>> out = os.path.join(tempfile.mkdtemp(), "s.zarr")
    >>> ds = sdp.series([ground(0.0), ground(0.0), ground(0.05)], output=out,
    ...                 cylinder=sdp.Cylinder(projection_scale=0.5))
    >>> print(ds.sizes["epoch"], round(float(np.median(ds.distance[2])), 3))
    3 0.05
    """
    return A.open_series(write_series(epochs, output=output, append=append, times=times, core_points=core_points,
                                      reference=reference, cylinder=cylinder, registration_error=registration_error,
                                      align=align, orientation=orientation, execution=execution, format=format,
                                      topic=topic))


def write_series(epochs, *, output, append: bool = False, times=None, core_points=None, reference: int | None = None,
                 cylinder: Cylinder | None = None, registration_error: float | str | None = None,
                 align: Registration | str | None = None, orientation=None, execution: Execution | None = None,
                 format: str | None = None, topic: str | None = None, check=None, before_commit=None) -> Path:
    """:func:`series` without opening the archive: its path (the command opens it without Dask).
    ``check(epochs, core_points)``: called with the archive's counts after the run as soon as
    they are known, before any epoch is measured or anything written (what the command will
    export from the archive: its refusal leaves an archive as it was). ``before_commit(folder)``:
    called with the folder holding the archive's new version, complete, before it is committed
    (the command writes its exports from it: their failure leaves the archive as it was)."""
    A.require_zarr()
    t_start = time.perf_counter()  # after zarr's import, start-up like Python's
    append = boolean("append", append)  # a string "no" would read as True: the archive appended to, not replaced
    if isinstance(epochs, (str, os.PathLike)):  # list() would make a file name a list of letters
        raise InvalidOptionError(f"epochs must be a list of files or clouds, got one path {os.fspath(epochs)!r}")
    epochs = list(epochs)
    if not epochs:
        raise InvalidOptionError("no epochs given")
    execution = as_options(Execution, execution, "execution")
    limit = resolve_memory_limit(execution.memory_limit)
    check_process_fits(limit)
    _check_bags(epochs, topic, bool(execution.tiled))
    if not isinstance(output, (str, os.PathLike)):  # Path(3) is a raw TypeError
        raise InvalidOptionError(f"output must be the archive's path (a .zarr folder), got {output!r}")
    out = Path(output)
    files = [e for e in epochs if isinstance(e, (str, os.PathLike))]
    inputs = files + ([core_points] if isinstance(core_points, (str, os.PathLike)) else [])
    check_outputs([out], inputs)
    if out.exists() and not A.is_series(out):
        raise SDPError(f"{out}: exists and is not a series archive; choose another output name")
    if out.suffix.lower() != ".zarr" and not A.is_series(out):
        raise InvalidOptionError(f"{out}: a series archive is a Zarr folder; name it ….zarr")
    registration = Registration.of(align)
    if registration is not None and registration.classes is not None:  # it would be ignored
        raise InvalidOptionError("align_class (--align-class) is not available in a series, whose epochs are aligned "
                                 "on all their points: give the alignment's method alone")
    cylinder = None if cylinder is None else as_options(Cylinder, cylinder, "cylinder")
    if registration_error is not None:
        auto_or_nonnegative("registration_error", registration_error)
    given = {"projection_scale": None if cylinder is None else cylinder.projection_scale,
             "normal_scale": None if cylinder is None else cylinder.normal_scale,
             "max_distance": None if cylinder is None else cylinder.max_distance,
             "registration_error": registration_error,
             "align": None if registration is None else registration.method,
             # None unless asked for: archives written before it was recorded append as before
             "fix_horizontal": True if registration is not None and registration.fix_horizontal else None,
             "orientation": None if orientation is None else [float(v) for v in np.asarray(orientation).reshape(-1)],
             "reference": reference}
    if append:
        if not A.archive_exists(out):
            raise SDPError(f"{out}: no archive to append to; run without --append first")
        with A.writing(out):  # held to the end: no other run writes the archive meanwhile
            g = A.read_group(out)
            attrs = g.attrs.asdict()
            params = attrs["parameters"]
            _check_append(params, given, core_points, out)
            old_times = np.asarray([e["time"] for e in attrs["epochs"]], np.float64)
            by_index = times is None and all(e["time_source"] == "index" for e in attrs["epochs"])
            if by_index:  # the archive counts its epochs: the new ones go on counting, whatever their files say
                t_new = np.arange(len(old_times), len(old_times) + len(epochs), dtype=np.float64)
                kind, source, note = "number", "index", None
            else:
                t_new, kind, source, note = _resolve_times(epochs, times, start_index=len(old_times), topic=topic)
            if kind != attrs["time_kind"]:
                why = "their files record no date: give times (--times)" if times is None else "give dates"
                raise InvalidOptionError(f"the archive's epochs are dated and the new epochs' times are "
                                         f"{'indices' if source == 'index' else 'numbers'} ({why})"
                                         if attrs["time_kind"] == "date" else
                                         "the archive's epochs are numbered and the new epochs' times are dates "
                                         "(give numbers)")
            dup = np.intersect1d(t_new, old_times)
            if dup.size:
                raise InvalidOptionError(f"epoch time {A.show_time(dup[0], kind)} is already in the archive {out}")
            if t_new.min() <= old_times.max():
                raise InvalidOptionError(f"appended epochs must come after the archive's last time "
                                         f"{A.show_time(old_times.max(), kind)}")
            if np.any(np.diff(t_new) <= 0):
                raise InvalidOptionError("the times of the epochs must increase (and differ), in the order given")
            if core_points is not None:
                core = np.asarray(_core_xyz(_load(core_points, format))[0], np.float64)
                stored = np.c_[g["x"][:], g["y"][:], g["z"][:]]
                if core.shape != stored.shape or not np.array_equal(core, stored):
                    raise InvalidOptionError(f"the core points given differ from the archive's ({out})")
            if check is not None:
                check(len(old_times) + len(epochs), g["x"].shape[0])
            E = len(old_times) + len(epochs)  # rows smoothed: from the saved state (lag + 1 more), else all
            go_on = params.get("smoother", {}).get("estimated_from_epochs") == _noise_epochs(E)
            _check_smoother(g["x"].shape[0], min(E, len(epochs) + int(params["used"]["lag"]) + 1) if go_on else E,
                            limit)
            reg_opt = params["given"]["registration_error"]
            registration = Registration.of(params["given"]["align"])
            if registration is not None and params["given"].get("fix_horizontal"):
                registration = dataclasses.replace(registration, fix_horizontal=True)
            tiles = plan_series(epochs, reference=None, core_count=g["x"].shape[0], execution=execution,
                                format=format, align=registration is not None)
            if tiles is None:
                execution.say_in_memory()
            _run(epochs, out, t_new, kind, source, note=note, attrs=attrs, registration=registration, reg_opt=reg_opt,
                 limit=limit, fmt=format, t_start=t_start, tiles=tiles, before_commit=before_commit, topic=topic)
        return out
    if reference is None:
        reference = 0
    reference = integer_at_least("reference", reference, 0)
    if reference >= len(epochs):
        raise InvalidOptionError(f"reference {reference} is not an epoch (there are {len(epochs)})")
    cylinder = as_options(Cylinder, cylinder, "cylinder")  # the defaults where none was given
    t, kind, source, note = _resolve_times(epochs, times, topic=topic)
    if len(np.unique(t)) != len(t):
        twice = np.sort(t)[np.argmax(np.diff(np.sort(t)) == 0)]
        raise InvalidOptionError(f"two epochs have the time {A.show_time(twice, kind)}"
                                 f" ({source}): give distinct --times")
    if np.any(np.diff(t) <= 0):
        raise InvalidOptionError("the times of the epochs must increase, in the order given"
                                 + ("" if source == "given" else f" (read from the files: {source})"))
    reg_opt = DEFAULTS.registration_error if registration_error is None else registration_error

    core_count = 0 if core_points is None else count_points(core_points, format) or 0  # not read twice
    _check_smoother(core_count, len(epochs), limit)  # the given core points: before the reference is read
    tiles = plan_series(epochs, reference=reference, core_count=core_count, execution=execution, format=format,
                        align=registration is not None)
    if tiles is None:
        execution.say_in_memory()
    faced = None  # the sensors the normals face, where the reference's file records them
    if tiles is not None:  # the reference prepared tile by tile, its state assembled as in memory
        try:
            prepared = tiles.prepare(epochs[reference], core_points, cylinder=cylinder, orientation=orientation)
        except BaseException:
            tiles.close()
            raise
        ref_cloud = epochs[reference]
        core_source = (f"the reference subsampled at the projection scale ({prepared.projection_scale:.6g})"
                       if core_points is None else _core_name(core_points))
    else:
        ref_cloud = _load(epochs[reference], format, topic, limit)
        d_opt = auto_or_positive("projection_scale", cylinder.projection_scale)
        with _naming(_name(epochs[reference], reference)):
            ref_xyz = _xyz(ref_cloud)
            if d_opt == "auto":
                voxel, sigma_voxels = resolve_lattice([as_points(ref_xyz)], k=DEFAULTS.k)
                d_opt = 4.0 * sigma_voxels * voxel
        if core_points is None:
            core = ref_xyz[subsample(ref_xyz, d_opt)]
            core_source = f"the reference subsampled at the projection scale ({d_opt:.6g})"
        else:
            core, dropped = _core_xyz(_load(core_points, format))
            core_source = _core_name(core_points) + (f" ({dropped:,} rows holding NaN or Inf left out)"
                                                    if dropped else "")
        # the normals face the reference's sensors where its file records them, as sdp.distance's do
        origins = None if orientation is not None else getattr(ref_cloud, "sensor_origins", None)
        sensor = None if origins is None else _sensor_per_point(origins if len(origins) > 1 else origins[0],
                                                                ref_cloud, ref_xyz, core)
        if sensor is not None:
            faced = "towards the sensor" if len(origins) == 1 else "towards each point's scanner"
        prepared = PreparedReference.prepare(
            ref_xyz, core, cylinder=Cylinder(projection_scale=d_opt, normal_scale=cylinder.normal_scale,
                                             max_distance=cylinder.max_distance),
            orientation=orientation, memory_limit=limit, sensor=sensor)
    if check is not None or core_count == 0:
        try:
            _check_smoother(len(prepared.core_points), len(epochs), limit)
            if check is not None:
                check(len(epochs), len(prepared.core_points))
        except BaseException:
            if tiles is not None:
                tiles.close()
            raise
    arrays, scalars = prepared.state()
    used = {"projection_scale": prepared.projection_scale, "normal_scale": prepared.normal_scale,
            "max_distance": prepared.max_distance, "registration_error": reg_opt,
            "align": None if registration is None else registration.method,
            "orientation": faced or scalars["orientation"], "reference": reference, "lag": DEFAULTS.smoothing_lag}
    given_rec = dict(given, projection_scale=cylinder.projection_scale, normal_scale=cylinder.normal_scale,
                     max_distance=cylinder.max_distance, registration_error=reg_opt, reference=reference,
                     orientation=(faced or scalars["orientation"]) if orientation is None else given["orientation"])
    attrs = {"format": A.ARCHIVE_FORMAT, "format_version": A.ARCHIVE_VERSION, "sdp_version": _version(),
             "time_kind": kind, "epochs": [], "runs": [],
             "parameters": {"given": given_rec, "used": used, "reference_state": scalars,
                            "reference_file": _name(epochs[reference], reference), "core_points": core_source,
                            "min_object_points": min_object_points(prepared.core_points,
                                                                   prepared.projection_scale)}}
    with A.writing(out) if out.is_dir() else contextlib.nullcontext():  # an archive replaced: not while appended to
        _run(epochs, out, t, kind, source, note=note, attrs=attrs, registration=registration, reg_opt=reg_opt,
             limit=limit, fmt=format, t_start=t_start, prepared=prepared, state=arrays,
             ref_cloud=(reference, ref_cloud), tiles=tiles, before_commit=before_commit, topic=topic)
    return out


def _random_sd(d) -> float | None:
    """The median random part of an epoch's level (its level of detection without the registration
    error, over 1.96): what an epoch's registration error is weighed against in the summary."""
    if not d.comparable.any():
        return None
    return float(np.median(d.lod[d.comparable]) / LEVEL_Z - d.registration_error)


def _run(epochs, out: Path, t_new, kind, source, *, note=None, attrs, registration, reg_opt, limit, fmt, t_start,
         prepared=None, state=None, ref_cloud=None, tiles=None, before_commit=None, topic=None):
    append = prepared is None
    timings = {}
    params = attrs["parameters"]
    n_old = len(attrs["epochs"])
    E = n_old + len(epochs)
    first_epochs = _noise_epochs(E)
    go_on = append and params.get("smoother", {}).get("estimated_from_epochs") == first_epochs
    filt, tracked, recent = A.read_state(out) if go_on else (None, None, None)
    untouched = None
    if append:
        untouched = A.untouched_by_append(rows=n_old, rewritten_from=max(filt.epoch, 0) if go_on else 0,
                                          epochs_per_chunk=_DERIVED_EPOCHS)
    with tiles or contextlib.nullcontext(), A.transaction(out, untouched=untouched) as folder, A.many_chunks_at_once():
        w = A.Writer(folder, create=not append)
        if append:
            # an archive written before the reference's centroid across the axis was kept has none
            state = w.read_all([name for name in A.REFERENCE_SIDE if (Path(folder) / name).is_dir()])
            arrays = {"core_points": np.c_[state["x"], state["y"], state["z"]],
                      "normal": np.c_[state["normal_x"], state["normal_y"], state["normal_z"]],
                      **{k: state[k] for k in ("ref_mean", "ref_spread", "ref_count", "ref_level")}}
            if "ref_across_var" in state:
                arrays.update(ref_across=np.c_[state["ref_across_x"], state["ref_across_y"], state["ref_across_z"]],
                              ref_across_var=state["ref_across_var"])
            if "ref_front" in state:  # an archive from before it: no surface found in front is measured there
                arrays["ref_front"] = state["ref_front"]
            prepared = PreparedReference.from_state(arrays, params["reference_state"])
            w.resize_all({name: (E, len(prepared.core_points))
                          for name in ("distance", "lod", "significant") + (A.REWRITTEN if go_on else ())})
        else:
            m = len(prepared.core_points)
            w.write_all({**{axis: (state["core_points"][:, a], ("point",), None) for a, axis in enumerate("xyz")},
                         **{f"normal_{axis}": (state["normal"][:, a], ("point",), None)
                            for a, axis in enumerate("xyz")},
                         **{name: (state[name], ("point",), None)
                            for name in ("ref_mean", "ref_spread", "ref_count", "ref_level", "ref_across_var",
                                         "ref_front")},
                         **{f"ref_across_{axis}": (state["ref_across"][:, a], ("point",), None)
                            for a, axis in enumerate("xyz")}})
            for name, dtype in (("distance", "f4"), ("lod", "f4"), ("significant", "bool")):
                w.array(name, (len(epochs), m), dtype, _EPOCH_DIMS)
        m = len(prepared.core_points)
        ref_var = state["ref_spread"] ** 2 / state["ref_count"]  # the reference's part of each level
        ref_xyz = None
        if registration is not None:
            ref_xyz = _xyz(ref_cloud[1]) if ref_cloud is not None else _xyz(_load(attrs["parameters"]["reference_file"],
                                                                                   fmt, topic, limit))
        t0 = time.perf_counter()
        # rows are written a few epochs at a time (one call writes their chunks together)
        flush = int(max(1, min(len(epochs), 64, (limit / 16.0) // max(9.0 * m, 1.0))))
        buffered: list = []
        # the new rows of distance and lod also kept for the smoother when they take little memory
        fresh: list | None = [] if 8.0 * len(epochs) * m <= limit / 16.0 else None

        def write_rows():
            if buffered:
                a = n_old + buffered[0][0]
                rows = (slice(a, a + len(buffered)), slice(None))
                w.set_all({name: (rows, np.stack([r[c] for r in buffered]))
                           for c, name in enumerate(("distance", "lod", "significant"), start=1)})
                if fresh is not None:
                    fresh.extend(r[1:3] for r in buffered)
                buffered.clear()

        ref_k = ref_cloud[0] if ref_cloud is not None else -1
        with contextlib.closing(_read_ahead(epochs, fmt, skip=ref_k, tiled=bool(tiles), topic=topic, limit=limit,
                                            fits=lambda n: _AHEAD_BYTES * n + CORE_BYTES * m <= limit)) as loaded:
            for k, (epoch, cloud) in enumerate(zip(epochs, loaded)):
                row = n_old + k
                is_ref = k == ref_k
                cloud = ref_cloud[1] if is_ref else (epoch if tiles else cloud)
                record = {"file": _name(epoch, row), "time": float(t_new[k]), "time_source": source}
                with _naming(record["file"]):
                    xyz = None if tiles else _xyz(cloud)  # in tiles the epoch is read slice by slice
                reg = reg_opt
                if tiles:
                    d, n_points = tiles.measure(prepared, cloud, registration_error=reg, reference=is_ref)
                elif registration is not None and not is_ref:
                    with _naming(record["file"]):
                        cloud, xyz, d, record["alignment"] = _aligned_on_stable_part(
                            prepared, ref_xyz, cloud, xyz, registration, registration_error=reg, memory_limit=limit)
                    n_points = len(xyz)
                else:
                    # a cloud that knows its sensors: no distance where they could not see the core point
                    epoch_points = cloud if isinstance(cloud, Cloud) else xyz
                    with _naming(record["file"]):
                        d = prepared.measure(epoch_points, registration_error=reg, memory_limit=limit)
                    n_points = len(xyz)
                buffered.append((k, d.distance.astype(np.float32), d.lod.astype(np.float32), d.significant))
                if len(buffered) >= flush:
                    write_rows()
                record.update(registration_error=float(d.registration_error),
                              registration_source=d.registration_source, points=int(n_points),
                              comparable=int(d.comparable.sum()), significant=int(d.significant.sum()),
                              random_sd=_random_sd(d))
                attrs["epochs"].append(record)
                del cloud, xyz, d
        write_rows()
        if tiles:
            tiles.close()  # the cluster's workers are not needed by the smoother
        timings["epochs"] = time.perf_counter() - t0
        times = np.array([e["time"] for e in attrs["epochs"]])
        reg = np.array([e["registration_error"] for e in attrs["epochs"]])
        time_attrs = {"units": "days since 1970-01-01"} if kind == "date" else {}
        w.update_all({"time": (times, ("epoch",), time_attrs), "registration_error": (reg, ("epoch",), None)})
        lag = int(params["used"]["lag"])
        t0 = time.perf_counter()
        fresh = None if fresh is None else tuple(map(np.stack, zip(*fresh)))
        q, info, held, filt, step, recent = _smooth_all(w, E, m, times, reg, ref_var, limit, lag=lag,
                                                        first_epochs=first_epochs,
                                                        reference=int(params["used"].get("reference", 0)),
                                                        frozen=params["smoother"] if go_on else None, state=filt,
                                                        recent=recent, fresh=fresh)
        timings["smoother"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        xyz = prepared.core_points
        r0 = info.pop("first_row")
        min_points = params["min_object_points"]
        if go_on:
            tracker = Tracker.from_state(xyz, tracked, min_points=min_points)
        else:
            tracker = Tracker(xyz, min_points=min_points)
            w.array("object", (E, m), "i4", _EPOCH_DIMS, epochs_per_chunk=_DERIVED_EPOCHS)
        rows: dict = {}  # epochs read a chunk row at a time

        def read(k):
            if held is not None:  # the rows are in memory: no read
                sm, sd, vel = (a[k - r0].astype(np.float64) for a in held[:3])
                unseen = held[3][k - r0]
            else:
                a = k - k % _DERIVED_EPOCHS
                if a not in rows:
                    rows.clear()
                    rows[a] = [w[n][a:a + _DERIVED_EPOCHS] for n in ("smoothed", "smoothed_sigma", "velocity")]
                sm, sd, vel = (r[k - a].astype(np.float64) for r in rows[a])
                unseen = ~np.isfinite(w["distance"][k])
            # a core point without a distance at this epoch was not seen: its smoothed value there is
            # the smoother's guess, and not seen is not changed (in no object, no onset)
            sd[unseen] = np.nan
            return sm, sd, vel

        saved = tracker.state() if E - 1 - lag < tracker.epoch + 1 else None
        labels = []
        for k in range(tracker.epoch + 1, E):
            if k == E - 1 - lag:  # the rows from here are not final yet: the next run goes on from here
                saved = tracker.state()
            labels.append(tracker.add(k, *read(k), step))
            if (k + 1) % _DERIVED_EPOCHS == 0 or k == E - 1:  # whole chunk rows: each written once
                w.set_all({"object": ((slice(k + 1 - len(labels), k + 1), slice(None)), np.stack(labels))})
                labels.clear()
        table = tracker.table(times)
        A.write_state(folder, filt, saved, recent)
        small = {"onset": (tracker.onset.astype(np.int32), ("point",),
                           {"meaning": "epoch the change starts, -1: none"}),
                 "onset_kind": (tracker.onset_kind.astype(np.int8), ("point",),
                                {"meaning": "0 none, 1 step, 2 gradual"}),
                 "object_id": (np.arange(1, len(table["object_start"]) + 1, dtype=np.int32), ("object_id",), None)}
        small.update({name: (np.asarray(table[name]), ("object_id",), time_attrs if name.endswith("_time") else None)
                      for name in OBJECT_FIELDS})
        w.update_all(small)
        timings["objects"] = time.perf_counter() - t0
        rate_unit = "per day" if kind == "date" else "per time unit"
        attrs["parameters"]["smoother"] = {
            "model": "constant velocity, white-noise acceleration", "process_noise": q,
            "process_noise_reason": "robust spread of the standardised second differences equal to one",
            "observation_noise": "(lod / 1.96)^2 per epoch and core point without the reference's part "
                                 "(ref_spread^2 / ref_count), which is added once to smoothed_sigma^2",
            "step_k": 4.0, "velocity": rate_unit, "lag": lag,
            "lag_reason": "an epoch is smoothed with the lag epochs after it; older epochs are final",
            **info}
        attrs["parameters"]["objects"] = {"neighbour_radius": table["radius"],
                                          "area_per_point": table["area_per_point"],
                                          "rule": "|smoothed| > 1.96 smoothed_sigma, same sign, connected in space "
                                                  "(radius) and tracked forward in time (consecutive epochs); an "
                                                  "object from min_object_points changed together"}
        timings["total"] = time.perf_counter() - t_start
        attrs["runs"].append({"when": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                              "sdp_version": _version(), "added": len(epochs), "append": append,
                              "timings": {k: round(v, 4) for k, v in timings.items()},
                              **({"times_note": note} if note else {}),
                              **({"tiled": tiles.record()} if tiles else {})})
        w.finish(attrs)
        if before_commit is not None:
            before_commit(folder)


#: A column's float32 inputs (distance, lod: 8 B) and results (four arrays: 16 B) per epoch and
#: core point, and Zarr's copies while it writes them all at once (the chunks merged, read back
#: where a row is partly rewritten, and encoded: 4.6 times the results, measured on an append of
#: 200,000 core points).
_COLUMN_BYTES = 96
#: What the end of a run holds per core point whatever the number of epochs, beside the smoother's
#: blocks and columns: the reference side (the prepared reference and its sorted copy, or an
#: append's arrays read from the archive, 160–250 B), the filter's state, its saved copy and the
#: epochs' inputs since it (180 B + 8 B per epoch of the lag), the tracker's neighbour pairs and
#: state (200 B), and the objects' stage: a chunk row (16 epochs) of three smoothed arrays (192 B),
#: the labels, stacked and written (400 B). Measured: 200,000 core points, 20 epochs.
END_CORE_BYTES = 1500
#: What the end of a run holds beside the process (:data:`~sdp.scale._budget.PROCESS_BYTES`) whatever
#: the core points: Zarr's event loop, its codecs' threads and buffers (measured: 48,000 and 200,000
#: core points peaked 273 MiB + 1,235 B per core point).
_END_BYTES = 64 * 2**20
_MIN_BLOCK = 256  # core points per block of the smoother at least (its kernel takes 64 per task)


def _smoother_budget(limit: float, m: int) -> float:
    """Bytes of each of the smoother's two shares (the block's working memory, the column's inputs
    and results): half of what the memory limit leaves beside the process and the end of the run's
    arrays per core point."""
    return (limit - PROCESS_BYTES - _END_BYTES - END_CORE_BYTES * m) / 2.0


def _check_smoother(m: int, rows: int, limit: float) -> None:
    """Refuse, before any work, a run whose end (the smoother over ``rows`` rows of ``m`` core points,
    the objects and the archive) would not fit the memory limit even in blocks of
    :data:`_MIN_BLOCK` core points: the message names the smallest limit that does."""
    need = (PROCESS_BYTES + _END_BYTES + END_CORE_BYTES * m
            + 2.0 * _MIN_BLOCK * rows * max(BYTES_PER_VALUE, _COLUMN_BYTES))
    check_memory(need, f"smoothing {m:,} core points over {rows:,} epochs", limit,
                 advice="measure at fewer core points (--core-points)")


def _noise_epochs(E: int) -> int:
    """How many of a series' ``E`` first epochs the smoother's noise is estimated from: the first
    2ⁿ (n as large as there are), so that an append between two powers of two filters on from the
    saved state and rewrites ``lag + 1`` rows, and one reaching the next power estimates again and
    runs over the whole series; three of three, as two epochs hold no second difference (an
    append to three epochs runs over all of them anyway)."""
    return E if E == 3 else 2 ** int(math.floor(math.log2(E)))


def _smooth_all(w, E: int, m: int, times: np.ndarray, reg: np.ndarray, ref_var: np.ndarray, limit: float, *,
                lag: int, first_epochs: int, reference: int, frozen: dict | None, state: FilterState | None,
                recent=None, fresh=None):
    """The smoother over blocks of core points (their number from the memory limit), from the
    saved filter ``state`` (an append) or the first epoch; the noise ``frozen`` (an append's) or
    estimated from the first ``first_epochs`` epochs. Returns (q, info, the rows written of
    (smoothed, smoothed_sigma, velocity) and where they had no distance if one block held them, else None, the filter state to
    save, each point's first step). ``reg``: each epoch's registration error; ``ref_var``: each
    core point's reference variance (ref_spread² / ref_count), added to every row's smoothed variance
    but the ``reference`` epoch's, whose distance to itself is exactly 0 (pinned by the smoother).
    ``fresh``: this run's rows of distance and lod, if kept (else read from the archive)."""
    names = ("smoothed", "velocity", "smoothed_sigma", "velocity_sigma")
    f = -1 if state is None else state.epoch
    r0, a0 = max(f, 0), f + 1  # the first row written, the first epoch read
    if state is None:
        for name in names:
            w.array(name, (E, m), "f4", _EPOCH_DIMS, epochs_per_chunk=_DERIVED_EPOCHS, rewritten=True)
        state = FilterState.start(m)
    else:
        w.resize_all({name: (E, m) for name in names})
    R = E - r0
    dist, lod = w["distance"], w["lod"]
    # the inputs from epoch a0 on: an append's older ones kept with the state, the new ones read
    recent = (np.zeros((0, m), np.float32),) * 2 if recent is None else recent
    a1 = a0 + len(recent[0])
    if fresh is not None and a1 != E - len(fresh[0]):  # a run over the whole series reads the older rows too
        fresh = None

    def inputs(a, b):
        new = (dist[a1:, a:b], lod[a1:, a:b]) if fresh is None else (fresh[0][:, a:b], fresh[1][:, a:b])
        if not len(recent[0]):
            return new
        return np.concatenate([recent[0][:, a:b], new[0]]), np.concatenate([recent[1][:, a:b], new[1]])

    budget = _smoother_budget(limit, m)  # a block of _MIN_BLOCK fits: checked before the run (_check_smoother)
    block = int(max(_MIN_BLOCK, min(m, budget // (R * BYTES_PER_VALUE))))
    whole = None
    col = m
    if block >= m:  # the rows fit: read them once
        whole = inputs(0, m)
    else:
        # columns of whole chunks of the results, written once (a block narrower than a chunk would read and
        # rewrite each chunk once per block; the inputs' wider row chunks are only read again), its inputs and
        # results in float32 and their writing (_COLUMN_BYTES) in the other share; else blocks of whole chunks, or
        # narrower ones read again per block
        col = int(budget // (R * _COLUMN_BYTES)) // A.POINT_CHUNK * A.POINT_CHUNK
        if col < A.POINT_CHUNK:
            if block >= A.POINT_CHUNK:
                block -= block % A.POINT_CHUNK
            col = block
    if frozen is None:
        # q from a sample of core points spread over the first epochs (the median needs no more)
        sample = np.arange(0, m, max(1, m // max(1, 200_000 // first_epochs)))
        if whole is not None and a0 == 0:  # the first epochs are in memory
            zs, ls = whole[0][:first_epochs, sample], whole[1][:first_epochs, sample]
        else:
            zs = dist.get_orthogonal_selection((slice(0, first_epochs), sample))
            ls = lod.get_orthogonal_selection((slice(0, first_epochs), sample))
        vs = observation_variance(ls, reg[:first_epochs], ref_var[sample])
        q = process_noise(zs.astype(np.float64), vs, times[:first_epochs])
        good = np.isfinite(vs) & (vs > 0)
        scale = float(np.sqrt(np.median(vs[good]))) if good.any() else 1.0  # one diffuse start for every block
        dt = float(np.median(np.diff(times[:first_epochs]))) if first_epochs > 1 else 1.0
    else:
        q, scale, dt = frozen["process_noise"], frozen["diffuse_scale"], frozen["diffuse_dt"]
    step = np.full(m, -1, np.int32)
    saved = []
    held = None
    # the reference's row among those written: where it has a distance (0 to itself), the smoother pinned it
    ref_row = reference - r0 if r0 <= reference < E else None
    ref_seen = np.isfinite(dist[reference]) if ref_row is not None else None
    for a in range(0, m, col):
        b = min(m, a + col)
        zc, lc = whole if whole is not None else inputs(a, b)
        results = [np.empty((R, b - a), np.float32) for _ in names]
        for c in range(0, b - a, block):
            d = min(b - a, c + block)
            z = zc[:, c:d].astype(np.float64)
            var = observation_variance(lc[:, c:d], reg[a0:], ref_var[a + c:a + d])
            sm, vel, ssd, vsd, step[a + c:a + d], kept = kalman(z, var, times, q, lag=lag, scale=scale, dt=dt,
                                                                state=state.columns(a + c, a + d),
                                                                reference=reference)
            shared = np.broadcast_to(ref_var[a + c:a + d], ssd.shape).copy()  # the reference's error, in every epoch
            if ref_row is not None:
                shared[ref_row, ref_seen[a + c:a + d]] = 0.0  # but the reference's own
            ssd = np.sqrt(ssd**2 + shared)
            for out, v in zip(results, (sm, vel, ssd, vsd)):
                out[:, c:d] = v
            saved.append(kept)
        w.set_all({name: ((slice(r0, E), slice(a, b)), v) for name, v in zip(names, results)})
        if whole is not None:  # and where each row's core points had no distance (from the first epoch read)
            unseen = np.zeros((R, m), bool)
            unseen[a0 - r0:] = ~np.isfinite(whole[0])
            held = (results[0], results[2], results[1], unseen)
    filt = FilterState(saved[0].epoch, np.concatenate([s.x for s in saved]), np.concatenate([s.seen for s in saved]),
                       np.concatenate([s.step for s in saved]))
    # the inputs after the saved epoch, for the next run
    keep = filt.epoch + 1
    if whole is not None:
        recent = whole[0][keep - a0:], whole[1][keep - a0:]
    else:
        recent = inputs(0, m) if keep == a0 else (dist[keep:], lod[keep:])
    info = {"block_points": block, "core_points_with_step": int((step >= 0).sum()), "first_row": r0,
            "estimated_from_epochs": first_epochs, "diffuse_scale": scale, "diffuse_dt": dt}
    return float(q), info, held, filt, step, recent
