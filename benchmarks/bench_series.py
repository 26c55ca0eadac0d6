"""Many epochs: ``sdp series`` on a simulated slope with known truth, against py4dgeo's
SpatiotemporalAnalysis on the same files, and appending.

Prints markdown (docs/benchmarks.md §13 quotes it; ``results/series.md`` keeps the last run):

1. The truth (:func:`sdp.data.slope_series`: a rough slope 20 m × 20 m, 100,000 points per
   epoch resampled at every epoch, noise σ = 4 mm along z, a registration error of 1 mm and
   0.003° per epoch; a creeping disk at −2 mm per epoch, a disk stepping +30 mm at the middle
   epoch, stable ground elsewhere), 25 epochs, 33,334 core points (every third reference point),
   projection scale 0.5 m, normal scale 1 m, registration error 2 mm: median |distance − truth|
   against σ/2; stable core points' significant share of epochs (≤ 6 %); median smoothed
   velocity on the creeping disk against the truth (within 10 %); the step's core points in an
   object starting at the step's epoch (≥ 90 %); stable core points in any object (≤ 2 %).
   Core points closer than d to a disk's rim are left out of the zones. 1b: a step right after
   the reference (10 epochs of 20,000 points, the step disk moving at epoch 1), in this process:
   the smoothed change against the truth, the velocity (truth 0), the onset and the object.
2. Side by side with py4dgeo 1.2's SpatiotemporalAnalysis (M3C2 of each epoch against the
   reference at the same core points: cylinder radius d/2, normal radius D/2, half-length
   0.75 d as sdp's cylinder, the same registration error), each tool as a whole job in its own
   process from the LAZ files, 5 and 25 epochs: time per epoch = (t₂₅ − t₅)/20, so start-up
   and imports cancel; the four jobs interleaved, ``--rounds`` times (3), the fastest of each; peak memory (the process's maximum resident set) and archive size per
   epoch × core point; median |sdp − M3C2| over all epochs as a share of d.
3. Appending the 25th epoch to a 24-epoch archive (``sdp series --append``, a whole job too):
   its time against one epoch of the full run ((t₂₅ − t₅)/20), the fastest of ``--rounds``, and
   whether every array of the archive equals the full run's.
4. ``--scale`` (or ``--only-scale``): 1,000 epochs × 100,000 core points (epochs of 120,000
   points as .npy files, a 40 m square with a subsiding disk), one job at ``--memory-limit 2GB``,
   niced: time and peak memory of the job, then of appending a 1,001st epoch
   (``results/series-scale.md``).
5. ``--only-tiled``: 5 epochs of 2,000,000 points (.npy) with ``--tiled --memory-limit 1500MB`` on a
   local Dask cluster of 2 workers against in memory, whole jobs of 2 and 5 epochs interleaved:
   time per epoch (t₅ − t₂)/3, peak memory of all the processes, the archives compared
   (``results/series-tiled.md``).

Usage: ``python benchmarks/bench_series.py [--quick] [--scale] [--only-tiled] [--rounds N] [--workdir DIR]``.
Needs py4dgeo (``pip install 'sdp[m3c2]'``) for 2.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import sdp
from sdp.data import slope_series

ROOT = Path(__file__).resolve().parents[1]
D, DN, REG = 0.5, 1.0, 0.002

P4D_JOB = r"""
import datetime, logging, sys, json, numpy as np
logging.getLogger("py4dgeo").setLevel(logging.WARNING)
import py4dgeo
files, core_file, out, d, dn, reg = sys.argv[1].split(","), sys.argv[2], sys.argv[3], *map(float, sys.argv[4:7])
t0 = datetime.datetime(2024, 1, 1)
analysis = py4dgeo.SpatiotemporalAnalysis(out, force=True)
ref = py4dgeo.read_from_las(files[0]); ref.timestamp = t0
analysis.reference_epoch = ref
analysis.corepoints = py4dgeo.read_from_las(core_file).cloud
analysis.m3c2 = py4dgeo.M3C2(cyl_radius=d / 2, normal_radii=(dn / 2,), max_distance=0.75 * d, registration_error=reg)
epochs = []
for k, f in enumerate(files):
    e = py4dgeo.read_from_las(f); e.timestamp = t0 + datetime.timedelta(days=k); epochs.append(e)
