import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import assert_changes_drawn, picture, slow_after

from sdp.io import read_points, write_points


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "sdp.cli", *map(str, args)], capture_output=True, text=True, cwd=cwd)


@pytest.fixture
def pair(tmp_path, rng):
    from conftest import box_surface, room_scene

    ref = room_scene(rng, n=40_000)
    cur = np.concatenate([room_scene(rng, n=40_000), box_surface(rng, [2.0, 1.2, 0.75], [2.4, 1.6, 1.35], 3000)])
    return write_points(tmp_path / "ref.ply", ref), write_points(tmp_path / "cur.ply", cur)


@pytest.mark.slow
def test_change_end_to_end(tmp_path, pair):
    ref, cur = pair
    p = run("change", ref, cur, "-o", tmp_path / "out.ply", "--both", "--voxel-size", "0.02", "--json",
            "--png", tmp_path / "out.png", "--min-region-points", "20")
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    assert s["current"]["appeared"] > 2000 and len(s["appeared_regions"]) == 1
    out = read_points(tmp_path / "out.ply")
    assert (out.fields["change"] == 1).sum() == s["current"]["appeared"]
    assert (out.fields["change"] == 2).sum() == s["current"]["not_comparable"]
    assert {"G", "F", "region"} <= set(out.fields)
    assert (tmp_path / "out_disappeared.ply").exists()
    assert_changes_drawn(tmp_path / "out.png")
    text = run("change", ref, cur, "-o", tmp_path / "out2.las", "--grid-size", "80")
    assert text.returncode == 0 and "appeared" in text.stdout and "time (ms)" in text.stdout


@pytest.mark.slow
def test_build_info_mesh(tmp_path, pair):
    ref, _ = pair
    assert run("build", ref, "-o", tmp_path / "ref.sdpf", "--voxel-size", "0.03").returncode == 0
    info = json.loads(run("info", tmp_path / "ref.sdpf").stdout)
    assert info["kind"] == "field" and info["voxel_size"] == pytest.approx(0.03)
    assert json.loads(run("info", ref).stdout)["points"] == 40_000
    m = run("mesh", tmp_path / "ref.sdpf", "-o", tmp_path / "ref.obj")
    assert m.returncode == 0 and (tmp_path / "ref.obj").stat().st_size > 1000


