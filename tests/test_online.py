import json

import numpy as np
import pytest
from conftest import box_surface, room_scene

import sdp
from sdp.stream._watch import watch


def test_accumulate_equals_a_rebuild_and_subtracting_undoes_it(rng):
    a, b = room_scene(rng, n=20_000), box_surface(rng, [3.5, 3.2, 0.0], [4.5, 4.0, 0.8], 4000)  # b grows the box
    fa = sdp.DensityField.from_points(a, voxel_size=0.04)
    both = sdp.DensityField.from_points(np.concatenate([a, b]), voxel_size=0.04)
    grown = fa.copy().accumulate(sdp.DensityField.from_points(b, voxel_size=0.04))
    q = rng.uniform([0, 0, 0], [4.5, 4.0, 2.5], (5000, 3))
    np.testing.assert_allclose(grown.density(q), both.density(q), atol=1e-4 * both.density(q).max())
    assert grown.n_points == len(a) + len(b)
    back = grown.accumulate(sdp.DensityField.from_points(b, voxel_size=0.04), weight=-1)
    np.testing.assert_allclose(back.density(q), fa.density(q), atol=1e-4 * both.density(q).max())
    with pytest.raises(sdp.IncompatibleFieldsError, match="voxel"):
        fa.accumulate(sdp.DensityField.from_points(b, voxel_size=0.05))
    # what is no field, or no finite weight, is refused in one line (not an AttributeError inside)
    for call, error in ((lambda: fa.accumulate(b), sdp.IncompatibleFieldsError),
                        (lambda: fa.copy().accumulate(fa, weight=float("nan")), sdp.InvalidOptionError),
                        (lambda: sdp.union(fa, b), sdp.IncompatibleFieldsError),
                        (lambda: fa.density([["a", "b", "c"]]), sdp.InvalidPointsError)):
        with pytest.raises(error):
            call()


def test_accumulating_a_stream_fills_spare_rows_and_equals_a_rebuild(rng):
    parts = [rng.normal([0.3 * i, 0, 0], 0.05, (2000, 3)) for i in range(8)]  # each adds blocks
    f = sdp.DensityField.from_points(parts[0], voxel_size=0.02)
    fields = [sdp.DensityField.from_points(p, voxel_size=0.02) for p in parts]
    snapshot = None
    for i, g in enumerate(fields[1:], start=1):
        f.accumulate(g)
        if i == 3:
            snapshot = f.copy()  # independent of the rows f keeps appending to
    assert f.nbytes >= f.blocks.values.nbytes + f.blocks.directory.nbytes  # spare rows are counted
    both = sdp.DensityField.from_points(np.concatenate(parts), voxel_size=0.02)
    q = np.concatenate(parts)[::7]
    np.testing.assert_allclose(f.density(q), both.density(q), atol=1e-5 * both.density(q).max())
    first4 = sdp.DensityField.from_points(np.concatenate(parts[:4]), voxel_size=0.02)
    np.testing.assert_allclose(snapshot.density(q), first4.density(q), atol=1e-5 * both.density(q).max())
    for g in fields[1:]:
        f.accumulate(g, weight=-1)
    np.testing.assert_allclose(f.density(q), fields[0].density(q), atol=1e-5 * both.density(q).max())


def test_scale_is_a_decay(rng):
    f = sdp.DensityField.from_points(room_scene(rng, n=5000), voxel_size=0.05)
    q = rng.uniform(0, 3, (100, 3))
    before = f.density(q)
    np.testing.assert_allclose(f.copy().scale(0.5).density(q), 0.5 * before, rtol=1e-6)
    np.testing.assert_array_equal(f.density(q), before)  # the copy was scaled, not the original


def stream(rng):
    """A static room seen three times, then with a box put on the table, seen three times."""
    box = box_surface(rng, [2.0, 1.2, 0.75], [2.4, 1.6, 1.1], 3000)
    return [room_scene(rng) for _ in range(3)] + [np.concatenate([room_scene(rng), box]) for _ in range(3)], box


