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
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())}


NAMES = ["ascii.pcd", "binary.pcd", "binary_compressed.pcd", "ascii.ply", "binary.ply", "a.las", "a.laz",
         "a.xyz", "a.csv", "a.npy", "a.npz"]


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
