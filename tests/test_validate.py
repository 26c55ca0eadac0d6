"""Bad options are refused with one clear line, before any allocation, Dask work or output (issue 17)."""

import math
import subprocess
import sys

import numpy as np
import pytest
from conftest import slow_after

import sdp
from sdp import DensityField
from sdp._core._memory import format_bytes, memory_limit, parse_bytes
from sdp._core._validate import integer_at_least, positive_finite
from sdp.fields._lattice import check_lattice


def run(*args, cwd=None, **kw):
    return subprocess.run([sys.executable, "-m", "sdp.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, **kw)


@pytest.fixture(scope="module")
def cloud():
    return np.random.default_rng(0).random((2000, 3))


@pytest.mark.parametrize("kw, error, match", [
    (dict(voxel_size=1e308), sdp.SDPError, "too large"),
    (dict(voxel_size=0), sdp.InvalidOptionError, "positive finite"),
    (dict(voxel_size=math.nan), sdp.InvalidOptionError, "positive finite"),
    (dict(voxel_size=-1), sdp.InvalidOptionError, "positive finite"),
    (dict(voxel_size=1e-9), sdp.GridTooLargeError, r"would need [0-9.e+]+ EB, above the memory limit of 4 GB"),
    (dict(voxel_size=0.05, sigma_voxels=1e308), sdp.InvalidOptionError, "reaches inf voxels"),
    (dict(voxel_size=0.05, sigma_voxels=1000), sdp.GridTooLargeError, "kernel of one point.*808 GB"),
    (dict(voxel_size=0.05, sigma_voxels=0.3), sdp.InvalidOptionError, "below 0.41 voxels"),
    (dict(voxel_size=0.05, k=math.nan), sdp.InvalidOptionError, "k must be a finite"),
    (dict(voxel_size=0.05, h=math.nan), sdp.InvalidOptionError, "h must be a positive"),
    (dict(voxel_size=0.05, h=-1), sdp.InvalidOptionError, "h must be a positive"),
    (dict(voxel_size=0.05, memory_limit="1e3"), sdp.InvalidOptionError, "1000 B, below the minimum of 1 MB"),
    (dict(voxel_size=0.05, memory_limit=0), sdp.InvalidOptionError, "positive"),
    (dict(voxel_size=0.05, memory_limit="garbage"), sdp.InvalidOptionError, "can't read memory size"),
    (dict(grid_size=0), sdp.InvalidOptionError, "grid_size"),
])
def test_field_and_detect_changes_refuse_bad_options(cloud, kw, error, match):
    with pytest.raises(error, match=match) as err:
        DensityField.from_points(cloud, **kw)
    assert "\n" not in str(err.value) and "0.00 GiB" not in str(err.value)
    with pytest.raises(error, match=match):
        limit = kw.pop("memory_limit", None)
        sdp.detect_changes(cloud, cloud, lattice=sdp.Lattice(**kw), memory_limit=limit)


def test_far_coordinates_are_refused_not_silently_wrong(cloud):
    # 1e12 m from zero at a 1 cm voxel: 1e14 voxels, beyond float64's sub-voxel precision
    with pytest.raises(sdp.InvalidPointsError, match=r"2\*\*40"):
        DensityField.from_points(cloud + 1e12, voxel_size=0.01)
    with pytest.raises(sdp.InvalidPointsError, match=r"2\*\*40"):
        sdp.detect_changes(cloud + 1e15, cloud + 1e15, lattice=sdp.Lattice(voxel_size=0.1))
    DensityField.from_points(cloud + 1e9, voxel_size=0.01)  # UTM-like offsets stay fine
    check_lattice([0, 0, 0], [2.0**39, 0, 0], 1.0)


@pytest.mark.parametrize("kw, match", [
    (dict(voxel_size=0), "positive finite"),
    (dict(voxel_size=1e308), "too large"),
    (dict(voxel_size=1e-9), "block directory of one tile"),
    (dict(voxel_size=0.05, sigma_voxels=1000), "kernel of one point"),
    (dict(voxel_size=0.05, h=-1), "h must be"),
    (dict(voxel_size=0.05, tile_size=-1), "tile_size"),
    (dict(voxel_size=0.05, workers=0), "workers"),
    (dict(voxel_size=0.05, workers=-1), "workers"),
    (dict(voxel_size=0.05, min_region_points=-5), "min_region_points"),
    (dict(voxel_size=0.05, memory_limit="1e3"), "below the minimum"),
    (dict(voxel_size=0.05, workdir="/nonexistent/sdp"), "no such folder"),
])
def test_tiled_refuses_bad_options_before_any_work(tmp_path, cloud, kw, match, monkeypatch):
    monkeypatch.setattr("sdp.scale._session._connect", lambda *a: pytest.fail("reached Dask"))
    kw.setdefault("workdir", tmp_path)
    lattice = {k: kw.pop(k) for k in ("voxel_size", "sigma_voxels", "h") if k in kw}
    regions = {k: kw.pop(k) for k in ("min_region_points",) if k in kw}
    with pytest.raises(sdp.SDPError, match=match):
        sdp.detect_changes_tiled(cloud, cloud, lattice=sdp.Lattice(**lattice), **regions,
                                 execution=sdp.Execution(scheduler="synchronous", **kw))
    if not regions:
        with pytest.raises(sdp.SDPError, match=match):
            sdp.build_field_tiled(cloud, tmp_path / "f.zarr", lattice=sdp.Lattice(**lattice),
                                  execution=sdp.Execution(scheduler="synchronous", **kw))
    assert list(tmp_path.iterdir()) == []  # no work folder, no store left


def test_helpers():
    assert positive_finite("x", "2.5") == 2.5
    with pytest.raises(sdp.InvalidOptionError, match="x must be a positive finite number, got 'inf'"):
        positive_finite("x", "inf")
    assert integer_at_least("n", "3", 1) == 3
    with pytest.raises(sdp.InvalidOptionError):
        integer_at_least("n", 2.5, 1)
    assert [format_bytes(v) for v in (512, 12.3 * 2**20, 4 * 2**30)] == ["512 B", "12.3 MB", "4 GB"]
    assert parse_bytes("2GB") == 2 * 2**30 and memory_limit(1000) == 1000  # numbers are bytes


def test_options_that_name_no_class_or_no_function_are_refused():
    # a LAS class is 0 to 255 (-1 names none); notify is called with a line of text
    assert sdp.Registration(method="density", align_class="2,9").classes == [2, 9]
    for bad in (-1, 256, "2,-1"):
        with pytest.raises(sdp.InvalidOptionError, match="LAS class numbers"):
            sdp.Registration(method="density", align_class=bad)
    with pytest.raises(sdp.InvalidOptionError, match="notify must be a function"):
        sdp.Execution(notify="x")
    assert sdp.Execution(notify=print).notify is print
    with pytest.raises(sdp.InvalidOptionError, match="min_region_points drops small regions"):
        next(iter(sdp.watch(np.zeros((10, 3)), [np.zeros((10, 3))], regions=False, min_region_points=5)))


@pytest.mark.slow
def test_unreachable_scheduler_is_one_line_error(cloud, tmp_path):
    with pytest.raises(sdp.SDPError, match="can't reach the Dask scheduler at tcp://127.0.0.1:1") as err:
        sdp.detect_changes_tiled(cloud, cloud, lattice=sdp.Lattice(voxel_size=0.1),
                                 execution=sdp.Execution(scheduler="tcp://127.0.0.1:1", workdir=tmp_path))
    assert "\n" not in str(err.value)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args", slow_after(1, [
    ["build", "g.npy", "-o", "f.sdpf", "--voxel-size", "1e308"],
    ["build", "g.npy", "-o", "f.sdpf", "--voxel-size", "0"],
    ["build", "g.npy", "-o", "f.sdpf", "--voxel-size", "nan"],
    ["build", "g.npy", "-o", "f.sdpf", "--voxel-size", "1e-9"],
    ["build", "g.npy", "-o", "f.sdpf", "--sigma-voxels", "1000"],
    ["build", "g.npy", "-o", "f.sdpf", "-k", "nan"],
    ["build", "g.npy", "-o", "f.sdpf", "--h", "-1"],
    ["build", "g.npy", "-o", "f.sdpf", "--memory-limit", "1e3"],
    ["build", "g.npy", "-o", "f.zarr", "--voxel-size", "1e-9"],
    ["change", "g.npy", "g.npy", "-o", "o.laz", "--tiled", "--voxel-size", "0"],
    ["change", "g.npy", "g.npy", "-o", "o.laz", "--tiled", "--voxel-size", "1e308"],
    ["change", "g.npy", "g.npy", "-o", "o.laz", "--tiled", "--sigma-voxels", "1e308"],
    ["change", "g.npy", "g.npy", "-o", "o.laz", "--tiled", "--workers", "-1"],
    ["change", "g.npy", "g.npy", "-o", "o.laz", "--tiled", "--tile-size", "-1"],
    ["change", "g.npy", "g.npy", "-o", "o.laz", "--min-region-points", "-5"],
    ["change", "g.npy", "g.npy", "-o", "o.laz", "--tiled", "--workdir", "/nonexistent"],
    ["change", "g.npy", "g.npy", "-o", "o.laz", "--tiled", "--memory-limit", "garbage"],
]))
def test_cli_refuses_bad_options_in_one_line(tmp_path, cloud, args):
    np.save(tmp_path / "g.npy", cloud)
    p = run(*args, cwd=tmp_path, timeout=300)  # a hang fails
    assert p.returncode == 2, p.stderr
    assert p.stderr.startswith("sdp: error: ") and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "Traceback" not in p.stderr and "0.00 GiB" not in p.stderr
    assert sorted(f.name for f in tmp_path.iterdir()) == ["g.npy"]


