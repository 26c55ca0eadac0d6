import subprocess
import sys

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d

from sdp import SDPError
from sdp.actions._actions import (
    BODY_SIZE,
    FLOW_WEIGHT,
    FOCAL,
    GAPS,
    HAND_GRID,
    HAND_HALF,
    HAND_SIZE,
    LEVELS,
    PARAMETERS,
    SIGMA,
    STEP,
    ActionModel,
    ActionStream,
    _blur_matrix,
    _body_frame,
    _densities,
    _flow_pattern,
    _hand_track,
    _soft_segments,
    depth_to_points,
    describe_sequences,
    evaluate_protocol,
    frame_densities,
    list_sequences,
    read_sequence,
    sequence_descriptor,
    train,
)


def person(t, arm, rng, h=240, w=320):
    """A depth frame of a stick figure at 2.5 m whose arm is raised by ``arm`` (0..1)."""
    d = np.zeros((h, w), np.uint16)
    d[60:200, 150:170] = 2500  # body
    d[60:80, 145:175] = 2500  # head and shoulders
    top = int(120 - 60 * arm)
    d[top:120, 170:176] = 2480  # right arm
    return d + (rng.integers(0, 3, d.shape) * (d > 0)).astype(np.uint16)


def sequence(kind, rng, frames=20, shift=0):
    raise_arm = np.linspace(0, 1, frames) if kind == 1 else np.linspace(1, 0, frames)
    return np.stack([np.roll(person(t, a, rng), shift, axis=1) for t, a in enumerate(raise_arm)])


def test_bin_reader_and_back_projection(tmp_path, rng):
    depth = sequence(1, rng, frames=3)
    t, h, w = depth.shape
    (tmp_path / "a01_s01_e01_sdepth.bin").write_bytes(
        np.array([t, w, h], "<u4").tobytes() + depth.astype("<u4").tobytes())
    np.testing.assert_array_equal(read_sequence(tmp_path / "a01_s01_e01_sdepth.bin"), depth)
    (tmp_path / "cut.bin").write_bytes(np.array([t, w, h], "<u4").tobytes() + b"\0" * 100)
    with pytest.raises(SDPError, match="cut.bin.*header says 3 frames"):
        read_sequence(tmp_path / "cut.bin")
    pts, frame = depth_to_points(depth[:1])
    assert len(pts) == (depth[0] > 0).sum() and (frame == 0).all()
    centre = depth_to_points(np.pad(np.array([[1000]], np.uint16), ((0, 0), (0, 0))))[0]
    np.testing.assert_allclose(centre, [[0, 0, 1000]])  # principal point at the image centre


@pytest.mark.slow
def test_descriptor_is_body_centred(rng):
    a = sequence_descriptor(sequence(1, rng))
    b = sequence_descriptor(sequence(1, rng, shift=40))  # the same action elsewhere in the image
    c = sequence_descriptor(sequence(2, rng))  # the reverse action
    assert a.dtype == np.float32 and np.isfinite(a).all()
    n_blocks = len(LEVELS) * (1 + 4 * len(GAPS))  # density; appeared, disappeared (sum, max) per gap
    # every (level, channel) block L2-normalized; the flow blocks together hold FLOW_WEIGHT of that; body and hand
    assert len(a) == BODY_SIZE + HAND_SIZE
    assert a[:BODY_SIZE] @ a[:BODY_SIZE] == pytest.approx(n_blocks * (1 + FLOW_WEIGHT), rel=1e-5)
    assert a[BODY_SIZE:] @ a[BODY_SIZE:] == pytest.approx(n_blocks * (1 + FLOW_WEIGHT), rel=1e-5)
    assert a @ b > 0.95 * (a @ a) and a @ c < a @ b
    with pytest.raises(SDPError, match="foreground"):
        sequence_descriptor(np.zeros((3, 10, 10), np.uint16))


