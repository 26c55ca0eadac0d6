"""Signed distances along the normal with M3C2's level of detection (sdp.distances)."""

import numpy as np
import pytest
from conftest import drawn_pixels, picture

import sdp
import sdp.distance._distances


def plane(rng, n, noise, z=0.0, size=4.0):
    return np.c_[rng.uniform(0, size, (n, 2)), z + noise * rng.standard_normal(n)]


def sphere(rng, n, radius, noise, centre=(0.0, 0.0, 0.0)):
    v = rng.standard_normal((n, 3))
    v /= np.linalg.norm(v, axis=1)[:, None]
    return np.asarray(centre) + v * (radius + noise * rng.standard_normal(n))[:, None]


@pytest.mark.parametrize("shift", [0.002, 0.03, 0.5])
def test_plane_shift_is_measured_with_its_sign(rng, shift):
    a = plane(rng, 40_000, 0.002)
    d = sdp.distances(a, plane(rng, 40_000, 0.002, z=shift))
    assert d.comparable.all()
    assert abs(np.median(d.distance) - shift) < 0.0005  # ≤ 1 mm and ≤ 25 % of the noise
    assert np.allclose(np.abs(d.normal[:, 2]), 1, atol=0.01) and (d.normal[:, 2] > 0).all()  # +z
    down = sdp.distances(a, plane(rng, 40_000, 0.002, z=-shift))
    assert abs(np.median(down.distance) + shift) < 0.0005


def test_static_pair_flags_about_five_percent(rng):
    d = sdp.distances(plane(rng, 60_000, 0.003), plane(rng, 60_000, 0.003))
    assert 0.03 < d.significant.mean() < 0.07
    assert abs(np.median(d.spread1) - 0.003) < 0.0006 and abs(np.median(d.spread2) - 0.003) < 0.0006


def test_large_shift_found_on_a_longer_cylinder(rng):
    a = plane(rng, 30_000, 0.002)
    d = sdp.distances(a, a + [0, 0, 1.0], cylinder=sdp.Cylinder(projection_scale=0.1))
    inner = ((a[:, :2] > 0.3) & (a[:, :2] < 3.7)).all(axis=1)  # a corner's normal tilts
    assert (d.level[inner] == 1).all()
    error = np.abs(d.distance - d.normal[:, 2])[inner]  # 1 m measured along the normal
    assert np.median(error) < 1e-4 and error.max() < 2e-3
    short = sdp.distances(a, a + [0, 0, 1.0], cylinder=sdp.Cylinder(projection_scale=0.1, max_distance=0.5))
    assert not short.comparable.any() and not short.significant.any()


def test_sphere_growth_along_outward_normals(rng):
    a = sphere(rng, 60_000, 1.0, 0.002)
    b = sphere(rng, 60_000, 1.01, 0.002)
    d = sdp.distances(a, b, sensor_origin=None, orientation=None)
    outward = np.einsum("ij,ij->i", d.normal, a) > 0
    signed = np.where(outward, d.distance, -d.distance)  # the sign follows the normal's side
    assert abs(np.median(signed) - 0.01) < 0.0005


def test_normals_point_to_the_sensor(rng):
    wall = np.c_[np.full(20_000, 2.0), rng.uniform(-1, 1, (20_000, 2))] + 0.002 * rng.standard_normal((20_000, 3))
    nearer = wall - [0.02, 0, 0]
    d = sdp.distances(wall, nearer, sensor_origin=[0.0, 0.0, 0.0])
    assert (d.normal[:, 0] < 0).all()  # towards the sensor at x = 0
    assert abs(np.median(d.distance) - 0.02) < 0.001  # the current lies on the sensor's side
    assert "sensor" in d.orientation
    # a cloud whose file records its sensor (a PCD's VIEWPOINT): an orientation given would be ignored, so
    # it is refused; without the sensor it is used
    cloud = sdp.io.Cloud(wall, {}, None, 0, None, np.array([0.0, 0, 0, 1, 0, 0, 0]), True, None)  # organized
    with pytest.raises(sdp.InvalidOptionError, match="records theirs"):
        sdp.distances(cloud, nearer, orientation=[1.0, 0, 0])
    away = sdp.distances(cloud, nearer, orientation=[1.0, 0, 0], sensor_origin=None)
    assert (away.normal[:, 0] > 0).all()


