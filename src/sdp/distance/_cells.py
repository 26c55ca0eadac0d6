"""Each epoch's points summed once into cubic cells of moments, and the kernels that read them.

The cells of :func:`sdp.distances` (:mod:`sdp.distance._distances`, its "moments on cells"): a
counting sort over the box of cells orders each epoch's points (beyond 2²⁵ cells, a sort by cell
key and the spatial hash of :mod:`sdp._core._cells`), each occupied cell keeps its count,
centroid and scatter, and the queries read the cells around them: the normals (a Gaussian of σ_n
over the cells' centroids, the smallest eigenvector of the weighted covariance), the cylinders
(each cell's points weighted by the Gaussian at its centroid, their offsets and spread along the
normal exact) and the search along a normal's line for the nearest surface, in steps of half a
cell, until the line passes an occupied cell or one of its 26 neighbours. A query costs the
same however dense the cloud is.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .._core._cells import BITS, MAX_INDEX, hashed_sort, table_row
from ..errors import InvalidOptionError

__all__ = ["CELL", "DENSE_CELLS", "NORMAL_REACH", "RADIUS", "CellLists", "bounds", "cell_moments", "rows_around"]


_MIN_POINTS = 2.0  # effective points an epoch needs in the cylinder: a spread needs two
# and as much weight as two points on the rim of M3C2's cylinder (radius d/2 = 2σ_p): a few points
# near the cut (3σ_p) weigh alike, so their effective count is full while they tell where the
# surface lies off the axis, not at it (on a normal tilted by 1°, 2 cm at 1 m)
_MIN_WEIGHT = 2.0 * math.exp(-2.0)
NORMAL_REACH = 2.0  # normal kernels cut at 2σ_n: the covariance's direction is settled by then
DENSE_CELLS = 2**25  # boxes of up to this many cells are sorted by counting (4 bytes per cell)
RADIUS = 3.0  # cylinder cut, in σ_p: the density kernel's truncation
CELL = 1.5  # cells of the cylinders' moments, in σ_p


class CellLists:
    """Each cloud's points sorted into cubic cells of one size, built once per (cloud, size)."""

    def __init__(self, lo, hi):
        self.lo = np.asarray(lo, np.float64)
        self.extent = np.asarray(hi, np.float64) - self.lo
        self._cache: dict = {}

    def order(self, xyz, cell):
        """(permutation that sorts ``xyz`` by cell, start of each cell's run in that order)."""
        entry = self.get(xyz, cell)
        return entry[5], entry[1]

    def get(self, xyz: np.ndarray, cell: float, *, point_cells: bool = False):
        """(points sorted by cell, start of each occupied cell's run, cell table, its box of
        cells (the first cell's index, then the box's size) or zeros for a hash table, cell
        size, the sorting permutation).

        A cell's index is floor((p − lo) / cell) in both tables, so the cells do not depend on
        which table holds them; the dense box spans the points' own cells only (a tile of a
        large cloud, whose cells start at the whole cloud's corner, gets a small box).
        ``point_cells``: each point's run is wanted too (:meth:`point_cells`): the counting
        sort writes it as it goes, in order, where a pass afterwards would scatter it."""
        key = (id(xyz), cell)
        if key not in self._cache:
            if np.max(self.extent) / cell >= MAX_INDEX - 4:
                raise InvalidOptionError(f"the clouds span {np.max(self.extent):g} units, more than 2**{BITS} cells "
                                         f"of {cell:g}: give a larger projection_scale, or compare in tiles")
            first, last = _index_box(xyz, self.lo, cell)
            size = last - first + 1
            if np.prod(size.astype(float)) <= DENSE_CELLS:  # a counting sort over the box of cells
                dims = np.r_[size, first]
                linear = np.empty(len(xyz), np.int32)  # at most 2**25 cells
                _box_cells(xyz, self.lo, cell, dims, linear)
                runs = np.empty(len(xyz) if point_cells else 0, np.int64)
                order, starts, table, ordered = _counting_sort(xyz, linear, int(np.prod(size)), runs)
                if point_cells:
                    self._cache[("cells", *key)] = runs
            else:
                order, starts, table = hashed_sort(xyz, self.lo, cell)
                dims = np.zeros(6, np.int64)
                ordered = _gather(xyz, order)
            self._cache[key] = (ordered, starts, table, dims, cell, order)
        return self._cache[key]

    def point_cells(self, xyz: np.ndarray, cell: float) -> np.ndarray:
        """Each point's cell: its run in :meth:`get`'s order (int64)."""
        key = ("cells", id(xyz), cell)
        if key not in self._cache:
            _, starts, _, _, _, order = self.get(xyz, cell, point_cells=True)
            if key not in self._cache:  # sorted before, or by hashing
                self._cache[key] = _runs_of(order, starts)
        return self._cache[key]

    def normals(self, xyz, queries, sigma, cell=None):
        """(unit normals (m, 3), NaN where fewer than 3 points; roughness = √λ_min).

        From the moments of cells of σ (count, centroid, scatter), each cell weighted by the
        Gaussian at its centroid: a few dozen cells per query instead of hundreds of points,
        and the direction of a covariance does not need each point's own weight. ``cell``:
        cells of another size instead (those of the cylinders, already sorted: no second sort
        where few queries are made)."""
        normal = np.empty((len(queries), 3))
        rough = np.empty(len(queries))
        _normals(*self.moments(xyz, sigma if cell is None else cell), self.lo, np.ascontiguousarray(queries), sigma,
                 NORMAL_REACH * sigma, normal, rough)
        return normal, rough

    def moments(self, xyz, cell):
        """(one row of count, centroid, scatter per occupied cell of ``xyz``; the cell table, its
        box of cells, the cell size), built once per cloud and cell size."""
        pts, starts, table, rows, cell, _ = self.get(xyz, cell)
        key = ("moments", id(xyz), cell)
        if key not in self._cache:
            self._cache[key] = cell_moments(pts, starts)
        return self._cache[key], table, rows, cell

    def cylinder(self, xyz, queries, normals, sigma, max_half):
        """(weighted mean offset, spread, effective count, level, centroid across the axis (m, 3),
        its variance) of ``xyz`` in the cylinders: level 0 around the core point; level 1 around
        the nearest cell of ``xyz`` on the normal's line within ``max_half``, where the first found
        too few points. The centroid across the axis is the weighted mean position's offset
        perpendicular to the normal (the same for a cylinder moved along it), its variance
        ``Σw|a − L|² / Σw`` over the effective count ``(Σw)² / Σw²`` (Kish), summed over both
        directions across
        (:func:`sdp.distance._distances.off_axis`)."""
        half = RADIUS * sigma
        out = self._cylinders(xyz, queries, normals, sigma, half)
        level = np.where(_enough(out), 0, -1)
        todo = np.flatnonzero(level < 0)
        if todo.size and max_half > half:
            q, n = queries[todo], normals[todo]
            _, _, table, dims, cell, _ = self.get(xyz, CELL * sigma)
            t = np.empty(todo.size)
            _nearest_along(table, dims, cell, self.lo, q, n, max_half, False, t)
            found = np.flatnonzero(np.isfinite(t))
            q, n, t = q[found], n[found], t[found]
            for _ in range(2):  # move the cylinder onto the surface found: twice settles it
                fine = self._cylinders(xyz, np.ascontiguousarray(q + t[:, None] * n), n, sigma, half)
                ok = fine[:, 2] >= _MIN_POINTS  # a first cylinder beside the surface moves onto it
                t = np.where(ok, t + np.nan_to_num(fine[:, 0]), t)
            fine[:, 0] = t
            keep = _enough(fine) & (np.abs(t) <= max_half)
            out[todo[found[keep]]] = fine[keep]
            level[todo[found[keep]]] = 1
        out[level < 0, :2] = np.nan
        out[level < 0, 4:] = np.nan
        return out[:, 0], out[:, 1], out[:, 2], level, np.ascontiguousarray(out[:, 4:7]), out[:, 7].copy()

    def free_ahead(self, xyz, queries, normals, sigma, start, reach):
        """How far along +n from each query the cloud ``xyz`` holds nothing, from ``start`` (m,) on
        (the query's own surface and its cylinder's half-length behind it) up to ``reach``: the offset
        from the query of the first cell (or one of its neighbours) holding points, inf where none
        does, NaN where ``start`` is NaN. Where an epoch finds a surface in front of a core point
        nearer than this, the reference held nothing there (:mod:`sdp.distance._seen`)."""
        start = np.asarray(start, np.float64)
        out = np.full(len(queries), np.nan)
        ok = np.flatnonzero(np.isfinite(start) & (start < reach))
        out[np.isfinite(start) & (start >= reach)] = np.inf
        if ok.size:
            _, _, table, dims, cell, _ = self.get(xyz, CELL * sigma)
            n = np.ascontiguousarray(normals[ok])
            q = np.ascontiguousarray(queries[ok] + start[ok, None] * n)
            t = np.empty(ok.size)
            _nearest_along(table, dims, cell, self.lo, q, n, float(reach), True, t)
            out[ok] = np.where(np.isnan(t) | (start[ok] + t > reach), np.inf, start[ok] + t)
        return out

    def _cylinders(self, xyz, queries, normals, sigma, half):
        """(mean offset, spread, effective count, weight, centroid across the axis (3), its
        variance) per cylinder; no mean, spread nor centroid where too few points answer."""
        out = np.empty((len(queries), 8))
        _cylinders(*self.moments(xyz, CELL * sigma), self.lo, np.ascontiguousarray(queries),
                   np.ascontiguousarray(normals), sigma, RADIUS * sigma, half, out)
        few = out[:, 2] < _MIN_POINTS
        out[few, :2] = np.nan
        out[few, 4:] = np.nan
        return out


