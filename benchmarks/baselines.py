"""Baseline change detectors a user would otherwise pick, for the benchmark of issue 4.

Every method has the signature ``method(reference_xyz, current_xyz, **params) -> Scored``: one
score per *current* point, larger meaning more likely "appeared"; the caller thresholds it
(``score > threshold``) at a threshold tuned on other pairs (:func:`tune_threshold`,
:func:`two_fold`). ``Scored.timings`` splits the time (``time.perf_counter``, seconds) into the
columns of the paper's Table I: building the representation of the reference, of the current
cloud, and detecting; a method without a step reports 0.0 for it.

Methods: :func:`c2c_ckdtree`, :func:`c2c_pykdtree` (cloud-to-cloud nearest distance, as
CloudCompare's C2C), :func:`m3c2` (py4dgeo), :func:`gmm` (Gaussian mixtures fitted by EM, as
Drews et al. and Núñez et al.), :func:`voxel_occupancy` (PCL's octree change detector rule) and
:func:`depth_difference` (pixel by pixel on the depth images of one fixed camera; it takes the
depth images, not the clouds).
"""

from __future__ import annotations

import importlib
import logging
from contextlib import contextmanager
from dataclasses import dataclass
from time import perf_counter
from types import ModuleType

import numpy as np
from scipy.spatial import cKDTree

from sdp.change._metrics import kappa

__all__ = ["Scored", "METHODS", "c2c_ckdtree", "c2c_pykdtree", "m3c2", "gmm", "voxel_occupancy",
           "depth_difference", "depth_image", "tune_threshold", "two_fold"]

_STEPS = ("build_reference", "build_current", "detect")


@dataclass
class Scored:
    """Per-point change scores of a baseline.

    Attributes
    ----------
    score : numpy.ndarray
        float64, one per current point; larger = more likely appeared (may hold ``+inf``).
    default_threshold : float or None
        An untuned threshold that makes sense without ground truth, None when there is none.
    timings : dict
        Seconds spent in "build_reference", "build_current" and "detect".
    """

    score: np.ndarray
    default_threshold: float | None
    timings: dict[str, float]


def _zero_timings() -> dict[str, float]:
    return dict.fromkeys(_STEPS, 0.0)


@contextmanager
def _timed(timings: dict[str, float], step: str):
    t0 = perf_counter()
    yield
    timings[step] = perf_counter() - t0


@contextmanager
def _quiet(logger_name: str):
    """Hold a logger at WARNING (py4dgeo logs INFO to stdout and to ./py4dgeo.log)."""
    logger = logging.getLogger(logger_name)
    level = logger.level
    logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(level)


def _require(module: str, extra: str) -> ModuleType:
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise ImportError(f"this baseline needs {module.split('.')[0]}: pip install 'sdp[{extra}]'") from e


def _c2c(reference_xyz, current_xyz, tree_type, query_kw) -> Scored:
    t = _zero_timings()
    ref, cur = np.ascontiguousarray(reference_xyz, np.float64), np.ascontiguousarray(current_xyz, np.float64)
    with _timed(t, "build_reference"):
        tree = tree_type(ref)
    with _timed(t, "detect"):
        d, _ = tree.query(cur, **query_kw)
    return Scored(np.asarray(d, np.float64), None, t)


def c2c_ckdtree(reference_xyz: np.ndarray, current_xyz: np.ndarray) -> Scored:
    """Cloud-to-cloud distance (CloudCompare's C2C): distance to the nearest reference point.

    Builds a ``scipy.spatial.cKDTree`` on the reference and queries every current point with all
    cores (``workers=-1``). No default threshold: C2C users pick a distance by eye.
    """
    return _c2c(reference_xyz, current_xyz, cKDTree, dict(workers=-1))


def c2c_pykdtree(reference_xyz: np.ndarray, current_xyz: np.ndarray) -> Scored:
    """As :func:`c2c_ckdtree` with ``pykdtree.kdtree.KDTree`` (OpenMP-parallel queries)."""
    return _c2c(reference_xyz, current_xyz, _require("pykdtree.kdtree", "bench").KDTree, {})