def test_build_counts_the_points_and_the_process_in_the_limit(tmp_path, capsys):
    """`sdp build`'s memory limit is the whole job's, as `sdp change`'s: points that would not fit
    with the process are refused before they are read, and the blocks get what is left."""
    from sdp.cli._main import main
    from sdp.scale._budget import untiled_point_bytes

    xyz = np.random.default_rng(0).uniform(0, 10, (500_000, 3))
    np.save(tmp_path / "g.npy", xyz)
    need = untiled_point_bytes(len(xyz))
    assert main(["build", str(tmp_path / "g.npy"), "-o", str(tmp_path / "f.sdpf"),
                 "--memory-limit", str(need - 2**20)]) == 2
    err = capsys.readouterr().err
    assert "500,000 points in memory with the process" in err and "-o FIELD.zarr" in err
    assert sorted(f.name for f in tmp_path.iterdir()) == ["g.npy"]
    assert main(["build", str(tmp_path / "g.npy"), "-o", str(tmp_path / "f.sdpf"), "--voxel-size", "0.01",
                 "--memory-limit", str(need + 2**20)]) == 2  # room for the points, not for these blocks
    err = capsys.readouterr().err
    assert "would need" in err and "limit less" in err and "500,000 points" in err
    assert not (tmp_path / "f.sdpf").exists()