@pytest.mark.parametrize("update", ["none", "window", "decay"])
def test_watch_reports_an_object_when_it_appears(rng, update):
    frames, box = stream(rng)
    given = {"window": {"window": 3}, "decay": {"decay": 0.5}}.get(update, {})  # each applies to its update
    reports = list(watch(room_scene(rng), frames, update=update, min_region_points=50,
                         lattice=sdp.Lattice(voxel_size=0.03), **given))
    assert [r.index for r in reports] == list(range(6))
    assert all(r.n_appeared == 0 for r in reports[:3])  # static: nothing
    first = reports[3]
    assert first.n_appeared > 0.5 * len(box)  # not the parts within σ of the table and len(first.regions) == 1
    assert np.allclose(first.regions[0].centroid, [2.2, 1.4, 0.95], atol=0.1)
    labels = first.appeared_labels  # each appeared row's region, as in detect_changes' result
    assert labels.dtype == np.int32 and len(labels) == len(frames[3])
    np.testing.assert_array_equal(labels >= 0, first.appeared)
    assert [int((labels == g.label).sum()) for g in first.regions] == [g.n_points for g in first.regions]
    if update == "none":  # the fixed reference keeps reporting it
        assert all(r.n_appeared > 0.5 * len(box) for r in reports[4:])
    else:  # the model has learnt it
        assert reports[-1].n_appeared < 0.1 * len(box)
    assert all(r.latency >= 0 and set(r.timings) == {"build", "detect", "regions", "update"} for r in reports)


def test_window_forgets_what_left(rng):
    frames, box = stream(rng)
    ref = np.concatenate([room_scene(rng), box])  # the box stands in the reference, leaves, comes back
    kept = list(watch(ref, frames, update="none", min_region_points=50, lattice=sdp.Lattice(voxel_size=0.03)))
    forgot = list(watch(ref, frames, update="window", window=2, min_region_points=50,
                        lattice=sdp.Lattice(voxel_size=0.03)))
    assert kept[3].n_appeared < 0.1 * len(box)  # still in the fixed reference
    assert forgot[3].n_appeared > 0.5 * len(box)  # left the 2-frame window: new again


@pytest.mark.parametrize("update", ["window", "decay"])
def test_an_empty_frame_is_reported_and_changes_nothing(rng, update, tmp_path, capsys):
    """A blinded sensor's frame (no finite point, or no point) is yielded empty and the stream goes
    on: the model neither learns nor forgets, so what follows is as without it."""
    frames, _ = stream(rng)
    blind = [np.full((7, 3), np.nan), np.zeros((0, 3))]
    opts = dict(update=update, lattice=sdp.Lattice(voxel_size=0.03), **({"window": 2} if update == "window" else {}))
    ref = room_scene(rng)
    plain = list(watch(ref, frames, **opts))
    gappy = list(watch(ref, frames[:4] + blind + frames[4:], **opts))
    assert [r.empty for r in gappy] == [False] * 4 + [True, True] + [False] * 2
    assert [len(r.appeared) for r in gappy[4:6]] == [7, 0] and not any(r.appeared.any() for r in gappy[4:6])
    for a, b in zip(plain, gappy[:4] + gappy[6:]):
        np.testing.assert_array_equal(a.appeared, b.appeared)
    # sdp watch: an empty file in the folder is a line of its own (JSON Lines with --json), not an error
    from sdp.cli._main import main

    np.save(tmp_path / "ref.npy", ref)
    for ext in (".ply", ".xyz", ".las"):  # an empty PLY, text file, LAS file of no point: each an empty frame
        folder = tmp_path / f"frames{ext}"
        folder.mkdir()
        for i, f in enumerate([frames[0], np.zeros((0, 3)), frames[3]]):
            if ext == ".xyz":  # sdp writes no text: the frames as text, the empty one a file of nothing
                np.savetxt(folder / f"f{i}.xyz", f)
            else:
                sdp.write_points(folder / f"f{i}{ext}", f)
        assert main([str(a) for a in ("watch", tmp_path / "ref.npy", folder, "--voxel-size", "0.03")]) == 0
        assert f"f1{ext}: 0 points, none finite: nothing compared" in capsys.readouterr().out
    assert main([str(a) for a in ("watch", tmp_path / "ref.npy", tmp_path / "frames.ply", "--voxel-size", "0.03",
                                  "--json")]) == 0
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["empty"] for r in lines] == [False, True, False] and lines[-1]["appeared"] > 0