def m3c2(reference_xyz: np.ndarray, current_xyz: np.ndarray, *, normal_radii: tuple[float, ...] = (0.015,),
         cyl_radius: float = 0.005, max_distance: float = 0.05, max_core_points: int | None = None,
         seed: int = 0) -> Scored:
    """M3C2 distance (Lague et al. 2013) by py4dgeo, reference = epoch 0, current = epoch 1.

    Core points are all current points, or with ``max_core_points`` a random subsample (``seed``)
    whose result every current point takes from its nearest core point (a cKDTree query, timed in
    "detect"). Normals are py4dgeo's multi-scale normals of the current cloud at the core points
    (``normal_radii``, metres); the distance is taken along them in a cylinder of radius
    ``cyl_radius`` and half-length ``max_distance``. Score = |distance|; a core point with no
    reference point in its cylinder (py4dgeo's NaN) has score ``+inf``: nothing to compare with,
    i.e. appeared. Defaults suit Kinect table-top scenes at 1–3 mm spacing.

    Timings: "build_reference" = reference epoch and its k-d tree; "build_current" = current epoch,
    its k-d tree and the core-point normals; "detect" = the cylinder distances.

    Raises
    ------
    ImportError
        If py4dgeo is missing (``pip install 'sdp[m3c2]'``).
    """
    py4dgeo = _require("py4dgeo", "m3c2")
    t = _zero_timings()
    with _quiet("py4dgeo"):
        with _timed(t, "build_reference"):
            ref = py4dgeo.Epoch(np.asarray(reference_xyz, np.float64))
            ref.build_kdtree()
        with _timed(t, "build_current"):
            cur = py4dgeo.Epoch(np.asarray(current_xyz, np.float64))
            cur.build_kdtree()
            core = cur.cloud
            if max_core_points is not None and max_core_points < len(core):
                core = core[np.sort(np.random.default_rng(seed).choice(len(core), max_core_points, replace=False))]
            algo = py4dgeo.M3C2(epochs=(ref, cur), corepoints=core, normal_radii=list(normal_radii),
                                cloud_for_normals=cur, cyl_radius=cyl_radius, max_distance=max_distance)
            algo.directions()
        with _timed(t, "detect"):
            d, _ = algo.run()
            score = np.where(np.isnan(d), np.inf, np.abs(d))
            if len(core) < len(cur.cloud):
                score = score[cKDTree(core).query(cur.cloud, workers=-1)[1]]
    return Scored(score, None, t)


def gmm(reference_xyz: np.ndarray, current_xyz: np.ndarray, *, n_components: int = 9,
        max_fit_points: int | None = 20_000, seed: int = 0, default_quantile: float = 0.99) -> Scored:
    """Gaussian mixture baseline (Drews et al.; Núñez et al.).

    A full-covariance ``sklearn.mixture.GaussianMixture`` of ``n_components`` is fitted by EM on
    the reference ("build_reference") and one on the current cloud ("build_current": the paper
    fits both, so its cost is timed, but the per-point rule below does not use it). Each fit uses
    at most ``max_fit_points`` points drawn at random (``seed``); None fits on all points.

    Rule: score = negative log-likelihood of each current point under the reference mixture
    ("detect"); points the reference explains badly are appeared. Default threshold: the
    ``default_quantile`` quantile of the reference fit points' own scores (a novelty rule that
    needs no ground truth; timed in "build_reference").
    """
    from sklearn.mixture import GaussianMixture

    t = _zero_timings()
    rng = np.random.default_rng(seed)

    def fit(xyz):
        xyz = np.asarray(xyz, np.float64)
        if max_fit_points is not None and max_fit_points < len(xyz):
            xyz = xyz[rng.choice(len(xyz), max_fit_points, replace=False)]
        return GaussianMixture(n_components, covariance_type="full", random_state=seed).fit(xyz), xyz

    with _timed(t, "build_reference"):
        model, fit_points = fit(reference_xyz)
        default = float(np.quantile(-model.score_samples(fit_points), default_quantile))
    with _timed(t, "build_current"):
        fit(current_xyz)
    with _timed(t, "detect"):
        score = -model.score_samples(np.asarray(current_xyz, np.float64))
    return Scored(score, default, t)


def voxel_occupancy(reference_xyz: np.ndarray, current_xyz: np.ndarray, *, voxel_size: float = 0.01) -> Scored:
    """PCL octree change detector rule: current points in voxels the reference leaves empty.

    Voxels are ``floor(xyz / voxel_size)``. Score = Chebyshev distance, in voxels, from a current
    point's voxel to the nearest voxel holding a reference point: 0 in an occupied voxel, 1 next to
    one, …, so thresholds stay tunable; the default threshold 0.5 is PCL's rule (any empty voxel).
    Timings: "build_reference" = reference voxels and a k-d tree on them, "build_current" = current
    voxels, "detect" = one query per occupied current voxel.
    """
    t = _zero_timings()

    def voxels(xyz):
        return np.unique(np.floor(np.asarray(xyz, np.float64) / voxel_size).astype(np.int64), axis=0,
                         return_inverse=True)

    with _timed(t, "build_reference"):
        tree = cKDTree(voxels(reference_xyz)[0])
    with _timed(t, "build_current"):
        cur_voxels, inverse = voxels(current_xyz)
    with _timed(t, "detect"):
        d, _ = tree.query(cur_voxels, p=np.inf, workers=-1)
        score = d[inverse.ravel()]
    return Scored(score.astype(np.float64), 0.5, t)


