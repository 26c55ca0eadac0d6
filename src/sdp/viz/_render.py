"""Pictures of results: changed points over unchanged ones (the paper's Figure 9), not comparable
points in a neutral grey, as PNG (matplotlib) or as an interactive page (plotly, the ``html``
extra), and slices of a field.

The picture is chosen by the data: a scene much wider than tall (airborne, mobile, terrain) is
drawn as a top-down map, in coordinates relative to a stated round origin, with a scale bar and a
north arrow (+y, as in projected coordinate systems); a room or an object as three 3-D views.
"Much wider" is :func:`is_map`: a height below a tenth of the horizontal extent. A map has no
origin for scenes near zero, and outlines and numbers the 12 largest regions. Colours are the
Okabe–Ito palette, told apart by colour-blind readers [1]: changed vermillion, unchanged blue,
not comparable a neutral grey; distances on a diverging purple–orange scale. Each picture is a
figure function (:func:`changes_figure`, :func:`distances_figure`) that the file writers and
:mod:`sdp.viz._report` share.

Lengths are labelled in :data:`UNIT`, metres: sdp's coordinates are world units, metres in its
docs and in every sample scan (``voxel_size``, distances and the alignment's shift are read the
same way); each picture takes ``unit=`` for clouds in other units. Every scale bar and every
axis of coordinates or distances names it.

References
----------
.. [1] M. Okabe, K. Ito, "Color Universal Design (CUD): how to make figures and presentations that
   are friendly to colorblind people", J*FLY, 2008.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from ..change._coverage import CHANGED, NOT_COMPARABLE, UNCHANGED
from ..errors import require
from ..io._output import atomic_path

__all__ = ["render_changes", "render_changes_html", "render_distances", "render_field", "changes_figure",
           "distances_figure", "png_bytes", "is_map", "map_origin", "map_axes", "axis_label", "scale_bar", "pyplot",
           "UNIT"]

#: The unit lengths are labelled in (see the module docstring).
UNIT = "m"

_VERMILLION, _BLUE, _GREY = "#D55E00", "#0072B2", "#B4B4B4"  # Okabe–Ito, and a neutral grey

_VIEWS = ((25, -60, "oblique"), (90, -90, "top"), (0, -90, "front"))
# drawn in this order (later on top): state value, name, colour, marker size (PNG, HTML)
_LAYERS = ((UNCHANGED, "unchanged", _BLUE, 0.6, 1), (NOT_COMPARABLE, "not comparable", _GREY, 0.8, 1),
           (CHANGED, "changed", _VERMILLION, 1.5, 2))
_FLAT = 0.25  # height below this share of the horizontal extent: a map
_MAP_REGIONS = 12  # regions outlined on a map, largest first


def render_changes(path: str | os.PathLike, xyz: np.ndarray, changed: np.ndarray, *, title: str = "",
                   max_points: int = 80_000, seed: int = 0, view: str = "auto", regions=(), unit: str = UNIT) -> Path:
    """Write a PNG of ``xyz``: changed points vermillion, unchanged blue, not comparable grey,
    with counts.

    ``changed`` is a boolean mask, or the ``change`` field of :mod:`sdp.change._coverage` (0 unchanged,
    1 changed, 2 not comparable). Unchanged and not comparable points are subsampled to
    ``max_points`` each for drawing; changed points are all drawn, on top. ``view``: ``"map"``
    (top-down, relative coordinates, scale bar, north arrow), ``"3d"`` (three views) or
    ``"auto"`` (a map when the scene's height is below a tenth of its horizontal extent).
    ``regions`` (:class:`sdp.Region`, or their ``to_dict()``): on a map, each is outlined and
    numbered by its label. ``unit``: of the coordinates, on the scale bar and the axes.
    """
    xyz, changed = _checked_changes("png", path, xyz, changed, max_points, seed, view)
    return _save_png(changes_figure(xyz, changed, title=title, max_points=max_points, seed=seed, view=view,
                                    regions=regions, unit=unit), path)


def _checked_changes(kind: str, path, xyz, changed, max_points, seed, view="auto"):
    """(xyz (n, 3) float64, change field (n,)) of a picture's arguments, checked before any
    drawing: the picture's name (``….png``, ``….html``), x, y, z of at least one point (a Cloud
    gives its own), one state per point (bool, or 0, 1, 2), the counts and the view."""
    from .._core import _validate as V
    from ..errors import InvalidOptionError, InvalidPointsError

    V.picture_path(kind, path)
    xyz = np.asarray(getattr(xyz, "xyz", xyz))
    if xyz.ndim != 2 or xyz.shape[1] != 3 or not len(xyz) or xyz.dtype.kind not in "iuf":
        raise InvalidPointsError(f"a picture draws x, y, z of at least one point: (n, 3) real numbers, got "
                                 f"{xyz.dtype} {xyz.shape}")
    state = np.asarray(changed)
    if state.shape != (len(xyz),) or not (state.dtype == bool or (state.dtype.kind in "iu" and
                                                                  np.isin(state, (0, 1, 2)).all())):
        raise InvalidOptionError(f"changed must hold one state per point ({len(xyz):,}: bool, or 0 unchanged, 1 "
                                 f"changed, 2 not comparable), got {state.dtype} {state.shape}")
    V.integer_at_least("max_points", max_points, 1)
    V.integer_at_least("seed", seed, 0)
    if view not in ("auto", "map", "3d"):
        raise InvalidOptionError(f"view must be 'auto', 'map' or '3d', got {view!r}")
    return np.asarray(xyz, np.float64), state


def changes_figure(xyz: np.ndarray, changed: np.ndarray, *, title: str = "", max_points: int = 80_000,
                   seed: int = 0, view: str = "auto", regions=(), size: float = 1.0, bounds=None,
                   unit: str = UNIT):
    """The matplotlib figure :func:`render_changes` saves (``size`` scales it), for other pages
    (:mod:`sdp.viz._report`); ``bounds`` (lo, hi) choose the view and a map's origin (default:
    the points'), so that two maps of one scene share them."""
    plt = pyplot()
    xyz = np.asarray(xyz)
    layers = _drawn(changed, max_points, seed)
    lo, hi = (xyz.min(axis=0), xyz.max(axis=0)) if bounds is None else (np.asarray(b) for b in bounds)
    if is_map(lo, hi, view, z=xyz[:, 2]):
        fig = _map(plt, xyz, layers, lo, hi, regions, size, unit)
    else:
        fig = plt.figure(figsize=(15 * size, 5.4 * size), dpi=110, layout="constrained")
        for i, (elev, azim, name) in enumerate(_VIEWS):
            ax = fig.add_subplot(1, 3, i + 1, projection="3d")
            for idx, label, n, color, size_, _ in layers:
                ax.scatter(*xyz[idx].T, s=size_, c=color, alpha=0.9 if color == _VERMILLION else 0.5, linewidths=0,
                           label=f"{label} ({n:,})")
            ax.view_init(elev=elev, azim=azim)
            ax.set_box_aspect(np.maximum(hi - lo, 1e-9))
            ax.set_title(name)
            ax.set_xlabel(axis_label("x", 0, unit))
            ax.set_ylabel(axis_label("y", 0, unit))
            ax.set_zlabel(axis_label("z", 0, unit))
            if name != "oblique":  # the axis seen end-on carries no information
                (ax.set_zticks if name == "top" else ax.set_yticks)([])
                (ax.set_zlabel if name == "top" else ax.set_ylabel)("")
            if i == 0:
                ax.legend(loc="upper left", markerscale=8, fontsize=9)
    if title:
        fig.suptitle(title)
    return fig


