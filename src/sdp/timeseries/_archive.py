"""The series archive: one Zarr folder per series, written all or nothing, appended epoch by epoch.

Layout (a Zarr v3 group, ``*.zarr``, readable with ``xarray.open_zarr``)::

    attrs          format "sdp-series", format_version, sdp_version, parameters (each option as
                   given and as used), epochs (file, time, time source, registration error,
                   alignment), time_units, runs (what each run added)
    distance, lod, significant       (epoch, point)  float32, float32, bool: chunks of one epoch
                                                     row and 65,536 points, written once
    smoothed, velocity, smoothed_sigma, velocity_sigma, object   (epoch, point): float32 (LZ4)
                                     and int32, in chunks of 16 epochs × 16,384 points; an
                                     append rewrites the rows from the saved epoch on
    time, registration_error         (epoch,)
    x, y, z, onset, onset_kind       (point,): chunks of 65,536 points
    normal_x/y/z, ref_mean, ref_spread, ref_count, ref_level     (point,): the reference side
    ref_across_x/y/z, ref_across_var (:class:`sdp.distance.PreparedReference`) that appending
    ref_front                        reuses (an archive without ref_across_*: no place off the axis;
                                     without ref_front: no surface found in front measured there)
    object_id, object_start, object_end, object_start_time, object_end_time, object_points,
    object_area, object_peak_change, object_mean_velocity        (object_id,): the object table
    state.npz                        what an append goes on from (:func:`write_state`), not a
                                     dataset variable
    .sdp-lock                        an empty file a run writing the archive holds a lock on (:func:`writing`)

Atomicity: a new archive is written under a temporary name beside it, marked complete, renamed
to ``.NAME.pending`` and swapped in (``NAME`` to ``.NAME.old``, ``.NAME.pending`` to ``NAME``,
then the old one removed); a run interrupted before the mark leaves what was there (its temporary
folder is removed by the next run), one interrupted after it is completed by the next run or
:func:`open_series` (:func:`recover`). An append writes in place behind an undo journal
(``.NAME.journal``): first hard links to every file it may replace (Zarr writes a chunk through a
new file renamed over the old one, so a link keeps the old bytes) and the names each folder held,
then the writes, then the journal renamed away (the commit) and removed. A run interrupted before
the commit is rolled back by the next run or :func:`open_series` (what it added removed, what it
replaced put back); so an append costs the files it writes, not a copy of the archive's thousands
of chunk files.

References
----------
.. [1] A. Miles et al., "Zarr: chunked, compressed, N-dimensional arrays", https://zarr.dev.
.. [2] S. Hoyer, J. Hamman, "xarray: N-D labeled arrays and datasets in Python", J. Open Res.
   Softw. 5(1) (2017).
"""

from __future__ import annotations

import json
import os
import shutil
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ..errors import InvalidOptionError, SDPError, require
from ..io._output import commit_point

__all__ = ["ARCHIVE_FORMAT", "ARCHIVE_VERSION", "archive_exists", "open_series", "open_version", "recover", "writing",
           "transaction", "untouched_by_append", "Writer",
           "many_chunks_at_once", "write_state", "read_state", "objects_by_size", "read_group"]

ARCHIVE_FORMAT = "sdp-series"
ARCHIVE_VERSION = 2  # 2: the state an append goes on from (fixed-lag smoother, tracked objects)
#: Points per chunk of the arrays the smoother and the tracker write in columns (16 epochs per
#: chunk): a column of whole chunks fits a small memory limit at 1,000 epochs.
POINT_CHUNK = 16384
#: Points per chunk of the measured rows (one epoch per chunk) and of the per-point arrays: Zarr
#: spends about a millisecond per chunk file, more than its bytes cost, so an epoch of 100,000
#: core points is 2 files per array rather than 7; the smoother reads them in columns.
ROW_CHUNK = 65536
#: The per-point arrays of the reference side, which appending reads and never writes.
REFERENCE_SIDE = ("x", "y", "z", "normal_x", "normal_y", "normal_z", "ref_mean", "ref_spread", "ref_count",
                  "ref_level", "ref_across_x", "ref_across_y", "ref_across_z", "ref_across_var", "ref_front")
