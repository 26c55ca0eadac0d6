"""A place the other epoch's sensor could not see gets no distance (:mod:`sdp.distance._seen`)."""

from pathlib import Path

import numpy as np

import sdp


def shadowed_floor(rng, n=60_000):
    """A floor seen from 3 m above its middle; in the second epoch a plate 0.3 m above the floor
    hides part of it from the same sensor (the floor points under it are not returned)."""
    origin = np.array([2.0, 2.0, 3.0])
    floor = np.c_[rng.uniform(0, 4, (n, 2)), 0.001 * rng.standard_normal(n)]
    plate = np.c_[rng.uniform(1.6, 2.4, (n // 25, 2)), 0.3 + 0.001 * rng.standard_normal(n // 25)]
    # where the ray from the sensor to a floor point crosses the plate's height
    t = (3.0 - 0.3) / 3.0
    cross = origin[:2] + t * (floor[:, :2] - origin[:2])
    shadow = np.all((cross > 1.6) & (cross < 2.4), axis=1)
    second = np.r_[floor[~shadow], plate]
    return sdp.Cloud(floor, sensors=origin[None]), sdp.Cloud(second, sensors=origin[None]), shadow


def test_a_plate_put_before_the_floor_is_measured_where_it_stands(tmp_path):
    """The floor's sensor saw the space above the floor free, so the plate put there is new and
    hides the floor itself: measured where it stands (M3C2's +0.3 m), and where it left the
    other way (−0.3 m: the first epoch's sensor saw through its place)."""
    rng = np.random.default_rng(3)
    first, second, shadow = shadowed_floor(rng)
    blind = sdp.distances(first, second, sensor_origin=None)  # M3C2: the plate found along the normal
    assert np.nanmedian(blind.distance[shadow]) > 0.25 and blind.level[shadow].max() == 1
    d = sdp.distances(first, second)  # the sensor known
    inner = shadow & np.all(np.abs(first.xyz[:, :2] - 2.0) < 0.3, axis=1)
    assert inner.sum() > 500 and d.comparable[inner].all() and d.significant[inner].all()
    assert np.allclose(d.distance[inner], 0.3, atol=0.01) and np.array_equal(d.distance[inner], blind.distance[inner])
    assert d.comparable[~shadow].mean() > 0.99 and d.significant[~shadow].mean() < 0.07
    back = sdp.distances(second, first)  # the plate's core points: the floor found behind, their place seen free
    plate = second.xyz[:, 2] > 0.2
    assert back.comparable[plate].mean() > 0.95 and np.allclose(np.nanmedian(back.distance[plate]), -0.3, atol=0.01)
    from sdp.cli._main import main

    sdp.write_points(tmp_path / "a.ply", first.xyz)
    sdp.write_points(tmp_path / "b.ply", second.xyz)
    assert main(["distance", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "-o", str(tmp_path / "d.npz"),
                 "--sensor-origin", "2,2,3"]) == 0
    assert np.array_equal(np.load(tmp_path / "d.npz")["distance"], d.distance, equal_nan=True)


def test_a_ledge_both_epochs_hold_is_no_measurement_of_the_floor_it_hides_from_one():
    """A ledge 0.3 m over the floor in both epochs: the first sensor, low at the side, saw the
    floor under it; the second, above, could not. The ledge found in front of that floor is no
    new surface (the reference held it there): the floor gets no distance, where M3C2 reads +0.3."""
    rng = np.random.default_rng(12)
    low, high = np.array([-1.0, 2.0, 0.6]), np.array([2.0, 2.0, 3.0])
    floor = np.c_[rng.uniform(0, 4, (80_000, 2)), np.zeros(80_000)]
    ledge = np.c_[rng.uniform(1.6, 2.4, (6_000, 2)), np.full(6_000, 0.3)]

    def lit(sensor):  # the floor points whose ray from the sensor misses the ledge
        t = (0.3 - sensor[2]) / (floor[:, 2] - sensor[2])
        cross = sensor[:2] + t[:, None] * (floor[:, :2] - sensor[:2])
        return floor[~(((t > 0) & (t < 1))[:, None] & (cross > 1.6) & (cross < 2.4)).all(axis=1)]

    def noisy(p):
        return p + 0.001 * rng.standard_normal(p.shape)

    first = sdp.Cloud(noisy(np.r_[lit(low), ledge]), sensors=low[None])
    second = sdp.Cloud(noisy(np.r_[lit(high), ledge]), sensors=high[None])
    under = (np.abs(first.xyz[:, :2] - 2.0) < 0.3).all(axis=1) & (first.xyz[:, 2] < 0.1)
    assert under.sum() > 100
    blind = sdp.distances(first, second, sensor_origin=None)
    assert np.nanmedian(blind.distance[under]) > 0.25  # M3C2: the ledge
    d = sdp.distances(first, second)
    assert not d.comparable[under].any() and d.not_seen >= under.sum()


def test_a_series_epoch_measures_the_plate_and_not_a_face_seen_from_behind(tmp_path):
    rng = np.random.default_rng(4)
    first, second, shadow = shadowed_floor(rng, n=30_000)
    ds = sdp.series([first, second], output=tmp_path / "s.zarr")
    core = np.c_[ds["x"].values, ds["y"].values, ds["z"].values]
    u = ds.attrs["parameters"]["used"]
    cyl = sdp.Cylinder(projection_scale=u["projection_scale"], normal_scale=u["normal_scale"],
                       max_distance=u["max_distance"])
    pair = sdp.distances(first, second, core_points=core, cylinder=cyl)
    under = np.all(np.abs(core[:, :2] - 2.0) < 0.3, axis=1)
    assert under.sum() > 10 and np.allclose(ds["distance"].values[1, under], 0.3, atol=0.01)
    assert np.allclose(ds["distance"].values[1], pair.distance, atol=1e-6, equal_nan=True)
    a, b = box_scans(rng)  # the box's west face seen by A only; B saw its east face, from behind the west one's normal
    ds = sdp.series([a, b], output=tmp_path / "box.zarr")
    core = np.c_[ds["x"].values, ds["y"].values, ds["z"].values]
    west = (np.abs(core[:, 0]) < 0.01) & (np.abs(core[:, 1]) < 0.6) & (core[:, 2] > 0.2) & (core[:, 2] < 0.8)
    assert west.sum() > 5 and np.isnan(ds["distance"].values[1, west]).all()
    u = ds.attrs["parameters"]["used"]
    pair = sdp.distances(a, b, core_points=core, cylinder=sdp.Cylinder(
        projection_scale=u["projection_scale"], normal_scale=u["normal_scale"], max_distance=u["max_distance"]))
    assert np.array_equal(np.isnan(ds["distance"].values[1]), np.isnan(pair.distance))


def box_scans(rng, *, lift=0.0, n=40_000):
    """A floor and a box 2 × 2 × 1 m, scanned from x = −3 m (A: the box's west face and top) and
    from x = +5 m (B: its east face and top, the top ``lift`` higher), each floor without the
    box's shadow from its sensor: nothing else moved."""
    a, b = np.array([-3.0, 0.0, 1.5]), np.array([5.0, 0.0, 1.5])
    floor = np.c_[rng.uniform(-4, 6, n), rng.uniform(-1.6, 1.6, n), np.zeros(n)]

    def lit(p, sensor):
        """The floor points whose ray from ``sensor`` misses the box (a slab test)."""
        d = p - sensor
        with np.errstate(divide="ignore", invalid="ignore"):
            t0, t1 = (np.array([0, -1, 0]) - sensor) / d, (np.array([2, 1, 1]) - sensor) / d
        near, far = np.nanmax(np.minimum(t0, t1), axis=1), np.nanmin(np.maximum(t0, t1), axis=1)
        return p[~((near <= far) & (near < 1) & (far > 0))]

    def face(x):
        return np.c_[np.full(n // 8, x), rng.uniform(-1, 1, n // 8), rng.uniform(0, 1, n // 8)]

    def top(z):
        return np.c_[rng.uniform(0, 2, n // 4), rng.uniform(-1, 1, n // 4), np.full(n // 4, z)]

    def noisy(p):
        return p + 0.002 * rng.standard_normal(p.shape)

    first = sdp.Cloud(noisy(np.r_[lit(floor, a), face(0.0), top(1.0)]), sensors=a[None])
    second = sdp.Cloud(noisy(np.r_[lit(floor, b), face(2.0), top(1.0 + lift)]), sensors=b[None])
    return first, second


def test_a_face_the_other_sensor_saw_from_behind_gets_no_distance():
    """The place measured must be one the other epoch's sensor saw: the west face's cylinders near
    the top edge hold the top's points in B at their rim (M3C2 measures them, centimetres off),
    but B saw that place only through the box; those points lie off the cylinders' axis, so that
    place gets no distance already without the sensors (``off_axis``). A surface that moved
    towards the sensor, hiding the old place, is still measured: the place measured is on it."""
    rng = np.random.default_rng(8)
    first, second = box_scans(rng, lift=0.05)
    cyl = sdp.Cylinder(projection_scale=0.8, normal_scale=0.8)
    west = np.c_[np.zeros(200), rng.uniform(-0.5, 0.5, 200), rng.uniform(0.5, 0.8, 200)]
    onto = np.c_[rng.uniform(0.7, 1.3, 200), rng.uniform(-0.3, 0.3, 200), np.ones(200)]  # clear of its edges
    core = np.r_[west, onto]
    blind = sdp.distances(first, second, core_points=core, cylinder=cyl, sensor_origin=None, orientation=[-1, 0, 0])
    edge = np.zeros(len(core), bool)
    edge[:200] = 1.0 - west[:, 2] < 0.4
    assert edge.sum() > 50 and not blind.comparable[edge].any() and blind.off_axis[edge].all()
    d = sdp.distances(first, second, core_points=core, cylinder=cyl, registration_error=0.005)
    assert not d.comparable[:200].any() and d.not_seen + int(d.off_axis[:200].sum()) >= 200
    assert np.allclose(d.distance[200:], 0.05, atol=0.005) and d.significant[200:].all()


def test_points_beyond_the_cylinders_rim_alone_give_no_distance():
    """A few points between M3C2's rim (d/2 = 2σ_p) and the kernel's cut (3σ_p) weigh less than two
    points on the rim: they tell where the surface lies off the axis, so no distance there."""
    rng = np.random.default_rng(9)
    plane = np.c_[rng.uniform(-1, 1, (20_000, 2)), 0.001 * rng.standard_normal(20_000)]
    far = np.c_[2.5 * 0.05 * np.cos([0.0, 2.1, 4.2]), 2.5 * 0.05 * np.sin([0.0, 2.1, 4.2]), np.zeros(3)]
    near = far * 0.6  # inside the rim: the same three points measure
    cyl = sdp.Cylinder(projection_scale=0.2, normal_scale=0.4, max_distance=0.1)
    core = np.zeros((1, 3))
    assert not sdp.distances(plane, far, core_points=core, cylinder=cyl, sensor_origin=None).comparable[0]
    assert sdp.distances(plane, near, core_points=core, cylinder=cyl, sensor_origin=None).comparable[0]


def test_a_walls_far_face_is_no_measurement_of_its_near_one():
    """A 5 cm wall scanned from either side: within the cylinder, the far face the current's
    scanner saw from behind the near face's normal is no measurement of the near face (M3C2:
    5 cm off, every core point significant)."""
    rng = np.random.default_rng(11)
    yz = rng.uniform(-1, 1, (20_000, 2))
    near = np.c_[0.001 * rng.standard_normal(20_000), yz]
    far = np.c_[0.05 + 0.001 * rng.standard_normal(20_000), yz]
    cyl = sdp.Cylinder(projection_scale=0.2, max_distance=0.3)
    blind = sdp.distances(near, far, cylinder=cyl, sensor_origin=None, orientation=[-1, 0, 0], registration_error=0)
    assert (blind.level == 0).mean() > 0.9 and abs(np.median(blind.distance) + 0.05) < 0.005
    assert blind.significant.mean() > 0.9
    d = sdp.distances(near, far, cylinder=cyl, sensor_origin=[[-1.0, 0, 0], [1.2, 0, 0]], registration_error=0)
    assert not d.comparable.any() and d.not_seen == len(near)


def test_a_laser_scans_band_is_its_kernel_not_a_depth_cameras():
    from sdp.change._visibility import sensor_range_noise
    from sdp.defaults import DEFAULTS

    xyz = np.zeros((3, 3))
    laser = sdp.io.Cloud(xyz, path=Path("survey.e57"), range_noise=0.0)  # as read_points reads an E57 file
    assert sensor_range_noise(laser, DEFAULTS.range_noise) == 0.0
    assert sensor_range_noise(laser, 0.004) == 0.004  # given: kept
    assert sensor_range_noise(laser.transformed(np.eye(4)), DEFAULTS.range_noise) == 0.0
    assert sensor_range_noise(sdp.io.Cloud(xyz, path=Path("frame.pcd")), DEFAULTS.range_noise) == DEFAULTS.range_noise
    assert sensor_range_noise(xyz, DEFAULTS.range_noise) == DEFAULTS.range_noise


def test_a_las_files_sensor_is_a_laser_where_its_position_is_given(tmp_path, rng):
    # LAS is LiDAR's format: with the scanner's position given, the rays' band is the kernel's, not
    # a depth camera's 0.015·r² (6 m at 20 m, which took a crate 0.6 m before the wall for the wall)
    def wall(crate: bool):
        yz = rng.uniform([-4, 0], [4, 3], (40_000, 2))
        pts = [np.c_[yz[:, 0], np.full(len(yz), 20.0), yz[:, 1]]]
        if crate:  # the face of a crate 0.6 m before the wall, the part of the wall it hides gone
            face = rng.uniform([-0.5, 0], [0.5, 1.0], (3_000, 2))
            hid = (np.abs(pts[0][:, 0] * 19.4 / 20.0) < 0.5) & (pts[0][:, 2] * 19.4 / 20.0 < 1.0)
            pts = [pts[0][~hid], np.c_[face[:, 0], np.full(len(face), 19.4), face[:, 1]]]
        return np.concatenate(pts) + rng.normal(0, 0.003, (sum(map(len, pts)), 3))

    for name, crate in (("a.las", False), ("b.las", True)):
        sdp.write_points(tmp_path / name, wall(crate))
    a, b = sdp.read_points(tmp_path / "a.las"), sdp.read_points(tmp_path / "b.las")
    assert a.range_noise == 0.0  # a laser's: millimetres at any range
    r = sdp.detect_changes(a, b, coverage=sdp.Coverage(sensor_origin=[0.0, 0.0, 1.5]))
    face = np.abs(b.xyz[:, 1] - 19.4) < 0.05
    assert r.appeared[face].mean() > 0.9 and r.appeared[~face].mean() < 0.01


def test_a_hole_in_an_unorganized_scan_pattern_is_not_a_place_seen():
    # the change masks' rule for scans that did not send every ray (sdp.change._visibility.rays_sent)
    from sdp.distance._seen import not_seen

    rng = np.random.default_rng(4)
    u, v = rng.uniform(-0.5, 0.5, (2, 60_000))
    keep = ~((np.abs(u) < 0.15) & (np.abs(v) < 0.15))  # a square of directions never sampled
    wall = np.c_[np.full(keep.sum(), 3.0), 3.0 * u[keep], 3.0 * v[keep]]
    place = np.array([[3.0, 0.0, 0.0]])  # on the wall, in the hole's middle
    assert not not_seen(place, wall, np.zeros(3), None, sigma=0.01, range_noise=0.0, rays=True)[0]
    assert not_seen(place, wall, np.zeros(3), None, sigma=0.01, range_noise=0.0, rays=False)[0]


def test_a_mound_seen_at_grazing_incidence_is_measured_where_it_stands():
    """A scanner 1.6 m up sees the ground 13–16 m away at about 6°, and a mound 0.5 m high put
    there. The mound is the second scan's own returns, found in front of the ground where the first
    held nothing: measured there (+0.5 m) wherever M3C2 measures it. At such angles the normals tilt
    towards the rays, and asking whether the mound's place faces the sensor lost two thirds of it."""
    rng = np.random.default_rng(13)
    sensor = np.array([-2.0, 0.0, 1.6])
    az, el = np.meshgrid(np.radians(np.arange(-20, 20, 0.12)), np.radians(np.arange(-12, -3, 0.12)))
    rays = np.c_[(np.cos(el) * np.cos(az)).ravel(), (np.cos(el) * np.sin(az)).ravel(), np.sin(el).ravel()]

    def scan(mound: bool):
        t = -sensor[2] / rays[:, 2]  # the ground z = 0
        if mound:
            lo, hi = np.array([13.0, -1.5, 0.0]), np.array([16.0, 1.5, 0.5])
            with np.errstate(divide="ignore", invalid="ignore"):
                t0, t1 = (lo - sensor) / rays, (hi - sensor) / rays
            near, far = np.nanmax(np.minimum(t0, t1), axis=1), np.nanmin(np.maximum(t0, t1), axis=1)
            t = np.where((near <= far) & (near > 0) & (near < t), near, t)
        pts = sensor + t[:, None] * rays + 0.002 * rng.standard_normal(len(t))[:, None] * rays
        return sdp.Cloud(pts, sensors=sensor[None])

    first, second = scan(False), scan(True)
    core = first.xyz[(np.abs(first.xyz[:, 0] - 14.5) < 1.0) & (np.abs(first.xyz[:, 1]) < 1.0)]
    cyl = sdp.Cylinder(projection_scale=0.15, normal_scale=0.3)
    blind = sdp.distances(first.xyz, second.xyz, core_points=core, cylinder=cyl, sensor_origin=None,
                          orientation=[0, 0, 1])  # M3C2: the mound found along the normal
    assert blind.comparable.mean() > 0.25 and np.allclose(np.nanmedian(blind.distance), 0.5, atol=0.01)
    d = sdp.distances(first, second, core_points=core, cylinder=cyl)
    assert d.comparable.mean() >= blind.comparable.mean() - 0.02 and d.not_seen == 0
    assert np.allclose(np.nanmedian(np.abs(d.distance)), 0.5, atol=0.01)


def test_an_appended_epoch_measures_the_plate_as_the_first_run_and_an_old_archive_keeps_the_old_rule(tmp_path):
    import json
    import shutil

    rng = np.random.default_rng(5)
    first, second, _ = shadowed_floor(rng, n=20_000)
    whole = sdp.series([first, second, second], output=tmp_path / "whole.zarr")
    sdp.series([first, second], output=tmp_path / "grown.zarr")
    grown = sdp.series([second], output=tmp_path / "grown.zarr", append=True)
    core = np.c_[whole["x"].values, whole["y"].values, whole["z"].values]
    under = np.all(np.abs(core[:, :2] - 2.0) < 0.3, axis=1)
    assert np.allclose(grown["distance"].values[2, under], 0.3, atol=0.01)
    assert np.allclose(grown["distance"].values[2], whole["distance"].values[2], atol=1e-6, equal_nan=True)
    out = tmp_path / "old.zarr"  # written before ref_front was kept: the floor under the plate not seen
    sdp.series([first, second], output=out)
    meta = json.loads((out / "zarr.json").read_text())
    shutil.rmtree(out / "ref_front")
    del meta["consolidated_metadata"]["metadata"]["ref_front"]
    (out / "zarr.json").write_text(json.dumps(meta))
    old = sdp.series([second], output=out, append=True)
    assert np.isnan(old["distance"].values[2, under]).all()
    assert np.isfinite(old["distance"].values[2, ~under]).mean() > 0.9
