"""sdp.pipeline: the commands as Python functions give what the commands give (issue 18)."""

import inspect
import json

import numpy as np
import pytest
import test_cli
from conftest import assert_changes_drawn

import sdp
from sdp import cli as pipeline
from sdp.io import read_points, write_points

pair, run = test_cli.pair, test_cli.run  # the fixture of two clouds as PLY files; sdp on the command line


def without_times(summary):
    return {k: v for k, v in summary.items() if k not in ("timings", "outputs")}


@pytest.mark.slow  # a CLI process or a Dask run: the full suite's
def test_compare_files_equals_sdp_change(tmp_path, pair):
    ref, cur = pair
    opts = ["--both", "--voxel-size", "0.03", "--min-region-points", "20", "--sensor-origin", "2,1.5,2"]
    p = run("change", ref, cur, "-o", tmp_path / "cli.ply", "--json", *opts)
    text = run("change", ref, cur, "-o", tmp_path / "cli2.ply", *opts)
    assert p.returncode == 0 and text.returncode == 0, p.stderr + text.stderr
    r = sdp.compare_files(ref, cur, output=tmp_path / "py.ply", min_region_points=20,
                          lattice=sdp.Lattice(voxel_size=0.03),
                          coverage=sdp.Coverage(sensor_origin="2,1.5,2"), outputs=sdp.Outputs(both=True))
    assert not r.tiled and r.outputs == [str(tmp_path / "py.ply"), str(tmp_path / "py_disappeared.ply")]
    assert without_times(json.loads(p.stdout)) == json.loads(json.dumps(without_times(r.summary)))
    assert r.summary["current"]["appeared"] > 1500 and r.summary["coverage"]["appeared"] == "sensor rays"
    for suffix in ("", "_disappeared"):
        a, b = read_points(tmp_path / f"cli{suffix}.ply"), read_points(tmp_path / f"py{suffix}.ply")
        for name in ("change", "region", "G", "F"):
            np.testing.assert_array_equal(a.fields[name], b.fields[name])

    def table(s):  # the printed table but for the times and the file names
        return [ln for ln in s.splitlines() if not ln.startswith(("time (ms)", "wrote"))]

    assert table(r.summary_text()) == table(text.stdout)