#: The (epoch, point) arrays measured once per epoch (one epoch per chunk row, written once).
MEASURED = ("distance", "lod", "significant")
#: The (epoch, point) arrays an append writes again from the saved epoch on (16 epochs per chunk row).
REWRITTEN = ("smoothed", "velocity", "smoothed_sigma", "velocity_sigma", "object")
#: Values per chunk of the arrays of one dimension that appends lengthen (time, the object table):
#: written over in place, their chunks do not depend on their first length.
_GROWING_CHUNK = 4096
_STATE = "state.npz"  # what an append goes on from (not a dataset variable)
_LOCK = ".sdp-lock"  # inside the archive: an append holds an exclusive flock on it
_HELD: set = set()  # the archives whose append lock this process holds
_COMPLETE = ".sdp-complete"


class SeriesArchiveError(SDPError, OSError):
    """An archive that is not an sdp series, or that can't be written."""


def require_series():
    """(xarray, zarr), or a one-line :class:`~sdp.MissingDependencyError` naming the extra."""
    return (require("xarray", "series", "a series archive"), require_zarr())


def require_zarr():
    """zarr, having checked that xarray is installed too (the ``series`` extra), without importing
    it: writing and summarising an archive need only zarr, and importing xarray and pandas is much
    of a short command's start-up."""
    import importlib.util

    if importlib.util.find_spec("xarray") is None:
        require("xarray", "series", "a series archive")  # the one-line error naming the extra
    return require("zarr", "series", "a series archive")


def _siblings(path: Path) -> tuple[Path, Path]:
    return path.parent / f".{path.name}.pending", path.parent / f".{path.name}.old"


def archive_exists(path) -> bool:
    """An archive at ``path``, or a new version of it that an interrupted run left beside it
    (:func:`recover` swaps it in)."""
    path = Path(path)
    return path.exists() or _siblings(path)[0].exists()


def _journal(path: Path) -> tuple[Path, Path]:
    """(the undo journal of an append in progress, the same once committed)."""
    return path.parent / f".{path.name}.journal", path.parent / f".{path.name}.committed"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    else:
        p.unlink(missing_ok=True)


def _roll_back(path: Path, journal: Path) -> None:
    """Undo an append that did not commit: remove what it added, put back what it replaced."""
    listing = json.loads((journal / "names.json").read_text())
    for entry in os.scandir(path):
        before = listing.get(entry.name, False)
        if before is False:
            _remove(Path(entry.path))
        elif before is not None and entry.is_dir():
            kept = set(before)
            for f in os.scandir(entry.path):
                if f.name not in kept:
                    _remove(Path(f.path))
    saved = journal / "saved"
    for root, _, files in os.walk(saved):
        rel = Path(root).relative_to(saved)
        (path / rel).mkdir(parents=True, exist_ok=True)
        for f in files:
            os.replace(Path(root) / f, path / rel / f)
    shutil.rmtree(journal)


def recover(path) -> str | None:
    """Finish or undo what an interrupted run left beside the archive ``path``; what was done, or None.

    A complete new version (``.NAME.pending``) is swapped in, an append that did not commit rolled
    back (``.NAME.journal``); what is left of runs that are no longer alive is removed."""
    path = Path(path)
    pending, old = _siblings(path)
    journal, committed = _journal(path)
    done = None
    if pending.is_dir() and (pending / _COMPLETE).exists():
        if path.exists():
            if old.exists():
                shutil.rmtree(old)
            os.rename(path, old)
        os.rename(pending, path)
        done = "completed an interrupted run"
    if old.exists() and path.exists():
        shutil.rmtree(old, ignore_errors=True)
    if journal.is_dir() and path.is_dir():
        with _writer_gone(path) as gone:
            if gone:  # else an append is running: its journal is not left over
                _roll_back(path, journal)
                done = "undid an interrupted append"
    if committed.exists():
        shutil.rmtree(committed, ignore_errors=True)
    for tmp in [*path.parent.glob(f".{path.name}.tmp-*"), *path.parent.glob(f".{path.name}.journal-*")]:
        try:
            pid = int(tmp.name.rsplit("-", 1)[1])
        except ValueError:
            continue
        if not _alive(pid) or pid == os.getpid():
            shutil.rmtree(tmp, ignore_errors=True)
            done = done or "removed what an interrupted run left"
    return done