def test_no_data_is_not_comparable(rng):
    a = plane(rng, 20_000, 0.002, size=4.0)
    b = plane(rng, 20_000, 0.002, size=2.0)  # covers only a quarter of a
    d = sdp.distances(a, b)
    inside = (a[:, :2] < 1.8).all(axis=1)
    outside = (a[:, :2] > 2.3).any(axis=1)
    assert d.comparable[inside].all() and not d.comparable[outside].any()
    assert np.isnan(d.lod[outside]).all() and not d.significant[outside].any()
    s = d.summary()
    assert s["comparable"] + s["not_comparable"] == len(a) and s["not_comparable"] == int((~d.comparable).sum())


def test_core_points_and_registration_error(rng):
    a, b = plane(rng, 20_000, 0.002), plane(rng, 20_000, 0.002, z=0.004)
    core = np.c_[rng.uniform(0.5, 3.5, (50, 2)), np.zeros(50)]
    d = sdp.distances(a, b, core_points=core, registration_error=0)  # M3C2's level: the whole plane moved
    assert d.core_points.shape == (50, 3) and d.distance.shape == (50,)
    assert abs(np.median(d.distance) - 0.004) < 0.001
    wide = sdp.distances(a, b, core_points=core, registration_error=0.01)
    assert np.allclose(wide.lod - d.lod, 1.96 * 0.01) and not wide.significant.any()
    cur = sdp.distances(a, b, core_points="current")
    assert len(cur.distance) == len(b)
    # a core point holding NaN keeps its row, without a distance: the others stay where they were given
    holed = core.copy()
    holed[[3, 17]] = [np.nan, 1.0, 0.0], [np.inf, 2.0, 0.0]
    h = sdp.distances(a, b, core_points=holed, registration_error=0)
    assert h.distance.shape == (50,) and np.isnan(h.distance[[3, 17]]).all() and (h.level[[3, 17]] == -1).all()
    kept = np.ones(50, bool)
    kept[[3, 17]] = False
    np.testing.assert_allclose(h.distance[kept], d.distance[kept], atol=1e-9)
    assert not h.significant[[3, 17]].any() and h.normal.shape == (50, 3)
    assert (h.summary()["core_points"], h.summary()["core_points_dropped"], h.summary()["not_comparable"]) == \
        (48, 2, d.summary()["not_comparable"] - int((~np.isfinite(d.distance[[3, 17]])).sum()))


def test_results_do_not_share_the_callers_arrays(rng):
    # editing a result's core points (a shift to a local datum) must leave the inputs as they were
    a, b = plane(rng, 2000, 0.002), plane(rng, 2000, 0.002, z=0.01)
    core = a[:40].copy()
    kw = dict(cylinder=sdp.Cylinder(projection_scale=0.4))
    for d, given in ((sdp.distances(a, b, **kw), a), (sdp.distances(a, b, core_points=core, **kw), core),
                     (sdp.distances(a, b, core_points="current", **kw), b)):
        assert not np.shares_memory(d.core_points, given) and np.array_equal(d.core_points, given)
    prep = sdp.distance.PreparedReference.prepare(a, core, **kw)
    first, second = prep.measure(b), prep.measure(b)
    assert not np.shares_memory(prep.core_points, core)
    assert not np.shares_memory(first.core_points, prep.core_points)
    assert not np.shares_memory(first.core_points, second.core_points)


def test_default_core_points_keep_the_references_nan_rows(rng):
    # the default core points (every reference row) keep a NaN row in place, as core_points=ref does
    a, b = plane(rng, 2000, 0.002), plane(rng, 2000, 0.002, z=0.01)
    a[::100] = np.nan
    kw = dict(cylinder=sdp.Cylinder(projection_scale=0.4), registration_error=0)
    default, given = sdp.distances(a, b, **kw), sdp.distances(a, b, core_points=a, **kw)
    assert default.distance.shape == (2000,) and np.isnan(default.distance[::100]).all()
    assert default.summary()["core_points_dropped"] == given.summary()["core_points_dropped"] == 20
    for name in sdp.distance._distances.DISTANCE_FIELDS:
        assert np.array_equal(default.fields()[name], given.fields()[name], equal_nan=True), name
    b[7] = np.nan
    assert sdp.distances(a, b, core_points="current", **kw).summary()["core_points_dropped"] == 1