@pytest.mark.slow
@pytest.mark.parametrize("align", [None, "gicp"])
def test_sdp_watch_folder(tmp_path, rng, align):
    import subprocess
    import sys

    frames, box = stream(rng)
    if align:  # a camera that moves 1.5° and 4 cm per frame
        frames = [moved(f, 1.5 * (i + 1), np.array([0.03, -0.02, 0.01]) * (i + 1)) for i, f in enumerate(frames)]
    sdp.write_points(tmp_path / "ref.ply", room_scene(rng))
    (tmp_path / "frames").mkdir()
    for i, f in enumerate(frames):
        sdp.write_points(tmp_path / "frames" / f"frame{i + 8}.npz", f)  # natural order: 8, 9, 10, ...
    np.savetxt(tmp_path / "frames" / "poses.txt", np.zeros((30, 8)))  # a recording's sidecar: not a frame
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "watch", str(tmp_path / "ref.ply"), str(tmp_path / "frames"),
                        "--voxel-size", "0.03", "--json"] + (["--align", align] if align else []),
                       capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    out = [json.loads(line) for line in p.stdout.splitlines()]  # JSON Lines: a frame a line
    assert [r["name"] for r in out] == [f"frame{i + 8}.npz" for i in range(6)]
    assert "1 file(s) of other formats left out, not frames: poses.txt" in p.stderr
    assert [r["appeared"] > 0 for r in out] == [False, False, False, True, False, False]
    assert all((r["transform"] is None) == (align is None) for r in out)


def moved(points, degrees, shift, centre=(2.0, 2.0, 1.0)):
    """``points`` turned about a vertical axis through ``centre`` and shifted: a camera that moved."""
    a = np.radians(degrees)
    r = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    return (points - centre) @ r.T + centre + shift


@pytest.mark.slow
@pytest.mark.parametrize("align", ["gicp", "density"])
def test_watch_registers_the_frames_of_a_moving_camera(rng, align):
    frames, box = stream(rng)
    poses = [(1.5 * (i + 1), np.array([0.03, -0.02, 0.01]) * (i + 1)) for i in range(len(frames))]
    seen = [moved(f, deg, shift) for f, (deg, shift) in zip(frames, poses, strict=True)]  # 1.5° and 4 cm more per frame
    still = list(watch(room_scene(rng), seen, update="window", window=3, min_region_points=50,
                       lattice=sdp.Lattice(voxel_size=0.03)))
    assert all(r.n_appeared + r.not_comparable.sum() > 0 for r in still[:3])  # not registered: walls look new
    reports = list(watch(room_scene(rng), seen, update="window", window=3, min_region_points=50, align=align,
                         lattice=sdp.Lattice(voxel_size=0.03)))
    assert all(r.n_appeared == 0 and r.not_comparable.sum() < 20 for r in reports[:3])  # registered: the room again
    assert reports[3].n_appeared > 0.5 * len(box)
    assert np.allclose(reports[3].regions[0].centroid, [2.2, 1.4, 0.95], atol=0.1)  # in the reference's frame
    for r, f, g in zip(reports, frames, seen, strict=True):  # the transform undoes the camera's motion
        assert np.sqrt(np.mean(np.sum((sdp.transform_points(r.transform, g) - f) ** 2, axis=1))) < 0.003
        assert "align" in r.timings and r.summary()["transform"] == r.transform.tolist()


