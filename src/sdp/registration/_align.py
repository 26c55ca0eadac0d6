"""Rigid alignment of a current scan onto a reference before comparing them.

Two methods behind one function, :func:`align`:

- ``"density"``: Gauss–Newton on the ridges of the density fields, coarse to fine over a
  pyramid (σ doubling per level). At every current point the reference field gives, from G,
  its gradient and its Hessian (the gradient of the same trilinear grid, differenced), the
  surface normal n (the direction of strongest curvature of log G) and the Newton step along
  n to the ridge of G: a point-to-plane residual that does not depend on how densely the
  surface was sampled, so sampling patterns do not pull along surfaces as they do on a
  plain "maximise the density" objective. Each current point is first moved onto the ridge of
  the current scan's own field (same σ): blurring rounds corners and thins edges alike in
  both scans, so the two ridges coincide where nothing changed and the blur's bias cancels.
  Points are used only where both scans overlap (reference density at least a quarter of
  the point's own, relative to the median ratio): changed regions (people, new objects,
  parts seen by one scan only) have no reference density there and pull on nothing; the
  rest are weighted by Tukey's biweight. Directions of the motion that the geometry does not
  constrain (a flat ground leaves the horizontal free, a corridor its axis) are kept at the
  initial value instead of drifting with noise: see ``min_constraint`` and
  ``fix_horizontal``. Works from a saved field alone (no reference points needed).
  The residuals use G's gradient and Hessian from node differences of the same blocks; thin
  surfaces (ground, walls) weigh more than foliage; a direction constrained less than 1 % as
  strongly as the best (``min_constraint``) is frozen. The pyramid's reference levels are
  rebuilt from the reference points when given (about 10× faster), else
  :meth:`sdp.DensityField.coarsen`; the rotation is a rotation vector about the current
  points' centroid.
- ``"gicp"``: generalized ICP from small_gicp (the ``align`` extra), the proven baseline.

References
----------
.. [1] A. Segal, D. Haehnel and S. Thrun, "Generalized-ICP", Robotics: Science and Systems, 2009.
.. [2] K. Koide, "small_gicp: Efficient and parallel algorithms for point cloud registration",
   Journal of Open Source Software 9(100), 2024.
.. [3] P. Biber and W. Straßer, "The normal distributions transform: a new approach to laser
   scan matching", IROS 2003 (scan matching by maximising a density score).
.. [4] J. Zhang, M. Kaess and S. Singh, "On degeneracy of optimization-based state estimation
   problems", ICRA 2016 (leaving unconstrained directions of the update out).
"""

from __future__ import annotations

import contextlib
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from dataclasses import field as dataclass_field

import numpy as np
from scipy.spatial.transform import Rotation

from .._core._points import as_points, other_units
from .._core._validate import boolean, finite, integer_at_least, positive_finite
from ..defaults import DEFAULTS
from ..errors import GridTooLargeError, InvalidOptionError, InvalidPointsError, require
from ..fields._density import DensityField
from ..fields._spacing import auto_voxel_size

__all__ = ["Alignment", "align", "transform_points", "GicpTarget", "ROTATION_CONVENTION"]


#: How :attr:`Alignment.roll_pitch_yaw` reads the rotation (scipy's extrinsic ``"xyz"`` Euler angles).
ROTATION_CONVENTION = ("R = Rz(yaw) Ry(pitch) Rx(roll): roll about x, then pitch about y, then yaw about z, "
                       "each about the fixed axes through the centre")


