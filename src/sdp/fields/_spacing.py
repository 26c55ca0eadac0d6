"""Choosing the voxel size from the data.

The paper ties σ to the grid (σ = 2 voxels, grid = 80 segments of the longest side). On real
scans that choice ignores how densely the surfaces were sampled: a grid too fine for a sparse
laser scan leaves each point alone in its kernel (G < h everywhere), so every point of a
sparse region looks "new"; a grid too coarse for a Kinect frame merges small objects into the
table. :func:`auto_voxel_size` sets σ from the spacing of the points instead.

The spacing comes from exact k-th nearest-neighbour distances of a few thousand sampled points
(:func:`kth_neighbour_distance`): one pass puts the cloud into a hashed grid of cells, then each
sampled point scans a few cells around its own. On a 200k-point Kinect frame that takes about a
fifth of the time of building a k-d tree of the cloud for the same queries, with the same
distances to the last bit. (The cells are the shared spatial hash of :mod:`sdp._core._cells`;
the query kernels live here, beside the only estimate they serve.)
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numba as nb
import numpy as np

from .._core._cells import MAX_INDEX, find_cell, linked_cells, table_bits
from .._core._parallel import map_concurrently
from .._core._points import Points, as_points, finite_bounds

__all__ = ["auto_voxel_size", "kth_neighbour_distance", "resolve_lattice", "resolve_sigma_voxels"]

_MAX_RING = 2  # rings of cells scanned around a query before a 4x coarser grid takes it over
_GUESS = 3.0  # first cell size, in point spacings estimated from the box as if on surfaces
_PER_CELL = 6.0  # points per cell expected at the first guess (sizes the hash table)
_PILOT = 256  # queries measured at the first guess to set the cell size
_CELL_PER_MEDIAN = 3.0  # cell size in median k-th distances of the pilot queries
_RETUNE = 1.5  # rebuild when the pilot's cell size differs from the guess by more than this factor
_SLOTS_PER_CELL = 2.5  # hash table slots per expected cell (kept at most half full)
_SLACK = 1e-6  # cell units: keeps the stop and skip tests safe from rounding of the cell coordinates


def auto_voxel_size(*clouds, k: int = 3, quantile: float = 0.9, scale: float = 1.5,
                    sigma_voxels: float = 1.5, sample: int = 5_000, seed: int = 0) -> float:
    """A voxel size for clouds sampled like these: σ = ``scale`` × the ``quantile`` of each
    point's distance to its ``k``-th nearest neighbour, l = σ / ``sigma_voxels``.

    With σ at least the local spacing, a point on a surface sampled like its cloud has about
    2πσ²/s² ≥ 2h neighbours' worth of density, so surfaces seen in both scans stay inside
    both cluster volumes; the high quantile covers the sparser parts of the scan (far from
    the sensor). Use it for real scans whose density you don't know; use ``grid_size=`` to
    reproduce the paper.

    Parameters
    ----------
    *clouds : array_like (n, 3)
        The clouds to be compared (a random subsample of each is used).
    k : int
        Neighbour rank; matches the threshold's k (3 in the paper).
    quantile : float
        Quantile of the k-th neighbour distances, in (0, 1].
    scale : float
        σ in units of that distance.
    sigma_voxels : float
        σ in voxels: 1.5 (default) gives the lattice ``voxel_size="auto"`` uses (pass it on with
        ``sigma_voxels=1.5``); 2 gives the lattice on which the paper's σ of 2 voxels is this σ.
    sample : int
        Points drawn from each cloud to measure spacing.
    seed : int
        Seed of the subsample.

    Returns
    -------
    float
        Voxel length in world units.
    """
    return auto_voxel_size_of([as_points(cloud, name=f"cloud {i}") for i, cloud in enumerate(clouds)], k=k,
                              quantile=quantile, scale=scale, sigma_voxels=sigma_voxels, sample=sample, seed=seed)


def resolve_sigma_voxels(sigma_voxels: float | str, *, automatic: bool) -> float:
    """σ in voxels: ``"auto"`` is :data:`~sdp.defaults.AUTO_SIGMA_VOXELS` on the automatic
    lattice (``automatic``), :data:`~sdp.defaults.PAPER_SIGMA_VOXELS` on a given one; a number
    is checked (positive, finite) and used."""
    from .._core._validate import auto_or_positive
    from ..defaults import AUTO_SIGMA_VOXELS, PAPER_SIGMA_VOXELS

    sigma_voxels = auto_or_positive("sigma_voxels", sigma_voxels)
    if sigma_voxels == "auto":
        return AUTO_SIGMA_VOXELS if automatic else PAPER_SIGMA_VOXELS
    return sigma_voxels


def resolve_lattice(clouds: Sequence[Points], *, voxel_size: float | str | None = "auto",
                    grid_size: int | None = None, k: float = 3,
                    sigma_voxels: float | str = "auto") -> tuple[float, float]:
    """(voxel length, σ in voxels) of a comparison of ``clouds`` (validated), one for all of them.

    ``grid_size`` (the paper's parameterization: the longest side of the box holding all the
    clouds in ``grid_size`` segments) wins over the default ``voxel_size="auto"``
    (:func:`auto_voxel_size` of all the clouds, neighbour rank ``k``: σ from the point
    spacing); a length is used as given. ``sigma_voxels`` as :func:`resolve_sigma_voxels`.

    Raises
    ------
    InvalidOptionError
        ``grid_size`` with a length, a length that is not positive and finite, or an unknown word.
    """
    from .._core._validate import positive_finite
    from ..errors import InvalidOptionError
    from ._lattice import voxel_size_for_grid_size

    automatic = grid_size is None and (voxel_size is None or isinstance(voxel_size, str))
    sv = resolve_sigma_voxels(sigma_voxels, automatic=automatic)
    if grid_size is not None:
        if voxel_size not in (None, "auto"):
            raise InvalidOptionError("give grid_size= or voxel_size=, not both")
        lo = np.min([c.lo for c in clouds], axis=0)
        hi = np.max([c.hi for c in clouds], axis=0)
        return voxel_size_for_grid_size(lo, hi, grid_size), sv
    if automatic:
        if voxel_size not in (None, "auto"):
            raise InvalidOptionError(f"voxel_size must be a length or 'auto', got {voxel_size!r}")
        # the threshold's k as the neighbour rank; a k below 1 (h down to 1) still spaces by the nearest
        return auto_voxel_size_of(clouds, k=max(1, int(round(k))), sigma_voxels=sv), sv
    return positive_finite("voxel_size", voxel_size), sv


def auto_voxel_size_of(clouds: Sequence[Points], *, k: int = 3, quantile: float = 0.9, scale: float = 1.5,
                       sigma_voxels: float = 2.0, sample: int = 5_000, seed: int = 0) -> float:
    """:func:`auto_voxel_size` of clouds already validated by :func:`sdp._core._points.as_points`."""
    rng = np.random.default_rng(seed)
    jobs = []
    for pts in clouds:
        xyz = pts.xyz
        # sorted: the queries then visit the cloud in its own order (scans are ordered in space),
        # which keeps the memory they touch warm; the quantile doesn't depend on the order
        idx = np.sort(rng.choice(len(xyz), sample, replace=False)) if len(xyz) > sample else None
        if len(xyz) > k:
            jobs.append((pts, xyz if idx is None else xyz[idx], idx))
    def spacing(job):
        pts, queries, idx = job
        # each query is a point of the cloud: its k + 1-th neighbour is its k-th other point
        d = kth_in_image(pts, np.arange(len(pts.xyz)) if idx is None else idx, k + 1)
        if d is None:
            d = kth_neighbour_distance(pts.xyz, queries, k + 1, lo=pts.lo, hi=pts.hi)
        elif np.isnan(d).any():  # not proven by the image: the grid
            todo = np.isnan(d)
            d[todo] = kth_neighbour_distance(pts.xyz, queries[todo], k + 1, lo=pts.lo, hi=pts.hi)
        if (d == 0).any():  # exact duplicates (merged scans, repeated rows) sample no space: distinct points
            unique = np.unique(pts.xyz, axis=0)
            d = kth_neighbour_distance(unique, np.unique(queries, axis=0), k + 1, lo=pts.lo, hi=pts.hi) \
                if len(unique) > k else np.zeros(0)
        return d

    dists = map_concurrently(spacing, jobs)
    d = np.concatenate(dists) if dists else np.zeros(0)
    d = d[d > 0]
    if d.size == 0:
        from ..errors import InvalidPointsError

        raise InvalidPointsError(f"can't measure point spacing: the clouds need more than k={k} distinct points")
    voxel = float(scale * np.quantile(d, quantile) / sigma_voxels)
    if not np.isfinite(voxel):  # coordinates so large their differences overflow
        from ..errors import InvalidPointsError

        reach = max(float(np.abs(np.r_[c.lo, c.hi]).max()) for c in clouds)
        raise InvalidPointsError(f"can't measure the point spacing of coordinates this large (up to {reach:.3g}): "
                                 "move the clouds near the origin, or give a voxel size")
    return voxel


def kth_neighbour_distance(points: np.ndarray, queries: np.ndarray, k: int, *, cell: float | None = None,
                           lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> np.ndarray:
    """Exact Euclidean distance from each query to its ``k``-th nearest point of ``points``.

    A query that is one of the points counts itself, at distance 0, as
    ``scipy.spatial.cKDTree(points).query(queries, k)[0][:, k - 1]`` does (same value).

    ``points`` go into a hashed grid of cubic cells, one pass. Each query scans the cells around
    its own in rings, skipping cells farther than its k-th distance so far, until that distance
    lies inside the cells scanned: the result is exact whatever the cell size, which only sets
    the speed. Queries not resolved within ``_MAX_RING`` rings (sparse parts of the cloud) go on
    to a grid of 4× the cell, and so on (a cell as large as the box resolves every query).
    Cell size: ``cell`` (world units) or, by default, a guess from the box and the number of
    points as if they sampled surfaces (shrunk while the cells hold too many points, as when
    outliers stretch the box), then ``_CELL_PER_MEDIAN`` × the median k-th distance of
    ``_PILOT`` of the queries. Queries outside the box of ``points`` are scanned against every point.

    Parameters
    ----------
    points : ndarray (n, 3) of float64, finite
    queries : ndarray (m, 3) of float64, finite
    k : int
        1 ≤ k ≤ n.
    cell : float, optional
    lo, hi : ndarray (3,), optional
        Bounding box of ``points``, if known.

    Returns
    -------
    ndarray (m,) of float64
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    queries = np.ascontiguousarray(queries, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    if not 1 <= k <= n:
        raise ValueError(f"k must be in [1, {n}] (the number of points), got {k}")
    if lo is None or hi is None:
        lo, hi, _ = finite_bounds(points)  # one pass; points.min(axis=0) is much slower
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    out = np.full(len(queries), np.nan)
    inside = ((queries >= lo) & (queries <= hi)).all(axis=1)
    if not inside.all():
        out[~inside] = _brute_force(points, queries[~inside], k)
    todo = np.flatnonzero(inside)
    if not todo.size:
        return out
    size = float((hi - lo).max())
    floor = max(size / (MAX_INDEX - 2), 1e-300)  # keeps the cell coordinates within 21 bits
    if cell is not None:
        c = max(float(cell), floor)
        grid, cells = _build(points, lo, c, n / _PER_CELL)
    else:
        e = np.sort(hi - lo)[::-1]
        c = max(_GUESS * max(math.sqrt(e[0] * e[1] / n), e[0] / n), floor)  # a line's spacing at least
        grid, cells = _build(points, lo, c, n / _PER_CELL)
        for _ in range(8):  # far outliers, or a volume rather than surfaces: too many points per cell
            if n / cells <= 8 * _PER_CELL or c <= floor:
                break
            c = max(c * math.sqrt(_PER_CELL * cells / n), floor)
            grid, cells = _build(points, lo, c, n / _PER_CELL)
        step = max(len(todo) // _PILOT, 1)
        pilot, todo = todo[::step].copy(), np.delete(todo, np.s_[::step])  # contiguous: one compiled _query
        _resolve(points, queries, pilot, out, grid, cells, c, k, lo, size)
        d = out[pilot]
        d = d[d > 0]
        if d.size:
            target = max(_CELL_PER_MEDIAN * float(np.median(d)), floor)
            if not c / _RETUNE <= target <= _RETUNE * c:
                grid, cells = _build(points, lo, target, min(cells * (c / target) ** 2, n))
                c = target
    _resolve(points, queries, todo, out, grid, cells, c, k, lo, size)
    return out


#: Half-widths (pixels) of the windows an organized frame's queries are searched in, in turn.
_WINDOWS = (2, 5, 11)
#: Pixels per return beyond which an organized frame's index of pixels (4 bytes each) is not built.
_PIXELS_PER_POINT = 8


def kth_in_image(pts: Points, rows: np.ndarray, k: int) -> np.ndarray | None:
    """:func:`kth_neighbour_distance` of the cloud's rows ``rows`` from an organized frame's pixels
    (:attr:`sdp._core._points.Points.image`), or None without one (or where its returns fit no
    pinhole camera). The k nearest returns within a window of pixels around the query's own are
    the k nearest of the cloud when the k-th of them is nearer than any return outside the
    window can be: such a return's ray makes an angle θ with the query's whose sine is at least
    S·d (:func:`sdp._core._pinhole.ray_sine_per_pixel`) for d the pixels between their
    projections, at least the window's half-width + 1 less twice the largest reprojection error,
    and it lies at least r·sin θ from a query at range r. Where that is not proven in the
    widest window, NaN (for the grid to answer): the same distances, to the last bit."""
    from .._core._pinhole import fit_camera, ray_sine_per_pixel, reprojection_error

    if pts.image is None or len(pts.xyz) < k:
        return None
    pixels, (height, width), origin = pts.image
    if height * width > _PIXELS_PER_POINT * len(pts.xyz) + 2**20:  # a sparse grid: its index would outweigh the cloud
        return None
    camera = fit_camera(pts.xyz, pixels, (height, width), origin)
    if camera is None:
        return None
    error = reprojection_error(pts.xyz, camera.pixels, width, origin, camera.matrix)
    if not error < 1.0:
        return None
    sine = ray_sine_per_pixel(camera, height, error)
    index = np.full(height * width, -1, np.int32)
    index[camera.pixels] = np.arange(len(camera.pixels), dtype=np.int32)
    rows = np.asarray(rows, np.int64)
    out = np.full(len(rows), np.nan)
    for half in _WINDOWS:  # each window only for the rows the ones before did not prove
        _window_kth(pts.xyz, camera.pixels, index, width, height, origin, rows, k, half, sine * (half + 1 - 2 * error),
                    out)
    return out


@nb.njit(cache=True, nogil=True)
def _window_kth(points, pixels, index, width, height, origin, rows, k, half, sine, out):
    """``out[i]`` = the k-th nearest distance of row ``rows[i]`` from the returns within ``half``
    pixels of its own, where it is below ``sine`` times the query's range (none outside is nearer);
    rows already answered are left."""
    best = np.empty(k)
    for i in range(rows.shape[0]):
        if not math.isnan(out[i]):
            continue
        q = rows[i]
        x, y, z = points[q, 0], points[q, 1], points[q, 2]
        r0, c0 = pixels[q] // width, pixels[q] % width
        best[:] = np.inf
        for r in range(max(r0 - half, 0), min(r0 + half + 1, height)):
            for c in range(max(c0 - half, 0), min(c0 + half + 1, width)):
                p = index[r * width + c]
                if p >= 0:
                    dx = points[p, 0] - x
                    dy = points[p, 1] - y
                    dz = points[p, 2] - z
                    _insert(best, dx * dx + dy * dy + dz * dz)
        ox, oy, oz = x - origin[0], y - origin[1], z - origin[2]
        bound = math.sqrt(ox * ox + oy * oy + oz * oz) * sine * (1.0 - 1e-9)
        if bound > 0.0 and best[k - 1] <= bound * bound:
            out[i] = math.sqrt(best[k - 1])


def _resolve(points, queries, todo, out, grid, cells, c, k, lo, size):
    """Fill ``out[todo]`` on ``grid`` (cell ``c``, ``cells`` cells), then on coarser grids for
    the queries left."""
    while todo.size:
        _query(*grid, points, queries, todo, out, lo, c, k, _MAX_RING)
        todo = todo[np.isnan(out[todo])]
        if not todo.size:
            return
        if c > 2 * size:  # not expected: a cell larger than the box holds every point within one ring
            out[todo] = _brute_force(points, queries[todo], k)
            return
        c *= 4.0
        grid, cells = _build(points, lo, c, cells / 8)


def _build(points, lo, c, expected_cells):
    """(cell list of ``points`` with cell ``c`` (:func:`sdp._core._cells.linked_cells`), its number
    of cells); the hash table is sized for ``expected_cells`` and rebuilt larger if they were too few."""
    while True:
        keys, heads, nxt, cells, done = linked_cells(points, lo, c, table_bits(_SLOTS_PER_CELL * expected_cells))
        if len(nxt):
            return (keys, heads, nxt), cells
        expected_cells = 2.0 * cells * len(points) / max(done, 1)  # the table filled up at point `done`


@nb.njit(cache=True, inline="always")
def _gap2(d, f0, f1):
    """Squared distance (cell units, less the slack) along one axis from a query to the cells
    ``d`` cells from its own; ``f0``, ``f1``: its distances to its own cell's lower and upper faces."""
    g = 0.0 if d == 0 else (d - 1 + f1 if d > 0 else -d - 1 + f0) - _SLACK
    return g * g if g > 0 else 0.0


@nb.njit(cache=True, nogil=True)
def _query(keys, heads, nxt, points, queries, todo, out, lo, c, k, max_ring):
    """``out[q]`` = the k-th nearest distance of query ``q``, for each ``q`` in ``todo`` (inside the
    points' box); left as it is when not resolved within ``max_ring`` rings of cells."""
    mask = keys.shape[0] - 1
    shift = 64 - int(round(math.log2(keys.shape[0])))
    inv = 1.0 / c
    c2 = c * c
    best = np.empty(k)  # squared distances, ascending
    for q in todo:
        x, y, z = queries[q, 0], queries[q, 1], queries[q, 2]
        ux, uy, uz = (x - lo[0]) * inv, (y - lo[1]) * inv, (z - lo[2]) * inv
        cx, cy, cz = int(math.floor(ux)), int(math.floor(uy)), int(math.floor(uz))
        fx0, fx1, fy0, fy1, fz0, fz1 = ux - cx, cx + 1 - ux, uy - cy, cy + 1 - uy, uz - cz, cz + 1 - uz
        face = min(fx0, fx1, fy0, fy1, fz0, fz1)
        best[:] = np.inf
        for r in range(max_ring + 1):
            for ix in range(cx - r, cx + r + 1):
                gx = _gap2(ix - cx, fx0, fx1)
                for iy in range(cy - r, cy + r + 1):
                    gxy = gx + _gap2(iy - cy, fy0, fy1)
                    edge = ix == cx - r or ix == cx + r or iy == cy - r or iy == cy + r
                    iz = cz - r
                    while iz <= cz + r:  # the shell of the cube: its inside was scanned at smaller r
                        # skip cells farther than the k-th distance so far (find_cell: and off the grid)
                        if (gxy + _gap2(iz - cz, fz0, fz1)) * c2 <= best[k - 1]:
                            s = find_cell(keys, ix, iy, iz, shift, mask)
                            p = heads[s] if s >= 0 else -1
                            while p >= 0:
                                dx = points[p, 0] - x
                                dy = points[p, 1] - y
                                dz = points[p, 2] - z
                                _insert(best, dx * dx + dy * dy + dz * dz)
                                p = nxt[p]
                        iz += 1 if (edge or iz == cz + r) else 2 * r
            reach = (r + face - _SLACK) * c  # every point outside the cube is at least this far
            if reach > 0 and best[k - 1] <= reach * reach:
                out[q] = math.sqrt(best[k - 1])
                break


@nb.njit(cache=True, nogil=True)
def _brute_force(points, queries, k):
    """k-th nearest distance of each query, by a scan over every point."""
    out = np.empty(queries.shape[0])
    best = np.empty(k)
    for q in range(queries.shape[0]):
        best[:] = np.inf
        for j in range(points.shape[0]):
            dx = points[j, 0] - queries[q, 0]
            dy = points[j, 1] - queries[q, 1]
            dz = points[j, 2] - queries[q, 2]
            _insert(best, dx * dx + dy * dy + dz * dz)
        out[q] = math.sqrt(best[k - 1])
    return out


@nb.njit(cache=True, inline="always")
def _insert(best, d2):
    """Insert the squared distance d2 into the sorted k best (a no-op when it is not among them)."""
    k = best.shape[0]
    if d2 < best[k - 1]:
        i = k - 1
        while i > 0 and best[i - 1] > d2:
            best[i] = best[i - 1]
            i -= 1
        best[i] = d2
