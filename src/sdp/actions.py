"""Human action recognition from depth sequences with space-time density patterns.

The paper's second application (method.md §5), in the spirit of STOP (Vieira et al., space-time
occupancy patterns): a depth sequence becomes a 4-D (x, y, z, t) density pattern.

1. Every foreground pixel is back-projected (focal ≈ 280 px, principal point at the image
   centre; x right, y up, z away from the camera, in the file's depth units).
2. Points are centred on the sequence's median point and scaled by the body height (median over
   frames of the 1–99 % vertical extent), so the pattern is body-centred and scale-free.
3. Each frame's points add Gaussian RBFs (σ = 2 voxels) on a 36 × 36 × 26 grid over
   ±(0.75, 0.8, 0.6) body heights, each frame with unit mass (trilinear binning, then a
   separable Gaussian blur, as :class:`sdp.DensityField`'s fast path).
4. The frame grids G_t give three channels: density G_t, appeared density max(G_t+1 − G_t, 0)
   and disappeared density max(G_t − G_t+1, 0) — the Boolean difference of consecutive frames
   used by change detection, here as signed 3-D motion energy.
5. Time is cut by cumulative motion energy into a pyramid of 1, 2 and 4 segments (density
   averaged, motion summed per segment); grids are subsampled by 2 (the blur oversamples), each
   (level, channel) block is square-rooted and L2-normalized, and all are concatenated.

A linear ridge classifier (one-vs-rest least squares) separates the actions; its ``alpha`` is
chosen by leave-one-subject-out cross-validation on the training subjects only. Comparing two
patterns is a dot product: linear in the grid.

References
----------
.. [1] A. W. Vieira et al., "STOP: Space-Time Occupancy Patterns for 3D action recognition from
   depth map sequences", CIARP 2012.
.. [2] W. Li, Z. Zhang and Z. Liu, "Action recognition based on a bag of 3D points", CVPR
   Workshops 2010 (MSR Action3D and its cross-subject protocol).
"""

from __future__ import annotations

import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numba as nb
import numpy as np
from scipy.ndimage import gaussian_filter1d

from .errors import SDPError, require
from .io import atomic_path

__all__ = ["read_sequence", "depth_to_points", "frame_densities", "sequence_descriptor", "list_sequences",
           "describe_sequences", "ActionModel", "train", "evaluate_protocol", "SUBSETS", "FOCAL"]

FOCAL = 280.0
GRID = (36, 36, 26)  # nodes along x, y (up), z (depth)
HALF = (0.75, 0.8, 0.6)  # half extent of the box, in body heights
SIGMA = 2.0  # voxels
LEVELS = (1, 2, 4)  # temporal pyramid: segments per level
ALPHAS = (0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0)
#: The standard subsets of MSR Action3D (a classifier each) and all 20 actions.
SUBSETS = {"AS1": (2, 3, 5, 6, 10, 13, 18, 20), "AS2": (1, 4, 7, 8, 9, 11, 12, 14),
           "AS3": (6, 14, 15, 16, 17, 18, 19, 20), "all": tuple(range(1, 21))}
TRAIN_SUBJECTS, TEST_SUBJECTS = (1, 3, 5, 7, 9), (2, 4, 6, 8, 10)
_NAME = re.compile(r"a(\d+)_s(\d+)_e(\d+)")


def read_sequence(path: str | os.PathLike) -> np.ndarray:
    """A depth sequence as a (T, H, W) array: MSR Action3D ``.mat`` (variable ``depth``,
    H × W × T) or the original ``.bin`` (three little-endian uint32 frames, width, height, then
    frames × height × width uint32 depths, row-major)."""
    path = Path(path)
    try:
        if path.suffix.lower() == ".bin":
            raw = np.fromfile(path, dtype="<u4")
            if raw.size < 3:
                raise SDPError("shorter than its 12-byte header")
            t, w, h = (int(v) for v in raw[:3])
            if raw.size != 3 + t * w * h:
                raise SDPError(f"header says {t} frames of {w}x{h}, the file holds {raw.size - 3} values")
            return raw[3:].reshape(t, h, w)
        if path.suffix.lower() == ".mat":
            import scipy.io

            d = scipy.io.loadmat(path, variable_names=["depth"]).get("depth")
            if d is None or d.ndim != 3:
                raise SDPError("no H x W x T variable 'depth'")
            return np.ascontiguousarray(np.transpose(d, (2, 0, 1)))
    except FileNotFoundError:
        raise SDPError(f"{path}: no such file") from None
    except (SDPError, ValueError, OSError) as exc:
        raise SDPError(f"{path}: can't read a depth sequence ({exc})") from None
    raise SDPError(f"{path}: unknown depth-sequence format; use .mat (MSR Action3D) or .bin")


