"""Human action recognition from depth sequences with space-time density patterns.

The paper's second application (method.md §5), in the spirit of STOP (Vieira et al., space-time
occupancy patterns): a depth sequence becomes a 4-D (x, y, z, t) density pattern.

1. Every foreground pixel is back-projected (focal ≈ 280 px, principal point at the image
   centre; x right, y up, z away from the camera, in the file's depth units).
2. Points are centred on the sequence's median point and scaled by the body height (median over
   frames of the 1–99 % vertical extent), so the pattern is body-centred and scale-free.
3. Each frame's points add Gaussian RBFs (σ = 2 voxels) on a 36 × 36 × 26 grid over
   ±(0.75, 0.8, 0.6) body heights, each frame with unit mass (trilinear binning, then a
   separable Gaussian blur, as :class:`sdp.DensityField`'s fast path). The blur oversamples, so
   grids keep every second node (18 × 18 × 13), each axis decimated right after its blur pass.
4. The frame grids G_t give seven channels: density G_t and, for frame gaps k = 1, 2, 4, the
   appeared density max(G_t+k − G_t, 0) and the disappeared density max(G_t − G_t+k, 0) — the
   Boolean difference of change detection, here as signed 3-D motion energy at three speeds.
5. Time is measured by cumulative motion energy (|G_t+1 − G_t| summed), so a pattern does not
   depend on how fast an action is performed, and cut into a pyramid of 1, 2 and 4 segments with
   soft (triangular) membership: a frame between two segment centres counts in both, by its
   distance. Density is averaged per segment; motion is summed, and also taken at its maximum
   over each segment's frames (hard segments), which keeps a brief fast stroke. Each (level,
   channel, pooling) block is raised to the power 0.35 (a power normalization, stronger than
   the square root) and L2-normalized (39 blocks, 383,292 values).
6. Directional motion: the normal flow of the density between consecutive frames,
   −(G_t+1 − G_t) · ∂G/∂a for a = x, y, z (for a density carried at velocity v it is
   v_a (∂G/∂a)²), split by sign into motion towards +a and −a: six channels, each taken at its
   maximum over the hard segments of the pyramid, powered and L2-normalized as above, then
   scaled so that the 18 flow blocks together weigh a quarter of the 39 others in a dot product
   (176,904 values; 560,196 for the body).
7. The hand box: the same 57 blocks (on the body's motion time) in a finer box that follows the
   moving hand, 16³ nodes over ±0.25 body heights (every second node kept: 8³, 0.031 body heights
   apart, the body's 0.083). The hand is tracked as the centroid of the motion energy
   |G_t+1 − G_t| above the body's centre, smoothed over time (σ = 2 frames, weighted by motion
   mass): the hand-trajectory actions (draw x, hand catch) move one hand, and the body's box sees
   it at a coarse scale only (68,096 values; 628,292 in all).

Two linear ridge classifiers (one-vs-rest least squares), one on the body's part of the
descriptor and one on the hand's, separate the actions; their decision values are averaged (score
fusion; a mix of linear models is one linear model, so a model is one coefficient matrix). Each
part's ``alpha`` is chosen by its own leave-one-subject-out cross-validation on the training
subjects only. Each is solved in the dual, from the Gram matrix of the training descriptors' part
(a few hundred sequences against half a million values), which is also what the cross-validation
needs; the coefficients are kept in float32. Comparing two patterns is a dot product: linear in
the grid. Every other constant here (gaps, soft pyramid, power, σ, the flow channels and their
weight, the hand box, its track and its share) was chosen by the same cross-validation, on the
training subjects of MSR Action3D (``benchmarks/actions_configurations.tsv`` lists the
configurations compared). :class:`ActionStream` applies a model to a live stream of
frames: the window of the last frames, every few frames.

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
from functools import lru_cache
from pathlib import Path

import numba as nb
import numpy as np

from ..defaults import DEFAULTS
from ..errors import SDPError
from ..io._cloud import natural_key
from ..io._output import atomic_path

__all__ = ["read_sequence", "depth_to_points", "frame_densities", "sequence_descriptor", "list_sequences",
           "describe_sequences", "ActionModel", "ActionStream", "read_frames", "train", "evaluate_protocol", "SUBSETS",
           "FOCAL", "PARAMETERS"]

FOCAL = 280.0
GRID = (36, 36, 26)  # nodes along x, y (up), z (depth)
HALF = (0.75, 0.8, 0.6)  # half extent of the box, in body heights
SIGMA = 2.0  # voxels
STEP = 2  # grids keep every STEP-th node (the blur oversamples)
LEVELS = (1, 2, 4)  # temporal pyramid: segments per level
GAPS = (1, 2, 4)  # frame gaps of the appeared / disappeared channels
POWER = 0.35  # power normalization of each block, before its L2 normalization
FLOW_GAP = 1  # frame gap of the directional-motion (normal flow) channels
FLOW_WEIGHT = 0.25  # the flow blocks' share of the kernel, relative to the density and motion blocks'
HAND_GRID = 16  # nodes per axis of the hand box (every STEP-th kept, as the body's)
HAND_HALF = 0.25  # half extent of the hand box, in body heights
HAND_SMOOTH = 2.0  # frames: the temporal σ of the hand track
HAND_WEIGHT = 0.5  # the hand classifier's share of the decision values (score fusion with the body's)
ALPHAS = (0.0003, 0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0)
#: What a saved model's descriptors depend on; a model made with other values is refused.
PARAMETERS = {"grid": GRID, "half": HALF, "sigma": SIGMA, "step": STEP, "levels": LEVELS, "gaps": GAPS,
              "power": POWER, "flow_gap": FLOW_GAP, "flow_weight": FLOW_WEIGHT, "hand_grid": HAND_GRID,
              "hand_half": HAND_HALF, "hand_smooth": HAND_SMOOTH, "hand_weight": HAND_WEIGHT, "version": 5}
_BLOCK_SEGMENTS = sum(LEVELS) * (1 + 4 * len(GAPS) + 6)  # segments × channels: density, motion (sum, max), flow
#: Values of the body's pattern and of the hand's in a descriptor (body first).
BODY_SIZE = _BLOCK_SEGMENTS * int(np.prod([-(-n // STEP) for n in GRID]))
HAND_SIZE = _BLOCK_SEGMENTS * (-(-HAND_GRID // STEP)) ** 3
#: The descriptor's parts, each with a ridge classifier of its own: (first value, end, share of the decision values).
PARTS = ((0, BODY_SIZE, 1.0 - HAND_WEIGHT), (BODY_SIZE, BODY_SIZE + HAND_SIZE, HAND_WEIGHT))
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
    if not path.is_file():  # SciPy names a missing .mat otherwise ("Reader needs file name …")
        raise SDPError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    try:
        if path.suffix.lower() == ".bin":
            raw = np.fromfile(path, dtype="<u4")
            if raw.size < 3:
                raise SDPError("shorter than its 12-byte header")
            t, w, h = (int(v) for v in raw[:3])
            if raw.size != 3 + t * w * h:
                raise SDPError(f"header says {t} frames of {w}x{h}, the file holds {raw.size - 3} values")
            return _checked_depth(raw[3:].reshape(t, h, w))
        if path.suffix.lower() == ".mat":
            import scipy.io

            d = scipy.io.loadmat(path, variable_names=["depth"]).get("depth")
            if d is None or d.ndim != 3:
                raise SDPError("no H x W x T variable 'depth'")
            return _checked_depth(np.ascontiguousarray(np.transpose(d, (2, 0, 1))))
    except FileNotFoundError:
        raise SDPError(f"{path}: no such file") from None
    except Exception as exc:  # SciPy's MatReadError, a zlib error, a short read: all name the file
        raise SDPError(f"{path}: can't read a depth sequence ({exc or type(exc).__name__})") from None
    raise SDPError(f"{path}: unknown depth-sequence format; use .mat (MSR Action3D) or .bin")


def _checked_depth(depth: np.ndarray) -> np.ndarray:
    """``depth`` (T, H, W) if it is a sequence of depths: real, finite, not negative, at least two
    frames (a motion needs two); else :class:`SDPError` (the caller names the file)."""
    if depth.dtype.kind not in "uif" or depth.dtype == bool:
        raise SDPError(f"'depth' holds {depth.dtype} values, not depths (MSR Action3D's are uint16 millimetres)")
    if depth.shape[0] < 2:
        raise SDPError(f"'depth' holds {depth.shape[0]} frame(s): an action needs at least 2")
    if depth.dtype.kind == "f" and not np.isfinite(depth).all():
        raise SDPError("'depth' holds NaN or infinite values")
    if depth.min(initial=0) < 0:
        raise SDPError("'depth' holds negative depths")
    return depth


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
def _bin_depth(depth, focal, centres, scale, n_nodes, out):
    """Back-project every foreground pixel of ``depth`` (T, H, W) and add it trilinearly to its
    frame's grid ``out[t]`` with weight 1 / (the frame's foreground pixels): grid coordinates are
    (point − centres[t]) · scale + (n_nodes − 1) / 2 per axis, as :func:`depth_to_points` gives
    points (one centre per frame: the body's box stays, the hand's follows the hand)."""
    n_frames, h, w = depth.shape
    nx, ny, nz = out.shape[1], out.shape[2], out.shape[3]
    for t in range(n_frames):
        count = 0
        for r in range(h):
            for c in range(w):
                if depth[t, r, c] != 0:
                    count += 1
        if count == 0:
            continue
        weight = 1.0 / count
        for r in range(h):
            for c in range(w):
                if depth[t, r, c] == 0:
                    continue
                z = float(depth[t, r, c])
                fx = ((c - (w - 1) / 2.0) * z / focal - centres[t, 0]) * scale[0] + (n_nodes[0] - 1) / 2.0
                fy = (((h - 1) / 2.0 - r) * z / focal - centres[t, 1]) * scale[1] + (n_nodes[1] - 1) / 2.0
                fz = (z - centres[t, 2]) * scale[2] + (n_nodes[2] - 1) / 2.0
                if fx < 0 or fy < 0 or fz < 0 or fx > nx - 1 or fy > ny - 1 or fz > nz - 1:
                    continue
                ix, iy, iz = min(int(fx), nx - 2), min(int(fy), ny - 2), min(int(fz), nz - 2)
                ax, ay, az = fx - ix, fy - iy, fz - iz
                for dx in range(2):
                    wx = weight * (ax if dx else 1.0 - ax)
                    for dy in range(2):
                        wy = wx * (ay if dy else 1.0 - ay)
                        for dz in range(2):
                            out[t, ix + dx, iy + dy, iz + dz] += wy * (az if dz else 1.0 - az)


def _body_frame(depth: np.ndarray) -> tuple[np.ndarray, float]:
    """The body's centre (median point) and height (median over frames of the 1–99 % vertical
    extent) of a sequence, estimated on every second pixel row and column."""
    _, h, w = depth.shape
    half = np.ascontiguousarray(depth[:, ::2, ::2])  # contiguous: nonzero and the gather twice as fast
    t, r, c = np.nonzero(half)
    z = half[t, r, c].astype(np.float64)
    r, c = 2 * r, 2 * c
    x, y = (c - (w - 1) / 2.0) * z / FOCAL, ((h - 1) / 2.0 - r) * z / FOCAL  # a column each: contiguous
    bounds = np.searchsorted(t, np.arange(len(depth) + 1))
    heights = [np.subtract(*np.percentile(y[a:b], [99.0, 1.0])) for a, b in zip(bounds[:-1], bounds[1:], strict=True)
               if b - a > 12]
    height = float(np.median(heights)) if heights else float(np.ptp(y))
    return np.array([np.median(x), np.median(y), np.median(z)]), height or 1.0


@lru_cache(maxsize=8)
def _blur_matrix(n: int, step: int) -> np.ndarray:
    """The Gaussian blur (σ = :data:`SIGMA` nodes, truncated at 3σ, zero outside: scipy's
    ``gaussian_filter1d(mode="constant", truncate=3.0)``) of an axis of ``n`` nodes as a matrix,
    keeping every ``step``-th output node: (⌈n / step⌉, n), float32."""
    radius = int(3.0 * SIGMA + 0.5)
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / SIGMA) ** 2)
    offset = np.arange(n)[None] - np.arange(n)[:, None]
    m = np.where(np.abs(offset) <= radius, (kernel / kernel.sum())[np.clip(offset + radius, 0, 2 * radius)], 0.0)
    return np.ascontiguousarray(m[::step], dtype=np.float32)


def frame_densities(depth: np.ndarray, *, step: int = 1) -> np.ndarray:
    """Per-frame density grids in the body-centred, height-scaled box, float32.

    ``(T, 36, 36, 26)``, or every ``step``-th node of it (``step=2``: ``(T, 18, 18, 13)``, the
    full grids subsampled, to float rounding: each axis is decimated by its own blur pass).
    """
    _check_depth(depth)
    centre, height = _body_frame(depth)
    return _densities(depth, np.tile(centre, (len(depth), 1)), np.asarray(HALF) * height, GRID, step)


def _check_depth(depth: np.ndarray) -> None:
    if depth.ndim != 3 or not depth.any():
        raise SDPError("a depth sequence needs frames of depths (T, H, W; a .mat file's H x W x T) with some "
                       "non-zero (foreground) pixels")


def _densities(depth: np.ndarray, centres: np.ndarray, half: np.ndarray, shape: tuple[int, int, int],
               step: int) -> np.ndarray:
    """Blurred per-frame density grids (T, ...) of ``shape`` nodes over ±``half`` around each
    frame's centre ``centres[t]`` (depth units), every ``step``-th node kept."""
    n = np.asarray(shape, np.float64)
    scale = (n - 1) / (2.0 * half)
    grids = np.zeros((depth.shape[0], *shape), np.float32)
    _bin_depth(np.ascontiguousarray(depth), FOCAL, np.ascontiguousarray(centres, np.float64), scale, n,
               grids)  # unit mass per frame
    # the separable blur as three small matrix products (BLAS), each computing only the kept nodes
    t, nx, ny, nz = grids.shape
    grids = np.matmul(_blur_matrix(nx, step), grids.reshape(t, nx, ny * nz)).reshape(t, -1, ny, nz)
    grids = np.matmul(_blur_matrix(ny, step), grids)
    return np.ascontiguousarray(np.matmul(grids, _blur_matrix(nz, step).T))


