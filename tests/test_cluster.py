"""The tiles on a real Dask cluster: a ``dask scheduler`` and two ``dask worker`` processes started
from the command line, as on separate hosts (no LocalCluster), sharing a work folder; and the
same with a worker killed while it holds a tile of the compare stage."""

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np
import pytest
from conftest import box_surface, write_las

# one xdist worker runs them all (--dist loadgroup): the pair is made once, one cluster at a time
pytestmark = [pytest.mark.slow, pytest.mark.xdist_group("cluster")]

BIN = Path(sys.executable).parent
PRELOAD = Path(__file__).with_name("cluster_stall.py")
UTM = np.array([630_000.0, 4_830_000.0, 100.0])


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """Two LAZ epochs of a 24 m × 16 m street (60 k points each), boxes gone and new, and the
    in-memory result to hold the cluster's against."""
    rng = np.random.default_rng(7)
    folder = tmp_path_factory.mktemp("pair")

    def street(boxes, n=60_000):
        ground = np.c_[rng.uniform(0, 24, n), rng.uniform(0, 16, n), 0.01 * rng.standard_normal(n)]
        return np.concatenate([ground, *(box_surface(rng, lo, hi, 3000) for lo, hi in boxes)]) + UTM

    a = write_las(folder / "a.laz", street([([2, 2, 0], [4, 5, 1.5]), ([11, 5.5, 0], [13, 6.5, 2])]))
    b = write_las(folder / "b.laz", street([([2, 2, 0], [4, 5, 1.5]), ([5.5, 11.5, 0], [6.8, 12.8, 1.2]),
                                            ([19, 3, 0], [20, 4, 1])]))
    local = sdp_change(a, b, folder / "local.laz")
    assert local.returncode == 0, local.stderr
    return a, b, read(folder / "local.laz"), read(folder / "local_disappeared.laz")


def sdp_change(a, b, out, *options, wait=True):
    cmd = [str(BIN / "sdp"), "change", str(a), str(b), "-o", str(out), "--voxel-size", "0.1", "--both",
           "--quiet", *map(str, options)]
    if wait:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=300)  # a guard against a hang
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)


def read(path):
    las = laspy.read(str(path))
    return {"change": np.asarray(las.change), "region": np.asarray(las.region), "intensity": np.asarray(las.intensity)}


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Cluster:
    """A scheduler and workers, each its own process group, all killed at the end."""

    def __init__(self, folder: Path, allowed_failures: int):
        self.folder, self.procs, self.port = folder, {}, free_port()
        self.address = f"tcp://127.0.0.1:{self.port}"
        self.env = dict(os.environ, NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1",
                        DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES=str(allowed_failures))
        self.start("scheduler", "scheduler", "--host", "127.0.0.1", "--port", str(self.port), "--no-dashboard")

    def start(self, name, *args, **env):
        log = open(self.folder / f"{name}.log", "w")
        self.procs[name] = subprocess.Popen([str(BIN / "dask"), *args], stdout=log, stderr=subprocess.STDOUT,
                                            env=dict(self.env, **env), start_new_session=True)

    def worker(self, name, **env):
        self.start(name, "worker", self.address, "--name", name, "--nthreads", "1", "--memory-limit", "0",
                   "--no-dashboard", "--preload", str(PRELOAD), **env)

    def wait_for_workers(self, n, timeout=180):  # a guard against a hang
        from dask.distributed import Client

        with Client(self.address, timeout=timeout) as client:
            client.wait_for_workers(n, timeout=timeout)

    def kill(self, name):
        proc = self.procs.pop(name)
        try:
            os.killpg(proc.pid, signal.SIGKILL)  # the nanny and its worker process
        except ProcessLookupError:
            pass
        proc.wait(timeout=30)

    def close(self):
        for name in list(self.procs):
            self.kill(name)


