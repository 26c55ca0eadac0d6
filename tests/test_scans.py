"""Scans as sensors record them (issue 35): E57 files with every scan's pose, several scanners
in one epoch (coverage against each of them, normals towards each point's own)."""

import json
import subprocess
import sys

import numpy as np
import pytest

import sdp
from sdp.io import CloudFileError

pye57 = pytest.importorskip("pye57")

PUMP = "e57/pumpAVisualReferenceImage.e57"


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "sdp.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=300)


def cast(origin, boxes, *, step_deg=0.6, el_range=(-85, 60)):
    """A terrestrial scanner at ``origin``: the nearest hit of a grid of rays (full turn in
    azimuth, ``el_range`` in elevation, ``step_deg`` apart) on axis-aligned boxes (lo, hi).
    Returns (points, NaN where a ray hits nothing; row; column)."""
    az = np.deg2rad(np.arange(-180, 180, step_deg))
    el = np.deg2rad(np.arange(el_range[0], el_range[1], step_deg))
    a, e = np.meshgrid(az, el, indexing="ij")
    d = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], -1).reshape(-1, 3)
    best = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        for lo, hi in boxes:
            t1, t2 = (np.asarray(lo) - origin) * inv, (np.asarray(hi) - origin) * inv
            near, far = np.nanmax(np.minimum(t1, t2), axis=1), np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (near <= far) & (near > 0) & (near < best)
            best[hit] = near[hit]
    pts = np.full((len(d), 3), np.nan)
    ok = np.isfinite(best)
    pts[ok] = origin + d[ok] * best[ok, None]
    rows, cols = np.meshgrid(np.arange(len(az)), np.arange(len(el)), indexing="ij")
    return pts, rows.ravel(), cols.ravel()


def write_e57(path, scans):
    """An E57 file of ``scans`` [(world points with NaN rows, row, column, origin, yaw)]: each
    scan stored in its scanner's frame (turned by ``yaw`` about z) with its pose, the rays that
    hit nothing flagged invalid."""
    e = pye57.E57(str(path), mode="w")
    for pts, row, col, origin, yaw in scans:
        c, s = np.cos(yaw), np.sin(yaw)
        turn = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        local = (pts - origin) @ turn  # turnᵀ (p − origin)
        bad = ~np.isfinite(local).all(axis=1)
        local[bad] = 0
        e.write_scan_raw({"cartesianX": local[:, 0], "cartesianY": local[:, 1], "cartesianZ": local[:, 2],
                          "cartesianInvalidState": bad.astype(np.int8), "rowIndex": row.astype(np.int32),
                          "columnIndex": col.astype(np.int32), "intensity": np.full(len(pts), 0.5)},
                         rotation=np.array([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]), translation=np.asarray(origin))
    e.close()
    return path


# A floor, a wall, a tower (2 m wide, 3 m tall) and a box. The reference's two scanners stand
# low on either side of the tower; in the current epoch they stand higher (they see the tower's
# top), the box has moved, a box stands behind the tower (hidden from scanner A by the tower,
# seen by scanner B) and one on the tower's top (hidden from both reference scanners).
FLOOR, WALL, TOWER = ([-6, -6, -0.1], [6, 6, 0]), ([-6, 5, 0], [6, 5.2, 3]), ([-1, -1, 0], [1, 1, 3])
BOX_BEFORE, BOX_AFTER = ([-0.3, 2.5, 0], [0.3, 3.1, 0.6]), ([-0.3, -3.1, 0], [0.3, -2.5, 0.6])
BEHIND, ON_TOP = ([1.3, -0.3, 0], [1.9, 0.3, 0.6]), ([-0.3, -0.3, 3], [0.3, 0.3, 3.4])
A, B = np.array([-3.5, 0, 1.5]), np.array([3.5, 0.6, 1.5])
LIFT = np.array([0, 0, 3.5])


def inside(x, lo, hi, pad=0.01):
    return ((x >= np.asarray(lo) - pad) & (x <= np.asarray(hi) + pad)).all(axis=1)


@pytest.fixture(scope="module")
def two_epochs(tmp_path_factory):
    d = tmp_path_factory.mktemp("e57")
    before = [FLOOR, WALL, TOWER, BOX_BEFORE]
    after = [FLOOR, WALL, TOWER, BOX_AFTER, BEHIND, ON_TOP]
    ref = write_e57(d / "ref.e57", [(*cast(A, before), A, 0.0), (*cast(B, before), B, np.pi)])
    cur = write_e57(d / "cur.e57", [(*cast(A + LIFT, after), A + LIFT, 0.0),
                                    (*cast(B + LIFT, after), B + LIFT, np.pi)])
    return ref, cur