def _soft_segments(at: np.ndarray, level: int) -> np.ndarray:
    """Membership (len(at), level) of times ``at`` in [0, 1] in ``level`` equal segments:
    triangular around each segment's centre, reaching the neighbouring centres (a frame at a
    centre belongs to that segment only; before the first or after the last centre, to it)."""
    centres = (np.arange(level) + 0.5) / level
    return np.maximum(0.0, 1.0 - np.abs(np.clip(at, centres[0], centres[-1])[:, None] - centres[None]) * level)


def _hard_max(values: np.ndarray, at: np.ndarray, level: int) -> np.ndarray:
    """Maximum of ``values`` (n, m) over the frames of each of ``level`` equal (hard) segments of
    the times ``at`` (non-decreasing, in [0, 1]); zero for a segment without frames."""
    seg = np.minimum((at * level).astype(int), level - 1)
    peak = np.zeros((level, values.shape[1]), values.dtype)
    for k in np.unique(seg):
        peak[k] = values[seg == k].max(axis=0)
    return peak


def _motion_time(grids: np.ndarray) -> np.ndarray:
    """Each frame's time in [0, 1] by cumulative motion energy (|G_t+1 − G_t| summed); uniform
    when nothing moves."""
    n_frames = len(grids)
    dg = np.diff(grids, axis=0) if n_frames > 1 else np.zeros_like(grids)
    energy = np.concatenate([[0.0], np.cumsum(np.abs(dg).reshape(len(dg), -1).sum(axis=1))])
    return energy / energy[-1] if energy[-1] > 0 else np.linspace(0.0, 1.0, n_frames)


