"""A hook that holds a tiled run in its compare stage, for tests that must act at that moment (kill a
worker, signal the command) instead of at one guessed with a timer.

Loaded as a Dask worker preload by tests/test_cluster.py (``dask worker --preload cluster_stall.py``),
and imported before the command by the signal tests of tests/test_bad_input.py, whose local workers
then receive this module's function as the compare task (Dask names a task's function by module and
name) and import it. On a worker started with ``$SDP_TEST_STALL`` (a folder), the first compare
task writes ``stalled-<pid>`` into that folder and then waits (60 s at most), so that the test
knows the run is alive, its cluster up and its buckets written. Other workers, and every other
task, run the library's own function.
"""

import os
import time
from pathlib import Path

import sdp.scale._tiles

_compare_tile = getattr(sdp.scale._tiles._compare_tile, "__wrapped__", sdp.scale._tiles._compare_tile)  # imported twice by Dask


def _stalling_compare_tile(*args, **kwargs):
    folder = os.environ.get("SDP_TEST_STALL")
    if folder:
        os.environ.pop("SDP_TEST_STALL")  # once: if the test does not kill this worker, it goes on
        Path(folder, f"stalled-{os.getpid()}").write_text(str(args[0]))
        time.sleep(60)
    return _compare_tile(*args, **kwargs)


# Tasks name their function by module and name (cloudpickle), so the worker runs this one.
_stalling_compare_tile.__wrapped__ = _compare_tile
sdp.scale._tiles._compare_tile = _stalling_compare_tile
