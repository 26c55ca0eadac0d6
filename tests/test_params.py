"""The automatic voxel size: its k-th neighbour distances against scipy's k-d tree."""

import numpy as np
import pytest
from conftest import room_scene
from scipy.spatial import cKDTree

import sdp
from sdp.fields._spacing import kth_neighbour_distance


def reference_voxel(*clouds, k=3, quantile=0.9, scale=1.5, sigma_voxels=1.5, sample=5_000, seed=0):
    """auto_voxel_size as it was first written: a k-d tree over each whole cloud."""
    rng = np.random.default_rng(seed)
    dists = []
    for pts in clouds:
        query = pts[rng.choice(len(pts), sample, replace=False)] if len(pts) > sample else pts
        if len(pts) <= k:
            continue
        dists.append(cKDTree(pts).query(query, k=k + 1)[0][:, k])
    d = np.concatenate(dists)
    d = d[d > 0]
    return scale * np.quantile(d, quantile) / sigma_voxels


def clouds(rng):
    """Clouds that push the cell grid around: surfaces, a volume, a line, sparse and dense parts,
    far outliers, two clusters far apart (a box mostly empty), exact duplicates, a handful of points."""
    plane = np.c_[rng.random((40_000, 2)), np.zeros(40_000)]
    near = rng.normal(size=(20_000, 3)) * [0.3, 0.3, 0.01]
    far = rng.normal(size=(2_000, 3)) * [3, 3, 0.01] + [0, 0, 1]  # 10x sparser, like a scan's far range
    line = np.c_[np.linspace(0, 10, 5_000), np.zeros(5_000), np.zeros(5_000)] + 1e-4 * rng.standard_normal((5_000, 3))
    return {"room": room_scene(rng, n=40_000),
            "plane": plane,
            "sparse plane": plane[::16],
            "volume": rng.random((30_000, 3)),
            "line": line,
            "dense and sparse": np.r_[near, far],
            "far outliers": np.r_[0.1 * rng.normal(size=(20_000, 3)), rng.uniform(-1e3, 1e3, (30, 3))],
            "two clusters": np.r_[0.01 * rng.random((10_000, 3)), 0.01 * rng.random((10_000, 3)) + 500],
            "duplicates": np.repeat(rng.random((3_000, 3)), 3, axis=0),
            "far from the origin": room_scene(rng, n=20_000) + [4e5, 5e6, 100.0],
            "few points": rng.random((6, 3))}


@pytest.mark.parametrize("k", [1, 4, 10])
def test_kth_neighbour_distance_equals_a_kd_tree(rng, k):
    for name, pts in clouds(rng).items():
        k_ = min(k, len(pts))
        queries = pts[rng.choice(len(pts), min(3_000, len(pts)), replace=False)]
        expected = cKDTree(pts).query(queries, k=k_)[0].reshape(len(queries), -1)[:, k_ - 1]
        np.testing.assert_allclose(kth_neighbour_distance(pts, queries, k_), expected, rtol=1e-12, atol=0,
                                   err_msg=name)


@pytest.mark.parametrize("cell", [1e-5, 1e-3, 0.05, 10.0])
def test_any_cell_size_gives_the_exact_distances(rng, cell):
    """Far too fine cells (queries go on to coarser grids) or far too coarse: same distances."""
    pts = room_scene(rng, n=20_000)
    queries = pts[:2_000]
    expected = cKDTree(pts).query(queries, k=4)[0][:, 3]
    np.testing.assert_allclose(kth_neighbour_distance(pts, queries, 4, cell=cell), expected, rtol=1e-12, atol=0)