@pytest.fixture
def cluster(tmp_path):
    made = []

    def start(*, allowed_failures=3, stall=False):
        c = Cluster(tmp_path, allowed_failures)
        made.append(c)
        stalls = tmp_path / "stalls"
        stalls.mkdir(exist_ok=True)
        c.worker("a", **({"SDP_TEST_STALL": str(stalls)} if stall else {}))
        c.worker("b")
        c.wait_for_workers(2)
        return c

    yield start
    for c in made:
        c.close()


def run_on(cluster, pair, folder, *, kill_a=False):
    """``sdp change`` on the cluster, tiles of 4 m (24 tiles); with ``kill_a`` worker a is killed
    once it holds a compare tile. Returns (completed process, output folder, work folder)."""
    out, work = folder / "out", folder / "work"
    out.mkdir()
    work.mkdir()
    proc = sdp_change(*pair[:2], out / "c.laz", "--tiled", "--tile-size", "4", "--scheduler", cluster.address,
                      "--workdir", work, wait=False)
    try:
        if kill_a:  # the event: worker a holds a compare tile (or the run ended without it: a failure)
            while not any((folder / "stalls").iterdir()):
                assert proc.poll() is None, ("worker a never took a compare tile", proc.communicate())
                time.sleep(0.05)
            cluster.kill("a")
        stdout, stderr = proc.communicate(timeout=300)  # a guard against a hang, not a measure of speed
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr), out, work


def assert_same(out, pair):
    for suffix, expected in (("", pair[2]), ("_disappeared", pair[3])):
        got = read(out / f"c{suffix}.laz")
        for name in ("change", "region", "intensity"):
            np.testing.assert_array_equal(got[name], expected[name], err_msg=f"{name}{suffix}")
    assert (pair[2]["change"] == 1).sum() > 2000 and (pair[3]["change"] == 1).sum() > 1000


def test_a_cluster_gives_the_local_result(cluster, pair, tmp_path):
    r, out, work = run_on(cluster(), pair, tmp_path)
    assert r.returncode == 0, r.stderr
    assert_same(out, pair)
    assert sorted(p.name for p in out.iterdir()) == ["c.laz", "c_disappeared.laz"]
    assert list(work.iterdir()) == []  # the buckets are gone


def test_a_worker_killed_in_the_compare_stage(cluster, pair, tmp_path):
    """Dask runs the lost tile again on the other worker: the same result."""
    r, out, work = run_on(cluster(stall=True), pair, tmp_path, kill_a=True)
    assert r.returncode == 0, r.stderr
    assert_same(out, pair)
    assert list(work.iterdir()) == []


def test_a_lost_worker_beyond_the_allowed_failures_stops_the_run(cluster, pair, tmp_path):
    """A scheduler that allows no failure: one line, exit 2, no output at all, no buckets left."""
    r, out, work = run_on(cluster(allowed_failures=0, stall=True), pair, tmp_path, kill_a=True)
    assert r.returncode == 2, r.stderr
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("sdp: error: ") and "died" in r.stderr, r.stderr
    assert list(out.iterdir()) == [] and list(work.iterdir()) == []


def _too_big(x):
    from sdp.errors import GridTooLargeError

    raise GridTooLargeError(f"tile {x}: 787,284 blocks would need 1.57 GB")


def _out_of_memory(x):
    raise MemoryError


@pytest.mark.slow
def test_a_tiles_memory_error_comes_back_as_one_sdp_error():
    """Distributed sends a MemoryError (GridTooLargeError is one) back as a bare Exception holding its
    repr, which the command printed as a traceback (exit 1): the tasks send it as an SDPError."""
    from dask.distributed import Client, LocalCluster

    import sdp
    from sdp.scale._session import _run

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as cluster, \
            Client(cluster) as client:
        with pytest.raises(sdp.SDPError, match="a tile: tile 1: 787,284 blocks would need 1.57 GB"):
            _run(client, _too_big, [(1,)], "compare")
        with pytest.raises(sdp.SDPError, match="ran out of memory"):
            _run(client, _out_of_memory, [(1,)], "compare")
