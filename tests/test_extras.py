"""Optional extras: `import sdp` needs none of them, and a missing one is one line naming its install."""

import subprocess
import sys

import numpy as np
import pytest
from conftest import assert_changes_drawn

import sdp

EXTRAS = {"tiles": ["dask", "distributed", "zarr"], "plots": ["matplotlib", "plotly"],
          "align": ["small_gicp"]}


@pytest.mark.slow  # a second or two; the quick tier keeps a lighter test of the same module
def test_import_sdp_loads_no_extra():
    code = ("import sys, sdp, sdp.cli._main, sdp.scale._tiles, sdp.scale._store, sdp.actions._actions, sdp.viz._render, sdp.stream._watch\n"
            f"print(sorted(m for m in {sum(EXTRAS.values(), [])!r} if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


@pytest.fixture
def without(monkeypatch):
    """without(*names): importing these packages (and their submodules) fails as when they are not
    installed (None in sys.modules), until the test ends."""
    def hide(*names):
        for name in [m for m in sys.modules if m.split(".")[0] in names] + list(names):
            monkeypatch.setitem(sys.modules, name, None)

    return hide


def _one_line(err, extra):
    message = str(err.value)
    assert "\n" not in message and f"pip install 'sdp[{extra}]'" in message, message
    assert isinstance(err.value, ImportError) and isinstance(err.value, sdp.SDPError)


def test_tiles_without_dask(without, tmp_path):
    without("dask", "distributed")
    pts = np.random.default_rng(0).random((200, 3))
    with pytest.raises(sdp.MissingDependencyError, match="needs dask") as err:
        sdp.detect_changes_tiled(pts, pts, lattice=sdp.Lattice(voxel_size=0.1),
                                 execution=sdp.Execution(workdir=tmp_path))
    _one_line(err, "tiles")
    with pytest.raises(sdp.MissingDependencyError, match="needs dask") as err:
        sdp.detect_changes_tiled(pts, pts, lattice=sdp.Lattice(voxel_size=0.1),
                                 execution=sdp.Execution(scheduler="synchronous", workdir=tmp_path))
    _one_line(err, "tiles")
    assert list(tmp_path.iterdir()) == []  # refused before any work


def test_field_store_without_zarr(without, tmp_path):
    field = sdp.DensityField.from_points(np.random.default_rng(0).random((200, 3)), voxel_size=0.1)
    without("zarr")
    with pytest.raises(sdp.MissingDependencyError, match="field store.*needs zarr") as err:
        sdp.FieldStore.from_field(field, tmp_path / "f.zarr")
    _one_line(err, "tiles")
    with pytest.raises(sdp.MissingDependencyError, match="needs zarr"):
        sdp.FieldStore.open(tmp_path / "f.zarr")
    with pytest.raises(sdp.MissingDependencyError, match="needs zarr"):
        sdp.build_field_tiled(np.random.default_rng(0).random((200, 3)), tmp_path / "g.zarr",
                              lattice=sdp.Lattice(voxel_size=0.1))
    assert list(tmp_path.iterdir()) == []


def test_action_classifier_without_scikit_learn(without):
    """The classifier is NumPy's (a ridge solved in the dual): no extra to install."""
    from sdp.actions import _actions as actions

    without("sklearn")
    rng = np.random.default_rng(0)
    x, y = rng.random((8, 5)), np.repeat([1, 2], 4)
    model, _ = actions.train(x + y[:, None], y, np.tile([1, 2], 4))
    assert np.array_equal(model.predict(x + y[:, None]), y)


def test_pictures_without_matplotlib_or_plotly(without, tmp_path):
    xyz = np.random.default_rng(0).random((50, 3))
    without("matplotlib", "plotly", "mpl_toolkits")
    with pytest.raises(sdp.MissingDependencyError, match="PNG needs matplotlib") as err:
        sdp.render_changes(tmp_path / "c.png", xyz, xyz[:, 0] > 0.5)
    _one_line(err, "plots")
    with pytest.raises(sdp.MissingDependencyError, match="needs matplotlib"):
        sdp.render_field(tmp_path / "f.png", sdp.DensityField.from_points(xyz, voxel_size=0.1))
    with pytest.raises(sdp.MissingDependencyError, match="HTML view needs plotly") as err:
        sdp.render_changes_html(tmp_path / "c.html", xyz, xyz[:, 0] > 0.5)
    _one_line(err, "plots")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("hidden", [("plotly",), ("matplotlib", "mpl_toolkits")])
def test_report_without_its_extras_fails_before_any_work(without, tmp_path, hidden):
    rng = np.random.default_rng(0)
    for name in ("a.npy", "b.npy"):
        np.save(tmp_path / name, rng.random((300, 3)))
    without(*hidden)
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(sdp.MissingDependencyError, match=f"--report.*needs {hidden[0]}") as err:
        sdp.compare_files(tmp_path / "a.npy", tmp_path / "b.npy", output=tmp_path / "o.ply",
                          outputs=sdp.Outputs(report=tmp_path / "r.html"))
    _one_line(err, "plots")
    with pytest.raises(sdp.MissingDependencyError, match=f"needs {hidden[0]}"):
        sdp.distance_files(tmp_path / "a.npy", tmp_path / "b.npy", output=tmp_path / "d.ply",
                           outputs=sdp.Outputs(report=tmp_path / "d.html"))
    if hidden[0] == "matplotlib":
        with pytest.raises(sdp.MissingDependencyError, match="--png.*needs matplotlib"):
            sdp.compare_files(tmp_path / "a.npy", tmp_path / "b.npy", output=tmp_path / "o.ply",
                              outputs=sdp.Outputs(png=tmp_path / "c.png"))
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_gicp_without_small_gicp(without):
    pts = np.random.default_rng(0).random((500, 3))
    without("small_gicp")
    with pytest.raises(sdp.MissingDependencyError, match="GICP needs small_gicp") as err:
        sdp.align(pts, pts, method="gicp")
    _one_line(err, "align")


def test_cli_names_the_extra(without, tmp_path, capsys):
    from sdp import cli

    a = tmp_path / "a.npy"
    np.save(a, np.random.default_rng(0).random((300, 3)))
    without("dask", "distributed")
    assert cli.main(["change", str(a), str(a), "-o", str(tmp_path / "out.laz"), "--tiled", "--voxel-size", "0.1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("sdp: error:") and "pip install 'sdp[tiles]'" in err[-1], err
    assert not (tmp_path / "out.laz").exists()


def test_pictures_with_the_plots_extra(tmp_path):
    """The quick tier's check of sdp.render (the slow CLI tests draw real scenes, and the HTML view)."""
    xyz = np.random.default_rng(0).random((300, 3))
    state = (xyz[:, 0] > 0.7).astype(np.uint8) + (xyz[:, 1] > 0.9)  # 0, 1 and 2
    assert_changes_drawn(sdp.render_changes(tmp_path / "c.png", xyz, state))  # a room: three 3-D views
    flat = xyz * [10, 10, 0.1]  # a map, without a changed point
    assert_changes_drawn(sdp.render_changes(tmp_path / "n.png", flat, state * (state == 2)), changed=False)


def test_import_sdp_is_lazy_and_every_public_name_resolves():
    import subprocess
    import sys

    code = ("import sys, sdp; heavy = [m for m in ('numba', 'scipy', 'dask', 'matplotlib') if m in sys.modules]; "
            "assert not heavy, heavy; assert all(getattr(sdp, n) is not None for n in sdp.__all__); "
            "assert sdp.distance._distances.DISTANCE_FIELDS and 'numba' in sys.modules")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