def _enough(out: np.ndarray) -> np.ndarray:
    """The cylinders (rows of :meth:`CellLists._cylinders`) that measure: as many effective points
    as a spread needs, as much weight as two points on M3C2's rim."""
    return (out[:, 2] >= _MIN_POINTS) & (out[:, 3] >= _MIN_WEIGHT)


def _index_box(xyz, lo, cell):
    """(first, last) cell index per axis of the points, as the kernels index them: from the
    points' corners, since ⌊(x − lo) / cell⌋ never decreases with x (one serial pass: a parallel
    reduction waits for every core, and a series decodes its next epoch on them meanwhile)."""
    low, high = bounds(xyz)
    return (np.floor((low - lo) / cell).astype(np.int64), np.floor((high - lo) / cell).astype(np.int64))


@nb.njit(cache=True, nogil=True)
def bounds(xyz):
    """(lowest, highest) corner of the points, in one pass."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for i in range(xyz.shape[0]):
        for a in range(3):
            lo[a] = min(lo[a], xyz[i, a])
            hi[a] = max(hi[a], xyz[i, a])
    return lo, hi


@nb.njit(cache=True, nogil=True, parallel=True)
def _box_cells(xyz, lo, cell, dims, linear):
    """Each point's cell as a row of the box of ``dims[:3]`` cells from cell ``dims[3:]``."""
    for i in nb.prange(xyz.shape[0]):
        ix = min(max(int(math.floor((xyz[i, 0] - lo[0]) / cell)) - dims[3], 0), dims[0] - 1)
        iy = min(max(int(math.floor((xyz[i, 1] - lo[1]) / cell)) - dims[4], 0), dims[1] - 1)
        iz = min(max(int(math.floor((xyz[i, 2] - lo[2]) / cell)) - dims[5], 0), dims[2] - 1)
        linear[i] = (ix * dims[1] + iy) * dims[2] + iz