@dataclass
class Alignment:
    """The rigid transform that maps the current scan onto the reference.

    A person reads it as a rotation about the current scan's centroid (:attr:`centre`) and a
    shift of that centroid: ``aligned = R @ (p − centre) + centre + shift``. The matrix's own
    translation (:attr:`translation`) is the motion of the world origin, which for a scene far
    from it is mostly the rotation's lever arm: a scan lifted by 0.41 m and tilted by a
    thousandth of a degree at a UTM northing of 4,800 km has a translation of some 80 m.

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
    used : float
        ``"density"``: fraction of the current points that took part at the finest level (in
        the overlap of both scans, on a surface of the reference); NaN for ``"gicp"``.
    conditioning : ndarray (6,)
        ``"density"``: eigenvalues of the Gauss–Newton matrix at the finest level, ascending,
        relative to the largest (rotations counted as displacement at the points' RMS radius):
        how strongly the geometry pins each direction of the motion. Near 0: a direction the
        scene leaves free (flat ground: horizontal shifts and the turn about the vertical).
        Empty for ``"gicp"``.
    frozen : int
        ``"density"``: how many of those directions were left at the initial transform
        (below ``min_constraint``, or fixed by ``fix_horizontal``).
    centre : ndarray (3,)
        The centroid of the current scan, before the transform: the pivot of the rotation and
        the point whose motion is :attr:`shift`. The world origin when not known.
    kept : tuple of str
        ``"density"``: the motions those frozen directions mostly are (``"yaw (about z)"``,
        ``"x shift"``, …) at the finest level: not refined there, left as the coarser levels
        left them (the initial transform where they were frozen there too).
    sigma : float
        The kernel σ of the finest level, which :attr:`rmse` is read against: after a right
        registration the surfaces coincide within it (0.3–0.65σ on the re-scans measured), a
        residual beyond it says they do not.
    diverged : bool
        The estimate ended with a share of the scan inside the reference's volume more than
        :data:`LOST_OVERLAP` below the one it started from (for ``"density"``: from every
        number of pyramid levels down to the finest alone): it moved the surfaces apart, and the
        initial transform was kept (``matrix`` is ``init``).
    """

    matrix: np.ndarray
    method: str
    inside_before: float
    inside_after: float
    rmse: float
    seconds: float
    used: float = np.nan
    conditioning: np.ndarray = dataclass_field(default_factory=lambda: np.zeros(0))
    frozen: int = 0
    centre: np.ndarray = dataclass_field(default_factory=lambda: np.zeros(3))
    kept: tuple = ()
    sigma: float = np.nan
    diverged: bool = False

    @property
    def translation(self) -> np.ndarray:
        """The matrix's translation: where the world origin goes (see :attr:`shift`)."""
        return self.matrix[:3, 3].copy()

    @property
    def shift(self) -> np.ndarray:
        """How far the current scan's centroid (:attr:`centre`) moves: ``R @ centre + t − centre``
        (world units)."""
        c = np.asarray(self.centre, np.float64)
        return self.matrix[:3, :3] @ c + self.matrix[:3, 3] - c

    @property
    def rotation_degrees(self) -> float:
        """Angle of the rotation, in degrees (about its own axis)."""
        return float(np.degrees(Rotation.from_matrix(self.matrix[:3, :3]).magnitude()))

    @property
    def roll_pitch_yaw(self) -> np.ndarray:
        """The rotation as angles about x, y and z, in degrees (:data:`ROTATION_CONVENTION`:
        ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``, about the fixed axes)."""
        return Rotation.from_matrix(self.matrix[:3, :3]).as_euler("xyz", degrees=True)

    def apply(self, points) -> np.ndarray:
        """The points mapped onto the reference frame."""
        return transform_points(self.matrix, points)

    def summary(self) -> dict:
        """A JSON-serializable summary: the method, the 4×4 ``matrix``, and as a person reads it
        the ``shift`` of the current scan's ``centre`` (world units) and the ``rotation`` about
        that centre (degrees: ``roll``, ``pitch``, ``yaw`` about x, y, z, and the total
        ``angle``, with the convention); then the overlap, residual, time and conditioning."""
        roll, pitch, yaw = (float(v) for v in self.roll_pitch_yaw)
        return {"method": self.method, "matrix": self.matrix.tolist(),
                "centre": np.asarray(self.centre, np.float64).tolist(), "shift": self.shift.tolist(),
                "rotation": {"roll": roll, "pitch": pitch, "yaw": yaw, "angle": self.rotation_degrees,
                             "unit": "degrees", "convention": ROTATION_CONVENTION},
                "inside_before": self.inside_before, "inside_after": self.inside_after, "rmse": self.rmse,
                "seconds": self.seconds, "used": self.used, "conditioning": np.asarray(self.conditioning).tolist(),
                "frozen": self.frozen, "kept": list(self.kept), "sigma": self.sigma, "diverged": self.diverged}


