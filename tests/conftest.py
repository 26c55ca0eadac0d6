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


def picture(path):
    """A PNG written by :mod:`sdp.viz` (a path, or its bytes) as an (H, W, 3) array of RGB in [0, 1],
    refused when it is blank (one flat colour, or next to nothing drawn on the white)."""
    import io

    import matplotlib.image as mpimg

    img = mpimg.imread(io.BytesIO(path) if isinstance(path, bytes) else path, format="png")[..., :3]
    assert (img.min(axis=-1) < 0.9).mean() > 0.005 and img[::4, ::4].std() > 0.02, "a blank picture"
    return img


def drawn_pixels(img, colour, *, min_alpha=0.3, tolerance=0.08):
    """Pixels of ``img`` painted in ``colour`` (a hex string: the constants of :mod:`sdp.viz._render`)
    at an opacity of ``min_alpha`` or more over white (points are drawn half transparent, and
    anti-aliased), not counting the legend's marker of that colour, the largest patch of it (a
    legend's marker is drawn six to eight times a point's size)."""
    from matplotlib.colors import to_rgb
    from scipy.ndimage import label

    ink = 1.0 - np.array(to_rgb(colour))
    # only pixels dark enough in some channel can be the colour at min_alpha (the white and the 3-D
    # views' pale panes are most of a picture)
    rows, cols = np.nonzero(img.min(axis=-1) < 1.0 - min_alpha * ink.max() + tolerance)
    px = img[rows, cols]
    alpha = (1.0 - px) @ ink / (ink @ ink)  # px = 1 - alpha * ink, least squares
    ok = (alpha >= min_alpha) & (np.abs(px - (1.0 - alpha[:, None] * ink)).max(axis=1) < tolerance)
    mask = np.zeros(img.shape[:2], bool)
    mask[rows[ok], cols[ok]] = True
    patches, n = label(mask)
    if n == 0:
        return 0
    sizes = np.bincount(patches.ravel())[1:]
    return int(sizes.sum() - sizes.max())


def assert_changes_drawn(png, *, changed=True):
    """A picture of changes (:func:`sdp.render_changes`, ``--png``; a path or its bytes) is not blank,
    shows unchanged points in blue, and changed points in vermillion when ``changed`` (and not one
    when not)."""
    from sdp.viz._render import _BLUE, _VERMILLION

    img = picture(png)
    assert drawn_pixels(img, _BLUE) > 0, "no unchanged point drawn"
    n = drawn_pixels(img, _VERMILLION)
    assert (n > 0) == changed, f"{n} pixels of changed points, expected {'some' if changed else 'none'}"
    return img