def test_fields_and_summary(rng):
    d = sdp.distances(plane(rng, 5_000, 0.002), plane(rng, 5_000, 0.002, z=0.05), registration_error=0)
    f = d.fields()
    assert list(f) == list(sdp.distance._distances.DISTANCE_FIELDS)
    assert all(len(v) == 5_000 for v in f.values()) and f["significant"].dtype == np.uint8
    s = d.summary()
    assert s["significant_positive"] == s["significant"] > 4_900
    assert s["projection_scale"] == pytest.approx(d.projection_scale) and s["normal_scale"] >= 2 * s["projection_scale"]


def test_scales_are_the_density_kernel(rng):
    a, b = plane(rng, 20_000, 0.002), plane(rng, 20_000, 0.002)
    sigma = sdp.detect_changes(a, b).current_field.sigma  # the density kernel's σ, from the point spacing
    d = sdp.distances(a, b)
    assert d.projection_scale == pytest.approx(4 * sigma)
    assert sigma == pytest.approx(2 * sdp.auto_voxel_size(a, b, sigma_voxels=2))


@pytest.mark.parametrize("kwargs", [lambda: dict(cylinder=sdp.Cylinder(projection_scale=0)),
                                    lambda: dict(cylinder=sdp.Cylinder(projection_scale=float("nan"))),
                                    lambda: dict(cylinder=sdp.Cylinder(normal_scale=-1)),
                                    lambda: dict(cylinder=sdp.Cylinder(max_distance="far")),
                                    dict(registration_error=-0.1), dict(orientation=[0, 0, 0]),
                                    dict(core_points="both"), dict(core_points=np.zeros((0, 3))),
                                    dict(orientation=[1, 0, 0], sensor_origin=[0, 0, 5])])  # one would be ignored
def test_bad_options_are_refused(rng, kwargs):
    a = plane(rng, 1_000, 0.002)
    with pytest.raises(sdp.SDPError):
        sdp.distances(a, a, **(kwargs() if callable(kwargs) else kwargs))


def test_bad_clouds_and_memory_are_refused_before_work(rng):
    a = plane(rng, 1_000, 0.002)
    for bad in (np.zeros((0, 3)), np.zeros((1, 3)), np.full((10, 3), np.nan), np.zeros((5, 2))):
        with pytest.raises(sdp.SDPError):
            sdp.distances(bad, a)
    with pytest.raises(sdp.GridTooLargeError, match="would need"):
        sdp.distances(a, a, memory_limit=10_000)
    with pytest.raises(sdp.SDPError):
        sdp.distances(a, a, memory_limit="lots")
    with pytest.raises(sdp.InvalidPointsError, match="the core points reach 1e\\+09 units across"):
        sdp.distances(a, a, core_points=[[0, 0, 0], [1e9, 1e9, 1e9]])  # the core points at fault, not the clouds


def test_huge_offsets_keep_sub_millimetre_distances(rng):
    a = plane(rng, 20_000, 0.002) + [634_000.0, 4_831_000.0, 80.0]
    b = plane(rng, 20_000, 0.002, z=0.01) + [634_000.0, 4_831_000.0, 80.0]
    d = sdp.distances(a, b)
    assert abs(np.median(d.distance) - 0.01) < 0.0005


def run_sdp(*args):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "sdp.cli", *map(str, args)], capture_output=True, text=True)


@pytest.mark.slow
def test_sdp_distance_writes_every_field_in_each_format(rng, tmp_path):
    a, b = plane(rng, 8_000, 0.002), plane(rng, 8_000, 0.002, z=0.02)
    sdp.write_points(tmp_path / "a.ply", a)
    sdp.write_points(tmp_path / "b.ply", b)
    expected = sdp.distances(a, b)
    for ext in ("ply", "laz", "npz"):
        r = run_sdp("distance", tmp_path / "a.ply", tmp_path / "b.ply", "-o", tmp_path / f"d.{ext}", "--json")
        assert r.returncode == 0, r.stderr
        out = sdp.read_points(tmp_path / f"d.{ext}")
        assert set(sdp.distance._distances.DISTANCE_FIELDS) <= set(out.fields)
        tol = 2e-3 if ext == "laz" else 1e-6  # LAS coordinates on a 1 mm scale
        assert np.allclose(out.fields["distance"], expected.distance, atol=tol)
        assert (np.asarray(out.fields["significant"]) == expected.significant).all()
    import json

    s = json.loads(r.stdout)
    assert s["comparable"] == 8_000 and s["significant"] == int(expected.significant.sum())


