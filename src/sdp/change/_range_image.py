"""The range image: what a scan saw along each ray from its sensor, and the class of a point's ray.

The range image is spherical (azimuth, elevation about the sensor origin), as Underwood et al.
[1] for change detection along laser rays, so any field of view works, from a Kinect's 57° to
a full turn; each cell keeps the nearest and the farthest return. Cells are ``cell_factor``
times the scan's angular point spacing, measured from the solid angle the scan covers (O(n), no
neighbour search). A scan that samples one axis more sparsely than the other (a spinning LiDAR's
rings, 0.5–2° apart, 0.2° along them) gets cells of ``cell_factor`` times its step along that
axis (:func:`_axis_cells`; at most twice the square cell, so that rings far apart in range do not
share one), and there a ray whose cells on one side hold returns all nearer and on the other side
all farther passes through the surface sampled between them (same surface), as the floor between
two rings; where no ring lies within reach on a side (a VLP-32C's rings, 0.33° apart near the
horizon and 9.4° at the bottom), the nearest one within ``_MAX_GAP_CELLS`` cells is asked. A ray
beyond the angles the scan sent rays to (more than half a cell past its extreme returns, none along
a sparse axis) is unobserved whatever the cells beside it hold: the floor below a LiDAR's lowest ring.

An organized depth camera's frame (a PCD image, an organized bag message) needs no angles: its
returns fit one pinhole camera (:func:`sdp._core._pinhole.fit_camera`), and its image is then the camera's own
pixels (cells of ``cell_factor`` pixels over the rows and columns holding a return, each return in
the cell of its pixel, a point's ray through the pixel the fitted camera projects it to). Every
pixel of the frame is a ray the camera sent, whether it returned or not, so the field of view is
the whole image up to its border, not the hull of the returns.

A scanner whose vertical is known (an E57 scan's pose: ``pole``) has its image laid out about it,
so that the image's rows are its own and the angles it sent rays to its own: the direction its
returns spread least along tilts towards a cliff filling one side (10–16° on a rock cut), where
the image's rows would cut the scanner's aslant and the ground below its lowest ray (never
sampled) lies inside the image beside ground it did see. Its elevation is then bridged as a
sparse axis's (:attr:`RangeImage.scanner_rows`): at grazing range consecutive rows lie metres apart
on the ground, farther than the band, and a ray between a nearer row and a farther one passes
through the ground between them.

A point's ray is compared with the returns of the cells within ``reach`` of its own, with a band
``b(r) = max(range_noise·r², floor)``: the band grows as r², as the depth noise of triangulation
sensors such as the Kinect (Khoshelham and Elberink [2]: σ_z ≈ 1.4e-3·r² m, depth steps ≈
2.9e-3·r²). The classes (:meth:`RangeImage.classify`) and what :mod:`sdp.change._visibility` makes
of them are described there.

References
----------
.. [1] J. P. Underwood, D. Gillsjö, T. Bailey, V. Vlaskine, "Explicit 3D change detection using
   ray-tracing in spherical coordinates", ICRA 2013.
.. [2] K. Khoshelham, S. O. Elberink, "Accuracy and resolution of Kinect depth data for indoor
   mapping applications", Sensors 12(2), 2012.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
import numpy.typing as npt

from .._core._pinhole import Camera
from ..errors import InvalidPointsError

__all__ = ["HIDDEN", "SAME_SURFACE", "SEEN_FREE", "UNOBSERVED", "RangeImage", "sees"]

#: Classes of :meth:`RangeImage.classify`.
SEEN_FREE, SAME_SURFACE, HIDDEN, UNOBSERVED = 0, 1, 2, 3

_MAX_CELLS = 50_000_000  # a range image larger than this gets coarser cells (400 MB of float64)
_DIRECTION_SAMPLE = 5_000  # points used to choose the image's frame
_MAX_COARSENING = 6  # doublings of a sparse axis's cell (64×): a 16-ring LiDAR's 2° rings at a 0.2° step need 2
_SPARSE = 0.75  # an axis whose occupied cells have an occupied next cell this much less often is sampled sparsely
_MAX_STRETCH = 2.0  # a sparse axis's cells at most this many square cells: wider, near and far rings share a cell
_MAX_GAP_CELLS = 8  # cells searched beyond reach along a sparse axis for the rings on either side of a ray

# ---------------------------------------------------------------- kernels (compiled once, cached)
# Serial on purpose: a few ms of work each, where a thread pool on busy shared cores costs more
# than it saves (measured: the plane fits 0.5 ms serial, 16 ms parallel on a loaded 2-core machine).

# Each branch below is a select of two values both computed (no early exit, no exception: the
# numpy error model), so that the angles' loop runs on SIMD lanes; the values are those of the
# branching form, operation for operation.

@nb.njit(cache=True, inline="always")
def _atan01(a):
    """atan(a) for 0 ≤ a ≤ 1 within 4e-10 rad: above tan(π/8), π/4 + atan((a − 1)/(a + 1)), so
    the argument of the alternating Taylor series stays within ±tan(π/8), where its terms up to
    t¹⁹ leave less than the next (twice as fast as libm's atan2, far below a range-image cell)."""
    big = a > 0.41421356237309503
    off = 0.7853981633974483 if big else 0.0
    a = (a - 1.0) / (a + 1.0) if big else a
    s = a * a
    p = -1.0 / 19.0
    p = p * s + 1.0 / 17.0
    p = p * s - 1.0 / 15.0
    p = p * s + 1.0 / 13.0
    p = p * s - 1.0 / 11.0
    p = p * s + 1.0 / 9.0
    p = p * s - 1.0 / 7.0
    p = p * s + 1.0 / 5.0
    p = p * s - 1.0 / 3.0
    return off + a + a * s * p


@nb.njit(cache=True, inline="always")
def _atan2(y, x):
    """atan2(y, x) by :func:`_atan01` (atan2(0, 0) = 0)."""
    ax, ay = abs(x), abs(y)
    steep = ax < ay
    num = ax if steep else ay
    den = ay if steep else ax
    r = _atan01(num / den) if den > 0.0 else 0.0
    r = 1.5707963267948966 - r if steep else r
    r = 3.141592653589793 - r if x < 0.0 else r
    return -r if y < 0.0 else r


_BLOCK = 512  # points whose coordinates are copied into contiguous buffers before the SIMD loop


@nb.njit(cache=True, nogil=True, fastmath={"contract", "arcp"}, error_model="numpy")  # no NaN or inf assumptions
def _angles(points, origin, frame):
    """Azimuth, elevation (radians) and range of each point seen from ``origin``; frame rows are
    forward (azimuth 0), left (azimuth +π/2) and pole (elevation +π/2). Range 0 gives NaN angles.
    Also (lowest azimuth, lowest elevation, highest azimuth, highest elevation, count) of the
    finite angles. The points go through in blocks, each copied to three contiguous columns
    first: the SIMD loop then loads contiguous lanes (from the rows' interleaved coordinates
    the compiled loop stays on scalars)."""
    n = points.shape[0]
    az = np.empty(n)
    el = np.empty(n)
    rng = np.empty(n)
    bx = np.empty(_BLOCK)
    by = np.empty(_BLOCK)
    bz = np.empty(_BLOCK)
    o0, o1, o2 = origin[0], origin[1], origin[2]
    f00, f01, f02 = frame[0, 0], frame[0, 1], frame[0, 2]
    f10, f11, f12 = frame[1, 0], frame[1, 1], frame[1, 2]
    f20, f21, f22 = frame[2, 0], frame[2, 1], frame[2, 2]
    lo_a = lo_e = np.inf
    hi_a = hi_e = -np.inf
    count = 0
    for b0 in range(0, n, _BLOCK):
        m = min(_BLOCK, n - b0)
        for i in range(m):
            bx[i] = points[b0 + i, 0] - o0
            by[i] = points[b0 + i, 1] - o1
            bz[i] = points[b0 + i, 2] - o2
        for i in range(m):
            dx, dy, dz = bx[i], by[i], bz[i]
            f = dx * f00 + dy * f01 + dz * f02
            lf = dx * f10 + dy * f11 + dz * f12
            p = dx * f20 + dy * f21 + dz * f22
            h2 = f * f + lf * lf
            r = math.sqrt(h2 + p * p)
            a = _atan2(lf, f)
            e = _atan2(p, math.sqrt(h2))
            rng[b0 + i] = r
            az[b0 + i] = a if r > 0.0 else np.nan
            el[b0 + i] = e if r > 0.0 else np.nan
        for i in range(b0, b0 + m):  # in order, as min and max of ±0 depend on it
            a = az[i]
            if math.isfinite(a):
                lo_a, hi_a = min(lo_a, a), max(hi_a, a)
                lo_e, hi_e = min(lo_e, el[i]), max(hi_e, el[i])
                count += 1
    return az, el, rng, (lo_a, lo_e, hi_a, hi_e, count)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _project(points, origin, matrix):
    """Column, row (pixels) and range of each point seen by a pinhole camera at ``origin``
    (``matrix``: :attr:`Camera.matrix`); NaN pixels behind the camera or at its origin. The
    fourth item, empty bounds, keeps :func:`_angles`' signature."""
    n = points.shape[0]
    u = np.empty(n)
    v = np.empty(n)
    rng = np.empty(n)
    m = matrix
    for i in range(n):
        dx, dy, dz = points[i, 0] - origin[0], points[i, 1] - origin[1], points[i, 2] - origin[2]
        w = m[2, 0] * dx + m[2, 1] * dy + m[2, 2] * dz
        rng[i] = math.sqrt(dx * dx + dy * dy + dz * dz)
        if w > 0.0:
            u[i] = (m[0, 0] * dx + m[0, 1] * dy + m[0, 2] * dz) / w
            v[i] = (m[1, 0] * dx + m[1, 1] * dy + m[1, 2] * dz) / w
        else:
            u[i] = v[i] = np.nan
    return u, v, rng, (0.0, 0.0, 0.0, 0.0, 0)


@nb.njit(cache=True, nogil=True)
def _near_far_pixels(points, pixels, width, origin, lo_u, lo_v, cell, n_u, n_v):
    """:func:`_near_far` of a camera's returns on cells of ``cell`` pixels from its own pixels
    (row · width + column, ascending): the columns' and rows' cells looked up, no angle."""
    near = np.full(n_u * n_v, np.inf)
    far = np.full(n_u * n_v, -np.inf)
    col = np.empty(width, np.int64)
    for c in range(width):
        col[c] = min(max(int((c - lo_u) / cell), 0), n_u - 1) * n_v
    row, start, e = -1, 0, 0
    for i in range(pixels.shape[0]):
        p = pixels[i]
        if p >= start + width or row < 0:  # a new row (pixels ascend)
            row = p // width
            start = row * width
            e = min(max(int((row - lo_v) / cell), 0), n_v - 1)
        dx, dy, dz = points[i, 0] - origin[0], points[i, 1] - origin[1], points[i, 2] - origin[2]
        r = math.sqrt(dx * dx + dy * dy + dz * dz)
        j = col[p - start] + e
        near[j] = min(near[j], r)
        far[j] = max(far[j], r)
    return near, far


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _occupied_solid_angle(az, el, lo_az, lo_el, bin_size, n_az, n_el):
    """Solid angle (sr) of the bins of a coarse (azimuth, elevation) grid holding a point, and the
    number of points binned. Each block's bins are computed on SIMD lanes first (-1: no angle)."""
    occ = np.zeros(n_az * n_el, np.bool_)
    bins = np.empty(_BLOCK, np.int64)
    n = 0
    for b0 in range(0, az.shape[0], _BLOCK):
        m = min(_BLOCK, az.shape[0] - b0)
        for i in range(m):
            x, y = az[b0 + i], el[b0 + i]
            a = min(int((x - lo_az) / bin_size), n_az - 1)
            e = min(int((y - lo_el) / bin_size), n_el - 1)
            bins[i] = a * n_el + e if math.isfinite(x) else -1
        for i in range(m):
            if bins[i] >= 0:
                occ[bins[i]] = True
                n += 1
    omega = 0.0
    for a in range(n_az):
        for e in range(n_el):
            if occ[a * n_el + e]:
                omega += bin_size * bin_size * math.cos(lo_el + (e + 0.5) * bin_size)
    return omega, n


@nb.njit(cache=True, nogil=True)
def _near_far(az, el, rng, lo_az, lo_el, cell, cell_el, n_az, n_el, half):
    """Nearest and farthest range per cell (inf / -inf: no return); cells of ``cell`` in azimuth,
    ``cell_el`` in elevation. ``half`` (2 n_az × 2 n_el, or empty): marks the cells of half
    those sizes holding a return, in the same pass."""
    halves = half.shape[0] > 0
    near = np.full(n_az * n_el, np.inf)
    far = np.full(n_az * n_el, -np.inf)
    for i in range(az.shape[0]):
        if not math.isfinite(az[i]):
            continue
        u = (az[i] - lo_az) / cell
        v = (el[i] - lo_el) / cell_el
        a = int(u)
        e = int(v)
        if a < 0 or e < 0 or a >= n_az or e >= n_el:
            continue
        if halves:
            half[min(int(2 * u), 2 * n_az - 1) * 2 * n_el + min(int(2 * v), 2 * n_el - 1)] = True
        j = a * n_el + e
        near[j] = min(near[j], rng[i])
        far[j] = max(far[j], rng[i])
    return near, far


@nb.njit(cache=True, nogil=True)
def _classify(az, el, rng, near, far, lo, hi, margin, cell, cell_el, n_az, n_el, reach, noise, floor, sparse):
    """Class of each ray (see :meth:`RangeImage.classify`) from the cells within ``reach`` of its own,
    and for hidden rays the range of the hiding surface (the farthest of the nearer cells' returns).
    A ray beyond the angles of the scan's returns (``lo``, ``hi``: azimuth, elevation) by more
    than ``margin`` (:attr:`RangeImage.margin`) is unobserved: the scan sent no ray there. Along the
    ``sparse`` axis (0 azimuth, 1 elevation, -1 none: :func:`_axis_cells`), a ray between a cell
    whose returns are all nearer and one on its other side whose returns are all farther passes
    through the surface sampled on either side of it: the same surface; on a side without a return
    within reach, the nearest cells up to ``_MAX_GAP_CELLS`` away are asked (for that alone: so far
    off, they neither hide the ray nor say it was seen)."""
    out = np.empty(az.shape[0], np.int8)
    hider = np.full(az.shape[0], np.nan)
    for i in range(az.shape[0]):
        r = rng[i]
        band = max(noise * r * r, floor)
        observed = False
        same = False
        nearer = False
        hide = -np.inf
        below_nearer = below_farther = above_nearer = above_farther = False
        seen_below = seen_above = False  # a return within reach strictly on that side of the ray's cell
        if math.isfinite(az[i]):
            a0 = int(math.floor((az[i] - lo[0]) / cell))
            e0 = int(math.floor((el[i] - lo[1]) / cell_el))
            off = not (lo[0] - margin[0] <= az[i] <= hi[0] + margin[0]) or not (lo[1] - margin[1] <= el[i]
                                                                                   <= hi[1] + margin[1])
            if off:
                a0 = e0 = -2 * reach - 2  # off the scan's angles: no cell within reach
            for a in range(max(a0 - reach, 0), min(a0 + reach + 1, n_az)):
                for e in range(max(e0 - reach, 0), min(e0 + reach + 1, n_el)):
                    j = a * n_el + e
                    if near[j] == np.inf:
                        continue
                    observed = True
                    if near[j] - band <= r <= far[j] + band:
                        same = True
                        break  # the same surface decides: the other cells need not be read
                    step = (a - a0) if sparse == 0 else (e - e0)
                    seen_below |= step < 0
                    seen_above |= step > 0
                    if r > far[j]:
                        nearer = True
                        hide = max(hide, far[j])
                        below_nearer |= step <= 0
                        above_nearer |= step >= 0
                    else:
                        below_farther |= step <= 0
                        above_farther |= step >= 0
                if same:
                    break
            if sparse >= 0 and not same and not off:  # the nearest rings beyond reach, when none is within it
                for side in (-1, 1):
                    if seen_below if side < 0 else seen_above:
                        continue
                    for k in range(reach + 1, reach + 1 + _MAX_GAP_CELLS):
                        found = False
                        for o in range(-reach, reach + 1):
                            a, e = (a0 + side * k, e0 + o) if sparse == 0 else (a0 + o, e0 + side * k)
                            if a < 0 or e < 0 or a >= n_az or e >= n_el:
                                continue
                            j = a * n_el + e
                            if near[j] == np.inf:
                                continue
                            found = True  # its returns bracket the ray or not; they hide nothing this far
                            if r > far[j]:
                                below_nearer |= side < 0
                                above_nearer |= side > 0
                            else:
                                below_farther |= side < 0
                                above_farther |= side > 0
                        if found:
                            break
                same = (below_nearer and above_farther) or (below_farther and above_nearer)
        if same:
            out[i] = 1  # SAME_SURFACE
        elif nearer:
            out[i] = 2  # HIDDEN
            hider[i] = hide
        elif observed:
            out[i] = 0  # SEEN_FREE
        else:
            out[i] = 3  # UNOBSERVED
    return out, hider


@nb.njit(cache=True, nogil=True)
def _sampled_around(az, el, near, lo, cell, cell_el, n_az, n_el):
    """Per ray: at least half of the 5 × 5 cells around its own (those on the image) hold a return."""
    out = np.zeros(az.shape[0], np.bool_)
    for i in range(az.shape[0]):
        if not math.isfinite(az[i]):
            continue
        a0 = int(math.floor((az[i] - lo[0]) / cell))
        e0 = int(math.floor((el[i] - lo[1]) / cell_el))
        held = cells = 0
        for a in range(max(a0 - 2, 0), min(a0 + 3, n_az)):
            for e in range(max(e0 - 2, 0), min(e0 + 3, n_el)):
                cells += 1
                held += near[a * n_el + e] < np.inf
        out[i] = cells > 0 and 2 * held >= cells
    return out


@nb.njit(cache=True, nogil=True)
def _hider_points(points, origin, hide, rng, cls):
    """Where the surface hiding each :data:`HIDDEN` point was seen: origin + (point − origin) ·
    hide / range (NaN rows for the other classes)."""
    out = np.full(points.shape, np.nan)
    for i in range(points.shape[0]):
        if cls[i] == 2:  # HIDDEN
            t = hide[i] / rng[i]
            for d in range(3):
                out[i, d] = origin[d] + (points[i, d] - origin[d]) * t
    return out


def _camera_shape(camera: Camera, cell: float) -> tuple[int, int]:
    """Cells (columns, rows) of ``cell`` pixels over the rows and columns of ``camera`` holding a return."""
    r0, r1, c0, c1 = (int(b) for b in camera.box)
    return int(math.ceil((c1 - c0 + 1) / cell)), int(math.ceil((r1 - r0 + 1) / cell))


# ---------------------------------------------------------------- range image

@dataclass(frozen=True)
class RangeImage:
    """The nearest and farthest range a scan saw per angular cell, seen from its sensor origin.

    Attributes
    ----------
    origin : ndarray (3,) float64
        Sensor position (world units).
    frame : ndarray (3, 3) float64
        Rows: forward (azimuth 0, the scan's main viewing direction), left, pole (elevation
        +π/2: the scanner's own vertical where known, else the direction the scan spreads least
        along).
    cell : float
        Cell size in azimuth (radians).
    spacing : float
        Angular point spacing the cell was derived from (radians).
    lo : ndarray (2,) float64
        Azimuth and elevation of the first cell's corner.
    shape : tuple of int
        Cells along azimuth and elevation.
    near, far : ndarray (shape[0] * shape[1],) float64
        Nearest and farthest range per cell; ``inf`` and ``-inf`` where the scan has no return.
    view : ndarray of bool (shape[0] * shape[1],)
        The field of view: the convex hull of the cells with a return (a cell without return
        inside it is a ray that found nothing in range).
    reach_range : float
        The farthest return of the scan: how far the sensor is known to see.
    cell_el : float
        Cell size in elevation (radians): ``cell`` unless the scan samples one axis more
        sparsely than the other (:func:`_axis_cells`: a spinning LiDAR's rings).
    sparse : int
        That axis (0 azimuth, 1 elevation), whose cells were made coarser; -1 for neither. Along
        it, a ray between returns nearer and farther than its point is on the surface between them.
    hi : ndarray (2,) float64
        The highest azimuth and elevation of a return: with ``lo``, the angles the scan sent rays
        to (and :attr:`margin` beyond them; the last cell reaches farther).
    rays_sent : bool
        The scan sent a ray along every direction of its field of view, whatever share of them came
        back (a camera's image, an organized cloud, a terrestrial scan's grid): a missing return
        inside the view is then a ray that found nothing (:meth:`seen_free`). False for a scan known
        to sample its view irregularly (an unorganized file or message from a sensor: a rosette
        scanner's petals leave half of its view unsampled).
    scanner_rows : bool
        The image is laid out about its scanner's own vertical (``pole``): its rows are the
        scanner's, and elevation is bridged as a sparse axis is (a ray between a row nearer and
        one farther is on the ground between them, metres apart at grazing range), its cells and
        margin left square.
    camera : ndarray (3, 3) float64 or None
        A depth camera's image (:meth:`from_points` with a :class:`Camera`): the
        :attr:`Camera.matrix` projecting a point to its pixel, and the axes called azimuth and
        elevation above are its columns and rows, in pixels (``frame`` unused, ``spacing`` 1).
    """

    origin: np.ndarray
    frame: np.ndarray
    cell: float
    spacing: float
    lo: np.ndarray
    shape: tuple[int, int]
    near: np.ndarray
    far: np.ndarray
    view: np.ndarray
    reach_range: float
    cell_el: float
    sparse: int
    hi: np.ndarray
    rays_sent: bool = True
    scanner_rows: bool = False
    camera: np.ndarray | None = None

    @classmethod
    def from_points(cls, points: np.ndarray, origin: npt.ArrayLike, *, cell_factor: float = 1.5,
                    spacing: float | None = None, rays_sent: bool = True,
                    camera: Camera | None = None, pole: npt.ArrayLike | None = None) -> RangeImage:
        """Range image of ``points`` seen from ``origin``.

        Parameters
        ----------
        points : ndarray (n, 3) float64
            The scan (finite rows).
        origin : array_like (3,)
            Its sensor position.
        cell_factor : float
            Cell size in units of the angular point spacing.
        spacing : float, optional
            Angular point spacing (radians); when None, sqrt(solid angle covered / points).
        rays_sent : bool
            :attr:`rays_sent`.
        camera : Camera, optional
            The pinhole fitted to ``points``, an organized frame (:func:`sdp._core._pinhole.fit_camera`, its pixels
            one per row of ``points``): the image is then the camera's pixels (module docstring),
            its view the whole image, reaching its border whether those rays returned or not (a
            camera's pixels beyond its range, the sky), where the returns alone would end it at
            the farthest pixels that returned.
        pole : array_like (3,), optional
            The sensor's own vertical (:attr:`sdp.io.Cloud.poles`: an E57 scan's z turned by its
            pose), the image's elevation +π/2: its rows are then the scanner's, and the angles it
            sent rays to (:attr:`lo`, :attr:`hi`) its own (:attr:`scanner_rows`). None: the
            direction the points spread least along (:func:`_view_frame`).

        Returns
        -------
        RangeImage
        """
        points = np.ascontiguousarray(points, dtype=np.float64)
        origin = np.asarray(origin, dtype=np.float64)
        # a sparse grid of many pixels (a TLS grid stored as an organized PCD) beyond _MAX_CELLS: the
        # angular image, whose cells coarsen
        if camera is not None and len(camera.pixels) == len(points) \
                and math.prod(_camera_shape(camera, cell_factor)) <= _MAX_CELLS:
            return cls._from_camera(points, origin, camera, cell_factor=cell_factor, rays_sent=rays_sent)
        frame = _view_frame(points, origin, None if pole is None else _unit_pole(pole))
        az, el, rng, (lo_a, lo_e, hi_a, hi_e, n) = _angles(points, origin, frame)
        if n == 0:
            raise InvalidPointsError("sensor_origin coincides with every point: no ray to follow")
        lo = np.array([lo_a, lo_e])
        extent = np.array([hi_a, hi_e]) - lo
        if spacing is None:
            spacing = _angular_spacing(az, el, lo, extent, n)
        cell = max(cell_factor * spacing, 1e-9, float(np.sqrt(np.prod(extent + 1e-9) / _MAX_CELLS)))
        shape = (int(extent[0] // cell) + 1, int(extent[1] // cell) + 1)
        # the cells of half a cell holding a return (not for images this large: a dense scanner's)
        half = np.zeros(4 * shape[0] * shape[1] if 4 * shape[0] * shape[1] <= _MAX_CELLS else 0, np.bool_)
        near, far = _near_far(az, el, rng, lo[0], lo[1], cell, cell, shape[0], shape[1], half)
        cells, sparse = ([cell, cell], -1) if not half.size else \
            _axis_cells(az, el, lo, extent, cell, cell_factor, half.reshape(2 * shape[0], 2 * shape[1]))
        if sparse >= 0:
            shape = (int(extent[0] // cells[0]) + 1, int(extent[1] // cells[1]) + 1)
            near, far = _near_far(az, el, rng, lo[0], lo[1], cells[0], cells[1], shape[0], shape[1], half[:0])
        occupied = np.isfinite(near).reshape(shape)
        view = _convex_hull(occupied)
        return cls(origin, frame, float(cells[0]), float(spacing), lo, shape, near, far, view.ravel(),
                   float(far[np.isfinite(far)].max()), float(cells[1]), sparse, np.array([hi_a, hi_e]),
                   bool(rays_sent), pole is not None)

    @classmethod
    def _from_camera(cls, points, origin, camera: Camera, *, cell_factor: float, rays_sent: bool) -> RangeImage:
        """:meth:`from_points` of an organized camera frame: cells of ``cell_factor`` pixels over the
        rows and columns holding a return, every one of them in the view."""
        r0, r1, c0, c1 = camera.box
        cell = float(cell_factor)
        lo = np.array([c0 - 0.5, r0 - 0.5], np.float64)  # the edges of the outer pixels
        hi = np.array([c1 + 0.5, r1 + 0.5], np.float64)
        shape = _camera_shape(camera, cell)
        near, far = _near_far_pixels(points, camera.pixels, camera.width, origin, lo[0], lo[1], cell, *shape)
        returned = far[np.isfinite(far)]
        if returned.size == 0 or not returned.max() > 0:
            raise InvalidPointsError("sensor_origin coincides with every point: no ray to follow")
        return cls(origin, np.eye(3), cell, 1.0, lo, shape, near, far, np.ones(shape[0] * shape[1], bool),
                   float(returned.max()), cell, -1, hi, bool(rays_sent), camera=camera.matrix)

    @property
    def margin(self) -> np.ndarray:
        """How far beyond its extreme returns (azimuth, elevation) the scan is taken to have looked:
        half a cell (a pixel's own width), none along a sparse axis (below a LiDAR's lowest ring,
        the floor was never sampled, however near the ring); none for a camera's image, whose
        edges are its outer pixels' own."""
        if self.camera is not None:
            return np.zeros(2)
        return np.array([0.0 if self.sparse == 0 else self.cell / 2, 0.0 if self.sparse == 1 else self.cell_el / 2])

    def _coords(self, points: np.ndarray):
        """(azimuth, elevation, range, bounds) of contiguous ``points``: a camera's columns and rows."""
        if self.camera is not None:
            return _project(points, self.origin, self.camera)
        return _angles(points, self.origin, self.frame)

    def seen_free(self, points: np.ndarray) -> np.ndarray:
        """Did the sensor look along each ray (of :data:`UNOBSERVED` points) and find nothing?
        Inside the field of view (:meth:`in_view`); for a scan not known to have sent every ray
        (not :attr:`rays_sent`), also where it sampled the directions around: at least half of
        the 5 × 5 cells around the ray's own hold a return. A camera's dropout (a dark or shiny
        patch) is a ray that went out and came back empty; a scan pattern that leaves most
        directions unsampled (a rosette scanner's gaps between its petals) says nothing of the
        rays it did not send."""
        points = np.ascontiguousarray(points, dtype=np.float64)
        view = self.in_view(points)
        if self.rays_sent:
            return view
        az, el, _, _ = self._coords(points)
        return view & _sampled_around(az, el, self.near, self.lo, self.cell, self.cell_el, self.shape[0],
                                      self.shape[1])

    def in_view(self, points: np.ndarray) -> np.ndarray:
        """Is each point inside the field of view (:attr:`view`) and within :attr:`reach_range`?"""
        az, el, rng, _ = self._coords(np.ascontiguousarray(points, dtype=np.float64))
        with np.errstate(invalid="ignore"):
            a = np.floor((az - self.lo[0]) / self.cell)
            e = np.floor((el - self.lo[1]) / self.cell_el)
            ok = (a >= 0) & (a < self.shape[0]) & (e >= 0) & (e < self.shape[1]) & (rng <= self.reach_range) \
                & (az <= self.hi[0] + self.margin[0]) & (el <= self.hi[1] + self.margin[1])
        out = np.zeros(len(az), bool)
        out[ok] = self.view[a[ok].astype(np.int64) * self.shape[1] + e[ok].astype(np.int64)]
        return out

    def classify(self, points: np.ndarray, *, range_noise: float, floor: float = 0.0, reach: int = 1,
                 hiders: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Class of each point along its ray from :attr:`origin` (int8, one per point); with
        ``hiders``, also where the surface hiding each :data:`HIDDEN` point was seen (world
        coordinates on the point's ray, NaN for the other classes).

        The returns compared are those of the cells within ``reach`` cells of the ray's own;
        the band is b = max(``range_noise``·r², ``floor``) at the point's range r.
        :data:`SAME_SURFACE` (1): a cell spans the point's range (nearest − b ≤ r ≤ farthest + b);
        else :data:`HIDDEN` (2): a cell's returns are all nearer; else :data:`SEEN_FREE` (0):
        the returns are all farther than r + b; :data:`UNOBSERVED` (3): no return at all.
        """
        points = np.ascontiguousarray(points, dtype=np.float64)
        az, el, rng, _ = self._coords(points)
        cls, hide = _classify(az, el, rng, self.near, self.far, self.lo, self.hi, self.margin, self.cell, self.cell_el,
                              self.shape[0], self.shape[1], int(reach), float(range_noise), float(floor),
                              1 if self.scanner_rows and self.sparse < 0 else self.sparse)
        if not hiders:
            return cls
        return cls, _hider_points(points, self.origin, hide, rng, cls)


def _axis_cells(az, el, lo, extent, cell: float, cell_factor: float, half: np.ndarray) -> tuple[list[float], int]:
    """([azimuth cell, elevation cell], the axis sampled sparsely or -1); ``half``: the cells of
    half ``cell`` holding a return.

    ``cell`` comes from the mean angular spacing (the square root of the solid angle per point),
    right for a camera's square pixels. A spinning LiDAR steps 0.5–2° between its rings and 0.2°
    along them: on square cells of the mean spacing, a point between two rings finds only one
    ring's returns near its ray, the nearer (hidden) or the farther (seen free), on a floor the
    sensor did see. Along an axis sampled at least once per cell, an occupied cell's next cell is
    occupied as often as along the other axis (surfaces continue; edges and dropouts cut both
    alike); where the sampling step s exceeds the cell c, a share s/c − 1 of the rows is empty
    and that frequency falls to about 2 − s/c. On cells of half ``cell``, an axis whose frequency
    is below :data:`_SPARSE` of the other's (s > 0.6 ``cell``, while the other axis is sampled
    finer) is sparse: its cell is doubled until it is sampled again (c ≥ s/1.25), and that
    axis's cells are ``cell_factor`` times that step, at least ``cell`` and at most
    :data:`_MAX_STRETCH` times it (rings spaced unevenly double the cell up to their widest gap: 8°
    on a VLP-32C, where a cell then held the ground from 5 to 40 m and a car 12 m away "was" it;
    the gaps wider than the cell are bridged by :func:`_classify`). A camera's pixels leave both
    axes alike, and its cells as they were."""
    def occupancy(cells):
        shape = (int(extent[0] // cells[0]) + 1, int(extent[1] // cells[1]) + 1)
        return _occupied(az, el, lo[0], lo[1], cells[0], cells[1], shape[0], shape[1]).reshape(shape)

    fine = [cell / 2, cell / 2]
    freq = _next_occupied(half)
    if freq[1] < _SPARSE * freq[0]:
        axis = 1
    elif freq[0] < _SPARSE * freq[1]:
        axis = 0
    else:
        return [cell, cell], -1
    for _ in range(_MAX_COARSENING):
        fine[axis] *= 2.0
        freq = _next_occupied(occupancy(fine))
        if freq[axis] >= _SPARSE * freq[1 - axis]:
            break
    cells = [cell, cell]
    cells[axis] = min(max(cell, cell_factor * fine[axis]), _MAX_STRETCH * cell)
    return cells, axis


@nb.njit(cache=True, nogil=True)
def _next_occupied(occupied):
    """How often an occupied cell's next cell along azimuth, and along elevation, is occupied."""
    n_az, n_el = occupied.shape
    cells = next_az = next_el = 0
    for a in range(n_az):
        for e in range(n_el):
            if occupied[a, e]:
                cells += 1
                next_az += a + 1 < n_az and occupied[a + 1, e]
                next_el += e + 1 < n_el and occupied[a, e + 1]
    return (next_az / cells, next_el / cells) if cells else (1.0, 1.0)


@nb.njit(cache=True, nogil=True)
def _occupied(az, el, lo_az, lo_el, cell, cell_el, n_az, n_el):
    """Cells of ``cell`` × ``cell_el`` holding a return."""
    occ = np.zeros(n_az * n_el, np.bool_)
    for i in range(az.shape[0]):
        if math.isfinite(az[i]):
            a = min(int((az[i] - lo_az) / cell), n_az - 1)
            e = min(int((el[i] - lo_el) / cell_el), n_el - 1)
            occ[a * n_el + e] = True
    return occ


@nb.njit(cache=True, nogil=True)
def _hull_polygon(p):
    """Vertices of the convex hull of points ``p`` sorted by x then y, counter-clockwise from the
    lowest-x point, collinear points left out (Andrew's monotone chain)."""
    n = p.shape[0]
    hull = np.empty((2 * n, 2))
    m = 0
    for sweep in range(2):  # the lower chain left to right, then the upper one back
        first = m
        for j in range(n):
            i = j if sweep == 0 else n - 1 - j
            while m - first >= 2 and ((hull[m - 1, 0] - hull[m - 2, 0]) * (p[i, 1] - hull[m - 2, 1])
                                     - (hull[m - 1, 1] - hull[m - 2, 1]) * (p[i, 0] - hull[m - 2, 0])) <= 0.0:
                m -= 1
            hull[m] = p[i]
            m += 1
        m -= 1  # each chain's last point starts the other
    return hull[:max(m, 1)]


def _convex_hull(seen: np.ndarray) -> np.ndarray:
    """The cells whose centre lies inside the convex hull of the True cells' squares: the hull of
    each row's outermost cells, filled row by row (a convex polygon cuts each row in one
    interval), 0.25 ms on a Kinect frame's image where ``skimage.morphology.convex_hull_image``,
    whose border rule differs slightly, takes 18 ms."""
    corners = _sorted_corners(seen)
    if len(corners) == 0:
        return np.zeros_like(seen)
    return _fill_polygon(_hull_polygon(corners), seen.shape[0], seen.shape[1])


@nb.njit(cache=True, nogil=True)
def _sorted_corners(seen):
    """The corners of each row's first and last True cell (the cell (a, c) spans a ± 0.5,
    c ± 0.5), sorted by x then y, in one pass over the grid: the corners at x = a − 0.5 are
    those of rows a − 1 and a, eight at most, sorted by insertion."""
    n_rows, n_cols = seen.shape
    first = np.full(n_rows, -1, np.int64)
    last = np.full(n_rows, -1, np.int64)
    used = 0
    for a in range(n_rows):
        for c in range(n_cols):
            if seen[a, c]:
                first[a] = c
                break
        if first[a] >= 0:
            used += 1
            for c in range(n_cols - 1, -1, -1):
                if seen[a, c]:
                    last[a] = c
                    break
    out = np.empty((8 * used, 2))
    ys = np.empty(8)
    m = 0
    for xa in range(n_rows + 1):  # the line x = xa − 0.5
        cnt = 0
        for a in range(xa - 1, xa + 1):
            if 0 <= a < n_rows and first[a] >= 0:
                ys[cnt], ys[cnt + 1] = first[a] - 0.5, first[a] + 0.5
                ys[cnt + 2], ys[cnt + 3] = last[a] - 0.5, last[a] + 0.5
                cnt += 4
        for i in range(1, cnt):
            y = ys[i]
            j = i
            while j > 0 and ys[j - 1] > y:
                ys[j] = ys[j - 1]
                j -= 1
            ys[j] = y
        for i in range(cnt):
            out[m, 0], out[m, 1] = xa - 0.5, ys[i]
            m += 1
    return out


@nb.njit(cache=True, nogil=True)
def _fill_polygon(v, n_rows, n_cols):
    """Cells (row, column) of an (n_rows, n_cols) grid whose centre lies in the convex polygon
    ``v`` (vertices in order; x along rows): per row, the interval between the lowest and the
    highest crossing of the polygon's edges."""
    out = np.zeros((n_rows, n_cols), np.bool_)
    m = v.shape[0]
    for a in range(n_rows):
        lo, hi = np.inf, -np.inf
        for i in range(m):
            p0, p1 = v[i, 0], v[i, 1]
            q0, q1 = v[(i + 1) % m, 0], v[(i + 1) % m, 1]
            if not min(p0, q0) <= a <= max(p0, q0):
                continue
            t = (a - p0) / (q0 - p0) if q0 != p0 else 0.0
            e = p1 + t * (q1 - p1)
            lo, hi = min(lo, e), max(hi, e)
        for c in range(n_cols):
            out[a, c] = lo <= c <= hi
    return out


@nb.njit(cache=True, nogil=True)
def _unit_directions(points, origin, step):
    """Unit vectors from ``origin`` to every ``step``-th point (those at the origin left out), as
    ``d / np.linalg.norm(d, axis=1)`` computes them, in one pass."""
    m = (points.shape[0] + step - 1) // step
    out = np.empty((m, 3))
    k = 0
    for i in range(0, points.shape[0], step):
        dx = points[i, 0] - origin[0]
        dy = points[i, 1] - origin[1]
        dz = points[i, 2] - origin[2]
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        if norm > 0.0:
            out[k, 0], out[k, 1], out[k, 2] = dx / norm, dy / norm, dz / norm
            k += 1
    return out[:k]


def _view_frame(points: np.ndarray, origin: np.ndarray, pole: np.ndarray | None = None) -> np.ndarray:
    """Forward = main eigenvector of the unit directions' second moments (sign: towards the mean
    direction), pole = the least one: a camera's cone sits on the equator around azimuth 0, a
    horizontal 360° scan gets a vertical pole; the azimuth seam (±π) lies behind the sensor.

    A scanner's own vertical (``pole``, a unit vector) is taken as it is, forward being the main
    direction made perpendicular to it: the least direction of a terrestrial scan's returns tilts
    towards a cliff filling one side (10–16° on a rock cut), and the image's rows of constant
    elevation would cut the scanner's own rows aslant, its lowest and highest rays (the limits of
    what it sent) no longer a row of the image."""
    d = _unit_directions(points, origin, max(1, len(points) // _DIRECTION_SAMPLE))
    if len(d) == 0 and pole is None:
        return np.eye(3)
    if pole is None:
        w, v = np.linalg.eigh(d.T @ d / len(d))
        forward, pole = v[:, 2], v[:, 0]
    else:
        flat = d - np.outer(d @ pole, pole)  # the directions seen from above the scanner
        w, v = np.linalg.eigh(flat.T @ flat / max(len(d), 1))
        forward = v[:, 2] - (v[:, 2] @ pole) * pole
        if not np.linalg.norm(forward) > 1e-9:  # no direction off the pole: any forward
            forward = np.eye(3)[np.argmin(np.abs(pole))] - pole * pole[np.argmin(np.abs(pole))]
        forward = forward / np.linalg.norm(forward)
    if len(d) and forward @ d.mean(axis=0) < 0:
        forward = -forward
    left = np.cross(pole, forward)
    return np.ascontiguousarray(np.stack([forward, left / np.linalg.norm(left), pole]))


def _unit_pole(pole) -> np.ndarray:
    """``pole`` as a unit vector (3,); one-line :class:`InvalidPointsError` for anything else."""
    p = np.asarray(pole, np.float64)
    if p.shape != (3,) or not np.isfinite(p).all() or not np.linalg.norm(p) > 0:
        raise InvalidPointsError(f"pole: expected a non-zero finite vector x, y, z, got {np.asarray(pole).tolist()}")
    return p / np.linalg.norm(p)


def _angular_spacing(az, el, lo, extent, n) -> float:
    """sqrt(occupied solid angle / n): the pixel pitch of a depth camera, the step of a scanner.
    The solid angle is counted on bins holding about 32 points each where the scan is dense."""
    area = max(float(np.prod(extent)), 1e-18)
    bin_size = math.sqrt(area * 32.0 / max(n, 1))
    n_az, n_el = int(extent[0] // bin_size) + 1, int(extent[1] // bin_size) + 1
    omega, n_binned = _occupied_solid_angle(az, el, lo[0], lo[1], bin_size, n_az, n_el)
    return math.sqrt(omega / max(n_binned, 1))


def sees(image: RangeImage, query: np.ndarray, *, range_noise: float, floor: float) -> np.ndarray:
    """Which of ``query`` the sensor of ``image`` could see: a return at its range (the same
    surface) or beyond it (seen through), or none near its ray inside the field of view (free
    space); not where every return near the ray is nearer (hidden) or outside the view."""
    cls = image.classify(query, range_noise=range_noise, floor=floor)
    seen = (cls == SAME_SURFACE) | (cls == SEEN_FREE)
    missing = cls == UNOBSERVED
    seen[missing] = image.seen_free(query[missing])
    return seen
