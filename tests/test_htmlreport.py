"""The HTML report (sdp.htmlreport, `--report`): one self-contained page, its checks before any work,
and the page itself in headless Chromium (tests/browser.py; `make browser` installs Chromium)."""

import base64
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_changes_drawn

import sdp

sys.path.insert(0, str(Path(__file__).parent))
import browser  # noqa: E402

IMAGES = re.compile(r'<img class="\w+" alt="[^"]*" src="data:image/png;base64,')
OUTSIDE = re.compile(r"<(?:script|img|link|iframe)\b[^>]*\b(?:src|href)\s*=\s*[\"'](?!data:)", re.I)


def landscape(rng, *, building=True):
    """An airborne-like pair (wider than tall: drawn as a map) at UTM-sized coordinates; the current
    epoch has a 20 m × 15 m roof 8 m up (the ground under it unseen) and a shed of 6 m × 6 m."""
    gx, gy = np.meshgrid(np.arange(0, 100, 1.0), np.arange(0, 60, 1.0))
    xy = np.c_[gx.ravel(), gy.ravel()] + rng.uniform(-0.3, 0.3, (gx.size, 2))
    ref = np.c_[xy, 0.05 * rng.standard_normal(len(xy))]
    cur = ref.copy()
    if building:
        for x0, y0, x1, y1 in ((30, 20, 50, 35), (80, 50, 86, 56)):
            roof = (xy[:, 0] > x0) & (xy[:, 0] < x1) & (xy[:, 1] > y0) & (xy[:, 1] < y1)
            cur[roof, 2] += 8.0
    offset = np.array([634_000.0, 4_831_000.0, 80.0])
    return ref + offset, cur + offset


def drawn_note(page: str):
    """(drawn, total, factor of the others) from the sentence above the 3-D view."""
    m = re.search(r"([\d,]+) of ([\d,]+) (?:core )?points drawn", page)
    f = re.search(r"the others 1 in (\d+)", page)
    return int(m[1].replace(",", "")), int(m[2].replace(",", "")), int(f[1]) if f else 1


@pytest.mark.slow  # the quick tier keeps lighter tests of the same module
def test_change_report_is_one_self_contained_page(tmp_path, rng):
    ref, cur = landscape(rng)
    np.save(tmp_path / "ref.npy", ref)
    np.save(tmp_path / "cur.npy", cur)
    r = sdp.compare_files(tmp_path / "ref.npy", tmp_path / "cur.npy", output=tmp_path / "out.ply",
                          outputs=sdp.Outputs(both=True, report=tmp_path / "report.html"))
    assert str(tmp_path / "report.html") in r.outputs and "report" in r.summary["timings"]
    page = (tmp_path / "report.html").read_text()
    assert not OUTSIDE.findall(page)  # nothing fetched: every picture and script is inside
    assert "<script" in page and "Plotly.newPlot" in page and "sdpRendered" in page
    n_regions = len(r.summary["appeared_regions"]) + len(r.summary["disappeared_regions"])
    assert n_regions >= 2
    # two maps, the histogram and a thumbnail per region
    assert len(IMAGES.findall(page)) == 3 + n_regions
    assert page.count('class="thumb"') == n_regions
    appeared = re.search(r'<img class="figure" alt="appeared points of [^"]*" src="data:image/png;base64,([^"]+)"',
                         page)
    assert_changes_drawn(base64.b64decode(appeared[1]))
    assert re.search(r"relative to \(63\d,\d\d0, 4,83\d,\d\d0\)", page)  # the stated round origin
    assert "634,000 (m)" in page and "z (m)" in page  # the 3-D view's axes name their unit
    for text in ("ref.npy", "cur.npy", "default: ", "Timings", f"{r.summary['current']['appeared']:,} appeared"):
        assert text in page, text
    drawn, total, factor = drawn_note(page)
    assert drawn == total == len(cur) + r.summary["reference"]["disappeared"] and factor == 1  # within the budget


