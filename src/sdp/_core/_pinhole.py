"""A depth camera's pinhole fitted to an organized frame's returns (the direct linear transform):
which pixel a point projects to, and how far apart the rays of two pixels are at least.

An organized frame (a PCD image, an organized bag message) keeps each return's pixel; its returns
lie on the rays of one pinhole camera, whatever its pose. :func:`fit_camera` finds that camera, so
the frame's own pixels can serve as the neighbourhoods and the range image of the sensor
(:mod:`sdp.change._range_image`, :mod:`sdp.fields._spacing`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

__all__ = ["Camera", "fit_camera", "ray_sine_per_pixel", "reprojection_error"]


@dataclass(frozen=True)
class Camera:
    """A pinhole camera fitted to an organized depth frame (:func:`fit_camera`).

    Attributes
    ----------
    matrix : ndarray (3, 3) float64
        Takes a point's offset d from the sensor to (column · w, row · w, w), w > 0 in front of
        the camera: the intrinsics times the rotation, for the image's own pixels.
    box : ndarray (4,) int64
        The first and last row, first and last column holding a return.
    pixels : ndarray (n,) int64
        Each return's pixel (row · width + column), ascending.
    width : int
        The image's columns.
    """

    matrix: np.ndarray
    box: np.ndarray
    pixels: np.ndarray
    width: int

    def describe(self) -> dict:
        """The camera's intrinsics (K of ``matrix = K R``, Hartley and Zisserman §6.1, with a
        positive diagonal): focal lengths and principal point in pixels, and the field of view
        (degrees) across the rows and columns holding a return, through the principal point."""
        from scipy.linalg import rq

        k = rq(self.matrix)[0]
        k = k * np.sign(np.diag(k))[None, :]  # R's columns' signs moved into K's
        k = k / k[2, 2]
        inv = np.linalg.inv(k)
        r0, r1, c0, c1 = (float(b) for b in self.box)

        def angle(a, b):
            u, v = inv @ np.array([a[0], a[1], 1.0]), inv @ np.array([b[0], b[1], 1.0])
            return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(u, v)), u @ v)))

        cx, cy = float(k[0, 2]), float(k[1, 2])
        return {"focal_px": [float(k[0, 0]), float(k[1, 1])], "principal_point_px": [cx, cy],
                "field_of_view_deg": [angle((c0 - 0.5, cy), (c1 + 0.5, cy)), angle((cx, r0 - 0.5), (cx, r1 + 0.5))]}


def fit_camera(xyz: np.ndarray, pixels: np.ndarray, image: tuple[int, int], origin, *,
               tolerance: float = 0.5, sample: int = 512) -> Camera | None:
    """The pinhole camera of an organized frame's returns, or None where they fit none.

    A depth camera's point of pixel (column c, row r) lies on the ray ``H⁻¹ (c, r, 1)`` from its
    origin, for one 3 × 3 matrix H (the camera's intrinsics times its rotation: a pinhole camera,
    whatever its pose). H is fitted to the returns (``xyz`` at ``pixels``, row · width + column,
    of an ``image`` of (height, width)) by the direct linear transform [1]_ on at most
    ``sample`` of them. None where the returns do not fit one pinhole within ``tolerance``
    pixels (RMS): an organized LiDAR's rings and columns, a distorted image, too few returns, or
    returns whose pixels lie on one line (a single row or column: their rays lie in one plane, which
    every camera seeing that plane along the line fits, so none is the frame's).

    The image is that of the rows and columns holding a return (:attr:`Camera.box`): whole rows
    or columns without one at the image's edge are the margins a depth image registered to a
    colour camera leaves (the PCL grabber's frames: 32 columns and 15 rows), pixels the sensor
    never measured, not rays that found nothing (there, 0.07–0.22 % of a static pair read
    changed after a centimetre's motion). A wall beyond range across the whole image's top is
    lost with them.

    References
    ----------
    .. [1] R. Hartley, A. Zisserman, "Multiple View Geometry in Computer Vision", 2nd ed.,
       Cambridge University Press, 2004, §4.1 (the DLT) and §4.4 (normalization).
    """
    height, width = image
    if len(pixels) < 8 or height < 2 or width < 2:
        return None
    # in kernels that release the GIL: the two epochs' images are built at once on two threads,
    # where some forty small NumPy steps each took three times their time
    step = max(1, len(pixels) // sample)
    origin = np.asarray(origin, np.float64)
    pixels = np.asarray(pixels, np.int64)
    normal, centre, scale, across, n = _pinhole_sums(xyz, pixels, width, origin, step)
    if n < 8 or across < _MIN_ACROSS:
        return None
    try:
        h = np.linalg.eigh(normal)[1][:, 0].reshape(3, 3)  # the least-squares null vector
        inv = np.linalg.inv(h)
    except np.linalg.LinAlgError:  # returns no camera explains (rays in one plane, NaN rows)
        return None
    rms, facing = _pinhole_check(xyz, pixels, width, origin, step, h, inv, centre, scale)
    if not rms <= tolerance:
        return None
    # H is known up to its sign: the one putting the returns in front; then back to whole pixels
    pixel_of = np.array([[scale, 0.0, centre[0]], [0.0, scale, centre[1]], [0.0, 0.0, 1.0]])
    matrix = pixel_of @ (h if facing else -h)
    return Camera(np.ascontiguousarray(matrix), _returned_box(pixels, width), pixels, int(width))


@nb.njit(cache=True, nogil=True)
def _returned_box(pixels, width):
    """(first row, last row, first column, last column) holding a return; ``pixels`` ascending,
    as a frame's rows are kept: each row's first and last return found by bisection."""
    r0, r1 = pixels[0] // width, pixels[-1] // width
    c0, c1 = width, -1
    for r in range(r0, r1 + 1):
        i = np.searchsorted(pixels, r * width)
        j = np.searchsorted(pixels, (r + 1) * width) - 1
        if i <= j:
            c0, c1 = min(c0, pixels[i] % width), max(c1, pixels[j] % width)
    return np.array([r0, r1, c0, c1])


#: The least variance (pixels²) of the returns' pixels across their main direction for a camera to be
#: fitted: 0 for a single row or column, 1/12 for a digital line, thousands for a frame.
_MIN_ACROSS = 1.0


@nb.njit(cache=True, nogil=True)
def _pinhole_sums(xyz, pixels, width, origin, step):
    """(the DLT's normal matrix AᵀA (9, 9), the pixels' centre, their scale, their variance across
    their main direction (pixels²), the rows used) over every ``step``-th return: unit directions d
    and normalized pixels (u, v), two rows each, (dᵀ, 0, −u dᵀ) and (0, dᵀ, −v dᵀ)."""
    n = 0
    su = sv = su2 = sv2 = suv = 0.0
    for i in range(0, pixels.shape[0], step):
        c, r = pixels[i] % width, pixels[i] // width
        su += c
        sv += r
        su2 += c * c
        sv2 += r * r
        suv += c * r
        n += 1
    cu, cv = su / n, sv / n
    vu, vv, cov = max(su2 / n - cu * cu, 0.0), max(sv2 / n - cv * cv, 0.0), suv / n - cu * cv
    across = 0.5 * (vu + vv) - math.sqrt(0.25 * (vu - vv) ** 2 + cov * cov)  # the 2 × 2 covariance's least eigenvalue
    scale = max(math.sqrt(vu) + math.sqrt(vv), 1.0)
    ata = np.zeros((9, 9))
    row = np.empty(9)
    used = 0
    for i in range(0, pixels.shape[0], step):
        dx, dy, dz = xyz[i, 0] - origin[0], xyz[i, 1] - origin[1], xyz[i, 2] - origin[2]
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        if norm == 0.0:
            continue
        dx, dy, dz = dx / norm, dy / norm, dz / norm
        u, v = (pixels[i] % width - cu) / scale, (pixels[i] // width - cv) / scale
        for which in range(2):
            w = u if which == 0 else v
            for k in range(9):
                row[k] = 0.0
            row[3 * which], row[3 * which + 1], row[3 * which + 2] = dx, dy, dz
            row[6], row[7], row[8] = -w * dx, -w * dy, -w * dz
            for a in range(9):
                if row[a] != 0.0:
                    for b in range(9):
                        ata[a, b] += row[a] * row[b]
        used += 1
    return ata, np.array([cu, cv]), scale, across, used


@nb.njit(cache=True, nogil=True)
def _pinhole_check(xyz, pixels, width, origin, step, h, inv, centre, scale):
    """(RMS reprojection error in pixels of the returns used, whether ``inv`` maps their pixels to
    rays pointing at them rather than away)."""
    err2 = 0.0
    dot = 0.0
    n = 0
    for i in range(0, pixels.shape[0], step):
        d0, d1, d2 = xyz[i, 0] - origin[0], xyz[i, 1] - origin[1], xyz[i, 2] - origin[2]
        u, v = (pixels[i] % width - centre[0]) / scale, (pixels[i] // width - centre[1]) / scale
        p0 = h[0, 0] * d0 + h[0, 1] * d1 + h[0, 2] * d2
        p1 = h[1, 0] * d0 + h[1, 1] * d1 + h[1, 2] * d2
        p2 = h[2, 0] * d0 + h[2, 1] * d1 + h[2, 2] * d2
        err2 += ((p0 / p2 - u) ** 2 + (p1 / p2 - v) ** 2) * scale * scale if p2 != 0.0 else np.inf
        for a in range(3):
            dot += (inv[a, 0] * u + inv[a, 1] * v + inv[a, 2]) * (d0 if a == 0 else (d1 if a == 1 else d2))
        n += 1
    return math.sqrt(err2 / max(n, 1)), dot > 0.0


def ray_sine_per_pixel(camera: Camera, height: int, slack: float) -> float:
    """S such that the rays through any two image points (column, row) of the frame's rectangle
    grown by ``slack`` pixels, d pixels apart, make an angle θ with sin θ ≥ S·d.

    The matrix is K R (K upper triangular, K₃₃ = 1, R a rotation; Hartley and Zisserman §6.1): a
    pixel x's ray is Rᵀ (p, 1) with p = A x + t the camera's normalized coordinates (A, t from K⁻¹).
    For two pixels, |(p₁, 1) × (p₂, 1)| = |(p₁, 1) × (p₂ − p₁, 0)| ≥ |p₂ − p₁| ≥ σ_min(A) d, so
    sin θ ≥ σ_min(A) d / (|(p₁, 1)| |(p₂, 1)|); the norms are at most their largest value on the
    rectangle, at a corner (a convex function)."""
    from scipy.linalg import rq

    k = rq(camera.matrix)[0]
    k = k / k[2, 2]
    inv = np.linalg.inv(k)
    lo, hi = -0.5 - slack, np.array([camera.width, height]) - 0.5 + slack
    corners = np.array([[c, r, 1.0] for c in (lo, hi[0]) for r in (lo, hi[1])]) @ inv.T
    reach = float((corners[:, 0] ** 2 + corners[:, 1] ** 2).max() + 1.0)
    return float(np.linalg.svd(inv[:2, :2], compute_uv=False)[-1] / reach)


@nb.njit(cache=True, nogil=True)
def reprojection_error(xyz, pixels, width, origin, matrix):
    """The largest distance (pixels) from a return's projection by ``matrix`` to its own pixel
    (``pixels`` ascending; inf when one projects behind the camera)."""
    worst = 0.0
    row, start = -1, 0
    for i in range(pixels.shape[0]):
        if row < 0 or pixels[i] >= start + width:  # a new row
            row = pixels[i] // width
            start = row * width
        dx, dy, dz = xyz[i, 0] - origin[0], xyz[i, 1] - origin[1], xyz[i, 2] - origin[2]
        w = matrix[2, 0] * dx + matrix[2, 1] * dy + matrix[2, 2] * dz
        if not w > 0.0:
            return np.inf
        u = matrix[0, 0] * dx + matrix[0, 1] * dy + matrix[0, 2] * dz - (pixels[i] - start) * w
        v = matrix[1, 0] * dx + matrix[1, 1] * dy + matrix[1, 2] * dz - row * w
        if u * u + v * v > worst * (w * w):  # divided only for a new largest error
            worst = (u * u + v * v) / (w * w)
    return math.sqrt(worst)
