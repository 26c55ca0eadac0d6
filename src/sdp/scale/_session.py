"""A tiled run's session: the lattice and the tiling from the first slices, the buckets on disk,
the Dask cluster (local, or a scheduler's address) and the tasks run on it, stopped at the first
failure, with Ctrl-C and SIGTERM ending the run and removing the work folder.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import os
import shutil
import signal
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._core._memory import check_memory, format_bytes
from .._core._memory import memory_limit as _memory_limit
from .._core._progress import bar
from .._core._validate import check_grid_options, check_tile_options
from ..defaults import DEFAULTS
from ..errors import GridTooLargeError, InvalidPointsError, SDPError, WorkerLostError, require
from ..fields._lattice import BLOCK, check_kernel, check_lattice
from ..io._source import PointSource
from . import _kernels as K
from ._budget import BYTES_PER_ROW_READ, BYTES_PER_TILE_POINT, JobBudget, TaskShare, megabytes

__all__ = ["Tiling", "load_bucket", "Session", "sampled_lattice", "first_slices", "CONNECT_TIMEOUT", "TASK_RETRIES"]


_PART_ROWS = 8_000_000  # rows read by one bucketing task


@dataclass(frozen=True)
class Tiling:
    """Square columns of ``blocks`` × ``blocks`` lattice blocks, with a halo (world units)."""

    voxel_size: float
    blocks: int
    halo: float

    @property
    def edge(self) -> float:
        return self.blocks * BLOCK * self.voxel_size

    def owns(self, key, xyz: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Mask of the points whose cell, floor(p / l), lies in tile ``key``'s blocks (x, y), or
        within ``margin`` (world units) of them."""
        n = self.blocks * BLOCK
        m = margin / self.voxel_size
        u = xyz[:, 0] / self.voxel_size
        v = xyz[:, 1] / self.voxel_size
        return ((u >= key[0] * n - m) & (u < (key[0] + 1) * n + m) & (v >= key[1] * n - m)
                & (v < (key[1] + 1) * n + m))


