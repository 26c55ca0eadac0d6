"""Properties of the field algebra, checked by Hypothesis on small random clouds.

Clouds are drawn from a seed and a few shape parameters (a blob, a plane, or both), so every
example is a plausible scan, not a pile of degenerate rows. Fields use a fixed voxel size: the
lattice is then global, and two fields share their nodes (Boolean results are exact there).
"""

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import sdp
from sdp import BLOCK, DensityField

VOXEL = 0.05
SETTINGS = settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@st.composite
def clouds(draw, min_points=30, max_points=400):
    """(n, 3) float64 points: a Gaussian blob, a noisy plane, or both, somewhere near the origin."""
    seed = draw(st.integers(0, 2**32 - 1))
    n = draw(st.integers(min_points, max_points))
    kind = draw(st.sampled_from(["blob", "plane", "both"]))
    centre = np.array(draw(st.tuples(*[st.floats(-2, 2)] * 3)))
    spread = draw(st.floats(0.05, 0.6))
    rng = np.random.default_rng(seed)
    blob = centre + spread * rng.standard_normal((n, 3))
    plane = np.c_[centre[:2] + spread * rng.uniform(-2, 2, (n, 2)), np.full(n, centre[2])]
    plane[:, 2] += 0.003 * rng.standard_normal(n)
    pts = {"blob": blob, "plane": plane, "both": np.concatenate([blob[: n // 2], plane[n // 2:]])}[kind]
    return pts


def _field(pts, **kw):
    return DensityField.from_points(pts, voxel_size=VOXEL, **kw)


def _nodes(*fields, n=400, seed=0):
    """World positions of nodes of the fields' blocks (a sample, plus a margin of empty space)."""
    keys = np.unique(np.concatenate([f.global_keys for f in fields]), axis=0)
    rng = np.random.default_rng(seed)
    lo, hi = keys.min(axis=0) * BLOCK - 4, (keys.max(axis=0) + 1) * BLOCK + 4
    return rng.integers(lo, hi, (n, 3)) * VOXEL


@SETTINGS
@given(clouds(), clouds())
def test_boolean_operations_are_min_max_at_the_nodes(pa, pb):
    a, b = _field(pa), _field(pb)
    q = _nodes(a, b)
    fa, fb = a.field(q), b.field(q)
    tol = 1e-5 * (1 + max(np.abs(fa).max(), np.abs(fb).max()))
    np.testing.assert_allclose(sdp.union(a, b).field(q), np.minimum(fa, fb), rtol=0, atol=tol)
    np.testing.assert_allclose(sdp.intersection(a, b).field(q), np.maximum(fa, fb), rtol=0, atol=tol)
    np.testing.assert_allclose(sdp.difference(a, b).field(q), np.maximum(fa, -fb), rtol=0, atol=tol)


@SETTINGS
@given(clouds(), clouds())
def test_union_and_intersection_commute(pa, pb):
    a, b = _field(pa), _field(pb)
    for op in (sdp.union, sdp.intersection):
        ab, ba = op(a, b), op(b, a)
        np.testing.assert_array_equal(ab.global_keys, ba.global_keys)
        np.testing.assert_array_equal(ab.node_values(ab.global_keys), ba.node_values(ab.global_keys))
        assert ab.h == ba.h


@SETTINGS
@given(clouds())
def test_a_minus_a_is_empty_and_a_union_a_is_a(pts):
    a = _field(pts)
    d = sdp.difference(a, a)
    assert np.all(d.h - d.node_values(d.global_keys) >= 0)  # |F| at every node: nothing inside
    assert not d.inside(pts).any()
    u = sdp.union(a, a)
    keys = a.global_keys
    np.testing.assert_allclose(u.h - u.node_values(keys), a.h - a.node_values(keys), rtol=0, atol=1e-5 * (1 + a.h))
    q = _nodes(a)
    np.testing.assert_allclose(u.field(q), a.field(q), rtol=0, atol=1e-4 * (1 + a.h))


@SETTINGS
@given(clouds(), clouds(), st.sampled_from(["exact", "fast"]))
def test_accumulate_then_subtract_returns_the_field(pa, pb, method):
    a, b = _field(pa, method=method), _field(pb, method=method)
    q = np.concatenate([pa, pb, _nodes(a, b, n=200)])
    before = a.density(q)
    both = a.copy().accumulate(b)
    tol = 1e-5 * (1 + np.abs(both.density(q)).max())
    # G is linear in the points: accumulating b's field is building from both clouds
    np.testing.assert_allclose(both.density(q), _field(np.concatenate([pa, pb]), method=method).density(q),
                               rtol=0, atol=tol)
    back = both.accumulate(b, weight=-1.0)
    np.testing.assert_allclose(back.density(q), before, rtol=0, atol=tol)
    assert back.n_points == a.n_points


@SETTINGS
@given(clouds(), st.tuples(*[st.integers(-40, 40)] * 3), st.sampled_from(["exact", "fast"]))
def test_shifting_by_whole_blocks_shifts_the_field(pts, blocks, method):
    shift = np.array(blocks) * BLOCK * VOXEL
    a, b = _field(pts, method=method), _field(pts + shift, method=method)
    rng = np.random.default_rng(1)
    between = _nodes(a, n=100) + VOXEL * rng.random((100, 3))  # inside cells, not only at nodes
    q = np.concatenate([pts, pts + 0.1 * rng.standard_normal(pts.shape), between])
    ga, gb = a.density(q), b.density(q + shift)
    np.testing.assert_allclose(gb, ga, rtol=0, atol=1e-5 * (1 + ga.max()))
    assert a.n_blocks == b.n_blocks


@SETTINGS
@given(clouds(100, 600), clouds(100, 600), st.booleans())
def test_change_masks_swap_with_the_clouds(pa, pb, coverage):
    opts = dict(lattice=sdp.Lattice(voxel_size=VOXEL), coverage=sdp.Coverage(sensor_origin=None, enabled=coverage),
                min_region_points=5)
    ab, ba = sdp.detect_changes(pa, pb, **opts), sdp.detect_changes(pb, pa, **opts)
    np.testing.assert_array_equal(ab.appeared, ba.disappeared)
    np.testing.assert_array_equal(ab.disappeared, ba.appeared)
    np.testing.assert_array_equal(ab.current_not_comparable, ba.reference_not_comparable)
    assert len(ab.appeared_regions) == len(ba.disappeared_regions)


def test_the_properties_hold_on_a_known_change(rng):
    """A fixed example of the last property, so a failure there is not only ever a random one."""
    ref = rng.random((2000, 3))
    cur = np.concatenate([ref, [0.5, 0.5, 1.4] + 0.05 * rng.standard_normal((300, 3))])
    ab = sdp.detect_changes(ref, cur, lattice=sdp.Lattice(voxel_size=VOXEL),
                            coverage=sdp.Coverage(sensor_origin=None, enabled=False))
    ba = sdp.detect_changes(cur, ref, lattice=sdp.Lattice(voxel_size=VOXEL),
                            coverage=sdp.Coverage(sensor_origin=None, enabled=False))
    assert ab.appeared[2000:].mean() > 0.9 and not ab.disappeared.any()
    np.testing.assert_array_equal(ab.appeared, ba.disappeared)