def test_multi_scan_e57_reads_every_scan_with_its_pose(two_epochs):
    ref = sdp.read_points(two_epochs[0])
    assert np.allclose(ref.sensors, [A, B]) and ref.sensor_origin is None
    assert np.allclose(ref.sensor_origins, [A, B])
    raw = [pye57.E57(str(two_epochs[0])).read_scan(i) for i in range(2)]  # pye57 applies the poses too
    assert np.bincount(ref.scan).tolist() == [len(r["cartesianX"]) for r in raw]
    for i, r in enumerate(raw):
        assert np.allclose(ref.xyz[ref.scan == i], np.c_[r["cartesianX"], r["cartesianY"], r["cartesianZ"]])
    # the invalid rays (into the sky) are dropped and counted; the grid is kept
    e = pye57.E57(str(two_epochs[0]))
    assert ref.n_dropped == e.get_header(0).point_count + e.get_header(1).point_count - len(ref)
    assert {"row", "column", "intensity", "scan"} <= set(ref.fields)
    assert ref.range_noise == 0.0  # a laser's: the rays' band is the kernel's (sensor_range_noise)
    # the scanner B's frame is turned by 180°: its points lie on its +x side
    assert np.median(ref.xyz[ref.scan == 1, 0]) < B[0] and np.all(ref.xyz[ref.scan == 0, 0] >= -6 - 1e-9)
    moved = ref.transformed(np.array([[1, 0, 0, 1.0], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]]))
    assert np.allclose(moved.sensors, ref.sensors + [1, 2, 3])


def test_a_series_of_multi_scan_epochs_measures_what_some_scanner_saw(two_epochs, tmp_path):
    """A series reads its epochs' x, y, z alone, but keeps which scanner saw each point: each epoch's
    distances equal the pair's with the epoch's scanners (tests/test_seen.py: what they did not see)."""
    lean = sdp.read_points(two_epochs[1], fields=False)
    assert np.array_equal(lean.scan, sdp.read_points(two_epochs[1]).scan) and lean.scan.max() == 1
    ds = sdp.series(list(two_epochs), output=tmp_path / "s.zarr")
    core = np.c_[ds["x"].values, ds["y"].values, ds["z"].values]
    u = ds.attrs["parameters"]["used"]
    pair = sdp.distances(sdp.read_points(two_epochs[0]), lean, core_points=core, cylinder=sdp.Cylinder(
        projection_scale=u["projection_scale"], normal_scale=u["normal_scale"], max_distance=u["max_distance"]))
    assert pair.orientation == u["orientation"] == "towards each point's scanner"  # as the pair's normals
    assert np.allclose(ds["distance"].values[1], pair.distance, atol=1e-5, equal_nan=True)


def test_every_scanner_of_the_other_epoch_is_asked(two_epochs):
    ref, cur = (sdp.read_points(p) for p in two_epochs)
    res = sdp.detect_changes(ref, cur, coverage=sdp.Coverage(range_noise=0.001))  # a laser scanner's noise
    assert res.coverage == {"appeared": "sensor rays", "disappeared": "sensor rays"}
    x, state = cur.xyz, res.current_state
    moved = state[inside(x, [-0.3, -3.1, 0.2], [0.3, -2.5, 0.6])]
    behind = state[inside(x, [1.3, -0.3, 0.2], [1.9, 0.3, 0.6])]
    on_top = state[inside(x, [-0.3, -0.3, 3.2], [0.3, 0.3, 3.4])]
    floor = state[x[:, 2] < 0.01]
    assert len(moved) > 200 and (moved == sdp.CHANGED).mean() > 0.95 and not (moved == sdp.NOT_COMPARABLE).any()
    # hidden from scanner A by the tower, seen through by scanner B: changed
    assert len(behind) > 200 and (behind == sdp.CHANGED).mean() > 0.95
    # in the shadow of both: not comparable, never changed
    assert len(on_top) > 200 and (on_top == sdp.NOT_COMPARABLE).mean() > 0.8 and not (on_top == sdp.CHANGED).any()
    assert (floor == sdp.UNCHANGED).all()
    gone = res.reference_state[inside(ref.xyz, [-0.3, 2.5, 0.2], [0.3, 3.1, 0.6])]
    assert len(gone) > 200 and (gone == sdp.CHANGED).mean() > 0.95 and not (gone == sdp.NOT_COMPARABLE).any()
    assert np.allclose(res.summary()["sensor_origin"]["reference"], [A, B])
    # with scanner A alone (its own points, its own position), the box behind the tower is not comparable
    alone = sdp.detect_changes(ref.xyz[ref.scan == 0], cur, coverage=sdp.Coverage(sensor_origin=[A, A + LIFT],
                                                                                     range_noise=0.001))
    behind_alone = alone.current_state[inside(x, [1.3, -0.3, 0.2], [1.9, 0.3, 0.6])]
    assert (behind_alone == sdp.CHANGED).mean() < 0.05


