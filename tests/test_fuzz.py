"""Fuzzed files of every supported format: only sdp's own errors come out (issue 17).

Seed files are written once per session; Hypothesis cuts them short, flips bits or replaces
them by random bytes. ``sdp.read_points`` may succeed or raise an :class:`sdp.SDPError`,
nothing else; the command line exits 0 or 2 (one line on stderr, no output file).
"""

import subprocess
import sys

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import sdp  # noqa: E402

FUZZ = settings(max_examples=120, deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


@pytest.fixture(scope="session")
def seeds(tmp_path_factory):
    """Small valid files: name → bytes."""
    from plyfile import PlyData, PlyElement
    from pypcd4 import Encoding, PointCloud

    d = tmp_path_factory.mktemp("fuzz-seeds")
    xyz = np.random.default_rng(7).random((60, 3)).astype(np.float32)
    for enc in ("ascii", "binary", "binary_compressed"):
        PointCloud.from_xyz_points(xyz).save(d / f"{enc}.pcd", encoding=Encoding(enc))
    vert = np.rec.fromarrays(xyz.T, names="x,y,z")
    PlyData([PlyElement.describe(vert, "vertex")], text=True).write(str(d / "ascii.ply"))
    PlyData([PlyElement.describe(vert, "vertex")]).write(str(d / "binary.ply"))
    sdp.write_points(d / "a.las", xyz.astype(float))
    sdp.write_points(d / "a.laz", xyz.astype(float))
    np.savetxt(d / "a.xyz", xyz)
    np.savetxt(d / "a.csv", xyz, delimiter=",", header="x,y,z", comments="")
    np.save(d / "a.npy", xyz)
    np.savez(d / "a.npz", xyz=xyz, label=np.arange(60))
    _e57_seed(d / "a.e57", xyz)
    _bag_seed(d / "a.bag", xyz)
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())}


def _e57_seed(path, xyz):
    """Two scans, each with its pose and an intensity (pye57, the scans extra)."""
    pye57 = pytest.importorskip("pye57")
    e = pye57.E57(str(path), mode="w")
    for k in range(2):
        e.write_scan_raw({"cartesianX": xyz[:, 0].astype(float), "cartesianY": xyz[:, 1].astype(float),
                          "cartesianZ": xyz[:, 2].astype(float), "intensity": xyz[:, 0].astype(float)},
                         translation=np.array([k, 0, 0.0]))
    e.close()


def _bag_seed(path, xyz):
    """A ROS 1 bag of two 6×10 organized PointCloud2 frames on /points (rosbags, the scans extra)."""
    pytest.importorskip("rosbags")
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    pc2, pf = ts.types["sensor_msgs/msg/PointCloud2"], ts.types["sensor_msgs/msg/PointField"]
    header, time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    fields = [pf(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    with Writer(path) as w:
        conn = w.add_connection("/points", pc2.__msgtype__, typestore=ts)
        for k in range(2):
            msg = pc2(header=header(seq=k, stamp=time(sec=k, nanosec=0), frame_id="s"), height=6, width=10,
                      fields=fields, is_bigendian=False, point_step=12, row_step=120,
                      data=np.frombuffer(np.ascontiguousarray(xyz, "<f4").tobytes(), np.uint8), is_dense=False)
            w.write(conn, k + 1, ts.serialize_ros1(msg, pc2.__msgtype__))


NAMES = ["ascii.pcd", "binary.pcd", "binary_compressed.pcd", "ascii.ply", "binary.ply", "a.las", "a.laz",
         "a.xyz", "a.csv", "a.npy", "a.npz", "a.e57"]


@st.composite
def mutated(draw):
    name = draw(st.sampled_from(NAMES))
    kind = draw(st.sampled_from(["cut", "flip", "random"]))
    return name, kind, draw(st.integers(0, 2**32 - 1)), draw(st.binary(max_size=600))


def mutate(data: bytes, kind: str, seed: int, noise: bytes) -> bytes:
    rng = np.random.default_rng(seed)
    if kind == "cut":
        return data[:int(rng.integers(0, len(data)))]
    if kind == "random":
        return noise
    buf = bytearray(data)
    head = min(len(buf), 400)  # headers matter most: half the flips land there
    for _ in range(int(rng.integers(1, 9))):
        i = int(rng.integers(0, head)) if rng.random() < 0.5 else int(rng.integers(0, len(buf)))
        buf[i] ^= 1 << int(rng.integers(0, 8))
    return bytes(buf)


@FUZZ
@given(case=mutated())
def test_read_points_raises_only_sdp_errors(seeds, tmp_path, case):
    name, kind, seed, noise = case
    path = tmp_path / name
    path.write_bytes(mutate(seeds[name], kind, seed, noise))
    try:
        cloud = sdp.read_points(path)
    except sdp.SDPError as exc:
        assert "\n" not in str(exc), str(exc)
    else:
        assert cloud.xyz.ndim == 2 and cloud.xyz.shape[1] == 3 and np.isfinite(cloud.xyz).all()
    if name.endswith((".las", ".laz", ".npy", ".ply")):
        try:
            src = sdp.PointSource.open(path)
            for _ in src.chunks(25):
                pass
        except sdp.SDPError as exc:
            assert "\n" not in str(exc), str(exc)


@FUZZ
@given(case=st.tuples(st.sampled_from(["cut", "flip", "random"]), st.integers(0, 2**32 - 1), st.binary(max_size=600)))
def test_bag_frames_raise_only_sdp_errors(seeds, tmp_path, case):
    from sdp.io._bag import bag_frames

    path = tmp_path / "a.bag"
    path.write_bytes(mutate(seeds["a.bag"], *case))
    try:
        for _, cloud in bag_frames(path, "/points"):
            assert cloud.xyz.ndim == 2 and np.isfinite(cloud.xyz).all()
    except sdp.SDPError as exc:
        assert "\n" not in str(exc), str(exc)


@pytest.mark.slow
@settings(max_examples=4, deadline=None, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(case=mutated())
def test_cli_change_exits_0_or_2(seeds, tmp_path_factory, case):
    name, kind, seed, noise = case
    d = tmp_path_factory.mktemp("fuzz-cli")
    (d / "ref.npy").write_bytes(seeds["a.npy"])
    (d / name).write_bytes(mutate(seeds[name], kind, seed, noise))
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "change", "ref.npy", name, "-o", "out.ply", "-q",
                        "--voxel-size", "0.1"], cwd=d, capture_output=True, text=True, timeout=300)  # a hang fails
    assert p.returncode in (0, 2), p.stderr
    if p.returncode == 2:
        assert len(p.stderr.strip().splitlines()) == 1 and p.stderr.startswith("sdp: error: "), p.stderr
        assert sorted(f.name for f in d.iterdir()) == sorted({"ref.npy", name})
