"""Speed of the whole job (issue 20): sdp change step by step on real Kinect pairs, the command
warm and cold, and the baselines in the same run.

1. In-process, the 27 fixed-camera mOSD pairs (ground truth of bench_decision.py), read by
   ``sdp.read_points`` (each PCD's VIEWPOINT gives the sensor origin): ``sdp.detect_changes``
   with the defaults, the median over pairs of each step and of the whole call, and kappa; the
   paper's σ of 2 voxels on the automatic voxel beside it (what the default gave before it took
   1.5 voxels); and, interleaved pair by pair, C2C both ways (a k-d tree on each cloud queried
   with the other, as sdp finds both what appeared and what disappeared) with pykdtree and with
   scipy's cKDTree (all cores), M3C2 (py4dgeo) on 20,000 core points, and depth differencing
   (pixel by pixel on the depth images: the pairs share one fixed camera; its kappa at a
   threshold tuned two-fold on the other pairs, ``baselines.two_fold``). Each method runs
   ``REPEAT`` times per pair; the fastest counts (the machine is shared: say its load).
   Then (1c) the automatic voxel's neighbours of each current frame from its pixels against the
   hashed grid: how many the pixels proved, whether they are the grid's to the last bit, and their time.
2. Start-up: ``import sdp``; ``sdp --version``; ``sdp change A.pcd B.pcd -o OUT.ply`` warm (median
   of 5 runs); cold: in a new Numba cache (the first run compiles every kernel it needs), and
   in another new cache after ``sdp warmup`` (what a fresh install's first command adds); the
   warm command also through ``sdp.cli._main.main`` alone, without the program's collector tuning. Beside
   them, Numba's own floor: ``import numba``, and a script that calls one trivial kernel cached on
   disk (serial, and ``parallel=True``), warm: what any command built on Numba's cached kernels
   pays before its own work.

Prints markdown and writes benchmarks/results/speed.md. Needs ../shared/data (about 5 minutes).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from functools import partial
from pathlib import Path

import baselines as B
import flat
import numpy as np
from bench_decision import LEARN, labelled_pairs

import sdp

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SDP = str(Path(sys.executable).with_name("sdp"))
REPEAT = 3
M3C2_CORE_POINTS = 20_000
CLI_PAIR = ("learn12.pcd", "learn13.pcd")


def both_ways(c2c, ref, cur):
    """C2C in both directions: what appeared (current → reference) and what disappeared."""
    return c2c(ref, cur), c2c(cur, ref)


def in_process(out):
    pairs = [(sdp.read_points(LEARN / f"learn{t - 1}.pcd"), sdp.read_points(LEARN / f"learn{t}.pcd"), truth, scored,
              (B.depth_image(LEARN / f"learn{t - 1}.pcd"), B.depth_image(LEARN / f"learn{t}.pcd")))
             for t, _, _, truth, scored in labelled_pairs()]
    depth = "depth differencing, pixel by pixel (one fixed camera)"
    methods = {"sdp (defaults, sensor origin)": lambda a, b, _: sdp.detect_changes(a, b),
               "sdp, σ = 2 voxels (the paper's, on the automatic voxel)":
                   lambda a, b, _: flat.detect_changes(a, b, sigma_voxels=2.0),
               "pykdtree C2C, both ways": lambda a, b, _: both_ways(B.c2c_pykdtree, a.xyz, b.xyz),
               "cKDTree C2C, both ways": lambda a, b, _: both_ways(B.c2c_ckdtree, a.xyz, b.xyz),
               f"M3C2, {M3C2_CORE_POINTS:,} core points": lambda a, b, _: partial(
                   B.m3c2, max_core_points=M3C2_CORE_POINTS)(a.xyz, b.xyz),
               depth: lambda a, b, images: B.depth_difference(*images)}
    for m in methods.values():  # warm-up: kernels loaded, imports done
        m(*pairs[0][:2], pairs[0][4])
    seconds = {name: [] for name in methods}
    steps = {name: {} for name in methods if name.startswith("sdp")}
    kappa = {name: [] for name in steps}
    depth_scores = []
    load = [os.getloadavg()[0]]
    for ref, cur, truth, scored, images in pairs:
        for name, m in methods.items():
            best = None
            for _ in range(REPEAT):
                t = time.perf_counter()
                r = m(ref, cur, images)
                dt = time.perf_counter() - t
                if best is None or dt < best[0]:
                    best = (dt, r)
            seconds[name].append(best[0])
            if name in steps:
                for step, v in best[1].timings.items():
                    steps[name].setdefault(step, []).append(v)
                kappa[name].append(sdp.kappa(truth[scored], best[1].appeared[scored]))
            elif name == depth:
                depth_scores.append(best[1].score[scored])
        load.append(os.getloadavg()[0])
    kappa[depth] = B.two_fold(depth_scores, [p[2][p[3]] for p in pairs])
    n_pts = np.mean([len(p[1]) for p in pairs])
    out(f"## 1. In-process, {len(pairs)} mOSD pairs ({n_pts:,.0f} current points on average)\n")
    out(f"Load average (1 min) {min(load):.1f}–{max(load):.1f} during the run; each method "
        f"{REPEAT}× per pair, the fastest counted; medians over the pairs.\n")
    base = np.median(seconds["sdp (defaults, sensor origin)"])
    out("| method | median per pair (ms) | its time ÷ sdp's | kappa (mean over pairs with an appeared object; "
        "depth differencing: threshold tuned two-fold) |")
    out("|---|---:|---:|---:|")
    for name, s in seconds.items():
        k = f"{np.nanmean(kappa[name]):.3f}" if name in kappa else "—"
        out(f"| {name} | {1e3 * np.median(s):.1f} | {np.median(s) / base:.2f}× | {k} |")
    out("\nSteps of sdp (median ms per pair; the two directions' coverage and regions run on two threads "
        "at once and are summed here):\n")
    names = list(steps)
    out("| step | " + " | ".join(names) + " |")
    out("|---|" + "---:|" * len(names))
    for step in steps[names[0]]:
        out(f"| {step} | " + " | ".join(f"{1e3 * np.median(steps[n][step]):.1f}" for n in names) + " |")
    out("")


def plane_fit_neighbours(out):
    """The sensor test's neighbour query (the 50 nearest of every 8th unchanged current point to
    the mean of each cube of 2σ of changed points), by sdp's k-d tree and by scipy's cKDTree, built
    and queried, on every 9th pair (the same neighbours' distances: checked; equal distances may
    come in another order)."""
    from scipy.spatial import cKDTree

    from sdp._core._kdtree import k_nearest
    from sdp.change._detect import inside_difference
    from sdp.change._planes import _cube_means

    out("## 1b. The plane fits' neighbours: sdp's k-d tree against cKDTree\n")
    out("| pair | unchanged points | cubes | sdp._kdtree (ms) | cKDTree (ms) | same distances |")
    out("|---|---:|---:|---:|---:|---|")
    for t, _, _, _, _ in list(labelled_pairs())[::9]:
        ref, cur = sdp.read_points(LEARN / f"learn{t - 1}.pcd"), sdp.read_points(LEARN / f"learn{t}.pcd")
        r = sdp.detect_changes(ref, cur, regions=False)
        changed, _ = inside_difference(r.current_field, r.reference_field, cur.xyz)
        static = np.ascontiguousarray(cur.xyz[np.flatnonzero(~changed)[::8]])
        _, centres = _cube_means(cur.xyz[changed], 2 * r.current_field.sigma)
        ms, found = {}, {}
        for name, fn in (("sdp", partial(k_nearest, static, centres, 50)),
                         ("ckdtree", lambda s=static, c=centres: cKDTree(s, balanced_tree=False, compact_nodes=False)
                          .query(c, k=50, workers=1)[1])):
            seconds = []
            for _ in range(3 * REPEAT):
                t0 = time.perf_counter()
                found[name] = fn()
                seconds.append(time.perf_counter() - t0)
            ms[name] = 1e3 * min(seconds)
        same = np.array_equal(*(np.linalg.norm(static[i] - centres[:, None], axis=2) for i in found.values()))
        out(f"| learn{t - 1} → learn{t} | {len(static):,} | {len(centres):,} | {ms['sdp']:.1f} | {ms['ckdtree']:.1f} "
            f"| {same} |")
    out("")


def voxel_from_pixels(out):
    """The automatic voxel's k-th neighbour distances of each pair's current frame (its 5,000
    sampled rows, as ``auto_voxel_size_of`` draws them), from the frame's pixels
    (``kth_in_image``) and from the hashed grid (``kth_neighbour_distance``): how many the pixels
    proved, whether they equal the grid's to the last bit, and the time of each."""
    from sdp._core._points import as_points
    from sdp.fields._spacing import kth_in_image, kth_neighbour_distance

    proven = total = differ = 0
    ms = {"pixels": [], "grid": []}
    for t, *_ in labelled_pairs():
        pts = as_points(sdp.read_points(LEARN / f"learn{t}.pcd"))
        rows = np.sort(np.random.default_rng(0).choice(len(pts.xyz), 5_000, replace=False))
        for name, fn in (("pixels", lambda: kth_in_image(pts, rows, 4)),
                         ("grid", lambda: kth_neighbour_distance(pts.xyz, pts.xyz[rows], 4, lo=pts.lo, hi=pts.hi))):
            seconds = []
            for _ in range(REPEAT + 1):
                t0 = time.perf_counter()
                got = fn()
                seconds.append(time.perf_counter() - t0)
            ms[name].append(1e3 * min(seconds[1:]))
            if name == "pixels":
                d = got
        ok = ~np.isnan(d)
        proven, total = proven + int(ok.sum()), total + len(d)
        differ += int((d[ok] != got[ok]).sum())
    out("## 1c. The automatic voxel's neighbours from a frame's pixels\n")
    out(f"27 current frames, 5,000 sampled rows each: {proven:,} of {total:,} distances proven by the pixel windows, "
        f"{differ} differing from the grid's; median per frame {np.median(ms['pixels']):.2f} ms from the pixels, "
        f"{np.median(ms['grid']):.2f} ms from the grid (serial kernels, fastest of 3).\n")