def _try_lock(path: Path):
    """An open file holding the append lock of the archive ``path``, or None if another run holds
    it. Where the system has no flock (Windows), every caller gets it."""
    try:
        import fcntl
    except ImportError:
        return open(path / _LOCK, "a")
    f = open(path / _LOCK, "a")
    try:
        fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.close()
        return None
    return f


def _holder(lock: Path) -> int | None:
    """The process holding the flock on the file ``lock``, as Linux lists it in ``/proc/locks``
    (``FLOCK ADVISORY WRITE pid major:minor:inode …``); None elsewhere, or if it is not listed."""
    try:
        st = os.stat(lock)
        table = Path("/proc/locks").read_text()
    except OSError:
        return None
    node = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    for line in table.splitlines():
        fields = line.split()
        if len(fields) > 5 and fields[1] == "FLOCK" and fields[5] == node and fields[4].isdigit():  # "->": waiting
            return int(fields[4])
    return None


@contextmanager
def _writer_gone(path: Path):
    """Whether no live run is writing ``path`` (this process holds its lock, or it is free: then
    held for the block)."""
    if path.resolve() in _HELD:
        yield True
        return
    f = _try_lock(path)
    try:
        yield f is not None
    finally:
        if f is not None:
            f.close()


@contextmanager
def writing(path):
    """Hold the write lock of the archive ``path`` for the block (an append, or a run replacing
    it), then finish or undo what an interrupted run left (:func:`recover`). The lock is a flock on
    a file inside the archive: the system releases it when the process ends, however it ends, so a
    killed run leaves no stale lock, and a run or :func:`open_series` never rolls back the journal
    of an append still running.

    Raises
    ------
    SeriesArchiveError
        Another run is writing this archive.
    """
    path = Path(path)
    if not path.is_dir():
        recover(path)  # a new version left pending by an interrupted run
    f = _try_lock(path)
    if f is None:
        pid = _holder(path / _LOCK)
        raise SeriesArchiveError(f"{path}: another sdp run{f' (process {pid})' if pid else ''} is writing this "
                                 "archive; run again when it has ended (its lock goes with it, however it ends)")
    key = path.resolve()
    _HELD.add(key)
    try:
        recover(path)
        yield
    finally:
        _HELD.discard(key)
        f.close()


