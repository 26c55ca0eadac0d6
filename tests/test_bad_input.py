"""Bad files and bad output paths: one-line errors, nothing written, no input overwritten (issue 17)."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import slow_after

import sdp
from sdp.io import CloudFileError, PointSource, atomic_path, check_outputs, read_points
from sdp.io._las import las_scale_offset


def run(*args, cwd=None, env=None, timeout=120):
    return subprocess.run([sys.executable, "-m", "sdp.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, env=env, timeout=timeout)


def one_line_error(p):
    return p.returncode == 2 and p.stderr.startswith("sdp: error: ") and len(p.stderr.strip().splitlines()) == 1


@pytest.fixture
def clouds(tmp_path):
    rng = np.random.default_rng(1)
    xyz = rng.random((5000, 3))
    sdp.write_points(tmp_path / "a.laz", xyz)
    sdp.write_points(tmp_path / "a.las", xyz)
    np.save(tmp_path / "g.npy", xyz)
    (tmp_path / "t.laz").write_bytes((tmp_path / "a.laz").read_bytes()[:400])
    (tmp_path / "t.las").write_bytes((tmp_path / "a.las").read_bytes()[:3000])
    import laspy

    laspy.LasData(laspy.LasHeader(point_format=3, version="1.4")).write(str(tmp_path / "header_only.las"))
    return tmp_path


def test_bad_pcd_header_is_one_line(tmp_path):
    bad = tmp_path / "bad.pcd"
    bad.write_text("VERSION .7\nFIELDS x y z\nDATA ascii\n1 2 3\n")  # pydantic lists five missing fields
    with pytest.raises(CloudFileError, match=r"bad.pcd: can't read as pcd .*SIZE: Field required.*and 2 more") as e:
        read_points(bad)
    assert "\n" not in str(e.value) and "pydantic.dev" not in str(e.value)


@pytest.mark.parametrize("name, match", [
    ("t.laz", r"t.laz: truncated: the LAS header puts the points at byte"),
    ("t.las", r"t.las: truncated: the LAS header announces 5,000 points"),
    ("header_only.las", r"header_only.las: holds no point"),
])
def test_cut_or_empty_las_is_refused_by_both_readers(clouds, name, match):
    with pytest.raises(CloudFileError, match=match):
        read_points(clouds / name)
    with pytest.raises(CloudFileError, match=match):
        PointSource.open(clouds / name)


def test_truncated_laz_in_chunks_names_the_file(clouds):
    whole = (clouds / "a.laz").read_bytes()
    src = PointSource.open(clouds / "a.laz")
    (clouds / "a.laz").write_bytes(whole[:len(whole) // 2])  # cut after opening: a worker reading slices
    with pytest.raises(CloudFileError, match="a.laz: can't read as las"):
        for _ in src.chunks(1000):
            pass


def test_directory_and_unknown_format(tmp_path):
    (tmp_path / "d.ply").mkdir()
    with pytest.raises(CloudFileError, match="is a directory, not a point-cloud file"):
        read_points(tmp_path / "d.ply")
    with pytest.raises(CloudFileError, match="is a directory"):
        PointSource.open(tmp_path / "d.ply")
    np.save(tmp_path / "g.npy", np.zeros((3, 3)))
    with pytest.raises(CloudFileError, match="unknown format 'foo'"):
        read_points(tmp_path / "g.npy", format="foo")


@pytest.mark.parametrize("args", slow_after(1, [
    ["build", "t.laz", "-o", "t.zarr", "--voxel-size", "0.1"],
    ["build", "header_only.las", "-o", "e.zarr", "--voxel-size", "0.1"],
    ["info", "t.las"],
    ["info", "a.las", "--format", "foo"],
]))
def test_cli_bad_files(clouds, args):
    before = sorted(os.listdir(clouds))
    p = run(*args, cwd=clouds)
    assert one_line_error(p), p.stderr
    assert sorted(os.listdir(clouds)) == before


def test_wide_clouds_are_written_as_las(tmp_path):
    rng = np.random.default_rng(2)
    xyz = rng.random((200, 3)) * [5e6, 10, 1e9] + [0, 0, -3e8]  # wider than 2**31 mm along x and z
    sdp.write_points(tmp_path / "w.las", xyz)
    back = read_points(tmp_path / "w.las").xyz
    scales, _ = las_scale_offset(xyz.min(0), xyz.max(0))
    assert list(scales) == [0.01, 0.001, 1.0]
    assert (np.abs(back - xyz) <= scales / 2 + 1e-9).all()
    src = PointSource.open(np.save(tmp_path / "w.npy", xyz) or tmp_path / "w.npy")
    sdp.write_points_streamed(tmp_path / "s.laz", src, lambda a, b: {"change": np.zeros(b - a, np.uint8)})
    assert np.abs(read_points(tmp_path / "s.laz").xyz - xyz).max() <= 0.5


def test_align_refuses_too_few_points_and_tiny_references(rng):
    ref = rng.random((2000, 3))
    for cur in (ref[:1], ref[:3], np.repeat(ref[:2], 20, axis=0)):
        with pytest.raises(sdp.InvalidPointsError, match="too few to align"):
            sdp.align(ref, cur)
    with pytest.raises(sdp.GridTooLargeError, match="would need"):
        sdp.align(rng.random((100, 3)) * 1e-9, ref)


def test_check_outputs(tmp_path):
    src = tmp_path / "in.ply"
    src.write_text("x")
    (tmp_path / "dir.ply").mkdir()
    os.link(src, tmp_path / "hard.ply")
    for outputs, match in [([tmp_path / "nodir" / "o.ply"], "does not exist"),
                           (["/sys/o.ply"], "can't create files in '/sys'"),
                           ([tmp_path / "dir.ply"], "is an existing directory"),
                           ([src], "refusing to overwrite an input"),
                           ([tmp_path / "hard.ply"], "refusing to overwrite an input"),
                           ([tmp_path / "." / "in.ply"], "refusing to overwrite an input"),
                           ([tmp_path / "x.png", tmp_path / "x.png"], "given for two outputs")]:
        with pytest.raises(sdp.SDPError, match=match):
            check_outputs(outputs, [src])
    check_outputs([tmp_path / "new.ply", None], [src])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.ply", "hard.ply", "in.ply"]


def test_atomic_path_leaves_nothing_on_any_exception(tmp_path):
    for exc in (ValueError, KeyboardInterrupt, SystemExit):
        with pytest.raises(exc), atomic_path(tmp_path / "o.ply") as tmp:
            tmp.write_text("partial")
            raise exc()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args", slow_after(1, [
    ["build", "g.npy", "-o", "nodir/o.sdpf"],
    ["mesh", "f.sdpf", "-o", "/sys/o.ply"],
    ["mesh", "f.sdpf", "-o", "existing_dir.ply"],
    ["render", "lab.ply", "--png", "nodir/x.png"],
    ["render", "lab.ply", "--png", "lab.ply"],
    ["render", "f.sdpf", "--png", "f.sdpf"],
    ["render", "lab.ply", "--png", "x.png", "--html", "x.png"],
    ["bool", "union", "f.sdpf", "g.npy", "-o", "f.sdpf"],
    ["align", "g.npy", "g.npy", "-o", "g.npy"],
    ["align", "g.npy", "g.npy", "-o", "nodir/T.txt"],
    ["align", "g.npy", "few.npy", "-o", "T.txt"],
    ["change", "g.npy", "g2.npy", "-o", "o.ply", "--png", "g2.npy"],
    ["change", "g.npy", "g2.npy", "-o", "x.png", "--png", "x.png"],
    ["change", "o_disappeared.ply", "g2.npy", "-o", "o.ply", "--both"],  # OUT_disappeared is the reference
    ["change", "g.npy", "g2.npy", "-o", "o.ply", "--both", "--png", "o_disappeared.ply"],
    ["change", "g.npy", "g2.npy", "-o", "o.ply", "--png", "nodir/x.png"],
    ["change", "g.npy", "g2.npy", "-o", "o.ply", "--report", "g.npy"],
    ["change", "g.npy", "g2.npy", "-o", "o.laz", "--report", "r.html", "--tiled"],
    ["distance", "g.npy", "g2.npy", "-o", "d.ply", "--report", "d.ply"],
    ["change", "g.npy", "g2.npy", "-o", "nodir/o.ply"],
    ["change", "g.npy", "g2.npy", "-o", "existing_dir.ply"],
    ["change", "g.npy", "g2.npy", "-o", "o.ply", "--voxel-size", "0.001", "--memory-limit", "1MB"],  # tiles: LAS
    ["action", "train", ".", "-o", "nodir/model.npz"],
]))
def test_cli_output_paths_are_checked_first(tmp_path, args):
    xyz = np.random.default_rng(3).random((3000, 3))
    np.save(tmp_path / "g.npy", xyz)
    np.save(tmp_path / "few.npy", xyz[:3])
    np.save(tmp_path / "g2.npy", xyz + 0.01)
    sdp.write_points(tmp_path / "o_disappeared.ply", xyz)
    sdp.write_points(tmp_path / "lab.ply", xyz, {"change": (xyz[:, 0] > 0.5).astype(np.uint8)})
    sdp.DensityField.from_points(xyz, voxel_size=0.05).save(tmp_path / "f.sdpf")
    (tmp_path / "existing_dir.ply").mkdir()
    before = {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()}
    p = run(*args, cwd=tmp_path)
    assert one_line_error(p), p.stderr
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()} == before


# The signalled command: `python -m sdp.cli` with Ctrl-C's default handler whatever the test run's (a
# test run started in the background of a shell inherits SIGINT ignored, and Python would keep it so
# in the command), and tests/cluster_stall.py loaded, so that each of its Dask workers stops at its
# first compare tile after saying so: the test signals a run that is certainly alive, its cluster up
# and its buckets written, at a moment it knows instead of one guessed with a timer.
STALLED_COMMAND = [sys.executable, "-c", (
    "import runpy, signal; signal.signal(signal.SIGINT, signal.default_int_handler); import cluster_stall; "
    "runpy.run_module('sdp.cli', run_name='__main__', alter_sys=True)")]


def start_stalled(tmp_path, *args):
    """The tiled ``sdp`` command of ``args`` in ``tmp_path``, its temporary files in ``tmp_path/tmp``,
    its workers stalling at their first compare tile (they write into ``tmp_path/stalls``);
    returns once one of them stalled."""
    stalls, scratch = tmp_path / "stalls", tmp_path / "tmp"
    stalls.mkdir()
    scratch.mkdir()
    path = [str(Path(__file__).parent), *filter(None, [os.environ.get("PYTHONPATH")])]  # the hook, for the workers too
    env = dict(os.environ, TMPDIR=str(scratch), SDP_TEST_STALL=str(stalls), PYTHONPATH=os.pathsep.join(path))
    p = subprocess.Popen([*STALLED_COMMAND, *args], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        while not any(stalls.iterdir()):  # the event, or the run's end (a failure)
            if p.poll() is not None:
                raise AssertionError(f"the run ended (status {p.returncode}) before it held a compare tile: "
                                     f"{p.communicate()[1]}")
            time.sleep(0.02)
    except BaseException:
        p.kill()
        p.communicate()
        raise
    return p


def assert_nothing_left(tmp_path, inputs):
    """Only the inputs and the test's own folders in the command's folder (no output, no hidden
    temporary one), and no work folder of the tiles left in its temporary folder."""
    assert sorted(f.name for f in tmp_path.iterdir()) == sorted([*inputs, "stalls", "tmp"])
    assert not [f.name for f in (tmp_path / "tmp").iterdir() if f.name.startswith("sdp-tiles-")]


def signalled_clouds(tmp_path, *names):
    rng = np.random.default_rng(4)
    for name in names:
        np.save(tmp_path / name, rng.random((20_000, 3)) * [20, 20, 2])


@pytest.mark.slow
def test_sigterm_on_the_tiled_path_cleans_up(tmp_path):
    signalled_clouds(tmp_path, "a.npy", "b.npy")
    p = start_stalled(tmp_path, "change", "a.npy", "b.npy", "-o", "o.laz", "--tiled", "--voxel-size", "0.1", "-q")
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=300)  # a guard against a hang, not a measure of speed
    assert p.returncode == 128 + signal.SIGTERM and err == "sdp: terminated\n" and out == "", err
    assert_nothing_left(tmp_path, ["a.npy", "b.npy"])


@pytest.mark.slow
def test_interrupt_is_one_line(tmp_path):
    signalled_clouds(tmp_path, "a.npy")
    p = start_stalled(tmp_path, "change", "a.npy", "a.npy", "-o", "o.laz", "--tiled", "--voxel-size", "0.1", "-q",
                      "--workers", "1")
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=300)  # a guard against a hang, not a measure of speed
    assert p.returncode == 130 and err == "sdp: interrupted\n" and out == "", err
    assert_nothing_left(tmp_path, ["a.npy"])


def test_corrupt_las_counts_are_refused_before_laspy_loops_or_lazrs_aborts(clouds):
    import struct

    data = bytearray((clouds / "a.laz").read_bytes())
    vlrs = bytearray(data)
    vlrs[100:104] = struct.pack("<I", 134_217_729)  # laspy would loop over 1.3e8 records
    (clouds / "vlrs.laz").write_bytes(bytes(vlrs))
    offset = struct.unpack_from("<I", data, 96)[0]
    table = struct.unpack_from("<q", data, offset)[0]
    chunks = bytearray(data)
    chunks[table + 4:table + 8] = struct.pack("<I", 4_213_908_307)  # lazrs would allocate 67 GB and abort
    (clouds / "chunks.laz").write_bytes(bytes(chunks))
    for name, match in (("vlrs.laz", "records do not fit"), ("chunks.laz", "corrupt LAZ chunk table")):
        with pytest.raises(CloudFileError, match=match):
            read_points(clouds / name)
        with pytest.raises(CloudFileError, match=match):
            PointSource.open(clouds / name)


def test_a_command_writes_all_its_outputs_or_none(tmp_path):
    from sdp.io import all_or_none

    xyz = np.random.default_rng(6).random((100, 3))
    with pytest.raises(RuntimeError), all_or_none():
        sdp.write_points(tmp_path / "first.ply", xyz)
        assert not (tmp_path / "first.ply").exists()  # kept under its temporary name until the end
        raise RuntimeError("the second output failed")
    assert list(tmp_path.iterdir()) == []
    with all_or_none():
        sdp.write_points(tmp_path / "first.ply", xyz)
        sdp.write_points(tmp_path / "second.npz", xyz)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["first.ply", "second.npz"]