# the least a program calling one Numba kernel cached on disk can take (a sum, nothing of sdp); it
# ends as the sdp program does (sdp.cli._main.run: gc.freeze() before the interpreter shuts down)
NUMBA_FLOOR = """import gc

import numba
import numpy as np


@numba.njit(cache=True, parallel={parallel})
def total(x):
    s = 0.0
    for i in numba.prange(x.shape[0]):
        s += x[i]
    return s


total(np.ones(3))
gc.freeze()
"""


def run(args, env=None) -> float:
    t = time.perf_counter()
    subprocess.run(args, check=True, capture_output=True, env=env)
    return time.perf_counter() - t


def start_up(out):
    a, b = (str(LEARN / f) for f in CLI_PAIR)
    with tempfile.TemporaryDirectory() as tmp:
        change = [SDP, "change", a, b, "-o", str(Path(tmp) / "out.ply")]
        imports = [run([sys.executable, "-c", "import sdp"]) for _ in range(5)]
        version = [run([SDP, "--version"]) for _ in range(5)]
        # the same command through main() alone, without the program's collector tuning
        # (sdp.cli._main.run), alternating with it
        untuned = [sys.executable, "-c", "import sys; from sdp.cli._main import main; sys.exit(main())", *change[1:]]
        run(change)
        warm, warm_untuned = [], []
        for _ in range(5):
            warm.append(run(change))
            warm_untuned.append(run(untuned))
        fresh = {**os.environ, "NUMBA_CACHE_DIR": str(Path(tmp) / "cold")}
        cold = run(change, fresh)
        warmed = {**os.environ, "NUMBA_CACHE_DIR": str(Path(tmp) / "warmed")}
        t_warmup = run([SDP, "warmup", "--quiet"], warmed)
        after = run(change, warmed)
        floor_env = {**os.environ, "NUMBA_CACHE_DIR": str(Path(tmp) / "floor")}
        import_numba = [run([sys.executable, "-c", "import numba"]) for _ in range(5)]
        floor = {}
        for parallel in (False, True):
            script = Path(tmp) / f"floor_{parallel}.py"
            script.write_text(NUMBA_FLOOR.format(parallel=parallel))
            run([sys.executable, str(script)], floor_env)  # compiles and caches
            floor[parallel] = [run([sys.executable, str(script)], floor_env) for _ in range(5)]
    out(f"## 2. Start-up (`sdp change {CLI_PAIR[0]} {CLI_PAIR[1]} -o out.ply`, labelled PLY written)\n")
    out(f"Load average (1 min) {os.getloadavg()[0]:.1f} at the end.\n")
    out("| what | seconds |\n|---|---:|")
    out(f"| `python -c 'import sdp'` (median of 5) | {np.median(imports):.2f} |")
    out(f"| `sdp --version` (median of 5) | {np.median(version):.2f} |")
    out(f"| `sdp change`, warm (median of 5) | {np.median(warm):.2f} |")
    out(f"| the same through `main()` alone, without the program's collector tuning (median of 5, alternating) | "
        f"{np.median(warm_untuned):.2f} |")
    out(f"| `sdp change`, first run in a new Numba cache (compiles) | {cold:.1f} |")
    out(f"| `sdp warmup` in another new cache | {t_warmup:.1f} |")
    out(f"| `sdp change` after it: first run (compilation added: {after - np.median(warm):+.2f}) | {after:.2f} |")
    out(f"| Numba's floor: `python -c 'import numba'` (median of 5) | {np.median(import_numba):.2f} |")
    out(f"| Numba's floor: one trivial kernel cached on disk, called by a script (median of 5) | "
        f"{np.median(floor[False]):.2f} |")
    out(f"| the same kernel with `parallel=True` (median of 5) | {np.median(floor[True]):.2f} |")
    out("")


def main():
    if not LEARN.is_dir():
        print(f"skipped: {LEARN} not found")
        return
    lines = []

    def out(line=""):
        print(line, flush=True)
        lines.append(line)

    out("# Speed of the whole job\n")
    out(f"`python benchmarks/bench_speed.py`, {time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores.\n")
    in_process(out)
    plane_fit_neighbours(out)
    voxel_from_pixels(out)
    start_up(out)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "speed.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