def test_train_predict_save_load(tmp_path, rng):
    x = np.stack([sequence_descriptor(sequence(k, rng, shift=int(rng.integers(-30, 30))))
                  for k in (1, 2) for _ in range(6)])
    y, subjects = np.repeat([1, 2], 6), np.tile([1, 2, 3, 4, 5, 6], 2)
    model, cv = train(x, y, subjects)
    assert cv == 1.0 and (model.predict(x) == y).all()
    again = ActionModel.load(model.save(tmp_path / "m.npz"))
    np.testing.assert_array_equal(again.predict(x), y)
    assert again.coef.dtype == np.float32  # half the size of float64, and faster to load
    (tmp_path / "bad.npz").write_bytes(b"not a model")
    with pytest.raises(SDPError, match="not an sdp action model") as err:
        ActionModel.load(tmp_path / "bad.npz")
    assert "pickle" not in str(err.value)  # NumPy's advice to load pickled data is not passed on
    np.savez(tmp_path / "cloud.npz", xyz=np.zeros((3, 3)), change=np.zeros(3))  # an .npz, not a model
    with pytest.raises(SDPError, match="cloud.npz: not an sdp action model .an .npz file that 'sdp action train'"):
        ActionModel.load(tmp_path / "cloud.npz")
    with pytest.raises(SDPError, match="gone.mat: no such file"):
        read_sequence(tmp_path / "gone.mat")
    from sdp.cli import train_actions

    with pytest.raises(SDPError, match="name it ….npz"):
        train_actions(tmp_path, output=tmp_path / "m.txt")


@pytest.mark.slow
@pytest.mark.shared_data
def test_real_sequences_two_actions(shared_data, tmp_path):
    """High arm wave vs. two-hand wave on MSR Action3D: trained on odd subjects, tested on even."""
    rows = [r for r in list_sequences(shared_data / "msr_action3d") if r[1] in (1, 5)]
    x = describe_sequences([r[0] for r in rows], workers=2)
    y, s = np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
    odd = s % 2 == 1
    model, _ = train(x[odd], y[odd], s[odd])
    assert np.mean(model.predict(x[~odd]) == y[~odd]) > 0.85
    model.save(tmp_path / "m.npz")
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "action", "predict", str(tmp_path / "m.npz"),
                        str(rows[0][0])], capture_output=True, text=True)
    assert p.returncode == 0 and p.stdout.strip().endswith("a01"), p.stderr
    # A stream of two test sequences, one after the other: at the last frame of each, the report is
    # that sequence's own prediction (the window then holds exactly it); with every=1, a report at
    # every frame once the window has its first min_frames.
    test = [(r, read_sequence(r[0])) for r in rows if r[2] % 2 == 0]
    first = next(d for r, d in test if r[1] == 1)
    second = next(d for r, d in test if r[1] == 5 and len(d) >= len(first))
    stream = ActionStream(model, window=len(second), every=1)
    for depth in (first, second):
        labels = [stream.push(frame) for frame in depth]
        assert labels[-1] == model.predict(sequence_descriptor(depth))[0]
    assert None not in labels  # the second sequence: reported at each of its frames


def test_frame_densities_unit_mass_and_exact_decimation(rng):
    depth = sequence(1, rng, frames=4)
    full = frame_densities(depth)
    assert full.shape == (4, 36, 36, 26)
    np.testing.assert_allclose(full.sum(axis=(1, 2, 3)), 1.0, atol=0.02)  # unit mass per frame (blur edges)
    np.testing.assert_allclose(frame_densities(depth, step=2), full[:, ::2, ::2, ::2], rtol=1e-5, atol=1e-9)
    for n in (36, 26):  # the blur is scipy's Gaussian filter (zero outside the grid), as a matrix
        impulses = gaussian_filter1d(np.eye(n), SIGMA, axis=0, mode="constant", truncate=3.0)
        np.testing.assert_allclose(_blur_matrix(n, 1), impulses, atol=1e-7)
        np.testing.assert_allclose(_blur_matrix(n, 2), impulses[::2], atol=1e-7)
    moved = np.roll(depth, 40, axis=2)  # the same body elsewhere in the image: the same grids
    np.testing.assert_allclose(frame_densities(moved), full, atol=0.05 * full.max())


def test_soft_temporal_segments():
    at = np.linspace(0.0, 1.0, 101)
    for level in (1, 2, 4):
        w = _soft_segments(at, level)
        assert w.shape == (101, level) and (w >= 0).all()
        np.testing.assert_allclose(w.sum(axis=1), 1.0)  # every frame counted once in all
    w = _soft_segments(np.array([0.125, 0.25, 0.375, 0.0, 1.0]), 4)
    np.testing.assert_allclose(w, [[1, 0, 0, 0], [0.5, 0.5, 0, 0], [0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1]])