def _space_time_pattern(grids: np.ndarray, tau: np.ndarray | None = None) -> list[np.ndarray]:
    """Blocks of the temporal pyramid, one per (level, channel): (level, *grid) arrays.

    ``grids`` (T, ...) are a sequence's frame densities; channels are the density (averaged per
    segment) and, for each gap in :data:`GAPS`, the appeared and disappeared densities, each
    summed (soft segments) and by its maximum (hard segments). ``tau``: each frame's time in
    [0, 1] (default: the grids' own motion time; the hand box takes the body's).
    """
    n_frames = len(grids)
    tau = _motion_time(grids) if tau is None else tau
    channels = [(grids.reshape(n_frames, -1), tau, True)]
    for k in GAPS:
        if n_frames > k:
            d, at = (grids[k:] - grids[:-k]).reshape(n_frames - k, -1), 0.5 * (tau[k:] + tau[:-k])
        else:
            d, at = np.zeros((1, grids[0].size), grids.dtype), np.zeros(1)
        channels += [(np.maximum(d, 0.0), at, False), (np.maximum(-d, 0.0), at, False)]
    blocks = []
    for level in LEVELS:
        for values, at, mean in channels:
            w = _soft_segments(at, level)
            pooled = w.T @ values
            if mean:
                pooled /= np.maximum(w.sum(axis=0), 1e-12)[:, None]
            blocks.append(pooled.reshape(level, *grids.shape[1:]))
            if not mean:  # motion also by its maximum over each (hard) segment's frames, which keeps a brief stroke
                blocks.append(_hard_max(values, at, level).reshape(level, *grids.shape[1:]))
    return blocks


