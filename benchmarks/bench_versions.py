"""Two versions of sdp on the same Kinect pairs, interleaved in one process (is a change faster?).

On a shared machine the speed of everything drifts by 10-30 % over minutes, more than most changes
gain, so runs of two checkouts one after the other do not tell them apart. Here the other version's
package (``OTHER/src/sdp`` of another checkout, e.g. ``git worktree add /tmp/before <commit>``) is
copied under the name ``sdp_other`` and imported beside this checkout's ``sdp``; on each of the 27
fixed-camera mOSD pairs (``bench_decision.labelled_pairs``) both run ``detect_changes`` with their
defaults, alternately, ``REPEAT`` times each, the fastest of each counted (wall and CPU time). Also
checks that both give the same ``change`` fields.

    python benchmarks/bench_versions.py /tmp/before/src/sdp [LABEL]

Prints markdown and writes benchmarks/results/versions.md. Needs ../shared/data (about 2 minutes;
the other version's kernels compile on the first pair).
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_decision import LEARN, labelled_pairs

import sdp

RESULTS = Path(__file__).resolve().parents[1] / "benchmarks" / "results"
REPEAT = 5


def load_other(package: Path, into: Path):
    """The sdp package at ``package`` imported as ``sdp_other`` (sdp's modules import each other
    relatively, so a copy under another name is a second, independent package)."""
    shutil.copytree(package, into / "sdp_other", ignore=shutil.ignore_patterns("__pycache__"))
    sys.path.insert(0, str(into))
    import sdp_other

    return sdp_other


def main():
    if len(sys.argv) < 2 or not LEARN.is_dir():
        print(__doc__ if len(sys.argv) < 2 else f"skipped: {LEARN} not found")
        return
    label = sys.argv[2] if len(sys.argv) > 2 else sys.argv[1]
    with tempfile.TemporaryDirectory() as tmp:
        versions = {"other": load_other(Path(sys.argv[1]), Path(tmp)), "this": sdp}
        pairs = [(sdp.read_points(LEARN / f"learn{t - 1}.pcd"), sdp.read_points(LEARN / f"learn{t}.pcd"))
                 for t, *_ in labelled_pairs()]
        for v in versions.values():  # kernels loaded (or compiled) before timing
            v.detect_changes(*pairs[0])
        wall = {k: [] for k in versions}
        cpu = {k: [] for k in versions}
        same = True
        load = [os.getloadavg()[0]]
        for ref, cur in pairs:
            w = {k: [] for k in versions}
            c = {k: [] for k in versions}
            fields = {}
            for _ in range(REPEAT):
                for k, v in versions.items():
                    t, p = time.perf_counter(), time.process_time()
                    r = v.detect_changes(ref, cur)
                    w[k].append(time.perf_counter() - t)
                    c[k].append(time.process_time() - p)
                    fields[k] = (r.current_state, r.reference_state)
            same &= all(np.array_equal(a, b) for a, b in zip(fields["other"], fields["this"]))
            for k in versions:
                wall[k].append(min(w[k]))
                cpu[k].append(min(c[k]))
        load.append(os.getloadavg()[0])
    ratio = np.array(wall["this"]) / np.array(wall["other"])
    lines = ["# Two versions of sdp, interleaved (`benchmarks/bench_versions.py`)\n",
             f"{time.strftime('%Y-%m-%d %H:%M')}, {os.cpu_count()} cores, load average (1 min) "
             f"{min(load):.1f}–{max(load):.1f}. {len(pairs)} mOSD pairs, `detect_changes` with the defaults "
             f"(sensor origin from the files), each version {REPEAT}× per pair in turn, the fastest counted; "
             f"medians over the pairs.\n",
             "| version | wall (ms) | CPU (ms) |", "|---|---:|---:|",
             f"| other: `{label}` | {1e3 * np.median(wall['other']):.1f} | {1e3 * np.median(cpu['other']):.1f} |",
             f"| this checkout | {1e3 * np.median(wall['this']):.1f} | {1e3 * np.median(cpu['this']):.1f} |",
             "",
             f"This ÷ other, per pair: median {np.median(ratio):.3f} (range {ratio.min():.3f}–{ratio.max():.3f}). "
             f"Same `change` fields on every pair: {same}.", ""]
    print("\n".join(lines))
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "versions.md").write_text("\n".join(lines))


if __name__ == "__main__":
    main()