@pytest.mark.slow
@pytest.mark.parametrize("make_bad, match", [
    (lambda d: d / "missing.ply", "no such file"),
    (lambda d: (d / "x.foo").write_text("1 2 3") and d / "x.foo", "unknown point-cloud format"),
    (lambda d: (d / "t.ply").write_bytes(b"ply\nformat ascii") and d / "t.ply", "can't read"),
])
def test_bad_input_exits_2_and_writes_nothing(tmp_path, pair, make_bad, match):
    ref, _ = pair
    bad = make_bad(tmp_path)
    p = run("change", ref, bad, "-o", tmp_path / "o.ply")
    assert p.returncode == 2 and match in p.stderr and len(p.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o.ply").exists()


@pytest.mark.slow
def test_refuses_to_overwrite_input(tmp_path, pair):
    ref, cur = pair
    before = cur.read_bytes()
    p = run("change", ref, cur, "-o", cur, "--voxel-size", "0.03")
    assert p.returncode == 2 and "overwrite" in p.stderr
    assert cur.read_bytes() == before


def test_python_m_sdp_is_the_program():
    p = subprocess.run([sys.executable, "-m", "sdp", "info", "no-such-file.ply"], capture_output=True, text=True)
    assert (p.returncode, p.stdout) == (2, "") and p.stderr.startswith("sdp: error: no-such-file.ply")


def test_every_option_says_what_it_does_and_the_store_commands_name_stores():
    import argparse

    from sdp.cli._main import build_parser

    def commands(parser, name):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for sub, p in action.choices.items():
                    yield from commands(p, f"{name} {sub}")
        yield name, parser

    bare = [(name, a.option_strings) for name, p in commands(build_parser(), "sdp") for a in p._actions
            if a.option_strings and not a.help]
    assert bare == []
    parsers = dict(commands(build_parser(), "sdp"))
    help_of = {(name, a.dest): a.help for name, p in parsers.items() for a in p._actions}
    for command, dest in [("bool", "a"), ("bool", "b"), ("bool", "output"), ("mesh", "input"), ("info", "file")]:
        assert ".zarr" in help_of[f"sdp {command}", dest], (command, dest)


@pytest.mark.slow
def test_demo(tmp_path):
    p = run("demo", "-o", tmp_path / "demo")
    assert p.returncode == 0, p.stderr
    assert "kappa" in p.stdout
    kappa = float(p.stdout.split("comparable points: kappa ")[1].split(",")[0])
    assert kappa > 0.8
    for name in ("reference.ply", "current_labelled.ply", "current_cluster_volume.ply"):
        assert (tmp_path / "demo" / name).stat().st_size > 1000
    assert_changes_drawn(tmp_path / "demo" / "changes.png")


def test_a_failed_demo_leaves_no_folder_it_made(tmp_path, monkeypatch, capsys):
    import sdp
    import sdp.data._scene
    from sdp.cli._main import main

    def fail(**kwargs):
        raise sdp.SDPError("the disk is full")

    monkeypatch.setattr(sdp.data._scene, "office_scene", fail)
    assert main(["demo", "-o", str(tmp_path / "a" / "b")]) == 2
    assert "the disk is full" in capsys.readouterr().err and not (tmp_path / "a").exists()
    (tmp_path / "kept").mkdir()  # a folder that was there stays
    assert main(["demo", "-o", str(tmp_path / "kept")]) == 2 and (tmp_path / "kept").is_dir()


@pytest.mark.slow
def test_bool_fields_and_clouds(tmp_path, pair):
    ref, cur = pair
    assert run("build", ref, "-o", tmp_path / "ref.sdpf", "--voxel-size", "0.03").returncode == 0
    # a cloud combined with a field is built on the field's lattice; the result saved as a field
    p = run("bool", "difference", cur, tmp_path / "ref.sdpf", "-o", tmp_path / "new.sdpf")
    assert p.returncode == 0, p.stderr
    import sdp

    new = sdp.DensityField.load(tmp_path / "new.sdpf")
    assert new.voxel_size == pytest.approx(0.03)
    assert new.inside(np.array([[2.2, 1.4, 1.35]]))[0]  # on the added box's top
    assert not new.inside(np.array([[0.5, 0.5, 0.0]]))[0]  # the floor is in both
    # two clouds, automatic voxel from both: the surface of the union as a mesh
    m = run("bool", "union", ref, cur, "-o", tmp_path / "u.stl")
    assert m.returncode == 0 and "triangles" in m.stdout and (tmp_path / "u.stl").stat().st_size > 1000
    again = run("bool", "union", tmp_path / "ref.sdpf", tmp_path / "new.sdpf", "-o", tmp_path / "ref.sdpf")
    assert again.returncode == 2 and "overwrite" in again.stderr


@pytest.mark.slow
def test_eval_matches_library_scores(tmp_path, rng):
    import sdp

    truth = rng.random(500) < 0.3
    pred = truth ^ (rng.random(500) < 0.1)
    xyz = rng.random((500, 3))
    write_points(tmp_path / "p.ply", xyz, {"change": pred.astype(np.uint8)})
    write_points(tmp_path / "t.npz", xyz, {"label": truth.astype(np.int32) * 7})
    p = run("eval", tmp_path / "p.ply", tmp_path / "t.npz", "--truth-field", "label", "--json")
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout) == pytest.approx(sdp.scores(truth, pred), nan_ok=True)
    from sdp.cli import evaluate_files

    write_points(tmp_path / "r.npz", xyz, {"region": np.where(pred, np.arange(500) % 3, -1)})  # ids from 0, -1 none
    assert evaluate_files(tmp_path / "r.npz", tmp_path / "t.npz", predicted_field="region",
                          truth_field="label").scores == pytest.approx(sdp.scores(truth, pred), nan_ok=True)
    bad = run("eval", tmp_path / "p.ply", tmp_path / "t.npz")
    assert bad.returncode == 2 and "no per-point field 'change'" in bad.stderr and "label" in bad.stderr


@pytest.mark.slow
def test_render_cloud_and_field(tmp_path, pair):
    ref, cur = pair
    assert run("change", ref, cur, "-o", tmp_path / "c.ply", "--voxel-size", "0.03", "-q").returncode == 0
    p = run("render", tmp_path / "c.ply", "--png", tmp_path / "c.png", "--html", tmp_path / "c.html")
    assert p.returncode == 0, p.stderr
    assert_changes_drawn(tmp_path / "c.png")
    page = (tmp_path / "c.html").read_text()
    assert "<html" in page and "plotly" in page and "changed (" in page  # self-contained, legend counts
    assert run("build", ref, "-o", tmp_path / "ref.sdpf", "--voxel-size", "0.03").returncode == 0
    s = run("render", tmp_path / "ref.sdpf", "--png", tmp_path / "slices.png")
    assert s.returncode == 0, s.stderr
    img = picture(tmp_path / "slices.png")  # F = h - G on a diverging blue-red scale: inside blue, outside red
    assert ((img[..., 2] - img[..., 0]) > 0.3).sum() > 1000 and ((img[..., 0] - img[..., 2]) > 0.3).sum() > 1000
    assert run("render", tmp_path / "ref.sdpf").returncode == 2  # nothing asked for


