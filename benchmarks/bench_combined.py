"""One decision from density and distance, and an honest level of detection (issue 34).

1. The 27 fixed-camera mOSD pairs of ``bench_decision.py`` read as ``sdp change`` reads them
   (``sdp.read_points``: the sensor from each PCD's VIEWPOINT), each pair compared with
   ``decision="point"`` (density alone, the paper's) and ``decision="combined"``, interleaved pair
   by pair so that the shared machine's load falls on both alike: kappa over the scored points,
   false positives (scored points) on the pairs without change, time per pair.
2. Static real pairs: the share flagged changed and the share significant (``|distance| > lod``)
   of ``decision="combined"``: the PCL grabber sequence (6 ordered pairs, after GICP), the DLUT
   re-scans (after GICP; outside the people = points the density test leaves unchanged), the
   Toronto ground (class 2, after density alignment).
3. The combined decision in tiles against memory on the Toronto pair (:func:`tiles`).
4. Where the misses lie (:func:`misses`): each decision's missed and false points of the 24 pairs
   with an appeared object, by where the current return lies against the reference's return at
   the same pixel, and the kappa either kind would give if the decision had them right.
5. The plane test's reach from what the other epoch lost (:func:`reaches`): kappa and the static
   pairs' false positives of both decisions with the reach at 2σ … 10σ instead of 2·truncate·σ.

Nothing here is fitted: the rule's constants are in ``sdp.change._combined`` and
``sdp.distance._noise`` with their reasons. Prints markdown; ``--only kinect|static|tiles|misses|reaches``.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
from bench_decision import LEARN, labelled_pairs

import sdp

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def kinect(ablation: bool = False):
    """``ablation``: also ``"combined"`` without the noise model (M3C2's level: the spreads alone,
    no range law, no systematic part), to tell the distance's part of the gain from the model's."""
    decisions = ("point", "combined") + (("m3c2 level",) if ablation else ())
    rows = []
    first = True
    for t, _, _, truth, scored in labelled_pairs():
        ref, cur = sdp.read_points(LEARN / f"learn{t - 1}.pcd"), sdp.read_points(LEARN / f"learn{t}.pcd")
        if first:  # each decision's kernels loaded once before any timing (the first call loads them)
            for dec in ("point", "combined"):
                sdp.detect_changes(ref, cur, decision=dec)
            first = False
        row = {"pair": t, "static": not truth.any()}
        for dec in decisions:
            t0 = time.perf_counter()
            if dec == "m3c2 level":
                with _without_noise_model():
                    r = sdp.detect_changes(ref, cur, decision="combined")
            else:
                r = sdp.detect_changes(ref, cur, decision=dec)
            row[f"{dec}_s"] = time.perf_counter() - t0
            app = r.appeared
            row[dec] = sdp.kappa(truth[scored], app[scored]) if truth.any() else float("nan")
            row[f"{dec}_fp"] = int((app & scored & ~truth).sum())
            if dec != "point":
                d, lod = r.current_distance, r.current_lod
                ok = np.isfinite(d) & (r.current_state == 0)
                row[f"{dec}_significant"] = float((np.abs(d[ok]) > lod[ok]).mean())
        rows.append(row)
        print(row, flush=True)
    ks = {dec: np.nanmean([r[dec] for r in rows]) for dec in decisions}
    times = {dec: np.median([r[f"{dec}_s"] for r in rows]) for dec in decisions}
    static = [r for r in rows if r["static"]]
    print("\n| decision | kappa (27 pairs) | FP on the static pairs (scored points) | significant, static pairs "
          "| s per pair (median) |")
    print("|---|---:|---|---|---:|")
    for dec in decisions:
        sig = ", ".join(f"{100 * r[f'{dec}_significant']:.1f} %" for r in static) if dec != "point" else "—"
        print(f"| {dec} | {ks[dec]:.3f} | {', '.join(str(r[f'{dec}_fp']) for r in static)} | {sig} | {times[dec]:.3f} |")
    ratios = [r["combined_s"] / r["point_s"] for r in rows]
    print(f"\ntime ratio combined / point: {times['combined'] / times['point']:.2f} (of the medians; per pair "
          f"{min(ratios):.2f}–{max(ratios):.2f}); load {os.getloadavg()}")


class _without_noise_model:
    """``decision="combined"`` with M3C2's level of detection: the spreads alone (no range law,
    no systematic part), for the ablation."""

    def __enter__(self):
        import sdp.distance._noise as N

        self.module, self.original = N, N.point_distances

        def plain(*args, **kw):
            return self.original(*args, **{**kw, "registration_error": 0.0, "range_exponent": 0.0})

        N.point_distances = plain

    def __exit__(self, *exc):
        self.module.point_distances = self.original


def share(r):
    """(flagged share, significant share over comparable unchanged points) of both directions."""
    n = r.n_current + r.n_reference
    flagged = (int(r.appeared.sum()) + int(r.disappeared.sum())) / n
    sig = tot = 0
    for d, lod, st in ((r.current_distance, r.current_lod, r.current_state),
                       (r.reference_distance, r.reference_lod, r.reference_state)):
        ok = np.isfinite(d) & (st == 0)
        sig += int((np.abs(d[ok]) > lod[ok]).sum())
        tot += int(ok.sum())
    return flagged, sig / max(tot, 1)


def static():
    print("| data | pair | flagged changed | significant (unchanged points) |")
    print("|---|---|---:|---:|")
    seq = sorted((DATA / "pcl_kinect" / "grabber_sequence").glob("*.pcd"))
    for i in range(len(seq)):
        for j in range(len(seq)):
            if i == j:
                continue
            ref, cur = sdp.read_points(seq[i]), sdp.read_points(seq[j])
            a = sdp.align(ref, cur, method="gicp")
            moved = a.apply(cur.xyz)
            o = np.stack([ref.sensor_origin, a.matrix[:3, :3] @ cur.sensor_origin + a.matrix[:3, 3]])
            r = sdp.detect_changes(ref, moved, decision="combined", coverage=sdp.Coverage(sensor_origin=o))
            f, s = share(r)
            print(f"| grabber | {i}→{j} | {100 * f:.2f} % | {100 * s:.1f} % |", flush=True)
    dl = DATA / "dlut"
    ref = sdp.read_points(dl / "A603_reference.pcd")
    for k in (1, 2):
        cur = sdp.read_points(dl / f"A603_rescan{k}.pcd")
        a = sdp.align(ref, cur, method="gicp")
        o = np.stack([ref.sensor_origin, a.matrix[:3, :3] @ cur.sensor_origin + a.matrix[:3, 3]])
        r = sdp.detect_changes(ref, a.apply(cur.xyz), decision="combined", coverage=sdp.Coverage(sensor_origin=o))
        f, s = share(r)
        dens = sdp.detect_changes(ref, a.apply(cur.xyz), decision="point", coverage=sdp.Coverage(sensor_origin=o))
        fd = (int(dens.appeared.sum()) + int(dens.disappeared.sum())) / (dens.n_current + dens.n_reference)
        print(f"| DLUT | reference→rescan{k} (people are changes; density alone flags {100 * fd:.2f} %) | "
              f"{100 * f:.2f} % | {100 * s:.1f} % |", flush=True)
    t15, t23 = sdp.read_points(DATA / "als_toronto" / "TTP_2015.laz"), sdp.read_points(DATA / "als_toronto" / "TTP_2023.laz")
    g15 = t15.xyz[t15.fields["classification"] == 2]
    g23 = t23.xyz[t23.fields["classification"] == 2]
    a = sdp.align(g15, g23, method="density", fix_horizontal=True)
    r = sdp.detect_changes(g15, a.apply(g23), decision="combined")
    f, s = share(r)
    print(f"| Toronto ground | 2015→2023 aligned | {100 * f:.2f} % | {100 * s:.1f} % |", flush=True)
    print(f"\nload {os.getloadavg()}")


def misses():
    """The missed (FN) and false (FP) points of each decision on the 24 pairs with an appeared
    object, by the current return against the reference's return at the same pixel (the camera
    stayed put): in front of it by more than 1 cm (the reference saw through the place), within
    1 cm, behind it by more than 1 cm (the reference could not see the place: its hider is gone
    or still there), or no reference return at that pixel. Behind, the decision rests on the
    plane test (:mod:`sdp.change._planes`): a point behind a gone hider continuing the unchanged
    surface is unchanged (a moved object's table), else changed. "Kappa with the tables right":
    the false points behind counted unchanged; "with the hidden objects right": the missed points
    behind counted changed."""
    decisions = ("point", "combined")
    where = ("in front", "within 1 cm", "behind", "no reference return")
    counts = {(dec, kind, w): 0 for dec in decisions for kind in ("FN", "FP") for w in where}
    gone = dict.fromkeys(decisions, 0)
    kappas = {(dec, k): [] for dec in decisions for k in ("as is", "tables right", "hidden objects right", "both")}
    for t, _, _, truth, scored in labelled_pairs():
        if not truth.any():
            continue
        ref, cur = sdp.read_points(LEARN / f"learn{t - 1}.pcd"), sdp.read_points(LEARN / f"learn{t}.pcd")
        rng = np.full(ref.image[0] * ref.image[1], np.nan)
        rng[ref.pixels] = np.linalg.norm(ref.xyz - ref.sensor_origin, axis=1)
        ahead = rng[cur.pixels] - np.linalg.norm(cur.xyz - cur.sensor_origin, axis=1)  # > 0: current in front
        with np.errstate(invalid="ignore"):
            w = np.select([ahead > 0.01, np.abs(ahead) <= 0.01, ahead < -0.01], where[:3], where[3])
        behind = w == "behind"
        for dec in decisions:
            r = sdp.detect_changes(ref, cur, decision=dec)
            app = r.appeared
            fn, fp = truth & ~app, scored & ~truth & app
            for kind, m in (("FN", fn), ("FP", fp)):
                for x in where:
                    counts[dec, kind, x] += int((m & (w == x)).sum())
            gone_ref = np.zeros(len(rng), bool)
            gone_ref[ref.pixels] = r.disappeared
            gone[dec] += int((fn & behind & gone_ref[cur.pixels]).sum())
            tables, hidden = app & ~(behind & ~truth), app | (behind & truth)
            for k, a in (("as is", app), ("tables right", tables), ("hidden objects right", hidden),
                         ("both", tables | (behind & truth))):
                kappas[dec, k].append(sdp.kappa(truth[scored], a[scored]))
        print(t, flush=True)
    print("\n| decision | points | " + " | ".join(where) + " |")
    print("|---|---|" + "---:|" * len(where))
    for dec in decisions:
        for kind in ("FN", "FP"):
            print(f"| {dec} | {kind} | " + " | ".join(f"{counts[dec, kind, x]:,}" for x in where) + " |")
    for dec in decisions:
        print(f"\n{dec}: missed points behind, whose reference return at that pixel the decision marked "
              f"disappeared: {gone[dec]:,} of {counts[dec, 'FN', 'behind']:,}; kappa " +
              ", ".join(f"{k} {np.mean(v):.3f}" for (d, k), v in kappas.items() if d == dec))
    print(f"\nload {os.getloadavg()}")


def reaches(factors=(2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0)):
    """Kappa (24 pairs) and false positives (3 static pairs) of ``point`` and ``combined`` with the
    plane test's patch leaving out the unchanged points within ``f``·σ of a point gone from the other
    epoch, for each ``f`` of ``factors`` (the default: 2·truncate = 6)."""
    import sdp.change._detect as detect

    original = detect.visibility_states
    pairs = [(t, truth, scored, sdp.read_points(LEARN / f"learn{t - 1}.pcd"), sdp.read_points(LEARN / f"learn{t}.pcd"))
             for t, _, _, truth, scored in labelled_pairs()]
    print("| reach | kappa `point` | kappa `combined` | false positives `point` | `combined` |")
    print("|---|---:|---:|---|---|")
    try:
        for f in factors:
            detect.visibility_states = lambda *a, f=f, **kw: original(*a, **{**kw, "gone_reach": f})
            k, fp = {"point": [], "combined": []}, {"point": [], "combined": []}
            for t, truth, scored, ref, cur in pairs:
                for dec in k:
                    app = sdp.detect_changes(ref, cur, decision=dec).appeared
                    if truth.any():
                        k[dec].append(sdp.kappa(truth[scored], app[scored]))
                    else:
                        fp[dec].append(int((app & scored).sum()))
            print(f"| {f:g}σ | {np.mean(k['point']):.3f} | {np.mean(k['combined']):.3f} | "
                  f"{', '.join(map(str, fp['point']))} | {', '.join(map(str, fp['combined']))} |", flush=True)
    finally:
        detect.visibility_states = original
    print(f"\nload {os.getloadavg()}")


def tiles():
    """The combined decision in tiles against memory on the Toronto pair (whole scene, 2023 aligned
    to 2015 with ``fix_horizontal``): the states, and the time, with Dask's synchronous scheduler
    (this process) and a local cluster; then with memory's level given (what remains is the
    tiles' own doing); then memory's own spread, the level's 1,024-cell sample shifted by one to
    five cells (what differs between tilings is that sample)."""
    from sdp.distance import _noise
    from sdp.scale._tiles import detect_changes_tiled

    t15, t23 = sdp.read_points(DATA / "als_toronto" / "TTP_2015.laz"), sdp.read_points(DATA / "als_toronto" / "TTP_2023.laz")
    ref, cur = t15.xyz, sdp.align(t15.xyz, t23.xyz, method="density", fix_horizontal=True).apply(t23.xyz)
    sdp.detect_changes(ref, cur, decision="combined")
    t0 = time.perf_counter()
    memory = sdp.detect_changes(ref, cur, decision="combined")
    seconds = time.perf_counter() - t0
    lattice = sdp.Lattice(voxel_size=memory.voxel_size, sigma_voxels=memory.sigma / memory.voxel_size)
    print("| run | tiles | appeared | disappeared | same state as memory (current / reference) | s |")
    print("|---|---:|---:|---:|---|---:|")
    print(f"| memory | — | {memory.appeared.sum():,} | {memory.disappeared.sum():,} | — | {seconds:.2f} |")
    for size in (None, 600.0, 300.0):
        for scheduler in ("synchronous", None):
            t0 = time.perf_counter()
            r = detect_changes_tiled(ref, cur, lattice=lattice, decision="combined",
                                     execution=sdp.Execution(scheduler=scheduler, tile_size=size))
            seconds = time.perf_counter() - t0
            same = [100 * float((a == b).mean()) for a, b in ((r.appeared, memory.appeared),
                                                               (r.disappeared, memory.disappeared))]
            print(f"| tiles of {size or 'the memory limit'} m, {scheduler or 'local cluster'} | {r.n_tiles} | "
                  f"{r.appeared.sum():,} | {r.disappeared.sum():,} | {same[0]:.2f} / {same[1]:.2f} % | {seconds:.2f} |",
                  flush=True)
    levels = [tuple(memory._distances[k].surface.level) for k in (1, 0)]  # appeared's, disappeared's
    fit = _noise.fit_level
    for size in (600.0, 300.0, 150.0):  # memory's level given: what remains is the tiles' own doing
        calls = iter(levels)  # the tiles fit the appeared direction's level first
        _noise.fit_level = lambda *a, **k: next(calls)
        r = detect_changes_tiled(ref, cur, lattice=lattice, decision="combined",
                                 execution=sdp.Execution(scheduler="synchronous", tile_size=size))
        same = [100 * float((a == b).mean()) for a, b in ((r.appeared, memory.appeared),
                                                           (r.disappeared, memory.disappeared))]
        print(f"| tiles of {size} m, memory's level | {r.n_tiles} | {r.appeared.sum():,} | {r.disappeared.sum():,} | "
              f"{same[0]:.2f} / {same[1]:.2f} % | — |", flush=True)
    _noise.fit_level = fit
    sample = _noise.SurfaceDistances.calibration_sample
    for shift in range(1, 6):  # memory with the regular sample of cells started `shift` cells later
        def shifted(self, shift=shift):
            m = len(self._measured)
            step = max(1, m // _noise._CALIBRATION_CELLS)
            rows = np.arange(shift % step, m, step)
            self._measure(rows)
            idx = self.points_of(rows)
            idx = _noise.thinned(np.sort(idx[np.isfinite(self._dist[idx]) & self._stable[idx]]))
            return self._dist[idx], self._random[idx], self._r[idx]
        _noise.SurfaceDistances.calibration_sample = shifted
        r = sdp.detect_changes(ref, cur, decision="combined")
        print(f"| memory, the sample {shift} cell(s) on | — | {r.appeared.sum():,} | {r.disappeared.sum():,} | — | — |")
    _noise.SurfaceDistances.calibration_sample = sample
    print(f"\nload {os.getloadavg()}")


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("--only", choices=("kinect", "static", "tiles", "misses", "reaches"))
    p.add_argument("--ablation", action="store_true", help="also the combined decision without the noise model")
    a = p.parse_args()
    if a.only in (None, "kinect"):
        kinect(a.ablation)
    if a.only in (None, "static"):
        static()
    if a.only in (None, "tiles"):
        tiles()
    if a.only in (None, "misses"):
        misses()
    if a.only in (None, "reaches"):
        reaches()