def transform_points(matrix, points) -> np.ndarray:
    """Apply a 4×4 rigid transform to (n, 3) points (float64).

    Raises
    ------
    InvalidOptionError
        ``matrix`` is not a 4×4 array of numbers, or ``points`` not (n, 3).
    """
    try:
        m, p = np.asarray(matrix, np.float64), np.asarray(points, np.float64)
    except (TypeError, ValueError):
        raise InvalidOptionError(f"a transform is a 4x4 matrix of numbers applied to (n, 3) points, got "
                                 f"{type(matrix).__name__} and {type(points).__name__}") from None
    if m.shape != (4, 4) or p.ndim != 2 or p.shape[1] != 3:
        raise InvalidOptionError(f"a transform is a 4x4 matrix applied to (n, 3) points, got shapes {m.shape} and "
                                 f"{p.shape}")
    return p @ m[:3, :3].T + m[:3, 3]


def align(reference, current, *, method: str = DEFAULTS.align_method, voxel_size: float | str = DEFAULTS.voxel_size,
          levels: int = 4,
          max_points: int = 100_000, init=None, seed: int = 0, min_constraint: float = 0.01,
          fix_horizontal: bool = False) -> Alignment:
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
        Voxel of the finest level (``"auto"``: :func:`sdp.auto_voxel_size` of the reference, the
        automatic lattice's voxel): σ = 2 of these voxels (a third wider than change detection's
        1.5 on the same lattice), sampled at half that voxel. Ignored when ``reference`` is a field.
    levels : int
        Levels of the pyramid (``"density"``): the coarsest has σ × 2^(levels−1), which sets
        the largest offset that can be recovered (about that σ).
    max_points : int
        Current points used for the estimate (a random subset of larger scans).
    init : array_like (4, 4), optional
        Starting transform (default: identity).
    seed : int
        Seed of the subset.
    min_constraint : float
        ``"density"``: a direction of the motion constrained less than ``min_constraint`` ×
        the best-constrained one (eigenvalues of the Gauss–Newton matrix, see
        :attr:`Alignment.conditioning`) is not moved: along it any residual bias or noise
        would be amplified √(1/min_constraint) times (10× at 0.01), so it keeps its initial
        value. 0 moves every direction that has any constraint at all.
    fix_horizontal : bool
        ``"density"``: estimate only the vertical shift and the tilts (z is up); the
        horizontal shift and the turn about the vertical keep their initial values. For
        epochs of nearly flat terrain (airborne scans of open ground), where the horizontal
        is pinned by little more than noise and real change.

    Returns
    -------
    Alignment
    """
    if method not in ("density", "gicp"):
        raise InvalidOptionError(f"method must be 'density' or 'gicp', got {method!r}")
    if method == "gicp" and fix_horizontal:
        raise InvalidOptionError("fix_horizontal is available with method='density' only")
    if not 0 <= finite("min_constraint", min_constraint) < 1:
        raise InvalidOptionError(f"min_constraint must be in [0, 1), got {min_constraint}")
    if not 1 <= integer_at_least("levels", levels, 1) <= _MAX_LEVELS:
        raise InvalidOptionError(f"levels must be at most {_MAX_LEVELS} (the coarsest σ is 2^(levels-1) times the "
                                 f"finest), got {levels}")
    max_points, seed = integer_at_least("max_points", max_points, 3), integer_at_least("seed", seed, 0)
    boolean("fix_horizontal", fix_horizontal)
    cur = _enough_points(as_points(current, name="current").xyz, "current")
    ref_xyz = None
    if isinstance(reference, DensityField):
        if method == "gicp":
            raise InvalidOptionError("the GICP alignment needs the reference points, not a density field")
        ref_field = reference
    else:
        ref_xyz = _enough_points(as_points(reference, name="reference").xyz, "reference")
        l = auto_voxel_size(ref_xyz) if isinstance(voxel_size, str) and voxel_size == "auto" else \
            positive_finite("voxel_size", voxel_size)
        # σ = 2l as for change detection, sampled at l/2: a trilinear interpolant sags between
        # nodes (3 % at σ = 2 voxels, 0.8 % at 4), which would pull planes onto node planes
        ref_field = DensityField.from_points(ref_xyz, voxel_size=l / 2, sigma_voxels=4)
    t0 = np.eye(4) if init is None else rigid_matrix(init, "init")
    rng = np.random.default_rng(seed)
    sample = cur if len(cur) <= max_points else cur[rng.choice(len(cur), max_points, replace=False)]
    start = time.perf_counter()
    info = {}
    before = float(ref_field.inside(transform_points(t0, sample)).mean())
    # both methods refine the pose they start from: one that ends with less of the scan inside the
    # reference's volume than it began has moved the surfaces apart. The density method's coarsest
    # level can do so (a room's walls at 8σ pull a turned camera onto the room's symmetry): the
    # finer levels alone, whose basins are smaller but start where the pose already is, go on
    # from there; the start is kept when none of them gains
    diverged = True
    for top in range(levels, 0, -1) if method == "density" else (levels,):
        if method == "density":
            try:
                matrix, info = _align_density(ref_field, ref_xyz, sample, t0, top, min_constraint, fix_horizontal)
            except GridTooLargeError as exc:  # the current's grid at the reference's voxel: why so large
                span = [float(np.max(np.ptp(x, axis=0))) for x in (ref_xyz if ref_xyz is not None else cur, cur)]
                if other_units(*span):
                    raise GridTooLargeError(f"{exc}; but the current spans {span[1]:.4g} units and the reference "
                                            f"{span[0]:.4g}: are they in the same units (metres and millimetres)?"
                                            ) from None
                raise exc
        else:
            matrix = _align_gicp(ref_xyz, sample, t0, ref_field.voxel_size, ref_field.sigma)
        after = float(ref_field.inside(transform_points(matrix, sample)).mean())
        diverged = after < before - LOST_OVERLAP
        if not diverged:
            break
    seconds = time.perf_counter() - start
    if diverged:
        matrix, after = t0, before
    rmse = np.nan
    if ref_xyz is not None:
        from scipy.spatial import cKDTree

        d, _ = cKDTree(ref_xyz).query(transform_points(matrix, sample), distance_upper_bound=3 * ref_field.sigma,
                                       workers=-1)
        d = d[np.isfinite(d)]
        rmse = float(np.sqrt(np.mean(d**2))) if d.size else np.nan
    if after == 0 or (ref_xyz is not None and not np.isfinite(rmse)):  # nothing to register on: no answer
        gap = "" if ref_xyz is None else \
            f"; their centres are {np.linalg.norm(transform_points(t0, cur).mean(axis=0) - ref_xyz.mean(axis=0)):.4g} apart"
        raise InvalidPointsError(f"the clouds do not overlap (no current point within the reference's volume{gap}): "
                                 f"an alignment needs them within about "
                                 f"{ref_field.sigma * 2 ** (levels - 1):.3g} of each other; move them together "
                                 "first (in Python: init=, a rough transform)")
    return Alignment(matrix=matrix, method=method, inside_before=before, inside_after=after, rmse=rmse,
                     seconds=seconds, centre=cur.mean(axis=0), sigma=float(ref_field.sigma), diverged=diverged,
                     **info)


def rigid_matrix(matrix, name: str = "matrix") -> np.ndarray:
    """``matrix`` as a 4×4 float64 rigid transform (a rotation, determinant +1, and a translation;
    last row 0 0 0 1), else a one-line :class:`~sdp.InvalidOptionError`: a scale, a shear or a
    mirror would make the alignment's answer no rigid motion."""
    try:
        m = np.array(matrix, np.float64)
    except (TypeError, ValueError):
        raise InvalidOptionError(f"{name} must be a 4×4 matrix of numbers") from None
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise InvalidOptionError(f"{name} must be a 4×4 matrix of finite numbers, got shape {m.shape}")
    r = m[:3, :3]
    if not (np.allclose(m[3], [0, 0, 0, 1], atol=1e-9) and np.allclose(r @ r.T, np.eye(3), atol=1e-6)
            and np.linalg.det(r) > 0):
        raise InvalidOptionError(f"{name} must be a rigid transform (a rotation and a translation, last row 0 0 0 1): "
                                 f"no scale, shear or mirror")
    return m


