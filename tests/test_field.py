import math

import numpy as np
import pytest

import sdp
import sdp.fields._density
from sdp import DensityField


def brute_force(points, queries, sigma, cutoff):
    d = queries[:, None, :] - points[None]
    g = np.exp(-(d**2).sum(-1) / (2 * sigma**2))
    g[~(np.abs(d) <= cutoff).all(-1)] = 0.0
    return g.sum(1)


def node_positions(field, every=37):
    dense, origin = field.to_dense()
    idx = np.argwhere(np.ones(dense.shape, bool))[::every]
    return dense[tuple(idx.T)], idx * field.voxel_size + origin


@pytest.mark.parametrize("seed", [0, 1])
def test_exact_splat_equals_brute_force_sum(seed):
    rng = np.random.default_rng(seed)
    pts = rng.random((200, 3)) * [2.0, 1.5, 1.0] - 0.3
    f = DensityField.from_points(pts, voxel_size=0.1, method="exact")
    values, xyz = node_positions(f)
    expected = brute_force(pts, xyz, f.sigma, f.truncate * f.sigma)
    assert expected.max() > 3  # the comparison covers dense parts
    np.testing.assert_allclose(values, expected, rtol=1e-5, atol=1e-5)


def test_peak_is_one_for_a_lone_point():
    # the fast path keeps each point's mass, not its exact shape: a lone point peaks within 7 %
    f = DensityField.from_points([[0.3, 0.2, 0.1]], voxel_size=0.05)
    assert f.density([[0.3, 0.2, 0.1]])[0] == pytest.approx(1.0, abs=0.07)
    e = DensityField.from_points([[0.3, 0.2, 0.1]], voxel_size=0.05, method="exact")
    assert e.density([[0.3, 0.2, 0.1]])[0] == pytest.approx(1.0, abs=1e-6)
    # at distance sigma the kernel is e^-1/2
    assert e.density([[0.3 + e.sigma, 0.2, 0.1]])[0] == pytest.approx(math.exp(-0.5), abs=1e-6)


@pytest.mark.parametrize("kind", ["volume", "surface"])
def test_fast_path_departs_from_exact_sum_by_less_than_2_percent_of_peak(rng, kind):
    if kind == "volume":
        pts, l = rng.random((3000, 3)) * 2, 0.1
    else:
        pts, l = np.c_[rng.random((20000, 2)) * 2, 0.01 * rng.standard_normal(20000)], 0.02
    exact, _ = DensityField.from_points(pts, voxel_size=l, method="exact").to_dense()
    fast, _ = DensityField.from_points(pts, voxel_size=l, method="fast").to_dense()
    assert np.abs(fast - exact).max() < 0.02 * exact.max()
    h = sdp.threshold(3)
    assert ((fast > h) == (exact > h)).mean() > 0.995


def test_trilinear_query_equals_nodes_and_is_linear_between(rng):
    pts = rng.random((500, 3))
    f = DensityField.from_points(pts, voxel_size=0.07)
    values, xyz = node_positions(f, every=11)
    np.testing.assert_allclose(f.density(xyz), values, rtol=1e-6, atol=1e-6)
    # along an edge between two nodes the query is the straight line between them
    i = np.argmax(values)
    a, b = xyz[i], xyz[i] + [f.voxel_size, 0, 0]
    t = np.linspace(0, 1, 9)[:, None]
    line = f.density(a + t * (b - a))
    np.testing.assert_allclose(line, line[0] + t[:, 0] * (line[-1] - line[0]), rtol=1e-5, atol=1e-5)


def test_query_outside_grid_is_zero_and_nan_propagates(rng):
    f = DensityField.from_points(rng.random((100, 3)), voxel_size=0.1)
    out = f.density([[50.0, 0, 0], [-1e9, 3, 3], [np.nan, 0, 0]])
    assert out[0] == 0 and out[1] == 0 and np.isnan(out[2])
    assert not f.inside([[np.nan, 0, 0]])[0]


def test_threshold_and_field():
    assert sdp.threshold(3) == pytest.approx(1 + 3 * math.exp(-0.5))
    f = DensityField.from_points([[0, 0, 0], [0.01, 0, 0]], voxel_size=0.05, k=3)
    q = np.array([[0.005, 0, 0]])
    assert f.field(q)[0] == pytest.approx(f.h - f.density(q)[0])
    g = f.with_threshold(h=1.5)
    assert g.h == 1.5 and g.inside(q)[0] and not f.inside(q)[0]