def test_a_stream_against_a_reference_of_two_scanners(two_epochs):
    ref, cur = (sdp.read_points(p) for p in two_epochs)
    frame = next(sdp.watch(ref, [cur], coverage=sdp.Coverage(range_noise=0.001)))
    x = cur.xyz
    behind = inside(x, [1.3, -0.3, 0.2], [1.9, 0.3, 0.6])  # hidden from scanner A, seen through by B
    on_top = inside(x, [-0.3, -0.3, 3.2], [0.3, 0.3, 3.4])  # hidden from both
    assert frame.appeared[behind].mean() > 0.95
    assert not frame.appeared[on_top].any() and frame.not_comparable[on_top].mean() > 0.8


def test_normals_face_each_points_own_scanner(two_epochs):
    ref, cur = (sdp.read_points(p) for p in two_epochs)
    d = sdp.distances(ref, cur)
    assert d.orientation == "towards each point's scanner"
    x, n = d.core_points, d.normal
    west = (np.abs(x[:, 0] + 1) < 0.005) & (x[:, 2] > 0.3) & (x[:, 2] < 2.7) & (np.abs(x[:, 1]) < 0.8)
    east = (np.abs(x[:, 0] - 1) < 0.005) & (x[:, 2] > 0.3) & (x[:, 2] < 2.7) & (np.abs(x[:, 1]) < 0.8)
    assert west.sum() > 1000 and east.sum() > 1000
    assert (ref.scan[west] == 0).all() and (ref.scan[east] == 1).all()  # each face seen by one scanner
    assert (n[west, 0] < -0.9).all() and (n[east, 0] > 0.9).all()
    # one sensor for all (scanner A's): the east face's normals turn away from the scanner that saw it
    one = sdp.distances(ref, cur, sensor_origin=A)
    assert (one.normal[east, 0] < -0.9).all()


def test_sdp_info_lists_the_scans_and_poses(two_epochs):
    p = run("info", two_epochs[0])
    assert p.returncode == 0, p.stderr
    info = json.loads(p.stdout)
    assert [s["translation"] for s in info["scans"]] == [A.tolist(), B.tolist()]
    assert np.allclose(info["scans"][1]["rotation"], [0, 0, 0, 1], atol=1e-12)
    assert info["scans"][0]["grid"] == [600, len(np.arange(-85, 60, 0.6))]
    assert sum(s["kept"] for s in info["scans"]) == info["points"]
    assert info["sensors"] == [A.tolist(), B.tolist()]


def test_sdp_change_between_multi_scan_e57_files_says_how_many_scanners(two_epochs, tmp_path):
    # the text summary once formatted an origin per direction, and several scanners crashed it
    p = run("change", two_epochs[0], two_epochs[1], "-o", tmp_path / "c.ply")
    assert p.returncode == 0, p.stderr
    assert "the reference's sensor rays (2 scanners)" in p.stdout and "Traceback" not in p.stderr
    assert (tmp_path / "c.ply").exists()


def test_spherical_scans_are_converted():
    from sdp.io._e57 import _scan_points  # pye57 writes Cartesian scans only

    raw = {"sphericalRange": np.array([2.0, 3.0, 1.0]), "sphericalAzimuth": np.array([0.0, np.pi / 2, 0.0]),
           "sphericalElevation": np.array([0.0, np.pi / 6, 0.0]), "sphericalInvalidState": np.array([0, 0, 1])}
    turn = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])  # 90° about z
    got = _scan_points(raw, turn, np.array([1.0, 0, 0]), 3, "s.e57")
    assert np.allclose(got["xyz"][:2], [[1, 2, 0], [1 - 3 * np.cos(np.pi / 6), 0, 1.5]])
    assert np.isnan(got["xyz"][2]).all() and (got["scan"] == 3).all()