@pytest.mark.slow
def test_outputs_get_a_normal_file_mode(tmp_path, pair):
    ref, cur = pair
    assert run("build", ref, "-o", tmp_path / "ref.sdpf", "--voxel-size", "0.03").returncode == 0
    import os

    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "ref.sdpf").stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's private 0o600


@pytest.mark.slow
def test_align_writes_a_loadable_matrix_and_change_uses_it(tmp_path, rng):
    from conftest import room_scene

    from sdp.registration._align import transform_points

    truth = np.eye(4)
    truth[:3, 3] = [0.04, -0.03, 0.02]
    write_points(tmp_path / "ref.ply", room_scene(rng, n=200_000))
    write_points(tmp_path / "cur.ply", transform_points(np.linalg.inv(truth), room_scene(rng, n=200_000)))
    p = run("align", tmp_path / "ref.ply", tmp_path / "cur.ply", "-o", tmp_path / "T.txt")
    assert p.returncode == 0, p.stderr
    np.testing.assert_allclose(np.loadtxt(tmp_path / "T.txt")[:3, 3], truth[:3, 3], atol=0.003)
    plain = json.loads(run("change", tmp_path / "ref.ply", tmp_path / "cur.ply", "-o", tmp_path / "a.ply",
                           "--voxel-size", "0.01", "--json").stdout)
    aligned = json.loads(run("change", tmp_path / "ref.ply", tmp_path / "cur.ply", "-o", tmp_path / "b.ply",
                             "--voxel-size", "0.01", "--json", "--align", "gicp").stdout)
    assert aligned["current"]["appeared"] < 0.2 * plain["current"]["appeared"]  # the offset's false changes
    assert aligned["alignment"]["method"] == "gicp" and "align" in aligned["timings"]


@pytest.mark.slow
def test_change_sensor_origin(tmp_path, pair):
    ref, cur = pair
    p = run("change", ref, cur, "-o", tmp_path / "o.ply", "--voxel-size", "0.02", "--json",
            "--sensor-origin", "2,1.5,2")
    assert p.returncode == 0, p.stderr
    s = json.loads(p.stdout)
    assert s["coverage"] == {"appeared": "sensor rays", "disappeared": "sensor rays"}
    assert s["current"]["appeared"] > 2000
    assert s["sensor_origin"]["reference"] == [2, 1.5, 2]
    bad = run("change", ref, cur, "-o", tmp_path / "o.ply", "--sensor-origin", "viewpoint")
    assert bad.returncode == 2 and "records no sensor position" in bad.stderr
    # the band of the rays with no rays to follow: said, not silently ignored
    p = run("change", ref, cur, "-o", tmp_path / "f.ply", "--voxel-size", "0.02", "--range-noise", "0.5")
    assert p.returncode == 0 and "--range-noise 0.5 was not used: neither file records" in p.stderr