#: Fewest (finite, distinct) points of a cloud to align: a rigid motion has 6 unknowns, and a
#: handful of points pins none of them against a density field.
MIN_ALIGN_POINTS = 10


def _enough_points(xyz: np.ndarray, name: str) -> np.ndarray:
    """``xyz`` if it holds at least :data:`MIN_ALIGN_POINTS` distinct points, else InvalidPointsError."""
    n = len(xyz) if len(xyz) > 10_000 else len(np.unique(xyz, axis=0))  # duplicates pin nothing
    if n < MIN_ALIGN_POINTS:
        raise InvalidPointsError(f"{name} has {n} distinct point{'s' * (n != 1)}: too few to align "
                                 f"(at least {MIN_ALIGN_POINTS})")
    return xyz


_G_MIN = 0.05  # density below which a point sees no surface (a lone point's kernel at 2.4σ)
_OVERLAP = 0.25  # reference density / own density, relative to the median ratio, to take part
_MAX_ITER = 30  # Gauss–Newton iterations per level
_COARSE_POINTS = 20_000  # current points used on the coarser levels
_MAX_LEVELS = 16  # pyramid levels: the coarsest σ 2^15 times the finest, beyond any scene's size
_TOL = 1e-3  # stop a level when the step moves points by less than this × σ
#: Share of the scan inside the reference's volume an estimate may lose before it is taken to
#: have moved the surfaces apart (the share below which the summary calls a start a guess).
LOST_OVERLAP = 0.05
#: The motions of the Gauss–Newton unknowns (ω·radius about x, y, z; shifts along x, y, z).
_MOTIONS = ("roll (about x)", "pitch (about y)", "yaw (about z)", "x shift", "y shift", "z shift")


