"""One self-contained HTML page per comparison: what was compared, how, what changed, and where.

:func:`change_report` (``sdp change --report``) and :func:`distance_report` (``sdp distance
--report``) write a single file that opens in any browser without a server or a network: the
pictures are PNGs in ``data:`` URIs and plotly.js is inline. A page holds

- the summary: the inputs, the parameters with the reason each was chosen (a default's reason
  is the one :class:`sdp.Defaults` documents), the counts and the timings, and the JSON summary;
- the map of the changes (a top-down map for scenes much wider than tall, else three 3-D
  views: :func:`sdp.viz._render.changes_figure`) or of the distances (:func:`sdp.viz._render.distances_figure`);
- a histogram: of the change regions' sizes, or of the signed distances with the level of
  detection;
- the region table, with a thumbnail of each of the largest regions;
- an interactive 3-D view (plotly), decimated above a point budget by a stated factor so that
  it stays responsive for inputs of tens of millions of points.

Colours are the Okabe–Ito palette [1] (appeared vermillion, disappeared reddish purple, unchanged
blue, not comparable a neutral grey). Both extras of ``sdp[plots]`` are needed (matplotlib for the
pictures, plotly for the 3-D view); :func:`require_extras` checks them before any work.

The 3-D view draws at most :data:`POINT_BUDGET` points: the changed points get up to half, the
rest a random 1 in f, and the page states f. Its WebGL markers are squares, two triangles each:
a circle costs many, which made 200k points take 2.4× as long in software rendering. The page
is built in memory and written through :func:`sdp.io.atomic_path` with the command's other
outputs (:func:`sdp.io.all_or_none`); the tiled path refuses ``--report`` before any work (the
page needs every point in memory). ``tests/test_htmlreport.py`` opens reports in headless
Chromium (``tests/browser.py``: Selenium and Debian's chromedriver, SwiftShader for WebGL) and
checks that there is no console error, that the 3-D view drew and that the screenshot is not
one flat colour; ``make browser`` installs Chromium, and without it those tests skip.

References
----------
.. [1] M. Okabe, K. Ito, "Color Universal Design (CUD): how to make figures and presentations that
   are friendly to colorblind people", J*FLY, 2008.
.. [2] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
   terrestrial laser scanner", ISPRS J. Photogramm. 82 (2013) (the level of detection).
"""

from __future__ import annotations

import base64
import html
import inspect
import math
import os
import re
import time
from pathlib import Path

import numpy as np

from .._core._json import dumps
from ..change._coverage import CHANGED, NOT_COMPARABLE, UNCHANGED
from ..defaults import DEFAULTS, Defaults
from ..errors import require
from ..io._output import atomic_path
from ._render import UNIT

__all__ = ["change_report", "distance_report", "series_report", "require_extras", "decimation", "POINT_BUDGET", "THUMBNAILS"]

#: Points drawn in the interactive 3-D view at most: above it, points are drawn 1 in ``factor``.
POINT_BUDGET = 100_000
#: Regions of each direction with a thumbnail (the largest).
THUMBNAILS = 12
_TABLE_ROWS = 200  # region table rows per direction (the largest); the count of all is stated
_VERMILLION, _PURPLE, _BLUE, _GREY = "#D55E00", "#CC79A7", "#0072B2", "#B4B4B4"  # Okabe–Ito, a neutral grey
_RENDERED = "document.documentElement.dataset.sdpRendered = 'yes';"  # set once plotly has drawn (tests wait for it)


def require_extras() -> None:
    """Raise :class:`sdp.MissingDependencyError` (one line) unless matplotlib and plotly are installed."""
    require("matplotlib", "plots", "--report (an HTML report)")
    require("plotly", "plots", "--report (an HTML report)")


def decimation(n: int, budget: int) -> int:
    """The factor f ≥ 1 such that drawing 1 point in f keeps ``n`` points within ``budget``."""
    return max(1, math.ceil(n / max(budget, 1)))


# --- sdp change ------------------------------------------------------------------------------------

