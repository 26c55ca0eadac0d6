"""Three states: changed, unchanged, not comparable (sdp.coverage), through every path and output."""

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import assert_changes_drawn

import sdp
from sdp.change._coverage import CHANGED, NOT_COMPARABLE, UNCHANGED, footprint_covered


def flight(rng, x_max, *, building=None, spacing=1.0):
    """Airborne-like epoch: jittered ground points on [0, x_max] x [0, 100] (z ~ 0), and optionally
    a flat roof 8 m up over ``building`` = (x0, y0, x1, y1), sampled like the ground (the ground under
    it unseen)."""
    gx, gy = np.meshgrid(np.arange(0, x_max, spacing), np.arange(0, 100, spacing))
    xy = np.c_[gx.ravel(), gy.ravel()] + rng.uniform(-0.3, 0.3, (gx.size, 2)) * spacing
    z = 0.05 * rng.standard_normal(len(xy))
    roof = np.zeros(len(xy), bool)
    if building is not None:
        x0, y0, x1, y1 = building
        roof = (xy[:, 0] > x0) & (xy[:, 0] < x1) & (xy[:, 1] > y0) & (xy[:, 1] < y1)
        z[roof] += 8.0
    return np.c_[xy, z], roof


def test_footprint_is_the_density_projected_on_the_ground(rng):
    pts = np.c_[rng.uniform(0, 2, (400, 2)), rng.uniform(0, 3, 400)]  # a 3 m tall cloud over 2 m x 2 m
    f = sdp.DensityField.from_points(pts, voxel_size=0.05, method="exact")
    q = np.c_[rng.uniform(-0.3, 2.3, (300, 2)), np.full(300, 40.0)]  # any height: the column counts
    d2 = ((q[:, None, :2] - pts[None, :, :2]) ** 2).sum(axis=2)
    brute = np.exp(-d2 / (2 * f.sigma**2)).sum(axis=1)  # each point's Gaussian integrated along z
    np.testing.assert_allclose(f.footprint(q), brute, atol=0.02 * brute.max())
    on = f.footprint(pts)
    assert (on >= f.density(pts) - 1e-6).all()  # a footprint is never below the density
    np.testing.assert_array_equal(footprint_covered(q, f), f.footprint(q) >= f.h)
    far = f.footprint(pts + [6e5, 5e6, 0] - [6e5, 5e6, 0])  # UTM-sized offsets cancel: same cells
    np.testing.assert_allclose(far, on)


def test_a_strip_only_one_flight_covered_is_not_comparable_and_a_new_building_is_found(rng):
    old, _ = flight(rng, 100)
    new, roof = flight(rng, 140, building=(40, 40, 60, 60))  # 40 m more to the east, a building inside
    r = sdp.detect_changes(old, new)
    strip = new[:, 0] > 103
    assert r.coverage == {"appeared": "footprint", "disappeared": "footprint"}
    assert r.current_not_comparable[strip].mean() > 0.97 and not r.appeared[strip].any()
    assert r.appeared[roof].mean() > 0.9 and not r.current_not_comparable[roof].any()
    assert r.appeared[~roof & ~strip].mean() < 0.01
    assert [round(float(v)) for v in r.appeared_regions[0].centroid[:2]] == [50, 50] and len(r.appeared_regions) == 1
    assert not (r.appeared & r.current_not_comparable).any()
    assert (r.appeared_labels[r.current_not_comparable] == -1).all()
    state = r.current_state
    assert set(np.unique(state)) == {UNCHANGED, CHANGED, NOT_COMPARABLE}
    assert (state == NOT_COMPARABLE).sum() == r.summary()["current"]["not_comparable"]
    # the old building: its roof disappeared; the ground under it is covered by the old roof's footprint
    back = sdp.detect_changes(new, old)
    np.testing.assert_array_equal(back.disappeared, r.appeared)
    np.testing.assert_array_equal(back.reference_not_comparable, r.current_not_comparable)
    off = sdp.detect_changes(old, new, coverage=sdp.Coverage(enabled=False))  # every point comparable: the strip looks new
    assert off.appeared[strip].mean() > 0.9 and not off.current_not_comparable.any()
    assert off.coverage["appeared"] == "off"


def test_scores_leave_not_comparable_points_out():
    truth = np.array([1, 1, 0, 0, 1, 0], bool)
    pred = np.array([1, 0, 0, 0, 0, 1], bool)
    comparable = np.array([1, 1, 1, 1, 0, 0], bool)
    s = sdp.scores(truth, pred, comparable=comparable)
    assert (s["tp"], s["fn"], s["tn"], s["fp"], s["not_comparable"]) == (1, 1, 2, 0, 2)
    assert s["kappa"] == pytest.approx(sdp.kappa(truth[:4], pred[:4]))
    assert sdp.scores(truth, pred)["not_comparable"] == 0