def depth_to_points(depth: np.ndarray, *, focal: float = FOCAL) -> tuple[np.ndarray, np.ndarray]:
    """Foreground (non-zero) pixels of a (H, W) frame or (T, H, W) sequence as 3-D points.

    Returns ``(points (n, 3) float64, frame index (n,))``; x right, y up, z away from the
    camera, in the depth's units.
    """
    d = depth[None] if depth.ndim == 2 else depth
    _, h, w = d.shape
    t, r, c = np.nonzero(d)
    z = d[t, r, c].astype(np.float64)
    return np.stack([(c - (w - 1) / 2.0) * z / focal, ((h - 1) / 2.0 - r) * z / focal, z], axis=1), t


@nb.njit(cache=True)
def _bin_frames(g, t, w, out):
    """Add weight w[i] of point i (grid coordinates g[i]) of frame t[i] to out[t] trilinearly."""
    nx, ny, nz = out.shape[1], out.shape[2], out.shape[3]
    for i in range(g.shape[0]):
        fx, fy, fz = g[i, 0], g[i, 1], g[i, 2]
        if fx < 0 or fy < 0 or fz < 0 or fx > nx - 1 or fy > ny - 1 or fz > nz - 1:
            continue
        ix, iy, iz = min(int(fx), nx - 2), min(int(fy), ny - 2), min(int(fz), nz - 2)
        ax, ay, az = fx - ix, fy - iy, fz - iz
        for dx in range(2):
            wx = w[i] * (ax if dx else 1.0 - ax)
            for dy in range(2):
                wy = wx * (ay if dy else 1.0 - ay)
                for dz in range(2):
                    out[t[i], ix + dx, iy + dy, iz + dz] += wy * (az if dz else 1.0 - az)


def frame_densities(depth: np.ndarray) -> np.ndarray:
    """Per-frame density grids (T, 36, 36, 26) float32 in the body-centred, height-scaled box."""
    if depth.ndim != 3 or not depth.any():
        raise SDPError("a depth sequence needs shape (T, H, W) and some non-zero (foreground) pixels")
    p, t = depth_to_points(depth)
    n_frames = depth.shape[0]
    bounds = np.searchsorted(t, np.arange(n_frames + 1))
    heights = [np.subtract(*np.percentile(p[a:b, 1], [99.0, 1.0])) for a, b in zip(bounds[:-1], bounds[1:], strict=True)
               if b - a > 50]
    height = float(np.median(heights)) if heights else float(np.ptp(p[:, 1])) or 1.0
    n, half = np.asarray(GRID), np.asarray(HALF)
    g = ((p - np.median(p, axis=0)) / height + half) / (2.0 * half) * (n - 1)
    counts = np.bincount(t, minlength=n_frames).astype(np.float64)
    grids = np.zeros((n_frames, *GRID), np.float32)
    _bin_frames(g, t.astype(np.int64), 1.0 / counts[t], grids)  # unit mass per frame
    for axis in (1, 2, 3):
        grids = gaussian_filter1d(grids, SIGMA, axis=axis, mode="constant", truncate=3.0)
    return grids


