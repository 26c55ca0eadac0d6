"""Pictures of results: changed points red over unchanged blue (the paper's Figure 9)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .io import atomic_path

__all__ = ["render_changes"]

_VIEWS = ((25, -60, "oblique"), (90, -90, "top"), (0, -90, "front"))


def render_changes(path: str | os.PathLike, xyz: np.ndarray, changed: np.ndarray, *, title: str = "",
                   max_points: int = 80_000, seed: int = 0) -> Path:
    """Write a PNG with three views of ``xyz``: changed points red, unchanged blue, with counts.

    Unchanged points are subsampled to ``max_points`` for drawing; changed points are all drawn,
    on top.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xyz, changed = np.asarray(xyz), np.asarray(changed, bool)
    rng = np.random.default_rng(seed)
    still = np.flatnonzero(~changed)
    if len(still) > max_points:
        still = rng.choice(still, max_points, replace=False)
    moved = np.flatnonzero(changed)
    fig = plt.figure(figsize=(15, 5.4), dpi=110)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    for i, (elev, azim, name) in enumerate(_VIEWS):
        ax = fig.add_subplot(1, 3, i + 1, projection="3d")
        ax.scatter(*xyz[still].T, s=0.6, c="#3b6fb6", alpha=0.5, linewidths=0,
                   label=f"unchanged ({(~changed).sum():,})")
        ax.scatter(*xyz[moved].T, s=1.5, c="#d62728", alpha=0.9, linewidths=0, label=f"changed ({changed.sum():,})")
        ax.view_init(elev=elev, azim=azim)
        ax.set_box_aspect(np.maximum(hi - lo, 1e-9))
        ax.set_title(name)
        ax.set_xlabel("x")
        ax.set_ylabel("y")
        ax.set_zlabel("z")
        if i == 0:
            ax.legend(loc="upper left", markerscale=8, fontsize=9)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
