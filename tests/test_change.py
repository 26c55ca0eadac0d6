import threading

import numpy as np
import pytest
from conftest import box_surface, room_scene

import sdp
import sdp.change._detect
from sdp.data._scene import office_scene


@pytest.fixture
def scene_pair(rng):
    reference = room_scene(rng, n=80_000)
    current = room_scene(rng, n=80_000)  # a new scan of the same room: new samples, new noise
    box = box_surface(rng, [2.0, 1.2, 0.75], [2.4, 1.6, 1.35], 3000)  # on the table
    current = np.concatenate([current, box])
    truth = np.r_[np.zeros(len(current) - len(box), bool), np.ones(len(box), bool)]
    return reference, current, truth


def test_identical_clouds_give_no_change(rng):
    pts = room_scene(rng, n=20000)
    r = sdp.detect_changes(pts, pts, lattice=sdp.Lattice(voxel_size=0.02))
    assert not r.appeared.any() and not r.disappeared.any()
    assert r.appeared_regions == [] and r.disappeared_regions == []


def test_rows_holding_nan_are_not_comparable(scene_pair):
    """A row without a position was not measured: not comparable and in no region, whichever
    cloud holds it; the other rows get what they get without it."""
    reference, current, _ = scene_pair
    gap = np.array([[np.nan, 1.0, 1.0], [1.0, np.inf, 1.0]])
    lattice = sdp.Lattice(voxel_size=0.015)
    r = sdp.detect_changes(np.r_[reference, gap], np.r_[gap, current], lattice=lattice)
    plain = sdp.detect_changes(reference, current, lattice=lattice)
    assert (r.reference_state[-2:] == sdp.NOT_COMPARABLE).all() and (r.current_state[:2] == sdp.NOT_COMPARABLE).all()
    assert (r.disappeared_labels[-2:] == -1).all() and (r.appeared_labels[:2] == -1).all()
    np.testing.assert_array_equal(r.current_state[2:], plain.current_state)
    np.testing.assert_array_equal(r.reference_state[:-2], plain.reference_state)
    s, t = r.summary()["current"], plain.summary()["current"]  # rows without a position: dropped, not points
    assert (s["points"], s["dropped"], s["not_comparable"]) == (t["points"], 2, t["not_comparable"])


def test_a_table_gives_its_x_y_z_columns_by_name(rng):
    # columns ordered z, x, y (after a merge) were read by position: 4,187 appeared instead of 270
    pd = pytest.importorskip("pandas")
    floor = np.c_[rng.random((4000, 2)), np.zeros(4000)]
    cur = np.concatenate([floor, rng.uniform([0.4, 0.4, 0.0], [0.6, 0.6, 0.2], (500, 3))])
    lattice = sdp.Lattice(voxel_size=0.02)
    want = sdp.detect_changes(floor, cur, lattice=lattice)
    table = pd.DataFrame(cur, columns=list("xyz"))
    for given in (table[["z", "x", "y"]], table.assign(intensity=1.0)):
        got = sdp.detect_changes(pd.DataFrame(floor, columns=list("xyz")), given, lattice=lattice)
        assert np.array_equal(got.appeared, want.appeared) and np.array_equal(got.disappeared, want.disappeared)
    unnamed = sdp.detect_changes(pd.DataFrame(floor), pd.DataFrame(cur), lattice=lattice)  # three columns: x, y, z
    assert np.array_equal(unnamed.appeared, want.appeared)
    with pytest.raises(sdp.InvalidPointsError, match=r'current: a table of 4 columns .*df\[\["x", "y", "z"\]\]'):
        sdp.detect_changes(floor, pd.DataFrame(np.c_[cur, cur[:, :1]], columns=list("abcd")), lattice=lattice)