@pytest.mark.slow  # the quick tier keeps lighter tests of the same module
def test_distance_files_core_points_png_and_refusals(rng, tmp_path, capsys):
    from sdp.cli._main import main

    a, b = plane(rng, 8_000, 0.002), plane(rng, 8_000, 0.002, z=0.02)
    sdp.write_points(tmp_path / "a.ply", a)
    sdp.write_points(tmp_path / "b.ply", b)
    core = np.c_[rng.uniform(1, 3, (30, 2)), np.zeros(30)]
    sdp.write_points(tmp_path / "core.npz", core)
    r = sdp.distance_files(tmp_path / "a.ply", tmp_path / "b.ply", output=tmp_path / "d.npz",
                           core_points=tmp_path / "core.npz", outputs=sdp.Outputs(png=tmp_path / "d.png"),
                           registration_error=0)  # M3C2's level: the whole plane moved
    assert len(r.result.distance) == 30 and r.result.significant.any()
    # the significant distances are drawn: the histogram's bars of them in orange (as sdp.viz draws them)
    assert drawn_pixels(picture(tmp_path / "d.png"), "#E69F00") > 0
    assert "significant" in r.summary_text() and r.summary["registration_error"] == 0.0
    for bad in (dict(output=tmp_path / "a.ply"), dict(output=tmp_path / "x.ply", registration_error=-1),
                dict(output=tmp_path / "x.ply", registration_error="big"),
                dict(output=tmp_path / "x.ply", orientation="up"), dict(output=tmp_path / "x.txt")):
        with pytest.raises(sdp.SDPError):
            sdp.distance_files(tmp_path / "a.ply", tmp_path / "b.ply", **bad)
    assert not (tmp_path / "x.ply").exists() and not (tmp_path / "x.txt").exists()
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_:  # the command's parser refuses it (in this process)
        main(["distance", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "-o", str(tmp_path / "y.ply"),
              "--registration-error", "-1"])
    assert exit_.value.code == 2 and len(capsys.readouterr().err.strip().splitlines()) == 1
    assert not (tmp_path / "y.ply").exists()
    # core points far off both clouds: every distance NaN, and a notice says why it may be
    sdp.write_points(tmp_path / "far.npz", core + [0, 0, 50])
    assert main(["distance", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "-o", str(tmp_path / "f.ply"),
                 "--core-points", str(tmp_path / "far.npz")]) == 0
    assert "no core point has a distance" in capsys.readouterr().err
    sdp.write_points(tmp_path / "holed.ply", np.r_[core, [[np.nan, 1.0, 0.0]]])  # a row without a position
    r = sdp.distance_files(tmp_path / "a.ply", tmp_path / "b.ply", output=tmp_path / "h.npz",
                           core_points=tmp_path / "holed.ply")
    assert r.summary["core_points"] == 30 and r.summary["core_points_dropped"] == 1
    assert "(and 1 row holding NaN or Inf, left out)" in r.summary_text()
    # the rows left out go with their fields: the others keep theirs (an E57's invalid returns)
    sdp.write_points(tmp_path / "holed_i.ply", np.r_[core, [[np.nan, 1.0, 0.0]]], {"intensity": np.arange(31.0)})
    r = sdp.distance_files(tmp_path / "a.ply", tmp_path / "b.ply", output=tmp_path / "hi.ply",
                           core_points=tmp_path / "holed_i.ply")
    assert np.array_equal(sdp.read_points(tmp_path / "hi.ply").fields["intensity"], np.arange(30.0))
    # core points carrying normals of their own: kept as given, not used, and said so
    sdp.write_points(tmp_path / "normals.ply", core, {"nx": np.ones(30), "ny": np.zeros(30), "nz": np.zeros(30)})
    r = sdp.distance_files(tmp_path / "a.ply", tmp_path / "b.ply", output=tmp_path / "n.ply",
                           core_points=tmp_path / "normals.ply")
    assert r.summary["input_normals"] == ["nx", "ny", "nz"] and "(nx, ny, nz) were not used" in r.summary_text()
    assert np.abs(r.result.normal[:, 2]).min() > 0.99  # measured on the planes, not the file's (1, 0, 0)
    # a search shorter than the cylinder, and scales below the spacing, each said in its own words
    capsys.readouterr()
    assert main(["distance", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "-o", str(tmp_path / "s.ply"),
                 "--core-points", str(tmp_path / "core.npz"), "--max-distance", "0.001"]) == 0
    assert "--max-distance 0.001 is shorter than the cylinder itself" in capsys.readouterr().err
    sdp.write_points(tmp_path / "own.npz", a[::100])  # the reference's own points: on the cloud
    assert main(["distance", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "-o", str(tmp_path / "t.ply"),
                 "--core-points", str(tmp_path / "own.npz"), "--normal-scale", "0.002"]) == 0
    out = capsys.readouterr()
    assert "no core point has a normal" in out.err and "no normal (80)" in out.out