def test_model_refuses_other_parameters(tmp_path, rng):
    x = rng.random((8, 5)).astype(np.float32)
    model, _ = train(x, np.repeat([1, 2], 4), np.tile([1, 2, 3, 4], 2))
    path = model.save(tmp_path / "m.npz")
    with np.load(path) as z:
        saved = dict(z)
    assert {k: tuple(np.atleast_1d(saved[k])) for k in PARAMETERS} == {
        k: tuple(np.atleast_1d(v)) for k, v in PARAMETERS.items()}
    saved["gaps"] = np.array([1, 2])
    np.savez(tmp_path / "old.npz", **saved)
    with pytest.raises(SDPError, match="old.npz: not an sdp action model.*other pattern parameters \\(gaps\\)"):
        ActionModel.load(tmp_path / "old.npz")


@pytest.mark.slow  # a CLI process or a Dask run: the full suite's
def test_action_stream_reports_each_action_soon_after_it_ends(tmp_path, rng, capsys):
    """Raise-arm then lower-arm, 20 frames each, in one stream: reported every 5 frames from the
    window of the last 20; the first action by frame 20, the second by frame 40."""
    from sdp.cli._main import main

    x = np.stack([sequence_descriptor(sequence(k, rng, shift=int(rng.integers(-30, 30))))
                  for k in (1, 2) for _ in range(4)])
    model, _ = train(x, np.repeat([1, 2], 4), np.tile([1, 2, 3, 4], 2))
    stream = ActionStream(model, window=20, every=5)
    frames = np.concatenate([sequence(1, rng), sequence(2, rng)])
    reports = {i + 1: label for i, f in enumerate(frames) if (label := stream.push(f)) is not None}
    assert sorted(reports) == [10, 15, 20, 25, 30, 35, 40]  # min_frames 10, then every 5
    assert reports[20] == 1 and reports[40] == 2
    with pytest.raises(SDPError, match="one \\(H, W\\) shape"):
        stream.push(frames[0][:10])
    with pytest.raises(SDPError, match="window >= min_frames"):
        ActionStream(model, window=5, min_frames=10)
    model.save(tmp_path / "m.npz")
    (tmp_path / "frames").mkdir()
    for i, f in enumerate(frames):
        np.save(tmp_path / "frames" / f"{i:04d}.npy", f)
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "action", "predict", str(tmp_path / "m.npz"), "--stream",
                        str(tmp_path / "frames"), "--window", "20", "--every", "10"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    lines = p.stdout.splitlines()
    assert [line.split(":")[0] for line in lines] == ["frame 10", "frame 20", "frame 30", "frame 40"], p.stdout
    assert lines[1] == "frame 20: a01" and lines[3] == "frame 40: a02", p.stdout
    capsys.readouterr()
    assert main(["action", "predict", str(tmp_path / "m.npz")]) == 2  # the command's own refusal, in this process
    assert "needs depth sequences, or --stream" in capsys.readouterr().err


def test_a_folder_of_depth_frames_is_read_in_natural_name_order(tmp_path):
    """f2 before f10, as sdp watch reads its frames: a plain sort would replay f10 after f1."""
    from sdp.actions._actions import read_frames

    for i in (1, 2, 10, 11):
        np.save(tmp_path / f"f{i}.npy", np.full((2, 3), i, np.uint16))
    assert [int(f[0, 0]) for f in read_frames(tmp_path)] == [1, 2, 10, 11]


def test_flow_channels_point_the_way_the_density_moves():
    """A blob carried along +x (then along −y) lights the +x (then −y) channel, not its opposite."""
    x = np.arange(18.0)[:, None, None]
    y, z = np.arange(18.0)[None, :, None], np.arange(13.0)[None, None, :]
    blob = [np.exp(-((x - 5 - t) ** 2 + (y - 9) ** 2 + (z - 6) ** 2) / 8) for t in range(8)]
    blocks = _flow_pattern(np.stack(blob).astype(np.float32))
    assert len(blocks) == 6 * len(LEVELS) and blocks[0].shape == (1, 18, 18, 13)
    plus_x, minus_x, plus_y, minus_y = (blocks[i].sum() for i in range(4))  # level 1: +x, −x, +y, −y, +z, −z
    assert plus_x > 20 * minus_x
    # normal flow sees the blob's flanks move along y too, as much one way as the other: no net y motion
    assert abs(plus_y - minus_y) < 0.01 * plus_x
    down = [np.exp(-((x - 9) ** 2 + (y - 12 + t) ** 2 + (z - 6) ** 2) / 8) for t in range(8)]
    blocks = _flow_pattern(np.stack(down).astype(np.float32))
    assert blocks[3].sum() > 20 * blocks[2].sum()
    assert all((b == 0).all() for b in _flow_pattern(np.stack(blob[:1]).astype(np.float32)))  # one frame: no motion


