"""``sdp series`` as a function: many epochs against one reference, into one archive, files to files.

References
----------
.. [1] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
   terrestrial laser scanner", ISPRS J. Photogramm. 82 (2013) (M3C2).
.. [2] L. Winiwarter et al., "Full four-dimensional change analysis of topographic point cloud
   time series using Kalman filtering", Earth Surf. Dynam. 11 (2023) 593–613.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InvalidOptionError, SDPError
from ..io._output import all_or_none, atomic_path, check_format, check_outputs
from ..options import Execution, Outputs, as_options
from ._text import series_text

__all__ = ["SeriesRun", "series_files", "describe_series", "point_table"]


@dataclass
class SeriesRun:
    """What :func:`series_files` measured and wrote."""

    archive: str
    dataset: object  # xarray.Dataset, opened for the exports; None when there were none
    summary: dict
    outputs: list = field(default_factory=list)

    def summary_text(self) -> str:
        return series_text(self.summary)


def _epoch_index(text: str, n: int) -> int:
    try:
        k = int(text)
    except ValueError:
        raise InvalidOptionError(f"--epoch-output wants K:FILE with K an epoch index, got {text!r}") from None
    if not -n <= k < n:
        raise InvalidOptionError(f"--epoch-output {k}: the archive has epochs 0..{n - 1}")
    return k % n


def _point_list(text: str | None) -> list[int] | None:
    if text is None:
        return None
    try:
        return [int(v) for v in str(text).split(",") if v.strip()]
    except ValueError:
        raise InvalidOptionError(f"--points wants core point indices I,J,..., got {text!r}") from None


def series_files(epochs, *, output, append: bool = False, times=None, options: dict | None = None,
                 execution: Execution | None = None, outputs: Outputs | None = None,
                 exports: dict | None = None) -> SeriesRun:
    """Distances of many epochs against one reference in one archive, smoothed, with objects of
    change: ``sdp series`` as a function (see :func:`sdp.series`).

    Parameters
    ----------
    epochs : sequence of path-like
        The epochs' files, in time order.
    output : path-like
        The archive (``.zarr``).
    append, times, execution
        As :func:`sdp.series` (``times`` also "T1,T2,…").
    options : dict, optional
        The other keywords of :func:`sdp.series`: ``core_points`` (a file), ``reference``,
        ``cylinder``, ``registration_error``, ``align``, ``orientation``, ``format``, ``topic`` (the
        PointCloud2 topic of the epochs that are ROS bags, each bag one epoch).
    outputs : Outputs, optional
        ``report``: one HTML page (maps of total change and velocity, the largest objects' series,
        the object table, the parameters with their reasons); ``field_names``: the exports' names
        of the fields CloudCompare's M3C2 or PDAL's ``filters.m3c2`` also write (distance, level
        of detection, significance, normal), as ``sdp distance`` names them.
    exports : dict, optional
        ``epochs``: list of (epoch index, file): that epoch's distances, smoothed change, velocity
        and object per core point (.las, .laz, .ply, .npz, as ``sdp distance`` writes them);
        ``points``: (file, indices or None): per-point series as CSV or Parquet (default: the
        core point of each of the five largest objects with the largest change).

    Returns
    -------
    SeriesRun

    References
    ----------
    .. [1] Lague et al. 2013 (M3C2); Winiwarter et al. 2023 (Kalman smoothing).
    """
    from ..timeseries._archive import open_series, open_version
    from ..timeseries._compute import write_series

    outputs = as_options(Outputs, outputs, "outputs").only("sdp series", "report", "field_names")
    execution = as_options(Execution, execution, "execution")
    exports = {} if exports is None else exports
    options = dict(options or {})
    unknown = set(options) - {"core_points", "reference", "cylinder", "registration_error", "align", "orientation",
                              "format", "topic"}
    if unknown:
        raise InvalidOptionError(f"series_files: unknown option(s) {sorted(unknown)}")
    core_points = options.get("core_points")
    epochs = [str(e) for e in epochs]
    inputs = epochs + ([core_points] if core_points else [])
    epoch_files = list(exports.get("epochs") or [])
    points = exports.get("points")
    report = outputs.report
    for _, f in epoch_files:
        check_format(f, "points")
    if points is not None and Path(points[0]).suffix.lower() not in (".csv", ".parquet"):
        raise InvalidOptionError(f"{points[0]}: per-point series are written as .csv or .parquet")
    if points is not None and Path(points[0]).suffix.lower() == ".parquet":
        import importlib.util

        if importlib.util.find_spec("pyarrow") is None:
            raise SDPError(f"{points[0]}: Parquet needs pyarrow (pip install 'sdp[parquet]'); or write .csv")
    check_outputs([output, report, *(f for _, f in epoch_files), points[0] if points else None], inputs)
    if report:
        from ..viz._report import require_extras

        require_extras()
    chosen_points = _point_list(points[1]) if points is not None else None

    def check(n_epochs, n_points):  # the exports' indices, before the archive is touched
        for k_text, _ in epoch_files:
            _epoch_index(str(k_text), n_epochs)
        bad = [p for p in chosen_points or () if not 0 <= p < n_points]
        if bad:
            raise InvalidOptionError(f"--points {bad[0]}: the archive has core points 0..{n_points - 1}")

    exported = bool(epoch_files) or points is not None or bool(report)
    written = [str(output)]

    def export(folder):
        # from the archive's new version before its commit, under temporary names renamed after it:
        # an export that fails (a full disk) leaves the archive as it was, and the command wrote nothing.
        # The dataset only for exports (importing xarray and pandas is much of a job's start-up); without
        # Dask's arrays: the command reads the rows and columns it indexes, and importing them costs more
        ds = open_version(folder)
        summary = describe_series(Path(output), version=folder)
        like = _core_records(ds, execution.memory_limit) if epoch_files else None
        for k_text, f in epoch_files:
            _write_epoch(ds, _epoch_index(str(k_text), summary["epochs"]), f, inputs, outputs.field_names, like)
            written.append(str(f))
        if points is not None:
            _write_points(ds, points[0], chosen_points, inputs, outputs.field_names)
            written.append(str(points[0]))
        if report:
            from ..viz._report import series_report

            chosen = chosen_points if chosen_points is not None else default_points(ds)
            series_report(report, ds, summary=summary, points=chosen[:5])
            written.append(str(report))

    t0 = time.perf_counter()
    with all_or_none():
        archive = write_series(epochs, output=output, append=append, times=times, execution=execution, check=check,
                               before_commit=export if exported else None, **options)
    summary = describe_series(archive)
    ds = open_series(archive, chunks=None) if exported else None
    summary["outputs"] = written
    summary["seconds"] = round(time.perf_counter() - t0, 4)
    return SeriesRun(str(output), ds, summary, written)


def _core_records(ds, memory_limit=None):
    """The LAS/LAZ records of the core points (a :class:`~sdp.Cloud` of them alone), for the
    epochs' exports to keep their every dimension and the file's CRS as ``sdp distance`` does:
    from the core points' file, else the reference's, when its rows hold every core point
    exactly (none dropped) and the file fits the memory limit; else None (the exports then carry
    x, y, z and the series' values, at sdp's own scale and offset)."""
    import copy
    from dataclasses import replace

    import laspy

    from .._core._memory import memory_limit as limit
    from ..io._read import read_points
    from ..io._source import PointSource
    from ..scale._budget import untiled_point_bytes

    params = ds.attrs["parameters"]
    core = np.c_[ds.x.values, ds.y.values, ds.z.values]
    for name in (params.get("core_points"), params.get("reference_file")):
        path = Path(str(name))
        if path.suffix.lower() not in (".las", ".laz") or not path.is_file():
            continue
        try:
            if untiled_point_bytes(PointSource.open(path).n_rows) > limit(memory_limit):
                continue
            cloud = read_points(path)
        except SDPError:
            continue
        rows = _rows_holding(cloud.xyz, core)
        if rows is None or cloud.n_dropped or cloud.las is None:
            continue
        las = laspy.LasData(copy.deepcopy(cloud.las.header), points=cloud.las.points[rows])
        return replace(cloud, xyz=cloud.xyz[rows], fields={k: np.asarray(v)[rows] for k, v in cloud.fields.items()},
                       las=las)
    return None


def _rows_holding(points: np.ndarray, xyz: np.ndarray) -> np.ndarray | None:
    """The row of ``points`` equal to each row of ``xyz`` (bit for bit), or None if one is missing."""
    def keys(a):
        return np.ascontiguousarray(a, np.float64).view(np.dtype((np.void, 24))).ravel()

    have, want = keys(points), keys(xyz)
    if not len(have):
        return None
    order = np.argsort(have, kind="stable")
    rows = order[np.minimum(np.searchsorted(have[order], want), len(order) - 1)]
    return rows if np.array_equal(have[rows], want) else None


def _write_epoch(ds, k: int, path, inputs, field_names: str, like=None) -> None:
    from ..distance._names import rename_fields
    from ..io._output import write_points

    xyz = np.c_[ds.x.values, ds.y.values, ds.z.values]
    row = ds.isel(epoch=k)
    fields = {name: np.asarray(row[name].values) for name in ("distance", "lod", "smoothed", "velocity",
                                                               "smoothed_sigma", "object")}
    fields["significant"] = np.asarray(row["significant"].values).astype(np.uint8)
    for axis in "xyz":
        fields[f"normal_{axis}"] = ds[f"normal_{axis}"].values
    write_points(path, xyz, rename_fields(fields, field_names, path=path), like=like, inputs=inputs)


def default_points(ds, count: int = 5) -> list[int]:
    """The core point of largest smoothed change in each of the ``count`` largest objects."""
    chosen = []
    objects = ds.object.values
    change = np.abs(np.nan_to_num(ds.smoothed.values))
    from ..timeseries._archive import objects_by_size

    for oid in ds.object_id.values[objects_by_size(ds)[:count]]:
        where = np.where(objects == oid, change, -1.0)
        chosen.append(int(np.unravel_index(np.argmax(where), where.shape)[1]))
    return sorted(set(chosen))


def point_table(ds, points: list[int]):
    """Per-point series as a pandas DataFrame (point, epoch, time, each per-epoch value)."""
    import pandas as pd

    m = ds.sizes["point"]
    bad = [p for p in points if not 0 <= p < m]
    if bad:
        raise InvalidOptionError(f"--points {bad[0]}: the archive has core points 0..{m - 1}")
    sub = ds.isel(point=points)
    cols = {"point": np.repeat(points, ds.sizes["epoch"]),
            "epoch": np.tile(np.arange(ds.sizes["epoch"]), len(points)),
            "time": np.tile(ds.time.values, len(points))}
    for axis in "xyz":
        cols[axis] = np.repeat(sub[axis].values, ds.sizes["epoch"])
    for name in ("distance", "lod", "significant", "smoothed", "smoothed_sigma", "velocity", "velocity_sigma",
                 "object"):
        cols[name] = np.asarray(sub[name].values).T.reshape(-1)
    return pd.DataFrame(cols)


def _write_points(ds, path, points, inputs, field_names: str) -> None:
    from ..distance._names import rename_fields

    table = point_table(ds, default_points(ds) if points is None else points)
    table.columns = list(rename_fields(dict.fromkeys(table.columns), field_names))  # the names, in order
    with atomic_path(path, inputs=inputs) as tmp:
        if Path(path).suffix.lower() == ".parquet":
            try:
                table.to_parquet(tmp, index=False)
            except ImportError as exc:
                raise SDPError(f"{path}: Parquet needs pyarrow ({exc}); write .csv instead") from None
        else:
            table.to_csv(tmp, index=False)


def _epoch_notices(epochs: list, ref: int) -> dict:
    """The epochs a reader should look at twice, from their records: measured at fewer than half the
    core points of the median epoch (a partial scan: its objects may break there); a registration
    error measured as M3C2's 0 (too few stable places), or more than three times both the median of
    the others and the epoch's own random part (the epoch moved as a whole: a misaligned scan, or a
    change everywhere such as snow, which the measured error then hides)."""
    others = [(k, e) for k, e in enumerate(epochs) if k != ref and e["comparable"] > 0]
    counts = np.array([e["comparable"] for _, e in others])
    partial = [{"epoch": k, "file": e["file"], "comparable": e["comparable"], "median": int(np.median(counts))}
               for k, e in others if e["comparable"] < 0.5 * np.median(counts)]
    auto = [(k, e) for k, e in others if e.get("registration_source", "given") != "given"]
    fell_back = [{"epoch": k, "file": e["file"]} for k, e in auto if not e["registration_source"].startswith("measured")]
    large = []
    for k, e in auto:
        rest = [o["registration_error"] for j, o in auto if j != k]
        typical = float(np.median(rest)) if rest else 0.0
        if e.get("random_sd") is not None and e["registration_error"] > 3 * max(typical, e["random_sd"]):
            large.append({"epoch": k, "file": e["file"], "registration_error": e["registration_error"],
                          "median_others": typical, "random_sd": e["random_sd"]})
    return {"partial_epochs": partial, "registration": {"auto_epochs": len(auto), "fell_back": fell_back,
                                                        "large": large}}


def describe_series(path, *, version=None) -> dict:
    """What ``sdp info ARCHIVE.zarr`` prints: epochs, times, core points, objects, every parameter
    (read with zarr: no dataset is opened). ``version``: the folder of the archive's new version
    this process is writing, described before its commit (:func:`~sdp.timeseries._archive.open_version`)."""
    from ..timeseries._archive import objects_by_size, read_group, show_time

    g = read_group(path) if version is None else read_group(version, settle=False)
    attrs = g.attrs.asdict()
    epochs = attrs["epochs"]
    n_points = g["x"].shape[0]
    # of the cells measured after the reference (against itself it is never significant), from each
    # epoch's record: no pass over the archive
    ref = attrs["parameters"]["used"]["reference"]
    measured = [e for k, e in enumerate(epochs) if k != ref]
    cells = sum(e["comparable"] for e in measured)
    sig_fraction = sum(e["significant"] for e in measured) / cells if cells else 0.0
    kind = attrs["time_kind"]
    times = [e["time"] for e in epochs]
    if kind == "date":
        times = [show_time(t, kind) for t in times]
    # the last epoch where it was measured (elsewhere the smoother's value is a guess): one row each
    seen = np.isfinite(np.asarray(g["distance"][-1])) if epochs else np.zeros(0, bool)
    last = np.asarray(g["smoothed"][-1])[seen] if epochs else np.empty(0)
    vel = np.asarray(g["velocity"][-1])[seen] if epochs else np.empty(0)
    order = objects_by_size(g)
    table = [{"id": int(i), "start": int(s), "end": int(e), "core_points": int(n), "area": float(a),
              "peak_change": float(p), "mean_velocity": float(v)}
             for i, s, e, n, a, p, v in zip(*(np.asarray(g[name][...])[order] for name in (
                 "object_id", "object_start", "object_end", "object_points", "object_area", "object_peak_change",
                 "object_mean_velocity")))]
    return {"kind": "series archive", "path": str(path), "format_version": attrs["format_version"],
            "sdp_version": attrs["sdp_version"], "epochs": len(epochs), "core_points": int(n_points),
            "time_kind": kind, "time_source": sorted({e["time_source"] for e in epochs}),
            "first_time": times[0] if times else None, "last_time": times[-1] if times else None,
            "reference": attrs["parameters"]["reference_file"],
            "significant_fraction": sig_fraction,
            # a file in another frame, or of another place, gives an epoch measured nowhere
            "unmeasured_epochs": [{"epoch": k, "file": e["file"]} for k, e in enumerate(epochs)
                                  if k != ref and e["comparable"] == 0],
            **_epoch_notices(epochs, ref),
            "median_abs_smoothed_last": float(np.nanmedian(np.abs(last))) if np.isfinite(last).any() else None,
            "max_abs_velocity_last": float(np.nanmax(np.abs(vel))) if np.isfinite(vel).any() else None,
            "objects": len(table), "largest_objects": table[:10], "parameters": attrs["parameters"],
            "runs": attrs["runs"]}