@pytest.mark.shared_data
def test_pump_scan_reads_as_pye57_reports(shared_data):
    path = shared_data / PUMP
    c = sdp.read_points(path)
    e = pye57.E57(str(path))
    ref = e.read_scan(0, intensity=True, colors=True, row_column=True)
    assert len(c) == len(ref["cartesianX"]) == e.get_header(0).point_count - c.n_dropped
    assert np.array_equal(c.xyz, np.c_[ref["cartesianX"], ref["cartesianY"], ref["cartesianZ"]])
    for ours, theirs in (("red", "colorRed"), ("green", "colorGreen"), ("blue", "colorBlue"),
                         ("intensity", "intensity"), ("row", "rowIndex"), ("column", "columnIndex")):
        assert np.array_equal(c.fields[ours], ref[theirs]), ours
    assert np.allclose(c.sensor_origin, 0)  # no pose: the scanner at the scan frame's origin


@pytest.mark.slow
@pytest.mark.shared_data
def test_sdp_change_finds_a_box_added_to_the_pump_scan(shared_data, tmp_path):
    path = shared_data / PUMP
    raw = pye57.E57(str(path)).read_scan_raw(0)
    xyz = np.c_[raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]]
    # a 0.3 m box between the scanner and the pump, its faces sampled every 5 mm
    centre = 0.7 * np.median(xyz, axis=0)
    g = np.arange(-0.15, 0.15 + 1e-9, 0.005)
    u, v = (a.ravel() for a in np.meshgrid(g, g))
    faces = [np.c_[np.full_like(u, s * 0.15), u, v] for s in (-1, 1)]
    faces += [np.c_[u, np.full_like(u, s * 0.15), v] for s in (-1, 1)]
    faces += [np.c_[u, v, np.full_like(u, s * 0.15)] for s in (-1, 1)]
    box = np.unique(np.concatenate(faces), axis=0) + centre
    data = {k: np.concatenate([raw[k], np.zeros(len(box), raw[k].dtype)]) for k in raw}
    data["cartesianX"][-len(box):], data["cartesianY"][-len(box):], data["cartesianZ"][-len(box):] = box.T
    data["rowIndex"][-len(box):], data["columnIndex"][-len(box):] = 0, 0
    e = pye57.E57(str(tmp_path / "with_box.e57"), mode="w")
    e.write_scan_raw(data)
    e.close()
    p = run("change", path, tmp_path / "with_box.e57", "-o", tmp_path / "out.ply", "--json")
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    assert s["coverage"]["appeared"] == "sensor rays" and s["reference"]["disappeared"] == 0
    regions = s["appeared_regions"]
    assert len(regions) >= 1 and np.allclose(regions[0]["centroid"], centre, atol=0.1)
    out = sdp.read_points(tmp_path / "out.ply")
    change = out.fields["change"]
    # the box's side facing the scanner (seen through in the reference): changed
    assert (change[-len(box):] == sdp.CHANGED).mean() > 0.5
    assert (change[:-len(box)] == sdp.CHANGED).mean() < 0.01


def test_corrupt_or_foreign_e57_is_one_line(two_epochs, tmp_path):
    cut = tmp_path / "cut.e57"
    cut.write_bytes(two_epochs[0].read_bytes()[:5000])
    (tmp_path / "text.e57").write_text("not an e57 file\n")
    for name in ("cut.e57", "text.e57"):
        with pytest.raises(CloudFileError, match=f"{name}: can't read as e57") as e:
            sdp.read_points(tmp_path / name)
        assert "\n" not in str(e.value)
    p = run("change", two_epochs[0], cut, "-o", tmp_path / "out.ply")
    assert p.returncode == 2 and p.stderr.startswith("sdp: error: ") and len(p.stderr.strip().splitlines()) == 1
    assert "cut.e57: can't read as e57" in p.stderr and not (tmp_path / "out.ply").exists()


def test_e57_without_the_extra_says_how_to_install(monkeypatch, two_epochs):
    monkeypatch.setitem(sys.modules, "pye57", None)
    with pytest.raises(sdp.MissingDependencyError, match=r"pip install 'sdp\[scans\]'"):
        sdp.read_points(two_epochs[0])


class _EmptySafe(np.ndarray):
    """pye57's writer takes each field's min and max: a scan of no point needs them said."""

    def min(self, *a, **k):
        return 0 if self.size == 0 else np.asarray(self).min(*a, **k)

    def max(self, *a, **k):
        return 2 if self.size == 0 else np.asarray(self).max(*a, **k)


class _FromZero(np.ndarray):
    """pye57 bounds an integer field by its values, and libE57Format's prototype holds 0."""

    def min(self, *a, **k):
        return 0