def _flow_pattern(grids: np.ndarray, tau: np.ndarray | None = None) -> list[np.ndarray]:
    """Blocks of directional motion, one per (level, direction): (level, *grid) arrays.

    The normal flow of the density between frames t and t + :data:`FLOW_GAP`: for a density
    carried at velocity v, −∂G/∂t · ∂G/∂a = v_a (∂G/∂a)², so −(G_t+k − G_t) times the spatial
    gradient of their mean, split by sign, is the motion towards +a and −a for a = x, y, z (six
    channels: where the appeared/disappeared densities say that something moved, these say which
    way). Each is taken at its maximum over the hard segments of every pyramid level (times
    ``tau`` as in :func:`_space_time_pattern`).
    """
    n_frames, k = len(grids), FLOW_GAP
    tau = _motion_time(grids) if tau is None else tau
    if n_frames <= k:
        return [np.zeros((level, *grids.shape[1:]), grids.dtype) for level in LEVELS for _ in range(6)]
    change = grids[k:] - grids[:-k]
    mean = 0.5 * (grids[k:] + grids[:-k])
    at = 0.5 * (tau[k:] + tau[:-k])
    channels = []
    for axis in (1, 2, 3):
        p = (-change * np.gradient(mean, axis=axis)).reshape(n_frames - k, -1)
        channels += [np.maximum(p, 0.0), np.maximum(-p, 0.0)]
    return [_hard_max(values, at, level).reshape(level, *grids.shape[1:]) for level in LEVELS for values in channels]


def _hand_track(grids: np.ndarray, centre: np.ndarray, height: float) -> np.ndarray:
    """The moving hand's position in each frame (T, 3), in the depth's units, from the body's
    frame densities ``grids`` (every :data:`STEP`-th node of the :data:`GRID` box).

    The centroid of the motion energy |G_t+1 − G_t| above the body's centre (where the hands
    move; the legs' motion would pull it down), each frame taking its two frame pairs' by their
    motion mass, then smoothed over time with a Gaussian of :data:`HAND_SMOOTH` frames weighted
    by motion mass, so that still frames follow their moving neighbours. Without motion, a chest
    point (a quarter of the body height above the centre).
    """
    n_frames = len(grids)
    n = np.asarray(GRID, np.float64)
    scale = (n - 1) / (2.0 * np.asarray(HALF) * height)
    coords = [(np.arange(0, int(n[a]), STEP) - (n[a] - 1) / 2.0) / scale[a] for a in range(3)]
    upper = coords[1] > 0
    position = np.tile(centre + np.array([0.0, 0.25 * height, 0.0]), (n_frames, 1))
    mass = np.zeros(n_frames)
    if n_frames > 1:
        energy = np.abs(np.diff(grids, axis=0))[:, :, upper, :]
        m = energy.sum(axis=(1, 2, 3), dtype=np.float64)
        c = np.stack([energy.sum(axis=(2, 3)) @ coords[0], energy.sum(axis=(1, 3)) @ coords[1][upper],
                      energy.sum(axis=(1, 2)) @ coords[2]], axis=1) / np.maximum(m, 1e-12)[:, None] + centre
        total = np.zeros((n_frames, 3))
        total[:-1] += c * m[:, None]
        total[1:] += c * m[:, None]
        mass[:-1] += m
        mass[1:] += m
        moving = mass > 0
        position[moving] = total[moving] / mass[moving, None]
    t = np.arange(n_frames)
    weight = mass + 1e-9 * mass.max() if mass.max() > 0 else np.ones(n_frames)
    kernel = np.exp(-0.5 * ((t[:, None] - t[None]) / HAND_SMOOTH) ** 2) * weight[None]
    return (kernel @ position) / kernel.sum(axis=1, keepdims=True)


