"""The memory of a tiled job: one limit for the whole job, shared by the command and the workers.

The command takes a fixed share (its process and the streamed output's chunk); the rest is split
over the workers, and each worker's share less its own process is one task's, which sets the
tile size and the rows decoded at a time (:class:`JobBudget`). The module docstring of
:mod:`sdp.scale._tiles` says what is counted and what is not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .._core._memory import format_bytes
from .._core._validate import positive_finite
from ..errors import GridTooLargeError
from ..fields._lattice import kernel_reach

__all__ = ["BYTES_PER_ROW_READ", "BYTES_PER_TILE_POINT", "dense_grid_bytes", "BYTES_PER_POINT_IN_MEMORY",
           "PROCESS_BYTES", "untiled_point_bytes", "CLIENT_BYTES", "WORKER_BYTES", "WRITE_BYTES", "megabytes",
           "JobBudget", "TaskShare"]


BYTES_PER_ROW_READ = 600  # a decoded row in a bucketing task: record, x y z, tile keys, sort, bucket record
BYTES_PER_TILE_POINT = 1200  # a point of one epoch in a compare task: bucket record, its share of two fields
# (blocks, blur buffer, difference), masks: the 100 M-point benchmark peaked at 3.4 GiB (client and 2 workers)
# with 1.2 M points per tile and epoch


def dense_grid_bytes(lo, hi, voxel_size: float, *, sigma_voxels: float = 2.0, truncate: float = 3.0) -> float:
    """Bytes of one float32 dense grid over the box [lo, hi] with its kernel margin: the size
    at which :func:`detect_changes_tiled` is worth its overhead (``sdp change`` switches when
    two of them exceed the memory limit). Infinite when the box has no finite size in nodes (a
    1e-300 voxel, coordinates near ±1e308)."""
    reach = kernel_reach(sigma_voxels, truncate)
    nodes = np.floor((np.asarray(hi, float) - np.asarray(lo, float)) / positive_finite("voxel_size", voxel_size))
    with np.errstate(over="ignore", invalid="ignore"):
        total = float(np.prod(nodes + 2 * reach + 2)) * 4
    return total if np.isfinite(total) else math.inf


#: Resident bytes of ``sdp change`` in memory, per point of both clouds: float64 x, y, z, the file
#: records, the fields' share, masks, labels and the output's records (measured: 1.26 GiB at the peak
#: for two LAZ clouds of 2.9 M and 3 M points at 1 m voxels, the process itself included).
BYTES_PER_POINT_IN_MEMORY = 200


#: The in-memory command's process before any data: the interpreter, NumPy, SciPy and Numba's kernels
#: (measured: 197 MiB after a small comparison).
PROCESS_BYTES = 224 * 2**20


def check_process_fits(cap: float) -> None:
    """Refuse a memory limit ``cap`` (bytes) the process itself exceeds: the limit is the whole
    job's, in every command."""
    if PROCESS_BYTES >= cap:
        raise GridTooLargeError(f"the process itself needs about {format_bytes(PROCESS_BYTES)}, above the memory "
                                f"limit of {format_bytes(cap)}: raise the memory limit (--memory-limit, "
                                "$SDP_MEMORY_LIMIT)")


def untiled_point_bytes(n_points: int) -> int:
    """Bytes the in-memory comparison of ``n_points`` (both clouds) holds at its peak, the process
    itself included (the fields' blocks are checked against the memory limit when allocated)."""
    return PROCESS_BYTES + int(n_points) * BYTES_PER_POINT_IN_MEMORY


#: Resident memory of the processes themselves, before any data (measured here: 220 MiB for the
#: command with NumPy, Numba's kernels, Dask's client and the local scheduler; 210 MiB for a Dask
#: worker that has run a tile), and of the streamed output in the command (a chunk of LAS records
#: read, its labelled copy and the LAZ encoder's buffers).
CLIENT_BYTES = 256 * 2**20
WORKER_BYTES = 256 * 2**20


WRITE_BYTES = 2_000_000 * 120


def megabytes(nbytes: float) -> str:
    """A size in whole MB, rounded up, as ``--memory-limit`` reads it."""
    return f"{math.ceil(nbytes / 2**20)}MB"


@dataclass(frozen=True)
class JobBudget:
    """How one memory limit is shared by the processes of a tiled run: the command (``client``:
    its process and the streamed output; not counted: the changed rows and the face nodes of the
    regions, ≈ 48 bytes per changed point, and the result's rows, which the command never turns
    into per-point arrays) and each of ``workers`` (its process and one task's
    data); with ``separate=False`` the tasks run in the command's own process (Dask's local
    schedulers), ``workers`` of them at once."""

    limit: int
    workers: int
    separate: bool = True

    @property
    def client(self) -> int:
        """The command's share: its process and the streamed output's chunk."""
        return CLIENT_BYTES + WRITE_BYTES

    @property
    def worker(self) -> int:
        """The memory of one worker: what the command leaves, over the workers."""
        return (self.limit - self.client) // self.workers

    @property
    def task(self) -> int:
        """The data one task may hold: a worker's share less the worker process itself."""
        return self.worker - (WORKER_BYTES if self.separate else 0)

    @property
    def task_budget(self) -> str:
        """What :attr:`task` is, and its size, for messages."""
        itself = f", less {format_bytes(WORKER_BYTES)} for the worker itself" if self.separate else ""
        return (f"a task's share ({format_bytes(self.task)}) of the memory limit of {format_bytes(self.limit)} (less "
                f"{format_bytes(self.client)} for the command, over {self.workers} worker(s){itself})")

    def parts(self) -> str:
        """Who takes what, for messages."""
        each = (f"each of {self.workers} Dask worker(s) {format_bytes(WORKER_BYTES)} plus its tile" if self.separate
                else f"each of {self.workers} task(s) its tile")
        return f"the command itself takes {format_bytes(self.client)} and {each}"

    def smallest(self, task_bytes: float) -> int:
        """The smallest limit under which a task may hold ``task_bytes``."""
        return int(self.client + self.workers * (task_bytes + (WORKER_BYTES if self.separate else 0)))


class TaskShare(int):
    """A task's share of a tiled job's memory limit (bytes, :attr:`JobBudget.task`), given to the
    tasks as their memory limit: a refusal (:func:`sdp._core._memory.check_memory`) names it as a
    share of the job's limit, not as the limit, and gives the limit whose share would hold the work.

    ``edge``: the tiles' edge, with ``sized`` when it follows from the share (no ``--tile-size``):
    such tiles grow with the limit, and so does what a task holds, so a larger limit alone does
    not help; with their edge given, it does."""

    def __new__(cls, job: JobBudget, edge: float | None = None, sized: bool = False):
        share = super().__new__(cls, job.task)
        share.job, share.edge, share.sized = job, edge, sized
        return share

    def __reduce__(self):  # to the Dask workers with what it is
        return (TaskShare, (self.job, self.edge, self.sized))

    def beyond(self, nbytes: float) -> tuple[str, str]:
        """(what the share is, the limit that holds ``nbytes``), for a refusal of ``nbytes``."""
        limit = megabytes(self.job.smallest(nbytes))
        if self.sized and self.edge is not None:
            step = 10.0 ** (math.floor(math.log10(self.edge)) - 3)
            edge = math.floor(self.edge / step) * step  # 4 digits, rounded down: not a block wider than these tiles
            return self.job.task_budget, (f"give --tile-size {edge:.4g} (these tiles' edge: tiles sized from the "
                                          f"limit grow with it) with --memory-limit {limit} or more")
        return self.job.task_budget, f"give --memory-limit {limit} or more"