def test_inserted_box_is_found_as_one_region(scene_pair):
    reference, current, truth = scene_pair
    r = sdp.detect_changes(reference, current, lattice=sdp.Lattice(voxel_size=0.015))
    assert sdp.kappa(truth, r.appeared) > 0.9
    assert r.disappeared.mean() < 0.001
    big = r.appeared_regions[0]
    assert big.n_points > 0.8 * truth.sum() and big.n_points > 0.95 * r.appeared.sum()
    np.testing.assert_allclose(big.centroid[:2], [2.2, 1.4], atol=0.05)
    assert np.all(big.bbox_min > [1.9, 1.1, 0.7]) and np.all(big.bbox_max < [2.5, 1.7, 1.4])
    assert 0 < big.volume < 2 * 0.4 * 0.4 * 0.6  # cells of the box's thickened surface
    assert sum(x.n_points for x in r.appeared_regions) == r.appeared.sum()
    assert r.appeared_labels.dtype == np.int32 and r.current_state.dtype == np.uint8 and not r.tiled
    assert (r.appeared_labels >= 0).sum() == r.appeared.sum()
    np.testing.assert_array_equal(r.appeared_labels == 0, r.appeared & (r.appeared_labels == big.label))
    assert set(r.timings) == {"build_reference", "build_current", "detect", "coverage", "regions"}
    # dropping stray regions leaves exactly the box
    s = sdp.detect_changes(reference, current, min_region_points=20, lattice=sdp.Lattice(voxel_size=0.015))
    assert len(s.appeared_regions) == 1 and sdp.kappa(truth, s.appeared) >= sdp.kappa(truth, r.appeared)


def test_removed_box_is_disappeared(scene_pair):
    reference, current, truth = scene_pair
    r = sdp.detect_changes(current, reference, lattice=sdp.Lattice(voxel_size=0.015))  # swap: the box disappeared
    assert sdp.kappa(truth, r.disappeared) > 0.9
    assert not r.appeared.mean() > 0.001


def test_cluster_decision_promotes_mostly_changed_clusters(rng):
    reference = room_scene(rng, n=80_000)
    # a box standing free in the air above the table is a cluster of its own: a point-wise
    # detection that misses part of it (here: its lower part overlaps an old box) is completed
    old = box_surface(rng, [2.0, 1.2, 1.5], [2.4, 1.6, 1.6], 1500)
    new = box_surface(rng, [2.0, 1.2, 1.5], [2.4, 1.6, 2.1], 4000)
    current = np.concatenate([room_scene(rng, n=80_000), new])
    truth = np.r_[np.zeros(80_000, bool), np.ones(len(new), bool)]
    point = sdp.detect_changes(np.concatenate([reference, old]), current, lattice=sdp.Lattice(voxel_size=0.015))
    cluster = sdp.detect_changes(np.concatenate([reference, old]), current, decision="cluster",
                                 lattice=sdp.Lattice(voxel_size=0.015))
    assert point.appeared[truth].mean() < 0.95
    assert cluster.appeared[truth].mean() > 0.99
    assert sdp.kappa(truth, cluster.appeared) > sdp.kappa(truth, point.appeared)
    assert cluster.appeared_regions[0].n_points >= len(new)


def test_cluster_fraction_given_as_text_is_the_number(rng):
    # "0.5" passed the check as a number, then reached NumPy as text (a raw TypeError)
    floor = np.c_[rng.random((4000, 2)), np.zeros(4000)]
    cur = np.concatenate([floor, rng.uniform([0.4, 0.4, 0.0], [0.6, 0.6, 0.2], (500, 3))])
    kw = dict(lattice=sdp.Lattice(voxel_size=0.02), decision="cluster")
    text, number = (sdp.detect_changes(floor, cur, cluster_fraction=f, **kw) for f in ("0.5", 0.5))
    assert number.appeared.sum() > 0 and np.array_equal(text.appeared, number.appeared)


def test_far_from_origin_gives_the_same_result(scene_pair):
    reference, current, truth = scene_pair
    shift = np.array([1e6, 2e6, 100.0])  # a multiple of 8·l: the lattice phase is unchanged
    a = sdp.detect_changes(reference, current, lattice=sdp.Lattice(voxel_size=0.025))
    b = sdp.detect_changes(reference + shift, current + shift, lattice=sdp.Lattice(voxel_size=0.025))
    np.testing.assert_array_equal(a.appeared, b.appeared)
    np.testing.assert_array_equal(a.disappeared, b.disappeared)
    np.testing.assert_allclose(b.appeared_regions[0].centroid - shift, a.appeared_regions[0].centroid, atol=1e-6)
    # the paper's grid_size: the voxel is a fraction of the box, the same at both places
    c = sdp.detect_changes(reference, current, lattice=sdp.Lattice(grid_size=200))
    d = sdp.detect_changes(reference + shift, current + shift, lattice=sdp.Lattice(grid_size=200))
    assert c.voxel_size == pytest.approx(d.voxel_size, rel=1e-9)
    assert (c.appeared == d.appeared).mean() > 0.999


