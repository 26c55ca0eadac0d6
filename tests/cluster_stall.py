"""A hook that holds a tiled run at a known stage, for tests that must act at that moment (kill a
worker, signal the command) instead of at one guessed with a timer.

Loaded as a Dask worker preload by tests/test_cluster.py (``dask worker --preload cluster_stall.py``),
and imported before the command by the signal tests of tests/test_bad_input.py, whose local workers
then receive this module's functions as their tasks (Dask names a task's function by module and
name) and import it. With ``$SDP_TEST_STALL`` (a folder) set, the first task of the stage
``$SDP_TEST_STALL_AT`` writes ``stalled-<pid>`` into that folder and then waits (60 s at most), so
that the test knows the run is alive at that stage:

- ``bucket``: a worker reading and bucketing a slice of a cloud;
- ``compare`` (the default): a worker comparing a tile, the cluster up and the buckets written;
- ``write``: the command itself, writing the streamed LAS/LAZ output after every tile.

Other processes, and every other task, run the library's own functions.
"""

import os
import time
from pathlib import Path

import sdp.io._source
import sdp.scale._session
import sdp.scale._tiles


def _original(function):
    return getattr(function, "__wrapped__", function)  # this module may be imported twice (Dask)


def _stall(stage: str, note) -> None:
    folder = os.environ.get("SDP_TEST_STALL")
    if folder and os.environ.get("SDP_TEST_STALL_AT", "compare") == stage:
        os.environ.pop("SDP_TEST_STALL")  # once: if the test does not stop this process, it goes on
        Path(folder, f"stalled-{os.getpid()}").write_text(str(note))
        time.sleep(60)


def _stalling(stage: str, function):
    function = _original(function)

    def stalling(*args, **kwargs):
        _stall(stage, args[0] if args else "")
        return function(*args, **kwargs)

    stalling.__wrapped__ = function
    stalling.__name__ = stalling.__qualname__ = f"_stalling_{function.__name__.lstrip('_')}"
    globals()[stalling.__name__] = stalling  # found by name on the workers (cloudpickle by reference)
    return stalling


sdp.scale._tiles._compare_tile = _stalling("compare", sdp.scale._tiles._compare_tile)
sdp.scale._session._bucket_part = _stalling("bucket", sdp.scale._session._bucket_part)
sdp.io._source.write_points_streamed = _stalling("write", sdp.io._source.write_points_streamed)