@pytest.mark.slow  # a CLI process or a Dask run: the full suite's
def test_the_automatic_switch_to_tiles_from_python(tmp_path, rng):
    from test_tiles import street, write_las

    a = write_las(tmp_path / "a.laz", street(rng, [([2, 2, 0], [4, 5, 2.0])], n=40_000, mast=True))
    b = write_las(tmp_path / "b.laz", street(rng, [([2, 2, 0], [4, 5, 2.0]), ([20, 9, 0], [21.5, 10.5, 1.2])],
                                             n=40_000, mast=True))
    plan = sdp.plan_change(a, b, lattice=sdp.Lattice(voxel_size=0.1), execution=sdp.Execution(memory_limit="1GB"))
    assert plan.tiled and "exceed the memory limit of 1 GB" in plan.reason
    assert not sdp.plan_change(a, b, lattice=sdp.Lattice(voxel_size=0.1)).tiled  # fits in 4 GiB
    assert not sdp.plan_change(a, b, decision="cluster", lattice=sdp.Lattice(voxel_size=0.1),
                               execution=sdp.Execution(memory_limit="1GB")).tiled
    said = []
    tiled = sdp.compare_files(a, b, output=tmp_path / "t.laz", lattice=sdp.Lattice(voxel_size=0.1),
                              execution=sdp.Execution(memory_limit="1GB", tile_size=6, scheduler="synchronous", notify=said.append),
                              outputs=sdp.Outputs(both=True))
    assert tiled.tiled and said == [plan.reason] and tiled.summary["tiles"] > 1
    # the labelled files were streamed from the changed rows: no per-point array of either cloud was made
    assert tiled.result.tiled and tiled.result._current._state is None and tiled.result._reference._state is None
    assert "tiles of 6.4" in tiled.summary_text()
    whole = sdp.compare_files(a, b, output=tmp_path / "m.laz", lattice=sdp.Lattice(voxel_size=0.1),
                              outputs=sdp.Outputs(both=True))
    assert not whole.tiled and whole.summary["current"]["appeared"] == tiled.summary["current"]["appeared"] > 500
    for suffix in ("", "_disappeared"):
        x, y = read_points(tmp_path / f"t{suffix}.laz"), read_points(tmp_path / f"m{suffix}.laz")
        np.testing.assert_array_equal(x.fields["change"], y.fields["change"])
    with pytest.raises(sdp.SDPError, match="output streams to LAS/LAZ"):
        sdp.compare_files(a, b, output=tmp_path / "t.ply", lattice=sdp.Lattice(voxel_size=0.1),
                          execution=sdp.Execution(memory_limit="1GB"))
    # an earlier output compared again in tiles: its G and F, which tiles do not write, would be stale
    sdp.compare_files(a, tmp_path / "m.laz", output=tmp_path / "again.laz", lattice=sdp.Lattice(voxel_size=0.1),
                      execution=sdp.Execution(tiled=True, tile_size=6, scheduler="synchronous"))
    again = read_points(tmp_path / "again.laz")
    assert {"G", "F"} <= set(read_points(tmp_path / "m.laz").fields) and not {"G", "F"} & set(again.fields)
    np.testing.assert_array_equal(again.fields["change"], read_points(tmp_path / "t.laz").fields["change"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.laz", "again.laz", "b.laz", "m.laz", "m_disappeared.laz",
                                                          "t.laz", "t_disappeared.laz"]


def test_in_memory_the_limit_counts_the_whole_command(tmp_path, rng):
    """Files only the in-memory path reads (here XYZ text) under a limit the comparison would pass:
    refused after reading, before any field, with the smallest limit, which then works."""
    import re

    from sdp.scale._budget import untiled_point_bytes

    xyz = rng.uniform(0, 10, (30_000, 3))
    a, b = tmp_path / "a.xyz", tmp_path / "b.xyz"
    np.savetxt(a, xyz)
    np.savetxt(b, xyz[:20_000] + 0.01)
    need = untiled_point_bytes(50_000)
    assert need > 50_000 * 150 + 150 * 2**20  # the points and the process itself
    with pytest.raises(sdp.GridTooLargeError, match=r"comparing 50,000 points in memory needs about .*give "
                       r"--memory-limit \d+MB or more") as err:
        sdp.compare_files(a, b, output=tmp_path / "c.ply", lattice=sdp.Lattice(voxel_size=0.2),
                          execution=sdp.Execution(memory_limit=need - 2**20))
    assert not (tmp_path / "c.ply").exists()
    smallest = re.search(r"--memory-limit (\d+)MB", str(err.value)).group(1)
    assert sdp.compare_files(a, b, output=tmp_path / "c.ply", lattice=sdp.Lattice(voxel_size=0.2),
                             execution=sdp.Execution(memory_limit=f"{smallest}MB")).outputs


@pytest.mark.parametrize("make, match", [
    (lambda: dict(align=sdp.Registration(method="gicp", fix_horizontal=True)), "density alignment only"),
    (lambda: dict(align=sdp.Registration(align_class="ground")), "class numbers"),
    (lambda: dict(coverage=sdp.Coverage(sensor_origin="1,2")), "X,Y,Z"),
    (lambda: dict(execution=sdp.Execution(tiled=True), decision="cluster"),
     "--decision cluster is not available with --tiled"),
    (lambda: dict(lattice=sdp.Lattice(voxel_size=-1)), "voxel_size"),
    (lambda: dict(min_region_points=-1), "min_region_points"),
    (lambda: dict(align="icp"), "method must be 'density' or 'gicp'"),
])
def test_options_are_refused_before_any_file_is_read(tmp_path, make, match):
    with pytest.raises(sdp.SDPError, match=match):  # the inputs do not even exist
        sdp.compare_files(tmp_path / "none.ply", tmp_path / "nothing.ply", output=tmp_path / "o.ply", **make())
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_the_other_commands_as_functions(tmp_path, pair):
    ref, cur = pair
    fld = pipeline.build_field_file(ref, output=tmp_path / "r.sdpf", lattice=sdp.Lattice(voxel_size=0.03))
    assert sdp.DensityField.load(tmp_path / "r.sdpf").n_blocks == fld.n_blocks
    assert pipeline.describe_file(tmp_path / "r.sdpf")["voxel_size"] == pytest.approx(0.03)
    new = pipeline.combine_files("difference", cur, tmp_path / "r.sdpf", output=tmp_path / "n.sdpf")
    assert new.voxel_size == pytest.approx(0.03) and new.inside(np.array([[2.2, 1.4, 1.35]]))[0]
    mesh = pipeline.mesh_file(tmp_path / "r.sdpf", output=tmp_path / "m.ply")
    assert len(mesh.faces) > 1000 and (tmp_path / "m.ply").stat().st_size > 1000
    r = sdp.compare_files(ref, cur, output=tmp_path / "c.ply", lattice=sdp.Lattice(voxel_size=0.03))
    e = pipeline.evaluate_files(tmp_path / "c.ply", tmp_path / "c.ply")
    assert e.scores["kappa"] == pytest.approx(1.0) and e.predicted == r.summary["current"]["appeared"]
    assert pipeline.render_file(tmp_path / "c.ply", png=tmp_path / "c.png") == [str(tmp_path / "c.png")]
    assert_changes_drawn(tmp_path / "c.png")
    frames = tmp_path / "frames"
    frames.mkdir()
    write_points(frames / "f1.ply", read_points(cur).xyz)
    [frame] = list(pipeline.watch_folder(ref, frames, lattice=sdp.Lattice(voxel_size=0.03)))
    assert frame.name == "f1.ply" and frame.n_appeared > 1000


def test_the_functions_take_the_defaults_objects():
    for func in (sdp.compare_files, sdp.plan_change, pipeline.build_field_file, pipeline.watch_folder):
        for name, p in inspect.signature(func).parameters.items():
            if hasattr(sdp.DEFAULTS, name):
                # None: the DEFAULTS value where the option applies (refused where it would be ignored)
                conditional = name in ("window", "decay") and p.default is None
                assert conditional or p.default is getattr(sdp.DEFAULTS, name), (func.__name__, name)


def test_render_draws_a_fields_nan_as_no_value(tmp_path, rng):
    """`sdp render --field F`: F ≠ 0 is drawn vermillion, and NaN (nothing measured there) grey, not as
    ≠ 0."""
    from conftest import drawn_pixels, picture

    distance = np.zeros(1000, np.float32)
    distance[:900] = np.nan
    np.savez(tmp_path / "d.npz", xyz=rng.random((1000, 3)), distance=distance)
    pipeline.render_file(tmp_path / "d.npz", png=tmp_path / "d.png", field="distance")
    img = picture(tmp_path / "d.png")
    assert drawn_pixels(img, "#D55E00") == 0 and drawn_pixels(img, "#B4B4B4") > 0


def test_the_distances_memory_limit_counts_the_process(tmp_path, rng):
    # as in every command, the limit is the whole job's: 1,000 points under 200 MB go to tiles
    from sdp.cli._distance import _distances_in_tiles
    from sdp.scale._budget import PROCESS_BYTES

    write_points(tmp_path / "a.laz", rng.random((1000, 3)))
    said = []
    for limit, tiles in ((PROCESS_BYTES - 2**20, True), (PROCESS_BYTES + 2**22, False)):
        ex = sdp.Execution(memory_limit=limit, notify=said.append)
        got = _distances_in_tiles(tmp_path / "a.laz", tmp_path / "a.laz", tmp_path / "o.laz", format=None,
                                  execution=ex, core_points=None, align=None, png=None)
        assert (got is not None) is tiles
    # said by the tiles once taken, with what the work needs in memory for a refusal of theirs
    reason, need = _distances_in_tiles(tmp_path / "a.laz", tmp_path / "a.laz", tmp_path / "o.laz", format=None,
                                       execution=sdp.Execution(memory_limit=PROCESS_BYTES - 2**20),
                                       core_points=None, align=None, png=None).switched
    assert said == [] and "with the process" in reason and need == PROCESS_BYTES + 650 * 1000


def test_both_draws_what_disappeared_beside_what_appeared(tmp_path, pair):
    # the box is in the reference only: nothing appeared, it disappeared
    with_box, without = pair[1], pair[0]
    sdp.compare_files(with_box, without, output=tmp_path / "c.ply", lattice=sdp.Lattice(voxel_size=0.03),
                      outputs=sdp.Outputs(both=True, png=tmp_path / "c.png"))
    assert_changes_drawn(tmp_path / "c.png", changed=False)
    assert_changes_drawn(tmp_path / "c_disappeared.png")


def test_a_run_in_memory_says_it_leaves_the_tiles_options(tmp_path, pair):
    said = []
    sdp.compare_files(*pair, output=tmp_path / "c.ply", lattice=sdp.Lattice(voxel_size=0.03),
                      execution=sdp.Execution(workers=2, scheduler="tcp://127.0.0.1:8786", notify=said.append))
    assert said == ["in memory: --scheduler, --workers used by tiles only (--tiled, or work beyond --memory-limit)"]