def test_sparse_storage_follows_occupied_surface_not_box(rng):
    # two small clusters 20 m apart at 1 cm voxels: a dense box would hold 8e9 nodes
    a = rng.normal(0, 0.02, (1000, 3))
    pts = np.concatenate([a, a + [20.0, 20.0, 20.0]])
    f = DensityField.from_points(pts, voxel_size=0.01)
    assert f.n_blocks <= 2 * 6**3
    dense_bytes = 4 * np.prod(np.asarray(f.grid.shape, float))
    assert f.nbytes < dense_bytes / 100  # the block directory costs 1/128 byte per box node
    assert f.density([[20, 20, 20]])[0] > 10


@pytest.mark.slow
def test_block_layout_matches_dense_reference(rng):
    # every allocated node equals the exact sum computed densely with numpy over the box
    pts = rng.random((300, 3)) * 0.5
    f = DensityField.from_points(pts, voxel_size=0.05, method="exact")
    dense, origin = f.to_dense()
    axes = [origin[d] + np.arange(dense.shape[d]) * f.voxel_size for d in range(3)]
    xyz = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    expected = brute_force(pts, xyz, f.sigma, f.truncate * f.sigma).reshape(dense.shape)
    np.testing.assert_allclose(dense, expected, rtol=1e-5, atol=1e-5)


def test_grid_size_is_the_papers_parameterization(rng):
    pts = rng.random((1000, 3)) * [4.0, 2.0, 1.0]
    f = DensityField.from_points(pts, grid_size=80)
    assert f.voxel_size == pytest.approx(np.ptp(pts[:, 0]) / 80)
    assert f.sigma == pytest.approx(2 * f.voxel_size)
    origin_in_voxels = f.grid.origin / f.voxel_size
    np.testing.assert_allclose(origin_in_voxels, np.round(origin_in_voxels), atol=1e-6)


def test_save_load_round_trip_is_exact(tmp_path, rng):
    f = DensityField.from_points(rng.random((2000, 3)) + 1e6, voxel_size=0.05, k=4)
    path = f.save(tmp_path / "f.sdpf")
    g = DensityField.load(path)
    assert (g.h, g.sigma, g.voxel_size, g.truncate, g.n_points, g.method) == \
           (f.h, f.sigma, f.voxel_size, f.truncate, f.n_points, f.method)
    np.testing.assert_array_equal(g.grid.block_origin, f.grid.block_origin)
    np.testing.assert_array_equal(g.blocks.values, f.blocks.values)
    q = rng.random((100, 3)) + 1e6
    np.testing.assert_array_equal(g.density(q), f.density(q))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.sdpf"]  # no temporary left


def test_load_rejects_bad_files(tmp_path):
    bad = tmp_path / "bad.sdpf"
    bad.write_bytes(b"not a zip")
    with pytest.raises(sdp.FieldFileError, match="bad.sdpf"):
        DensityField.load(bad)
    with pytest.raises(sdp.FieldFileError, match="no such file"):
        DensityField.load(tmp_path / "missing.sdpf")


def test_coarsen_matches_a_field_built_at_twice_the_voxel(rng):
    pts = rng.random((4000, 3)) * [2, 2, 0.2]
    fine = DensityField.from_points(pts, voxel_size=0.02, method="exact")
    coarse = fine.coarsen()
    direct = DensityField.from_points(pts, voxel_size=0.04, method="exact")
    assert coarse.voxel_size == pytest.approx(0.04) and coarse.sigma == pytest.approx(direct.sigma)
    q = pts[rng.choice(len(pts), 500)] + rng.normal(0, 0.02, (500, 3))
    a, b = coarse.density(q), direct.density(q)
    assert np.abs(a - b).max() < 0.03 * b.max()