analysis.add_epochs(*epochs)
np.save(out + ".distances.npy", analysis.distances)
"""


def job(args: list[str], *, nice: int = 0) -> dict:
    """Run a whole job in its own process: wall time and its peak resident memory."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            preexec_fn=(lambda: os.nice(nice)) if nice else None)
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - t0
    err = proc.stderr.read().decode()
    proc.stderr.close()
    if status != 0:
        raise RuntimeError(f"{' '.join(args[:4])}…: status {status}: {err[-2000:]}")
    return {"seconds": seconds, "peak_mb": usage.ru_maxrss / 1024.0}


def sdp_job(files, core, out, *, append=False, times=None, nice=0):
    times = times or list(range(len(files)))
    args = [sys.executable, "-m", "sdp.cli", "series", *map(str, files), "-o", str(out), "--core-points", str(core),
            "--projection-scale", str(D), "--normal-scale", str(DN), "--registration-error", str(REG),
            "--times", ",".join(map(str, times)), "--quiet"]
    if append:
        args = [a for a in args if a not in ("--core-points", str(core))] + ["--append"]
    return job(args, nice=nice)


def p4d_job(files, core, out):
    return job([sys.executable, "-c", P4D_JOB, ",".join(map(str, files)), str(core), str(out), str(D), str(DN),
                str(REG)])


def size_mb(path: Path) -> float:
    if path.is_file():
        return path.stat().st_size / 2**20
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) / 2**20


def truth_table(s, ds) -> list[str]:
    xyz = np.c_[ds.x.values, ds.y.values, ds.z.values]
    truth = s.truth(xyz)
    zone = s.zone(xyz, margin=D)
    dist = ds.distance.values
    err = float(np.nanmedian(np.abs(dist - truth)))
    stable_sig = float(ds.significant.values[:, zone == 0].mean())
    vel = float(np.nanmedian(ds.velocity.values[:, zone == 1]))
    obj = ds.object.values
    starts = dict(zip(ds.object_id.values.tolist(), ds.object_start.values.tolist()))
    se = s.step_epoch
    in_step = float(np.mean([starts.get(int(obj[se, p]), -1) == se for p in np.flatnonzero(zone == 2)]))
    stable_obj = float((obj[:, zone == 0] > 0).any(axis=0).mean())
    rows = [
        ("median \\|distance − truth\\|", f"{1000 * err:.2f} mm", f"≤ σ/2 = {1000 * s.noise / 2:.1f} mm",
         err <= s.noise / 2),
        ("stable core points: significant share of epochs", f"{100 * stable_sig:.2f} %", "≤ 6 %", stable_sig <= 0.06),
        ("creeping disk: median smoothed velocity", f"{1000 * vel:.3f} mm/epoch",
         f"{1000 * s.creep_rate:.1f} ± 10 %", abs(vel - s.creep_rate) <= 0.1 * abs(s.creep_rate)),
        ("step's core points in an object starting at its epoch", f"{100 * in_step:.1f} %", "≥ 90 %", in_step >= 0.9),
        ("stable core points in any object", f"{100 * stable_obj:.2f} %", "≤ 2 %", stable_obj <= 0.02),
    ]
    out = ["| measure | sdp | bar | met |", "|---|---|---|---|"]
    out += [f"| {a} | {b} | {c} | {'yes' if ok else 'no'} |" for a, b, c, ok in rows]
    out.append(f"\n{(zone == 0).sum():,} stable, {(zone == 1).sum():,} creeping, {(zone == 2).sum():,} step core "
               f"points; {len(starts)} objects; process noise q = {ds.attrs['parameters']['smoother']['process_noise']:.3g}")
    return out


def write_epochs(s, work: Path, prefix: str) -> tuple[list[Path], Path]:
    """The series' epochs as LAZ files ``PREFIXkk.laz`` and its core points (every third point of
    the reference) as ``PREFIX_core.laz``."""
    files = []
    for k, e in enumerate(s.epochs):
        files.append(work / f"{prefix}{k:02d}.laz")
        sdp.write_points(files[-1], e)
    core = work / f"{prefix}_core.laz"
    sdp.write_points(core, s.epochs[0][::3])
    return files, core


