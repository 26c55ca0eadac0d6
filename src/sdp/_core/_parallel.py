"""Threads: the pool of :func:`map_concurrently`, and how Numba's OpenMP workers wait.

Kept in one module because both are process-wide. Parallel kernels (``parallel=True``, in
:mod:`sdp.fields._kernels` and :mod:`sdp.fields._volume_kernels`, which import this module first) run on
Numba's OpenMP layer. By default its idle workers spin before they sleep, and on a machine whose
cores are busy with other jobs a spinning worker is descheduled: each parallel kernel then waited
~10 ms for it (measured on 2 shared cores; 0.01 ms when workers sleep). So this module sets
``OMP_WAIT_POLICY=PASSIVE`` at import, before OpenMP starts (it reads the variable when the first
parallel kernel runs); an explicit ``OMP_WAIT_POLICY`` is kept. The number of threads is Numba's
``NUMBA_NUM_THREADS`` (the cores by default; :mod:`sdp.scale._tiles` sets 1 on its Dask workers).
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba as nb  # noqa: E402

__all__ = ["concurrent", "map_concurrently"]


def map_concurrently(fn, items, *, parallel_kernels: bool = False) -> list:
    """``[fn(x) for x in items]``, the items at once on several threads when Numba may use more
    than one thread (``NUMBA_NUM_THREADS``: the cores by default, 1 on the Dask workers of
    :mod:`sdp.scale._tiles`): the kernels release the GIL (``nogil=True``), so independent pieces of
    work (the two directions of a comparison, the spacing of two clouds) overlap. The calling
    thread takes the first item; the others go to a pool of threads kept for the process
    (starting threads per call delayed the second piece by up to 4 ms of a 6 ms job). Called
    from a pool thread, the items run in turn. ``parallel_kernels``: ``fn`` also calls parallel
    kernels; they may run from two threads at once only on a thread-safe Numba threading layer
    (OpenMP, TBB; not the fallback "workqueue"), else the items run in turn."""
    items = list(items)
    if len(items) < 2 or not concurrent(parallel_kernels=parallel_kernels):
        return [fn(x) for x in items]
    futures = [_pool().submit(fn, x) for x in items[1:]]
    try:
        first = fn(items[0])
    except BaseException:
        for f in futures:
            f.cancel()
        raise
    return [first, *(f.result() for f in futures)]


def concurrent(*, parallel_kernels: bool = False) -> bool:
    """Whether :func:`map_concurrently` would run its items at once here (not in turn): work split
    for it pays only then."""
    if nb.config.NUMBA_NUM_THREADS < 2 or getattr(_in_pool, "yes", False):
        return False
    if parallel_kernels:
        try:
            return nb.threading_layer() in ("omp", "tbb")
        except ValueError:  # no parallel kernel has run yet: the layer is not chosen
            return False
    return True


_in_pool = threading.local()  # .yes in the pool's threads
_pool_lock = threading.Lock()
_pool_executor: ThreadPoolExecutor | None = None


def _pool() -> ThreadPoolExecutor:
    global _pool_executor
    with _pool_lock:
        if _pool_executor is None:
            _pool_executor = ThreadPoolExecutor(max(nb.config.NUMBA_NUM_THREADS - 1, 1), "sdp",
                                                initializer=lambda: setattr(_in_pool, "yes", True))
        return _pool_executor