@pytest.mark.slow
@pytest.mark.parametrize("ext", ["ply", "las", "laz", "npz"])
def test_the_third_state_survives_each_output_format(tmp_path, rng, ext):
    old, _ = flight(rng, 60, spacing=1.5)
    new, roof = flight(rng, 90, building=(20, 20, 35, 35), spacing=1.5)
    np.save(tmp_path / "old.npy", old)
    np.save(tmp_path / "new.npy", new)
    out = tmp_path / f"out.{ext}"
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "change", str(tmp_path / "old.npy"), str(tmp_path / "new.npy"),
                        "-o", str(out), "--both", "--json"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    expected = sdp.detect_changes(old, new)
    for path, state in ((out, expected.current_state),
                        (out.with_name(f"out_disappeared.{ext}"), expected.reference_state)):
        back = np.asarray(sdp.read_points(path).fields["change"])
        np.testing.assert_array_equal(back, state)
    assert s["current"]["not_comparable"] == (expected.current_state == NOT_COMPARABLE).sum() > 100
    assert s["coverage"]["appeared"] == "footprint" and s["sensor_origin"] == {"reference": None, "current": None}


@pytest.mark.slow
def test_the_tiled_path_marks_the_same_points_not_comparable(tmp_path, rng):
    old, _ = flight(rng, 60, spacing=1.5)
    new, _ = flight(rng, 90, building=(20, 20, 35, 35), spacing=1.5)
    whole = sdp.detect_changes(old, new, lattice=sdp.Lattice(voxel_size=1.0))
    tiled = sdp.detect_changes_tiled(old, new, lattice=sdp.Lattice(voxel_size=1.0),
                                     execution=sdp.Execution(tile_size=20.0, scheduler="synchronous", workdir=tmp_path))
    assert tiled.n_tiles > 4
    np.testing.assert_array_equal(tiled.current_state, whole.current_state)
    np.testing.assert_array_equal(tiled.reference_state, whole.reference_state)
    assert tiled.summary()["current"]["not_comparable"] == whole.current_not_comparable.sum() > 100
    # and through the command's streamed LAS output
    np.save(tmp_path / "old.npy", old)
    np.save(tmp_path / "new.npy", new)
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "change", str(tmp_path / "old.npy"), str(tmp_path / "new.npy"),
                        "-o", str(tmp_path / "t.laz"), "--tiled", "--voxel-size", "1", "--tile-size", "20",
                        "--workers", "1", "--json"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    np.testing.assert_array_equal(sdp.read_points(tmp_path / "t.laz").fields["change"], whole.current_state)


@pytest.mark.slow
def test_eval_scores_the_comparable_points_and_render_draws_them_grey(tmp_path, rng):
    old, _ = flight(rng, 60, spacing=1.5)
    new, roof = flight(rng, 90, building=(20, 20, 35, 35), spacing=1.5)
    r = sdp.detect_changes(old, new)
    sdp.write_points(tmp_path / "out.ply", new, {"change": r.current_state})
    sdp.write_points(tmp_path / "truth.ply", new, {"change": roof.astype(np.uint8)})
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "eval", str(tmp_path / "out.ply"), str(tmp_path / "truth.ply"),
                        "--json"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    assert s["not_comparable"] == r.current_not_comparable.sum() > 0
    assert s["kappa"] == pytest.approx(sdp.scores(roof, r.appeared, comparable=~r.current_not_comparable)["kappa"])
    assert s["kappa"] > 0.95
    from sdp.viz._render import _drawn

    names = [layer[1] for layer in _drawn(r.current_state, 1000, 0)]
    assert names == ["unchanged", "not comparable", "changed"]
    assert_changes_drawn(sdp.render_changes(tmp_path / "c.png", new, r.current_state))


def test_watch_marks_what_the_reference_never_covered(rng):
    old, _ = flight(rng, 60, spacing=1.5)
    frames = [flight(rng, 90, spacing=1.5)[0]]
    r = next(sdp.watch(old, frames))
    strip = frames[0][:, 0] > 63
    assert r.not_comparable[strip].mean() > 0.95 and not r.appeared[strip].any()
    assert r.summary()["not_comparable"] == r.not_comparable.sum()
    np.testing.assert_array_equal(r.state == NOT_COMPARABLE, r.not_comparable)


@pytest.mark.slow
def test_a_landscape_is_drawn_as_a_map_and_a_room_in_three_views(tmp_path, rng, monkeypatch):
    from sdp.viz import _render as render

    old, _ = flight(rng, 60, spacing=1.5)
    new, _ = flight(rng, 90, building=(20, 20, 35, 35), spacing=1.5)
    state = sdp.detect_changes(old, new).current_state
    drawn = []
    monkeypatch.setattr(render, "_map", lambda *a, _map=render._map: drawn.append("map") or _map(*a))
    render.render_changes(tmp_path / "map.png", new + [6e5, 5e6, 0], state)  # UTM-sized: relative axes
    render.render_changes(tmp_path / "room.png", rng.random((2000, 3)), rng.random(2000) < 0.1)
    assert drawn == ["map"]
    assert_changes_drawn(tmp_path / "map.png")
    assert_changes_drawn(tmp_path / "room.png")