def _probe(f: DensityField, q: np.ndarray):
    """G, ∇G and the Hessian of G at ``q``, each the trilinear interpolant of the nodes' central
    differences (so continuous across cells, unlike the derivative of the trilinear G, whose
    piecewise-constant gradient would put every ridge on a node plane). Shifting a query by
    exactly one voxel shifts the nodes it reads, so those interpolants are differences of
    trilinear values one voxel apart: 19 lookups per point."""
    h = f.voxel_size

    def at(offset):
        return f.density(q + offset)

    eye = np.eye(3) * h
    val = at(np.zeros(3))
    hi = [at(eye[k]) for k in range(3)]
    lo = [at(-eye[k]) for k in range(3)]
    grad = np.stack([(hi[k] - lo[k]) / (2 * h) for k in range(3)], axis=1)
    hess = np.empty((len(q), 3, 3))
    for i in range(3):
        hess[:, i, i] = (hi[i] - 2 * val + lo[i]) / h**2
        for j in range(i + 1, 3):
            hess[:, i, j] = hess[:, j, i] = (at(eye[i] + eye[j]) - at(eye[i] - eye[j]) - at(eye[j] - eye[i])
                                             + at(-eye[i] - eye[j])) / (4 * h**2)
    return val, grad, hess


def _ridge(f: DensityField, q: np.ndarray):
    """Per point: G, the normal n (eigenvector of the largest curvature of −log G), that
    curvature κ, the Newton step s along n to the ridge of G, and whether they are usable.

    For a plane sampled with any areal density ρ(u, v), G ∝ ρ̃(u, v)·exp(−d²/2σ²) with d the
    distance to the plane: log G is exactly quadratic along n with curvature 1/σ², and the
    Newton step along n is −d, whatever ρ is (the in-plane terms of ∇ log G are left out).
    """
    G, g, H = _probe(f, q)
    n = np.zeros_like(q)
    kappa, step = np.zeros(len(q)), np.zeros(len(q))
    ok = G > _G_MIN
    gl = g[ok] / G[ok, None]  # ∇ log G
    curv = gl[:, :, None] * gl[:, None, :] - H[ok] / G[ok, None, None]  # −∇² log G
    kappa[ok], n[ok] = _top_eigen(curv)
    good = ok & (kappa > 0.1 / f.sigma**2)  # a ridge, not the flat tail between surfaces
    step[good] = (n[good] * g[good]).sum(axis=1) / G[good] / kappa[good]
    return G, n, kappa, step, good