def test_a_tile_refusal_names_the_workers_share_of_the_limit(tmp_path, cloud, monkeypatch):
    monkeypatch.setattr("sdp.scale._session._connect", lambda *a: pytest.fail("reached Dask"))
    with pytest.raises(sdp.GridTooLargeError, match=r"a task's share \(1.51 GB\) of the memory limit of 4 GB \(less "
                       r"485 MB for the command, over 2 worker\(s\), less 256 MB for the worker itself\): .*give "
                       r"--memory-limit \d+MB or more$"):
        sdp.detect_changes_tiled(cloud, cloud, lattice=sdp.Lattice(voxel_size=0.05, sigma_voxels=1000),
                                 execution=sdp.Execution(workers=2, memory_limit="4GB", workdir=tmp_path))


def test_a_task_refusal_names_its_share_and_the_limit_whose_share_holds_it(tmp_path):
    # a tile's blocks of 319 MB were refused as "above the memory limit of 270 MB" where 1.5GB was given
    import pickle
    import re

    from sdp._core._memory import check_memory
    from sdp.scale._budget import JobBudget, TaskShare

    job = JobBudget(parse_bytes("1.5GB"), 2)
    for share in (TaskShare(job), pickle.loads(pickle.dumps(TaskShare(job)))):  # as a Dask worker gets it
        with pytest.raises(sdp.GridTooLargeError, match=r"above a task's share \(270 MB\) of the memory limit of 1.5 "
                                                        r"GB \(less .*\): .*give --memory-limit \d+MB or more$") as err:
            check_memory(319 * 2**20, "a tile's blocks", share)
        limit = int(re.search(r"--memory-limit (\d+)MB", str(err.value)).group(1)) * 2**20
        assert JobBudget(limit, 2).task >= 319 * 2**20 > JobBudget(limit - 2**20, 2).task
    # tiles sized from the share grow with the limit: their edge is given with it
    with pytest.raises(sdp.GridTooLargeError, match=r"give --tile-size 3.392 \(.*\) with --memory-limit \d+MB"):
        check_memory(319 * 2**20, "a tile's blocks", TaskShare(job, 3.3925, sized=True))
    # in a task: a tile's blocks beyond its share (one task at a time, in this process)
    xyz = np.random.default_rng(1).random((20_000, 3)) * [2, 2, 0.01]
    with pytest.raises(sdp.GridTooLargeError, match=r"blocks of 8³ nodes .* above a task's share \(\d+ MB\) of the "
                                                    r"memory limit of 600 MB .*give --memory-limit \d+MB or more$"):
        sdp.detect_changes_tiled(xyz, xyz, lattice=sdp.Lattice(voxel_size=0.0005), execution=sdp.Execution(
            memory_limit="600MB", tile_size=1.0, scheduler="synchronous", workdir=tmp_path))


