"""Right by default: sdp with no option at all on the real scans beside the project.

1. The 27 fixed-camera mOSD Kinect pairs (ground truth of bench_decision.py) through
   ``sdp change A.pcd B.pcd -o OUT.ply`` with no option, and through
   ``sdp.detect_changes(sdp.read_points(A), sdp.read_points(B))``: kappa on the scored points
   (not comparable counted as unchanged, as the paper scores) and on the comparable scored
   points (as ``sdp eval`` scores), false positives on the pairs without an appeared object,
   beside the best configuration measured before the defaults changed (automatic voxel,
   ``min_region_points=50``, both PCD VIEWPOINTs, no coverage test).
2. The static grabber sequence (no change at all) through ``sdp change ... --align gicp``:
   the share of points flagged.
3. Toronto ALS 2015 → 2023 (``--align density --align-class 2 --fix-horizontal``): appeared
   points outside the 2015 flight's coverage (farther than 5 m / 10 m in x, y from every 2015
   point; the 2015 flight's 90th-percentile point spacing is 1.2 m), and the appeared regions
   before (no coverage test) and after, both with ``min_region_points=1`` and with the default.

Prints markdown and writes benchmarks/results/defaults.md. Needs ../shared/data (about 3 minutes).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import flat
import numpy as np
from bench_decision import LEARN, labelled_pairs
from scipy.spatial import cKDTree

import sdp

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "benchmarks" / "results"
BEFORE = dict(voxel_size="auto", min_region_points=50, coverage=False)  # + both VIEWPOINTs: the best measured


def sdp_change(*args) -> dict:
    """``sdp change`` in a fresh process, as a user runs it: its JSON summary."""
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "change", *map(str, args), "--json"],
                       capture_output=True, text=True)
    if p.returncode:
        raise RuntimeError(p.stderr)
    return json.loads(p.stdout)


def mosd(out, tmp: Path):
    rows, same = [], True
    for t, _, _, truth, scored in labelled_pairs():
        a, b = LEARN / f"learn{t - 1}.pcd", LEARN / f"learn{t}.pcd"
        s = sdp_change(a, b, "-o", tmp / "out.ply")
        state = np.asarray(sdp.read_points(tmp / "out.ply").fields["change"])
        py = sdp.detect_changes(sdp.read_points(a), sdp.read_points(b))
        same &= bool(np.array_equal(py.current_state, state))
        ra, rb = sdp.read_points(a), sdp.read_points(b)
        before = flat.detect_changes(ra.xyz, rb.xyz, sensor_origin=[ra.sensor_origin, rb.sensor_origin], **BEFORE)
        appeared, comparable = state == sdp.CHANGED, state != sdp.NOT_COMPARABLE
        rows.append(dict(t=t, truth=int(truth.sum()),
                         all=sdp.kappa(truth[scored], appeared[scored]),
                         comparable=sdp.scores(truth[scored], appeared[scored], comparable=comparable[scored])["kappa"],
                         before=sdp.kappa(truth[scored], before.appeared[scored]),
                         not_comparable=int((~comparable[scored]).sum()), scored=int(scored.sum()),
                         fp=int((appeared & scored & ~truth).sum()), seconds=s["timings"],
                         coverage=s["coverage"]["appeared"]))
        print(f"mOSD learn{t - 1} -> learn{t}: kappa {rows[-1]['all']:.3f}", file=sys.stderr, flush=True)
    mean = {k: float(np.nanmean([r[k] for r in rows])) for k in ("all", "comparable", "before")}
    empty = [r for r in rows if r["truth"] == 0]
    out("## 1. mOSD: 27 Kinect pairs, `sdp change A.pcd B.pcd -o OUT.ply` with no option\n")
    out(f"Coverage decided by: {sorted({r['coverage'] for r in rows})} (the PCD files' VIEWPOINT, read by "
        "`--sensor-origin auto`, the default).\n")
    out("| | kappa (mean over pairs) |\n|---|---:|")
    out(f"| sdp change, no option: scored points, not comparable as unchanged | **{mean['all']:.4f}** |")
    out(f"| sdp change, no option: comparable scored points (as `sdp eval`) | **{mean['comparable']:.4f}** |")
    out(f"| best measured before (auto voxel, min_region_points=50, VIEWPOINTs, no coverage test) | "
        f"{mean['before']:.4f} |\n")
    out(f"- Not comparable: {sum(r['not_comparable'] for r in rows):,} of {sum(r['scored'] for r in rows):,} "
        "scored points.")
    names = ", ".join(f"learn{r['t'] - 1}→{r['t']}" for r in empty)
    out(f"- Pairs without an appeared object: {names}; false positives on their scored points: "
        f"{[r['fp'] for r in empty]}.")
    out(f"- `sdp.detect_changes(sdp.read_points(a), sdp.read_points(b))` gives the same `change` field as the "
        f"command on every pair: {same}.\n")
    out("| pair | kappa | kappa (comparable) | before | not comparable |\n|---|---:|---:|---:|---:|")
    for r in rows:
        out(f"| learn{r['t'] - 1}→{r['t']} | {r['all']:.3f} | {r['comparable']:.3f} | {r['before']:.3f} | "
            f"{r['not_comparable']:,} |")
    out()


def grabber(out, tmp: Path):
    frames = sorted((DATA / "pcl_kinect" / "grabber_sequence").glob("*.pcd"))
    out("## 2. Static grabber sequence (no change): `sdp change Fi Fj -o OUT.ply --align gicp`\n")
    out("| pair | points | appeared | share | not comparable |\n|---|---:|---:|---:|---:|")
    for i in range(len(frames)):
        for j in range(len(frames)):
            if i != j:
                s = sdp_change(frames[i], frames[j], "-o", tmp / "g.ply", "--align", "gicp")["current"]
                out(f"| {i} → {j} | {s['points']:,} | {s['appeared']:,} | {s['appeared'] / s['points']:.2%} | "
                    f"{s['not_comparable']:,} |")
    out()


def toronto(out, tmp: Path):
    d = DATA / "als_toronto"
    a, b = sdp.read_points(d / "TTP_2015.laz"), sdp.read_points(d / "TTP_2023.laz")
    align = ("--align", "density", "--align-class", "2", "--fix-horizontal")
    s = sdp_change(d / "TTP_2015.laz", d / "TTP_2023.laz", "-o", tmp / "t.laz", *align)
    c = sdp.read_points(tmp / "t.laz")
    state = np.asarray(c.fields["change"])
    ground = a.xyz[a.fields["classification"] == 2], b.xyz[b.fields["classification"] == 2]
    moved = b.transformed(sdp.align(*ground, fix_horizontal=True).matrix)
    dist, _ = cKDTree(a.xyz[:, :2]).query(moved.xyz[:, :2])
    spacing = np.quantile(cKDTree(a.xyz[:, :2]).query(a.xyz[:, :2], k=2)[0][:, 1], 0.9)
    out("## 3. Toronto ALS 2015 → 2023, `sdp change 2015.laz 2023.laz -o OUT.laz --align density "
        "--align-class 2 --fix-horizontal`\n")
    out(f"2015 flight: 90th-percentile point spacing {spacing:.2f} m in x, y; voxel {s['voxel_size']:.3f} m, "
        f"σ {s['sigma']:.2f} m; coverage by {s['coverage']['appeared']}.\n")
    out("| 2023 points farther from every 2015 point than | points | appeared | share | not comparable |")
    out("|---|---:|---:|---:|---:|")
    for limit in (5.0, 10.0):
        far = dist > limit
        n_app = int((state[far] == sdp.CHANGED).sum())
        out(f"| {limit:g} m | {far.sum():,} | {n_app:,} | {n_app / max(far.sum(), 1):.2%} | "
            f"{int((state[far] == sdp.NOT_COMPARABLE).sum()):,} |")
    out(f"\nWhole 2023 epoch: {s['current']['appeared']:,} appeared, {s['current']['not_comparable']:,} not "
        f"comparable of {s['current']['points']:,}.\n")
    out("Appeared regions (points, centroid x y, nearest 2015 point from the centroid):\n")
    tree = cKDTree(a.xyz[:, :2])
    for name, kw in (("before (no coverage test), min_region_points=1", dict(coverage=False, min_region_points=1)),
                     ("after (the defaults), min_region_points=1", dict(min_region_points=1)),
                     ("after, the defaults (min_region_points=50)", {})):
        r = flat.detect_changes(a, moved, **kw)
        regs = ", ".join(f"{g.n_points} at ({g.centroid[0]:.0f}, {g.centroid[1]:.0f}; "
                         f"{tree.query(g.centroid[:2])[0]:.0f} m)" for g in r.appeared_regions)
        out(f"- {name}: {regs or 'none'}")
    out()


def main():
    if not LEARN.is_dir():
        print(f"skipped: {LEARN} not found")
        return
    lines = []

    def out(s=""):
        print(s, flush=True)
        lines.append(s)

    load = os.getloadavg()
    out("# Right by default (benchmarks/bench_defaults.py)\n")
    out(f"Load average at start {load[0]:.1f}; sdp {sdp.__version__}; defaults: `{sdp.DEFAULTS}`.\n")
    with tempfile.TemporaryDirectory() as tmp:
        mosd(out, Path(tmp))
        grabber(out, Path(tmp))
        toronto(out, Path(tmp))
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "defaults.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