@pytest.mark.slow
def test_align_on_a_class_with_fixed_horizontal(tmp_path, rng):
    # two epochs of gently rolling ground (class 2) with shrubs (class 5) that grew; the second
    # epoch lies 0.3 m lower: registered on the ground with the horizontal fixed, the lift is
    # 0.3 m and the horizontal stays exactly where it was
    def epoch(shrub_height):
        g = rng.uniform(0, 60, (40_000, 2))
        ground = np.c_[g, 0.5 * np.sin(g[:, 0] / 9) + 0.3 * np.cos(g[:, 1] / 7) + rng.normal(0, 0.02, len(g))]
        s = rng.uniform(0, 60, (8_000, 2))
        shrubs = np.c_[s, rng.uniform(0.2, shrub_height, len(s))]
        return np.r_[ground, shrubs], np.r_[np.full(len(g), 2, np.uint8), np.full(len(s), 5, np.uint8)]

    ref, ref_class = epoch(1.0)
    cur, cur_class = epoch(2.5)
    cur[:, 2] -= 0.3
    write_points(tmp_path / "ref.las", ref, {"classification": ref_class})
    write_points(tmp_path / "cur.las", cur, {"classification": cur_class})
    p = run("align", tmp_path / "ref.las", tmp_path / "cur.las", "-o", tmp_path / "T.txt", "--align-class", "2",
            "--fix-horizontal")
    assert p.returncode == 0, p.stderr
    t = np.loadtxt(tmp_path / "T.txt")
    assert abs(t[2, 3] + t[2, :3] @ cur.mean(axis=0) - cur.mean(axis=0)[2] - 0.3) < 0.02  # lift at the centroid
    np.testing.assert_allclose(t[:2, :2], np.eye(2), atol=1e-3)  # no turn about the vertical
    assert np.abs(t[:2, :3] @ cur.mean(axis=0) + t[:2, 3] - cur.mean(axis=0)[:2]).max() < 1e-3  # no slide
    change = run("change", tmp_path / "ref.las", tmp_path / "cur.las", "-o", tmp_path / "c.las", "--json",
                 "--align", "density", "--align-class", "2", "--fix-horizontal")
    assert change.returncode == 0, change.stderr
    al = json.loads(change.stdout)["alignment"]  # the lift of the scan's centroid, estimated on its ground
    assert abs(al["shift"][2] - 0.3) < 0.05 and np.abs(al["shift"][:2]).max() < 1e-3
    np.testing.assert_allclose(al["centre"], cur.mean(axis=0), atol=1e-3)
    assert "matrix" in al and "translation" not in al
    for args, message in ((("--align-class", "ground"), "class numbers"), (("--align-class", "7"), "too few"),
                          (("--method", "gicp", "--fix-horizontal"), "density alignment only")):
        bad = run("align", tmp_path / "ref.las", tmp_path / "cur.las", "-o", tmp_path / "U.txt", *args)
        assert bad.returncode == 2 and message in bad.stderr and not (tmp_path / "U.txt").exists()
    write_points(tmp_path / "cur.ply", cur)
    bad = run("align", tmp_path / "ref.las", tmp_path / "cur.ply", "-o", tmp_path / "U.txt", "--align-class", "2")
    assert bad.returncode == 2 and "classification" in bad.stderr
    bad = run("change", tmp_path / "ref.las", tmp_path / "cur.las", "-o", tmp_path / "d.las", "--align-class", "2")
    assert bad.returncode == 2 and "--align density" in bad.stderr and not (tmp_path / "d.las").exists()


def test_the_program_exits_with_the_status_of_main_and_freezes_what_is_left(tmp_path, monkeypatch):
    import gc
    from importlib.metadata import entry_points

    from sdp import cli

    assert entry_points(group="console_scripts")["sdp"].value == "sdp.cli:run"  # the installed `sdp`
    np.save(tmp_path / "a.npy", np.zeros((0, 3)))
    monkeypatch.setattr(sys, "argv", ["sdp", "change", str(tmp_path / "a.npy"), str(tmp_path / "a.npy"), "-o",
                                      str(tmp_path / "o.ply")])
    threshold = gc.get_threshold()
    try:
        with pytest.raises(SystemExit) as exit_:
            cli.run()
        frozen, tuned = gc.get_freeze_count(), gc.get_threshold()
    finally:  # this process goes on: give the collector back
        gc.unfreeze()
        gc.set_threshold(*threshold)
    assert exit_.value.code == 2  # an empty cloud: main's one-line error
    # the first two generations as run() found them; full collections rarer than a fresh interpreter's
    fresh = [sys.executable, "-c", "import gc, json; print(json.dumps(gc.get_threshold()))"]
    default = json.loads(subprocess.run(fresh, capture_output=True, text=True, check=True).stdout)
    assert frozen > 0 and tuned[:2] == threshold[:2] and tuned[2] > default[2]
    assert not (tmp_path / "o.ply").exists()


@pytest.fixture
def quiet_inputs(tmp_path, rng):
    """Small inputs for every command that prints: two epochs, a field, frames, a labelled cloud,
    an action model and depth frames."""
    from conftest import box_surface, room_scene

    import sdp

    d = tmp_path / "in"
    d.mkdir()
    ref = room_scene(rng, n=12_000)
    cur = np.concatenate([room_scene(rng, n=12_000), box_surface(rng, [2.0, 1.2, 0.75], [2.4, 1.6, 1.35], 2000)])
    np.save(d / "ref.npy", ref)
    np.save(d / "cur.npy", cur)
    sdp.DensityField.from_points(ref, voxel_size=0.05).save(d / "ref.sdpf")
    (d / "frames").mkdir()
    np.save(d / "frames" / "0.npy", cur)
    write_points(d / "lab.ply", cur, {"change": (cur[:, 2] > 1.0).astype(np.uint8)})
    return d