def _bucket_part(source: PointSource, epoch: str, start: int, stop: int, part: int, tiling: Tiling,
                 root: str, chunk_rows: int) -> tuple[dict, np.ndarray, float]:
    """Bucket rows start … stop−1 of ``source``, ``chunk_rows`` at a time; returns ({tile: count},
    the rows dropped for holding NaN or Inf, seconds reading)."""
    counts: dict[tuple[int, int], int] = {}
    dropped, t_read = [], 0.0
    chunks = source.chunks(chunk_rows, start, stop)
    while True:
        t = time.perf_counter()
        item = next(chunks, None)
        t_read += time.perf_counter() - t
        if item is None:
            break
        first, xyz = item
        i0, j0, nj, sizes, records, n_bad = K.tile_buckets(xyz, first, tiling.voxel_size, tiling.blocks * BLOCK,
                                                            tiling.halo)
        if n_bad:  # which rows: a result marks them not comparable, as in memory
            dropped.append(first + np.flatnonzero(~np.isfinite(xyz).all(axis=1)))
        ends = np.cumsum(sizes)
        for b in np.flatnonzero(sizes):
            key = (int(i0 + b // nj), int(j0 + b % nj))
            path = Path(root, epoch, f"{key[0]}_{key[1]}")
            path.mkdir(exist_ok=True)  # not its parents: a run that ended removed them, and stays removed
            # the task's first write to a bucket truncates it: a task run again (its worker died) writes
            # its rows once
            try:
                with open(path / f"{part:06d}.bin", "ab" if key in counts else "wb") as f:
                    records[ends[b] - sizes[b]:ends[b]].tofile(f)
            except OSError as exc:  # NumPy's short write says neither the file nor why
                raise SDPError(f"{path}: can't write a tile's points ({exc.strerror or exc}): is the work folder's "
                               "disk full? give --workdir on a disk with room") from None
            counts[key] = counts.get(key, 0) + int(sizes[b])
    return counts, np.concatenate(dropped) if dropped else np.zeros(0, np.int64), t_read


def load_bucket(root: str, epoch: str, key) -> np.ndarray:
    """Bucket of tile ``key``: (m, 4) float64 rows x, y, z, row number, in row order."""
    folder = Path(root, epoch, f"{key[0]}_{key[1]}")
    if not folder.is_dir():
        return np.zeros((0, 4))
    return np.concatenate([np.fromfile(p, np.float64).reshape(-1, 4) for p in sorted(folder.iterdir())])


def _check_tile_points(tiling: Tiling, sources: dict, plan: JobBudget, *, given: bool,
                       point_bytes: float = 2 * BYTES_PER_TILE_POINT, in_memory: float | None = None) -> None:
    """Refuse, before any task runs, tiles whose points (with their halo, at the clouds' mean
    density) would need more than a task's share of the memory limit (``point_bytes`` per point
    of the denser cloud: a compare task holds two epochs). ``in_memory``: the limit the work
    would run in memory under, when it switched to tiles by itself; named when it is the smaller."""
    need = _tile_points(tiling, sources) * point_bytes
    if need <= plan.task:
        return
    points = f"about {_tile_points(tiling, sources):,} points per epoch with their halo"
    smallest = plan.smallest(need)
    # a run that came to tiles for want of memory runs in memory under a limit below the tiles' own
    alone = (f"; in memory it would need {format_bytes(in_memory)}"
             if in_memory is not None and in_memory < smallest else "")
    smallest = min(smallest, in_memory) if alone else smallest
    if given and plan.task > 0:
        raise GridTooLargeError(f"tiles of {tiling.edge:.4g} ({points}) would need {format_bytes(need)}, above "
                                f"{plan.task_budget}{alone}: give a smaller "
                                f"--tile-size, or --memory-limit {megabytes(smallest)} or more")
    raise GridTooLargeError(f"the memory limit of {format_bytes(plan.limit)} can't hold this job: {plan.parts()}, and "
                            f"{'these' if given else 'the smallest'} tiles (edge {tiling.edge:.4g}, {points}) need "
                            f"{format_bytes(need)}{alone}; give --memory-limit {megabytes(smallest)} or more")


def _tile_points(tiling: Tiling, sources: dict) -> int:
    """Points of the denser cloud in one tile and its halo, at its mean density in x, y (at most all of them)."""
    return min(max(s.n_rows for s in sources.values()),
               int(math.ceil(_density(sources) * (tiling.edge + 2 * tiling.halo) ** 2)))


def _density(sources: dict) -> float:
    lo = np.min([s.lo for s in sources.values()], axis=0)
    hi = np.max([s.hi for s in sources.values()], axis=0)
    area = max(float(np.prod(hi[:2] - lo[:2])), 1e-12)
    return max(s.n_rows for s in sources.values()) / area


class Session:
    """Workdir, Dask cluster and bucketed clouds of one tiled run; ``with`` closes them.

    ``point_bytes``: what a task holds per point of the denser cloud in its tile and halo (two
    epochs' fields by default), which sizes the tiles from a task's share of the memory limit.
    ``halo_sigmas``: the halo at least this many σ (the combined decision's distances read the
    other epoch farther than the kernel reaches). ``switched`` (:attr:`sdp.Execution.switched`):
    why the run came to tiles by itself, told to ``notify`` once the tiles pass their checks, and
    the limit it would run in memory under, which a refusal names when it is the smaller."""

    def __init__(self, clouds: dict, voxel_size, *, sigma_voxels, k, h, truncate, method, tile_size, tile_points,
                 memory_limit, scheduler, workers, workdir, halo: float | None = None, halo_sigmas: float = 0.0,
                 point_bytes: float = 2 * BYTES_PER_TILE_POINT, notify=None, switched=None):
        check_grid_options(voxel_size=voxel_size, sigma_voxels=sigma_voxels, k=k, h=h, truncate=truncate,
                           memory_limit=memory_limit)
        check_tile_options(tile_size=tile_size, tile_points=tile_points, workers=workers, workdir=workdir,
                           scheduler=scheduler)
        _dask("dask" if scheduler in ("synchronous", "threads") else "dask.distributed")  # before any work
        # "auto": the tiles need the lattice before the points
        voxel_size, sigma_voxels = sampled_lattice(list(clouds.values()), voxel_size=voxel_size or "auto", k=k,
                                                   sigma_voxels=sigma_voxels)
        self.voxel_size, self.sigma_voxels = float(voxel_size), float(sigma_voxels)
        workers = workers or os.cpu_count() or 1
        in_process = scheduler in ("synchronous", "threads")
        self.root = tempfile.mkdtemp(prefix="sdp-tiles-", dir=workdir)
        self.timings: dict[str, float] = {}
        self.executor = self.cluster = None
        try:
            if not (scheduler is None or in_process):  # a cluster of its own: its workers share the limit,
                self.executor, self.cluster = _connect(scheduler, workers, self.root)  # one task per thread
                workers = max(1, sum(self.executor.nthreads().values()))
            plan = JobBudget(_memory_limit(memory_limit), 1 if scheduler == "synchronous" else workers,
                             separate=not in_process)
            share = plan.task
            if tile_points is None:  # what a task's share holds (none: the smallest tiles, refused below)
                tile_points = int(max(0, share // point_bytes))
            self.sources = {e: _source(c, self.root, e) for e, c in clouds.items()}
            lo = np.min([src.lo for src in self.sources.values()], axis=0)
            hi = np.max([src.hi for src in self.sources.values()], axis=0)
            # with no share left, the reach alone is checked here and the tiles are refused below
            reach = check_kernel(sigma_voxels, truncate, TaskShare(plan) if share > 0 else 2**62)
            check_lattice(lo, hi, self.voxel_size, reach)
            self.lo, self.hi = lo, hi
            self.tiling = _tiling(self.sources, self.voxel_size, tile_size, tile_points, sigma_voxels, truncate, halo,
                                  halo_sigmas)
            _check_tile_points(self.tiling, self.sources, plan, given=tile_size is not None, point_bytes=point_bytes,
                               in_memory=switched[1] if switched else None)
            # the tasks' limit: a refusal in one names it as a share of the job's; tiles sized from it
            # grow with the limit until one spans the clouds
            share = TaskShare(plan, self.tiling.edge, sized=tile_size is None and (
                self.tiling.edge + 2 * self.tiling.halo < float(np.max(hi[:2] - lo[:2]))))
            self.opts = dict(voxel_size=self.voxel_size, sigma_voxels=sigma_voxels, k=k, h=h, truncate=truncate,
                             method=method, memory_limit=share)
            chunk_rows = int(min(2_000_000, max(10_000, share // (4 * BYTES_PER_ROW_READ))))
            _check_tile_directory(self.tiling, lo, hi, reach, share)
            if switched and notify is not None:  # the tiles are taken: not said before a refusal of theirs
                notify(switched[0])
            self._chunk_rows = chunk_rows
            if self.executor is None:
                self.executor, self.cluster = _connect(scheduler, workers, self.root)
            self.budget = plan
            self.dropped: dict[str, int] = {}
            self.dropped_rows: dict[str, np.ndarray] = {}  # each source's rows holding NaN or Inf, in order
            self.tiles = self._bucket(list(self.sources))
        except BaseException:
            self.__exit__(*sys.exc_info())
            raise

    def _bucket(self, names: list) -> list:
        """Bucket the sources ``names`` by tile (their rows dropped counted); their tiles, sorted."""
        for e in names:
            Path(self.root, e).mkdir()
        jobs = [(self.sources[e], e, s, s + _PART_ROWS, i, self.tiling, self.root, self._chunk_rows)
                for e in names for i, s in enumerate(range(0, self.sources[e].n_rows, _PART_ROWS))]
        done = self.tasks("bucket", _bucket_part, jobs, (), unit="slice")
        self.timings["read"] = self.timings.get("read", 0.0) + sum(d[2] for d in done)
        self.dropped_rows.update({e: np.concatenate([d[1] for d, j in zip(done, jobs, strict=True) if j[1] == e]
                                                    or [np.zeros(0, np.int64)]) for e in names})
        self.dropped.update({e: len(self.dropped_rows[e]) for e in names})
        return sorted({key for d in done for key in d[0]})

    def add(self, name: str, cloud, *, format: str | None = None) -> list:
        """Bucket one more cloud on this session's tiling and cluster (a series' next epoch): its
        tiles, sorted. Its points need not lie in the first clouds' box; its density sets no tile
        size (a denser cloud's tiles hold more points)."""
        if format is not None and isinstance(cloud, (str, os.PathLike)):
            cloud = PointSource.open(cloud, format=format, spill_dir=self.root)
        self.sources[name] = _source(cloud, self.root, name)
        return self._bucket([name])

    def drop(self, name: str) -> None:
        """Remove the buckets (and a spilled copy) of cloud ``name``: its disk space back."""
        self.sources.pop(name, None)
        shutil.rmtree(Path(self.root, name), ignore_errors=True)
        Path(self.root, f"{name}.npy").unlink(missing_ok=True)

    def tasks(self, step: str, func, jobs: list, summed: tuple, unit: str = "tile") -> list:
        """Run the jobs; time the step (wall) and sum the tasks' own timings named ``summed``;
        the progress bar counts ``unit`` (a tile, a slice of a file)."""
        t = time.perf_counter()
        results = _run(self.executor, func, jobs, {"bucket": "reading and tiling"}.get(step, f"{step} tiles"), unit)
        self.timings[step] = self.timings.get(step, 0.0) + time.perf_counter() - t  # a step run again adds up
        for name in summed:
            self.timings[name] = self.timings.get(name, 0.0) + sum(r[name] for r in results)
        return results

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        """Close the client and the local cluster, and remove the work folder whatever happens
        (an error, Ctrl-C, SIGTERM turned into an exception by ``sdp``'s ``main``).

        A run that failed or was interrupted stops its local workers at once: a graceful close
        waits for the tasks they are running (seconds each), and their results are not wanted."""
        executor, cluster = getattr(self, "executor", None), getattr(self, "cluster", None)
        # the connections to workers just stopped close as the client and cluster do: distributed
        # logs that (INFO, with a traceback) from its own thread; the command's error is the one line
        quiet = logging.getLogger("distributed")
        level = quiet.level
        quiet.setLevel(logging.CRITICAL)
        try:
            if executor is not None and not isinstance(executor, str):
                if exc and exc[0] is not None and cluster is not None:
                    _stop_workers(cluster)
                executor.close()
        finally:
            try:
                if getattr(self, "cluster", None) is not None:
                    self.cluster.close()  # stops the workers: nothing writes into the buckets any more
            finally:
                quiet.setLevel(level)
                shutil.rmtree(self.root, ignore_errors=True)


def _stop_workers(cluster) -> None:
    """Kill the worker processes of the run's own local cluster (their nannies' children)."""
    for nanny in list(getattr(cluster, "workers", {}).values()):
        pid = getattr(nanny, "pid", None)
        if pid:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGTERM)  # no clean-up in the worker: a graceful close would wait for its task


def sampled_lattice(clouds: list, *, voxel_size: float | str = DEFAULTS.voxel_size, k: float = DEFAULTS.k,
                    sigma_voxels: float | str = DEFAULTS.sigma_voxels) -> tuple[float, float]:
    """(voxel, σ in voxels) as :func:`sdp.fields._spacing.resolve_lattice`, ``"auto"`` measured on the
    first slice of each cloud (a path, :class:`~sdp.io.PointSource` or array): clouds too large
    to read whole."""
    from ..fields._spacing import resolve_lattice

    if not isinstance(voxel_size, str):
        return resolve_lattice([], voxel_size=voxel_size, sigma_voxels=sigma_voxels)
    return resolve_lattice(first_slices(clouds), voxel_size=voxel_size, k=k, sigma_voxels=sigma_voxels)


def first_slices(clouds: list) -> list:
    """The first slice of each cloud (a path, :class:`~sdp.io.PointSource` or array), validated:
    what the tiles measure spacing and scales on before they read the points."""
    from .._core._points import as_points

    firsts = []
    for c in clouds:
        if isinstance(c, (str, os.PathLike)):
            c = PointSource.open(c)
        firsts.append(as_points(next(c.chunks())[1] if isinstance(c, PointSource) else c))
    return firsts


def _source(s, root: str, epoch: str) -> PointSource:
    if isinstance(s, PointSource):
        return s
    if isinstance(s, (str, os.PathLike)):
        return PointSource.open(s, spill_dir=root)
    xyz = np.asarray(s, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise InvalidPointsError(f"{epoch} points must be an (n, 3) array, got shape {xyz.shape}")
    path = Path(root, f"{epoch}.npy")
    np.save(path, xyz)
    return PointSource.open(path)


def _tiling(sources: dict, voxel_size: float, tile_size: float | None, tile_points: int, sigma_voxels: float,
            truncate: float, halo: float | None = None, halo_sigmas: float = 0.0) -> Tiling:
    if halo is None:
        halo = (math.ceil(truncate * sigma_voxels) + 3) * voxel_size  # kernel reach + binning + interpolation + margin
    halo = max(halo, halo_sigmas * sigma_voxels * voxel_size)
    cell = BLOCK * voxel_size
    if tile_size is None:  # tile_points in the tile and its halo at the mean density: whole blocks, rounded down
        blocks = math.floor((math.sqrt(tile_points / max(_density(sources), 1e-12)) - 2 * halo) / cell)
    else:  # a tile wider than the clouds is one tile: its size in blocks stays a small number
        lo = np.min([s.lo for s in sources.values()], axis=0)
        hi = np.max([s.hi for s in sources.values()], axis=0)
        span = float(np.max(hi[:2] - lo[:2])) + cell
        blocks = math.ceil(min(tile_size, span) / cell) if math.isfinite(span) else math.ceil(tile_size / cell)
    blocks = max(1, blocks, math.ceil(2 * halo / cell))
    return Tiling(voxel_size, blocks, halo)


def _check_tile_directory(tiling: Tiling, lo, hi, reach: int, share: TaskShare) -> None:
    """Refuse, before any task runs, tiles whose block directory alone exceeds a task's share of
    the memory limit (a voxel far below the point spacing: 1e-9 for metres). A tile's field spans
    its points, which lie in the clouds' box [lo, hi]: no wider than that, however wide the tile."""
    x, y = np.minimum(tiling.edge + 2 * tiling.halo, np.asarray(hi[:2], float) - np.asarray(lo[:2], float))
    z = float(hi[2]) - float(lo[2])
    blocks = [(extent / tiling.voxel_size + 2 * reach + 2 * BLOCK) / BLOCK for extent in (x, y, z)]
    check_memory(float(np.prod(blocks)) * 5, f"the block directory of one tile (voxel {tiling.voxel_size:g}, tile "
                 f"edge {tiling.edge:.4g})", share,
                 advice="give a smaller --tile-size (the tiles' width follows the clouds' mean density over their "
                        "box, which a few far outliers lower), or use a larger voxel size")


#: Seconds to wait for a ``dask.distributed`` scheduler to answer.
CONNECT_TIMEOUT = 10


#: Run in each local worker process as it starts (a Dask preload): Ctrl-C in a terminal reaches the
#: whole process group, and the client, not each worker, ends the run (a worker would print a
#: KeyboardInterrupt traceback); the client closes the cluster on its way out.
_WORKER_PRELOAD = """
import signal, threading
if threading.current_thread() is threading.main_thread():
    signal.signal(signal.SIGINT, signal.SIG_IGN)
"""


def _dask(module: str):
    """``dask`` or ``dask.distributed`` (the ``tiles`` extra), or a one-line :class:`~sdp.MissingDependencyError`."""
    return require(module, "tiles", "the tiled path (Dask)")


_TRACKER_WARNING = "ignore:resource_tracker:UserWarning"


def _connect(scheduler: str | None, workers: int, root: str):
    """(executor, cluster): a distributed ``Client`` (and the local cluster it drives, its
    workers' scratch space in the work folder ``root``), or the name of a Dask local scheduler."""
    if scheduler in ("synchronous", "threads"):
        return scheduler, None
    distributed = _dask("dask.distributed")
    Client, LocalCluster = distributed.Client, distributed.LocalCluster

    if scheduler is None:  # the tasks bound their own memory (``share``): no pausing by distributed
        # an interrupted run stops its workers at once (_stop_workers); the nannies' queues then
        # end with the process, and multiprocessing's resource tracker (started with this
        # process's warning options) would warn of "leaked semaphores" it reclaims anyway
        if _TRACKER_WARNING not in sys.warnoptions:
            sys.warnoptions.append(_TRACKER_WARNING)
        try:
            with _sigint_deferred() as interrupted, _dask("dask").config.set({"temporary-directory": root}):
                cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, memory_limit=0,
                                       dashboard_address=":0", env={"NUMBA_NUM_THREADS": "1"},  # a core per worker
                                       # a task's error reaches the client, which says it in one line: no
                                       # "Compute Failed" logs, no warnings about tasks cancelled on Ctrl-C
                                       silence_logs=logging.CRITICAL,
                                       preload=[_WORKER_PRELOAD])  # scratch space in root: removed with it
                try:
                    client = Client(cluster)
                except BaseException:
                    cluster.close()
                    raise
        except Exception as exc:
            # a Ctrl-C to the process group reaches the workers while they start, before they ignore it:
            # they die and the cluster fails to start ("Nanny failed to start"); the command was interrupted
            if interrupted():
                raise KeyboardInterrupt from None
            reason = str(exc).splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise SDPError(f"the local Dask cluster did not start ({reason})") from None
        if interrupted():
            client.close()
            cluster.close()
            raise KeyboardInterrupt
        return client, cluster
    try:
        return Client(scheduler, timeout=CONNECT_TIMEOUT), None
    except (OSError, TimeoutError, ValueError) as exc:  # refused, unreachable, or not an address
        reason = str(exc).splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise SDPError(f"can't reach the Dask scheduler at {scheduler} within {CONNECT_TIMEOUT} s ({reason}); "
                       "start it (dask scheduler) or check the address") from None


@contextlib.contextmanager
def _sigint_deferred():
    """Hold Ctrl-C back in the block (main thread only), and tell afterwards whether it came."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: False
        return
    hits = []
    previous = signal.signal(signal.SIGINT, lambda *_: hits.append(True))
    try:
        yield lambda: bool(hits)
    finally:
        signal.signal(signal.SIGINT, previous)


#: Retries of a task that raised (a shared file system's passing error); a task whose worker died
#: is rescheduled by Dask itself, up to its scheduler's ``allowed-failures``.
TASK_RETRIES = 1


def _guarded(func, *args):
    """``func(*args)`` in a Dask worker. Distributed sends a ``MemoryError`` back as a bare
    ``Exception`` holding its repr, which the command could not tell from a fault of its own: a
    tile's grid beyond its share of the memory limit (:class:`GridTooLargeError`, a MemoryError
    too) goes back as the :class:`SDPError` it is, in one line, and so does a tile that ran out of
    memory."""
    try:
        return func(*args)
    except GridTooLargeError as exc:
        message = f"a tile: {exc}"
    except MemoryError:
        message = "a tile ran out of memory in its worker: give a larger --memory-limit, or a smaller --tile-size"
    # raised outside the handler: distributed looks at the error this one happened in, and would see the
    # MemoryError again
    raise SDPError(message)


def _run(executor, func, jobs: list, what: str, unit: str = "tile") -> list:
    """func(*job) for every job, in order, on a distributed ``Client`` or a local Dask scheduler (its name).

    The first task that fails for good stops the run: the others are cancelled and its error
    is raised (a worker lost more often than the scheduler allows: :class:`WorkerLostError`).
    """
    if not jobs:
        return []
    if isinstance(executor, str):
        dask = _dask("dask")

        return list(dask.compute(*[dask.delayed(func, pure=False)(*job) for job in jobs], scheduler=executor))
    distributed = _dask("dask.distributed")

    futures = executor.map(functools.partial(_guarded, func), *zip(*jobs, strict=True), pure=False,
                           retries=TASK_RETRIES)
    try:
        with bar(len(futures), what, unit=unit) as pb:
            for future in distributed.as_completed(futures):
                if future.status == "error":
                    future.result()  # raises the task's error: no waiting for the other tasks
                pb.update(1)
        return executor.gather(futures)
    except distributed.KilledWorker as exc:
        worker = getattr(exc.args[1], "address", "?") if len(exc.args) > 1 else "?"
        tries = exc.args[2] + 1 if len(exc.args) > 2 else 1
        raise WorkerLostError(f"{what}: the Dask workers running one task died {tries} time(s) (the last: {worker}); "
                              "the run was stopped: check the workers' memory and logs") from None
    finally:
        executor.cancel([f for f in futures if not f.done()])