def test_every_scale_bar_and_axis_names_its_unit(rng):
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    from sdp.viz._render import changes_figure, distances_figure

    def texts(fig):
        bars = [a.txt_label.get_text() for ax in fig.axes for a in ax.artists if isinstance(a, AnchoredSizeBar)]
        labels = [t for ax in fig.axes for t in (ax.get_xlabel(), ax.get_ylabel()) if t]
        return bars, labels

    ref, cur = landscape(rng)
    state = (cur[:, 2] - ref[:, 2] > 4).astype(np.uint8)
    bars, labels = texts(changes_figure(cur, state))  # a map
    assert bars == ["20 m"] and labels == ["x − 634,000 (m)", "y − 4,831,000 (m)"], (bars, labels)
    bars, labels = texts(changes_figure(cur, state, unit="mm"))
    assert bars == ["20 mm"] and labels[0].endswith("(mm)")
    room = rng.random((3000, 3)) * [4, 3, 2.5]
    bars, labels = texts(changes_figure(room, room[:, 0] > 3.5))  # three 3-D views: their axes
    assert not bars and labels and all(t.endswith("(m)") for t in labels), labels
    d = cur[:, 2] - ref[:, 2]
    bars, labels = texts(distances_figure(cur, d, np.abs(d) > 1, np.full(len(d), 0.1)))
    assert bars == ["20 m"] and "signed distance (m)" in labels and "points" in labels


@pytest.mark.slow
def test_the_3d_view_is_decimated_above_the_budget_by_the_stated_factor(tmp_path, rng):
    from sdp.viz._report import decimation

    ref, cur = landscape(rng)
    r = sdp.detect_changes(ref, cur)
    path = sdp.change_report(tmp_path / "r.html", r, ref, cur, max_points=2_000, thumbnails=1)
    page = path.read_text()
    drawn, total, factor = drawn_note(page)
    n_changed = int(r.appeared.sum() + r.disappeared.sum())
    assert total == len(cur) + int(r.disappeared.sum())
    assert factor == decimation(total - n_changed, 2_000 - int(np.ceil(n_changed / decimation(n_changed, 1_000))))
    assert factor > 1 and drawn < 2_000 * 1.1  # a random 1 in factor: the budget, give or take the sampling
    assert page.count('class="thumb"') == 2  # one per direction


@pytest.mark.slow  # a second or two; the quick tier keeps a lighter test of the same module
def test_distance_report(tmp_path, rng):
    ref, cur = landscape(rng)
    d = sdp.distances(ref, cur)
    page = sdp.distance_report(tmp_path / "d.html", d, names=("a.laz", "b.laz"), max_points=5_000).read_text()
    assert not OUTSIDE.findall(page) and "Plotly.newPlot" in page
    assert len(IMAGES.findall(page)) == 1  # the map with its histogram
    drawn, total, _ = drawn_note(page)
    assert total == len(ref) and drawn < 5_500 and f"{d.summary()['significant']:,}" in page
    assert "level of detection" in page
    assert "no sensor known: the default direction, up (+z)" in page  # the normals' own reason