def depth_image(path) -> np.ndarray:
    """The (height, width) depth image (the z coordinate, float64) of an organized PCD, NaN where
    the sensor had no return (NaN or 0, 0, 0 in the file, as :func:`sdp.read_points` reads them):
    its finite pixels in row-major order are the rows :func:`sdp.read_points` keeps."""
    from pypcd4 import PointCloud

    pc = PointCloud.from_path(path)
    names = list(pc.fields)
    data = pc.numpy()
    xyz = np.stack([data[:, names.index(c)] for c in "xyz"], axis=1).astype(np.float64)
    missing = ~np.isfinite(xyz).all(axis=1) | ~xyz.any(axis=1)
    return np.where(missing, np.nan, xyz[:, 2]).reshape(pc.metadata.height, pc.metadata.width)


def depth_difference(reference_depth: np.ndarray, current_depth: np.ndarray) -> Scored:
    """Depth differencing, the rule of a fixed depth camera: per pixel, how much nearer the current
    return is than the reference's, ``z_ref − z_cur`` (along the optical axis, the PCD's z).

    Both depth images come from one camera that did not move (:func:`depth_image`). A pixel that
    either image has no return at is not compared (score ``-inf``: never flagged). One score per
    finite pixel of the current image, in row-major order (the rows :func:`sdp.read_points`
    keeps). No default threshold. Timings: all in "detect" (there is no representation to build).
    """
    t = _zero_timings()
    with _timed(t, "detect"):
        z_ref, z_cur = reference_depth.ravel(), current_depth.ravel()
        kept = np.isfinite(z_cur)
        with np.errstate(invalid="ignore"):
            score = z_ref[kept] - z_cur[kept]
        score[np.isnan(score)] = -np.inf
    return Scored(score, None, t)


METHODS = {"c2c_ckdtree": c2c_ckdtree, "c2c_pykdtree": c2c_pykdtree, "m3c2": m3c2, "gmm": gmm,
           "voxel_occupancy": voxel_occupancy}


def _mean_kappa(threshold: float, scores_list, truths_list) -> float:
    return float(np.mean([kappa(t, s > threshold) for s, t in zip(scores_list, truths_list)]))


def tune_threshold(scores_list: list[np.ndarray], truths_list: list[np.ndarray], *, n_candidates: int = 200) -> float:
    """Threshold maximizing the mean Cohen's kappa of ``score > threshold`` over the pairs.

    Candidates are ``n_candidates`` quantiles of the pooled scores (actual score values, so
    ``+inf`` scores are fine). Pass only the scored points of each pair. Pairs whose truth is
    constant (nothing changed) are left out of the mean: their kappa is 0 with any false positive
    and NaN without one, so a NaN-skipping mean would reward thresholds that drop them.
    """
    kept = [(s, t) for s, t in zip(scores_list, truths_list) if 0 < np.count_nonzero(t) < len(t)]
    if not kept:
        raise ValueError("every pair has a constant truth: kappa cannot rank thresholds")
    scores_list, truths_list = zip(*kept)
    pooled = np.concatenate(scores_list)
    candidates = np.unique(np.quantile(pooled, np.linspace(0, 1, n_candidates), method="lower"))
    return float(candidates[np.argmax([_mean_kappa(c, scores_list, truths_list) for c in candidates])])


def two_fold(scores_list: list[np.ndarray], truths_list: list[np.ndarray]) -> np.ndarray:
    """Held-out kappa per pair: tuned on even-indexed pairs and scored on odd ones, and reverse.

    A pair without changed points gets 0 (some false positive) or NaN (none), as :func:`sdp.kappa`.
    """
    out = np.full(len(scores_list), np.nan)
    for train, test in ((slice(0, None, 2), slice(1, None, 2)), (slice(1, None, 2), slice(0, None, 2))):
        threshold = tune_threshold(scores_list[train], truths_list[train])
        out[test] = [kappa(t, s > threshold) for s, t in zip(scores_list[test], truths_list[test])]
    return out
