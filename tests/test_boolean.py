import numpy as np
import pytest

import sdp
from sdp import DensityField, difference, intersection, union


@pytest.fixture
def two_fields(rng):
    a = rng.normal([0, 0, 0], 0.3, (4000, 3))
    b = rng.normal([0.4, 0, 0], 0.3, (4000, 3))
    fa = DensityField.from_points(a, voxel_size=0.05)
    fb = DensityField.from_points(b, voxel_size=0.05)
    q = rng.uniform(-1.5, 2.0, (20000, 3))
    return fa, fb, q


def test_boolean_identities(two_fields):
    fa, fb, q = two_fields
    ia, ib = fa.inside(q), fb.inside(q)
    assert ia.sum() > 500 and ib.sum() > 500 and (ia & ib).sum() > 100
    u, i, d = union(fa, fb).inside(q), intersection(fa, fb).inside(q), difference(fa, fb).inside(q)
    # exact at the nodes; interpolation can differ within one cell of the boundary
    assert (u | ~(ia | ib)).mean() > 0.995 and (u >= ia).mean() > 0.995 and (u >= ib).mean() > 0.995
    assert (~i | (ia & ib)).mean() > 0.995
    assert not (d & ib).sum() > 0.005 * len(q)
    assert (d <= ia).mean() > 0.995
    assert d.sum() > 100


def test_boolean_is_exact_at_shared_nodes(two_fields):
    fa, fb, _ = two_fields
    d = difference(fa, fb)
    keys = d.global_keys
    fa_n = fa.h - fa.node_values(keys)
    fb_n = fb.h - fb.node_values(keys)
    np.testing.assert_allclose(d.h - d.node_values(keys), np.maximum(fa_n, -fb_n), atol=1e-5)
    u = union(fa, fb)
    np.testing.assert_allclose(u.h - u.node_values(keys), np.minimum(fa_n, fb_n), atol=1e-5)


def test_boolean_results_are_fields(tmp_path, two_fields):
    fa, fb, q = two_fields
    u = union(fa, fb)
    assert u.method == "union" and u.voxel_size == fa.voxel_size
    g = DensityField.load(u.save(tmp_path / "u.sdpf"))
    np.testing.assert_array_equal(g.field(q), u.field(q))
    assert u.mesh().area > fa.mesh().area  # the union's boundary encloses more than either part


def test_far_from_both_fields_the_result_is_outside(two_fields):
    fa, fb, _ = two_fields
    for op in (union, intersection, difference):
        r = op(fa, fb)
        assert r.field([[100.0, 100.0, 100.0]])[0] > 0


def test_mismatched_voxel_sizes_are_refused(rng):
    fa = DensityField.from_points(rng.random((100, 3)), voxel_size=0.05)
    fb = DensityField.from_points(rng.random((100, 3)), voxel_size=0.06)
    with pytest.raises(sdp.IncompatibleFieldsError, match="same voxel size"):
        union(fa, fb)


def test_fields_far_apart_are_refused_before_their_directory_is_allocated(rng):
    a = DensityField.from_points(rng.random((300, 3)), voxel_size=0.01)
    b = DensityField.from_points(rng.random((300, 3)) + [5e6, 0, 0], voxel_size=0.01)
    for op in (union, intersection, difference):
        with pytest.raises(sdp.GridTooLargeError, match="the fields span 5e\\+06 units together"):
            op(a, b)


@pytest.mark.slow
def test_difference_volume_equals_the_stored_difference(two_fields, rng):
    """Change detection evaluates max(F_a, -F_b) node by node (regions.Volume); the tiled path and
    the Boolean API store it. Both must give the same values, signs and regions, bit for bit."""
    from sdp.change._regions import Volume, label_points, label_volume
    from sdp.fields._boolean import difference_on_own_blocks

    a, b, _ = two_fields
    stored = difference_on_own_blocks(a, b)
    volume = Volume.difference(a, b)
    # points across a's box, many in cells that straddle blocks or reach past a's blocks
    lo, hi = a.grid.origin, a.grid.origin + np.asarray(a.grid.shape) * a.voxel_size
    pts = lo + rng.random((20_000, 3)) * (hi - lo)
    np.testing.assert_array_equal(volume.at(a, pts), a.interpolate(stored, pts))
    # the masks' sign-only evaluation: the same signs, also where it exits early (inside b)
    on_points = np.concatenate([pts, rng.normal([0.2, 0.0, 0.0], 0.3, (20_000, 3))])
    np.testing.assert_array_equal(volume.negative_at(a, on_points), volume.at(a, on_points) < 0)
    assert volume.negative_at(a, on_points).sum() > 1000 and (a.inside(on_points) & b.inside(on_points)).sum() > 1000
    labels, counts = label_volume(a, volume, pts)
    expected_labels, expected_counts = label_points(a, stored, pts)
    assert (stored < 0).any() and len(counts) > 0
    np.testing.assert_array_equal(labels, expected_labels)
    np.testing.assert_array_equal(counts, expected_counts)


def test_a_boolean_result_is_flagged_and_refuses_what_needs_a_density(tmp_path, two_fields):
    fa, fb, _ = two_fields
    for op in (union, intersection, difference):
        r = op(fa, fb)
        assert r.is_boolean and r.method == op.__name__
        assert DensityField.load(r.save(tmp_path / "r.sdpf")).is_boolean  # the flag is the saved method
        with pytest.raises(sdp.IncompatibleFieldsError, match=f"coarsen.*{op.__name__}"):
            r.coarsen()
        with pytest.raises(sdp.IncompatibleFieldsError, match="accumulate"):
            r.copy().accumulate(fa)
        with pytest.raises(sdp.IncompatibleFieldsError, match="accumulate"):
            fa.copy().accumulate(r)
        with pytest.raises(sdp.IncompatibleFieldsError, match=f"scale.*{op.__name__}"):
            r.copy().scale(0.5)
        with pytest.raises(sdp.IncompatibleFieldsError, match=f"footprint.*{op.__name__}"):
            r.footprint([[0.0, 0.0, 0.0]])
    # a union or intersection moves with the threshold; a difference is refused
    high = np.random.default_rng(1).random((2000, 3))
    for op in (union, intersection):
        moved = op(fa, fb).with_threshold(k=30)
        assert np.array_equal(moved.inside(high), op(fa.with_threshold(k=30), fb.with_threshold(k=30)).inside(high))
    with pytest.raises(sdp.IncompatibleFieldsError, match="set it on both fields"):
        difference(fa, fb).with_threshold(k=30)
    assert not (fa.is_boolean or fa.coarsen().is_boolean or fa.with_threshold(k=4).is_boolean)