def sequence_descriptor(depth: np.ndarray) -> np.ndarray:
    """The space-time density pattern of a (T, H, W) depth sequence as one vector (float32): the
    body's density and motion blocks, then its directional-motion (flow) blocks (:data:`BODY_SIZE`
    values), then the same blocks of the hand box (:data:`HAND_SIZE` values)."""
    _check_depth(depth)
    centre, height = _body_frame(depth)
    grids = _densities(depth, np.tile(centre, (len(depth), 1)), np.asarray(HALF) * height, GRID, STEP)
    tau = _motion_time(grids)
    # the hand box: a finer pattern (0.031 body heights a kept node, the body's 0.083) that follows the hand,
    # on the body's time
    hand = _densities(depth, _hand_track(grids, centre, height), np.full(3, HAND_HALF * height), (HAND_GRID,) * 3,
                      STEP)
    pattern, flow = _space_time_pattern(grids, tau), _flow_pattern(grids, tau)
    # unit blocks, the flow blocks scaled so that they hold FLOW_WEIGHT of their part's kernel (a dot product
    # of descriptors)
    flow_scale = np.sqrt(FLOW_WEIGHT * len(pattern) / len(flow))
    scaled = [(b, 1.0) for b in pattern] + [(b, flow_scale) for b in flow]
    scaled += [(b, 1.0) for b in _space_time_pattern(hand, tau)] + [(b, flow_scale) for b in _flow_pattern(hand, tau)]
    v = np.empty(sum(b.size for b, _ in scaled), np.float32)
    start = 0
    for block, scale in scaled:  # block by block, in place in the output: no full-length temporaries
        part = v[start:start + block.size]
        start += block.size
        np.maximum(block.reshape(-1), 0.0, out=part, casting="same_kind")
        np.power(part, np.float32(POWER), out=part)
        norm = np.sqrt(np.square(part, dtype=np.float64).sum())
        part *= np.float32((1.0 / norm if norm > 0 else 0.0) * scale)
    return v


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
    depth = read_sequence(path)
    try:
        return sequence_descriptor(depth)
    except SDPError as exc:  # in a folder of hundreds, the file to look at
        raise SDPError(f"{path}: {exc}") from None


def describe_sequences(paths, *, workers: int = os.cpu_count() or 1) -> np.ndarray:
    """Descriptors (n, d) of depth-sequence files, in ``workers`` processes."""
    paths = [str(p) for p in paths]
    return _stack(_describe_each(paths, workers=workers), len(paths))


def _describe_each(paths: list[str], *, workers: int):
    """The descriptor of each file, in order, as they are computed (``workers`` processes)."""
    sequence_descriptor(np.full((2, 8, 8), 500, np.uint16))  # compile once, before forking
    if workers > 1 and len(paths) > 1:
        from concurrent.futures import ProcessPoolExecutor
        from multiprocessing import get_context

        with ProcessPoolExecutor(workers, mp_context=get_context("fork")) as pool:
            yield from pool.map(_describe_file, paths, chunksize=4)
    else:
        yield from map(_describe_file, paths)


def _stack(vectors, n: int) -> np.ndarray:
    """``n`` vectors into one (n, d) array as they arrive (not a list of them and then a copy)."""
    out = None
    for i, v in enumerate(vectors):
        if out is None:
            out = np.empty((n, len(v)), v.dtype)
        out[i] = v
    return out


