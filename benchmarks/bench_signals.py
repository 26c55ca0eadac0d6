"""How fast an interrupted tiled run ends: the time from the signal to the command's exit, at each
stage, with nothing left behind (issue 32's bar: 130/143 within 3 s).

Usage: bench_signals.py [POINTS] [REPEATS]

Each run is ``sdp change a.npy b.npy -o o.laz --tiled`` on two random clouds of POINTS points
(default 2,000,000), held at a known moment by the hook of ``tests/cluster_stall.py`` (a worker's
first bucketing or compare task, or the command's streamed writer, which then waits 60 s), then
sent SIGINT or SIGTERM. Printed per stage and signal: the exit status, the seconds from the
signal to the exit (median and largest of REPEATS, default 3), and whether anything was left (an
output, a temporary file, the tiles' work folder, Dask's scratch space). The load of the machine
is printed with them: the time grows with it.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HOOK = Path(__file__).resolve().parent.parent / "tests"
COMMAND = [sys.executable, "-c", "import runpy, signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
           "import cluster_stall; runpy.run_module('sdp.cli', run_name='__main__', alter_sys=True)"]


def one(folder: Path, stage: str, sig: int) -> tuple[int, float, list[str]]:
    stalls, scratch = folder / "stalls", folder / "tmp"
    for d in (stalls, scratch):
        d.mkdir(exist_ok=True)
        for f in d.iterdir():
            f.unlink()
    env = dict(os.environ, TMPDIR=str(scratch), SDP_TEST_STALL=str(stalls), SDP_TEST_STALL_AT=stage,
               PYTHONPATH=os.pathsep.join(filter(None, [str(HOOK), os.environ.get("PYTHONPATH")])))
    p = subprocess.Popen([*COMMAND, "change", "a.npy", "b.npy", "-o", "o.laz", "--tiled", "-q"], cwd=folder, env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    while not any(stalls.iterdir()):
        if p.poll() is not None:
            raise SystemExit(f"the run ended before it was held at {stage}")
        time.sleep(0.01)
    t = time.perf_counter()
    p.send_signal(sig)
    status = p.wait()
    seconds = time.perf_counter() - t
    left = [f.name for f in folder.iterdir() if f.name not in ("a.npy", "b.npy", "stalls", "tmp")]
    left += [f"tmp/{f.name}" for f in scratch.iterdir()]
    return status, seconds, left


def main() -> None:
    n = int(float(sys.argv[1])) if len(sys.argv) > 1 else 2_000_000
    repeats = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as d:
        folder = Path(d)
        for name in ("a.npy", "b.npy"):
            np.save(folder / name, rng.random((n, 3)) * [200, 200, 5])
        print(f"{n:,} points per cloud; load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        print("| stage | signal | status | s to exit (median, max) | left |\n|---|---|---|---|---|")
        for stage in ("bucket", "compare", "write"):
            for sig in (signal.SIGINT, signal.SIGTERM):
                runs = [one(folder, stage, sig) for _ in range(repeats)]
                times = sorted(r[1] for r in runs)
                left = sorted({x for r in runs for x in r[2]})
                print(f"| {stage} | {signal.Signals(sig).name} | {sorted({r[0] for r in runs})} | "
                      f"{times[len(times) // 2]:.2f}, {times[-1]:.2f} | {', '.join(left) or 'nothing'} |", flush=True)
        print(f"load after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