def _space_time_pattern(grids: np.ndarray) -> list[list[np.ndarray]]:
    """Blocks of the temporal pyramid: for each (level, channel), its segments' grids."""
    n_frames = len(grids)
    dg = np.diff(grids, axis=0) if n_frames > 1 else np.zeros_like(grids)
    energy = np.concatenate([[0.0], np.cumsum(np.abs(dg).reshape(len(dg), -1).sum(axis=1))])
    tau = energy / energy[-1] if energy[-1] > 0 else np.linspace(0.0, 1.0, n_frames)  # motion time
    tau_step = 0.5 * (tau[1:] + tau[:-1]) if n_frames > 1 else np.zeros(1)
    channels = ((grids, tau, np.mean), (np.maximum(dg, 0.0), tau_step, np.sum),
                (np.maximum(-dg, 0.0), tau_step, np.sum))
    blocks = []
    for level in LEVELS:
        for values, at, reduce in channels:
            seg = np.minimum((at * level).astype(int), level - 1)
            blocks.append([reduce(values[seg == k], axis=0)[::2, ::2, ::2] if (seg == k).any()
                           else np.zeros(values.shape[1:], values.dtype)[::2, ::2, ::2] for k in range(level)])
    return blocks


def sequence_descriptor(depth: np.ndarray) -> np.ndarray:
    """The space-time density pattern of a (T, H, W) depth sequence as one vector (float32)."""
    out = []
    for block in _space_time_pattern(frame_densities(depth)):
        v = np.sqrt(np.maximum(np.concatenate([b.ravel() for b in block]).astype(np.float64), 0.0))
        norm = np.linalg.norm(v)
        out.append(v / norm if norm > 0 else v)
    return np.concatenate(out).astype(np.float32)


