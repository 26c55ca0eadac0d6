"""Peak memory of a whole ``sdp change`` job (the command and every process it starts), its time and kappa.

Usage: bench_tiled_memory.py EPOCH1 EPOCH2 OUT.laz [sdp change options...]
       bench_tiled_memory.py --floor EPOCH1 EPOCH2     (decode both, encode EPOCH2 once: the LAZ floor)

Runs ``sdp change EPOCH1 EPOCH2 -o OUT.laz OPTIONS``, sums the resident memory (RSS) of the
process and all its children (the Dask workers) every 0.2 s, and prints the peak of that sum,
the wall time, the CPU seconds of the command and its workers (a figure that contention on a shared
machine inflates less than the wall time), the command's own step timings and, when EPOCH2 holds the truth of "appeared" in
``user_data`` (``../shared/tools/city_epochs.py`` writes it so), kappa of the output's
``change == 1`` against it. Example (docs/benchmarks.md §5, "Clouds beyond memory, tiles")::

    python ../shared/tools/city_epochs.py 1e7 /tmp/city10m
    python benchmarks/bench_tiled_memory.py /tmp/city10m/epoch1.laz /tmp/city10m/epoch2.laz /tmp/c.laz \\
        --voxel-size 0.25 --memory-limit 2GB
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil


def tree_rss(proc: psutil.Process) -> int:
    """Resident bytes of ``proc`` and all its descendants (0 for those gone meanwhile)."""
    total = 0
    for p in [proc, *proc.children(recursive=True)]:
        try:
            total += p.memory_info().rss
        except psutil.Error:
            pass
    return total


def run(cmd: list[str], period: float = 0.2) -> tuple[int, float, subprocess.CompletedProcess, list]:
    """Run ``cmd``; (peak summed RSS, wall seconds, the completed process, the samples (s, bytes))."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ps = psutil.Process(proc.pid)
    samples: list[tuple[float, int]] = []
    done = threading.Event()

    def sample():
        while not done.is_set():
            samples.append((time.perf_counter() - t0, tree_rss(ps)))
            done.wait(period)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    out, err = proc.communicate()
    done.set()
    thread.join()
    wall = time.perf_counter() - t0
    return max((b for _, b in samples), default=0), wall, subprocess.CompletedProcess(cmd, proc.returncode, out,
                                                                                        err), samples


def floor(a: str, b: str) -> dict:
    """Wall and CPU seconds to decode both epochs and encode the second once, as the command's
    streamed output does (lazrs' parallel backend, chunks of 2 M points): what no change detection
    can beat."""
    import tempfile

    import laspy

    t, c = time.perf_counter(), time.process_time()
    for path in (a, b):
        with laspy.open(path, laz_backend=laspy.LazBackend.LazrsParallel) as r:
            for _ in r.chunk_iterator(2_000_000):
                pass
    decode = time.perf_counter() - t
    with tempfile.TemporaryDirectory() as tmp, laspy.open(b, laz_backend=laspy.LazBackend.LazrsParallel) as r, \
            laspy.open(str(Path(tmp, "o.laz")), mode="w", header=r.header, do_compress=True,
                       laz_backend=laspy.LazBackend.LazrsParallel) as w:
        for chunk in r.chunk_iterator(2_000_000):
            w.write_points(chunk)
    return {"decode_both_s": round(decode, 2), "decode_both_encode_one_s": round(time.perf_counter() - t, 2),
            "cpu_s": round(time.process_time() - c, 2)}


def main(argv: list[str]) -> int:
    if argv[:1] == ["--floor"] and len(argv) == 3:
        print(f"load (1 min) before: {os.getloadavg()[0]:.2f}")
        print(json.dumps(floor(*argv[1:])))
        return 0
    if len(argv) < 3:
        sys.exit(__doc__)
    a, b, out, *options = argv
    sdp = str(Path(sys.executable).with_name("sdp"))
    load = os.getloadavg()[0]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    peak, wall, r, samples = run([sdp, "change", a, b, "-o", out, "--json", *options])
    after = resource.getrusage(resource.RUSAGE_CHILDREN)  # the command and the workers it waited for
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    print(f"load (1 min) before: {load:.2f}, after: {os.getloadavg()[0]:.2f}")
    if r.returncode != 0:
        print(r.stderr.strip())
        print(f"exit {r.returncode} after {wall:.1f} s, peak {peak / 2**30:.2f} GiB")
        return r.returncode
    summary = json.loads(r.stdout)
    import laspy
    import numpy as np

    import sdp as S

    truth_las, got = laspy.read(b), laspy.read(out)
    line = {"wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "peak_rss_gib": round(peak / 2**30, 3),
            "tiles": summary.get("tiles"), "tile_size": summary.get("tile_size"),
            "timings": {k: round(v, 2) for k, v in summary["timings"].items()},
            "appeared": summary["current"]["appeared"],
            "regions": len(summary["appeared_regions"])}
    if "user_data" in truth_las.point_format.dimension_names:
        line["kappa"] = round(S.kappa(np.asarray(truth_las.user_data) == 1, np.asarray(got.change) == 1), 4)
    print(json.dumps(line))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