def first_step_table(work: Path) -> list[str]:
    """A step right after the reference: 10 epochs of 20,000 points, the step disk moving at
    epoch 1 (in this process, the defaults). Truth after the step: the step's height, rate 0."""
    s = slope_series(10, 20_000, step_epoch=1, seed=11)
    files, core = write_epochs(s, work, "first")
    ds = sdp.series(files, output=work / "first.zarr", core_points=core,
                    cylinder=sdp.Cylinder(projection_scale=D, normal_scale=DN))
    xyz = np.c_[ds.x.values, ds.y.values, ds.z.values]
    step = s.zone(xyz, margin=D) == 2
    truth = s.truth(xyz)[:, step]
    err = float(np.nanmedian(np.abs(ds.smoothed.values[1:, step] - truth[1:])))
    rate = float(np.nanmedian(np.abs(ds.velocity.values[1:, step])))
    onset = float(np.mean((ds.onset.values[step] == 1) & (ds.onset_kind.values[step] == 1)))
    starts = dict(zip(ds.object_id.values.tolist(), ds.object_start.values.tolist()))
    in_obj = float(np.mean([starts.get(int(o), -1) == 1 for o in ds.object.values[1, step]]))
    return ["### 1b. A step right after the reference (10 epochs of 20,000 points, the step at epoch 1)", "",
            "| measure on the step's core points, epochs 1–9 | sdp | truth |", "|---|---|---|",
            f"| median \\|smoothed − truth\\| | {1000 * err:.2f} mm | 0 (noise σ {1000 * s.noise:.0f} mm) |",
            f"| median \\|velocity\\| | {1000 * rate:.3f} mm/epoch | 0 |",
            f"| onset at epoch 1, a step | {100 * onset:.1f} % | 100 % |",
            f"| in an object starting at epoch 1 | {100 * in_obj:.1f} % | 100 % |", "",
            f"{int(step.sum()):,} step core points; the step {1000 * s.step:.0f} mm", ""]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="20,000 points per epoch, no py4dgeo")
    ap.add_argument("--scale", action="store_true", help="also 1,000 epochs × 100,000 core points")
    ap.add_argument("--only-scale", action="store_true", help="only 1,000 epochs × 100,000 core points")
    ap.add_argument("--only-real", action="store_true", help="only the real epochs against sdp distance per pair")
    ap.add_argument("--only-tiled", action="store_true", help="only epochs of 2,000,000 points in tiles on Dask "
                    "against in memory")
    ap.add_argument("--tiled-points", type=int, default=2_000_000, help="points per epoch of --only-tiled")
    ap.add_argument("--tiled-limit", type=int, default=1500, help="--memory-limit (MB) of --only-tiled's tiles: "
                    "below 200 bytes per point the command takes tiles by itself")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved runs of each job, the fastest kept (3)")
    ap.add_argument("--workdir", default=None, help="folder for the epochs and archives (default: a temporary one)")
    a = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_series_", dir=a.workdir))
    out = []
    alone = None  # (the part run alone, its results file)
    if a.only_real:
        alone = (lambda: real_epochs(work)), "series-real.md"
    elif a.only_tiled:
        alone = ((lambda: tiled_run(work, a.rounds, a.tiled_points, a.tiled_limit)),
                 "series-tiled.md" if a.tiled_points == 2_000_000 else f"series-tiled-{a.tiled_points}.md")
    elif a.only_scale:
        alone = (lambda: scale_run(work)), "series-scale.md"
    if alone:
        try:
            out = alone[0]()
        finally:
            shutil.rmtree(work, ignore_errors=True)
        print("\n".join(out))
        (ROOT / "benchmarks" / "results" / alone[1]).write_text("\n".join(out) + "\n")
        return
    try:
        n = 20_000 if a.quick else 100_000
        s = slope_series(25, n, seed=7)
        files, core = write_epochs(s, work, "epoch")
        m = len(s.epochs[0][::3])
        load = os.getloadavg()
        out += [f"## Series: {n:,} points per epoch, {m:,} core points (load {load[0]:.1f} {load[1]:.1f} "
                f"{load[2]:.1f} on {os.cpu_count()} cores)", ""]
        sdp_job(files[:2], core, work / "warm.zarr")  # compile the kernels once (the cache on disk)
        # the tools' jobs interleaved, a.rounds times, the fastest of each kept: a shared machine's
        # load varies over minutes, and the least disturbed run is the one that measures the tool
        runs: dict = {}

        def fastest(key, fn):
            r = fn()
            if key not in runs or r["seconds"] < runs[key]["seconds"]:
                runs[key] = r
        for _ in range(a.rounds):
            fastest("s5", lambda: sdp_job(files[:5], core, work / "s5.zarr"))
            if not a.quick:
                fastest("p5", lambda: p4d_job(files[:5], core, work / "p5.zip"))
            fastest("s25", lambda: sdp_job(files, core, work / "s25.zarr"))
            if not a.quick:
                fastest("p25", lambda: p4d_job(files, core, work / "p25.zip"))
        t5, t25 = runs["s5"], runs["s25"]
        ds = sdp.open_series(work / "s25.zarr")
        out += ["### 1. Against the truth (25 epochs)", ""] + truth_table(s, ds) + [""]
        out += first_step_table(work)
        per_sdp = (t25["seconds"] - t5["seconds"]) / 20
        # 3. appending the 25th epoch to a 24-epoch archive
        sdp_job(files[:24], core, work / "a24.zarr")
        ta, inproc = None, np.inf
        for _ in range(a.rounds):
            shutil.rmtree(work / "a.zarr", ignore_errors=True)
            shutil.copytree(work / "a24.zarr", work / "a.zarr")
            r = sdp_job(files[24:], core, work / "a.zarr", append=True, times=[24])
            ta = r if ta is None or r["seconds"] < ta["seconds"] else ta
            grown = sdp.open_series(work / "a.zarr")
            inproc = min(inproc, grown.attrs["runs"][-1]["timings"]["total"])
        same = all(np.array_equal(ds[v].values, grown[v].values, equal_nan=True) for v in ds.variables)
        warm = np.inf  # in this process, kernels loaded and modules imported (a service appending as epochs come)
        for r in range(a.rounds + 1):  # the first round loads the kernels: not counted
            shutil.rmtree(work / "a.zarr", ignore_errors=True)
            shutil.copytree(work / "a24.zarr", work / "a.zarr")
            t0 = time.perf_counter()
            sdp.series(files[24:], output=work / "a.zarr", append=True, times=[24])
            if r:
                warm = min(warm, time.perf_counter() - t0)
        full_inproc = ds.attrs["runs"][-1]["timings"]["total"] / 25
        out += ["### 3. Appending one epoch to a 24-epoch archive", "",
                "| | seconds |", "|---|---|",
                f"| one epoch of the full run, (t₂₅ − t₅)/20 | {per_sdp:.3f} |",
                f"| the append job, whole (start-up and imports included) | {ta['seconds']:.3f} |",
                f"| the append inside the job (sdp.series, from its record) | {inproc:.3f} |",
                f"| the full run inside its job, per epoch | {full_inproc:.3f} |",
                f"| the append in a warm process (`sdp.series(append=True)`, fastest of {a.rounds}) | {warm:.3f} |",
                "",
                f"Every array equals the full run's: {'yes' if same else 'NO'}. The append inside the job is "
                f"{inproc / per_sdp:.2f}× one epoch of the full run (bar: ≤ 1.5×), in a warm process "
                f"{warm / per_sdp:.2f}×; the whole job {ta['seconds'] / per_sdp:.1f}×.", ""]
        if not a.quick:
            p5, p25 = runs["p5"], runs["p25"]
            per_p4d = (p25["seconds"] - p5["seconds"]) / 20
            pd = np.load(str(work / "p25.zip") + ".distances.npy")  # (core points, epochs)
            diff = np.abs(ds.distance.values - pd.T)
            med = float(np.nanmedian(diff))
            both = np.isfinite(diff).mean()
            cells = 25 * m
            out += ["### 2. Side by side with py4dgeo's SpatiotemporalAnalysis (whole jobs from the LAZ files)", "",
                    "| | sdp series | py4dgeo | ratio |", "|---|---|---|---|",
                    f"| 5 epochs, s | {t5['seconds']:.2f} | {p5['seconds']:.2f} | |",
                    f"| 25 epochs, s | {t25['seconds']:.2f} | {p25['seconds']:.2f} | |",
                    f"| per epoch, (t₂₅ − t₅)/20, s | {per_sdp:.3f} | {per_p4d:.3f} | {per_p4d / per_sdp:.1f}× |",
                    f"| peak memory (25 epochs), MB | {t25['peak_mb']:.0f} | {p25['peak_mb']:.0f} | "
                    f"{p25['peak_mb'] / t25['peak_mb']:.1f}× |",
                    f"| archive, bytes per epoch × core point | {size_mb(work / 's25.zarr') * 2**20 / cells:.1f} | "
                    f"{size_mb(work / 'p25.zip') * 2**20 / cells:.1f} | |", "",
                    f"Median \\|sdp − M3C2\\| over {100 * both:.1f} % of (epoch, core point) with both: "
                    f"{1000 * med:.2f} mm = {med / D:.4f} d (bar ≤ 0.1 d). sdp's archive also holds the smoothed "
                    "change, velocity, their sigmas and the objects.", ""]
        if a.scale:
            out += scale_run(work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    text = "\n".join(out)
    print(text)
    (ROOT / "benchmarks" / "results").mkdir(exist_ok=True)
    (ROOT / "benchmarks" / "results" / "series.md").write_text(text + "\n")


def real_epochs(work: Path) -> list[str]:
    """Each epoch of a real series against ``sdp.distances`` on that pair with the archive's scales."""
    data = ROOT.parent / "shared" / "data"
    cases = [("Pheno4D tomato", [data / "pheno4d_tomato" / f for f in ("tomato_03-05.xyz", "tomato_03-06.xyz",
                                                                      "tomato_03-08.ply", "tomato_03-10.ply")],
              "2024-03-05,2024-03-06,2024-03-08,2024-03-10", None),
             ("Toronto ALS", [data / "als_toronto" / "TTP_2015.laz", data / "als_toronto" / "TTP_2023.laz"],
              "2015-06-01,2023-06-01", "density")]
    out = ["### Real epochs against `sdp.distances` on each pair", "",
           "| series | core points | epoch | largest \\|series − pair\\| | significance the same |", "|---|---|---|---|---|"]
    for name, files, times, align in cases:
        if not all(f.exists() for f in files):
            out.append(f"| {name} | skipped: data not found | | | |")
            continue
        ds = sdp.series(files, output=work / "real.zarr", times=times, align=align)  # the registration error: auto
        u = ds.attrs["parameters"]["used"]
        cyl = sdp.Cylinder(projection_scale=u["projection_scale"], normal_scale=u["normal_scale"],
                           max_distance=u["max_distance"])
        core = np.c_[ds.x.values, ds.y.values, ds.z.values]
        ref = sdp.read_points(files[0])
        for k in range(1, len(files)):
            cur = sdp.read_points(files[k]).xyz
            if align:  # the series' own alignment (on the epoch's stable part, sdp.series's docs)
                m = np.asarray(ds.attrs["epochs"][k]["alignment"]["matrix"])
                cur = cur @ m[:3, :3].T + m[:3, 3]
            pair = sdp.distances(ref, cur, core_points=core, cylinder=cyl, sensor_origin=None)
            a = ds.distance.values[k]
            same_nan = np.array_equal(np.isfinite(a), np.isfinite(pair.distance))
            both = np.isfinite(a) & np.isfinite(pair.distance)
            worst = float(np.max(np.abs(a[both] - pair.distance[both]))) if both.any() else 0.0
            agree = float(np.mean(ds.significant.values[k] == pair.significant))
            out.append(f"| {name} | {len(core):,} | {k} | {worst:.2g}{'' if same_nan else ' (NaN differ)'} | "
                       f"{100 * agree:.1f} % |")
    return out + ["", "The archive stores float32: differences at that rounding are equality.", ""]


def scale_run(work: Path) -> list[str]:
    """1,000 epochs × 100,000 core points: the epochs written as .npy, then one niced job."""
    rng = np.random.default_rng(11)
    n, E = 120_000, 1000
    xy = rng.uniform(0, 40, (n, 2))
    files = []
    for k in range(E):
        e = np.c_[xy + rng.normal(0, 0.01, (n, 2)), 0.2 * xy[:, 0] + 0.004 * rng.standard_normal(n)]
        e[(np.hypot(e[:, 0] - 10, e[:, 1] - 20) < 5), 2] -= 0.0002 * k
        files.append(work / f"big{k:04d}.npy")
        np.save(files[-1], e)
        if k == 0:
            np.save(work / "bigcore.npy", e[rng.choice(n, 100_000, replace=False)])
    load = os.getloadavg()
    r = job([sys.executable, "-m", "sdp.cli", "series", *map(str, files), "-o", str(work / "big.zarr"),
             "--core-points", str(work / "bigcore.npy"), "--projection-scale", "0.5", "--memory-limit", "2GB",
             "--quiet"], nice=10)
    ds = sdp.open_series(work / "big.zarr")
    t = ds.attrs["runs"][-1]["timings"]
    # stable ground (beyond the disk and a projection scale): how often its smoothed change reads as
    # significant (every 50th epoch), and how much of it falls in an object
    stable = np.hypot(ds.x.values - 10, ds.y.values - 20) > 5.5
    sm, sd = ds.smoothed[::50].values[:, stable], ds.smoothed_sigma[::50].values[:, stable]
    smoothed_share = float(np.mean(np.abs(sm) > 1.96 * sd))
    own_share = float(ds.significant[::50].values[:, stable].mean())
    in_object = np.zeros(int(stable.sum()), bool)
    for a in range(0, E, 100):
        in_object |= (ds.object[a:a + 100].values[:, stable] > 0).any(axis=0)
    e = np.c_[xy + rng.normal(0, 0.01, (n, 2)), 0.2 * xy[:, 0] + 0.004 * rng.standard_normal(n)]
    e[(np.hypot(e[:, 0] - 10, e[:, 1] - 20) < 5), 2] -= 0.0002 * E
    np.save(work / "next.npy", e)
    ra = job([sys.executable, "-m", "sdp.cli", "series", str(work / "next.npy"), "--append", "-o", str(work / "big.zarr"),
              "--memory-limit", "2GB", "--quiet"], nice=10)
    ta = sdp.open_series(work / "big.zarr").attrs["runs"][-1]["timings"]
    return ["### 4. 1,000 epochs × 100,000 core points", "",
            f"Epochs of {n:,} points (.npy), one job, `--memory-limit 2GB`, nice 10, load before {load[0]:.1f}: "
            f"{r['seconds']:.0f} s "
            f"({r['seconds'] / E:.3f} s per epoch), peak memory {r['peak_mb']:.0f} MB (the job is one process). "
            f"Inside: epochs {t['epochs']:.0f} s, smoother {t['smoother']:.0f} s, objects {t['objects']:.0f} s. "
            f"Archive {size_mb(work / 'big.zarr'):.0f} MB, {ds.sizes['epoch']} epochs × {ds.sizes['point']:,} "
            f"core points, {ds.sizes['object_id']} objects.", "",
            f"Stable core points (beyond the subsiding disk): the smoothed change significant at "
            f"{100 * smoothed_share:.1f} % of (epoch, point), each epoch's own distance at {100 * own_share:.1f} % "
            f"(every 50th epoch); {100 * in_object.mean():.2f} % of them in an object.", "",
            f"Appending a 1,001st epoch: the job {ra['seconds']:.1f} s, peak memory {ra['peak_mb']:.0f} MB; inside: "
            f"the epoch {ta['epochs']:.2f} s (Numba's first calls included), smoother {ta['smoother']:.2f} s, "
            f"objects {ta['objects']:.2f} s, total {ta['total']:.2f} s.", ""]


def tree_job(args: list[str]) -> dict:
    """A whole job: wall time and the peak of the summed resident memory of it and all its
    descendants (the Dask scheduler and workers), sampled every 0.1 s."""
    import psutil

    t0 = time.perf_counter()
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    parent, peak = psutil.Process(proc.pid), 0
    while proc.poll() is None:
        total = 0
        try:
            for q in [parent, *parent.children(recursive=True)]:
                try:
                    total += q.memory_info().rss
                except psutil.Error:
                    pass
        except psutil.Error:
            pass
        peak = max(peak, total)
        time.sleep(0.1)
    seconds = time.perf_counter() - t0
    err = proc.stderr.read().decode()
    proc.stderr.close()
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(args[:4])}…: status {proc.returncode}: {err[-2000:]}")
    return {"seconds": seconds, "peak_mb": peak / 2**20}