def test_a_tile_block_directory_spans_no_more_than_the_points():
    # a 10 m scene at 1e-4 had one tile's block directory put at 61.3 TB, sized for a tile of 82 m
    from sdp.fields._lattice import BLOCK
    from sdp.scale._budget import JobBudget, TaskShare
    from sdp.scale._session import Tiling, _check_tile_directory

    lo, hi, voxel, reach = np.zeros(3), np.array([10.0, 10.0, 1.0]), 1e-4, 6
    whole = np.prod([(e / voxel + 2 * reach + 2 * BLOCK) / BLOCK for e in hi - lo]) * 5
    with pytest.raises(sdp.GridTooLargeError, match=f"would need {format_bytes(whole)}, above") as err:
        _check_tile_directory(Tiling(voxel, 102_840, 9e-4), lo, hi, reach, TaskShare(JobBudget(4 * 2**30, 2)))
    assert "TB" not in str(err.value)


@pytest.mark.parametrize("args", [["build", "g.npy", "-o", "f.sdpf"], ["mesh", "g.npy", "-o", "m.ply"],
                                  ["bool", "union", "g.npy", "g.npy", "-o", "u.sdpf"],
                                  ["series", "g.npy", "g.npy", "-o", "s.zarr"]])
def test_every_command_counts_the_process_in_the_limit(tmp_path, cloud, capsys, args):
    """The same limit is refused alike by the commands that build fields or a series: the process
    itself does not fit in 100 MB (`sdp change` counts it too)."""
    from sdp.cli._main import main

    np.save(tmp_path / "g.npy", cloud)
    here = [str(tmp_path / a) if a.endswith((".npy", ".sdpf", ".ply", ".zarr")) else a for a in args]
    assert main([*here, "--memory-limit", "100MB"]) == 2
    assert "the process itself needs about" in capsys.readouterr().err
    assert sorted(f.name for f in tmp_path.iterdir()) == ["g.npy"]


def _field():
    return sdp.DensityField.from_points(np.random.default_rng(0).random((500, 3)), voxel_size=0.05)