def is_map(lo, hi, view: str = "auto", *, z=None) -> bool:
    """Whether a scene of bounds ``lo``, ``hi`` is drawn as a top-down map: ``view="map"``, or
    ``"auto"`` and its height below a quarter of its horizontal extent (``"3d"``: never): an
    airborne tile with its relief and buildings, not a room, a facade or a forest plot. With the
    points' heights ``z``, the height is that of their 1st to 99th percentile: a bird or a noise
    return 60 m above a district does not make it a scene of three views."""
    if view not in ("auto", "map", "3d"):
        raise ValueError(f"view must be 'auto', 'map' or '3d', got {view!r}")
    low, high = (lo[2], hi[2]) if z is None or not len(z) else np.percentile(z[::max(1, len(z) // 100_000)], [1, 99])
    return view == "map" or (view == "auto" and high - low < _FLAT * max(hi[0] - lo[0], hi[1] - lo[1]))


def _map(plt, xyz, layers, lo, hi, regions=(), size=1.0, unit=UNIT):
    """A top-down map: x, y relative to a round origin named on the axes, a scale bar, a north
    arrow; changed points drawn large enough to be found at a glance, regions outlined."""
    w, h = float(hi[0] - lo[0]), float(hi[1] - lo[1])
    aspect = min(max(h / max(w, 1e-9), 0.3), 3.0)
    fig, ax = plt.subplots(figsize=(9 * size, (9 * aspect * 0.9 + 1.2) * size), dpi=110, layout="constrained")
    origin = map_origin(lo, hi)
    for idx, label, n, color, size_, _ in layers:
        ax.scatter(xyz[idx, 0] - origin[0], xyz[idx, 1] - origin[1], s=size_ * (4 if color == _VERMILLION else 2),
                   c=color, linewidths=0, alpha=0.9 if color == _VERMILLION else 0.5, label=f"{label} ({n:,})")
    for g in list(regions)[:_MAP_REGIONS]:
        g = g if isinstance(g, dict) else g.to_dict()
        (x0, y0), (x1, y1) = (np.asarray(g["bbox_min"][:2]) - origin), (np.asarray(g["bbox_max"][:2]) - origin)
        ax.add_patch(plt.Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, ec="k", lw=0.8))
        ax.annotate(str(g["label"]), (x1, y1), fontsize=8, ha="left", va="bottom")
    ax.legend(loc="best", markerscale=6, fontsize=9, framealpha=0.9)
    map_axes(ax, origin, lo, hi, unit)
    return fig


def map_origin(lo, hi) -> np.ndarray:
    """A round x, y origin at the scene's corner (a multiple of the power of ten below its extent;
    a corner within 1 % of the extent beyond a round value takes that value, so that 499,999.7 gives
    500,000, not 499,000), or (0, 0) for a scene near the origin (within ten extents of it), whose
    own coordinates read well."""
    span = max(float(hi[0] - lo[0]), float(hi[1] - lo[1]), 1e-9)
    if max(abs(float(v)) for v in (*lo[:2], *hi[:2])) <= 10 * span:
        return np.zeros(2)
    step = 10.0 ** math.floor(math.log10(span))
    return np.floor((np.asarray(lo[:2], np.float64) + 0.01 * span) / step) * step


def axis_label(name: str, offset: float, unit: str | None = UNIT) -> str:
    """``"x − 634,000 (m)"``, or ``"x (m)"`` without an offset (no unit: ``unit=None``)."""
    text = f"{name} − {offset:,.0f}" if offset else name
    return f"{text} ({unit})" if unit else text


def scale_bar(ax, span: float, unit: str = UNIT, *, loc: str = "lower right", fontsize=None):
    """A scale bar of a round length (1, 2 or 5 × 10^k, at most a quarter of ``span``), labelled
    with its unit, on axes of equal aspect in data units."""
    from matplotlib.font_manager import FontProperties
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    bar = 10.0 ** math.floor(math.log10(span / 4))
    bar *= 5 if 5 * bar <= span / 4 else (2 if 2 * bar <= span / 4 else 1)
    font = FontProperties(size=fontsize) if fontsize else None
    ax.add_artist(AnchoredSizeBar(ax.transData, bar, f"{bar:g} {unit}", loc, pad=0.4 if fontsize else 0.6,
                                  frameon=True, size_vertical=span / 300, fontproperties=font))
    return bar


def map_axes(ax, origin, lo, hi, unit: str = UNIT):
    """Relative-coordinate labels and a scale bar with their unit, and a north arrow, on a top-down map."""
    from matplotlib.ticker import MaxNLocator

    span = max(float(hi[0] - lo[0]), float(hi[1] - lo[1]), 1e-9)
    ax.set_aspect("equal")
    ax.set_xlabel(axis_label("x", origin[0], unit))
    ax.set_ylabel(axis_label("y", origin[1], unit))
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(MaxNLocator(6))
    scale_bar(ax, span, unit)
    ax.annotate("N", xy=(0.04, 0.95), xytext=(0.04, 0.84), xycoords="axes fraction", ha="center", va="center",
                fontsize=12, fontweight="bold", arrowprops={"arrowstyle": "-|>", "color": "k", "lw": 1.5})


def render_distances(path: str | os.PathLike, xyz: np.ndarray, distance: np.ndarray, significant: np.ndarray,
                     lod: np.ndarray, *, title: str = "", max_points: int = 200_000, seed: int = 0,
                     view: str = "auto", unit: str = UNIT) -> Path:
    """Write a PNG of signed distances (:func:`sdp.distances`): a map (or, for rooms and objects,
    an oblique 3-D view) of the significant distances on a diverging purple–orange scale
    (readable by colour-blind readers), points within the level of detection pale, points
    without a distance grey; beside it, the histogram of the distances with the median level of
    detection marked. Above ``max_points`` points, a random subsample is drawn (the counts are
    of all points). ``unit``: of the coordinates and distances, on the axes and the scale bar."""
    return _save_png(distances_figure(xyz, distance, significant, lod, title=title, max_points=max_points, seed=seed,
                                      view=view, unit=unit), path)


def distances_figure(xyz: np.ndarray, distance: np.ndarray, significant: np.ndarray, lod: np.ndarray, *,
                     title: str = "", max_points: int = 200_000, seed: int = 0, view: str = "auto",
                     unit: str = UNIT):
    """The matplotlib figure :func:`render_distances` saves, for other pages (:mod:`sdp.viz._report`)."""
    from matplotlib.colors import TwoSlopeNorm

    plt = pyplot()
    xyz, distance = np.asarray(xyz), np.asarray(distance, np.float64)
    significant = np.asarray(significant, bool)
    ok = np.isfinite(distance)
    sig = ok & significant
    idx = np.arange(len(xyz))
    if len(idx) > max_points:
        idx = np.sort(np.random.default_rng(seed).choice(len(xyz), max_points, replace=False))
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    flat = is_map(lo, hi, view, z=xyz[:, 2])
    limit = float(np.quantile(np.abs(distance[sig]), 0.98)) if sig.any() else 1.0
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-max(limit, 1e-12), vmax=max(limit, 1e-12))
    fig = plt.figure(figsize=(15, 6.5), dpi=110, layout="constrained")
    ax = fig.add_subplot(1, 2, 1) if flat else fig.add_subplot(1, 2, 1, projection="3d")
    origin = map_origin(lo, hi) if flat else np.zeros(2)
    groups = ((ok[idx] & ~sig[idx], "#D9D9D9", f"within the level of detection ({int((ok & ~sig).sum()):,})"),
              (~ok[idx], _GREY, f"no distance ({int((~ok).sum()):,})"))
    for mask, colour, label in groups:
        p = xyz[idx[mask]]
        coords = (p[:, 0] - origin[0], p[:, 1] - origin[1]) if flat else p.T
        ax.scatter(*coords, s=1.0, c=colour, linewidths=0, alpha=0.6, label=label)
    p = xyz[idx[sig[idx]]]
    coords = (p[:, 0] - origin[0], p[:, 1] - origin[1]) if flat else p.T
    sc = ax.scatter(*coords, s=2.0, c=distance[idx[sig[idx]]], cmap="PuOr_r", norm=norm, linewidths=0,
                    label=f"significant ({int(sig.sum()):,})")
    fig.colorbar(sc, ax=ax, shrink=0.8, label=f"signed distance ({unit}; +: the current lies on the normal's side)")
    ax.legend(loc="upper right", markerscale=6, fontsize=9, framealpha=0.9)  # the north arrow is upper left
    if flat:
        map_axes(ax, origin, lo, hi, unit)
    else:
        ax.view_init(elev=25, azim=-60)
        ax.set_box_aspect(np.maximum(hi - lo, 1e-9))
        ax.set_xlabel(axis_label("x", 0, unit))
        ax.set_ylabel(axis_label("y", 0, unit))
        ax.set_zlabel(axis_label("z", 0, unit))
    hx = fig.add_subplot(1, 2, 2)
    if ok.any():
        span = max(limit, float(np.quantile(np.abs(distance[ok]), 0.98)), 1e-12)
        bins = np.linspace(-span, span, 81)
        hx.hist(np.clip(distance[ok], -span, span), bins=bins, color="#D9D9D9", label="all with a distance")
        hx.hist(np.clip(distance[sig], -span, span), bins=bins, color="#E69F00", label="significant")
        m = float(np.median(np.asarray(lod)[ok]))
        for x in (-m, m):
            hx.axvline(x, color="k", ls="--", lw=1)
        hx.plot([], [], "k--", lw=1, label=f"median level of detection ±{m:.3g} {unit}")
        hx.set_yscale("log")  # the significant tails stay visible beside the peak within the level of detection
        hx.legend(fontsize=9)
    else:  # nothing to count: say so rather than draw empty axes with an empty legend
        hx.text(0.5, 0.5, "no core point has a distance", ha="center", va="center", transform=hx.transAxes)
    hx.set_xlabel(f"signed distance ({unit})")
    hx.set_ylabel("points")
    if title:
        fig.suptitle(title)
    return fig


def render_changes_html(path: str | os.PathLike, xyz: np.ndarray, changed: np.ndarray, *, title: str = "",
                        max_points: int = 200_000, seed: int = 0, unit: str = UNIT) -> Path:
    """Write an interactive 3D view (plotly) that opens in a browser without a server.

    ``changed`` as in :func:`render_changes`. The page embeds plotly.js, so it works offline.
    Unchanged and not comparable points are subsampled to ``max_points`` each; changed points
    are all drawn. ``unit``: of the coordinates, on the axes.

    Raises
    ------
    MissingDependencyError
        plotly is not installed (``pip install 'sdp[plots]'``).
    """
    go = require("plotly.graph_objects", "plots", "an HTML view")
    xyz, changed = _checked_changes("html", path, xyz, changed, max_points, seed)
    fig = go.Figure([go.Scatter3d(x=xyz[i, 0], y=xyz[i, 1], z=xyz[i, 2], mode="markers", name=f"{name} ({n:,})",
                                  marker={"size": size, "color": color})
                     for i, name, n, color, _, size in _drawn(changed, max_points, seed)])
    axes = {f"{a}axis": {"title": {"text": axis_label(a, 0, unit)}} for a in "xyz"}
    fig.update_layout(title=title, scene={"aspectmode": "data", **axes}, legend={"itemsizing": "constant"})
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.write_html(tmp, include_plotlyjs=True)
    return path


def render_field(path: str | os.PathLike, field, *, center: np.ndarray | None = None,
                 max_pixels: int = 500, unit: str = UNIT) -> Path:
    """Write a PNG of three axis-aligned slices of F = h − G through ``center``.

    Each slice is sampled at the node spacing (coarser if a side would exceed ``max_pixels``)
    by the field's own trilinear query; blue is inside the cluster volume (F < 0), red outside,
    and the black line is the boundary F = 0. ``center`` defaults to the middle of the
    allocated blocks. ``unit``: of the coordinates, on the axes.
    """
    from .._core._validate import picture_path

    picture_path("png", path)  # a PNG under another name opens as nothing
    plt = pyplot()
    from matplotlib.colors import TwoSlopeNorm

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
        ax.set_title(f"{names[normal]} = {center[normal]:.4g} {unit}")
        ax.set_xlabel(axis_label(names[u], 0, unit))
        ax.set_ylabel(axis_label(names[v], 0, unit))
        ax.set_aspect("equal")
    fig.colorbar(im, ax=panels, shrink=0.8, label="F = h − G  (< 0: inside the cluster volume)")
    fig.suptitle(f"density field: voxel {l:.4g} {unit}, σ {field.sigma:.4g} {unit}, h {field.h:.3f}")
    return _save_png(fig, path)


def pyplot():
    """matplotlib.pyplot on the Agg backend, or :class:`sdp.MissingDependencyError` (``sdp[plots]``)."""
    matplotlib = require("matplotlib", "plots", "a PNG")

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _drawn(changed: np.ndarray, max_points: int, seed: int) -> list[tuple]:
    """The layers to draw, as (indices, name, count, colour, PNG size, HTML size): every changed
    point, at most ``max_points`` of the others per state; states without points are left out."""
    state = np.asarray(changed)
    state = state.astype(np.uint8) if state.dtype == bool else state
    rng = np.random.default_rng(seed)
    layers = []
    for value, name, color, png, html in _LAYERS:
        idx = np.flatnonzero(state == value)
        if value != CHANGED and len(idx) > max_points:
            idx = rng.choice(idx, max_points, replace=False)
        if len(idx) or value != NOT_COMPARABLE:
            layers.append((idx, name, int((state == value).sum()), color, png, html))
    return layers


def _save_png(fig, path) -> Path:
    import matplotlib.pyplot as plt

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path


def png_bytes(fig, *, dpi: float | None = None) -> bytes:
    """The PNG of a matplotlib figure, as bytes (the figure is closed)."""
    import io

    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi or fig.dpi)
    plt.close(fig)
    return buf.getvalue()