@nb.njit(cache=True, nogil=True)
def _counting_sort(xyz, linear, total, run_of):
    """Points sorted by cell in O(n + cells): (permutation, start of each occupied cell's run,
    dense table cell → run (-1: empty), the points in that order), ``linear``: each point's
    cell in a box of ``total`` cells (:func:`_box_cells`); ``run_of``, unless empty: each
    point's run."""
    n = xyz.shape[0]
    table = np.zeros(total, np.int32)
    for i in range(n):
        table[linear[i]] += 1
    starts = np.empty(n + 1, np.int64)
    runs = 0
    at = 0
    for c in range(total):  # counts → first slot of each cell; the table then maps cell → run
        k = table[c]
        if k:
            starts[runs] = at
            table[c] = runs
            runs += 1
            at += k
        else:
            table[c] = -1
    starts[runs] = n
    fill = starts[:runs].copy()
    order = np.empty(n, np.int64)
    ordered = np.empty_like(xyz)
    keep = run_of.shape[0] == n
    for i in range(n):
        r = table[linear[i]]
        if keep:
            run_of[i] = r
        j = fill[r]
        order[j] = i
        for a in range(3):
            ordered[j, a] = xyz[i, a]
        fill[r] = j + 1
    return order, starts[: runs + 1].copy(), table, ordered