@pytest.mark.parametrize("call", [
    lambda: sdp.Lattice(k=None),
    lambda: sdp.detect_changes(np.random.rand(50, 3), np.random.rand(50, 3), lattice=sdp.Lattice(voxel_size=1e300)),
    lambda: sdp.threshold("x"),
    lambda: sdp.threshold(-5),
    lambda: sdp.Coverage(enabled="false"),
    lambda: sdp.Coverage(sensor_origin=(0, 0, 1e300)),
    lambda: sdp.Execution(tiled="no"),
    lambda: sdp.Execution(workdir=0),
    lambda: sdp.Outputs(both="no"),
    lambda: sdp.Outputs(png=0),
    lambda: sdp.Registration(method="density", fix_horizontal="no"),
    lambda: sdp.detect_changes(np.random.rand(50, 3), np.random.rand(50, 3), regions="no"),
    lambda: sdp.detect_changes(np.random.rand(50, 3) + 0j, np.random.rand(50, 3)),
    lambda: _field().interpolate(np.zeros((3, 512), np.float32), np.zeros((1, 3))),
    lambda: _field().with_threshold(h=-1),
    lambda: _field().scale(float("nan")),
    lambda: _field().mesh(level="x"),
    lambda: sdp.extract_surface(np.zeros((5, 3))),
    lambda: sdp.footprint_covered(np.zeros((5, 3)), np.zeros((5, 3))),
    lambda: sdp.render_changes("x.ply", np.random.rand(10, 3), np.zeros(10, bool)),
    lambda: sdp.render_changes("x.png", np.random.rand(10, 3), np.zeros(3, bool)),
    lambda: sdp.align(np.random.rand(50, 3), np.random.rand(50, 3), levels=2.5),
    lambda: sdp.transform_points(np.eye(3), np.zeros((2, 3))),
    lambda: list(sdp.watch(np.random.rand(50, 3), 5)),
    lambda: list(sdp.watch(np.random.rand(50, 3), [np.random.rand(50, 3)], regions="no")),
    lambda: list(sdp.watch(np.random.rand(50, 3), [np.random.rand(50, 3)], window=2.5)),
    lambda: list(sdp.watch(np.random.rand(50, 3), [np.random.rand(50, 3)], update="decay", decay="x")),
    lambda: sdp.detect_changes_tiled(np.random.rand(50, 3), np.random.rand(50, 3), execution={"tiled": True}),
    lambda: sdp.series([np.random.rand(50, 3)] * 2, output=3),
    # accepted and ignored: refused, as watch refuses window without update="window"
    lambda: sdp.detect_changes(np.random.rand(50, 3), np.random.rand(50, 3), decision="point", cluster_fraction=0.9),
    lambda: sdp.detect_changes(np.random.rand(50, 3), np.random.rand(50, 3), regions=False, min_region_points=1000),
    lambda: sdp.write_points("x.ply", np.zeros((2, 3)), fields=[1, 2]),
    lambda: sdp.write_points("x.ply", np.zeros((2, 3)), like=np.zeros((2, 3))),
    lambda: sdp.scores([1, 0, 1], [1, 0, 0], comparable=[0, 1, 2]),
    lambda: sdp.render_field("slices.jpg", _field()),
])
def test_the_python_api_refuses_odd_values_in_one_line(call, tmp_path, monkeypatch):
    # each once ended in a raw TypeError, ValueError, OverflowError or AttributeError, or went on
    # with a wrong answer (a string "false" as True, values read past their rows, h < 0)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(sdp.SDPError) as refused:
        call()
    assert "\n" not in str(refused.value)
    assert not list(tmp_path.iterdir())


def test_numbers_given_as_text_are_kept_as_the_numbers_checked():
    # Execution(tile_size="0.5") passed its check, then met arithmetic as text in the tiles (a raw TypeError)
    e = sdp.Execution(tile_size="0.5", tile_points="1000", workers="1")
    assert (e.tile_size, e.tile_points, e.workers) == (0.5, 1000, 1) and isinstance(e.workers, int)
    rng = np.random.default_rng(0)
    ref, frame = rng.random((500, 3)), rng.random((500, 3))
    lattice = sdp.Lattice(voxel_size=0.05)
    for update, kw in (("window", ("window", "3")), ("decay", ("decay", "0.5"))):  # "3" < 1 was a raw TypeError
        text = list(sdp.watch(ref, [frame] * 3, lattice=lattice, update=update, **dict([kw])))
        number = list(sdp.watch(ref, [frame] * 3, lattice=lattice, update=update, **{kw[0]: float(kw[1])}))
        assert [f.appeared.sum() for f in text] == [f.appeared.sum() for f in number]