def test_an_organized_frames_pixels_give_the_same_distances(rng):
    # a 120 × 160 pinhole camera (f = 150 px), turned and moved, over a floor seen at grazing
    # angles, a wall and a box (depth edges), with depth noise and dropouts
    from scipy.spatial.transform import Rotation

    from sdp._core._points import as_points
    from sdp.fields._spacing import auto_voxel_size_of, kth_in_image
    from sdp.io import Cloud

    c, r = np.meshgrid(np.arange(160.0), np.arange(120.0))
    rays = np.c_[(c.ravel() - 79.5) / 150, (r.ravel() - 59.5) / 150, np.ones(c.size)]
    t_floor = 1.2 / np.where(rays[:, 1] > 1e-3, rays[:, 1], np.nan)  # the floor 1.2 m below the camera
    t = np.fmin(np.where(t_floor > 0, t_floor, np.inf), 4.0)  # the wall 4 m ahead
    in_box = (np.abs(rays[:, 0]) < 0.15) & (rays[:, 1] > 0.05) & (rays[:, 1] < 0.4)
    t[in_box] = np.minimum(t[in_box], 2.0)
    t *= 1 + rng.normal(0, 0.002, t.size)
    keep = np.flatnonzero(rng.random(t.size) > 0.05)
    turn, origin = Rotation.from_euler("zx", [40, -20], degrees=True).as_matrix(), np.array([3.0, 1.0, 0.5])
    xyz = origin + (rays * t[:, None])[keep] @ turn.T
    quat = Rotation.from_matrix(turn).as_quat()  # x, y, z, w
    cloud = Cloud(xyz, viewpoint=np.r_[origin, quat[3], quat[:3]], organized=True, image=(120, 160), pixels=keep)
    pts = as_points(cloud)
    assert pts.image is not None and as_points(xyz).image is None
    d = kth_in_image(pts, np.arange(len(xyz)), 4)
    proven = ~np.isnan(d)
    assert proven.mean() > 0.95
    expected = kth_neighbour_distance(xyz, xyz, 4)  # itself and its 3 nearest others
    np.testing.assert_array_equal(d[proven], expected[proven])
    assert auto_voxel_size_of([pts], k=3) == auto_voxel_size_of([as_points(xyz)], k=3)


def test_queries_anywhere(rng):
    """Queries that are not points of the cloud, inside and outside its box."""
    pts = room_scene(rng, n=20_000)
    queries = np.r_[rng.uniform(pts.min(0), pts.max(0), (1_000, 3)), rng.uniform(-20, 20, (200, 3))]
    expected = cKDTree(pts).query(queries, k=3)[0][:, 2]
    np.testing.assert_allclose(kth_neighbour_distance(pts, queries, 3), expected, rtol=1e-12, atol=0)
    with pytest.raises(ValueError, match="k must be"):
        kth_neighbour_distance(pts[:5], queries, 6)


def test_auto_voxel_size_equals_the_kd_tree_estimate(rng):
    cs = clouds(rng)
    for name, pts in cs.items():
        if name != "few points":
            assert sdp.auto_voxel_size(pts) == pytest.approx(reference_voxel(pts), rel=1e-12), name
    assert sdp.auto_voxel_size(cs["room"], cs["sparse plane"]) == pytest.approx(
        reference_voxel(cs["room"], cs["sparse plane"]), rel=1e-12)
    assert sdp.auto_voxel_size(cs["room"], k=5, quantile=0.5, sample=1_000, seed=3) == pytest.approx(
        reference_voxel(cs["room"], k=5, quantile=0.5, sample=1_000, seed=3), rel=1e-12)


@pytest.mark.shared_data
def test_auto_voxel_size_on_real_scans(shared_data):
    """The Kinect pair and the laser scans the benchmarks use."""
    mosd = shared_data / "mosd" / "learn"
    ref, cur = sdp.read_points(mosd / "learn3.pcd").xyz, sdp.read_points(mosd / "learn4.pcd").xyz
    assert sdp.auto_voxel_size(ref, cur) == pytest.approx(reference_voxel(ref, cur), rel=1e-12)
    dlut = [sdp.read_points(shared_data / "dlut" / f"A603_{n}.pcd").xyz for n in ("reference", "rescan1")]
    assert sdp.auto_voxel_size(*dlut) == pytest.approx(reference_voxel(*dlut), rel=1e-12)