def tiled_run(work: Path, rounds: int, n: int = 2_000_000, limit_mb: int = 1500) -> list[str]:
    """Epochs of ``n`` points (.npy, 200 per m²) in tiles on Dask against in memory, whole jobs of 2
    and 5 epochs interleaved: time per epoch (t₅ − t₂)/3, peak memory of all the processes, and
    whether the two archives are equal. Tiles: ``--memory-limit limit_mb``, with ``--tiled`` when
    the epochs would fit in memory under it, else taken by the command itself; the in-memory jobs
    run under the same limit, or 4 GB when the epochs need more."""
    E = 5
    need_mb = 200 * n / 2**20
    forced = need_mb <= limit_mb
    size = float(np.sqrt(n / 200.0))
    s = slope_series(E, n, size=size, seed=7)
    files = []
    for k, e in enumerate(s.epochs):
        files.append(work / f"big{k}.npy")
        np.save(files[-1], e)
    del s

    def args(k, out, tiled):
        limit = f"{limit_mb}MB" if tiled or forced else "4GB"
        return [sys.executable, "-m", "sdp.cli", "series", *map(str, files[:k]), "-o", str(out),
                "--projection-scale", str(D), "--normal-scale", str(DN), "--max-distance", "0.5",
                "--registration-error", str(REG), "--times", ",".join(map(str, range(k))), "--memory-limit", limit,
                "--quiet", *(["--workers", "2"] if tiled else []), *(["--tiled"] if tiled and forced else [])]

    load0 = os.getloadavg()
    tree_job(args(2, work / "warm.zarr", True))  # the kernels compiled once (Numba's cache on disk)
    runs: dict = {}
    for _ in range(rounds):
        for k in (2, E):
            for tiled in (False, True):
                r = tree_job(args(k, work / f"{'t' if tiled else 'm'}{k}.zarr", tiled))
                key = (tiled, k)
                if key not in runs or r["seconds"] < runs[key]["seconds"]:
                    runs[key] = r
    load1 = os.getloadavg()
    per = {t: (runs[(t, E)]["seconds"] - runs[(t, 2)]["seconds"]) / (E - 2) for t in (False, True)}
    m, t = sdp.open_series(work / f"m{E}.zarr"), sdp.open_series(work / f"t{E}.zarr")
    same = all(np.array_equal(m[v].values, t[v].values, equal_nan=m[v].dtype.kind == "f") for v in m.variables)
    rec = t.attrs["runs"][-1]["tiled"]
    inside = {w: ds.attrs["runs"][-1]["timings"]["epochs"] / E for w, ds in (("memory", m), ("tiles", t))}
    return ["### Epochs beyond memory: tiles on Dask", "",
            f"{E} epochs of {n:,} points (.npy, a {size:.0f} m slope), {m.sizes['point']:,} core points (the "
            f"default subsample), d = {D}, D = {DN}, max distance 0.5; tiles: `--memory-limit {limit_mb}MB --workers "
            f"2`{' --tiled' if forced else ''} ({rec['reason']}), {rec['tiles']} tiles of {rec['tile_size']:.1f} m; "
            f"in memory: `--memory-limit {f'{limit_mb}MB' if forced else '4GB'}`. Whole jobs of 2 and {E} epochs, "
            f"interleaved, fastest of {rounds}; load {load0[0]:.1f} before, {load1[0]:.1f} after, "
            f"{os.cpu_count()} cores.", "",
            "| | in memory | tiles on Dask | ratio |", "|---|---|---|---|",
            f"| time per epoch, (t{E} − t2)/{E - 2} | {per[False]:.2f} s | {per[True]:.2f} s | "
            f"{per[True] / per[False]:.1f}× |",
            f"| inside the job: the epochs' loop per epoch | {inside['memory']:.2f} s | {inside['tiles']:.2f} s | "
            f"{inside['tiles'] / inside['memory']:.1f}× |",
            f"| whole job, {E} epochs | {runs[(False, E)]['seconds']:.1f} s | {runs[(True, E)]['seconds']:.1f} s | "
            f"{runs[(True, E)]['seconds'] / runs[(False, E)]['seconds']:.1f}× |",
            f"| peak memory, all processes, {E} epochs | {runs[(False, E)]['peak_mb']:.0f} MB | "
            f"{runs[(True, E)]['peak_mb']:.0f} MB | |",
            f"| archives equal (every array) | | {'yes' if same else 'NO'} | |", "",
            "Tiled run's steps (s, summed over the run): "
            + ", ".join(f"{k} {v:.1f}" for k, v in rec["timings"].items()), ""]


if __name__ == "__main__":
    main()
