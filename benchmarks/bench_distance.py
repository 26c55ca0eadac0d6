"""How much it changed: sdp.distances against analytic truth and against py4dgeo's M3C2.

Prints markdown tables (docs/benchmarks.md quotes them; ``results/distance.md`` keeps the last
run):

1. Analytic truth: a rough plane and a sphere scanned twice with noise σ, the second moved by
   2 mm … 2 m (and the plane tilted by 1°): median |error| of the distance, as a share of σ,
   and the share of points flagged significant; a static pair (new noise only) must flag 5 %.
   Here and beside M3C2 the level is M3C2's (``registration_error=0``): a whole surface moved is
   the change measured (sdp's default would read it as a registration error, see
   ``bench_level.py``), and py4dgeo's M3C2 has ``reg = 0``.
2. The masks and the distance: the share of a moved plane's points ``sdp.detect_changes`` calls
   appeared, against the distance ``s·√(2 ln(G₀/h))`` the module docstring predicts.
3. Real scans side by side with py4dgeo's M3C2 on the same core points with matched scales
   (cylinder radius d/2, normal radius D/2, half-length 3σ_p = 0.75 d as sdp's cylinder; sdp
   also looks farther along the normal, M3C2 then has no distance), normals from the
   reference, oriented +z: Toronto ALS ground before and after the vertical alignment (the
   0.41 m offset), the two tree epochs, the DLUT re-scans. Median |sdp − M3C2|, as a share of
   d, agreement of the significance flags, the share without a distance (and of it, sdp's places
   off the cylinder's axis: M3C2's step edge), and the time ratio at 20,000 core points and at
   every point, in the same run.
4. 1 M points against 1 M points, every point a core point (sdp and M3C2).

Usage: ``python benchmarks/bench_distance.py [--quick]`` (``--quick``: smaller clouds, no
every-point M3C2 on 1 M points). Needs ``py4dgeo`` (``pip install 'sdp[m3c2]'``) for 3 and 4.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import flat
import numpy as np

import sdp

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
NOISE = 0.002


def rough_plane(rng, n, size=10.0):
    """Points of z = f(x, y) (1 cm bumps of 0.5 m wavelength) with noise; f and its gradient."""
    def f(xy):
        return 0.01 * np.sin(2 * np.pi * xy[..., 0] / 0.5) * np.sin(2 * np.pi * xy[..., 1] / 0.5)
    xy = rng.uniform(0, size, (n, 2))
    return np.c_[xy, f(xy)], f


def ray_to_surface(q, n, f, shift=0.0, tilt=0.0):
    """t with q + t·n on the surface z = f(x, y)·… moved by ``shift`` in z and tilted by ``tilt``
    radians about the line y = 5 (Newton's method on g(t) = z − surface(x, y))."""
    c, s = np.cos(tilt), np.sin(tilt)
    t = np.zeros(len(q))
    for _ in range(30):
        p = q + t[:, None] * n
        # the moved surface: points (x, y', z') = R·(x, y − 5, f) + (0, 5, shift); invert for (x, y)
        y0 = (p[:, 1] - 5) * c + (p[:, 2] - shift) * s  # back-rotated coordinates
        z0 = -(p[:, 1] - 5) * s + (p[:, 2] - shift) * c
        g = z0 - f(np.c_[p[:, 0], y0 + 5])
        eps = 1e-6
        p2 = q + (t + eps)[:, None] * n
        y2 = (p2[:, 1] - 5) * c + (p2[:, 2] - shift) * s
        z2 = -(p2[:, 1] - 5) * s + (p2[:, 2] - shift) * c
        g2 = z2 - f(np.c_[p2[:, 0], y2 + 5])
        t = t - g * eps / np.where(np.abs(g2 - g) > 1e-15, g2 - g, 1e-15)
    return t


def moved(pts, shift, tilt):
    c, s = np.cos(tilt), np.sin(tilt)
    y, z = pts[:, 1] - 5, pts[:, 2]
    return np.c_[pts[:, 0], y * c - z * s + 5, y * s + z * c + shift]


def analytic(out, rng, n):
    out(f"## 1. Analytic truth (noise σ = {NOISE * 1000:g} mm, {n:,} points per epoch)\n")
    out("Rough plane: 10 m × 10 m, z = 1 cm·sin(2πx/0.5 m)·sin(2πy/0.5 m). Sphere: radius 1 m. "
        "Truth: where the ray from each core point along sdp's normal meets the true surfaces of "
        "the two epochs (the difference of the two). Core points: every reference point.\n")
    out("| surface | move | median distance | median error | median abs. error | abs. error / σ | significant | "
        "not comparable | d | time |")
    out("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    base, f = rough_plane(rng, n)
    cases = [("plane", "static", 0.0, 0.0)] + [("plane", f"+{m * 1000:g} mm" if m < 1 else f"+{m:g} m", m, 0.0)
                                                  for m in (0.002, 0.01, 0.05, 0.2, 2.0)]
    cases.append(("plane", "tilted 1°", 0.0, np.radians(1.0)))
    for surface, label, shift, tilt in cases:
        a = base + [0, 0, 0] + NOISE * rng.standard_normal(base.shape)
        b0, _ = rough_plane(rng, n)
        b = moved(b0, shift, tilt) + NOISE * rng.standard_normal(b0.shape)
        t0 = time.perf_counter()
        d = sdp.distances(a, b, registration_error=0)  # M3C2's level: the whole surface moves
        el = time.perf_counter() - t0
        inner = ((a[:, :2] > 1) & (a[:, :2] < 9)).all(axis=1)  # away from the edges of the tilted copy
        truth = ray_to_surface(a, d.normal, f, shift, tilt) - ray_to_surface(a, d.normal, f)
        row(out, surface, label, d, truth, inner, el)
    for label, shift in (("static", 0.0), ("+2 mm", 0.002), ("+5 cm", 0.05), ("+50 cm", 0.5)):
        a = sphere(rng, n, 1.0) + NOISE * rng.standard_normal((n, 3))
        b = sphere(rng, n, 1.0) + NOISE * rng.standard_normal((n, 3)) + [shift, 0, 0]
        t0 = time.perf_counter()
        d = sdp.distances(a, b, registration_error=0)  # M3C2's level: the whole surface moves
        el = time.perf_counter() - t0
        truth = ray_sphere(a, d.normal, [shift, 0, 0]) - ray_sphere(a, d.normal, [0, 0, 0])
        row(out, "sphere", label, d, truth, np.ones(n, bool), el)
    out()


def sphere(rng, n, radius):
    v = rng.standard_normal((n, 3))
    return radius * v / np.linalg.norm(v, axis=1)[:, None]


def ray_sphere(q, n, centre, radius=1.0):
    """t of the intersection of q + t·n with the sphere nearest t = 0."""
    oc = q - np.asarray(centre)
    b = np.einsum("ij,ij->i", oc, n)
    c = np.einsum("ij,ij->i", oc, oc) - radius**2
    root = np.sqrt(np.maximum(b * b - c, 0))
    t1, t2 = -b - root, -b + root
    return np.where(np.abs(t1) < np.abs(t2), t1, t2)


def row(out, surface, label, d, truth, inner, el):
    ok = d.comparable & inner
    signed = d.distance[ok] - truth[ok]
    err = np.abs(signed)
    out(f"| {surface} | {label} | {np.median(d.distance[ok]) * 1000:.2f} mm | {np.median(signed) * 1000:+.3f} mm | "
        f"{np.median(err) * 1000:.3f} mm | "
        f"{np.median(err) / NOISE:.1%} | {d.significant[ok].mean():.1%} | {(~d.comparable).mean():.2%} | "
        f"{d.projection_scale * 100:.1f} cm | {el:.2f} s |")


def masks(out, rng, n):
    out("## 2. The masks and the distance (plane, noise 2 mm, moved along z)\n")
    a, _ = rough_plane(rng, n)
    a = a + NOISE * rng.standard_normal(a.shape)
    out("| move | move / σ | appeared (detect_changes) | median distance | predicted threshold |")
    out("|---:|---:|---:|---:|---:|")
    sigma = 2 * sdp.auto_voxel_size(a)
    for shift in sigma * np.array([0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0]):
        b, _ = rough_plane(rng, n)
        b = b + NOISE * rng.standard_normal(b.shape) + [0, 0, shift]
        r = flat.detect_changes(a, b, sensor_origin=None)
        d = sdp.distances(b, a, registration_error=0)  # core points on the current: the reference lies −shift away
        sigma = r.reference_field.sigma
        g0 = float(np.median(r.reference_field.density(a)))
        s = np.sqrt(sigma**2 + np.median(d.spread1) ** 2)
        threshold = s * np.sqrt(2 * np.log(g0 / r.h))
        out(f"| {shift * 100:.1f} cm | {shift / sigma:.1f} | {r.appeared.mean():.1%} | "
            f"{-np.median(d.distance) * 100:.2f} cm | "
            f"{threshold * 100:.2f} cm |")
    out()


def m3c2(ref, cur, core, d, *, normals=None):
    """py4dgeo's M3C2 at ``core`` with the scales sdp used (d: a Distances), with its own
    normals or the given ones."""
    import py4dgeo

    py4dgeo.set_num_threads(os.cpu_count() or 1) if hasattr(py4dgeo, "set_num_threads") else None
    t0 = time.perf_counter()
    e1, e2 = py4dgeo.Epoch(ref), py4dgeo.Epoch(cur)
    e1.build_kdtree()
    e2.build_kdtree()
    algo = py4dgeo.M3C2(epochs=(e1, e2), corepoints=core, normal_radii=[d.normal_scale / 2],
                        cyl_radius=d.projection_scale / 2, max_distance=0.75 * d.projection_scale,
                        corepoint_normals=normals)
    dist, unc = algo.run()
    return dist, unc["lodetection"], time.perf_counter() - t0


def side_by_side(out, name, ref, cur, rng, *, every=True, **kwargs):
    rows = []
    sizes = [20_000] + ([len(ref)] if every and len(ref) > 20_000 else [])
    for m in sizes:
        core = ref if m >= len(ref) else ref[np.sort(rng.choice(len(ref), m, replace=False))]
        t0 = time.perf_counter()
        d = flat.distances(ref, cur, core_points=core, sensor_origin=None, registration_error=0, **kwargs)  # as M3C2
        t_sdp = time.perf_counter() - t0
        dm, lod_m, t_m = m3c2(ref, cur, core, d)
        both = np.isfinite(d.distance) & np.isfinite(dm)
        diff = np.abs(d.distance[both] - dm[both])
        agree = (d.significant[both] == (np.abs(dm[both]) > lod_m[both])).mean()
        dn, lod_n, _ = m3c2(ref, cur, core, d, normals=d.normal)  # M3C2 along sdp's normals
        same = np.isfinite(d.distance) & np.isfinite(dn)
        agree_n = (d.significant[same] == (np.abs(dn[same]) > lod_n[same])).mean()
        rows.append(f"| {name} | {len(core):,} | {np.median(d.distance[both]):+.3f} | {np.median(dm[both]):+.3f} | "
                    f"{np.median(diff):.4f} ({np.median(diff) / d.projection_scale:.3f} d) | {agree:.1%} | "
                    f"{agree_n:.1%} | "
                    f"{d.significant[both].mean():.1%} / {(np.abs(dm[both]) > lod_m[both]).mean():.1%} | "
                    f"{(~np.isfinite(d.distance)).mean():.1%} / {(~np.isfinite(dm)).mean():.1%} | "
                    f"{d.summary()['off_axis'] / len(core):.1%} | "
                    f"{d.projection_scale:.3f} | {t_sdp:.2f} s | {t_m:.2f} s | {t_m / t_sdp:.1f}× |")
    for r in rows:
        out(r)


def real(out, rng, quick):
    out("## 3. Real scans: sdp.distances and py4dgeo's M3C2, same core points, matched scales\n")
    out("| pair | core points | sdp median | M3C2 median | median abs. difference | significance agrees | "
        "agrees, M3C2 on sdp's normals | significant sdp / M3C2 | no distance sdp / M3C2 | of which off the axis | "
        "d (m) | sdp | M3C2 | ratio |")
    out("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    warm = rng.random((2000, 3))
    sdp.distances(warm, warm)  # kernels loaded from the cache before the first timing
    t = DATA / "als_toronto"
    a, b = sdp.read_points(t / "TTP_2015.laz"), sdp.read_points(t / "TTP_2023.laz")
    ga, gb = a.xyz[a.fields["classification"] == 2], b.xyz[b.fields["classification"] == 2]
    side_by_side(out, "Toronto ground, as flown", ga, gb, rng, every=not quick)
    al = sdp.align(ga, gb, fix_horizontal=True)
    side_by_side(out, "Toronto ground, aligned", ga, sdp.transform_points(al.matrix, gb), rng, every=not quick)
    for tree in ("tree10", "tree73"):
        ta = np.loadtxt(DATA / "trees" / f"{tree}_2022.xyz")[:, :3]
        tb = np.loadtxt(DATA / "trees" / f"{tree}_2023.xyz")[:, :3]
        side_by_side(out, f"{tree} 2022 → 2023", ta, tb, rng, every=not quick)
    d = DATA / "dlut"
    ref = sdp.read_points(d / "A603_reference.pcd").xyz
    for scan in ("rescan1", "rescan2"):
        side_by_side(out, f"DLUT reference → {scan}", ref, sdp.read_points(d / f"A603_{scan}.pcd").xyz, rng,
                     every=not quick)
    out()


def million(out, rng, quick):
    n = 200_000 if quick else 1_000_000
    out(f"## 4. {n:,} points against {n:,}, every point a core point\n")
    size = 10.0 * np.sqrt(n / 200_000)
    a, _ = rough_plane(rng, n, size)
    b, _ = rough_plane(rng, n, size)
    a = a + NOISE * rng.standard_normal(a.shape)
    b = b + NOISE * rng.standard_normal(b.shape) + [0, 0, 0.01]
    sdp.distances(a[:1000], b[:1000])  # compiled kernels loaded
    t0 = time.perf_counter()
    d = sdp.distances(a, b)
    t_sdp = time.perf_counter() - t0
    out(f"sdp: {t_sdp:.2f} s ({', '.join(f'{k} {v:.2f}' for k, v in d.timings.items())}); "
        f"median distance {np.median(d.distance[d.comparable]) * 1000:.2f} mm (truth 10 mm).")
    try:
        dm, _, t_m = m3c2(a, b, a, d)
        out(f"M3C2 (py4dgeo, every point): {t_m:.2f} s, {t_m / t_sdp:.1f}× sdp's time; median "
            f"{np.nanmedian(dm) * 1000:.2f} mm.")
    except ImportError:
        out("M3C2: py4dgeo not installed.")
    out()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--only", choices=["analytic", "masks", "real", "million"])
    a = p.parse_args(argv)
    rng = np.random.default_rng(0)
    lines = []

    def out(text=""):
        print(text, flush=True)
        lines.append(text)

    load = os.getloadavg()[0]
    out(f"# sdp.distances (bench_distance.py{' --quick' if a.quick else ''}), load {load:.1f} on "
        f"{os.cpu_count()} cores\n")
    n = 50_000 if a.quick else 200_000
    if a.only in (None, "analytic"):
        analytic(out, rng, n)
    if a.only in (None, "masks"):
        masks(out, rng, n)
    if a.only in (None, "real") and DATA.is_dir():
        real(out, rng, a.quick)
    if a.only in (None, "million"):
        million(out, rng, a.quick)
    out(f"Load at the end: {os.getloadavg()[0]:.1f}.")
    if a.only is None:
        res = ROOT / "benchmarks" / "results"
        res.mkdir(exist_ok=True)
        (res / f"distance{'-quick' if a.quick else ''}.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
