"""Pictures of results: changed points red over unchanged blue (the paper's Figure 9) as PNG
(matplotlib) or as an interactive page (plotly, the ``html`` extra), and slices of a field."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .errors import MissingDependencyError
from .io import atomic_path

__all__ = ["render_changes", "render_changes_html", "render_field"]

_RED, _BLUE = "#d62728", "#3b6fb6"

_VIEWS = ((25, -60, "oblique"), (90, -90, "top"), (0, -90, "front"))


def render_changes(path: str | os.PathLike, xyz: np.ndarray, changed: np.ndarray, *, title: str = "",
                   max_points: int = 80_000, seed: int = 0) -> Path:
    """Write a PNG with three views of ``xyz``: changed points red, unchanged blue, with counts.

    Unchanged points are subsampled to ``max_points`` for drawing; changed points are all drawn,
    on top.
    """
    plt = _pyplot()
    xyz, changed = np.asarray(xyz), np.asarray(changed, bool)
    still, moved = _drawn(changed, max_points, seed)
    fig = plt.figure(figsize=(15, 5.4), dpi=110, layout="constrained")
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    for i, (elev, azim, name) in enumerate(_VIEWS):
        ax = fig.add_subplot(1, 3, i + 1, projection="3d")
        ax.scatter(*xyz[still].T, s=0.6, c=_BLUE, alpha=0.5, linewidths=0,
                   label=f"unchanged ({(~changed).sum():,})")
        ax.scatter(*xyz[moved].T, s=1.5, c=_RED, alpha=0.9, linewidths=0, label=f"changed ({changed.sum():,})")
        ax.view_init(elev=elev, azim=azim)
        ax.set_box_aspect(np.maximum(hi - lo, 1e-9))
        ax.set_title(name)
        ax.set_xlabel("x")
        ax.set_ylabel("y")
        ax.set_zlabel("z")
        if name != "oblique":  # the axis seen end-on carries no information
            (ax.set_zticks if name == "top" else ax.set_yticks)([])
        if i == 0:
            ax.legend(loc="upper left", markerscale=8, fontsize=9)
    if title:
        fig.suptitle(title)
    return _save_png(fig, path)


def render_changes_html(path: str | os.PathLike, xyz: np.ndarray, changed: np.ndarray, *, title: str = "",
                        max_points: int = 200_000, seed: int = 0) -> Path:
    """Write an interactive 3D view (plotly) that opens in a browser without a server.

    The page embeds plotly.js, so it works offline. Unchanged points are subsampled to
    ``max_points``; changed points are all drawn.

    Raises
    ------
    MissingDependencyError
        plotly is not installed (``pip install "sdp[html]"``).
    """
    try:
        import plotly.graph_objects as go
    except ImportError:
        raise MissingDependencyError('--html needs plotly: pip install "sdp[html]"') from None
    xyz, changed = np.asarray(xyz), np.asarray(changed, bool)
    still, moved = _drawn(changed, max_points, seed)
    fig = go.Figure([go.Scatter3d(x=xyz[i, 0], y=xyz[i, 1], z=xyz[i, 2], mode="markers", name=f"{name} ({n:,})",
                                  marker={"size": size, "color": color})
                     for i, name, n, size, color in ((still, "unchanged", (~changed).sum(), 1, _BLUE),
                                                     (moved, "changed", changed.sum(), 2, _RED))])
    fig.update_layout(title=title, scene={"aspectmode": "data"}, legend={"itemsizing": "constant"})
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.write_html(tmp, include_plotlyjs=True)
    return path


def render_field(path: str | os.PathLike, field, *, center: np.ndarray | None = None,
                 max_pixels: int = 500) -> Path:
    """Write a PNG of three axis-aligned slices of F = h − G through ``center``.

    Each slice is sampled at the node spacing (coarser if a side would exceed ``max_pixels``)
    by the field's own trilinear query; blue is inside the cluster volume (F < 0), red outside,
    and the black line is the boundary F = 0. ``center`` defaults to the middle of the
    allocated blocks.
    """
    from matplotlib.colors import TwoSlopeNorm

    plt = _pyplot()
    l = field.voxel_size
    keys = field.global_keys
    lo, hi = keys.min(axis=0) * 8 * l, (keys.max(axis=0) + 1) * 8 * l
    center = (lo + hi) / 2 if center is None else np.asarray(center, np.float64)
    step = max(l, float((hi - lo).max()) / max_pixels)
    axes = [np.arange(a, b, step) for a, b in zip(lo, hi, strict=True)]
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-3 * field.h, vmax=field.h)  # colours saturate deep inside
    fig, panels = plt.subplots(1, 3, figsize=(16, 5), dpi=110, layout="constrained")
    names = "xyz"
    for normal, ax in enumerate(panels):
        u, v = [a for a in range(3) if a != normal]
        uu, vv = np.meshgrid(axes[u], axes[v])
        pts = np.empty((uu.size, 3))
        pts[:, normal], pts[:, u], pts[:, v] = center[normal], uu.ravel(), vv.ravel()
        f = field.field(pts).reshape(uu.shape)
        im = ax.imshow(np.maximum(f, norm.vmin), origin="lower", cmap="RdBu_r", norm=norm, interpolation="nearest",
                       extent=(axes[u][0], axes[u][-1], axes[v][0], axes[v][-1]))
        if (f < 0).any() and (f > 0).any():
            ax.contour(uu, vv, f, levels=[0.0], colors="k", linewidths=0.7)
        ax.set_title(f"{names[normal]} = {center[normal]:.4g}")
        ax.set_xlabel(names[u])
        ax.set_ylabel(names[v])
        ax.set_aspect("equal")
    fig.colorbar(im, ax=panels, shrink=0.8, label="F = h − G  (< 0: inside the cluster volume)")
    fig.suptitle(f"density field: voxel {l:.4g}, σ {field.sigma:.4g}, h {field.h:.3f}")
    return _save_png(fig, path)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _drawn(changed: np.ndarray, max_points: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the unchanged points to draw (at most ``max_points``) and of all changed points."""
    still = np.flatnonzero(~changed)
    if len(still) > max_points:
        still = np.random.default_rng(seed).choice(still, max_points, replace=False)
    return still, np.flatnonzero(changed)


def _save_png(fig, path) -> Path:
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
