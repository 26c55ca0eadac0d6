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
    (tmp_path / "d").mkdir()
    for name in ("d.ply", "d"):  # a folder is a folder, whatever its name's extension
        with pytest.raises(CloudFileError, match="is a folder, not a point-cloud file"):
            read_points(tmp_path / name)
    with pytest.raises(CloudFileError, match="is a folder"):
        PointSource.open(tmp_path / "d.ply")
    (tmp_path / "f.sdpf").write_bytes(b"")
    with pytest.raises(CloudFileError, match="a density field .* not a point cloud"):
        read_points(tmp_path / "f.sdpf")
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


def test_close_points_keep_their_places_in_las(tmp_path):
    """A millimetre-sized object in metres (points 0.1–0.3 mm apart) is written at a scale finer than
    its spacing, in memory and chunk by chunk: no two points merge, none moves by more than a
    twentieth of the spacing; a centimetre-spaced scan keeps LAS's usual 1 mm."""
    from sdp.io._las import coordinate_scale

    rng = np.random.default_rng(5)
    small = rng.normal(0, 0.01, (20_000, 3)) + [2.0, -3.0, 0.5]  # a 4 cm ball of points
    assert coordinate_scale(small) <= 1e-5
    sdp.write_points(tmp_path / "s.las", small)
    src = PointSource.open(np.save(tmp_path / "s.npy", small) or tmp_path / "s.npy")
    sdp.write_points_streamed(tmp_path / "t.laz", src, lambda a, b: {"change": np.zeros(b - a, np.uint8)})
    for name in ("s.las", "t.laz"):
        back = read_points(tmp_path / name).xyz
        assert len(np.unique(back, axis=0)) == len(small) and np.abs(back - small).max() <= 5e-6
    room = rng.uniform(0, 4, (20_000, 3))  # about 2 cm apart
    assert coordinate_scale(room) == 0.001


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
    ["change", "g.npy", "g2.npy", "-o", "o.ply", "--png", "x.jpg"],  # a picture named as another format
    ["distance", "g.npy", "g2.npy", "-o", "d.ply", "--report", "d.pdf"],
    ["render", "lab.ply", "--html", "x.png"],
    ["series", "g.npy", "g2.npy", "-o", "s.foo"],  # an archive is a .zarr folder
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


