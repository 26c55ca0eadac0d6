"""One set of defaults, shared by the Python API and the command line; the sensor read from the file."""

import inspect
import json
import subprocess
import sys

import numpy as np
import pytest

import sdp
from sdp.cli._main import build_parser

PYTHON = {  # function or option object → the DEFAULTS fields it takes as keyword options
    sdp.Lattice: ("voxel_size", "sigma_voxels", "k", "truncate", "method"),
    sdp.Coverage: ("sensor_origin", "range_noise"),
    sdp.Cylinder: ("projection_scale", "normal_scale", "max_distance"),
    sdp.detect_changes: ("min_region_points", "decision", "cluster_fraction"),
    sdp.DensityField.from_points: ("voxel_size", "sigma_voxels", "k", "truncate", "method"),
    sdp.watch: ("min_region_points", "update"),  # window, decay: None, DEFAULTS' value where they apply
    sdp.detect_changes_tiled: ("min_region_points",),
    sdp.distances: ("registration_error",),
    sdp.align: ("voxel_size",),
    sdp.threshold: ("k",),
}
CLI = {"change": ("voxel_size", "sigma_voxels", "k", "min_region_points", "sensor_origin", "range_noise", "decision"),
       "watch": ("voxel_size", "min_region_points", "sensor_origin", "range_noise", "update"),
       "build": ("voxel_size", "sigma_voxels", "k"), "bool": ("voxel_size", "sigma_voxels", "k"),
       "series": ("projection_scale", "normal_scale", "max_distance")}


def test_python_and_cli_defaults_are_the_same_objects():
    for func, names in PYTHON.items():
        params = inspect.signature(func).parameters
        for name in names:
            assert params[name].default is getattr(sdp.DEFAULTS, name), (func.__name__, name)
    assert inspect.signature(sdp.Registration).parameters["method"].default is sdp.DEFAULTS.align_method
    assert inspect.signature(sdp.align).parameters["method"].default is sdp.DEFAULTS.align_method
    sub = next(a for a in build_parser()._actions if a.dest == "command").choices
    for command, names in CLI.items():
        defaults = {a.dest: a.default for a in sub[command]._actions}
        for name in names:
            assert defaults[name] is getattr(sdp.DEFAULTS, name), (command, name)
    assert sdp.DEFAULTS.voxel_size == "auto" and sdp.DEFAULTS.sensor_origin == "auto"
    with pytest.raises(AttributeError):
        sdp.DEFAULTS.min_region_points = 1  # frozen: one place to change them


def test_the_papers_grid_stays_one_option_away(rng):
    a, b = rng.random((3000, 3)), rng.random((3000, 3))
    r = sdp.detect_changes(a, b, lattice=sdp.Lattice(grid_size=80))
    extent = np.max(np.maximum(a.max(0), b.max(0)) - np.minimum(a.min(0), b.min(0)))
    assert r.voxel_size == pytest.approx(extent / 80)
    auto = sdp.detect_changes(a, b)
    assert auto.voxel_size == pytest.approx(sdp.auto_voxel_size(a, b))
    assert sdp.DensityField.from_points(a).voxel_size == pytest.approx(sdp.auto_voxel_size(a))
    assert auto.current_field.sigma == pytest.approx(1.5 * auto.voxel_size)  # σ from the spacing
    assert r.current_field.sigma == pytest.approx(2 * r.voxel_size)  # the paper's σ of 2 voxels
    with pytest.raises(ValueError, match="not both"):
        sdp.detect_changes(a, b, lattice=sdp.Lattice(grid_size=80, voxel_size=0.1))


def pcd(path, xyz, *, width, height, viewpoint="0 0 0 1 0 0 0"):
    header = (f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {width}\n"
              f"HEIGHT {height}\nVIEWPOINT {viewpoint}\nPOINTS {len(xyz)}\nDATA ascii\n")
    path.write_text(header + "\n".join(" ".join(f"{v:.6f}" for v in p) for p in xyz) + "\n")
    return path