@pytest.mark.parametrize("kw, match", [
    ({"report": "nodir/r.html"}, "does not exist"),
    ({"report": "ref.npy"}, "writes HTML; name it"),  # a page named as a cloud (the input, here)
    ({"report": "out.html", "html": "out.html"}, "two outputs"),
    ({"report": "r.html", "png": "r.html"}, "writes a PNG"),
    ({"report": "r.html", "tiled": True}, "--png/--html/--report is not available with --tiled"),
    ({"report": "r.html", "memory_limit": "1MB", "output": "out.laz"}, "made in memory"),  # tiles by themselves
])
def test_report_is_checked_before_any_work(tmp_path, rng, monkeypatch, kw, match):
    ref, cur = landscape(rng, building=False)
    np.save(tmp_path / "ref.npy", ref)
    np.save(tmp_path / "cur.npy", cur)
    monkeypatch.chdir(tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    execution = sdp.Execution(tiled=kw.pop("tiled", False), memory_limit=kw.pop("memory_limit", None))
    with pytest.raises(sdp.SDPError, match=match) as err:
        sdp.compare_files("ref.npy", "cur.npy", output=kw.pop("output", "out.ply"), outputs=sdp.Outputs(**kw),
                          execution=execution)
    assert "\n" not in str(err.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_distance_report_is_refused_in_tiles(tmp_path, rng):
    ref, _ = landscape(rng, building=False)
    np.save(tmp_path / "ref.npy", ref)
    with pytest.raises(sdp.SDPError, match="--report is not available with --tiled"):
        sdp.distance_files(tmp_path / "ref.npy", tmp_path / "ref.npy", output=tmp_path / "d.laz",
                           execution=sdp.Execution(tiled=True),
                           outputs=sdp.Outputs(report=tmp_path / "d.html"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ref.npy"]


def test_a_failing_report_leaves_no_output(tmp_path, rng, monkeypatch):
    from sdp.viz import _report as htmlreport

    ref, cur = landscape(rng)
    np.save(tmp_path / "ref.npy", ref)
    np.save(tmp_path / "cur.npy", cur)

    def broken(*a, **k):
        raise sdp.SDPError("the report broke")

    monkeypatch.setattr(htmlreport, "_thumbnail", broken)
    with pytest.raises(sdp.SDPError, match="the report broke"):
        sdp.compare_files(tmp_path / "ref.npy", tmp_path / "cur.npy", output=tmp_path / "out.ply",
                          outputs=sdp.Outputs(png=tmp_path / "c.png", report=tmp_path / "r.html"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cur.npy", "ref.npy"]  # all the outputs or none


# --- in a real browser ---------------------------------------------------------------------------

@pytest.fixture
def chromium():
    why = browser.missing()
    if why:
        pytest.skip(f"no headless browser: {why}")
    return browser


def assert_drawn(visit):
    assert visit.errors == [], visit.errors
    assert visit.rendered, "the 3-D view never drew"
    assert browser.blankness(visit.screenshot) > 0.05  # not one flat colour


@pytest.mark.slow
def test_the_browser_check_sees_a_javascript_error(tmp_path, chromium):
    page = tmp_path / "bad.html"
    page.write_text("<html><body><h1>a page</h1><script>undefinedFunction();</script></body></html>")
    v = chromium.visit(page)
    assert any("undefinedFunction" in e for e in v.errors), v.errors
    blank = tmp_path / "blank.html"
    blank.write_text("<html><body style='background:#fff'></body></html>")
    assert chromium.blankness(chromium.visit(blank).screenshot) < 0.01


@pytest.mark.slow
def test_the_report_opens_in_headless_chromium(tmp_path, rng, chromium):
    ref, cur = landscape(rng)
    r = sdp.detect_changes(ref, cur)
    path = sdp.change_report(tmp_path / "r.html", r, ref, cur)
    v = chromium.visit(path)
    assert_drawn(v)
    (tmp_path / "shot.png").write_bytes(v.screenshot)
    d = sdp.distances(ref, cur)
    assert_drawn(chromium.visit(sdp.distance_report(tmp_path / "d.html", d)))


@pytest.mark.slow
@pytest.mark.parametrize("case", ["toronto", "mosd"])
def test_real_scan_reports_open_in_headless_chromium(tmp_path, shared_data, chromium, case):
    if case == "toronto":
        a, b = shared_data / "als_toronto" / "TTP_2015.laz", shared_data / "als_toronto" / "TTP_2023.laz"
        kw = dict(align=sdp.Registration(method="density", align_class="2", fix_horizontal=True))
    else:
        a, b = shared_data / "mosd" / "learn" / "learn0.pcd", shared_data / "mosd" / "learn" / "learn1.pcd"
        kw = {}
    r = sdp.compare_files(a, b, output=tmp_path / "out.ply", **kw,
                          outputs=sdp.Outputs(both=True, report=tmp_path / "r.html"))
    page = (tmp_path / "r.html").read_text()
    assert not OUTSIDE.findall(page)
    if case == "toronto":  # a map, in coordinates relative to a stated round origin
        assert "Where it changed" in page and re.search(r"relative to \(63\d,\d\d0, 4,83\d,\d\d0\)", page)
    assert r.summary["current"]["appeared"] > 0
    assert_drawn(chromium.visit(tmp_path / "r.html"))


def test_the_combined_decisions_level_is_in_the_summary_table(tmp_path, rng):
    ref, cur = landscape(rng, building=False)
    cur[:, 2] += 0.01 * rng.standard_normal(len(cur))
    for decision, shown in (("combined", True), ("point", False)):
        r = sdp.detect_changes(ref, cur, decision=decision)
        page = sdp.change_report(tmp_path / f"{decision}.html", r, ref, cur, thumbnails=0).read_text()
        assert ("level of detection: systematic part" in page) == shown
        if shown:
            s = r.summary()["current"]["level"]
            assert f"1.96·σ_s = {1.96 * s['systematic']:.3g} m, p = {s['range_exponent']:.2f}" in page


def visible_text(page: str) -> str:
    """The page's text a reader sees without opening anything: no script, no collapsed <details>."""
    import html

    page = re.sub(r"<script.*?</script>|<details>.*?</details>", "", page, flags=re.S)
    return html.unescape(re.sub(r"<[^>]+>", " ", page))


def embedded_json(page: str, command: str) -> dict:
    import html
    import json

    return json.loads(html.unescape(re.search(rf"sdp {command} --json\)</summary><pre>(.*?)</pre>", page, re.S)[1]))


def small_scene(rng, tmp_path):
    """Two small PLY epochs with LAS classes (2 ground, 6 a roof 5 m up in the current), the
    current also 0.2 m higher: a density alignment on the ground finds the lift."""
    gx, gy = np.meshgrid(np.arange(0, 40, 1.0), np.arange(0, 30, 1.0))
    xy = np.c_[gx.ravel(), gy.ravel()] + rng.uniform(-0.3, 0.3, (gx.size, 2))
    ref = np.c_[xy, 0.05 * rng.standard_normal(len(xy)) + 0.3 * np.sin(xy[:, 0] / 5)]
    cur = ref + [0, 0, 0.2]
    roof = (xy[:, 0] > 10) & (xy[:, 0] < 20) & (xy[:, 1] > 10) & (xy[:, 1] < 18)
    cur[roof, 2] += 5
    classes = {"classification": np.where(roof, 6, 2).astype(np.uint8)}
    sdp.write_points(tmp_path / "ref.ply", ref, classes)
    sdp.write_points(tmp_path / "cur.ply", cur, classes)
    return ref, cur


def test_the_report_shows_how_it_aligned(tmp_path, rng):
    small_scene(rng, tmp_path)
    r = sdp.compare_files(tmp_path / "ref.ply", tmp_path / "cur.ply", output=tmp_path / "out.ply",
                          outputs=sdp.Outputs(report=tmp_path / "r.html"),
                          align=sdp.Registration(method="density", align_class="2", fix_horizontal=True))
    al = r.summary["alignment"]
    assert al["align_class"] == [2] and al["fix_horizontal"] is True  # in the JSON summary too
    page = (tmp_path / "r.html").read_text()
    row = re.search(r"<tr><td>alignment</td>.*?</tr>", page)[0]
    assert "given (--align density --align-class 2 --fix-horizontal)" in row and "class 2" in row
    assert f"inside the reference&#x27;s volume {al['inside_before']:.1%} → {al['inside_after']:.1%}" in row


def test_the_reports_json_is_what_json_prints_and_its_time_the_same(tmp_path, rng):
    import json

    from sdp._core._json import dumps

    small_scene(rng, tmp_path)
    for command, run in (("change", sdp.compare_files), ("distance", sdp.distance_files)):
        r = run(tmp_path / "ref.ply", tmp_path / "cur.ply", output=tmp_path / f"{command}.ply",
                outputs=sdp.Outputs(report=tmp_path / f"{command}.html"))
        page = (tmp_path / f"{command}.html").read_text()
        # the page's JSON is the summary --json prints, the report's own time in both
        assert embedded_json(page, command) == json.loads(dumps(r.summary)), command
        assert "report" in r.summary["timings"] and (command == "distance" or "inputs" in r.summary)
        shown = re.search(r"this report \(pictures, view\)</td><td>([\d,.]+) ms", page)[1]
        assert shown == f"{r.summary['timings']['report'] * 1e3:,.1f}", command


def test_an_alignment_from_almost_no_overlap_is_called_a_guess_in_view(tmp_path, rng):
    from sdp.cli._common import alignment_summary

    ref, cur = landscape(rng, building=False)
    r = sdp.detect_changes(ref, cur)
    s = r.summary()
    s["alignment"] = alignment_summary(sdp.Alignment(matrix=np.eye(4), method="gicp", inside_before=0.01,
                                                     inside_after=0.9, rmse=0.02, seconds=0.1),
                                       sdp.Registration(method="gicp"))
    page = sdp.change_report(tmp_path / "r.html", r, ref, cur, summary=s, thumbnails=0).read_text()
    shown = visible_text(page)
    assert "a registration from so little overlap is a guess" in shown
    assert "inside the reference's volume 1.0% → 90.0%" in shown and "given (--align gicp)" in shown


def test_the_series_report_shows_the_alignment_and_each_epoch(tmp_path, rng):
    from sdp.viz._report import series_report

    ref, cur = small_scene(rng, tmp_path)
    ds = sdp.series([ref, cur, cur + [0, 0, 0.1]], output=tmp_path / "s.zarr", align="density")
    page = series_report(tmp_path / "s.html", ds).read_text()
    shown = visible_text(page)
    assert re.search(r"alignment\s+density\s+given \(--align\)", shown)
    for k, e in enumerate(ds.attrs["epochs"]):
        cells = re.search(rf"<tr><td>{k}</td>(.*?)</tr>", page.split("<h3>Epochs")[1])[1]
        assert f"{e['points']:,}" in cells and f"{e['registration_error']:.4g}" in cells
        if k:  # the reference is not moved
            assert f"residual {e['alignment']['rmse']:.4g} m (RMS)" in cells
            assert f"{e['significant'] / e['comparable']:.1%}" in cells


def test_report_points_that_do_not_match_the_result_are_refused_in_one_line(tmp_path, rng):
    ref, cur = landscape(rng, building=False)
    r = sdp.detect_changes(ref, cur)
    with pytest.raises(sdp.InvalidPointsError, match=r"current: 5,999 points, but result.current_state describes "
                                                     r"6,000") as err:
        sdp.change_report(tmp_path / "r.html", r, ref, cur[:-1])
    assert "\n" not in str(err.value)
    with pytest.raises(sdp.InvalidPointsError, match=r"reference: x, y, z .* \(6000, 2\)"):
        sdp.change_report(tmp_path / "r.html", r, ref[:, :2], cur)
    for write, args in ((sdp.change_report, (r, ref, cur)), (sdp.distance_report, (None,))):
        with pytest.raises(sdp.InvalidOptionError, match="writes HTML; name it ….html or ….htm"):
            write(tmp_path / "r.png", *args)
    assert not list(tmp_path.iterdir())


def test_a_distance_report_without_any_distance_says_so_without_warnings(tmp_path, rng):
    import warnings

    from sdp.viz._render import distances_figure

    gx, gy = np.meshgrid(np.arange(0, 30, 1.0), np.arange(0, 20, 1.0))
    ref = np.c_[gx.ravel(), gy.ravel(), 0.05 * rng.standard_normal(gx.size)]
    d = sdp.distances(ref, ref + [500, 0, 0])  # far from every core point
    assert d.summary()["comparable"] == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # matplotlib's of an empty legend, of the layout
        sdp.distance_report(tmp_path / "d.html", d)
        hist = distances_figure(d.core_points, d.distance, d.significant, d.lod).axes[-1]
    assert [t.get_text() for t in hist.texts] == ["no core point has a distance"] and hist.get_legend() is None


def test_an_airborne_tile_is_a_map_whatever_a_noise_return_above_it():
    # a 200 m tile with 40 m of buildings is a map; one return 60 m above it does not make it a scene
    # of three views, nor does the noise's height count; a room stays three views
    from sdp.viz._render import is_map

    rng = np.random.default_rng(0)
    tile = np.c_[rng.uniform(0, 200, (5000, 2)), rng.uniform(0, 40, 5000)]
    noisy = np.r_[tile, [[100.0, 100.0, 100.0]]]
    lo, hi = noisy.min(axis=0), noisy.max(axis=0)
    assert not is_map(lo, hi)  # the bounds alone: 100 m of 200
    assert is_map(lo, hi, z=noisy[:, 2])
    room = rng.uniform([0, 0, 0], [5, 4, 3], (5000, 3))
    assert not is_map(room.min(axis=0), room.max(axis=0), z=room[:, 2])