def start_stalled(tmp_path, *args, stage="compare"):
    """The tiled ``sdp`` command of ``args`` in ``tmp_path``, its temporary files in ``tmp_path/tmp``,
    held at ``stage`` (tests/cluster_stall.py: a worker's first bucket or compare task, or the
    command's streamed writer); returns (process, pid of the process held) once it is held."""
    stalls, scratch = tmp_path / "stalls", tmp_path / "tmp"
    stalls.mkdir()
    scratch.mkdir()
    path = [str(Path(__file__).parent), *filter(None, [os.environ.get("PYTHONPATH")])]  # the hook, for the workers too
    env = dict(os.environ, TMPDIR=str(scratch), SDP_TEST_STALL=str(stalls), SDP_TEST_STALL_AT=stage,
               PYTHONPATH=os.pathsep.join(path))
    p = subprocess.Popen([*STALLED_COMMAND, *args], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    try:
        while not any(stalls.iterdir()):  # the event, or the run's end (a failure)
            if p.poll() is not None:
                raise AssertionError(f"the run ended (status {p.returncode}) before it was held at {stage}: "
                                     f"{p.communicate()[1]}")
            time.sleep(0.02)
    except BaseException:
        p.kill()
        p.communicate()
        raise
    return p, int(next(stalls.iterdir()).name.split("-")[1])


def assert_nothing_left(tmp_path, inputs):
    """Only the inputs and the test's own folders in the command's folder (no output, no hidden
    temporary one), and no work folder of the tiles, nor Dask's scratch space, in its temporary folder."""
    assert sorted(f.name for f in tmp_path.iterdir()) == sorted([*inputs, "stalls", "tmp"])
    assert not [f.name for f in (tmp_path / "tmp").iterdir() if f.name.startswith(("sdp-tiles-", "dask-"))]


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def signalled_clouds(tmp_path, *names):
    rng = np.random.default_rng(4)
    for name in names:
        np.save(tmp_path / name, rng.random((20_000, 3)) * [20, 20, 2])


@pytest.mark.slow
@pytest.mark.parametrize("stage, sig", [("bucket", signal.SIGINT), ("compare", signal.SIGTERM),
                                        ("write", signal.SIGINT)])
def test_a_signal_stops_a_tiled_run_at_any_stage_and_leaves_nothing(tmp_path, stage, sig):
    signalled_clouds(tmp_path, "a.npy", "b.npy")
    p, held = start_stalled(tmp_path, "change", "a.npy", "b.npy", "-o", "o.laz", "--tiled", "--voxel-size", "0.1",
                            "-q", stage=stage)
    p.send_signal(sig)
    out, err = p.communicate(timeout=300)  # a guard against a hang, not a measure of speed
    word = "interrupted" if sig == signal.SIGINT else "terminated"
    assert p.returncode == 128 + sig and err == f"sdp: {word}\n" and out == "", err
    assert_nothing_left(tmp_path, ["a.npy", "b.npy"])
    # the worker held in its task (60 s) was stopped, not waited for
    assert not alive(held)


@pytest.mark.slow
def test_interrupt_is_one_line(tmp_path):
    signalled_clouds(tmp_path, "a.npy")
    p, _ = start_stalled(tmp_path, "change", "a.npy", "a.npy", "-o", "o.laz", "--tiled", "--voxel-size", "0.1", "-q",
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


# --- Every promise holds, round 2 (issue 32) -------------------------------------------------------


@pytest.fixture
def pre(tmp_path):
    """The issue's two clouds: 2,000 points, and the same with 300 more in a box."""
    rng = np.random.default_rng(0)
    a = rng.random((2000, 3))
    np.save(tmp_path / "a.npy", a)
    np.save(tmp_path / "b.npy", np.r_[a, rng.random((300, 3)) * 0.2 + 0.4])
    return tmp_path


@pytest.mark.parametrize("name", slow_after(1, ["OUT.NPZ", "out.Npz"]))
def test_npz_in_any_case_holds_the_data_and_leaves_nothing_else(pre, name):
    (pre / name).write_bytes(b"old")
    p = run("change", "a.npy", "b.npy", "-o", name, "--both", "-q", cwd=pre)
    assert p.returncode == 0, p.stderr
    with np.load(pre / name) as z:
        assert len(z["xyz"]) == 2300 and len(z["change"]) == 2300
    assert sorted(f.name for f in pre.iterdir()) == sorted(["a.npy", "b.npy", name, disappeared_name(name)])
    sdp.write_points(pre / "x.NPZ", np.ones((3, 3)))
    assert np.load(pre / "x.NPZ")["xyz"].shape == (3, 3) and not list(pre.glob(".*"))


def disappeared_name(name):
    stem, ext = name.rsplit(".", 1)
    return f"{stem}_disappeared.{ext}"


def test_unusual_numpy_files_are_read_or_refused_in_one_line(tmp_path):
    rng = np.random.default_rng(1)
    s = np.zeros(50, dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"), ("intensity", "u2")])
    s["x"], s["intensity"] = rng.random(50), 7
    np.save(tmp_path / "structured.npy", s)
    cloud = read_points(tmp_path / "structured.npy")
    assert np.array_equal(cloud.xyz[:, 0], s["x"]) and (cloud.fields["intensity"] == 7).all()
    np.save(tmp_path / "complex.npy", rng.random((10, 3)) + 1j)
    with open(tmp_path / "archive.npy", "wb") as fh:
        np.savez(fh, xyz=rng.random((10, 3)))
    for name, message in (("complex.npy", "coordinates of type complex128"), ("archive.npy", "an NPZ archive")):
        p = run("info", name, cwd=tmp_path)
        assert one_line_error(p) and name in p.stderr and message in p.stderr, p.stderr


def test_header_counts_must_match_the_data_in_both_directions(tmp_path):
    import struct

    head = "VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {0}\nHEIGHT 1\n" \
           "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {0}\nDATA ascii\n"
    rows = "".join(f"{i} {i} {i}\n" for i in range(10))
    (tmp_path / "short.pcd").write_text(head.format(1000) + rows)
    (tmp_path / "long.pcd").write_text(head.format(4) + rows)
    (tmp_path / "columns.pcd").write_text(head.format(10).replace("SIZE 4 4 4", "SIZE 4 4") + rows)
    xyz = np.random.default_rng(2).random((60_000, 3))  # two chunks of LAZ's 50,000
    for ext in ("las", "laz"):
        sdp.write_points(tmp_path / f"full.{ext}", xyz)
        data = bytearray((tmp_path / f"full.{ext}").read_bytes())
        struct.pack_into("<I", data, 107, 10)  # the legacy count and LAS 1.4's 64-bit one: 10 of 120,000
        struct.pack_into("<Q", data, 247, 10)
        (tmp_path / f"under.{ext}").write_bytes(bytes(data))
    struct.pack_into("<Q", data, 247, 60_000)  # the two counts of LAS 1.4 disagree
    (tmp_path / "counts.laz").write_bytes(bytes(data))
    for name, message in (("short.pcd", "announces 1,000 points, the file holds 10"),
                          ("long.pcd", "announces 4 points, the file holds 10"),
                          ("columns.pcd", "FIELDS 3, SIZE 2"),
                          ("under.las", "announces 10 points, the file holds 60,000"),
                          ("under.laz", "announces 10 points, the LAZ chunk table holds 2 chunks"),
                          ("counts.laz", "it counts 10 points and 60,000")):
        with pytest.raises(CloudFileError, match=message):
            read_points(tmp_path / name)
    p = run("info", "short.pcd", cwd=tmp_path)  # the command says the same in one line
    assert one_line_error(p) and "announces 1,000 points" in p.stderr, p.stderr
    assert len(read_points(tmp_path / "full.laz")) == 60_000


def slow_after_pairs(n, cases):
    """:func:`conftest.slow_after` for cases of two parameters."""
    return [pytest.param(*c, marks=[pytest.mark.slow] if i >= n else []) for i, c in enumerate(cases)]


@pytest.mark.parametrize("args, message", slow_after_pairs(3, [
    (["change", "a.npy", "b.npy", "-o", "o.ply", "--voxel-size", "1e-300"], "1e+300 voxels of 1e-300"),
    (["change", "a.npy", "far.npy", "-o", "o.ply", "--voxel-size", "1"], "voxels of 1 from the origin"),
    (["change", "a.npy", "b.npy", "-o", "o.ply", "--h", "1e308"], "float32 range"),
    (["distance", "a.npy", "b.npy", "-o", "o.ply", "--orientation", "nan,0,1"], "three finite numbers X,Y,Z"),
    (["distance", "a.npy", "b.npy", "-o", "o.ply", "--orientation", "0,0,0"], "not all zero; got '0,0,0'"),
    (["distance", "a.npy", "b.npy", "-o", "o.ply", "--normal-scale", "1e-9"], "give a larger normal_scale"),
    (["change", "a.npy", "b.npy", "-o", "o.ply", "--memory-limit", "-5GB"], "can't read memory size '-5GB'"),
    (["change", "a.npy", "b.npy", "-o", "o.laz", "--tiled", "--workdir", "/proc"], "/proc': can't create folders"),
    (["change", "a.npy", "b.npy", "-o", "o.ply", "--tiled"], "--tiled streams its output to LAS/LAZ"),
    (["change", "a.npy", "b.npy", "-o", "o.ply", "--aligned-output"], "give --align too"),
    (["watch", "a.npy", "frames", "--decay", "0.5"], "decay applies to update='decay' only"),
    (["distance", "a.npy", "b.npy", "-o", "o.ply", "--orientation", "1,0,0", "--sensor-origin", "0,0,1"],
     "--orientation points the normals where no sensor is known"),
    (["change", "a.npy", "b.npy", "-o", "o.ply", "--sensor-origin", "none", "--range-noise", "0.01"],
     "range_noise is the sensor rays' band"),
    (["watch", "a.npy", "frames", "--update", "none", "--window", "3"], "window applies to update='window' only"),
    (["bool", "union", "a.sdpf", "b.npy", "-o", "u.sdpf", "--voxel-size", "0.5"], "a field sets the lattice"),
    (["mesh", "a.sdpf", "-o", "m.ply", "--sigma-voxels", "5"], "a field sets the lattice"),
    (["bool", "difference", "a.npy", "a.npy", "-o", "d.ply"], "the difference holds no volume"),
    (["watch", "a.sdpf", "frames", "--voxel-size", "0.5"], "a field sets the lattice"),
    (["change", "a.npy", "b.npy", "-o", "o.ply", "--h", "2", "-k", "4"], "give k or h, not both"),
    (["align", "a.npy", "far.npy", "-o", "al.txt"], "the clouds do not overlap"),
    (["align", "a.npy", "b.npy", "-o", "al.ply"], "written as a 4x4 text matrix, not as .ply"),
    (["change", "a.npy", "b.npy", "-o", "o.ply", "-o", "p.ply"], "-o given twice (-o o.ply, -o p.ply): give it once"),
    (["change", "a.npy", "b.npy", "-o", "o.ply", "--voxel-size", "0.1", "--voxel=0.2"], "--voxel-size given twice"),
    (["action", "predict", "model.npz", "empty.mat"], "empty.mat: can't read a depth sequence"),
]))
def test_options_and_inputs_round_2_are_one_line_errors(pre, args, message):
    a = np.load(pre / "a.npy")
    np.save(pre / "far.npy", np.r_[a, [[1.7e308] * 3]] if "--voxel-size" in args else a + 100)
    (pre / "frames").mkdir()
    np.save(pre / "frames" / "f.npy", a)
    (pre / "empty.mat").write_bytes(b"")
    sdp.DensityField.from_points(a, voxel_size=0.1).save(pre / "a.sdpf")
    sdp.actions.ActionModel(coef=np.zeros((2, 3), np.float32), intercept=np.zeros(2), classes=np.arange(1, 3),
                            alpha=(1.0,)).save(pre / "model.npz")
    before = sorted(f.name for f in pre.iterdir())
    p = run(*args, cwd=pre)
    assert one_line_error(p) and message in p.stderr, p.stderr
    assert sorted(f.name for f in pre.iterdir()) == before


def test_values_starting_with_a_dash_are_values():
    from sdp.cli._main import _dash_values, build_parser

    parser = build_parser()
    argv = ["distance", "a.npy", "b.npy", "-o", "d.ply", "--orientation", "-1,0,0", "-q"]
    args = parser.parse_args(_dash_values(parser, argv))
    assert args.orientation == "-1,0,0" and args.quiet and args.output == "d.ply"


@pytest.mark.parametrize("fields, message", [
    ({"a": np.ones(3)}, "field 'a' must hold one real number per point"),
    ({"a": np.ones((10, 2))}, "field 'a' must hold one real number per point"),
    ({"x": np.ones(10)}, "other than x, y, z"),
    ({"a b": np.ones(10)}, "PLY names have no space"),
])
def test_write_points_refuses_bad_fields_with_an_sdp_error(tmp_path, fields, message):
    with pytest.raises(sdp.InvalidPointsError, match=message):
        sdp.write_points(tmp_path / "o.ply", np.random.default_rng(3).random((10, 3)), fields)
    with pytest.raises(sdp.InvalidPointsError, match="an \\(n, 3\\) array"):
        sdp.write_points(tmp_path / "o.ply", np.ones((10, 2)))
    with pytest.raises(sdp.InvalidPointsError, match="at most 32 characters"):
        sdp.write_points(tmp_path / "o.las", np.ones((10, 3)), {"a" * 33: np.ones(10)})
    with pytest.raises(sdp.CloudFileError, match=r"/o.las: can.t write non-finite"):
        sdp.write_points(tmp_path / "o.las", np.full((10, 3), np.inf))
    with pytest.raises(sdp.InvalidOptionError, match="three finite numbers"):
        sdp.distances(np.ones((10, 3)), np.ones((10, 3)), orientation="up")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_a_full_stdout_writes_nothing_and_a_closed_one_writes_all(pre):
    with open("/dev/full", "w") as full:
        p = subprocess.run([sys.executable, "-m", "sdp.cli", "change", "a.npy", "b.npy", "-o", "o.ply"], cwd=pre,
                           stdout=full, stderr=subprocess.PIPE, text=True, timeout=120)
    assert one_line_error(p) and "standard output: No space left on device" in p.stderr, p.stderr
    assert not (pre / "o.ply").exists() and not list(pre.glob(".o.ply*"))
    shell = subprocess.run(f"{sys.executable} -m sdp.cli change a.npy b.npy -o o.ply --json | head -c 1", shell=True,
                           cwd=pre, capture_output=True, text=True, timeout=120)
    assert shell.stdout == "{" and (pre / "o.ply").exists()


@pytest.mark.slow  # the quick tier keeps lighter tests of the same module
def test_json_is_strict_and_eval_compares_the_same_points(pre):
    import json

    a = np.load(pre / "a.npy")
    sdp.write_points(pre / "truth.ply", a, {"change": np.zeros(2000, np.uint8)})
    sdp.write_points(pre / "reversed.ply", a[::-1], {"change": np.zeros(2000, np.uint8)})
    nan = np.zeros(2000)
    nan[5] = np.nan
    sdp.write_points(pre / "nan.ply", a, {"change": nan})
    sdp.write_points(pre / "wide.npz", a, {"change": np.zeros(2000)})
    with np.load(pre / "wide.npz") as z:
        np.savez(pre / "wide.npz", xyz=z["xyz"], change=np.zeros((2000, 2)))
    p = run("eval", "truth.ply", "truth.ply", "--json", cwd=pre)
    assert p.returncode == 0 and "NaN" not in p.stdout and json.loads(p.stdout)["kappa"] is None, p.stdout
    for other, message in (("reversed.ply", "not the same points in the same order"),
                           ("nan.ply", "1 labels that are not numbers"), ("wide.npz", "holds (2,) values per point")):
        p = run("eval", "truth.ply", other, cwd=pre)
        assert one_line_error(p) and message in p.stderr, p.stderr


@pytest.mark.slow
def test_a_full_work_folder_is_one_line(pre):
    # a file-size limit stands for a full disk: the bucket writes fail short, as on a full work folder
    limit = "import resource, signal; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); " \
            "resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000)); "
    big = np.random.default_rng(5).random((40_000, 3)) * [20, 20, 2]
    np.save(pre / "big.npy", big)
    p = subprocess.run([sys.executable, "-c", limit + "import runpy; runpy.run_module('sdp.cli', run_name='__main__', "
                        "alter_sys=True)", "change", "big.npy", "big.npy", "-o", "o.laz", "--tiled",
                        "--voxel-size", "0.1", "-q", "--workdir", str(pre)], cwd=pre, capture_output=True, text=True,
                       timeout=300)
    assert one_line_error(p) and "can't write a tile's points" in p.stderr and "disk full" in p.stderr, p.stderr
    assert sorted(f.name for f in pre.iterdir()) == ["a.npy", "b.npy", "big.npy"]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["o.laz", "o.las", "o.ply"])
def test_an_output_on_a_full_disk_is_one_line(tmp_path, name):
    # a file-size limit stands for a full disk; lazrs reports its failed writes as its own error
    limit = "import resource, signal; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); " \
            "resource.setrlimit(resource.RLIMIT_FSIZE, (30_000, 30_000)); "
    np.save(tmp_path / "a.npy", np.random.default_rng(7).random((20_000, 3)))
    p = subprocess.run([sys.executable, "-c", limit + "import runpy; runpy.run_module('sdp.cli', run_name='__main__', "
                        "alter_sys=True)", "change", "a.npy", "a.npy", "-o", name, "-q"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert one_line_error(p) and f"{name}: can't write" in p.stderr, p.stderr
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.npy"]


@pytest.mark.slow
def test_a_signal_while_laz_is_written_exits_130_with_nothing_written(tmp_path):
    # lazrs calls back into Python to write, and turns the KeyboardInterrupt raised there into its
    # own error; here the writer gets a real SIGINT and does the same: the command must still say it
    # was interrupted, in one line, and write nothing
    code = ("import os, signal, sys, time, laspy, lazrs\n"
            "def write(self, *args, **kwargs):\n"
            "    try:\n"
            "        os.kill(os.getpid(), signal.SIGINT)\n"
            "        time.sleep(5)\n"
            "    except KeyboardInterrupt:\n"
            "        raise lazrs.LazrsError('Failed to call write') from None\n"
            "laspy.LasData.write = write\n"
            "from sdp.cli import main\n"
            "sys.exit(main(sys.argv[1:]))\n")
    np.save(tmp_path / "a.npy", np.random.default_rng(7).random((3000, 3)))
    p = subprocess.run([sys.executable, "-c", code, "change", "a.npy", "a.npy", "-o", "o.laz", "-q"], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 130 and p.stderr == "sdp: interrupted\n", p.stderr
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.npy"]


@pytest.mark.slow
def test_a_successful_tiled_run_leaves_no_scratch_space(pre):
    (pre / "tmp").mkdir()
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "change", "a.npy", "b.npy", "-o", "o.laz", "--tiled", "-q"],
                       cwd=pre, capture_output=True, text=True, timeout=300, env=dict(os.environ, TMPDIR=str(pre / "tmp")))
    assert p.returncode == 0, p.stderr
    assert list((pre / "tmp").iterdir()) == []


def test_gicp_messages_become_errors(rng):
    pytest.importorskip("small_gicp")
    from sdp.registration._align import GicpTarget

    target = GicpTarget(rng.random((2000, 3)), resolution=0.05, max_distance=0.2)
    with pytest.raises(sdp.InvalidPointsError, match="GICP: warning: source point cloud is too small"):
        target.register(rng.random((3, 3)))


@pytest.mark.parametrize("args, output, says", [
    (["change", "bad.ply", "bad.ply", "-o", "o.xyz"], "o.xyz",
     "can't write points as .xyz; use .ply, .las, .laz or .npz"),
    (["distance", "bad.ply", "bad.ply", "-o", "o.txt"], "o.txt", "can't write points as .txt"),
    (["build", "bad.ply", "-o", "f.ply"], "f.ply", "can't write a density field as .ply; use .sdpf or .zarr"),
    (["mesh", "bad.ply", "-o", "m.txt"], "m.txt", "can't write a mesh as .txt; use .ply, .obj or .stl"),
    (["bool", "union", "bad.ply", "bad.ply", "-o", "u"], "u", "can't write a density field or a mesh as a file"),
    (["series", "bad.ply", "bad.ply", "-o", "s.zarr", "--epoch-output", "1:e.csv"], "e.csv", "can't write points"),
])
def test_an_output_no_writer_takes_is_refused_before_the_inputs_are_read(tmp_path, monkeypatch, capsys, args, output,
                                                                         says):
    # the input can't be read: an error naming the output shows that it was checked first
    from sdp.cli._main import main

    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"sdp: error: {output}: {says}") and len(err.strip().splitlines()) == 1, err
    assert sorted(f.name for f in tmp_path.iterdir()) == ["bad.ply"]


def test_a_missing_input_says_so_in_tiles_too(tmp_path, monkeypatch, capsys):
    from sdp.cli._main import main

    monkeypatch.chdir(tmp_path)
    assert main(["distance", "nope.laz", "nope.laz", "-o", "o.laz", "--tiled"]) == 2
    assert capsys.readouterr().err.strip() == "sdp: error: nope.laz: no such file"


@pytest.mark.parametrize("command", ["change", "distance"])
def test_a_file_announcing_more_than_memory_holds_is_refused_before_it_is_read(tmp_path, monkeypatch, capsys, command):
    # a PCD's header announces its points: 50 million of them would not fit 1 GB, whatever the file holds
    from sdp.cli._main import main

    (tmp_path / "big.pcd").write_text("VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                                      "WIDTH 50000000\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 50000000\n"
                                      "DATA ascii\n1 2 3\n")
    monkeypatch.chdir(tmp_path)
    assert main([command, "big.pcd", "big.pcd", "-o", "o.laz", "--memory-limit", "1GB"]) == 2
    err = capsys.readouterr().err
    assert ("100,000,000" if command == "change" else "50,000,000") in err and "memory limit of 1 GB" in err, err
    assert sorted(f.name for f in tmp_path.iterdir()) == ["big.pcd"]


@pytest.mark.parametrize("values, says", [
    (np.array(["0", "1"] * 5), "holds <U1 values, not numeric labels"),
    (np.array([0.5, 1.5] * 5),
     "holds values other than 0 (unchanged), 1 (changed) and 2 (not comparable), e.g. 0.5"),
])
def test_eval_refuses_labels_that_are_not_sdps(tmp_path, values, says):
    # text labels were all "changed", a change field of 0.5 or 7 all "unchanged": scores without a word
    from sdp.cli import evaluate_files

    xyz = np.random.default_rng(0).random((10, 3))
    np.savez(tmp_path / "p.npz", xyz=xyz, change=values)
    np.savez(tmp_path / "t.npz", xyz=xyz, change=np.zeros(10, np.uint8))
    import re

    with pytest.raises(sdp.SDPError, match=re.escape(f"p.npz: field 'change' {says}")):
        evaluate_files(tmp_path / "p.npz", tmp_path / "t.npz")


@pytest.mark.parametrize("args", [["-o", "new/deep", "--seed", "-5"], ["-o", ""]])
def test_the_demo_refuses_before_it_makes_a_folder(tmp_path, monkeypatch, capsys, args):
    from sdp.cli._main import main

    monkeypatch.chdir(tmp_path)
    assert main(["demo", *args]) == 2
    assert capsys.readouterr().err.startswith("sdp: error: ") and not list(tmp_path.iterdir())


def test_messages_name_the_cause_not_the_librarys_advice(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.random((3000, 3))
    np.savetxt(tmp_path / "short.xyz", np.r_[xyz[:5], [[1.0, 2.0, np.nan]], xyz[5:10]][:, :3])
    text = (tmp_path / "short.xyz").read_text().splitlines()
    text[5] = "1.0 2.0"
    (tmp_path / "short.xyz").write_text("\n".join(text) + "\n")
    noise = rng.integers(0, 256, 4096, dtype=np.uint8).tobytes()
    (tmp_path / "r.npy").write_bytes(b"\x93NUMPY\x01\x00v\x00{'descr': '|O', 'fortran_order': False, 'shape': (3,), }"
                                     .ljust(128, b" ") + noise)
    (tmp_path / "r.sdpf").write_bytes((tmp_path / "r.npy").read_bytes())
    np.save(tmp_path / "a.npy", xyz)
    (tmp_path / "a.sdpf").write_bytes((tmp_path / "a.npy").read_bytes())  # an array under a field's name
    np.savez(tmp_path / "p.npz", xyz=xyz, change=np.ones(3000))
    np.savez(tmp_path / "t.npz", xyz=xyz, change=np.ones(2999))
    for args, message in ((["info", "short.xyz"], "the number of columns changed from 3 to 2 at row 6)"),
                          (["info", "r.npy"], "not an array of numbers: random bytes or pickled Python objects"),
                          (["info", "r.sdpf"], "not a readable sdp field file (not an archive of arrays)"),
                          (["mesh", "a.sdpf", "-o", "m.ply"], "not a readable sdp field file (ValueError: an array, "),
                          (["eval", "p.npz", "t.npz"], "its array 'change' holds 2,999 values for 3,000 points")):
        p = run(*args, cwd=tmp_path)
        assert one_line_error(p) and message in p.stderr and "usecols" not in p.stderr, p.stderr
        assert "allow_pickle" not in p.stderr


def test_a_scan_in_other_units_is_asked_about(tmp_path):
    """A current in millimetres against a reference in metres compares to nothing useful: the
    summary asks, and a Kinect-sized frame against a room does not."""
    xyz = np.random.default_rng(0).random((4000, 3))
    sdp.write_points(tmp_path / "m.ply", xyz)
    sdp.write_points(tmp_path / "mm.ply", xyz * 1000)
    r = sdp.compare_files(tmp_path / "m.ply", tmp_path / "mm.ply", output=tmp_path / "o.ply")
    assert r.summary["extents"] == pytest.approx([1.0, 1000.0], rel=0.01)
    assert "are they in the same units" in r.summary_text()
    sdp.write_points(tmp_path / "part.ply", xyz[xyz[:, 0] < 0.1])
    r = sdp.compare_files(tmp_path / "m.ply", tmp_path / "part.ply", output=tmp_path / "p.ply")
    assert "extents" not in r.summary


def test_points_too_sparse_for_the_automatic_voxel_are_said_to_be_beyond_reach(tmp_path):
    """A dense object beside a sparse floor: the automatic voxel follows the object, and the floor's
    points lie outside their own cluster volume, where no change can be found: said."""
    rng = np.random.default_rng(1)
    g = np.arange(0, 2, 0.05)
    floor = np.c_[np.repeat(g, len(g)), np.tile(g, len(g)), np.zeros(len(g) ** 2)]
    dense = rng.random((60_000, 3)) * 0.2 + [0.9, 0.9, 0.0]
    sdp.write_points(tmp_path / "a.ply", np.r_[floor, dense])
    sdp.write_points(tmp_path / "b.ply", np.r_[floor, dense, floor[:200] + [0, 0, 0.3]])  # a new shelf
    r = sdp.compare_files(tmp_path / "a.ply", tmp_path / "b.ply", output=tmp_path / "o.ply")
    assert r.summary["current"]["outside_own_volume"] >= len(floor)
    assert "of the current's points lie outside its own cluster volume" in r.summary_text()
    r = sdp.compare_files(tmp_path / "a.ply", tmp_path / "b.ply", output=tmp_path / "p.ply",
                          lattice=sdp.Lattice(voxel_size=0.05))
    assert "outside its own cluster volume" not in r.summary_text() and r.summary["current"]["appeared"] > 0


def test_running_out_of_memory_while_reading_says_it_is_not_the_files_size(tmp_path, monkeypatch):
    """A stream's window can hold what the process has: a small file's read then fails for memory
    it does not take itself."""
    import sdp.io._read as R

    np.save(tmp_path / "f.npy", np.random.default_rng(0).random((100, 3)))

    def full(path):
        raise MemoryError

    monkeypatch.setitem(R._READERS, "npy", full)
    with pytest.raises(sdp.CloudFileError, match=r"out of memory reading it as npy \(0.0 MB on disk, on top of what"):
        sdp.read_points(tmp_path / "f.npy")


def test_ctrl_c_swallowed_by_a_destructor_still_stops_the_command(tmp_path, monkeypatch, capsys):
    """Python runs the signal handler wherever the main thread is, a destructor too, whose exception
    is only reported ("Exception ignored in …"): the command went on and wrote everything, exit 0,
    with that report on stderr. It now stops before its commit: exit 130, nothing written."""
    from sdp.cli import _main, main
    from sdp.io import _output

    class Finalized:
        def __del__(self):
            _main._on_signal(signal.SIGINT, None)  # Ctrl-C, its handler run in this destructor

    real = _output.write_ply

    def write_ply(*args, **kwargs):
        real(*args, **kwargs)
        Finalized()

    np.save(tmp_path / "a.npy", np.random.default_rng(7).random((3000, 3)))
    monkeypatch.setattr(_output, "write_ply", write_ply)
    assert main(["change", str(tmp_path / "a.npy"), str(tmp_path / "a.npy"), "-o", str(tmp_path / "o.ply"),
                 "-q"]) == 130
    assert capsys.readouterr().err == "sdp: interrupted\n"
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.npy"]


def test_a_signal_taken_by_another_thread_during_the_commit_waits_for_it(tmp_path, monkeypatch, capsys):
    """The renames of a command's outputs hold Ctrl-C back in the main thread only: the system may
    hand the signal to another thread, and Python runs the handler in the main thread all the same.
    It raised between two renames, and the command wrote one of its two outputs (exit 130); the
    commit now completes and the signal comes too late (exit 0, both written)."""
    from sdp.cli import _main, main

    real, renamed = os.replace, []

    def replace(src, dst, **kwargs):
        real(src, dst, **kwargs)
        renamed.append(dst)
        if len(renamed) == 1:
            _main._on_signal(signal.SIGINT, None)  # as Python runs it, whichever thread took the signal

    np.save(tmp_path / "a.npy", np.random.default_rng(7).random((3000, 3)))
    monkeypatch.setattr(os, "replace", replace)
    status = main(["change", str(tmp_path / "a.npy"), str(tmp_path / "a.npy"), "-o", str(tmp_path / "o.ply"),
                   "--both", "-q"])
    monkeypatch.undo()
    assert status == 0 and capsys.readouterr().err == ""
    assert sorted(f.name for f in tmp_path.iterdir()) == ["a.npy", "o.ply", "o_disappeared.ply"]