def _top_eigen(m: np.ndarray):
    """Largest eigenvalue and its unit eigenvector of each symmetric 3×3 matrix (k, 3, 3): the
    trigonometric closed form (O. K. Smith, CACM 1961), ~2.5x faster than a batched eigh."""
    a00, a11, a22 = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    a01, a02, a12 = m[:, 0, 1], m[:, 0, 2], m[:, 1, 2]
    q = (a00 + a11 + a22) / 3
    p = np.sqrt(((a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2 * (a01**2 + a02**2 + a12**2)) / 6)
    s = np.where(p > 0, p, 1.0)
    b00, b11, b22, b01, b02, b12 = (a00 - q) / s, (a11 - q) / s, (a22 - q) / s, a01 / s, a02 / s, a12 / s
    det = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    lam = q + 2 * p * np.cos(np.arccos(np.clip(det / 2, -1, 1)) / 3)
    rows = m - lam[:, None, None] * np.eye(3)
    cand = np.stack([np.cross(rows[:, 0], rows[:, 1]), np.cross(rows[:, 0], rows[:, 2]),
                     np.cross(rows[:, 1], rows[:, 2])], axis=1)  # each ⟂ to two rows of m − λI
    norm = np.linalg.norm(cand, axis=2)
    best = norm.argmax(axis=1)
    idx = np.arange(len(m))
    v, nv = cand[idx, best], norm[idx, best]
    v = np.where(nv[:, None] > 0, v / np.where(nv > 0, nv, 1.0)[:, None], [1.0, 0.0, 0.0])  # λI: any vector
    return lam, v


def _pyramid(ref_field: DensityField, ref_xyz, cur: np.ndarray, levels: int):
    """(reference, current) fields per level, finest first, on the reference's voxel and σ."""
    sv = ref_field.sigma / ref_field.voxel_size
    out = []
    for k in range(levels):
        voxel = ref_field.voxel_size * 2**k
        if k == 0:
            ref_k = ref_field
        elif ref_xyz is not None:  # from the points: ~10x faster than coarsen()
            ref_k = DensityField.from_points(ref_xyz, voxel_size=voxel, sigma_voxels=sv)
        else:
            ref_k = out[-1][0].coarsen()
        out.append((ref_k, DensityField.from_points(cur, voxel_size=voxel, sigma_voxels=sv)))
    return out


def _align_density(ref_field: DensityField, ref_xyz, points: np.ndarray, t0: np.ndarray, levels: int,
                   min_constraint: float, fix_horizontal: bool):
    pyramid = _pyramid(ref_field, ref_xyz, points, levels)
    coarse = points[np.sort(np.random.default_rng(0).permutation(len(points))[:_COARSE_POINTS])]
    x0 = transform_points(t0, points)
    c = x0.mean(axis=0)
    rot, t = np.eye(3), np.zeros(3)  # q = rot·(x − c) + c + t, x = t0·(point on its own ridge)
    used, conditioning, frozen, kept = 0.0, np.zeros(6), 0, ()
    for ref_k, cur_k in reversed(pyramid):
        sigma = ref_k.sigma
        # coarse levels only bring the estimate into the finest level's basin: fewer points
        pts = points if cur_k is pyramid[0][1] else coarse
        g_own, n_own, k_own, s_own, own_ok = _ridge(cur_k, pts)
        # thickness² of the surface at each point (κ = 1/(σ² + τ²) across a blurred layer of
        # thickness τ), at least a voxel: the residual's variance, for Gauss–Newton weights
        thick_own = np.maximum(1 / np.maximum(k_own, 1e-30) - sigma**2, 0) + ref_k.voxel_size**2
        ridge = pts + np.where(own_ok[:, None], np.clip(s_own, -sigma, sigma)[:, None] * n_own, 0.0)
        local = transform_points(t0, ridge) - c
        radius = float(np.sqrt((local**2).sum(axis=1).mean())) or 1.0
        damping, previous = 0.0, None
        for _ in range(_MAX_ITER):
            rp = local @ rot.T
            g_ref, n, k_ref, s, ok = _ridge(ref_k, rp + c + t)
            ok &= own_ok
            if ok.sum() < 6:
                break
            ratio = g_ref / np.maximum(g_own, 1e-12)
            ok &= ratio > _OVERLAP * np.median(ratio[ok])  # outside the overlap: changes, one-sided parts
            u = s[ok] / sigma
            w = np.where(np.abs(u) < 1, (1 - u**2) ** 2, 0.0)  # Tukey's biweight, c = σ
            thick_ref = np.maximum(1 / np.maximum(k_ref[ok], 1e-30) - sigma**2, 0) + ref_k.voxel_size**2
            w = w * sigma**2 / (thick_ref + thick_own[ok])  # thin surfaces (ground, walls) pin more than foliage
            jac = np.c_[np.cross(rp[ok], n[ok]) / radius, n[ok]]  # (ω·radius, t)
            if fix_horizontal:
                jac[:, [2, 3, 4]] = 0.0  # turn about z, shift in x and y
            a = (jac * w[:, None]).T @ jac
            b = (jac * w[:, None]).T @ s[ok]
            ev, vec = np.linalg.eigh(a)
            if ev[-1] <= 0:
                break
            keep = ev > max(min_constraint, 1e-9) * ev[-1]
            x = vec[:, keep] @ ((vec[:, keep].T @ b) / (ev[keep] + damping * ev[-1]))
            # Levenberg damping when the step turns back (the model overshot), eased otherwise
            damping = max(4 * damping, 1e-3) if previous is not None and x @ previous < 0 else damping / 2
            previous = x
            rot = Rotation.from_rotvec(x[:3] / radius).as_matrix() @ rot
            t = t + x[3:]
            used, conditioning, frozen = float(ok.mean()), ev / ev[-1], int((~keep).sum())
            kept = tuple(_MOTIONS[i] for i in np.argmax(np.abs(vec[:, ~keep]), axis=0)
                         if not (fix_horizontal and i in (2, 3, 4)))  # those were asked for
            if np.linalg.norm(x) < _TOL * sigma:
                break
    step = np.eye(4)
    step[:3, :3] = rot
    step[:3, 3] = c + t - rot @ c
    return step @ t0, {"used": used, "conditioning": conditioning, "frozen": frozen, "kept": kept}


def _align_gicp(ref: np.ndarray, cur: np.ndarray, t0: np.ndarray, voxel: float, sigma: float) -> np.ndarray:
    return GicpTarget(ref, resolution=voxel, max_distance=4 * sigma).register(cur, t0)


class GicpTarget:
    """A reference prepared once for small_gicp's GICP, to register many scans onto it.

    The reference is downsampled on a voxel grid of side ``resolution`` and given per-point
    covariances and a k-d tree [1, 2]; :meth:`register` prepares each scan the same way and
    returns the 4×4 transform that maps it onto the reference. Coarse to fine: GICP pairs points
    only up to ``max_distance`` apart, so a first pass on a grid of ``_COARSE``× the resolution,
    pairing up to ``_COARSE``× the distance, brings a scan that moved more than that (a camera
    panning 4° at 3 m moves its points 20 cm, 8σ of a fine lattice) into the fine pass's reach.
    Used by :func:`sdp.watch` (``align="gicp"``), where the reference is prepared once for the
    whole stream.

    Raises
    ------
    MissingDependencyError
        small_gicp is not installed (``pip install 'sdp[align]'``).
    """

    def __init__(self, reference: np.ndarray, *, resolution: float, max_distance: float):
        small_gicp = require("small_gicp", "align", "GICP")
        self._gicp, self.resolution, self.max_distance = small_gicp, float(resolution), float(max_distance)
        self._o = reference.mean(axis=0)  # local frame: small_gicp's voxel keys hold 21 bits per axis
        self._levels = [(_COARSE * self.resolution, _COARSE * self.max_distance), (self.resolution, self.max_distance)]
        self._targets = [self._prepare(reference, res) for res, _ in self._levels]

    def _prepare(self, points: np.ndarray, resolution: float):
        with _native_stderr("GICP"):
            return self._gicp.preprocess_points(points - self._o, downsampling_resolution=resolution, num_threads=2)

    def register(self, current: np.ndarray, init: np.ndarray | None = None) -> np.ndarray:
        """4×4 transform mapping ``current`` (finite rows) onto the reference, starting from ``init``."""
        shift, unshift = np.eye(4), np.eye(4)
        shift[:3, 3], unshift[:3, 3] = -self._o, self._o
        t = shift @ (np.eye(4) if init is None else np.asarray(init, np.float64)) @ unshift
        for (resolution, reach), (target, tree) in zip(self._levels, self._targets):
            source, _ = self._prepare(current, resolution)
            with _native_stderr("GICP"):
                t = self._gicp.align(target, source, tree, t, registration_type="GICP",
                                     max_correspondence_distance=reach, num_threads=2,
                                     max_iterations=100).T_target_source
        return unshift @ t @ shift


_COARSE = 4.0  # GicpTarget's first pass: grid and pairing distance, in units of the fine pass's


@contextlib.contextmanager
def _native_stderr(what: str):
    """Run a C++ library's call with its standard error (file descriptor 2) captured: small_gicp
    prints ``warning: …`` there when its input can't be registered (a cloud too small, points
    beyond its voxel keys) and returns a transform anyway. Such a message becomes one
    :class:`~sdp.InvalidPointsError` instead of a line on the terminal and an answer not to trust."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as capture:
        os.dup2(capture.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        capture.seek(0)
        text = capture.read().decode(errors="replace")
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if lines:
        raise InvalidPointsError(f"{what}: {lines[0]}" + (f" (and {len(lines) - 1} more lines)" if len(lines) > 1 else ""))