def list_sequences(folder: str | os.PathLike) -> list[tuple[Path, int, int]]:
    """``(path, action, subject)`` of the ``aXX_sYY_eZZ*.mat|.bin`` files of a folder, sorted."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SDPError(f"{folder}: not a folder of depth sequences")
    rows = [(p, int(m.group(1)), int(m.group(2))) for p in sorted(folder.iterdir())
            if p.suffix.lower() in (".mat", ".bin") and (m := _NAME.match(p.name))]
    if not rows:
        raise SDPError(f"{folder}: no depth sequence named like a01_s01_e01_sdepth.mat (or .bin)")
    return rows


def _describe_file(path) -> np.ndarray:
    return sequence_descriptor(read_sequence(path))


def describe_sequences(paths, *, workers: int = os.cpu_count() or 1) -> np.ndarray:
    """Descriptors (n, d) of depth-sequence files, in ``workers`` processes."""
    paths = [str(p) for p in paths]
    sequence_descriptor(np.full((2, 8, 8), 500, np.uint16))  # compile once, before forking
    if workers > 1 and len(paths) > 1:
        from concurrent.futures import ProcessPoolExecutor
        from multiprocessing import get_context

        with ProcessPoolExecutor(workers, mp_context=get_context("fork")) as pool:
            return np.stack(list(pool.map(_describe_file, paths, chunksize=4)))
    return np.stack([_describe_file(p) for p in paths])


@dataclass
class ActionModel:
    """A linear classifier of space-time density patterns: score = X · coef.T + intercept."""

    coef: np.ndarray
    intercept: np.ndarray
    classes: np.ndarray
    alpha: float

    def predict(self, descriptors: np.ndarray) -> np.ndarray:
        """Action label of each descriptor (n, d)."""
        scores = np.atleast_2d(descriptors) @ np.atleast_2d(self.coef).T + self.intercept
        if scores.shape[1] == 1:  # two actions: one decision function, positive for the second
            return self.classes[(scores[:, 0] > 0).astype(int)]
        return self.classes[np.argmax(scores, axis=1)]

    def save(self, path: str | os.PathLike) -> Path:
        """Write the model as a NumPy ``.npz`` (no pickle), atomically."""
        path = Path(path)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, coef=self.coef, intercept=self.intercept, classes=self.classes,
                                alpha=self.alpha, grid=np.asarray(GRID), levels=np.asarray(LEVELS))
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ActionModel":
        try:
            with np.load(path, allow_pickle=False) as z:
                if tuple(z["grid"]) != GRID or tuple(z["levels"]) != LEVELS:
                    raise SDPError("made with other pattern parameters")
                return cls(z["coef"], z["intercept"], z["classes"], float(z["alpha"]))
        except (OSError, KeyError, ValueError, SDPError) as exc:
            raise SDPError(f"{path}: not an sdp action model ({exc})") from None


def _ridge_dual(gram, train, test, y, alpha):
    """Predictions of RidgeClassifier(alpha) (intercept, ±1 targets), solved from a Gram matrix."""
    classes = np.unique(y[train])
    targets = np.where(y[train][:, None] == classes[None], 1.0, -1.0)
    k_tr, k_te = gram[np.ix_(train, train)], gram[np.ix_(test, train)]
    mean = k_tr.mean(axis=0)
    centred = k_tr - mean[:, None] - mean[None] + mean.mean()
    centred_te = k_te - k_te.mean(axis=1, keepdims=True) - mean[None] + mean.mean()
    a = np.linalg.solve(centred + alpha * np.eye(len(centred)), targets - targets.mean(axis=0))
    return classes[np.argmax(centred_te @ a + targets.mean(axis=0), axis=1)]


def _linear_model():
    """``sklearn.linear_model`` (the ``actions`` extra), or a one-line :class:`~sdp.MissingDependencyError`."""
    return require("sklearn.linear_model", "actions", "the action classifier", package="scikit-learn")


def train(descriptors: np.ndarray, actions: np.ndarray, subjects: np.ndarray, *,
          alphas=ALPHAS) -> tuple[ActionModel, float]:
    """Fit the classifier; ``alpha`` by leave-one-subject-out cross-validation on these data.

    Returns the model and its cross-validated accuracy (fraction).
    """
    RidgeClassifier = _linear_model().RidgeClassifier

    x, y, s = np.asarray(descriptors, np.float64), np.asarray(actions), np.asarray(subjects)
    if len(np.unique(y)) < 2 or len(np.unique(s)) < 2:
        raise SDPError("training needs at least two actions and two subjects")
    gram = x @ x.T
    folds = [(np.flatnonzero(s != v), np.flatnonzero(s == v)) for v in np.unique(s)]
    cv = {a: np.mean(np.concatenate([_ridge_dual(gram, tr, te, y, a) == y[te] for tr, te in folds]))
          for a in alphas}
    alpha = max(alphas, key=lambda a: (cv[a], a))  # ties: the stronger regularization
    clf = RidgeClassifier(alpha=alpha).fit(x, y)
    return ActionModel(clf.coef_, clf.intercept_, clf.classes_, alpha), float(cv[alpha])


def evaluate_protocol(folder: str | os.PathLike, *, workers: int = os.cpu_count() or 1) -> dict:
    """The cross-subject protocol: train on subjects 1, 3, 5, 7, 9, test on 2, 4, 6, 8, 10.

    One classifier per subset (AS1, AS2, AS3) and one for all 20 actions; every choice
    (``alpha``) is made by cross-validation on the training subjects. Returns accuracies as
    fractions, the cross-validated accuracies, per-subset confusion data and timings.
    """
    _linear_model()  # before describing the sequences
    t0 = time.perf_counter()
    rows = list_sequences(folder)
    x = describe_sequences([r[0] for r in rows], workers=workers)
    y, s = np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
    t1 = time.perf_counter()
    out = {"accuracy": {}, "cv_accuracy": {}, "alpha": {}, "confusion": {}}
    for name, acts in SUBSETS.items():
        tr, te = np.isin(y, acts) & np.isin(s, TRAIN_SUBJECTS), np.isin(y, acts) & np.isin(s, TEST_SUBJECTS)
        if not tr.any() or not te.any():
            raise SDPError(f"{folder}: subset {name} needs sequences of training and test subjects")
        model, cv = train(x[tr], y[tr], s[tr])
        pred = model.predict(x[te])
        out["accuracy"][name] = float(np.mean(pred == y[te]))
        out["cv_accuracy"][name], out["alpha"][name] = cv, model.alpha
        out["confusion"][name] = {"truth": y[te].tolist(), "predicted": pred.tolist()}
    out["accuracy"]["mean_AS"] = float(np.mean([out["accuracy"][k] for k in ("AS1", "AS2", "AS3")]))
    out["timings"] = {"read_and_describe": t1 - t0, "train_and_test": time.perf_counter() - t1}
    out["sequences"] = len(rows)
    return out