def test_both_fields_share_one_lattice(scene_pair):
    reference, current, _ = scene_pair
    r = sdp.detect_changes(reference, current[:1000], lattice=sdp.Lattice(grid_size=80))
    assert r.reference_field.voxel_size == r.current_field.voxel_size
    lo = np.minimum(reference.min(0), current[:1000].min(0))
    hi = np.maximum(reference.max(0), current[:1000].max(0))
    assert r.voxel_size == pytest.approx((hi - lo).max() / 80)


def test_auto_voxel_size_follows_point_spacing(rng):
    plane = np.c_[rng.random((40000, 2)), np.zeros(40000)]  # spacing ~ 1/200 = 5 mm
    sparse = plane[::16]  # spacing ~ 2 cm
    l1, l2 = sdp.auto_voxel_size(plane), sdp.auto_voxel_size(sparse)
    assert 2.5 < l2 / l1 < 6
    r = sdp.detect_changes(sparse, sparse[::-1].copy(), lattice=sdp.Lattice(voxel_size="auto"))
    assert not r.appeared.any()
    # with the automatic voxel a resampled surface is not "new"
    resampled = np.c_[rng.random((2500, 2)), np.zeros(2500)]
    assert sdp.detect_changes(sparse, resampled, lattice=sdp.Lattice(voxel_size="auto")).appeared.mean() < 0.01


def test_a_cloud_of_repeated_points_has_the_spacing_of_its_distinct_ones(rng):
    """Every point five times over: its 4th neighbour is itself again; the distinct points give the
    spacing (it was refused as having "no more than k distinct points")."""
    xyz = rng.random((20_000, 3)) * [4.0, 4.0, 0.05]
    once = sdp.auto_voxel_size(xyz)
    assert sdp.auto_voxel_size(np.repeat(xyz, 5, axis=0)) == pytest.approx(once, rel=0.1)


def test_summary_is_json_serializable(scene_pair):
    import json

    reference, current, _ = scene_pair
    s = sdp.detect_changes(reference, current, lattice=sdp.Lattice(voxel_size=0.02)).summary()
    again = json.loads(json.dumps(s))
    assert again["current"]["appeared"] > 0 and again["appeared_regions"][0]["n_points"] > 0


def test_no_change_at_all_with_a_region_size_filter(rng):
    pts = room_scene(rng, n=8000)
    r = sdp.detect_changes(pts, pts, min_region_points=10, lattice=sdp.Lattice(voxel_size=0.05))
    assert not r.appeared.any() and not r.disappeared.any() and r.appeared_regions == []


@pytest.mark.slow
def test_two_directions_on_threads_equal_one_thread(monkeypatch):
    # the directions run on two threads (map_concurrently); one at a time must give the same result
    s = office_scene(seed=3)
    kw = dict(lattice=sdp.Lattice(voxel_size="auto"), min_region_points=20,
              coverage=sdp.Coverage(sensor_origin=(0.3, 0.2, 2.2)))
    threaded = sdp.detect_changes(s.reference, s.current, **kw)
    monkeypatch.setattr(sdp.change._detect, "map_concurrently", lambda fn, items, **_: [fn(x) for x in items])
    serial = sdp.detect_changes(s.reference, s.current, **kw)
    for a, b in ((threaded.appeared, serial.appeared), (threaded.disappeared, serial.disappeared),
                 (threaded.appeared_labels, serial.appeared_labels)):
        np.testing.assert_array_equal(a, b)
    assert threaded.appeared.any() and threaded.disappeared.any()


def test_map_concurrently_keeps_order_and_raises():
    from sdp._core._parallel import map_concurrently

    assert map_concurrently(lambda x: x * x, range(5)) == [0, 1, 4, 9, 16]
    with pytest.raises(ZeroDivisionError):
        map_concurrently(lambda x: 1 / x, [1, 0])
    # a call from one of the pool's threads runs in turn instead of waiting for a thread of its own
    done = []
    outer = threading.Thread(target=lambda: done.append(map_concurrently(
        lambda x: map_concurrently(lambda y: x * y, [1, 2]), [1, 2, 3])), daemon=True)
    outer.start()
    outer.join(60)
    assert done == [[[1, 2], [2, 4], [3, 6]]]