def test_watch_align_needs_what_it_registers_onto(rng):
    field = sdp.DensityField.from_points(room_scene(rng, n=5000), voxel_size=0.05)
    with pytest.raises(ValueError, match="need the reference points"):
        next(watch(field, [room_scene(rng, n=5000)], align="gicp"))
    with pytest.raises(ValueError, match="need the reference points"):
        next(watch(field, [room_scene(rng, n=5000)], coverage=sdp.Coverage(sensor_origin=[0, 0, 1])))
    with pytest.raises(ValueError, match="method must be 'density' or 'gicp'"):
        next(watch(field, [room_scene(rng, n=5000)], align="icp"))


@pytest.mark.shared_data
def test_watch_sensor_origin_applies_the_visibility_test_of_detect_changes(shared_data):
    ref, cur = (sdp.read_points(shared_data / f"mosd/learn/learn{i}.pcd") for i in (6, 7))  # an object added
    voxel = sdp.auto_voxel_size(ref.xyz)
    plain = next(watch(ref.xyz, [cur.xyz], update="none", min_region_points=50,
                       lattice=sdp.Lattice(voxel_size=voxel), coverage=sdp.Coverage(enabled=False)))
    seen = next(watch(ref.xyz, [cur.xyz], update="none", min_region_points=50, lattice=sdp.Lattice(voxel_size=voxel),
                      coverage=sdp.Coverage(sensor_origin=ref.sensor_origin)))
    pair = sdp.detect_changes(ref.xyz, cur.xyz, min_region_points=50, lattice=sdp.Lattice(voxel_size=voxel),
                              coverage=sdp.Coverage(sensor_origin=np.stack([ref.sensor_origin, cur.sensor_origin])))
    np.testing.assert_array_equal(seen.appeared, pair.appeared)
    obj = cur.fields["label"] // 10
    new, old = obj == 3, obj == 2  # learn7 adds object 3 beside object 2
    assert seen.appeared[new].mean() > 0.9 and plain.appeared[new].mean() > 0.9
    assert seen.appeared[old].mean() < 0.5 * plain.appeared[old].mean()  # its edges: seen by the reference


@pytest.mark.slow
@pytest.mark.shared_data
def test_sdp_watch_decision_combined(tmp_path, shared_data):
    """``sdp watch --decision combined`` completes what the density finds on a real Kinect pair,
    as ``sdp.watch`` does."""
    import subprocess
    import sys

    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "learn21.pcd").symlink_to(shared_data / "mosd/learn/learn21.pcd")
    ref = shared_data / "mosd/learn/learn20.pcd"
    runs = [subprocess.run([sys.executable, "-m", "sdp.cli", "watch", str(ref), str(tmp_path / "frames"), "--json",
                            "--decision", dec], capture_output=True, text=True) for dec in ("point", "combined")]
    assert all(p.returncode == 0 for p in runs), runs[1].stderr
    density, combined = (json.loads(p.stdout.splitlines()[0])["appeared"] for p in runs)
    frame = next(sdp.watch(sdp.read_points(ref), [sdp.read_points(tmp_path / "frames" / "learn21.pcd")],
                           decision="combined"))
    assert 0 < density < combined == frame.n_appeared


@pytest.mark.slow  # subprocesses, 4–6 s: the whole suite only
def test_sdp_watch_sensor_origin_viewpoint(tmp_path, shared_data):
    import subprocess
    import sys

    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "learn7.pcd").symlink_to(shared_data / "mosd/learn/learn7.pcd")
    runs = [subprocess.run([sys.executable, "-m", "sdp.cli", "watch", str(shared_data / "mosd/learn/learn6.pcd"),
                            str(tmp_path / "frames"), "--json"] + extra, capture_output=True, text=True)
            for extra in (["--sensor-origin", "none"], ["--sensor-origin", "viewpoint"], [])]
    assert all(p.returncode == 0 for p in runs), runs[1].stderr
    plain, seen, default = (json.loads(p.stdout.splitlines()[0])["appeared"] for p in runs)
    assert 0 < seen < plain and default == seen  # the PCD's VIEWPOINT is used without being asked
    field = tmp_path / "ref.sdpf"
    ref = sdp.read_points(shared_data / "mosd/learn/learn6.pcd").xyz
    sdp.DensityField.from_points(ref, voxel_size=0.01).save(field)
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "watch", str(field), str(tmp_path / "frames"),
                        "--sensor-origin", "viewpoint"], capture_output=True, text=True)
    assert p.returncode != 0 and "not a field" in p.stderr


