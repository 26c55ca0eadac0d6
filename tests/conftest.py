from pathlib import Path

import numpy as np
import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def pytest_collection_modifyitems(config, items):
    """A test that takes the ``shared_data`` fixture carries the ``shared_data`` marker (so
    ``-m "not shared_data"`` leaves it out) even when its author forgot the decorator."""
    for item in items:
        if "shared_data" in getattr(item, "fixturenames", ()) and item.get_closest_marker("shared_data") is None:
            item.add_marker(pytest.mark.shared_data)


@pytest.fixture
def shared_data():
    """Path of ../shared/data; the test is skipped (with the reason shown) when it is absent."""
    if not SHARED.is_dir():
        pytest.skip(f"real scans not found at {SHARED} (CI provides ../shared/data beside the checkout)")
    return SHARED


def slow_after(n, cases):
    """Parametrize cases of which only the first ``n`` run in the quick tier (``make check``); the
    rest are marked slow (each, say, a CLI process of a second or two). Ids stay as without it."""
    return [c if i < n else pytest.param(c, marks=pytest.mark.slow) for i, c in enumerate(cases)]


def room_scene(rng, n=40_000, noise=0.003):
    """Floor, two walls and a table top sampled uniformly, with Gaussian noise (metres)."""
    m = n // 4
    parts = [np.c_[rng.uniform(0, 4, m), rng.uniform(0, 3, m), np.zeros(m)],
             np.c_[rng.uniform(0, 4, m), np.full(m, 3.0), rng.uniform(0, 2.5, m)],
             np.c_[np.zeros(m), rng.uniform(0, 3, m), rng.uniform(0, 2.5, m)],
             np.c_[rng.uniform(1, 3, m), rng.uniform(1, 2, m), np.full(m, 0.75)]]
    pts = np.concatenate(parts)
    return pts + noise * rng.standard_normal(pts.shape)


def box_surface(rng, lo, hi, n):
    """Points on the five visible faces (all but the bottom) of an axis-aligned box."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pts = rng.uniform(lo, hi, (n, 3))
    face = rng.integers(0, 5, n)
    for f in range(5):
        sel = face == f
        axis, side = divmod(f, 2) if f < 4 else (2, 1)
        pts[sel, axis] = hi[axis] if side else lo[axis]
    return pts


def write_las(path, xyz):
    """A LAS/LAZ file of ``xyz`` (1 mm scale) with an intensity per row, as scanners write them."""
    import laspy

    h = laspy.LasHeader(point_format=1, version="1.4")
    h.scales, h.offsets = [0.001] * 3, np.floor(xyz.min(axis=0))
    las = laspy.LasData(h)
    las.x, las.y, las.z = xyz.T
    las.intensity = np.arange(len(xyz)) % 60_000
    las.write(str(path))
    return path