def quiet_cases(d, out):
    """(args, takes --json) of each command that prints, writing into ``out``."""
    return [(["change", d / "ref.npy", d / "cur.npy", "-o", out / "c.ply", "--voxel-size", "0.05"], True),
            (["build", d / "ref.npy", "-o", out / "f.sdpf", "--voxel-size", "0.05"], False),
            (["mesh", d / "ref.sdpf", "-o", out / "m.ply"], False),
            (["bool", "union", d / "ref.sdpf", d / "cur.npy", "-o", out / "u.sdpf"], False),
            (["eval", d / "lab.ply", d / "lab.ply"], True),
            (["render", d / "lab.ply", "--png", out / "r.png"], False),
            (["watch", d / "ref.npy", d / "frames"], True),
            (["align", d / "ref.npy", d / "cur.npy", "-o", out / "T.txt"], True),
            (["distance", d / "ref.npy", d / "cur.npy", "-o", out / "d.ply"], True)]


@pytest.mark.parametrize("case", slow_after(2, list(range(9))))
def test_quiet_prints_nothing_but_errors_and_the_json_asked_for(tmp_path, quiet_inputs, capfd, case):
    from sdp.cli._main import main

    def outputs(tag):
        out = tmp_path / tag
        out.mkdir()
        return quiet_cases(quiet_inputs, out)[case]

    args, takes_json = outputs("loud")
    assert main(list(map(str, args))) == 0
    loud = capfd.readouterr()
    assert loud.out.strip(), f"{args[0]} prints something without --quiet"
    args, _ = outputs("quiet")
    assert main([*map(str, args), "-q"]) == 0
    assert capfd.readouterr() == ("", ""), args[0]
    if takes_json:
        args, _ = outputs("json")
        assert main([*map(str, args), "-q", "--json"]) == 0
        got = capfd.readouterr()
        assert json.loads(got.out) and got.err == "", args[0]


def test_quiet_keeps_errors_and_info_s_json_but_no_notice_nor_warning(tmp_path, quiet_inputs, capfd, monkeypatch):
    import warnings

    from sdp.cli import _change as P
    from sdp.cli._main import main

    d = quiet_inputs
    assert main(["info", str(d / "ref.npy"), "-q"]) == 0  # info's answer is JSON
    got = capfd.readouterr()
    assert json.loads(got.out)["points"] == 12_000 and got.err == ""
    assert main(["change", str(d / "missing.npy"), str(d / "cur.npy"), "-o", str(tmp_path / "x.ply"), "-q"]) == 2
    got = capfd.readouterr()
    assert got.out == "" and got.err.startswith("sdp: error: ") and got.err.count("\n") == 1
    compare = P.compare_files  # a notice, as the switch to tiles gives one

    def noisy(*args, **kw):
        kw["execution"].notify("comparing in tiles on Dask: ...")
        warnings.warn("something to ignore", UserWarning, stacklevel=1)
        return compare(*args, **kw)

    monkeypatch.setattr(P, "compare_files", noisy)
    args = ["change", str(d / "ref.npy"), str(d / "cur.npy"), "--voxel-size", "0.05"]
    for output, quiet in (("a.ply", []), ("b.ply", ["-q"])):
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            assert main([*args, "-o", str(tmp_path / output), *quiet]) == 0
        got = capfd.readouterr()
        if quiet:
            assert got == ("", "") and not seen
        else:
            assert "sdp: comparing in tiles" in got.err and len(seen) == 1


@pytest.mark.slow
def test_quiet_tiles_demo_and_actions(tmp_path, quiet_inputs, capfd, rng):
    from test_actions import sequence, sequence_descriptor, train

    from sdp.cli._main import main

    d = quiet_inputs
    x = np.stack([sequence_descriptor(sequence(k, rng)) for k in (1, 2) for _ in range(3)])
    model, _ = train(x, np.repeat([1, 2], 3), np.tile([1, 2, 3], 2))
    model.save(d / "m.npz")
    (d / "depth").mkdir()
    for i, f in enumerate(sequence(1, rng)):
        np.save(d / "depth" / f"{i:04d}.npy", f)
    for args in (["change", d / "ref.npy", d / "cur.npy", "-o", tmp_path / "t.laz", "--tiled", "--workers", "1",
                  "--voxel-size", "0.05"],
                 ["action", "predict", d / "m.npz", "--stream", d / "depth", "--window", "20", "--every", "10"],
                 ["demo", "-o", tmp_path / "demo"]):
        assert main([*map(str, args), "-q"]) == 0
        assert capfd.readouterr() == ("", ""), args[:2]
    assert main(["action", "predict", str(d / "m.npz"), "--stream", str(d / "depth"), "--window", "20"]) == 0
    assert "frame 20: a01" in capfd.readouterr().out