def _save(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:  # a file system without hard links: copy
        shutil.copy2(src, dst)


def _begin(path: Path, untouched) -> Path:
    """The undo journal of an append to ``path``: each folder's names, and hard links to every file
    but those ``untouched(folder, name)`` says the run leaves alone; made under a temporary name,
    then renamed (it is valid from then on)."""
    journal, _ = _journal(path)
    tmp = path.parent / f".{path.name}.journal-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        _record(path, tmp, untouched)
        os.rename(tmp, journal)
    except BaseException:  # a full disk, Ctrl-C: no journal, the archive untouched; nothing left beside it
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return journal


def _record(path: Path, tmp: Path, untouched) -> None:
    """The journal's content in the folder ``tmp``: ``names.json`` and the links in ``saved``."""
    saved = tmp / "saved"
    saved.mkdir(parents=True)
    listing: dict = {}
    for entry in os.scandir(path):
        if not entry.is_dir():
            listing[entry.name] = None
            _save(Path(entry.path), saved / entry.name)
            continue
        names = os.listdir(entry.path)
        listing[entry.name] = names
        keep = [f for f in names if not untouched(entry.name, f)]
        if keep:
            (saved / entry.name).mkdir()
        for f in keep:
            src = Path(entry.path) / f
            if src.is_dir():
                shutil.copytree(src, saved / entry.name / f, copy_function=_save)
            else:
                _save(src, saved / entry.name / f)
    (tmp / "names.json").write_text(json.dumps(listing))


def untouched_by_append(*, rows: int, rewritten_from: int, epochs_per_chunk: int):
    """The files an append leaves alone, as ``untouched(folder, name)`` for :func:`transaction`:
    the reference side, the measured arrays' first ``rows`` epoch rows, and the chunk rows of the
    rewritten arrays (``epochs_per_chunk`` epochs each) wholly before the epoch ``rewritten_from``."""
    def untouched(folder: str, name: str) -> bool:
        if folder in REFERENCE_SIDE:
            return True
        parts = name.split(".")
        if len(parts) < 2 or parts[0] != "c" or not parts[1].isdigit():
            return False
        if folder in MEASURED:
            return int(parts[1]) < rows
        if folder in REWRITTEN:
            return (int(parts[1]) + 1) * epochs_per_chunk <= rewritten_from
        return False

    return untouched


def _say_written(exc: BaseException, path: Path, state: str) -> None:
    """A write that failed in the file system (a full disk, a file-size limit, permissions) as one
    line naming the archive and what is left of it."""
    if isinstance(exc, OSError) and not isinstance(exc, SDPError):
        raise SeriesArchiveError(f"{path}: can't write the series archive ({exc.strerror or exc}; disk full?): "
                                 f"{state}") from None


@contextmanager
def transaction(path, *, untouched=None):
    """Yield the folder to write the archive's new version in (see the module docstring).

    ``untouched``: None for a new archive (a temporary folder, swapped in as ``path`` on success,
    else removed); for an append, ``untouched(folder, name)`` tells the files of ``path`` the run
    will not change, and the folder yielded is ``path`` itself, behind an undo journal."""
    path = Path(path)
    recover(path)
    if untouched is not None:
        if path.resolve() not in _HELD:
            raise RuntimeError("an append's transaction runs inside writing(path)")
        journal, committed = _journal(path)
        try:
            _begin(path, untouched)
        except BaseException as exc:
            _say_written(exc, path, "it is as it was before this append")
            raise
        try:
            yield path
        except BaseException as exc:
            _settle()
            _roll_back(path, journal)
            _say_written(exc, path, "it is as it was before this append")
            raise
        with commit_point():
            os.rename(journal, committed)  # the commit
        shutil.rmtree(committed, ignore_errors=True)
        return
    tmp = path.parent / f".{path.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    pending, old = _siblings(path)
    try:
        tmp.mkdir()
        yield tmp
        (tmp / _LOCK).touch()  # after the writer: zarr's mode "w" empties the folder
        (tmp / _COMPLETE).write_text("complete\n")
        os.rename(tmp, pending)
    except BaseException as exc:
        _settle()
        shutil.rmtree(tmp, ignore_errors=True)
        _say_written(exc, path, "nothing was written")
        raise
    # from here the new version is complete: a crash leaves it for recover() to swap in
    with commit_point():
        if path.exists():
            os.rename(path, old)
        os.rename(pending, path)
    (path / _COMPLETE).unlink()
    shutil.rmtree(old, ignore_errors=True)


@contextmanager
def many_chunks_at_once(n: int = 64, batch: int = 128):
    """Zarr reading and writing up to ``n`` chunks at once, and encoding or decoding ``batch``
    chunks per call of its codecs: a series reads and writes rows and columns of many small chunks
    (an epoch row each), and Zarr's defaults (10 at once, one per call) leave it waiting on each
    chunk in turn."""
    zarr = require_zarr()
    with zarr.config.set({"async.concurrency": n, "codec_pipeline.batch_size": batch}):
        yield


class Writer:
    """Arrays of one archive version being written (in a :func:`transaction` folder).

    Each array is opened once (an opening reads its metadata) and read, resized and written through
    the same handle; the ``*_all`` methods do their arrays in one round of Zarr's event loop (a
    series' arrays cost more in those rounds than in their bytes)."""

    def __init__(self, folder: Path, *, create: bool):
        zarr = require_zarr()
        self.folder = Path(folder)
        self.zarr = zarr
        self.group = zarr.open_group(str(folder), mode="w" if create else "r+")
        self._arrays: dict = {}  # name → zarr's AsyncArray

    def array(self, name, shape, dtype, dims, *, epochs_per_chunk: int = 1, rewritten: bool = False):
        """A new array (replacing one of that name); chunks: ``epochs_per_chunk`` epoch rows ×
        :data:`ROW_CHUNK` points (one row) or :data:`POINT_CHUNK` (several); chunk files ``c.i.j``
        side by side (no folder per row: an append's journal links files, not folders).
        ``rewritten``: rows every append writes again (the smoothed ones), compressed by LZ4 over
        shuffled bytes, nearly as small as Zarr's Zstd and written in half its time."""
        self._arrays.pop(name, None)
        if name in self.group:
            del self.group[name]
        arr = self.group.create_array(name, shape=shape, dtype=dtype, **_layout(dims, shape, dtype, epochs_per_chunk),
                                      **({"compressors": _quick_codec()} if rewritten else {}),
                                      attributes={"coordinates": "time x y z"} if tuple(dims) == ("epoch", "point")
                                      else {})
        self._arrays[name] = arr._async_array
        return arr

    def write_all(self, items: dict) -> None:
        """Whole arrays, ``{name: (values, dims, attrs or None)}``, created (replacing any of that
        name) and written together."""
        from zarr.api.asynchronous import open_group

        for name in items:
            self._arrays.pop(name, None)
            if (self.folder / name).exists():
                del self.group[name]
        (group,) = _at_once([open_group(store=str(self.folder), mode="r+")])

        async def one(name, values, dims, attrs):
            values = np.ascontiguousarray(values)
            self._arrays[name] = await group.create_array(name, data=values, attributes=attrs or {},
                                                          **_layout(dims, values.shape, values.dtype))

        _at_once([one(name, *item) for name, item in items.items()])

    def update_all(self, items: dict) -> None:
        """As :meth:`write_all`, but an array that exists with that dtype is resized if need be
        and written over (no new metadata unless its shape changes)."""
        self.open_all(name for name in items if (self.folder / name).is_dir())
        same = {name: item for name, item in items.items() if name in self._arrays
                and self._arrays[name].dtype == np.asarray(item[0]).dtype
                and self._arrays[name].ndim == np.ndim(item[0])}
        if len(same) < len(items):
            self.write_all({name: item for name, item in items.items() if name not in same})

        async def one(name, values):
            arr = self._arrays[name]
            if arr.shape != values.shape:
                await arr.resize(values.shape)
            await arr.setitem(..., values)

        _at_once([one(name, np.asarray(item[0])) for name, item in same.items()])

    def open_all(self, names) -> None:
        """The arrays ``names`` not opened yet, opened together."""
        from zarr.api.asynchronous import open_array

        todo = [name for name in names if name not in self._arrays]
        found = _at_once([open_array(store=str(self.folder), path=name, mode="r+") for name in todo])
        self._arrays.update(zip(todo, found))

    def resize_all(self, shapes: dict) -> None:
        """``{name: shape}`` together (those of another shape)."""
        self.open_all(shapes)
        _at_once([self._arrays[name].resize(shape) for name, shape in shapes.items()
                  if self._arrays[name].shape != tuple(shape)])

    def set_all(self, items: dict) -> None:
        """``{name: (selection, values)}`` written together."""
        self.open_all(items)
        _at_once([self._arrays[name].setitem(sel, values) for name, (sel, values) in items.items()])

    def read_all(self, names) -> dict:
        """Whole arrays read together."""
        names = list(names)
        self.open_all(names)
        return dict(zip(names, _at_once([self._arrays[name].getitem(...) for name in names])))

    def __getitem__(self, name):
        self.open_all([name])
        return self.zarr.Array(self._arrays[name])

    def finish(self, attrs: dict) -> None:
        """The group's attributes (JSON) and consolidated metadata (one read opens the archive, as
        :func:`zarr.consolidate_metadata` makes it), in one write of the group's metadata: the
        arrays' metadata from the handles they were resized and written through (zarr's own
        consolidation reads every array's metadata file again)."""
        from zarr.core.group import ConsolidatedMetadata, GroupMetadata
        from zarr.core.metadata.io import save_metadata

        members = sorted(e.name for e in os.scandir(self.folder) if e.is_dir() and
                         os.path.isfile(os.path.join(e.path, "zarr.json")))
        self.open_all(members)
        meta = GroupMetadata(attributes=json.loads(json.dumps(attrs, default=_plain)),
                             consolidated_metadata=ConsolidatedMetadata(
                                 metadata={name: self._arrays[name].metadata for name in members}))
        _at_once([save_metadata(self.group._async_group.store_path, meta)])


def _layout(dims, shape, dtype, epochs_per_chunk: int = 1) -> dict:
    """The chunks, fill value and names every array of an archive is made with. write_empty_chunks:
    Zarr otherwise compares every chunk with the fill value before writing it, which costs more
    than the write (a series' chunks are seldom empty)."""
    points = POINT_CHUNK if epochs_per_chunk > 1 else ROW_CHUNK
    chunks = tuple(max(1, epochs_per_chunk) if d == "epoch" and len(dims) > 1 else
                   max(1, min(points, s)) if d == "point" else _GROWING_CHUNK for d, s in zip(dims, shape))
    return {"chunks": chunks, "fill_value": np.nan if np.dtype(dtype).kind == "f" else 0,
            "dimension_names": list(dims), "config": {"write_empty_chunks": True},
            "chunk_key_encoding": {"name": "default", "separator": "."}}


def _settle(timeout: float = 30.0) -> None:
    """Wait for zarr's writes still running after one of them failed: ``asyncio.gather`` (in
    :func:`_at_once` and in zarr's own calls) raises the first error and leaves the others running,
    and a write landing after the rollback or the removal would undo it."""
    import sys

    if "zarr.core.sync" not in sys.modules:
        return
    import asyncio

    from zarr.core.sync import sync

    async def rest():
        others = [t for t in asyncio.all_tasks() if t is not asyncio.current_task()]
        if others:
            await asyncio.wait(others, timeout=timeout)

    sync(rest())


def _at_once(coroutines: list) -> list:
    """Zarr's asynchronous calls run together in one round of its event loop; their results in order."""
    import asyncio

    from zarr.core.sync import sync

    async def every():
        return await asyncio.gather(*coroutines)

    return sync(every())


def _quick_codec():
    from zarr.codecs import BloscCodec

    return BloscCodec(cname="lz4", clevel=5, shuffle="shuffle")


def write_state(folder, filt, tracker: dict, recent) -> None:
    """The filter and the tracker after the last final epoch, in one NumPy file beside the arrays
    (``state.npz``, written anew by every run, not a dataset variable): the filter per core point
    (its state, covariance, time of the last observation, first epoch seen and first step, float64),
    :meth:`sdp.timeseries._objects.Tracker.state`'s arrays and the distances and levels of the
    epochs after the filter's (a copy of their rows, which the next run reads at once)."""
    arrays = {"filter": np.c_[filt.x, filt.seen.astype(np.float64), filt.step.astype(np.float64)],
              "filter_epoch": np.array([filt.epoch]), "recent_distance": recent[0], "recent_lod": recent[1],
              **{f"tracker_{k}": v for k, v in tracker.items()}}
    target = Path(folder) / _STATE
    part = target.with_name(f".{_STATE}.{os.getpid()}.partial")
    with open(part, "wb") as f:  # then renamed over the old one: an append's journal holds a link to it
        np.savez(f, **arrays)
    os.replace(part, target)


def read_state(path):
    """(:class:`~sdp.timeseries._kalman.FilterState`, the tracker's arrays, the recent distances
    and levels) :func:`write_state` saved in the archive ``path``."""
    import zipfile

    from ._kalman import FilterState

    try:
        with np.load(Path(path) / _STATE, allow_pickle=False) as z:
            arrays = dict(z)
        f = arrays["filter"]
        if f.shape[1] == 7:  # saved before the time of the last observation was: unknown
            f = np.c_[f[:, :5], np.full(len(f), np.nan), f[:, 5:]]
        filt = FilterState(int(arrays["filter_epoch"][0]), np.ascontiguousarray(f[:, :6]), f[:, 6].astype(np.int64),
                           f[:, 7].astype(np.int32))
        recent = arrays["recent_distance"], arrays["recent_lod"]
    except (OSError, ValueError, KeyError, IndexError, EOFError, zipfile.BadZipFile) as exc:
        raise SeriesArchiveError(f"{path}: its state ({_STATE}) can't be read ({type(exc).__name__}): it can't be "
                                 "appended to; run the series again over all its epochs") from None
    tracked = {name[len("tracker_"):]: v for name, v in arrays.items() if name.startswith("tracker_")}
    return filt, tracked, recent


def _plain(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(f"{type(v).__name__} is not JSON")


def read_group(path, *, settle: bool = True):
    """The archive ``path`` as a zarr group (read only), checked to be an sdp series; what an
    interrupted run left is completed or undone first (:func:`recover`). ``settle=False``: the
    folder of a version this process is writing (a :func:`transaction`'s, before its commit),
    read as it is (settling would roll back this very append)."""
    path = Path(path)
    zarr = require_zarr()
    try:
        if settle:
            recover(path)
    except OSError:  # read-only: read what is there
        pass
    try:
        group = zarr.open_group(str(path), mode="r")
    except Exception as exc:  # zarr raises several types for missing or foreign folders
        raise SeriesArchiveError(f"{path}: not a readable series archive ({type(exc).__name__})") from None
    attrs = group.attrs
    if attrs.get("format") != ARCHIVE_FORMAT or attrs.get("format_version") != ARCHIVE_VERSION:
        raise SeriesArchiveError(f"{path}: format {attrs.get('format')!r} version {attrs.get('format_version')!r}; "
                                 f"this sdp reads {ARCHIVE_FORMAT} version {ARCHIVE_VERSION}")
    return group


def is_series(path) -> bool:
    """Whether ``path`` is a folder holding an sdp series archive."""
    path = Path(path)
    try:
        meta = json.loads((path / "zarr.json").read_text())
    except (OSError, ValueError):
        return False
    return meta.get("attributes", {}).get("format") == ARCHIVE_FORMAT


def show_time(value: float, kind: str) -> str:
    """An epoch's time as printed: a date (days since 1970-01-01) in ISO, with its fraction of a
    second where it has one (to the microsecond), else the number."""
    if kind != "date":
        return f"{value:g}"
    us = int(round(value * 86_400e6))
    stamp = np.datetime64("1970-01-01T00:00:00", "us") + np.timedelta64(us, "us")
    if us % 1_000_000 == 0:
        return str(stamp.astype("datetime64[s]"))
    return str(stamp).rstrip("0")


def objects_by_size(ds) -> np.ndarray:
    """Positions along ``object_id`` of an archive's objects, the most core points first (ids
    count in the order objects were found); ``ds``: the dataset or its zarr group."""
    return np.lexsort((np.asarray(ds["object_id"][...]), -np.asarray(ds["object_points"][...])))


def open_series(path, *, chunks="auto"):
    """The series archive at ``path`` as an :class:`xarray.Dataset` (lazy, Dask-backed arrays).

    An archive left by an interrupted run is completed or cleaned first (:func:`recover`).

    Parameters
    ----------
    path : path-like
        A folder written by :func:`sdp.series`.
    chunks : "auto", dict or None
        Dask chunks, as :func:`xarray.open_zarr` takes them (default ``"auto"``: multiples of
        the archive's own);
        None: no Dask, each variable read when it is indexed (what the command does: importing
        Dask's arrays costs more than its summary reads).

    Returns
    -------
    xarray.Dataset
        ``distance``, ``lod``, ``significant``, ``smoothed``, ``velocity``, ``smoothed_sigma``,
        ``velocity_sigma``, ``object`` (epoch, point); ``time`` (epoch); ``x``, ``y``, ``z``
        (point); the object table (object_id); every parameter in ``attrs``.

    Raises
    ------
    sdp.SDPError
        Not a series archive (or one of another format version): a ``SeriesArchiveError``.

    References
    ----------
    .. [1] S. Hoyer, J. Hamman, "xarray: N-D labeled arrays and datasets in Python" (2017).
    """
    xr, _ = require_series()
    if not (chunks is None or isinstance(chunks, dict) or (isinstance(chunks, str) and chunks == "auto")):
        raise InvalidOptionError(f"chunks must be 'auto', a dict of dimension sizes or None, got {chunks!r}")
    path = Path(path)
    read_group(path)
    return _dataset(xr, path, chunks)


def open_version(folder):
    """The version of an archive this process is writing (the folder a :func:`transaction`
    yields, complete, before its commit) as :func:`open_series` opens it with ``chunks=None``:
    what the command exports is read from it, so that an export that fails leaves the archive as
    it was."""
    xr, _ = require_series()
    read_group(folder, settle=False)
    return _dataset(xr, Path(folder), None)


def _dataset(xr, path: Path, chunks):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = xr.open_zarr(str(path), consolidated=True, chunks=chunks)
    coords = [c for c in ("time", "x", "y", "z") if c in ds.variables]
    return ds.set_coords(coords)