@pytest.mark.parametrize("method", ["fast", "exact"])
def test_building_in_chunks_gives_the_same_field(rng, monkeypatch, method):
    import sdp.fields._density

    pts = rng.random((5000, 3))
    whole = DensityField.from_points(pts, voxel_size=0.05, method=method)
    monkeypatch.setattr(sdp.fields._density, "_CHUNK", 777)  # large clouds are binned chunk by chunk
    chunked = DensityField.from_points(pts, voxel_size=0.05, method=method)
    np.testing.assert_allclose(chunked.density(pts), whole.density(pts), rtol=1e-5)


@pytest.mark.parametrize("method", ["fast", "exact"])
def test_building_two_clouds_at_once_gives_each_field_bit_for_bit(rng, method):
    from sdp._core._points import as_points
    from sdp.fields._density import build_fields

    a, b = rng.random((4000, 3)), rng.random((3000, 3)) + 0.3
    b[::97] = np.nan  # counted as dropped, as from_points does
    opts = dict(voxel_size=0.04, sigma_voxels=1.5, method=method)
    (fa, fb), seconds = build_fields([as_points(a), as_points(b)], **opts)
    for got, pts in ((fa, a), (fb, b)):
        want = DensityField.from_points(pts, **opts)
        assert np.array_equal(got.blocks.values, want.blocks.values)
        assert np.array_equal(got.blocks.keys, want.blocks.keys)
        assert (got.n_points, got.n_dropped, got.method) == (want.n_points, want.n_dropped, want.method)
    assert fb.n_dropped == 31 and len(seconds) == 2 and all(np.isfinite(seconds)) and min(seconds) >= 0

@pytest.mark.parametrize("chunk", [None, 1777])
def test_a_cloud_built_alone_on_two_threads_gives_its_field_bit_for_bit(rng, monkeypatch, chunk):
    # a cloud built alone marks its blocks in two halves and bins in two slabs along x at once
    import sdp.fields._density as density

    pts = rng.random((6000, 3)) * [1.0, 0.5, 0.3]
    monkeypatch.setattr(density, "_SPLIT_POINTS", 1000)
    if chunk:
        monkeypatch.setattr(density, "_CHUNK", chunk)
    monkeypatch.setattr(density, "concurrent", lambda **_: False)
    one = DensityField.from_points(pts, voxel_size=0.02, sigma_voxels=1.5)
    monkeypatch.setattr(density, "concurrent", lambda **_: True)
    slabs = density._slabs(pts, one.grid.origin[0], one.voxel_size)
    two = DensityField.from_points(pts, voxel_size=0.02, sigma_voxels=1.5)
    assert slabs[0][1] % 8 == 0 and 0 < slabs[0][1] < one.grid.shape[0]  # a block's face inside the grid
    assert np.array_equal(two.blocks.keys, one.blocks.keys)
    assert np.array_equal(two.blocks.values, one.blocks.values)
    assert two.h == one.h == sdp.fields._density.threshold() and two.n_points == 6000