def test_hash_cells_equal_dense_cells(rng, monkeypatch):
    a, b = plane(rng, 2_000, 0.002, size=2.0), plane(rng, 2_000, 0.002, z=0.3, size=2.0)
    dense = sdp.distances(a, b, cylinder=sdp.Cylinder(projection_scale=0.05))
    assert (dense.level == 1).sum() > 50  # the far search along the normals too
    from sdp.distance import _cells

    monkeypatch.setattr(_cells, "DENSE_CELLS", 0)  # boxes beyond the dense limit: hashed cells
    hashed = sdp.distances(a, b, cylinder=sdp.Cylinder(projection_scale=0.05))
    for name in sdp.distance._distances.DISTANCE_FIELDS:
        assert np.array_equal(dense.fields()[name], hashed.fields()[name], equal_nan=True), name


@pytest.mark.slow  # a second or two; the quick tier keeps a lighter test of the same module
def test_tiles_give_the_same_distances(rng):
    n = 60_000
    a = np.c_[rng.uniform(0, [12, 3], (n, 2)), 0.003 * rng.standard_normal(n)]
    xy = rng.uniform(0, [12, 3], (n, 2))
    b = np.c_[xy, 0.02 * (xy[:, 0] > 6) + 0.003 * rng.standard_normal(n)]
    a[5] = np.nan  # a row the reader would drop: no distance, in its place
    kw = dict(cylinder=sdp.Cylinder(projection_scale=0.08, normal_scale=0.16, max_distance=0.2))
    whole = sdp.distances(a, b, sensor_origin=None, **kw)
    tiled = sdp.distances_tiled(a, b, **kw, execution=sdp.Execution(tile_size=1.0, scheduler="synchronous"))
    assert tiled.tiles > 4 and len(tiled.distance) == len(whole.distance) == n and np.isnan(tiled.distance[5])
    for name in sdp.distance._distances.DISTANCE_FIELDS:
        assert np.array_equal(whole.fields()[name], tiled.fields()[name], equal_nan=True), name
    auto = sdp.distances_tiled(a, b, execution=sdp.Execution(scheduler="synchronous"))  # scales from the first slices
    assert abs(np.nanmedian(auto.distance[a[:, 0] > 7]) - 0.02) < 0.002


def test_tiles_say_the_orientation_as_memory_does_and_refuse_a_bad_one_before_any_tile(rng):
    n = 4000
    a = np.c_[rng.uniform(0, [2, 2], (n, 2)), 0.003 * rng.standard_normal(n)]
    b = a + [0, 0, 0.01]
    kw = dict(cylinder=sdp.Cylinder(projection_scale=0.1, normal_scale=0.2, max_distance=0.2))
    execution = sdp.Execution(scheduler="synchronous")
    for given in (None, (0, 0, 2)):
        whole = sdp.distances(a, b, sensor_origin=None, orientation=given, **kw)
        tiled = sdp.distances_tiled(a, b, orientation=given, execution=execution, **kw)
        assert tiled.orientation == whole.orientation == "towards (0, 0, 1)"  # DEFAULTS.orientation, unit
    assert sdp.DEFAULTS.orientation == (0.0, 0.0, 1.0)
    with pytest.raises(sdp.InvalidOptionError, match="orientation must be three finite numbers"):
        sdp.distances_tiled(a, b, orientation=(0, 0, 0), execution=execution, **kw)


