"""A simulated depth sensor in an office-like room: the scene ``make demo`` runs on.

Rays from a pinhole camera (Kinect-like: 57° × 43° field of view) are cast against the room's
walls and furniture (axis-aligned boxes), so objects occlude what lies behind them. Depth noise
follows the Kinect's axial model σ(z) = 1.2 mm + 1.9 mm·(z − 0.4 m)² (Nguyen et al.); returns
beyond 4.5 m are dropped as the sensor does.

References
----------
.. [1] C. V. Nguyen, S. Izadi, D. Lovell, "Modeling Kinect sensor noise for improved 3D
   reconstruction and tracking", 3DIMPVT 2012.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Box", "OfficeScene", "office_scene", "scan", "CAMERA"]

#: Where the simulated camera stands (metres), for both scans.
CAMERA = (0.3, 0.2, 2.2)


@dataclass(frozen=True)
class Box:
    """An axis-aligned box between corners ``lo`` and ``hi`` (metres)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    name: str = ""


ROOM = Box((0.0, 0.0, 0.0), (5.0, 4.0, 2.7), "room")
FURNITURE = (
    Box((1.0, 1.6, 0.72), (2.6, 2.6, 0.76), "table top"),
    Box((1.05, 1.65, 0.0), (1.12, 1.72, 0.72), "table leg"),
    Box((2.48, 2.48, 0.0), (2.55, 2.55, 0.72), "table leg"),
    Box((3.9, 3.0, 0.0), (4.8, 3.9, 1.8), "cabinet"),
    Box((0.0, 2.8, 0.0), (0.6, 3.9, 2.0), "shelf"),
    Box((2.9, 0.5, 0.0), (3.4, 1.0, 0.45), "stool"),
)
#: Ten inserted objects of various sizes (the paper's experiment inserts 10 objects).
INSERTED = (
    Box((1.2, 1.8, 0.76), (1.5, 2.1, 1.06), "box 30 cm"),
    Box((1.9, 2.2, 0.76), (2.0, 2.3, 0.98), "bottle"),
    Box((2.2, 1.7, 0.76), (2.45, 1.9, 0.88), "book stack"),
    Box((1.6, 1.75, 0.76), (1.68, 1.83, 0.86), "mug"),
    Box((3.0, 2.0, 0.0), (3.5, 2.6, 0.5), "crate"),
    Box((1.4, 0.6, 0.0), (1.8, 1.0, 1.1), "person-sized bag"),
    Box((4.0, 1.5, 0.0), (4.4, 2.2, 0.8), "chair"),
    Box((3.95, 3.1, 1.8), (4.35, 3.5, 2.05), "box on cabinet"),
    Box((2.95, 0.6, 0.45), (3.3, 0.9, 0.7), "box on stool"),
    Box((2.0, 3.4, 0.0), (2.25, 3.65, 1.5), "coat stand"),
)


@dataclass
class OfficeScene:
    """A reference scan, a current scan with objects inserted, and the per-point truth."""

    reference: np.ndarray
    current: np.ndarray
    appeared_truth: np.ndarray  # over current: the point lies on an inserted object
    object_of_current: np.ndarray  # index into INSERTED, -1 for room and furniture
    camera: tuple = CAMERA  # the sensor origin of both scans


def scan(boxes, *, camera=CAMERA, target=(3.0, 2.6, 0.7), width=320, height=240,
         max_range=4.5, rng=None) -> tuple[np.ndarray, np.ndarray]:
    """Cast one ray per pixel; return the noisy hit points (n, 3) and the index of the box hit.

    Index -1 is the room's walls, floor or ceiling; i ≥ 0 is ``boxes[i]``.
    """
    rng = np.random.default_rng() if rng is None else rng
    cam, tgt = np.asarray(camera, float), np.asarray(target, float)
    fwd = (tgt - cam) / np.linalg.norm(tgt - cam)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    fx = (width / 2) / np.tan(np.radians(57 / 2))
    fy = (height / 2) / np.tan(np.radians(43 / 2))
    u, v = np.meshgrid(np.arange(width) + 0.5 - width / 2, np.arange(height) + 0.5 - height / 2)
    d = fwd + (u.ravel() / fx)[:, None] * right - (v.ravel() / fy)[:, None] * up
    depth_per_t = 1.0 / np.linalg.norm(d, axis=1)  # depth z = t · cos(angle to the axis)
    d *= depth_per_t[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t1, t2 = (np.asarray(ROOM.lo) - cam) * inv, (np.asarray(ROOM.hi) - cam) * inv
        t_hit = np.maximum(t1, t2).min(axis=1)  # leaving the room from inside
        which = np.full(len(d), -1)
        for i, b in enumerate(boxes):
            a1, a2 = (np.asarray(b.lo) - cam) * inv, (np.asarray(b.hi) - cam) * inv
            near, far = np.minimum(a1, a2).max(axis=1), np.maximum(a1, a2).min(axis=1)
            hit = (near <= far) & (near > 0) & (near < t_hit)
            t_hit = np.where(hit, near, t_hit)
            which = np.where(hit, i, which)
    z = t_hit * depth_per_t
    keep = (z > 0.5) & (z < max_range)
    sigma = 0.0012 + 0.0019 * (z[keep] - 0.4) ** 2
    t_noisy = t_hit[keep] * (1 + sigma * rng.standard_normal(keep.sum()) / z[keep])
    return cam + d[keep] * t_noisy[:, None], which[keep]


def office_scene(*, seed: int = 0, width: int = 320, height: int = 240) -> OfficeScene:
    """Reference = room + furniture; current = the same plus :data:`INSERTED`, new sensor noise."""
    rng = np.random.default_rng(seed)
    reference, _ = scan(FURNITURE, width=width, height=height, rng=rng)
    current, which = scan(FURNITURE + INSERTED, width=width, height=height, rng=rng)
    obj = np.where(which >= len(FURNITURE), which - len(FURNITURE), -1)
    return OfficeScene(reference, current, obj >= 0, obj)