def change_report(path: str | os.PathLike, result, reference: np.ndarray, current: np.ndarray, *,
                  summary: dict | None = None, names: tuple[str, str] = ("reference", "current"),
                  options: dict | None = None, max_points: int = POINT_BUDGET, thumbnails: int = THUMBNAILS,
                  seed: int = 0, timings: dict | None = None) -> Path:
    """Write the HTML report of a change detection (``sdp change --report``).

    Parameters
    ----------
    path : path-like
        The page to write (atomically: under a temporary name, renamed at the end).
    result : ChangeResult
        Of :func:`sdp.detect_changes` (or any object with its ``current_state``,
        ``reference_state``, ``appeared_labels``, ``disappeared_labels``, ``appeared_regions``,
        ``disappeared_regions`` and ``summary()``).
    reference, current : ndarray (n, 3)
        The points the masks describe, in one frame (with an alignment: the moved current).
    summary : dict, optional
        The summary to show (default ``result.summary()``; :func:`sdp.compare_files` passes its
        own, with the reading time, the alignment and the outputs).
    names : (str, str)
        How the two clouds are called (their file names).
    options : dict, optional
        The options as given (``voxel_size``, ``sigma_voxels``, ``k``, ``decision``, …): a value
        equal to :data:`sdp.DEFAULTS` is shown with the reason it is the default.
    max_points : int
        Point budget of the interactive view (the changed points get up to half of it).
    thumbnails : int
        Regions per direction with a thumbnail, largest first.
    seed : int
        Of the random decimation.
    timings : dict, optional
        Where the report's own time goes, as ``"report"`` (seconds, to 0.1 ms: drawing and assembling
        the page; its writing, after, is not in it), before the page's JSON is made: ``sdp change``
        passes its summary's timings, so the page's table, its JSON and ``--json`` give one number.

    Returns
    -------
    Path

    Raises
    ------
    MissingDependencyError
        matplotlib or plotly is not installed (``pip install 'sdp[plots]'``).
    InvalidOptionError
        ``path`` is not named ``….html`` (or ``….htm``).
    InvalidPointsError
        ``reference`` or ``current`` is not (n, 3), or not as long as the result's states of it.

    Examples
    --------
    >>> r = sdp.detect_changes(ref, cur)  # doctest: +SKIP
    >>> sdp.change_report("report.html", r, ref, cur, names=("2015.laz", "2023.laz"))  # doctest: +SKIP
    """
    require_extras()
    from ._render import changes_figure, is_map, png_bytes

    t0 = time.perf_counter()
    _check_page(path)
    reference, current = (_checked_points(name, xyz, len(getattr(result, state)), f"result.{state}")
                          for name, xyz, state in (("reference", reference, "reference_state"),
                                                   ("current", current, "current_state")))
    s = summary if summary is not None else result.summary()
    clouds = [c for c in (reference, current) if len(c)]
    lo = np.min([c.min(axis=0) for c in clouds], axis=0)
    hi = np.max([c.max(axis=0) for c in clouds], axis=0)
    flat = is_map(lo, hi, z=np.concatenate([c[::max(1, len(c) // 50_000), 2] for c in clouds]))
    directions = (("appeared", names[1], current, result.current_state, result.appeared_labels,
                   s["appeared_regions"], _VERMILLION),
                  ("disappeared", names[0], reference, result.reference_state, result.disappeared_labels,
                   s["disappeared_regions"], _PURPLE))
    maps, tables = [], []
    for kind, name, xyz, state, labels, regions, _ in directions:
        if not len(xyz):
            continue
        fig = changes_figure(xyz, state, title=f"{kind} in {name} ({int((state == CHANGED).sum()):,} points, "
                             f"{len(regions):,} regions)", regions=regions, seed=seed, bounds=(lo, hi),
                             view="map" if flat else "3d")
        maps.append(_img(png_bytes(fig), f"{kind} points of {name}"))
        thumbs = [_thumbnail(xyz, state, labels, g, flat, png_bytes) for g in regions[:thumbnails]]
        tables.append(_region_table(kind, name, regions, thumbs))
    hist = _img(png_bytes(_region_histogram(s)), "histogram of the change regions' sizes")
    view, note = _change_view(directions, lo, hi, max_points, seed)
    title = f"sdp change: {names[0]} → {names[1]}"
    seconds = _report_seconds(t0, timings)
    from ..cli import _text as report

    body = [f"<h1>{_e(title)}</h1>",
            _section("Summary", _change_summary(s, names) + _parameters(s, options, "change")
                     + _timings(s, seconds)
                     + _details("The summary as printed", f"<pre>{_e(report.change_text(s, *names))}</pre>")
                     + _json_details("change", s)),
            _section("Where it changed" if flat else "Views", "".join(maps)
                     + ("<p>A top-down map: x, y relative to the round origin named on the axes, in metres "
                        "(the scale bar's unit), north up (+y); the largest regions outlined and numbered.</p>"
                        if flat else
                        "<p>Three views of each cloud (oblique, top, front).</p>")),
            _section("Region sizes", hist),
            _section("Regions", "".join(tables) or "<p>No change region.</p>"),
            _section("Interactive 3-D view", f"<p>{_e(note)}</p>{view}")]
    return _write(path, title, body)


def _change_summary(s: dict, names) -> str:
    rows = []
    level = all("level" in s[role] for role in ("reference", "current"))  # decision="combined"
    for role, name, kind in (("reference", names[0], "disappeared"), ("current", names[1], "appeared")):
        c = s[role]
        rows.append((role, name, f"{c['points']:,}", f"{c['dropped']:,}", f"{c[kind]:,} {kind}",
                     f"{c['not_comparable']:,}", f"{len(s[f'{kind}_regions']):,}")
                    + ((f"1.96·σ_s = {1.96 * c['level']['systematic']:.3g} {UNIT}, "
                        f"p = {c['level']['range_exponent']:.2f}",) if level else ()))
    head = ("epoch", "file", "points", "dropped (NaN)", "changed", "not comparable", "regions")
    # the distance's level of detection against the other epoch: its systematic part at the median
    # range, and how it grows with range, r^p (sdp.distance._noise)
    return _table(head + (("level of detection: systematic part, range exponent",) if level else ()), rows)


def _region_table(kind: str, name: str, regions: list, thumbs: list[str]) -> str:
    rows = []
    for i, g in enumerate(regions[:_TABLE_ROWS]):
        size = " × ".join(f"{hi - lo:.3g}" for lo, hi in zip(g["bbox_min"], g["bbox_max"], strict=True))
        rows.append((str(g["label"]), f"{g['n_points']:,}", ", ".join(f"{v:.3f}" for v in g["centroid"]), size,
                     f"{g['volume']:.4g}", thumbs[i] if i < len(thumbs) else ""))
    more = (f" (the largest {_TABLE_ROWS} of {len(regions):,})" if len(regions) > _TABLE_ROWS else "")
    head = f"<h3>{_e(kind)} in {_e(name)}: {len(regions):,} regions{more}</h3>"
    if not regions:
        return head + "<p>None.</p>"
    return head + _table(("#", "points", f"centroid (x, y, z; {UNIT})", f"size (x × y × z; {UNIT})",
                          f"volume ({UNIT}³)", "thumbnail"), rows, raw_last=True)


def _thumbnail(xyz, state, labels, g: dict, flat: bool, png_bytes) -> str:
    """A small picture around one region: its points vermillion, the rest by state; seen from
    above (a map), with a scale bar."""
    from ._render import pyplot, scale_bar

    plt = pyplot()
    lo, hi = np.asarray(g["bbox_min"], float), np.asarray(g["bbox_max"], float)
    half = np.maximum((hi - lo) * 0.75, 0.02 * max(float((hi - lo).max()), 1e-9) + 1e-9)
    mid = (lo + hi) / 2
    if flat:  # a square window, every height
        r = float(half[:2].max())
        a, b = mid - r, mid + r
        a[2], b[2] = -np.inf, np.inf
    else:
        a, b = mid - half, mid + half
    near = np.flatnonzero(np.all((xyz >= a) & (xyz <= b), axis=1))
    rng = np.random.default_rng(0)
    if len(near) > 20_000:
        near = np.sort(rng.choice(near, 20_000, replace=False))
    mine = labels[near] == g["label"]
    fig = plt.figure(figsize=(2.2, 2.2), dpi=80)
    ax = fig.add_axes((0, 0, 1, 1)) if flat else fig.add_axes((0, 0, 1, 1), projection="3d")
    small = 1.5 if len(near) > 3000 else 4.0
    for keep, colour, size, alpha in ((~mine & (state[near] == UNCHANGED), _BLUE, small, 0.35),
                                      (~mine & (state[near] == NOT_COMPARABLE), _GREY, small, 0.35),
                                      (~mine & (state[near] == CHANGED), "#E8A07A", small * 1.5, 0.6),
                                      (mine, _VERMILLION, 3 * small if mine.sum() < 2000 else small * 1.5, 1.0)):
        p = xyz[near[keep]]
        ax.scatter(*(p[:, :2].T if flat else p.T), s=size, c=colour, alpha=alpha, linewidths=0)
    if flat:
        ax.set_xlim(a[0], b[0])
        ax.set_ylim(a[1], b[1])
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        scale_bar(ax, float(b[0] - a[0]), UNIT, fontsize=7)
    else:
        ax.view_init(elev=25, azim=-60)
        ax.set_box_aspect(np.maximum(b - a, 1e-9))
        ax.set_axis_off()
    return _img(png_bytes(fig), f"region {g['label']}", css="thumb")


def _region_histogram(s: dict):
    from ._render import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 3.6), dpi=100, layout="constrained")
    sizes = {k: np.array([g["n_points"] for g in s[f"{k}_regions"]]) for k in ("appeared", "disappeared")}
    every = np.concatenate(list(sizes.values()))
    if every.size:
        top = max(float(every.max()), float(every.min()) * 1.01 + 1)
        bins = np.geomspace(max(float(every.min()), 1.0), top, 30)
        for (kind, v), colour in zip(sizes.items(), (_VERMILLION, _PURPLE), strict=True):
            if v.size:
                ax.hist(v, bins=bins, histtype="step", lw=2, color=colour, label=f"{kind} ({v.size:,} regions)")
        ax.set_xscale("log")
        ax.legend()
    else:
        ax.text(0.5, 0.5, "no change region", ha="center", va="center", transform=ax.transAxes)
    from matplotlib.ticker import MaxNLocator

    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("points per region")
    ax.set_ylabel("regions")
    return fig


def _change_view(directions, lo, hi, budget: int, seed: int) -> tuple[str, str]:
    """The plotly 3-D view of the current cloud by state and the disappeared reference points,
    decimated within ``budget``; and the sentence that says how."""
    from ._render import map_origin

    rng = np.random.default_rng(seed)
    (_, cur_name, cur, cur_state, *_), (_, ref_name, ref, ref_state, *_) = directions
    changed = [("appeared", np.flatnonzero(cur_state == CHANGED), cur, _VERMILLION, 2.5),
               ("disappeared", np.flatnonzero(ref_state == CHANGED), ref, _PURPLE, 2.5)]
    context = [("unchanged", np.flatnonzero(cur_state == UNCHANGED), cur, _BLUE, 1.2),
               ("not comparable", np.flatnonzero(cur_state == NOT_COMPARABLE), cur, _GREY, 1.2)]
    n_changed = sum(len(i) for _, i, *_ in changed)
    n_context = sum(len(i) for _, i, *_ in context)
    f_changed = decimation(n_changed, budget // 2 if n_context else budget)
    f_context = decimation(n_context, budget - math.ceil(n_changed / f_changed))
    origin = map_origin(lo, hi)
    traces = []
    for group, f in ((context, f_context), (changed, f_changed)):
        for name, idx, xyz, colour, size in group:
            n = len(idx)
            if f > 1:
                idx = idx[rng.random(n) < 1.0 / f]
            drawn = f", 1 in {f} drawn" if f > 1 else ""
            traces.append((f"{name} ({n:,}{drawn})", xyz[idx], colour, size))
    drawn = sum(len(p) for _, p, _, _ in traces)
    total = n_changed + n_context
    note = (f"{drawn:,} of {total:,} points drawn (budget {budget:,}): "
            + (f"the changed points 1 in {f_changed}, " if f_changed > 1 else "every changed point, ")
            + (f"the others 1 in {f_context} (a random sample)." if f_context > 1 else "every other point.")
            + f" Current points of {cur_name} by state, with the disappeared points of {ref_name}; "
            + _relative(origin) + " Drag to turn, scroll to zoom, click the "
            "legend to hide a layer.")
    return _plotly(traces, origin), note


# --- sdp distance ----------------------------------------------------------------------------------

def distance_report(path: str | os.PathLike, result, *, summary: dict | None = None,
                    names: tuple[str, str] = ("reference", "current"), options: dict | None = None,
                    max_points: int = POINT_BUDGET, seed: int = 0, timings: dict | None = None) -> Path:
    """Write the HTML report of signed distances (``sdp distance --report``).

    Parameters
    ----------
    path : path-like
        The page to write (atomically).
    result : Distances
        Of :func:`sdp.distances` (``core_points``, ``distance``, ``lod``, ``significant``,
        ``summary()``).
    summary, names, options, max_points, seed, timings
        As in :func:`change_report` (``options``: ``projection_scale``, ``normal_scale``,
        ``max_distance``, ``registration_error``, …).

    Returns
    -------
    Path

    Raises
    ------
    MissingDependencyError
        matplotlib or plotly is not installed (``pip install 'sdp[plots]'``).
    InvalidOptionError
        ``path`` is not named ``….html`` (or ``….htm``).

    References
    ----------
    .. [1] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
       terrestrial laser scanner", ISPRS J. Photogramm. 82 (2013).
    """
    require_extras()
    from ._render import distances_figure, is_map, map_origin, png_bytes

    t0 = time.perf_counter()
    _check_page(path)
    s = summary if summary is not None else result.summary()
    xyz = np.asarray(result.core_points, np.float64)
    d = np.asarray(result.distance, np.float64)
    sig, lod = np.asarray(result.significant, bool), np.asarray(result.lod, np.float64)
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    flat = is_map(lo, hi, z=xyz[:, 2])
    title = f"sdp distance: {names[0]} → {names[1]}"
    picture = _img(png_bytes(distances_figure(xyz, d, sig, lod, title="signed distance at the core points of "
                                              f"{names[0]}", seed=seed)), "map of the signed distances")
    ok = np.isfinite(d)
    idx = np.arange(len(xyz))
    f = decimation(len(idx), max_points)
    rng = np.random.default_rng(seed)
    if f > 1:
        idx = idx[rng.random(len(idx)) < 1.0 / f]
    origin = map_origin(lo, hi)
    limit = float(np.quantile(np.abs(d[ok & sig]), 0.98)) if (ok & sig).any() else 1.0
    groups = ((ok[idx] & ~sig[idx], "within the level of detection", "#D9D9D9"),
              (~ok[idx], "no distance (not comparable)", _GREY))
    traces = [(f"{name} ({int(m.sum()):,} drawn)", xyz[idx[m]], colour, 1.2) for m, name, colour in groups]
    s_idx = idx[sig[idx] & ok[idx]]
    traces.append((f"significant ({len(s_idx):,} drawn)", xyz[s_idx], d[s_idx], 2.0))
    note = (f"{len(idx):,} of {len(xyz):,} core points drawn (budget {max_points:,})"
            + (f": 1 in {f}, a random sample." if f > 1 else ".")
            + f" Significant distances coloured from −{limit:.3g} (purple) to +{limit:.3g} (orange)."
            + _relative(origin))
    view = _plotly(traces, origin, limit=limit)
    seconds = _report_seconds(t0, timings)
    from ..cli import _text as report

    body = [f"<h1>{_e(title)}</h1>",
            _section("Summary", _distance_summary(s, names) + _parameters(s, options, "distance")
                     + _timings(s, seconds)
                     + _details("The summary as printed", f"<pre>{_e(report.distance_text(s, *names))}</pre>")
                     + _json_details("distance", s)),
            _section("Distances: map and histogram" if flat else "Distances: view and histogram", picture
                     + "<p>Left: the significant distances (|distance| above the level of detection at 95 %), "
                     "points within it pale, points without a distance grey. Right: the histogram of the signed "
                     "distances, the median level of detection dashed.</p>"),
            _section("Interactive 3-D view", f"<p>{_e(note)}</p>{view}")]
    return _write(path, title, body)


def _distance_summary(s: dict, names) -> str:
    n = max(s["core_points"], 1)
    rows = [("reference", names[0]), ("current", names[1]),
            ("core points", f"{s['core_points']:,}"),
            ("with a distance", f"{s['comparable']:,} ({s['comparable'] / n:.1%})"),
            ("not comparable (an epoch has no points near)", f"{s['not_comparable']:,}"),
            ("significant", f"{s['significant']:,} ({s['significant_positive']:,} +, {s['significant_negative']:,} −)"),
            ("median distance (5–95 %)", f"{s['median_distance']:.4g} ({s['distance_p05']:.4g} … "
                                          f"{s['distance_p95']:.4g})"),
            ("median level of detection (95 %)", f"{s['median_lod']:.4g}")]
    return _table(("", ""), rows)


# --- the parts of a page ---------------------------------------------------------------------------

def _check_page(path) -> None:
    """Refuse, before any drawing, a page not named ``….html``: as ``--report`` does."""
    from .._core._validate import picture_path

    picture_path("report", path)


def _checked_points(name: str, xyz, n: int, described: str) -> np.ndarray:
    """``xyz`` as (n, 3) float64, or one line naming the mismatch: points that are not the ones
    the result describes would be drawn with another point's state (or fail deep in matplotlib)."""
    from ..errors import InvalidPointsError

    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1:] != (3,) or xyz.dtype.kind not in "iuf":
        raise InvalidPointsError(f"{name}: x, y, z of the points as (n, 3) real numbers, got {xyz.dtype} {xyz.shape}")
    if len(xyz) != n:
        raise InvalidPointsError(f"{name}: {len(xyz):,} points, but {described} describes {n:,}: give the points "
                                 "the result was computed from (with an alignment, the moved ones)")
    return xyz.astype(np.float64, copy=False)


def _reasons() -> dict[str, str]:
    """Each default's reason, as :class:`sdp.Defaults` documents it (the one place it is written)."""
    doc = inspect.cleandoc(Defaults.__doc__ or "").splitlines()
    reasons, name = {}, None
    for line in doc:
        head = line.split(" : ")
        if len(head) == 2 and head[0].isidentifier() and not line.startswith(" "):
            name = head[0]
            reasons[name] = ""
        elif name and line.startswith(" "):
            reasons[name] = (reasons[name] + " " + line.strip()).strip()
    return {k: re.sub(r":\w+:`~?([^`]+)`", r"\1", v).replace("``", "") for k, v in reasons.items()}  # plain text


def _parameters(s: dict, options: dict | None, kind: str) -> str:
    """The parameters used, each with why: the default and its reason, or given."""
    options = dict(options or {})
    reasons = _reasons()

    def why(name):
        if name not in options:
            return "as passed"
        given = options[name]
        if name in reasons and given == getattr(DEFAULTS, name):
            return "default: " + reasons[name]
        return "given" if given is not None else "default"

    if kind == "change":
        grid = options.get("grid_size")
        rows = [("voxel size", f"{s['voxel_size']:.4g}",
                 f"--grid-size {grid}: the paper's level of detail (longest side / {grid})" if grid else
                 (why("voxel_size") if options.get("voxel_size") == "auto" or "voxel_size" not in options
                  else f"given ({options['voxel_size']})")),
                ("σ (kernel)", f"{s['sigma']:.4g} ({s['sigma'] / s['voxel_size']:.3g} voxels)", why("sigma_voxels")),
                ("threshold h", f"{s['h']:.4f}", "given (--h)" if options.get("h") else why("k")),
                ("decision", s["decision"], why("decision"))]
        if "min_region_points" in options:  # not in the summary: known when the options are
            rows.append(("min region points", str(options["min_region_points"]), why("min_region_points")))
        rows.append(("coverage", _coverage(s), why("sensor_origin")))
        if "range_noise" in options and any(v == "sensor rays" for v in s["coverage"].values()):
            rows.append(("range noise", f"{options['range_noise']:g}", why("range_noise")))
    else:
        rows = [("projection scale d", f"{s['projection_scale']:.4g}", why("projection_scale")),
                ("normal scale D", f"{s['normal_scale']:.4g}", why("normal_scale")),
                ("searched along the normal", f"±{s['max_distance']:.4g}", why("max_distance")),
                ("registration error", f"{s['registration_error']:.4g}",
                 "measured: the smallest that keeps at most 5 % of the stable part beyond the level"
                 if s.get("registration_source") == "measured on the stable part" else
                 s["registration_source"] if s.get("registration_source", "given") != "given"
                 else why("registration_error")),
                ("normals", str(s["orientation"]), "given (--orientation)" if options.get("orientation") is not None
                 else "a surface faces the scanner that saw it: its position from the file or --sensor-origin"
                 if "sensor" in str(s["orientation"]) or "scanner" in str(s["orientation"])
                 else "no sensor known: the default direction, up (+z), as M3C2 orients its normals")]
    if "alignment" in s:
        rows.append(_alignment_row(s["alignment"]))
    return "<h3>Parameters</h3>" + _table(("parameter", "value", "why"), rows)


def _alignment_row(al: dict) -> tuple[str, str, str]:
    """The parameters' row of an alignment: how it was asked for (``--align-class``,
    ``--fix-horizontal``), the motion, the overlap before and after, the residual, and what it
    may have got wrong (:func:`sdp.cli._text.alignment_warnings`), in view rather than only in the
    JSON."""
    from ..cli._text import alignment_warnings, motion_text

    classes, fixed = al.get("align_class"), al.get("fix_horizontal")
    how = al["method"] + (f" on the points of class {', '.join(map(str, classes))} of both scans" if classes else "")
    how += ", x, y and the heading kept (the vertical shift and the tilts estimated)" if fixed else ""
    rmse = al.get("rmse")
    residual = (f"residual {rmse:.4g} m (RMS)" if rmse is not None and np.isfinite(rmse) else
                "no residual (a field holds no points to measure it to)")
    value = (f"{how}: {motion_text(al)}; inside the reference's volume {al['inside_before']:.1%} → "
             f"{al['inside_after']:.1%}; {residual}")
    warning = "; ".join(alignment_warnings(al))
    given = (f"--align {al['method']}" + (f" --align-class {','.join(map(str, classes))}" if classes else "")
             + (" --fix-horizontal" if fixed else ""))
    return "alignment", value + (f". Warning: {warning}." if warning else ""), f"given ({given})"


def _relative(origin) -> str:
    return f" x, y relative to ({origin[0]:,.0f}, {origin[1]:,.0f})." if origin.any() else ""


def _coverage(s: dict) -> str:
    return "; ".join(f"{k}: {v}" for k, v in s.get("coverage", {}).items()) or "off"


def _report_seconds(t0: float, timings: dict | None) -> float:
    """The report's time since ``t0``, to 0.1 ms, put in ``timings["report"]`` when given: the one
    number the page's table, its JSON and ``--json`` give."""
    seconds = round(time.perf_counter() - t0, 4)
    if timings is not None:
        timings["report"] = seconds
    return seconds


def _timings(s: dict, report_seconds: float) -> str:
    rows = [(k, f"{v * 1e3:,.1f} ms") for k, v in s.get("timings", {}).items() if k != "report"]
    rows.append(("this report (pictures, view)", f"{report_seconds * 1e3:,.1f} ms"))
    return "<h3>Timings</h3>" + _table(("step", "time"), rows)


def _json_details(command: str, s: dict) -> str:
    """The summary as ``sdp COMMAND --json`` prints it, and what of it the page could not know."""
    has_time = "report" in s.get("timings", {})
    note = ("<p>What --json prints: its timings' report is the time to draw and assemble this page (writing the "
            "file, after, is in no timing).</p>" if has_time else
            "<p>The report's own time is not in it (it is in the Timings table above).</p>")
    return _details(f"The summary as JSON (sdp {command} --json)", f"<pre>{_e(_json(s))}</pre>{note}")


def _plotly(traces, origin, *, limit: float | None = None) -> str:
    """A plotly 3-D scatter of ``traces`` (name, xyz, colour or values, size) as a ``<div>`` with
    plotly.js inline; coordinates float32 relative to ``origin`` (x, y), so none is lost to the
    offset and the page stays small."""
    import plotly.graph_objects as go
    import plotly.io as pio

    from ._render import axis_label

    data = []
    for name, xyz, colour, size in traces:
        p = np.asarray(xyz, np.float64)
        rel = np.column_stack([p[:, 0] - origin[0], p[:, 1] - origin[1], p[:, 2]]).astype(np.float32)
        marker = {"size": size, "symbol": "square"}  # WebGL draws a square in 2 triangles, a circle in many
        if isinstance(colour, str):
            marker["color"] = colour
        else:
            marker.update(color=np.asarray(colour, np.float32), colorscale="PuOr", reversescale=True, cmid=0.0,
                          cmin=-limit, cmax=limit, colorbar={"title": {"text": f"distance ({UNIT})"}})
        data.append(go.Scatter3d(x=rel[:, 0], y=rel[:, 1], z=rel[:, 2], mode="markers", name=name, marker=marker,
                                 hoverinfo="x+y+z+name"))
    fig = go.Figure(data)
    axes = {f"{a}axis": {"title": {"text": axis_label(a, o)}} for a, o in zip("xyz", (*origin, 0), strict=True)}
    fig.update_layout(scene={"aspectmode": "data", **axes},
                      legend={"itemsizing": "constant"}, height=700, margin={"l": 0, "r": 0, "t": 30, "b": 0})
    return pio.to_html(fig, include_plotlyjs=True, full_html=False, post_script=_RENDERED,
                       config={"displaylogo": False})


def _img(png: bytes, alt: str, *, css: str = "figure") -> str:
    return f'<img class="{css}" alt="{_e(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'


def _table(header, rows, *, raw_last: bool = False) -> str:
    head = "".join(f"<th>{_e(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c if raw_last and i == len(r) - 1 else _e(str(c))}</td>"
                                    for i, c in enumerate(r)) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _section(title: str, content: str) -> str:
    return f'<section><h2>{_e(title)}</h2>{content}</section>'


def _details(title: str, content: str) -> str:
    return f"<details><summary>{_e(title)}</summary>{content}</details>"


def _json(s: dict) -> str:
    return dumps(s)


def _e(text: str) -> str:
    return html.escape(str(text), quote=True)


_CSS = """body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1200px;
padding:1em 2em;color:#222;background:#fff}h1{font-size:1.5em}h2{border-bottom:1px solid #ccc;padding-bottom:.2em}
table{border-collapse:collapse;margin:.5em 0 1em}td,th{border:1px solid #ddd;padding:.25em .6em;text-align:left;
vertical-align:middle}th{background:#f3f3f3}img.figure{max-width:100%;height:auto;display:block;margin:.5em 0}
img.thumb{width:176px;height:176px}pre{background:#f7f7f7;padding:.6em;overflow-x:auto;font-size:.85em}
footer{color:#777;font-size:.85em;margin-top:2em}"""


def _write(path, title: str, body: list[str]) -> Path:
    from .. import __version__

    page = (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{_e(title)}</title>'
            f'<meta name="viewport" content="width=device-width, initial-scale=1"><style>{_CSS}</style></head>'
            f'<body>{"".join(body)}<footer>Written by sdp {_e(__version__)} on '
            f'{time.strftime("%Y-%m-%d %H:%M:%S %Z")}; one self-contained file: every picture and script is '
            "inside it.</footer></body></html>\n")
    path = Path(path)
    with atomic_path(path) as tmp:
        Path(tmp).write_text(page, encoding="utf-8")
    return path


# --- sdp series --------------------------------------------------------------------------------------

def series_report(path: str | os.PathLike, ds, *, summary: dict | None = None, points=None, seed: int = 0,
                  max_points: int = 200_000) -> Path:
    """Write the HTML report of a series archive (``sdp series --report``).

    Maps of the total (smoothed) change at the last epoch and of its velocity, the series of the
    five largest objects of change (their mean smoothed change, the raw distances of their peak
    core point) and of chosen core points, the object table, and each parameter with its reason.

    Parameters
    ----------
    path : path-like
        The page to write (atomically).
    ds : xarray.Dataset
        A series archive (:func:`sdp.open_series`).
    summary : dict, optional
        :func:`sdp.cli.describe_series` of it.
    points : list of int, optional
        Core points whose series are drawn too.
    seed, max_points
        The maps draw at most ``max_points`` core points (a random sample of them beyond).

    Returns
    -------
    Path

    References
    ----------
    .. [1] L. Winiwarter et al., "Full four-dimensional change analysis of topographic point cloud
       time series using Kalman filtering", Earth Surf. Dynam. 11 (2023) 593–613.
    """
    require_extras()
    from ._render import png_bytes, pyplot

    _check_page(path)
    plt = pyplot()
    t0 = time.perf_counter()
    attrs = ds.attrs
    E, m = ds.sizes["epoch"], ds.sizes["point"]
    xyz = np.c_[ds.x.values, ds.y.values, ds.z.values]
    last = ds.isel(epoch=E - 1)
    total = np.asarray(last.smoothed.values, np.float64)
    vel = np.asarray(last.velocity.values, np.float64)
    sig = np.abs(total) > 1.96 * np.asarray(last.smoothed_sigma.values, np.float64)
    idx = np.arange(m)
    f = decimation(m, max_points)
    if f > 1:
        idx = idx[np.random.default_rng(seed).random(m) < 1.0 / f]
    size = float(np.clip(40_000.0 / max(len(idx), 1), 1.5, 25.0))  # sparse core points stay visible
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5))
    for ax, values, what in ((axes[0], total, "smoothed change at the last epoch"),
                             (axes[1], vel, f"velocity ({attrs['parameters']['smoother']['velocity']})")):
        ok = np.isfinite(values[idx])
        lim = float(np.nanquantile(np.abs(values[idx][ok]), 0.98)) if ok.any() else 1.0
        pale = idx[ok & ~sig[idx]]
        ax.scatter(xyz[pale, 0], xyz[pale, 1], s=size, c="#D9D9D9", linewidths=0)
        strong = idx[ok & sig[idx]]
        sc = ax.scatter(xyz[strong, 0], xyz[strong, 1], s=1.5 * size, c=values[strong], cmap="PuOr_r", vmin=-lim, vmax=lim,
                        linewidths=0)
        fig.colorbar(sc, ax=ax, shrink=0.8)
        ax.set_aspect("equal")
        ax.set_title(what + " (significant change coloured)", fontsize=10)
        ax.set_xlabel("x")
        ax.set_ylabel("y")
    maps = _img(png_bytes(fig), "maps of the total change and the velocity")
    times = np.asarray(ds.time.values)
    from ..timeseries._archive import objects_by_size

    by_size = objects_by_size(ds)
    ids = ds.object_id.values[by_size[:5]]
    fig, ax = plt.subplots(figsize=(11, 4.5))
    obj = ds.object.values if len(ids) else None
    smoothed = ds.smoothed.values if len(ids) else None
    for oid in ids:
        mask = obj == oid
        mean = np.array([np.nanmean(smoothed[k][mask[k]]) if mask[k].any() else np.nan for k in range(E)])
        ax.plot(times, mean, lw=2, label=f"object {oid}: mean smoothed change")
    for p in list(points or []):
        ax.plot(times, ds.distance.values[:, p], ".", ms=4, label=f"core point {p}: distance")
        ax.plot(times, ds.smoothed.values[:, p], "-", lw=1, label=f"core point {p}: smoothed")
    ax.axhline(0, color="#999", lw=0.8)
    ax.set_xlabel("time")
    ax.set_ylabel("change along the normal")
    if len(ids) or points:
        ax.legend(fontsize=8, ncol=2)
    series_png = _img(png_bytes(fig), "series of the largest objects and chosen points")
    rows = [(int(i), int(s), int(e), int(n), f"{a:.4g}", f"{pk:+.4g}", f"{v:+.4g}")
            for i, s, e, n, a, pk, v in zip(*(ds[name].values[by_size[:_TABLE_ROWS]] for name in (
                "object_id", "object_start", "object_end", "object_points", "object_area", "object_peak_change",
                "object_mean_velocity")))]
    objects = (f"<p>{ds.sizes['object_id']:,} objects (the {min(len(rows), _TABLE_ROWS)} largest listed).</p>"
               + _table(("object", "start epoch", "end epoch", "core points", "area", "peak change",
                         "mean velocity"), rows))
    p = attrs["parameters"]
    used = p["used"]
    reasons = [("projection scale d", f"{used['projection_scale']:.4g}", "given" if p["given"]["projection_scale"]
                != "auto" else "auto: 4σ of the density kernel from the reference's point spacing"),
               ("normal scale D", f"{used['normal_scale']:.4g}", "given" if p["given"]["normal_scale"] != "auto"
                else "auto: 2d, raised to 20× the roughness (Lague et al.), at most 4d"),
               ("search along the normal", f"{used['max_distance']:.4g}", "12d unless given"),
               ("registration error", str(used["registration_error"]),
                "added to each epoch's level of detection; auto: measured on each epoch's stable part (the "
                "archive's registration_error per epoch)"),
               ("core points", p["core_points"], "where every epoch is measured"),
               ("process noise q", f"{p['smoother']['process_noise']:.3g}", p["smoother"]["process_noise_reason"]),
               ("observation noise", p["smoother"]["observation_noise"],
                "each epoch's own level of detection; the reference's share is one error for every epoch"),
               ("smoothing lag", f"{p['smoother']['lag']} epochs", p["smoother"]["lag_reason"]),
               ("steps", f"k = {p['smoother']['step_k']}", "an innovation beyond k σ confirmed by the next epoch"),
               ("objects", f"radius {p['objects']['neighbour_radius']:.4g}, ≥ {p['min_object_points']} core points",
                p["objects"]["rule"]),
               ("alignment", used.get("align") or "none",
                "given (--align): each epoch moved onto the reference before it was measured (its residual below)"
                if used.get("align") else "none given: each epoch is measured in its file's frame")]
    from ..cli._text import series_text

    s = summary or {}
    body = [f"<h1>{_e('sdp series: ' + str(s.get('path', '')))}</h1>",
            _section("Summary", (f"<pre>{_e(series_text(s))}</pre>" if s else "")
                     + _table(("parameter", "value", "why"), reasons)
                     + _epoch_table(attrs)
                     + f"<p>Report written in {time.perf_counter() - t0:.2f} s.</p>"
                     + _details("The summary as JSON (sdp info ARCHIVE.zarr)", f"<pre>{_e(_json(s))}</pre>")),
            _section("Total change and velocity", maps + "<p>Core points whose smoothed change at the last epoch "
                     "is significant (beyond 1.96 of its smoothed standard deviation) are coloured, the others pale."
                     "</p>"),
            _section("Through time", series_png),
            _section("Objects of change", objects)]
    return _write(path, "sdp series report", body)


def _epoch_table(attrs: dict) -> str:
    """One row per epoch from the archive's records: its time, points, the core points it was
    measured at, the significant share of those, its registration error and, where it was aligned,
    the alignment's rotation and residual (what the collapsed JSON alone held)."""
    from scipy.spatial.transform import Rotation

    from ..timeseries._archive import show_time

    epochs = attrs["epochs"]
    ref = attrs["parameters"]["used"]["reference"]
    rows = []
    for k, e in enumerate(epochs[:_TABLE_ROWS]):
        t = e["time"]
        when = show_time(t, attrs.get("time_kind"))
        share = ("reference" if k == ref else f"{e['significant'] / e['comparable']:.1%}" if e["comparable"]
                 else "not measured")
        al = e.get("alignment")
        if al:
            angle = np.degrees(Rotation.from_matrix(np.asarray(al["matrix"], np.float64)[:3, :3]).magnitude())
            moved = f"rotation {angle:.4f}°, residual {al['rmse']:.4g} m (RMS)"
        else:
            moved = "reference" if k == ref else "not aligned"
        reg = f"{e['registration_error']:.4g}"
        if k != ref and e.get("registration_source", "given") not in ("given", "measured on the stable part"):
            reg += f" ({e['registration_source']})"  # why a measured error is 0
        rows.append((str(k), when, f"{e['points']:,}", f"{e['comparable']:,}", share, reg, moved))
    more = f" (the first {_TABLE_ROWS} of {len(epochs):,})" if len(epochs) > _TABLE_ROWS else ""
    return (f"<h3>Epochs{more}</h3>"
            + _table(("epoch", "time", "points", "core points measured", "significant (of those measured)",
                      "registration error", "alignment"), rows))
