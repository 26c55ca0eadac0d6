"""Rigid alignment of a current scan onto a reference before comparing them.

Two methods behind one function, :func:`align`:

- ``"density"``: maximise the mean density of the transformed current points under the
  reference's own density field, G_ref(R·p + t), with the gradient of the same trilinear grid,
  coarse to fine over the level-of-detail pyramid (:meth:`DensityField.coarsen`, σ doubling per
  level). Points in changed regions fall where the reference has no density: their value and
  gradient are 0, so they pull on nothing and the estimate is robust to the changes without a
  rejection step. Works from a saved field alone (no reference points needed).
- ``"gicp"``: generalized ICP from small_gicp (the ``align`` extra), the proven baseline.

References
----------
.. [1] A. Segal, D. Haehnel and S. Thrun, "Generalized-ICP", Robotics: Science and Systems, 2009.
.. [2] K. Koide, "small_gicp: Efficient and parallel algorithms for point cloud registration",
   Journal of Open Source Software 9(100), 2024.
.. [3] P. Biber and W. Straßer, "The normal distributions transform: a new approach to laser
   scan matching", IROS 2003 (scan matching by maximising a density score).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from . import _kernels as K
from ._points import as_points
from .errors import MissingDependencyError
from .field import DensityField
from .params import auto_voxel_size

__all__ = ["Alignment", "align", "transform_points"]


@dataclass
class Alignment:
    """The rigid transform that maps the current scan onto the reference.

    Attributes
    ----------
    matrix : ndarray (4, 4)
        Homogeneous transform: ``aligned = R @ p + t`` with ``R = matrix[:3, :3]``,
        ``t = matrix[:3, 3]``. ``numpy.savetxt`` / ``numpy.loadtxt`` round-trip it.
    method : str
        ``"density"`` or ``"gicp"``.
    inside_before, inside_after : float
        Fraction of the current points inside the reference's cluster volume (F_ref < 0)
        before and after the transform: the overlap the alignment achieved.
    rmse : float
        Root-mean-square distance from the aligned current points to their nearest reference
        point, over the points closer than 3σ (the residual of static structure). NaN when
        the reference was given as a field.
    seconds : float
        Time taken by the estimate (the residual excluded).
    """

    matrix: np.ndarray
    method: str
    inside_before: float
    inside_after: float
    rmse: float
    seconds: float

    @property
    def translation(self) -> np.ndarray:
        return self.matrix[:3, 3].copy()

    @property
    def rotation_degrees(self) -> float:
        """Angle of the rotation, in degrees."""
        return float(np.degrees(Rotation.from_matrix(self.matrix[:3, :3]).magnitude()))

    def apply(self, points) -> np.ndarray:
        """The points mapped onto the reference frame."""
        return transform_points(self.matrix, points)

    def summary(self) -> dict:
        return {"method": self.method, "matrix": self.matrix.tolist(), "translation": self.translation.tolist(),
                "rotation_degrees": self.rotation_degrees, "inside_before": self.inside_before,
                "inside_after": self.inside_after, "rmse": self.rmse, "seconds": self.seconds}


def transform_points(matrix, points) -> np.ndarray:
    """Apply a 4×4 rigid transform to (n, 3) points (float64)."""
    m = np.asarray(matrix, np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"a transform is a 4x4 matrix, got shape {m.shape}")
    return np.asarray(points, np.float64) @ m[:3, :3].T + m[:3, 3]


def align(reference, current, *, method: str = "density", voxel_size: float | str = "auto", levels: int = 4,
          max_points: int = 100_000, init=None, seed: int = 0) -> Alignment:
    """Estimate the rigid transform that maps ``current`` onto ``reference``.

    Parameters
    ----------
    reference : array_like (n, 3) or DensityField
        The reference scan, or its field (``"density"`` only). Build such a field with
        ``sigma_voxels=4`` (half the voxel for the same σ): at 2 the trilinear interpolant
        sags between nodes and biases planes towards node planes by a few millimetres.
    current : array_like (m, 3)
        The scan to move.
    method : {"density", "gicp"}
        See the module docstring.
    voxel_size : float or "auto"
        Voxel of the finest level (``"auto"``: :func:`sdp.auto_voxel_size` of the reference).
        Ignored when ``reference`` is a field.
    levels : int
        Levels of the pyramid (``"density"``): the coarsest has σ × 2^(levels−1), which sets
        the largest offset that can be recovered (about that σ).
    max_points : int
        Current points used for the estimate (a random subset of larger scans).
    init : array_like (4, 4), optional
        Starting transform (default: identity).
    seed : int
        Seed of the subset.

    Returns
    -------
    Alignment
    """
    if method not in ("density", "gicp"):
        raise ValueError(f"method must be 'density' or 'gicp', got {method!r}")
    cur = as_points(current, name="current").xyz
    ref_xyz = None
    if isinstance(reference, DensityField):
        if method == "gicp":
            raise ValueError("method='gicp' needs the reference points, not a field")
        field = reference
    else:
        ref_xyz = as_points(reference, name="reference").xyz
        l = auto_voxel_size(ref_xyz) if isinstance(voxel_size, str) and voxel_size == "auto" else float(voxel_size)
        # σ = 2l as for change detection, sampled at l/2: a trilinear interpolant sags between
        # nodes (3 % at σ = 2 voxels, 0.8 % at 4), which would pull planes onto node planes
        field = DensityField.from_points(ref_xyz, voxel_size=l / 2, sigma_voxels=4)
    t0 = np.eye(4) if init is None else np.array(init, np.float64)
    rng = np.random.default_rng(seed)
    sample = cur if len(cur) <= max_points else cur[rng.choice(len(cur), max_points, replace=False)]
    start = time.perf_counter()
    if method == "density":
        matrix = _align_density(field, sample, t0, levels)
    else:
        matrix = _align_gicp(ref_xyz, sample, t0, field.voxel_size, field.sigma)
    seconds = time.perf_counter() - start
    rmse = np.nan
    if ref_xyz is not None:
        from scipy.spatial import cKDTree

        d, _ = cKDTree(ref_xyz).query(transform_points(matrix, sample), distance_upper_bound=3 * field.sigma,
                                       workers=-1)
        d = d[np.isfinite(d)]
        rmse = float(np.sqrt(np.mean(d**2))) if d.size else np.nan
    before, after = (float(field.inside(transform_points(m, sample)).mean()) for m in (t0, matrix))
    return Alignment(matrix=matrix, method=method, inside_before=before, inside_after=after, rmse=rmse,
                     seconds=seconds)


def _align_density(field: DensityField, points: np.ndarray, t0: np.ndarray, levels: int) -> np.ndarray:
    pyramid = [field]
    for _ in range(levels - 1):
        pyramid.append(pyramid[-1].coarsen())
    p = transform_points(t0, points)
    c = p.mean(axis=0)
    local = p - c
    radius = float(np.sqrt((local**2).sum(axis=1).mean())) or 1.0
    x = np.zeros(6)  # (rotation vector, translation), world units; q = R(ω)·(p − c) + c + t
    val, grad = np.empty(len(p)), np.empty((len(p), 3))
    for f in reversed(pyramid):
        scale = np.r_[np.full(3, f.sigma / radius), np.full(3, f.sigma)]  # unknowns in units of σ

        def cost(y, f=f, scale=scale):
            w, t = y[:3] * scale[:3], y[3:] * scale[3:]
            rot = Rotation.from_rotvec(w)
            rp = rot.apply(local)
            K.trilinear_gradient(rp + (c + t), f.grid.origin, f.voxel_size, f._directory, f._blocks, val, grad)
            g_t = grad.sum(axis=0)
            g_w = _left_jacobian(w).T @ np.cross(rp, grad).sum(axis=0)
            n = len(p)
            return -val.sum() / n, -np.r_[g_w, g_t] * scale / n

        x = minimize(cost, x / scale, jac=True, method="L-BFGS-B", options={"maxiter": 200}).x * scale
    step = np.eye(4)
    step[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix()
    step[:3, 3] = c + x[3:] - step[:3, :3] @ c
    return step @ t0


def _left_jacobian(w: np.ndarray) -> np.ndarray:
    """d(exp(ω)·v)/dω = −[exp(ω)·v]× · J_l(ω): the left Jacobian of SO(3)."""
    theta = float(np.linalg.norm(w))
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if theta < 1e-8:
        return np.eye(3) + k / 2
    return np.eye(3) + (1 - np.cos(theta)) / theta**2 * k + (theta - np.sin(theta)) / theta**3 * (k @ k)


def _align_gicp(ref: np.ndarray, cur: np.ndarray, t0: np.ndarray, voxel: float, sigma: float) -> np.ndarray:
    try:
        import small_gicp
    except ImportError:
        raise MissingDependencyError('method="gicp" needs small_gicp: pip install "sdp[align]"') from None
    o = ref.mean(axis=0)  # local frame: small_gicp's voxel keys hold 21 bits per axis
    shift, unshift = np.eye(4), np.eye(4)
    shift[:3, 3], unshift[:3, 3] = -o, o
    result = small_gicp.align(ref - o, cur - o, shift @ t0 @ unshift, registration_type="GICP",
                              downsampling_resolution=voxel, max_correspondence_distance=4 * sigma,
                              num_threads=2, max_iterations=100)
    return unshift @ result.T_target_source @ shift
