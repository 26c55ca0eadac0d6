"""Registration before comparison, and online updates (issue 7), on the real scans.

Alignment: the density method against small_gicp's GICP on the DLUT re-scans (people appeared),
the Toronto ALS epochs (ground ~0.41 m lower in 2023) and the two tree epochs (8-14 cm apart).
False changes on static structure: changed points outside the regions that look like people
(height 1.2-2.1 m, footprint under 1.3 m) before and after alignment.
Online: per-frame latency of `sdp.watch` on 200k-point Kinect frames (the static grabber sequence
and an mOSD run where objects are added one scene after another).
Writes benchmarks/results/align.md and benchmarks/results/online.md.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

import sdp
from sdp.io import read_points

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
RESULTS = ROOT / "benchmarks" / "results"


def disagreement(a, b, pts):
    """RMS displacement between two transforms over ``pts`` (m) and the angle between them (deg)."""
    d = sdp.transform_points(a, pts) - sdp.transform_points(b, pts)
    angle = Rotation.from_matrix(a[:3, :3] @ b[:3, :3].T).magnitude()
    return float(np.sqrt((d**2).sum(axis=1).mean())), float(np.degrees(angle))


def people_and_false(result):
    """Person-like regions, their points, and the other changed points (false changes on static
    structure)."""
    people = np.zeros_like(result.appeared)
    for g in result.appeared_regions:
        size = g.size
        if 1.2 <= size[2] <= 2.1 and max(size[0], size[1]) < 1.3:
            people |= result.appeared_region == g.label
    n_regions = len(np.unique(result.appeared_region[people]))
    return n_regions, int(people.sum()), int((result.appeared & ~people).sum())


def align_table():
    lines = ["# Registration before comparison (real scans)\n",
             "| data | method | rotation (°) | translation at centroid (m) | seconds | vs GICP: RMS displacement (mm), angle (°) |",
             "|---|---|---:|---|---:|---|"]
    change_lines = ["\n## DLUT: false changes on static structure (min_region_points=50)\n",
                    "| rescan | voxel | alignment | people regions | people points | other changed points | reduction |",
                    "|---|---|---|---:|---:|---:|---:|"]
    sets = [("DLUT rescan1", DATA / "dlut/A603_reference.pcd", DATA / "dlut/A603_rescan1.pcd"),
            ("DLUT rescan2", DATA / "dlut/A603_reference.pcd", DATA / "dlut/A603_rescan2.pcd"),
            ("Toronto ALS 2015→2023", DATA / "als_toronto/TTP_2015.laz", DATA / "als_toronto/TTP_2023.laz"),
            ("tree10 2022→2023", DATA / "trees/tree10_2022.xyz", DATA / "trees/tree10_2023.xyz"),
            ("tree73 2022→2023", DATA / "trees/tree73_2022.xyz", DATA / "trees/tree73_2023.xyz")]
    for name, rp, cp in sets:
        ref, cur = read_points(rp).xyz, read_points(cp).xyz
        c = cur.mean(axis=0)
        res = {m: sdp.align(ref, cur, method=m) for m in ("gicp", "density")}
        for m, a in res.items():
            move = a.apply(c[None])[0] - c
            rms, angle = disagreement(a.matrix, res["gicp"].matrix, cur)
            vs = "" if m == "gicp" else f"{rms * 1e3:.1f}, {angle:.3f}"
            lines.append(f"| {name} | {m} | {a.rotation_degrees:.3f} | {np.array2string(move, precision=3)} | "
                         f"{a.seconds:.2f} | {vs} |")
            print(lines[-1])
        if name.startswith("DLUT"):
            for voxel in ("auto", 0.02):
                base = None
                for label, xyz in (("none", cur), ("density", res["density"].apply(cur)),
                                   ("gicp", res["gicp"].apply(cur))):
                    r = sdp.detect_changes(ref, xyz, voxel_size=voxel, min_region_points=50)
                    n_reg, n_people, n_false = people_and_false(r)
                    base = n_false if base is None else base
                    red = "" if label == "none" else f"{1 - n_false / max(base, 1):.0%}"
                    change_lines.append(f"| {name} | {voxel} | {label} | {n_reg} | {n_people:,} | {n_false:,} | {red} |")
                    print(change_lines[-1])
                    if label != "gicp":
                        sdp.render_changes(RESULTS / f"dlut_{name.split()[-1]}_{voxel}_{label}.png", xyz, r.appeared,
                                           title=f"{name}: appeared (voxel {voxel}), alignment {label}")
    text = "\n".join(lines + change_lines) + "\n"
    (RESULTS / "align.md").write_text(text)
    return text


def online_table(repeats=3):
    """Per-frame latency of sdp.watch; each stream is run ``repeats`` times (medians over all frames)."""
    import glob

    steps = ("build", "detect", "regions", "update")
    lines = ["# Online: per-frame latency of sdp.watch (update + detection)\n",
             f"Medians over {repeats} runs of each stream; steps: the frame's field, detection against the model, "
             "change regions, model update.\n",
             "| stream | update | regions | frames | points/frame | appeared per frame | median latency (ms) | max (ms) | "
             + " / ".join(steps) + " (ms) |",
             "|---|---|---|---:|---:|---|---:|---:|---|"]
    grab = [read_points(p).xyz for p in sorted(glob.glob(str(DATA / "pcl_kinect/grabber_sequence/*.pcd")))]
    mosd = [read_points(DATA / f"mosd/learn/learn{i}.pcd").xyz for i in (6, 7, 8, 9, 10, 11)]
    load = os.getloadavg()[0]
    streams = {"static grabber sequence (x4)": (grab[0], grab[1:] + grab * 3),
               "mOSD learn6 → 7 … 11": (mosd[0], mosd[1:])}
    for name, (ref, frames) in streams.items():
        for update in ("window", "decay"):
            for regions in (True, False):
                list(sdp.watch(ref, frames[:2], update=update, regions=regions))  # warm the compiled kernels
                runs = [list(sdp.watch(ref, frames, update=update, regions=regions,
                                       min_region_points=50 if regions else 1)) for _ in range(repeats)]
                reps = runs[0]
                lat = np.array([r.latency for run in runs for r in run]) * 1e3
                step = " / ".join(f"{1e3 * np.median([r.timings[k] for run in runs for r in run]):.1f}" for k in steps)
                app = ", ".join(f"{r.n_appeared / r.appeared.size:.1%}" for r in reps)
                lines.append(f"| {name} | {update} | {'yes' if regions else 'no'} | {len(reps)} | "
                             f"{np.mean([r.appeared.size for r in reps]):,.0f} | {app} | {np.median(lat):.1f} | "
                             f"{lat.max():.1f} | {step} |")
                print(lines[-1])
    lines.append(f"\n{os.cpu_count()} cores; 1-minute load average {load:.1f} before the run, "
                 f"{os.getloadavg()[0]:.1f} after (other jobs share the machine).")
    text = "\n".join(lines) + "\n"
    (RESULTS / "online.md").write_text(text)
    return text


if __name__ == "__main__":
    import sys

    if not DATA.is_dir():
        print(f"skipped: {DATA} not found")
    else:
        t = time.perf_counter()
        if "online" not in sys.argv[1:]:
            align_table()
        if "align" not in sys.argv[1:]:
            online_table()
        print(f"({time.perf_counter() - t:.0f} s)")