@pytest.mark.parametrize("sigma_voxels", [0.5, 1.0, 2.0, 3.7])
def test_allocated_blocks_are_exactly_those_the_kernels_reach(rng, sigma_voxels):
    from sdp.fields._lattice import BLOCK

    pts = rng.random((300, 3)) * [1.0, 0.6, 0.3]
    f = DensityField.from_points(pts, voxel_size=0.013, sigma_voxels=sigma_voxels)
    reach = int(math.ceil(3.0 * sigma_voxels))
    i = np.floor(f.grid.to_grid_units(pts)).astype(int)
    expected = set()
    for lo, hi in zip((i - reach) // BLOCK, (i + reach + 1) // BLOCK, strict=False):
        expected.update(tuple(lo + d) for d in np.ndindex(*(hi - lo + 1)))
    assert set(map(tuple, f.blocks.keys)) == expected


@pytest.mark.parametrize("sigma_voxels", [1.0, 2.0])
def test_fast_build_is_trilinear_binning_then_a_separable_blur(rng, sigma_voxels):
    from scipy.ndimage import correlate1d

    pts = rng.random((3000, 3)) * [0.8, 0.5, 0.4]
    f = DensityField.from_points(pts, voxel_size=0.01, sigma_voxels=sigma_voxels)
    dense, _ = f.to_dense()
    u = f.grid.to_grid_units(pts)
    i, t = np.floor(u).astype(int), u - np.floor(u)
    binned = np.zeros(dense.shape)
    for corner in np.ndindex(2, 2, 2):
        c = np.array(corner)
        w = np.prod(np.where(c, t, 1 - t), axis=1)
        np.add.at(binned, tuple((i + c).T), w)
    s = math.sqrt(sigma_voxels**2 - 1 / 6)
    j = np.arange(-int(3 * sigma_voxels), int(3 * sigma_voxels) + 1)
    taps = np.exp(-j**2 / (2 * s * s)) * sigma_voxels / s
    expected = binned
    for axis in range(3):
        expected = correlate1d(expected, taps, axis=axis, mode="constant")
    np.testing.assert_allclose(dense, expected, rtol=1e-5, atol=1e-5 * expected.max())


@pytest.mark.parametrize("sigma_voxels", [0.5, 1.0, 1.5])
def test_unrolled_blur_equals_the_looped_one_bit_for_bit(rng, sigma_voxels):
    from sdp.fields._kernels import SHORT_TAPS, blur_pass, blur_pass_short

    # three clumps: lines of blocks with gaps, blocks written or not, neighbours on either side
    pts = np.concatenate([rng.normal(c, 0.02, (500, 3)) for c in ([0, 0, 0], [0.2, 0.05, 0.1], [0.05, 0.3, 0.0])])
    field, touched, taps = DensityField._binned(sdp._core._points.as_points(pts), voxel_size=0.006,
                                                sigma_voxels=sigma_voxels, k=3, h=None, truncate=3.0,
                                                method="fast", memory_limit=None)
    assert len(taps) <= SHORT_TAPS
    results = []
    for kernel in (blur_pass, blur_pass_short):
        values, nonzero = field.blocks.values.copy(), touched.copy()
        for axis in range(3):
            kernel(values, nonzero, field.blocks.directory, axis, taps)
        results.append(values)
    assert results[0].any()
    assert np.array_equal(results[0].view(np.uint32), results[1].view(np.uint32))


def test_regions_are_the_6_connected_components_of_the_negative_nodes(rng):
    from scipy.ndimage import label

    from sdp.change._regions import label_points

    centres = rng.random((40, 3)) * [0.5, 0.4, 0.3]  # 32 components, some merged, over ~1000 blocks
    pts = np.concatenate([rng.normal(c, 0.008, (60, 3)) for c in centres])
    f = DensityField.from_points(pts, voxel_size=0.005)
    values = f.h - f.blocks.values
    point_labels, node_counts = label_points(f, values, pts)
    dense = f.h - f.to_dense()[0]
    expected, n = label(dense < 0)  # 6-connectivity
    assert len(node_counts) == n > 20
    assert sorted(node_counts) == sorted(np.bincount(expected.ravel())[1:])
    # a point lies in the component of its cell's lowest negative corner
    u = np.floor(f.grid.to_grid_units(pts)).astype(int)
    corners = np.stack([u + c for c in np.ndindex(2, 2, 2)], axis=1)
    v = np.where(expected[tuple(corners.T)].T > 0, dense[tuple(corners.T)].T, np.inf)
    best = expected[tuple(corners[np.arange(len(pts)), v.argmin(axis=1)].T)]
    has = np.isfinite(v.min(axis=1))
    assert np.array_equal(point_labels >= 0, has)
    # the same partition of the points (numbering differs)
    pairs = set(zip(point_labels[has], best[has], strict=False))
    assert len(pairs) == len(set(point_labels[has])) == len(set(best[has]))


def test_regions_of_a_speckled_volume_match_scipy(rng):
    """Components made of many short runs of nodes, crossing blocks along every axis."""
    from scipy.ndimage import label

    from sdp.change._regions import label_points

    f = DensityField.from_points(rng.random((300, 3)) * 0.2, voxel_size=0.005)
    speckled = f.copy()
    speckled.blocks.values[:] = rng.random(speckled.blocks.values.shape) < 0.3  # G = 1 at 30 % of the nodes
    point_labels, node_counts = label_points(speckled, 0.5 - speckled.blocks.values, np.zeros((0, 3)))
    expected, n = label(speckled.to_dense()[0] > 0.5)
    assert len(node_counts) == n > 1000
    assert sorted(node_counts) == sorted(np.bincount(expected.ravel())[1:])