@dataclass
class ActionModel:
    """A linear classifier of space-time density patterns: score = X · coef.T + intercept
    (``coef`` float32, one row per action; two actions: one row, positive for the second).

    ``alpha``: the ridge regularization of each part of the descriptor (:data:`PARTS`: the body's,
    the hand's), whose classifiers' decision values the coefficients mix."""

    coef: np.ndarray
    intercept: np.ndarray
    classes: np.ndarray
    alpha: tuple[float, ...]

    def predict(self, descriptors: np.ndarray) -> np.ndarray:
        """Action label of each descriptor (n, d)."""
        coef = np.atleast_2d(self.coef)
        scores = np.atleast_2d(np.asarray(descriptors, coef.dtype)) @ coef.T + self.intercept  # one dtype: BLAS
        if scores.shape[1] == 1:  # two actions: one decision function, positive for the second
            return self.classes[(scores[:, 0] > 0).astype(int)]
        return self.classes[np.argmax(scores, axis=1)]

    def save(self, path: str | os.PathLike) -> Path:
        """Write the model as a NumPy ``.npz`` (no pickle), atomically; uncompressed: the float32
        coefficients hardly compress, and they load 5× faster so."""
        path = Path(path)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, coef=self.coef, intercept=self.intercept, classes=self.classes,
                     alpha=np.asarray(self.alpha, np.float64), **{k: np.asarray(v) for k, v in PARAMETERS.items()})
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "ActionModel":
        try:
            with np.load(path, allow_pickle=False) as z:
                if not {"coef", "intercept", "classes"} <= set(z.files):  # another .npz (a labelled cloud)
                    raise OSError
                for key, value in PARAMETERS.items():
                    if key not in z or not np.array_equal(z[key], np.asarray(value)):
                        raise SDPError(f"made with other pattern parameters ({key})")
                alpha = tuple(float(a) for a in np.atleast_1d(z["alpha"]))
                coef, intercept, classes = np.atleast_2d(z["coef"]), np.atleast_1d(z["intercept"]), z["classes"]
                rows = coef.shape[0]  # one per action, or one decision function for two
                if len(classes) < 2 or rows not in ({1, 2} if len(classes) == 2 else {len(classes)}) \
                        or intercept.shape != (rows,):
                    raise SDPError(f"{len(classes)} actions, {coef.shape[0]} rows of coefficients, "
                                   f"{intercept.size} intercepts")
                return cls(z["coef"], z["intercept"], classes, alpha)
        except (KeyError, SDPError) as exc:
            raise SDPError(f"{path}: not an sdp action model ({exc})") from None
        except FileNotFoundError:
            raise SDPError(f"{path}: no such file") from None
        except Exception:  # NumPy's own words (pickled data), a cut zip (EOFError, BadZipFile): not a model
            raise SDPError(f"{path}: not an sdp action model (an .npz file that 'sdp action train' writes)") from None


class ActionStream:
    """Actions in a stream of depth frames: the last ``window`` frames are classified every
    ``every`` frames, so an action is reported ``every`` frames (+ one descriptor, ~40–50 ms) after it
    ends at the latest: a third of a second at MSR Action3D's 15 frames per second with the defaults.

    ``push(frame)`` takes one (H, W) depth frame and returns the action label when a report is
    due (``None`` otherwise, or while the window holds no foreground). A window spans about one
    action: MSR Action3D's sequences hold 13–100 frames, 40 on average.
    """

    def __init__(self, model: ActionModel, *, window: int = DEFAULTS.action_window,
                 every: int = DEFAULTS.action_every, min_frames: int = 10):
        if not (window >= 2 and every >= 1 and 2 <= min_frames <= window):
            raise SDPError(f"an action stream needs window >= min_frames >= 2 and every >= 1, got window {window}, "
                           f"min_frames {min_frames}, every {every}")
        self.model, self.window, self.every, self.min_frames = model, window, every, min_frames
        self._frames: list[np.ndarray] = []
        self.n_frames = 0

    def push(self, frame: np.ndarray) -> int | None:
        frame = np.asarray(frame)
        if frame.ndim != 2 or (self._frames and frame.shape != self._frames[-1].shape):
            raise SDPError(f"a stream's frames need one (H, W) shape, got {frame.shape}")
        self._frames = (self._frames + [frame])[-self.window:]
        self.n_frames += 1
        if len(self._frames) < self.min_frames or self.n_frames % self.every:
            return None
        depth = np.stack(self._frames)
        if not depth.any():
            return None
        return int(self.model.predict(sequence_descriptor(depth))[0])