@pytest.mark.xdist_group("scikit-learn")  # one xdist worker imports it (2 s)
@pytest.mark.parametrize("n_classes", [2, 4])
def test_dual_fit_is_scikit_learns_ridge_classifier(rng, n_classes):
    """The classifier fitted from the Gram matrix is RidgeClassifier(alpha) on the float64 data:
    the same decision function (float32 coefficients) and the same labels."""
    from sklearn.linear_model import RidgeClassifier

    x = rng.random((48, 700)).astype(np.float32)
    y, subjects = rng.integers(1, n_classes + 1, 48), np.tile([1, 2, 3, 4], 12)
    model, _ = train(x, y, subjects)
    ref = RidgeClassifier(alpha=model.alpha[0]).fit(x.astype(np.float64), y)
    assert model.coef.dtype == np.float32 and len(model.alpha) == 1
    scores = x @ np.atleast_2d(model.coef).T + model.intercept
    np.testing.assert_allclose(scores.reshape(len(x), -1), ref.decision_function(x).reshape(len(x), -1), atol=1e-5)
    np.testing.assert_array_equal(model.predict(x), ref.predict(x))
    # two parts (as the body's and the hand's): the mix of a RidgeClassifier on each part's columns
    x[:, 500:] *= 3.0  # another scale: another alpha
    model, _ = train(x, y, subjects, parts=((0, 500, 0.7), (500, 700, 0.3)))
    assert len(model.alpha) == 2
    refs = [RidgeClassifier(alpha=a).fit(x[:, cols].astype(np.float64), y)
            for a, cols in zip(model.alpha, (slice(0, 500), slice(500, 700)), strict=True)]
    mixed = 0.7 * refs[0].decision_function(x[:, :500]) + 0.3 * refs[1].decision_function(x[:, 500:])
    scores = x @ np.atleast_2d(model.coef).T + model.intercept
    np.testing.assert_allclose(scores.reshape(len(x), -1), mixed.reshape(len(x), -1), atol=1e-5)


def test_hand_box_follows_the_moving_hand(rng):
    """A hand raised beside a still body: the hand track follows it (the body's still parts and
    sensor noise do not pull it), and the hand box holds the hand, centred."""
    frames, h, w = 16, 240, 320
    depth = np.stack([person(t, 0.0, rng) for t in range(frames)])
    rows = 110 - 4 * np.arange(frames)  # left of the body (columns 145-175; the box's half: 36 columns), upwards
    for t, r in enumerate(rows):
        depth[t, r:r + 8, 90:98] = 2400
    centre, height = _body_frame(depth)
    grids = frame_densities(depth, step=STEP)
    track = _hand_track(grids, centre, height)
    expected_x = (93.5 - (w - 1) / 2.0) * 2400 / FOCAL
    expected_y = ((h - 1) / 2.0 - rows - 3.5) * 2400 / FOCAL
    middle = slice(3, frames - 3)  # the temporal smoothing pulls the ends in
    assert np.abs(track[middle, 0] - expected_x).max() < 0.05 * height  # the box: ±0.25 body heights
    assert np.abs(track[middle, 1] - expected_y[middle]).max() < 0.05 * height
    assert (np.diff(track[:, 1]) > 0).all()
    # the hand box (the body is out of it): the hand's share of the frame's points, centred on the box
    box = _densities(depth, track, np.full(3, HAND_HALF * height), (HAND_GRID,) * 3, 1)[middle]
    share = 64 / (depth[middle] > 0).sum(axis=(1, 2))
    np.testing.assert_allclose(box.sum(axis=(1, 2, 3)), share, rtol=0.1)
    nodes = np.arange(HAND_GRID) - (HAND_GRID - 1) / 2.0
    for axis in (1, 2, 3):
        profile = box.sum(axis=tuple(a for a in (1, 2, 3) if a != axis))
        assert np.abs(profile @ nodes / profile.sum(axis=1)).max() < 2.0  # within two nodes (0.06 body heights)
    # a still sequence: nothing to follow, the chest point
    still = np.stack([person(0, 0.0, rng)] * 4)
    c, hgt = _body_frame(still)
    np.testing.assert_allclose(_hand_track(frame_densities(still, step=STEP), c, hgt),
                               np.tile(c + [0, 0.25 * hgt, 0], (4, 1)))