@nb.njit(cache=True, nogil=True)
def _runs_of(order, starts):
    """Each point's run of a sort by cell (permutation ``order``, runs ``starts``)."""
    out = np.empty(order.shape[0], np.int64)
    for k in range(starts.shape[0] - 1):
        for j in range(starts[k], starts[k + 1]):
            out[order[j]] = k
    return out



@nb.njit(cache=True, nogil=True, parallel=True)
def _gather(values, index):
    """``values[index]`` on all threads (a permutation of a scan touches memory at random)."""
    out = np.empty((index.shape[0],) + values.shape[1:], values.dtype)
    for i in nb.prange(index.shape[0]):
        out[i] = values[index[i]]
    return out


@nb.njit(cache=True, inline="always")
def rows_around(table, dims, shift, x, y, z, rows):
    """The rows of the 27 cells around cell (x, y, z), -1 where empty, into ``rows`` (27,): in a
    dense table (``dims``: the box's size, then its first cell) or a hash table (``dims`` zeros:
    :func:`sdp._core._cells.key_table`). The table's kind is tested once, outside the loops: a
    hash probe's loop beside a dense lookup in one loop body made the dense lookups ten times
    slower."""
    k = 0
    if dims[0] > 0:
        for dx in range(-1, 2):
            ix = x + dx - dims[3]
            for dy in range(-1, 2):
                iy = y + dy - dims[4]
                for dz in range(-1, 2):
                    iz = z + dz - dims[5]
                    if ix < 0 or iy < 0 or iz < 0 or ix >= dims[0] or iy >= dims[1] or iz >= dims[2]:
                        rows[k] = -1
                    else:
                        rows[k] = table[(ix * dims[1] + iy) * dims[2] + iz]
                    k += 1
    else:
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    rows[k] = table_row(table, x + dx, y + dy, z + dz, shift)
                    k += 1


@nb.njit(cache=True, inline="always")
def _cell_box(qx, qy, qz, ex, ey, ez, lo, cell):
    """First and last cell index per axis of the box (q ± e)."""
    return (int(math.floor((qx - ex - lo[0]) / cell)), int(math.floor((qx + ex - lo[0]) / cell)),
            int(math.floor((qy - ey - lo[1]) / cell)), int(math.floor((qy + ey - lo[1]) / cell)),
            int(math.floor((qz - ez - lo[2]) / cell)), int(math.floor((qz + ez - lo[2]) / cell)))