@pytest.mark.slow
def test_tiles_measure_the_automatic_scales_as_memory_does(rng):
    # a surface half rough: the roughness rule's median sits between the halves, where a sample's
    # cells (the tiles took their scales from one) moved the normal scale (15 % on the Toronto pair)
    n = 60_000  # the sample was every third point
    a = np.c_[rng.uniform(0, [12, 3], (n, 2)), 0.003 * rng.standard_normal(n)]
    a[a[:, 0] < 6, 2] += 0.03 * rng.standard_normal(int((a[:, 0] < 6).sum()))
    b = a + [0, 0, 0.01]
    memory = sdp.distances(a, b, sensor_origin=None)
    tiled = sdp.distances_tiled(a, b, execution=sdp.Execution(scheduler="synchronous"))  # one slice: the cloud
    assert (tiled.projection_scale, tiled.normal_scale) == (memory.projection_scale, memory.normal_scale)
    assert np.array_equal(memory.distance, tiled.distance, equal_nan=True)


@pytest.mark.slow
def test_sdp_distance_in_tiles_streams_the_reference_with_its_distances(rng, tmp_path):
    n = 30_000
    a = np.c_[rng.uniform(0, [8, 3], (n, 2)), 0.003 * rng.standard_normal(n)]
    b = np.c_[rng.uniform(0, [8, 3], (n, 2)), 0.02 + 0.003 * rng.standard_normal(n)]
    sdp.write_points(tmp_path / "a.laz", a)
    sdp.write_points(tmp_path / "b.laz", b)
    common = ["--projection-scale", "0.08", "--normal-scale", "0.16", "--max-distance", "0.2", "--json"]
    r = run_sdp("distance", tmp_path / "a.laz", tmp_path / "b.laz", "-o", tmp_path / "t.laz", "--tiled",
                "--tile-size", "1", "--scheduler", "synchronous", *common)
    assert r.returncode == 0, r.stderr
    whole_run = run_sdp("distance", tmp_path / "a.laz", tmp_path / "b.laz", "-o", tmp_path / "m.laz", *common)
    assert whole_run.returncode == 0, whole_run.stderr
    tiled, whole = sdp.read_points(tmp_path / "t.laz"), sdp.read_points(tmp_path / "m.laz")
    assert np.array_equal(tiled.xyz, whole.xyz)
    for name in sdp.distance._distances.DISTANCE_FIELDS:
        assert np.array_equal(tiled.fields[name], whole.fields[name], equal_nan=True), name
    refused = run_sdp("distance", tmp_path / "a.laz", tmp_path / "b.laz", "-o", tmp_path / "t.ply", "--tiled")
    assert refused.returncode == 2 and "LAS/LAZ" in refused.stderr
    # tiles follow no sensor: a sensor given is refused, not ignored (its normals' sign would be lost)
    for extra in (["--sensor-origin", "4,1,-5"], ["--report", tmp_path / "r.html"]):
        refused = run_sdp("distance", tmp_path / "a.laz", tmp_path / "b.laz", "-o", tmp_path / "s.laz", "--tiled",
                          *extra)
        assert refused.returncode == 2 and f"{extra[0]} is not available with --tiled" in refused.stderr
    assert not (tmp_path / "s.laz").exists()


def test_noiseless_scans_of_one_surface_are_not_significant_for_rounding():
    # one plane sampled twice without noise (two grids) at UTM offsets: the level is about 0 and the
    # distances are rounding: none of them a change
    from scipy.spatial.transform import Rotation

    def plane(shift):  # the same tilted plane, sampled on a grid moved by ``shift``
        x, y = np.meshgrid(np.arange(shift, 6.0, 0.05), np.arange(shift, 6.0, 0.05))
        return np.c_[x.ravel(), y.ravel(), 0.1 * x.ravel() + 0.05 * y.ravel()]

    turn = Rotation.from_euler("xyz", [20, -10, 30], degrees=True).as_matrix()
    offset = np.array([500_000.0, 5_000_000.0, 100.0])
    ref = plane(0.0) @ turn.T + offset  # both scans through a pose's turn, as an E57 reader moves them
    cur = plane(0.025) @ turn.T + offset
    d = sdp.distances(ref, cur, registration_error=0.0)
    ok = np.isfinite(d.distance)
    assert ok.mean() > 0.9 and np.abs(d.distance[ok]).max() < 1e-6
    assert not d.significant.any()