@pytest.mark.slow
def test_evaluate_protocol_trains_then_classifies_the_test_subjects(tmp_path, rng):
    """Two actions per subset (raise arm / lower arm), training subjects 1, 3, 5 and test subjects
    2, 4: each subset's classifier is right on every test sequence, and the summary counts them."""
    raising, lowering = (1, 2, 15), (4, 3, 16)  # AS2: 1 / 4, AS1: 2 / 3, AS3: 15 / 16
    for action in raising + lowering:
        for subject in (1, 2, 3, 4, 5):
            depth = sequence(1 if action in raising else 2, rng, frames=12, shift=int(rng.integers(-30, 30)))
            t, h, w = depth.shape
            (tmp_path / f"a{action:02d}_s{subject:02d}_e01_sdepth.bin").write_bytes(
                np.array([t, w, h], "<u4").tobytes() + depth.astype("<u4").tobytes())
    r = evaluate_protocol(tmp_path, workers=1)
    assert r["sequences"] == 30
    assert {k: r["accuracy"][k] for k in ("AS1", "AS2", "AS3")} == {"AS1": 1.0, "AS2": 1.0, "AS3": 1.0}
    assert len(r["confusion"]["all"]["truth"]) == 12 and len(r["confusion"]["AS1"]["predicted"]) == 4
    assert set(r["models"]) == {"AS1", "AS2", "AS3", "all"} and all(0 <= v <= 1 for v in r["cv_accuracy"].values())
    (tmp_path / "a02_s02_e01_sdepth.bin").unlink()
    (tmp_path / "a03_s04_e01_sdepth.bin").unlink()  # AS1 has no test sequence any more
    (tmp_path / "a03_s02_e01_sdepth.bin").unlink()
    (tmp_path / "a02_s04_e01_sdepth.bin").unlink()
    with pytest.raises(SDPError, match="subset AS1 needs sequences of training and test subjects"):
        evaluate_protocol(tmp_path, workers=1)


@pytest.mark.parametrize("depth, says", [
    (np.ones((4, 4, 3)) * (1 + 1j), "complex"),
    (np.full((4, 4, 3), np.nan), "NaN or infinite"),
    (np.full((4, 4, 3), -5, np.int16), "negative"),
    (np.ones((4, 4, 1), np.uint16), "1 frame"),
])
def test_a_depth_sequence_that_is_not_one_is_refused_naming_its_file(tmp_path, depth, says):
    import scipy.io

    scipy.io.savemat(tmp_path / "a01_s01_e01_sdepth.mat", {"depth": depth})
    with pytest.raises(SDPError, match=rf"a01_s01_e01_sdepth.mat: .*{says}"):
        read_sequence(tmp_path / "a01_s01_e01_sdepth.mat")


def test_a_cut_or_empty_model_file_is_not_a_model(tmp_path, rng):
    x = np.stack([sequence_descriptor(sequence(k, rng)) for k in (1, 2) for _ in range(3)])
    model, _ = train(x, np.repeat([1, 2], 3), np.tile([1, 2, 3], 2))
    model.save(tmp_path / "m.npz")
    (tmp_path / "empty.npz").write_bytes(b"")
    (tmp_path / "cut.npz").write_bytes((tmp_path / "m.npz").read_bytes()[:200])
    for name in ("empty.npz", "cut.npz"):
        with pytest.raises(SDPError, match="not an sdp action model"):
            ActionModel.load(tmp_path / name)
    with pytest.raises(SDPError, match="no such file"):
        ActionModel.load(tmp_path / "missing.npz")
    assert list(ActionModel.load(tmp_path / "m.npz").classes) == [1, 2]