def read_frames(source: str | os.PathLike):
    """Depth frames, one (H, W) array at a time, from a folder of ``.npy`` frames (in natural name
    order, as ``sdp watch`` reads its frames: ``f2`` before ``f10``) or from a depth-sequence file
    (``.mat``, ``.bin``: replayed frame by frame)."""
    source = Path(source)
    if source.is_dir():
        files = sorted((p for p in source.iterdir() if p.suffix.lower() == ".npy"), key=natural_key)
        if not files:
            raise SDPError(f"{source}: no .npy depth frame in the folder")
        for path in files:
            try:
                frame = np.load(path, allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise SDPError(f"{path}: can't read a depth frame ({exc})") from None
            if not isinstance(frame, np.ndarray) or frame.ndim != 2 or frame.dtype.kind not in "iuf":
                shape = getattr(frame, "shape", "an archive")
                raise SDPError(f"{path}: a depth frame is an (H, W) array of depths, got {shape}")
            yield frame
    else:
        yield from read_sequence(source)


def _centred(gram, train, test, y):
    """What a ridge classifier trained on the rows ``train`` of a Gram matrix and tested on the rows
    ``test`` reads of it: the classes and ±1 targets of the training rows, their centred Gram matrix
    and the test rows' centred dot products with them. The one place the Gram matrix is read by
    rows (the cross-subject evaluations' tests observe it)."""
    classes = np.unique(y[train])
    targets = np.where(y[train][:, None] == classes[None], 1.0, -1.0)
    k_tr, k_te = gram[np.ix_(train, train)], gram[np.ix_(test, train)]
    mean = k_tr.mean(axis=0)
    centred_te = k_te - k_te.mean(axis=1, keepdims=True) - mean[None] + mean.mean()
    return classes, targets, k_tr - mean[:, None] - mean[None] + mean.mean(), centred_te


def _ridge_scores(gram, train, test, y, alpha):
    """Classes and decision values (test, classes) of RidgeClassifier(alpha) (intercept, ±1 targets,
    one column per class), solved from a Gram matrix: the dual coefficients (:func:`_dual`)."""
    classes, targets, centred, centred_te = _centred(gram, train, test, y)
    offset = targets.mean(axis=0)
    return classes, centred_te @ np.linalg.solve(centred + alpha * np.eye(len(centred)), targets - offset) + offset


def _dual(gram, targets, alpha):
    """The ridge's dual coefficients a = (K + αI)⁻¹ (T − mean T), K the centred Gram matrix."""
    mean = gram.mean(axis=0)
    centred = gram - mean[:, None] - mean[None] + mean.mean()
    return np.linalg.solve(centred + alpha * np.eye(len(centred)), targets - targets.mean(axis=0))


_CHUNK = 16384  # descriptor columns per float64 block: the Gram and coefficients without a float64 copy of X


def _grams(x: np.ndarray, rows: np.ndarray, parts=PARTS) -> list[np.ndarray]:
    """X Xᵀ (float64) of the rows ``rows`` of ``x``, one per part (columns start:end) of ``parts``,
    accumulated over column blocks."""
    grams = []
    for start, end, _ in parts:
        gram = np.zeros((len(rows), len(rows)))
        for i in range(start, end, _CHUNK):
            block = x[rows, i:min(i + _CHUNK, end)].astype(np.float64)
            gram += block @ block.T
        grams.append(gram)
    return grams


def _loso_accuracy(grams, alphas, shares, y, folds) -> float:
    """Accuracy over the folds (train, test) of the ridge classifiers of ``grams`` at ``alphas``,
    their decision values mixed by ``shares``."""
    hits = []
    for tr, te in folds:
        mixed = sum(share * _ridge_scores(gram, tr, te, y, a)[1]
                    for gram, a, share in zip(grams, alphas, shares, strict=True))
        hits.append(np.unique(y[tr])[np.argmax(mixed, axis=1)] == y[te])
    return float(np.mean(np.concatenate(hits)))


def _choose_alphas(grams, y, folds, alphas) -> list[float]:
    """Each part's ``alpha`` (one per Gram matrix of ``grams``): the best accuracy of its own ridge
    classifier over the cross-validation ``folds`` (train, validation rows of the Gram matrices);
    ties go to the stronger regularization."""
    chosen = []
    for gram in grams:
        hits = {a: [] for a in alphas}
        for tr, te in folds:  # the fold's centred Gram matrices once, for every alpha (as _ridge_scores)
            classes, targets, centred, centred_te = _centred(gram, tr, te, y)
            offset, eye = targets.mean(axis=0), np.eye(len(tr))
            rhs = targets - offset
            for a in alphas:
                scores = centred_te @ np.linalg.solve(centred + a * eye, rhs) + offset
                hits[a].append(classes[np.argmax(scores, axis=1)] == y[te])
        cv = {a: float(np.mean(np.concatenate(hits[a]))) for a in alphas}
        chosen.append(max(alphas, key=lambda a: (cv[a], a)))
    return chosen


def _fit(x: np.ndarray, rows: np.ndarray, grams: list[np.ndarray], y: np.ndarray, s: np.ndarray,
         alphas, parts=PARTS) -> tuple[ActionModel, float]:
    """Ridge classifiers on the rows ``rows`` of ``x``, one per part of ``parts`` (``grams``: their
    Gram matrices, labels ``y``, subjects ``s``), their decision values mixed by the parts' shares:
    each part's ``alpha`` by its own leave-one-subject-out CV, then the fits in the dual.

    Each part's is the same model as scikit-learn's ``RidgeClassifier(alpha)`` on its columns
    (intercept, ±1 targets; two classes: one decision function, positive for the second): with K
    the centred Gram matrix and T the centred targets, a = (K + αI)⁻¹ T, coef = Xᵀ a (Σa = 0, so X
    need not be centred) and intercept = mean(targets) − mean(X) · coef. A mix of linear models is
    one: the parts' coefficients, each times its share, side by side. Returns the model and the
    mix's leave-one-subject-out accuracy (the parts at their chosen alphas).
    """
    folds = [(np.flatnonzero(s != v), np.flatnonzero(s == v)) for v in np.unique(s)]
    shares = [share for _, _, share in parts]
    chosen = _choose_alphas(grams, y, folds, alphas)
    classes = np.unique(y)
    targets = np.where(y[:, None] == classes[None], 1.0, -1.0)
    if len(classes) == 2:
        targets = targets[:, 1:]
    coef = np.empty((targets.shape[1], x.shape[1]), np.float32)
    offset = targets.mean(axis=0)
    for gram, alpha, (start, end, share) in zip(grams, chosen, parts, strict=True):
        dual = share * _dual(gram, targets, alpha)
        for i in range(start, end, _CHUNK):
            j = min(i + _CHUNK, end)
            block = x[rows, i:j].astype(np.float64)
            coef[:, i:j] = (block.T @ dual).T
            offset -= block.mean(axis=0) @ coef[:, i:j].T.astype(np.float64)
    return ActionModel(coef, offset, classes, tuple(float(a) for a in chosen)), _loso_accuracy(grams, chosen, shares, y,
                                                                                                folds)


def train(descriptors: np.ndarray, actions: np.ndarray, subjects: np.ndarray, *,
          alphas=ALPHAS, parts=None) -> tuple[ActionModel, float]:
    """Fit the classifier; each part's ``alpha`` by leave-one-subject-out cross-validation on these data.

    ``parts``: (first column, end, share) of each part of the descriptors with a classifier of its
    own; by default the body's and the hand's (:data:`PARTS`) for descriptors of
    :func:`sequence_descriptor`'s length, else one over all the columns. Returns the model and its
    cross-validated accuracy (fraction).
    """
    x, y, s = np.asarray(descriptors), np.asarray(actions), np.asarray(subjects)
    if len(np.unique(y)) < 2 or len(np.unique(s)) < 2:
        raise SDPError("training needs at least two actions and two subjects")
    if parts is None:
        parts = PARTS if x.shape[-1] == PARTS[-1][1] else ((0, x.shape[-1], 1.0),)
    if x.ndim != 2 or parts[-1][1] != x.shape[1]:
        raise SDPError(f"descriptors of {x.shape[-1]} values; the classifier's parts end at {parts[-1][1]}")
    rows = np.arange(len(x))
    return _fit(x, rows, _grams(x, rows, parts), y, s, alphas, parts)


def evaluate_protocol(folder: str | os.PathLike, *, workers: int = os.cpu_count() or 1) -> dict:
    """The cross-subject protocol: train on subjects 1, 3, 5, 7, 9, test on 2, 4, 6, 8, 10.

    One classifier per subset (AS1, AS2, AS3) and one for all 20 actions; every choice
    (each part's ``alpha``) is made by cross-validation on the training subjects. The training sequences are
    described and the four classifiers fitted before any test sequence is read; each test
    sequence is then described and classified as it comes (its descriptor is not kept). Returns
    accuracies as fractions, the cross-validated accuracies, per-subset confusion data, the models
    and timings.
    """
    t0 = time.perf_counter()
    rows = list_sequences(folder)
    y, s = np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
    training, test = np.flatnonzero(np.isin(s, TRAIN_SUBJECTS)), np.flatnonzero(np.isin(s, TEST_SUBJECTS))
    for name, acts in SUBSETS.items():
        if not np.isin(y[training], acts).any() or not np.isin(y[test], acts).any():
            raise SDPError(f"{folder}: subset {name} needs sequences of training and test subjects")
        if len(np.unique(y[training][np.isin(y[training], acts)])) < 2:
            raise SDPError(f"{folder}: subset {name} needs at least two actions among the training subjects' "
                           "sequences to tell apart")
        if len(np.unique(s[training][np.isin(y[training], acts)])) < 2:
            raise SDPError(f"{folder}: subset {name} needs at least two training subjects (its choices are "
                           "cross-validated leaving one subject out)")
    x = describe_sequences([rows[i][0] for i in training], workers=workers)
    t1 = time.perf_counter()
    grams = _grams(x, np.arange(len(x)))  # every subset's training rows are among these: one pass over x
    out = {"accuracy": {}, "cv_accuracy": {}, "alpha": {}, "confusion": {}, "models": {}}
    for name, acts in SUBSETS.items():
        fit = np.flatnonzero(np.isin(y[training], acts))
        model, cv = _fit(x, fit, [g[np.ix_(fit, fit)] for g in grams], y[training][fit], s[training][fit], ALPHAS)
        out["cv_accuracy"][name], out["alpha"][name], out["models"][name] = cv, model.alpha, model
    del x  # the test sequences' turn: only one descriptor at a time
    t2 = time.perf_counter()
    predicted = {name: [] for name in SUBSETS}
    for i, v in zip(test, _describe_each([str(rows[i][0]) for i in test], workers=workers), strict=True):
        for name, acts in SUBSETS.items():
            if y[i] in acts:
                predicted[name].append(int(out["models"][name].predict(v)[0]))
    for name, acts in SUBSETS.items():
        truth, pred = y[test][np.isin(y[test], acts)], np.array(predicted[name])
        out["accuracy"][name] = float(np.mean(pred == truth))
        out["confusion"][name] = {"truth": truth.tolist(), "predicted": pred.tolist()}
    out["accuracy"]["mean_AS"] = float(np.mean([out["accuracy"][k] for k in ("AS1", "AS2", "AS3")]))
    t3 = time.perf_counter()
    out["timings"] = {"describe_training": t1 - t0, "train": t2 - t1, "describe_and_test": t3 - t2}
    out["sequences"] = len(rows)
    return out
