"""sdp.series in tiles on Dask: the same archive as in memory, appends, the switch beyond memory."""

import json

import numpy as np
import pytest

import sdp
from sdp.cli import main
from sdp.data import slope_series

pytest.importorskip("xarray")
pytest.importorskip("zarr")
pytest.importorskip("dask")

#: Scales small enough for tiles of 4 (the halo is about 7 projection scales): 25 tiles on the slope.
CYL = sdp.Cylinder(projection_scale=0.5, normal_scale=1.0, max_distance=0.3)
TILES = sdp.Execution(tiled=True, tile_size=4.0, scheduler="synchronous")


@pytest.fixture(scope="module")
def slope():
    s = slope_series(4, 9000, size=20.0, step_epoch=2, seed=5)
    return [e + [1000.3, -52.7, 3.1] for e in s.epochs]  # away from the origin: the corners matter


def _same(a, b):
    """Every array of two archives equal, NaN where NaN (no tolerance: the sums run in the same order)."""
    assert sorted(a.variables) == sorted(b.variables)
    for name in a.variables:
        x, y = a[name].values, b[name].values
        assert x.shape == y.shape, name
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name
    keys = ("points", "comparable", "significant", "time")
    assert [{k: e[k] for k in keys} for e in a.attrs["epochs"]] == [{k: e[k] for k in keys} for e in b.attrs["epochs"]]
    assert a.attrs["parameters"]["used"] == b.attrs["parameters"]["used"]


def test_tiled_archive_equals_the_in_memory_one(slope, tmp_path):
    whole = sdp.series(slope, output=tmp_path / "m.zarr", cylinder=CYL, registration_error=0.002)
    tiled = sdp.series(slope, output=tmp_path / "t.zarr", cylinder=CYL, registration_error=0.002, execution=TILES)
    _same(whole, tiled)
    record = tiled.attrs["runs"][-1]["tiled"]
    assert record["tiles"] >= 4 and record["reason"] == "asked (tiled)" and "tiled" not in whole.attrs["runs"][-1]
    assert np.isfinite(tiled.distance.values).mean() > 0.9 and tiled.sizes["point"] > 1000


@pytest.mark.slow
def test_given_core_points_auto_normal_scale_and_another_reference(slope, tmp_path):
    kw = dict(core_points=slope[1][::5], reference=1, cylinder=sdp.Cylinder(projection_scale=0.5, max_distance=0.3))
    _same(sdp.series(slope, output=tmp_path / "m.zarr", **kw),
          sdp.series(slope, output=tmp_path / "t.zarr", execution=TILES, **kw))


@pytest.mark.slow
def test_append_in_tiles_equals_the_full_run(slope, tmp_path):
    full = sdp.series(slope, output=tmp_path / "full.zarr", cylinder=CYL)
    sdp.series(slope[:2], output=tmp_path / "a.zarr", cylinder=CYL, execution=TILES)
    grown = sdp.series(slope[2:], output=tmp_path / "a.zarr", append=True, execution=TILES)
    _same(full, grown)
    assert [r["added"] for r in grown.attrs["runs"]] == [2, 2] and grown.attrs["runs"][-1]["tiled"]["tiles"] >= 4


@pytest.mark.slow  # the quick tier keeps lighter tests of the same module
def test_epochs_beyond_the_memory_limit_switch_to_tiles(slope, tmp_path, monkeypatch):
    from sdp.scale import _series

    files = []
    for k, e in enumerate(slope):
        files.append(tmp_path / f"e{k}.npy")
        np.save(files[-1], e)
    said = []
    # an epoch of 9,000 points counted as 900 MB: above the limit of 600 MB, which a tile's task holds
    monkeypatch.setattr(_series, "POINT_BYTES", 1e5)
    low = sdp.Execution(memory_limit="600MB", tile_size=4.0, scheduler="synchronous", notify=said.append)
    tiled = sdp.series(files, output=tmp_path / "t.zarr", cylinder=CYL, execution=low)
    assert len(said) == 1 and "in tiles on Dask" in said[0] and "600" in said[0]
    assert tiled.attrs["runs"][-1]["tiled"]["reason"] == said[0]
    _same(sdp.series(slope, output=tmp_path / "m.zarr", cylinder=CYL), tiled)
    monkeypatch.setattr(_series, "POINT_BYTES", 200.0)  # they fit: in memory
    assert "tiled" not in sdp.series(files, output=tmp_path / "m2.zarr", cylinder=CYL, execution=low).attrs["runs"][-1]
    with pytest.raises(sdp.SDPError, match="--align registers whole epochs"):
        sdp.series(files, output=tmp_path / "x.zarr", align="density", execution=TILES)
    assert not (tmp_path / "x.zarr").exists()


def test_tiled_refuses_files_it_cannot_slice_in_one_line(slope, tmp_path, capsys):
    text = tmp_path / "e0.xyz"
    np.savetxt(text, slope[0][:100])
    assert main(["series", str(text), str(text), "--tiled", "-o", str(tmp_path / "x.zarr")]) == 2
    err = capsys.readouterr().err
    assert "in slices" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "x.zarr").exists()


@pytest.mark.slow
def test_command_series_tiled_on_a_local_cluster(slope, tmp_path, capsys):
    files = []
    for k, e in enumerate(slope):
        files.append(str(tmp_path / f"e{k}.laz"))
        sdp.write_points(files[-1], e)
    args = ["--projection-scale", "0.5", "--normal-scale", "1.0", "--max-distance", "0.3", "--times", "0,1,2,3"]
    assert main(["series", *files, "-o", str(tmp_path / "m.zarr"), *args, "--quiet"]) == 0
    assert main(["series", *files, "-o", str(tmp_path / "t.zarr"), *args, "--tiled", "--tile-size", "4",
                 "--workers", "2", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["runs"][-1]["tiled"]["tiles"] >= 4
    _same(sdp.open_series(tmp_path / "m.zarr"), sdp.open_series(tmp_path / "t.zarr"))


def test_the_in_memory_plan_counts_the_process(tmp_path):
    # 2 x 1 M points at 250MB ran in memory and peaked at 325 MB: the plan left the process out
    from sdp.scale._budget import PROCESS_BYTES
    from sdp.scale._series import POINT_BYTES, plan_series

    files = [np.save(tmp_path / f"e{k}.npy", np.zeros((100_000, 3))) or tmp_path / f"e{k}.npy" for k in range(2)]
    data = POINT_BYTES * 100_000
    fits = sdp.Execution(memory_limit=int(PROCESS_BYTES + data) + 1)
    assert plan_series(files, reference=0, core_count=0, execution=fits) is None
    said = []
    short = sdp.Execution(memory_limit=int(PROCESS_BYTES + data) - 1, notify=said.append)
    tiles = plan_series(files, reference=0, core_count=0, execution=short)
    reason, need = tiles.execution.switched  # said by the tiles once taken; their refusal names the need
    assert said == [] and "in tiles on Dask" in reason and need == PROCESS_BYTES + data
