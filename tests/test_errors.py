import numpy as np
import pytest

import sdp
from sdp import DensityField


@pytest.mark.parametrize("points, match", [
    (np.zeros((0, 3)), "empty"),
    (np.zeros((5, 2)), r"shape \(5, 2\)"),
    ([[1, 2, 3, 4]], "shape"),
    ("abc", "numbers|shape"),
    (np.full((4, 3), np.nan), "no finite point"),
])
def test_bad_points_raise_invalid_points_error(points, match):
    with pytest.raises(sdp.InvalidPointsError, match=match):
        DensityField.from_points(points, voxel_size=0.1)
    assert issubclass(sdp.InvalidPointsError, sdp.SDPError)


def test_coordinates_too_large_for_a_spacing_are_said_so():
    huge = np.random.default_rng(0).random((50, 3)) * 1e200  # their differences overflow
    import warnings

    with warnings.catch_warnings(), pytest.raises(sdp.InvalidPointsError, match="coordinates this large"):
        warnings.simplefilter("ignore", RuntimeWarning)  # NumPy's overflow on the way
        DensityField.from_points(huge)  # it said "voxel_size must be … finite, got nan"


def test_single_point_needs_an_explicit_voxel_size():
    with pytest.raises(sdp.InvalidPointsError, match="zero extent.*voxel size"):
        DensityField.from_points([[1.0, 2.0, 3.0]], grid_size=80)
    f = DensityField.from_points([[1.0, 2.0, 3.0]], voxel_size=0.1)
    assert f.density([[1.0, 2.0, 3.0]])[0] == pytest.approx(1.0, abs=0.07)


def test_nan_rows_are_dropped_and_counted(rng):
    pts = rng.random((100, 3))
    pts[[3, 50]] = [np.nan, 0, 0]
    pts[7] = [np.inf, 1, 1]
    f = DensityField.from_points(pts, voxel_size=0.1)
    assert (f.n_points, f.n_dropped) == (97, 3)
    r = sdp.detect_changes(pts, pts, lattice=sdp.Lattice(voxel_size=0.1))
    assert r.appeared.shape == (100,) and not r.appeared[[3, 7, 50]].any()
    assert r.summary()["current"]["dropped"] == 3


def test_flat_cloud_works(rng):
    # a planar scan (zero extent along z) is a valid cloud: the grid keeps a halo around it
    pts = np.c_[rng.random((5000, 2)), np.zeros(5000)]
    f = DensityField.from_points(pts, grid_size=40)
    assert f.inside(pts).mean() > 0.95
    r = sdp.detect_changes(pts, pts + [0, 0, 0.5], lattice=sdp.Lattice(grid_size=40))
    assert r.appeared.all() and r.disappeared.all()


def test_grid_over_memory_limit_is_refused_before_allocating(rng):
    pts = np.array([[0, 0, 0], [1000.0, 1000.0, 100.0]])
    with pytest.raises(sdp.GridTooLargeError, match=r"would need [0-9.e+]+ [KMGTPE]?B.*memory limit") as err:
        DensityField.from_points(pts, voxel_size=0.001, memory_limit="1GB")
    assert isinstance(err.value, MemoryError)
    # blocks are counted too: a dense cloud at a fine voxel
    dense = rng.random((20000, 3))
    with pytest.raises(sdp.GridTooLargeError, match="blocks"):
        DensityField.from_points(dense, voxel_size=0.005, memory_limit="10MB")


def test_memory_limit_from_environment(monkeypatch):
    monkeypatch.setenv("SDP_MEMORY_LIMIT", "1MB")
    with pytest.raises(sdp.GridTooLargeError):
        DensityField.from_points(np.random.default_rng(0).random((1000, 3)), voxel_size=0.01)


def test_options_are_checked():
    pts = np.random.default_rng(0).random((10, 3))
    with pytest.raises(ValueError, match="not both"):
        DensityField.from_points(pts, voxel_size=0.1, grid_size=10)
    with pytest.raises(ValueError, match="'auto'"):
        DensityField.from_points(pts, voxel_size="fine")
    with pytest.raises(ValueError, match="positive"):
        DensityField.from_points(pts, voxel_size=-1)
    with pytest.raises(ValueError, match="method"):
        DensityField.from_points(pts, voxel_size=0.1, method="magic")
    with pytest.raises(ValueError, match="decision"):
        sdp.detect_changes(pts, pts, decision="vote")


def test_wrong_types_in_the_python_api_are_sdp_errors(rng, tmp_path):
    """Every wrong type reaching the API is refused in one line as an sdp.SDPError, before work,
    not a TypeError, ValueError or AttributeError from inside."""
    a = np.c_[rng.uniform(0, 5, (3000, 2)), 0.01 * rng.standard_normal(3000)]
    cases = [lambda: sdp.detect_changes(a, a, min_region_points="five"),
             lambda: sdp.distances(a, a, corner=(1, 2)),
             lambda: sdp.series([a, a], output=tmp_path / "s.zarr", cylinder={"projection_scale": 1}),
             lambda: sdp.read_points(5),
             lambda: sdp.read_points(None)]
    for case in cases:
        with pytest.raises(sdp.SDPError):
            case()
    assert not (tmp_path / "s.zarr").exists()
    ds = sdp.series([a, a + [0, 0, 0.01], a], output=tmp_path / "t.zarr")
    with pytest.raises(sdp.SDPError, match="chunks"):
        sdp.open_series(tmp_path / "t.zarr", chunks="bogus")
    assert ds.sizes["epoch"] == 3
    # a whole number as text is that number, as on the command line (it was compared as text)
    assert sdp.detect_changes(a, a + 0.3, min_region_points="5").appeared.sum() == \
        sdp.detect_changes(a, a + 0.3, min_region_points=5).appeared.sum()


def test_query_shape_is_checked(rng):
    f = DensityField.from_points(rng.random((10, 3)), voxel_size=0.1)
    with pytest.raises(sdp.InvalidPointsError, match="shape"):
        f.density(np.zeros((4, 2)))


def test_a_far_outlier_is_named_as_what_makes_the_grid_too_large():
    room = np.random.default_rng(0).random((5_000, 3)) * [4.0, 4.0, 2.5]
    with pytest.raises(sdp.GridTooLargeError, match="the points span 1000 at a voxel of .*remove far outliers"):
        DensityField.from_points(np.r_[room, [[1000.0, 1000.0, 1000.0]]], voxel_size=0.05)