@nb.njit(cache=True, inline="always")
def _smallest_eigenvector(a00, a01, a02, a11, a12, a22):
    """Unit eigenvector of the smallest eigenvalue of a symmetric 3×3 matrix, and that eigenvalue
    (closed form: the trigonometric solution of the characteristic cubic, then the largest cross
    product of two rows of A − λI)."""
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    p = math.sqrt(p2 / 6.0)
    if p < 1e-300:
        return 0.0, 0.0, 1.0, q
    b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
    b01, b02, b12 = a01 / p, a02 / p, a12 / p
    r = (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)) / 2.0
    r = min(1.0, max(-1.0, r))
    lam = q + 2.0 * p * math.cos(math.acos(r) / 3.0 + 2.0 * math.pi / 3.0)
    r0 = (a00 - lam, a01, a02)
    r1 = (a01, a11 - lam, a12)
    r2 = (a02, a12, a22 - lam)
    best, bx, by, bz = -1.0, 0.0, 0.0, 1.0
    for u, v in ((r0, r1), (r0, r2), (r1, r2)):
        cx = u[1] * v[2] - u[2] * v[1]
        cy = u[2] * v[0] - u[0] * v[2]
        cz = u[0] * v[1] - u[1] * v[0]
        nn = cx * cx + cy * cy + cz * cz
        if nn > best:
            best, bx, by, bz = nn, cx, cy, cz
    s = math.sqrt(best)
    return bx / s, by / s, bz / s, lam


@nb.njit(cache=True, nogil=True)
def cell_moments(pts, starts):
    """Per cell of a sorted cloud, one row: point count, centroid (3), scatter about the centroid
    (xx, xy, xz, yy, yz, zz); one row per cell keeps a query's reads to a cache line or two."""
    c = starts.shape[0] - 1
    m = np.zeros((c, 10))
    for r in range(c):
        a, b = starts[r], starts[r + 1]
        m[r, 0] = b - a
        for j in range(a, b):
            for k in range(3):
                m[r, 1 + k] += pts[j, k]
        for k in range(3):
            m[r, 1 + k] /= b - a
        for j in range(a, b):
            dx, dy, dz = pts[j, 0] - m[r, 1], pts[j, 1] - m[r, 2], pts[j, 2] - m[r, 3]
            m[r, 4] += dx * dx
            m[r, 5] += dx * dy
            m[r, 6] += dx * dz
            m[r, 7] += dy * dy
            m[r, 8] += dy * dz
            m[r, 9] += dz * dz
    return m


@nb.njit(cache=True, inline="always")
def _normal_cell(cells, r, qx, qy, qz, r2max, inv2s2, acc):
    """``acc`` (points, weight, weighted sums of the offsets and of their products) with cell row
    ``r`` added if its centroid lies within reach, each point weighted by the Gaussian at it."""
    dx, dy, dz = cells[r, 1] - qx, cells[r, 2] - qy, cells[r, 3] - qz
    d2 = dx * dx + dy * dy + dz * dz
    if d2 > r2max:
        return acc
    npts, w, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz = acc
    g = math.exp(-d2 * inv2s2)
    n = cells[r, 0]
    gn = g * n
    return (npts + n, w + gn, sx + gn * dx, sy + gn * dy, sz + gn * dz,
            sxx + g * cells[r, 4] + gn * dx * dx, sxy + g * cells[r, 5] + gn * dx * dy,
            sxz + g * cells[r, 6] + gn * dx * dz, syy + g * cells[r, 7] + gn * dy * dy,
            syz + g * cells[r, 8] + gn * dy * dz, szz + g * cells[r, 9] + gn * dz * dz)