def test_which_files_know_their_sensor(tmp_path, rng):
    xyz = rng.random((6, 3)) + [0, 0, 1]
    organized = sdp.read_points(pcd(tmp_path / "o.pcd", xyz, width=3, height=2))
    merged = sdp.read_points(pcd(tmp_path / "m.pcd", xyz, width=6, height=1))
    posed = sdp.read_points(pcd(tmp_path / "p.pcd", xyz, width=6, height=1, viewpoint="1 2 3 1 0 0 0"))
    assert organized.organized and np.array_equal(organized.sensor_origin, [0, 0, 0])  # a camera's own frame
    assert merged.sensor_origin is None  # PCL's default VIEWPOINT on an unorganized map says nothing
    np.testing.assert_array_equal(posed.sensor_origin, [1, 2, 3])
    turn = np.array([[0, -1, 0, 5], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], float)
    moved = posed.transformed(turn)
    np.testing.assert_allclose(moved.sensor_origin, [3, 1, 3])
    np.testing.assert_allclose(moved.xyz, posed.xyz @ turn[:3, :3].T + turn[:3, 3])
    np.testing.assert_allclose(moved.viewpoint[3:], [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)], atol=1e-12)


def test_detect_changes_uses_the_sensor_a_cloud_brings(tmp_path):
    from sdp.data._scene import CAMERA, office_scene

    s = office_scene(seed=1, width=160, height=120)
    ref, cur = sdp.io.Cloud(s.reference), sdp.io.Cloud(s.current)
    ref.viewpoint = cur.viewpoint = np.r_[CAMERA, 1, 0, 0, 0]
    ref.organized = cur.organized = True
    auto = sdp.detect_changes(ref, cur)
    given = sdp.detect_changes(s.reference, s.current, coverage=sdp.Coverage(sensor_origin=CAMERA))
    np.testing.assert_array_equal(auto.current_state, given.current_state)
    assert auto.coverage["appeared"] == "sensor rays" and auto.summary()["sensor_origin"]["current"] == list(CAMERA)
    plain = sdp.detect_changes(ref, cur, coverage=sdp.Coverage(sensor_origin=None))
    assert plain.coverage == {"appeared": "footprint", "disappeared": "footprint"}
    one = sdp.detect_changes(ref, s.current)  # only the reference knows: appeared follows its rays
    assert one.coverage == {"appeared": "sensor rays", "disappeared": "footprint"}
    # the current's own sensor only tells where a hider it lacks could not be seen by it (then no change)
    assert not (auto.appeared & ~one.appeared).any() and (one.appeared != auto.appeared).mean() < 0.001


@pytest.mark.slow
@pytest.mark.shared_data
def test_sdp_change_and_detect_changes_agree_with_no_option(tmp_path, shared_data):
    a, b = (shared_data / f"mosd/learn/learn{i}.pcd" for i in (6, 7))
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "change", str(a), str(b), "-o", str(tmp_path / "o.ply"),
                        "--json"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    ra, rb = sdp.read_points(a), sdp.read_points(b)
    r = sdp.detect_changes(ra, rb)
    np.testing.assert_array_equal(sdp.read_points(tmp_path / "o.ply").fields["change"], r.current_state)
    assert s["coverage"] == {"appeared": "sensor rays", "disappeared": "sensor rays"}
    # the rows the PCD reader dropped (NaN pixels) are counted in the summary
    assert s["current"]["dropped"] == rb.n_dropped > 50_000 and r.summary()["current"]["dropped"] == rb.n_dropped


@pytest.mark.slow
def test_k_reaches_the_automatic_voxel_of_build_and_tiles(tmp_path, rng):
    pts = rng.random((4000, 3))
    np.save(tmp_path / "a.npy", pts)
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "build", str(tmp_path / "a.npy"),
                        "-o", str(tmp_path / "a.sdpf"), "-k", "5"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    built = sdp.DensityField.load(tmp_path / "a.sdpf")
    assert built.voxel_size == pytest.approx(sdp.auto_voxel_size(pts, k=5))
    assert built.h == pytest.approx(sdp.threshold(5))
    tiled = sdp.detect_changes_tiled(pts, pts + 0.001,
                                     execution=sdp.Execution(scheduler="synchronous", workdir=tmp_path))  # "auto" too
    assert tiled.voxel_size == pytest.approx(sdp.auto_voxel_size(pts, pts + 0.001))