def test_a_frame_sharing_nothing_with_the_model_says_its_pose_is_a_guess(rng):
    from sdp.cli._text import frame_text

    pytest.importorskip("small_gicp")  # (the density alignment refuses clouds that do not overlap at all)
    room = room_scene(rng, n=20_000)
    far = room_scene(rng, n=20_000) + [50.0, 0.0, 0.0]  # nowhere near what the model holds
    same, apart = watch(room, [room_scene(rng, n=20_000), far], align="gicp", lattice=sdp.Lattice(voxel_size=0.05))
    assert same.overlap > 0.9 and "a guess" not in frame_text(same)
    assert apart.overlap < 0.05 and "its pose, and what the model learns from it, are a guess" in frame_text(apart)
    assert same.summary()["overlap"] == same.overlap


def test_a_window_too_large_for_memory_is_refused_at_its_first_frame(rng, monkeypatch):
    monkeypatch.setenv("SDP_MEMORY_LIMIT", "300MB")
    ref = rng.random((20_000, 3)) * [4.0, 4.0, 2.0]
    frames = [rng.random((20_000, 3)) * [4.0, 4.0, 2.0] for _ in range(3)]
    with pytest.raises(sdp.GridTooLargeError, match="a window of 5000 frames' fields .* give a smaller window"):
        list(sdp.watch(ref, frames, window=5000))
    assert len(list(sdp.watch(ref, frames, window=10))) == 3


def test_a_frame_whose_registration_moved_it_away_keeps_the_previous_pose_and_says_so(rng, monkeypatch):
    import dataclasses

    import sdp.stream._watch as W
    from sdp.cli._text import frame_text

    real = W.align_density

    def astray(field, points, *, init):  # as sdp.align answers when every level lost overlap
        return dataclasses.replace(real(field, points, init=init), matrix=init, diverged=True)

    monkeypatch.setattr(W, "align_density", astray)
    frames, _ = stream(rng)
    out = list(watch(room_scene(rng), frames[:2], align="density", lattice=sdp.Lattice(voxel_size=0.03)))
    assert all(f.pose_kept and np.array_equal(f.transform, np.eye(4)) for f in out)
    assert "the previous frame's pose was kept" in frame_text(out[0]) and out[0].summary()["pose_kept"]


def test_watch_refuses_a_folder_path_as_frames(tmp_path):
    # iterated, the path was frames of one letter each ("frame 0: could not convert string to float: '/'")
    for frames in (str(tmp_path), tmp_path):
        with pytest.raises(sdp.InvalidOptionError, match=r"not a path .*sdp\.cli\.watch_folder\(reference, folder\)"):
            next(watch(np.random.default_rng(0).random((500, 3)), frames))


def test_watch_refusal_names_only_what_watch_accepts(tmp_path, capsys):
    # the advice named --memory-limit (which sdp watch rejects) and a grid size it has not
    from sdp.cli import main

    pts = np.random.default_rng(0).uniform(0, 10, (1000, 3))
    np.save(tmp_path / "ref.npy", pts)
    (tmp_path / "frames").mkdir()
    np.save(tmp_path / "frames" / "f0.npy", pts)
    assert main(["watch", str(tmp_path / "ref.npy"), str(tmp_path / "frames"), "--voxel-size", "1e-4", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "$SDP_MEMORY_LIMIT" in err and "--voxel-size" in err
    assert "--memory-limit" not in err and "grid size" not in err
