"""The Numba k-d tree of the sensor test's plane fits against scipy's cKDTree, and the field of
view's hull against Qhull's."""

import numpy as np
import pytest
from conftest import room_scene
from scipy.spatial import ConvexHull, cKDTree

from sdp._core._kdtree import k_nearest
from sdp.change._range_image import _hull_polygon


def clouds(rng):
    plane = np.c_[rng.random((8_000, 2)), np.zeros(8_000)]
    return {"room": room_scene(rng, n=20_000), "plane": plane, "volume": rng.random((5_000, 3)),
            "line": np.c_[np.linspace(0, 1, 3_000), np.zeros((3_000, 2))] + 1e-6 * rng.standard_normal((3_000, 3)),
            "far outliers": np.r_[0.01 * rng.normal(size=(5_000, 3)), rng.uniform(-1e3, 1e3, (20, 3))],
            "far from the origin": room_scene(rng, n=5_000) + [4e5, 5e6, 100.0],
            "few points": rng.random((7, 3))}


@pytest.mark.parametrize("k", [1, 4, 50])
def test_k_nearest_equals_a_kd_tree(rng, k):
    """Same neighbours in the same order as cKDTree, for queries on and off the points (clouds
    without equal distances: ties are ordered by row here, arbitrarily there)."""
    for name, pts in clouds(rng).items():
        k_ = min(k, len(pts))
        queries = np.r_[pts[rng.choice(len(pts), min(500, len(pts)), replace=False)],
                        rng.uniform(pts.min(0) - 1, pts.max(0) + 1, (200, 3))]
        _, expected = cKDTree(pts).query(queries, k=k_)
        np.testing.assert_array_equal(k_nearest(pts, queries, k_), expected.reshape(len(queries), k_), err_msg=name)


def test_a_deep_tree(rng):
    """Points at 2⁻ⁱ along a line: each split at a box's middle peels off two of them, so the tree
    is about a hundred levels deep."""
    pts = np.c_[2.0 ** -np.arange(240), np.zeros((240, 2))]
    queries = np.r_[pts[::3], rng.random((50, 3))]
    _, expected = cKDTree(pts).query(queries, k=10)
    np.testing.assert_array_equal(k_nearest(pts, queries, 10), expected)


def test_a_box_too_thin_to_split_at_its_middle():
    """Coordinates one float apart: the box's middle rounds onto one of them, every point falls on
    one side, and the node is split at the median instead."""
    x = np.repeat([1.0, np.nextafter(1.0, 2.0)], 100)
    pts = np.c_[x, np.zeros((200, 2))]
    queries = np.array([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    idx = k_nearest(pts, queries, 120)
    d = np.linalg.norm(pts[idx] - queries[:, None], axis=2)
    np.testing.assert_array_equal(d, cKDTree(pts).query(queries, k=120)[0])
    assert all(len(set(row)) == 120 for row in idx.tolist())


def test_ties_come_in_index_order(rng):
    """Repeated points are at equal distances: nearest first, then by row (cKDTree's tie order is
    unspecified, so the distances are compared, and the rows of each tie must ascend)."""
    pts = np.repeat(rng.random((300, 3)), 4, axis=0)
    queries = rng.random((100, 3))
    idx = k_nearest(pts, queries, 12)
    d = np.linalg.norm(pts[idx] - queries[:, None], axis=2)
    np.testing.assert_allclose(d, cKDTree(pts).query(queries, k=12)[0], rtol=0, atol=1e-12)
    assert np.all(np.diff(d, axis=1) >= 0)
    assert np.all(np.diff(idx, axis=1)[np.diff(d, axis=1) == 0] > 0)
    with pytest.raises(ValueError, match="k must be"):
        k_nearest(pts[:5], queries, 6)


def test_hull_polygon_equals_qhull(rng):
    """The field of view's hull: Qhull's vertices, in its (counter-clockwise) order."""
    for _ in range(100):
        pts = np.round(rng.normal(size=(rng.integers(4, 300), 2)) * 20) / 2 + 0.5
        pts = pts[np.lexsort((pts[:, 1], pts[:, 0]))]
        hull = _hull_polygon(pts)
        expected = pts[ConvexHull(pts).vertices]
        start = int(np.flatnonzero((expected == hull[0]).all(axis=1))[0])
        np.testing.assert_array_equal(hull, np.roll(expected, -start, axis=0))
