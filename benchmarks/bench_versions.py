"""Two versions of sdp on the same Kinect pairs, interleaved in one process (is a change faster?).

On a shared machine the speed of everything drifts by 10-30 % over minutes, more than most changes
gain, so runs of two checkouts one after the other do not tell them apart. Here the other version's
package (``OTHER/src/sdp`` of another checkout, e.g. ``git worktree add /tmp/before <commit>``) is
copied under the name ``sdp_other`` and imported beside this checkout's ``sdp``; on each of the 27
fixed-camera mOSD pairs (``bench_decision.labelled_pairs``) both run ``detect_changes`` with their
defaults, alternately, ``REPEAT`` times each, the fastest of each counted (wall and CPU time). Also
checks that both give the same ``change`` fields.

    python benchmarks/bench_versions.py /tmp/before/src/sdp [LABEL] [--decision combined]

``--decision D`` runs this checkout with ``decision=D`` (the other version with its defaults):
issue 34's "time per Kinect pair no more than 1.3× today's in the same run", today's being the
code the issue was filed against (``git worktree add /tmp/before34 f6002a7``). Each version reads
the pairs with its own ``read_points``.

Prints markdown and writes benchmarks/results/versions.md (``versions-D.md`` with ``--decision D``).
Needs ../shared/data (about 2 minutes; the other version's kernels compile on the first pair).
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
    args = sys.argv[1:]
    decision = None
    if "--decision" in args:
        at = args.index("--decision")
        decision = args[at + 1]
        del args[at:at + 2]
    if not args or not LEARN.is_dir():
        print(__doc__ if not args else f"skipped: {LEARN} not found")
        return
    label = args[1] if len(args) > 1 else args[0]
    options = {"other": {}, "this": {} if decision is None else {"decision": decision}}
    with tempfile.TemporaryDirectory() as tmp:
        versions = {"other": load_other(Path(args[0]), Path(tmp)), "this": sdp}
        cases = [(LEARN / f"learn{t - 1}.pcd", LEARN / f"learn{t}.pcd") for t, *_ in labelled_pairs()]
        # each version's own clouds: the other's checks its own Cloud class
        pairs = {k: [(v.read_points(a), v.read_points(b)) for a, b in cases] for k, v in versions.items()}
        for k, v in versions.items():  # kernels loaded (or compiled) before timing
            v.detect_changes(*pairs[k][0], **options[k])
        wall = {k: [] for k in versions}
        cpu = {k: [] for k in versions}
        same = True
        load = [os.getloadavg()[0]]
        for i in range(len(cases)):
            w = {k: [] for k in versions}
            c = {k: [] for k in versions}
            fields = {}
            for _ in range(REPEAT):
                for k, v in versions.items():
                    t, p = time.perf_counter(), time.process_time()
                    r = v.detect_changes(*pairs[k][i], **options[k])
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
             f"{min(load):.1f}–{max(load):.1f}. {len(cases)} mOSD pairs, `detect_changes` with the defaults "
             f"(sensor origin from the files), each version {REPEAT}× per pair in turn, the fastest counted; "
             f"medians over the pairs.\n",
             "| version | wall (ms) | CPU (ms) |", "|---|---:|---:|",
             f"| other: `{label}` | {1e3 * np.median(wall['other']):.1f} | {1e3 * np.median(cpu['other']):.1f} |",
             f"| this checkout{'' if decision is None else f', decision={decision!r}'} "
             f"| {1e3 * np.median(wall['this']):.1f} | {1e3 * np.median(cpu['this']):.1f} |",
             "",
             f"This ÷ other, per pair: median {np.median(ratio):.3f} (range {ratio.min():.3f}–{ratio.max():.3f}). "
             f"Same `change` fields on every pair: {same}.", ""]
    print("\n".join(lines))
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / ("versions.md" if decision is None else f"versions-{decision}.md")).write_text("\n".join(lines))


if __name__ == "__main__":
    main()