def test_a_scan_of_no_point_is_no_scanner(tmp_path, rng):
    """A scan of no record (older writers leave them; libE57Format can't read its empty vector,
    libE57Format issue 262), or of invalid points only, is skipped and is no scanner: the file
    reads as its other scans alone (a scanner that saw nothing would turn a one-station file into
    a survey of several, compared otherwise)."""
    xyz = rng.random((500, 3))
    for empty in ("no record", "all invalid"):
        e = pye57.E57(str(tmp_path / "s.e57"), mode="w")
        if empty == "all invalid":
            e.write_scan_raw({**{k: np.ascontiguousarray(xyz[:, i]).view(_EmptySafe) for i, k in
                                 enumerate(("cartesianX", "cartesianY", "cartesianZ"))},
                              "cartesianInvalidState": np.full(500, 2, np.int8).view(_FromZero)}, name="blind",
                             translation=np.array([0.5, 0.0, 0.0]))
        e.write_scan_raw({"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2]}, name="A",
                         translation=np.array([0.0, 0.0, 2.0]))
        if empty == "no record":
            e.write_scan_raw({k: np.zeros(0).view(_EmptySafe) for k in ("cartesianX", "cartesianY", "cartesianZ")},
                             name="empty", translation=np.array([0.5, 0.0, 0.0]))
        e.close()
        cloud = sdp.read_points(tmp_path / "s.e57")
        np.testing.assert_allclose(cloud.xyz, xyz + [0, 0, 2])
        assert cloud.sensors.shape == (1, 3) and set(cloud.fields["scan"].tolist()) == {0}, empty
        np.testing.assert_allclose(cloud.sensor_origin, [0, 0, 2])


def test_a_pair_of_sensors_with_one_unknown_keeps_every_scanner_of_the_other():
    """``sensor_origin=[None, scanners]``: the known cloud's k scanners, not the first alone (a
    (2, 3) read as one position per cloud) nor refused (k = 3)."""
    from sdp.change._visibility import resolve_sensor_origins

    for k in (2, 3):
        rows = np.arange(3.0 * k).reshape(k, 3)
        ref, cur = resolve_sensor_origins([None, rows], None, None)
        assert ref is None and np.array_equal(cur, rows)
    assert np.array_equal(resolve_sensor_origins([[1, 2, 3], None], None, None)[0], [1, 2, 3])
    with pytest.raises(sdp.InvalidPointsError, match="one row per scan"):
        resolve_sensor_origins([None, [[1, 2]]], None, None)


def test_several_scanners_without_a_scan_index_are_refused_before_any_work():
    xyz = np.random.default_rng(0).random((500, 3))
    rows = [[5.0, 5, 3], [2, 2, 3]]
    for pair in ([rows, None], [None, rows]):
        with pytest.raises(sdp.InvalidPointsError, match="no scan index per point"):
            sdp.distances(xyz, xyz + [0, 0, 0.01], sensor_origin=pair)


def test_a_field_some_scans_lack_is_kept_and_filled_at_the_others(tmp_path):
    # colour and intensity at one station only, as surveys often have: kept, 0 where a scan has none
    rng = np.random.default_rng(3)
    e = pye57.E57(str(tmp_path / "m.e57"), mode="w")
    colour = rng.integers(1, 256, (3, 500)).astype(np.uint8)
    e.write_scan_raw({"cartesianX": rng.random(500), "cartesianY": rng.random(500), "cartesianZ": rng.random(500),
                      "intensity": np.full(500, 0.25), "colorRed": colour[0], "colorGreen": colour[1],
                      "colorBlue": colour[2]}, rotation=np.array([1.0, 0, 0, 0]), translation=np.zeros(3))
    e.write_scan_raw({"cartesianX": rng.random(300), "cartesianY": rng.random(300), "cartesianZ": rng.random(300)},
                     rotation=np.array([1.0, 0, 0, 0]), translation=np.array([2.0, 0, 0]))
    e.close()
    cloud = sdp.read_points(tmp_path / "m.e57")
    assert {"intensity", "red", "green", "blue", "scan"} <= set(cloud.fields)
    first = cloud.fields["scan"] == 0
    assert first.sum() == 500 and np.array_equal(cloud.fields["red"][first], colour[0])
    assert (cloud.fields["red"][~first] == 0).all() and (cloud.fields["intensity"][~first] == 0).all()


def test_scans_of_no_pose_put_their_scanner_at_the_origin_only_alone(tmp_path):
    """One scan without a pose is in its scanner's frame (the standard's identity); several, in a
    registered export that kept no station, cannot all have stood at the origin: no scanner."""
    from sdp.cli._files import describe_file

    rng = np.random.default_rng(4)

    import inspect
    import textwrap

    # pye57 writes an identity pose when given none; a file without one, as registered exports are
    source = textwrap.dedent(inspect.getsource(pye57.E57.write_scan_raw)).replace(
        "def write_scan_raw(", "def write_without_pose(").replace(
        "if rotation is not None and translation is not None:", "if False:")
    assert "if False:" in source
    names = dict(vars(sys.modules[pye57.E57.__module__]))
    exec(source, names)

    def write(path, n_scans):
        e = pye57.E57(str(path), mode="w")
        for k in range(n_scans):
            xyz = rng.random((400, 3)) + [5.0 * k, 3.0, 0.0]
            names["write_without_pose"](e, {"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2]})
        e.close()
        return path

    one, two = sdp.read_points(write(tmp_path / "one.e57", 1)), sdp.read_points(write(tmp_path / "two.e57", 2))
    assert np.allclose(one.sensor_origin, 0) and two.sensors is None and two.sensor_origin is None
    assert one.poles is None and two.poles is None  # Cartesian points say nothing of the scanner's axes
    info = describe_file(tmp_path / "two.e57")
    assert "sensors" not in info and [s["pose"] for s in info["scans"]] == [False, False]
    assert [s["kept"] for s in info["scans"]] == [400, 400]


def _write_spherical_scan(e, local, bad, rotation, translation, start):
    """A scan stored as ``sphericalRange/Azimuth/Elevation`` (invalid rays flagged), as many
    scanners export: pye57 writes Cartesian scans only, so through its libE57Format bindings."""
    import uuid

    from pye57 import libe57

    f = e.image_file
    r = np.linalg.norm(local, axis=1)
    values = {"sphericalRange": np.where(bad, 0.0, r), "sphericalAzimuth": np.arctan2(local[:, 1], local[:, 0]),
              "sphericalElevation": np.arcsin(np.divide(local[:, 2], r, out=np.zeros_like(r), where=r > 0)),
              "sphericalInvalidState": bad.astype(np.int8)}
    scan = libe57.StructureNode(f)
    scan.set("guid", libe57.StringNode(f, "{%s}" % uuid.uuid4()))
    pose, turn, move, when = (libe57.StructureNode(f) for _ in range(4))
    for k, v in zip("wxyz", rotation):
        turn.set(k, libe57.FloatNode(f, float(v)))
    for k, v in zip("xyz", translation):
        move.set(k, libe57.FloatNode(f, float(v)))
    pose.set("rotation", turn)
    pose.set("translation", move)
    scan.set("pose", pose)
    when.set("dateTimeValue", libe57.FloatNode(f, float(start)))
    scan.set("acquisitionStart", when)
    proto = libe57.StructureNode(f)
    proto.set("sphericalRange", libe57.FloatNode(f, 0.0, libe57.E57_DOUBLE, 0.0, float(r.max())))
    proto.set("sphericalAzimuth", libe57.FloatNode(f, 0.0, libe57.E57_DOUBLE, -np.pi, np.pi))
    proto.set("sphericalElevation", libe57.FloatNode(f, 0.0, libe57.E57_DOUBLE, -np.pi / 2, np.pi / 2))
    proto.set("sphericalInvalidState", libe57.IntegerNode(f, 0, 0, 2))
    arrays, buffers = e.make_buffers(list(values), len(r))
    points = libe57.CompressedVectorNode(f, proto, libe57.VectorNode(f, True))
    scan.set("points", points)
    e.data3d.append(scan)
    writer = points.writer(buffers)
    for k, v in values.items():
        arrays[k][:] = v
    writer.write(len(r))
    writer.close()


def test_a_survey_in_a_projected_crs_with_spherical_scans_reads_and_measures_as_at_the_origin(tmp_path):
    """A TLS campaign as surveys deliver it: stations posed at UTM-sized coordinates, one scan stored
    spherical beside a Cartesian one, acquisition starts recorded. The spherical scan reads as its
    Cartesian twin; the file's time is its earliest start; distances at the offset equal those of
    the same data shifted to the origin within 1e-6 (scales commensurate with the lattice, so that
    both fall on the same cells)."""
    from sdp.io._time import file_time

    offset = np.array([500_000.0, 5_000_000.0, 300.0])
    a, b = np.array([-3.5, 0, 1.5]), np.array([3.5, 0.6, 1.5])
    stations = ((a, 0.0), (b, np.pi))

    def write(path, shapes, shift, spherical):
        e = pye57.E57(str(path), mode="w")
        for k, (o, yaw) in enumerate(stations):
            pts = cast(o, shapes, step_deg=1.5)[0]
            c, s = np.cos(yaw), np.sin(yaw)
            local = (pts - o) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
            bad = ~np.isfinite(local).all(axis=1)
            local[bad] = 0
            q, t, start = np.array([np.cos(yaw / 2), 0, 0, np.sin(yaw / 2)]), o + shift, 1.4e9 + 600 * (1 - k)
            if spherical and k == 1:
                _write_spherical_scan(e, local, bad, q, t, start)
                continue
            lo, hi = pts[~bad].min(0) + shift, pts[~bad].max(0) + shift
            e.write_scan_raw({"cartesianX": local[:, 0], "cartesianY": local[:, 1], "cartesianZ": local[:, 2],
                              "cartesianInvalidState": bad.astype(np.int8)}, rotation=q, translation=t,
                             scan_header=type("H", (), {"acquisitionStart_dateTimeValue": start,
                                                        **dict(zip(["xMinimum", "yMinimum", "zMinimum"], lo)),
                                                        **dict(zip(["xMaximum", "yMaximum", "zMaximum"], hi))})())
        e.close()
        return path

    before, after = [FLOOR, WALL, TOWER, BOX_BEFORE], [FLOOR, WALL, TOWER, BOX_AFTER]
    far = write(tmp_path / "far.e57", before, offset, True)
    got, twin = sdp.read_points(far), sdp.read_points(write(tmp_path / "twin.e57", before, offset, False))
    assert pye57.E57(str(far)).get_header(1).point_fields[0] == "sphericalRange"
    assert np.array_equal(got.scan, twin.scan) and np.allclose(got.sensors, [a + offset, b + offset])
    assert np.allclose(got.poles, [[0, 0, 1], [0, 0, 1]]) and np.allclose(twin.poles, got.poles)
    assert np.abs(got.xyz - twin.xyz).max() < 1e-5  # the Cartesian twin is stored in single precision
    # GPS seconds (from 1980-01-06, 3657 days after 1970-01-01; 18 leap seconds) to UTC days
    assert file_time(far)[0] == pytest.approx((1.4e9 - 18) / 86400 + 3657, abs=1e-9)
    cylinder = sdp.Cylinder(projection_scale=0.25, normal_scale=0.5, max_distance=1.0)
    core = got.xyz[::20] - offset
    out = [sdp.distances(sdp.read_points(write(tmp_path / f"ref{i}.e57", before, shift, True)),
                         sdp.read_points(write(tmp_path / f"cur{i}.e57", after, shift, False)),
                         core_points=core + shift, cylinder=cylinder) for i, shift in enumerate((offset, np.zeros(3)))]
    assert np.array_equal(np.isnan(out[0].distance), np.isnan(out[1].distance))
    assert np.nanmax(np.abs(out[0].distance)) > 0.5  # the box moved
    assert np.nanmax(np.abs(out[0].distance - out[1].distance)) < 1e-6
    assert np.nanmax(np.abs(out[0].lod - out[1].lod)) < 1e-6


# A rock cut: flat ground to 40 m, a 6 m cliff 6 m east of station A. The current campaign adds
# station C; a block has fallen on the ground west of A. Both scanners stand level (their poses'
# z is up), but their returns, crowded on the cliff's side, spread least along a direction 13°
# (A) and 24° (C) off the vertical.
CUT_GROUND, CUT_CLIFF = ([-40, -40, -0.1], [40, 40, 0]), ([6, -40, 0], [8, 40, 6])
FALLEN = ([-5, 2, 0], [-3.5, 3.5, 1])
CUT_A, CUT_C = np.array([0.0, 0.0, 1.5]), np.array([3.0, 10.0, 1.5])


def tls_scan(origin, boxes, rng, *, shift=0.0, step=0.6):
    """:func:`cast` over −60°…+60° of elevation (from ``shift`` above −60°: a station set up
    again samples other rays), with 2 mm of range noise."""
    pts, row, col = cast(origin, boxes, step_deg=step, el_range=(-60 + shift, 60))
    d = pts - origin
    r = np.linalg.norm(d, axis=1)
    return origin + d * ((r + 0.002 * rng.standard_normal(len(r))) / r)[:, None], row, col


@pytest.fixture(scope="module")
def rock_cut(tmp_path_factory):
    d = tmp_path_factory.mktemp("cut")
    rng = np.random.default_rng(1)
    before, after = [CUT_GROUND, CUT_CLIFF], [CUT_GROUND, CUT_CLIFF, FALLEN]
    ref = write_e57(d / "ref.e57", [(*tls_scan(CUT_A, before, rng), CUT_A, 0.0)])
    scans = [(*tls_scan(CUT_A, after, rng, shift=0.3), CUT_A, 0.0), (*tls_scan(CUT_C, after, rng), CUT_C, 0.0)]
    return ref, write_e57(d / "cur.e57", scans), write_e57(d / "c.e57", scans[1:])


def test_grazing_ground_beside_a_cliff_is_unchanged_where_a_station_was_added(rock_cut):
    """Each scanner's range image is laid out about its own vertical (its pose's z), its rows the
    image's: laid out about the direction its returns spread least along, tilted towards the
    cliff, 334 points of the ground C saw at grazing range read as changed against A's rays and
    2,380 as not comparable (359 and 2,983 with a laser scan's own band)."""
    ref, cur = (sdp.read_points(p) for p in rock_cut[:2])
    assert np.allclose(cur.poles, [[0, 0, 1], [0, 0, 1]])
    for noise in (0.001, None):  # the band of --range-noise 0.001, and a laser scan's own (σ)
        res = sdp.detect_changes(ref, cur, lattice=sdp.Lattice(voxel_size=0.05),
                                 coverage=sdp.Coverage() if noise is None else sdp.Coverage(range_noise=noise))
        block = inside(cur.xyz, *FALLEN, pad=0.05)
        state = res.current_state
        assert (state[~block] == sdp.UNCHANGED).all(), np.bincount(state[~block], minlength=3)
        assert block.sum() > 1000 and (state[block] == sdp.CHANGED).mean() > 0.8
        assert (res.reference_state == sdp.UNCHANGED).all()


def test_a_place_below_a_scanners_lowest_ray_is_not_seen(rock_cut):
    """An epoch of station C alone measures no core point under C, below its lowest ray (−60°:
    within 0.87 m of its foot), which no scanner of that epoch saw; in the image laid out about
    the returns' least direction, that ground lay beside ground C did see (2 of 25 measured, both
    "significant")."""
    from sdp.distance._seen import not_seen

    ref, cur = (sdp.read_points(p) for p in (rock_cut[0], rock_cut[2]))
    foot = np.linalg.norm(ref.xyz[:, :2] - CUT_C[:2], axis=1)
    under = ref.xyz[foot < 1.5 / np.tan(np.radians(60)) - 0.05]
    assert len(under) > 20
    assert not_seen(under, cur.xyz, cur.sensors[0], None, sigma=0.05, poles=cur.poles[0]).all()
    d = sdp.distances(ref, cur, core_points=under, cylinder=sdp.Cylinder(projection_scale=0.5, normal_scale=0.5))
    assert np.isnan(d.distance).all() and not d.significant.any()


def test_a_scanners_vertical_is_its_poses_z_and_moves_with_the_cloud(tmp_path):
    """A scanner set up 10° off level (its pose turns its z about x): its pole is that turned z,
    the range image's pole is it, and a moved cloud's poles turn with it; without one, the image
    is laid out about the least direction of its returns."""
    from sdp.change._range_image import RangeImage

    tilt = np.radians(10)
    q = np.array([np.cos(tilt / 2), np.sin(tilt / 2), 0, 0])  # 10° about x
    rng = np.random.default_rng(2)
    local = rng.normal(size=(2000, 3)) * [10, 10, 1]
    e = pye57.E57(str(tmp_path / "tilted.e57"), mode="w")
    e.write_scan_raw({"cartesianX": local[:, 0], "cartesianY": local[:, 1], "cartesianZ": local[:, 2]},
                     rotation=q, translation=np.array([1.0, 2.0, 3.0]))
    e.close()
    cloud = sdp.read_points(tmp_path / "tilted.e57")
    up = [0, -np.sin(tilt), np.cos(tilt)]
    np.testing.assert_allclose(cloud.poles, [up], atol=1e-12)
    image = RangeImage.from_points(cloud.xyz, cloud.sensors[0], pole=cloud.poles[0])
    np.testing.assert_allclose(image.frame[2], up, atol=1e-12)
    assert image.scanner_rows and abs(image.frame[0] @ up) < 1e-12
    assert not RangeImage.from_points(cloud.xyz, cloud.sensors[0]).scanner_rows
    turn = np.eye(4)
    turn[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # 90° about z
    np.testing.assert_allclose(cloud.transformed(turn).poles, [[np.sin(tilt), 0, np.cos(tilt)]], atol=1e-12)
    with pytest.raises(sdp.InvalidPointsError, match="pole"):
        RangeImage.from_points(cloud.xyz, cloud.sensors[0], pole=[0, 0, 0])