@nb.njit(cache=True, nogil=True, parallel=True)
def _normals(cells, table, dims, cell, lo, queries, sigma, reach, normal, rough):
    inv2s2 = 0.5 / (sigma * sigma)
    r2max = reach * reach
    shift = 64 - int(round(math.log2(max(table.shape[0] // 2, 1))))  # hash tables only
    for i in nb.prange(queries.shape[0]):
        qx, qy, qz = queries[i, 0], queries[i, 1], queries[i, 2]
        x0, x1, y0, y1, z0, z1 = _cell_box(qx, qy, qz, reach, reach, reach, lo, cell)
        acc = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if dims[0] > 0:  # a dense table: the box clipped to it once, each column's cells read in a row
            x0, x1 = max(x0 - dims[3], 0), min(x1 - dims[3], dims[0] - 1)
            y0, y1 = max(y0 - dims[4], 0), min(y1 - dims[4], dims[1] - 1)
            z0, z1 = max(z0 - dims[5], 0), min(z1 - dims[5], dims[2] - 1)
            for ix in range(x0, x1 + 1):
                for iy in range(y0, y1 + 1):
                    column = (ix * dims[1] + iy) * dims[2]
                    for c in range(column + z0, column + z1 + 1):
                        r = table[c]
                        if r >= 0:
                            acc = _normal_cell(cells, r, qx, qy, qz, r2max, inv2s2, acc)
        else:
            for ix in range(x0, x1 + 1):
                for iy in range(y0, y1 + 1):
                    for iz in range(z0, z1 + 1):
                        r = table_row(table, ix, iy, iz, shift)
                        if r >= 0:
                            acc = _normal_cell(cells, r, qx, qy, qz, r2max, inv2s2, acc)
        npts, w, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz = acc
        if npts < 3:
            normal[i, 0] = normal[i, 1] = normal[i, 2] = np.nan
            rough[i] = np.nan
            continue
        mx, my, mz = sx / w, sy / w, sz / w
        nx, ny, nz, lam = _smallest_eigenvector(sxx / w - mx * mx, sxy / w - mx * my, sxz / w - mx * mz,
                                                syy / w - my * my, syz / w - my * mz, szz / w - mz * mz)
        normal[i, 0], normal[i, 1], normal[i, 2] = nx, ny, nz
        rough[i] = math.sqrt(max(lam, 0.0))


@nb.njit(cache=True, nogil=True, parallel=True)
def _nearest_along(table, dims, cell, lo, queries, normals, reach, forward, out):
    """Per query: the signed offset t, nearest to 0 with |t| ≤ ``reach``, at which the line
    ``q + t·n`` passes an occupied cell or one of its 26 neighbours (steps of half a cell, both
    ways at once, or along +n alone with ``forward``; the neighbours bridge the gaps of a sparse
    surface); NaN if none."""
    shift = 64 - int(round(math.log2(max(table.shape[0] // 2, 1))))  # hash tables only
    step = 0.5 * cell
    ways = 1 if forward else 2
    for i in nb.prange(queries.shape[0]):
        rows = np.empty(27, np.int64)
        out[i] = np.nan
        s = step
        while s <= reach and np.isnan(out[i]):
            for way in range(ways):
                t = s if way == 0 else -s
                cx = int(math.floor((queries[i, 0] + t * normals[i, 0] - lo[0]) / cell))
                cy = int(math.floor((queries[i, 1] + t * normals[i, 1] - lo[1]) / cell))
                cz = int(math.floor((queries[i, 2] + t * normals[i, 2] - lo[2]) / cell))
                rows_around(table, dims, shift, cx, cy, cz, rows)
                if rows.max() >= 0:
                    out[i] = t
                    break
            s += step


@nb.njit(cache=True, inline="always")
def _cylinder_cell(cells, r, qx, qy, qz, nx, ny, nz, half, r2max, inv2s2, acc):
    """The sums of a cylinder with cell row ``r`` added if its centroid lies in the cylinder:
    weight, squared weight, weighted offset along the axis and its square, then the weighted
    offset across the axis (3) and the weighted squared offset across (its points' scatter across
    included)."""
    dx, dy, dz = cells[r, 1] - qx, cells[r, 2] - qy, cells[r, 3] - qz
    t = dx * nx + dy * ny + dz * nz
    if t > half or t < -half:
        return acc
    r2 = dx * dx + dy * dy + dz * dz - t * t
    if r2 > r2max:
        return acc
    w, w2, st, stt, lx, ly, lz, kk = acc
    g = math.exp(-r2 * inv2s2)
    n = cells[r, 0]
    along = (nx * (cells[r, 4] * nx + cells[r, 5] * ny + cells[r, 6] * nz)
             + ny * (cells[r, 5] * nx + cells[r, 7] * ny + cells[r, 8] * nz)
             + nz * (cells[r, 6] * nx + cells[r, 8] * ny + cells[r, 9] * nz))
    across = max(cells[r, 4] + cells[r, 7] + cells[r, 9] - along, 0.0)
    gn = g * n
    return (w + gn, w2 + g * gn, st + gn * t, stt + g * (n * t * t + along), lx + gn * (dx - t * nx),
            ly + gn * (dy - t * ny), lz + gn * (dz - t * nz), kk + g * (n * r2 + across))


@nb.njit(cache=True, nogil=True, parallel=True)
def _cylinders(cells, table, dims, cell, lo, queries, normals, sigma, radius, half, out):
    """Per query, a row of ``out``: kernel-weighted mean offset along its normal, spread, effective
    count and weight of the cells whose centroid lies within ``radius`` of its axis and ``half``
    along it, then their weighted centroid's offset across the axis (3) and that centroid's
    variance; each cell's points share the weight of its centroid, their offsets and spread are
    exact (the cell's centroid and scatter)."""
    inv2s2 = 0.5 / (sigma * sigma)
    r2max = radius * radius
    shift = 64 - int(round(math.log2(max(table.shape[0] // 2, 1))))  # hash tables only
    for i in nb.prange(queries.shape[0]):
        qx, qy, qz = queries[i, 0], queries[i, 1], queries[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        acc = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if not np.isfinite(nx):
            out[i, :] = np.nan
            out[i, 2] = out[i, 3] = 0.0
            continue
        ex = half * abs(nx) + radius * math.sqrt(max(0.0, 1.0 - nx * nx))
        ey = half * abs(ny) + radius * math.sqrt(max(0.0, 1.0 - ny * ny))
        ez = half * abs(nz) + radius * math.sqrt(max(0.0, 1.0 - nz * nz))
        x0, x1, y0, y1, z0, z1 = _cell_box(qx, qy, qz, ex, ey, ez, lo, cell)
        if dims[0] > 0:
            # a dense table: the box clipped to it once, each column's cells read in a row (most
            # of a box's cells are empty, so the per-cell index arithmetic was most of the time)
            x0, x1 = max(x0 - dims[3], 0), min(x1 - dims[3], dims[0] - 1)
            y0, y1 = max(y0 - dims[4], 0), min(y1 - dims[4], dims[1] - 1)
            z0, z1 = max(z0 - dims[5], 0), min(z1 - dims[5], dims[2] - 1)
            for ix in range(x0, x1 + 1):
                for iy in range(y0, y1 + 1):
                    column = (ix * dims[1] + iy) * dims[2]
                    for c in range(column + z0, column + z1 + 1):
                        r = table[c]
                        if r >= 0:
                            acc = _cylinder_cell(cells, r, qx, qy, qz, nx, ny, nz, half, r2max, inv2s2, acc)
        else:
            for ix in range(x0, x1 + 1):
                for iy in range(y0, y1 + 1):
                    for iz in range(z0, z1 + 1):
                        r = table_row(table, ix, iy, iz, shift)
                        if r >= 0:
                            acc = _cylinder_cell(cells, r, qx, qy, qz, nx, ny, nz, half, r2max, inv2s2, acc)
        w, w2, st, stt, lx, ly, lz, kk = acc
        if w <= 0.0:
            out[i, :] = np.nan
            out[i, 2] = out[i, 3] = 0.0
            continue
        out[i, 3] = w
        m = st / w
        n_eff = w * w / w2
        var = max(stt / w - m * m, 0.0)
        if n_eff > 1.0:
            var *= n_eff / (n_eff - 1.0)
        out[i, 0] = m
        out[i, 1] = math.sqrt(var)
        out[i, 2] = n_eff
        # the weighted centroid's offset across the axis, and the variance of that centroid's
        # position: its points' weighted scatter about it over the effective count (Kish)
        cx, cy, cz = lx / w, ly / w, lz / w
        out[i, 4], out[i, 5], out[i, 6] = cx, cy, cz
        out[i, 7] = max(kk / w - (cx * cx + cy * cy + cz * cz), 0.0) / n_eff
