"""Every k-subject split (sdp.actions._splits): no test subject's sequence in a split's training
or cross-validation, the same classifier as training on the split's subjects alone, the summary."""

import json
import subprocess
import sys
from math import comb

import numpy as np
import pytest

from sdp import SDPError
from sdp.actions import _actions, _splits
from sdp.actions._actions import train
from sdp.actions._splits import split_accuracies, training_sets
from sdp.cli._text import action_splits_text

SUBSETS = {"A": (1, 2), "B": (2, 3, 4), "all": (1, 2, 3, 4)}


def synthetic(rng, subjects=6, actions=4, repeats=2, dims=60):
    """Descriptors of ``actions`` classes (a mean each, plus a per-subject offset and noise): some
    errors, so that the splits differ."""
    means = rng.standard_normal((actions, dims))
    offsets = 0.8 * rng.standard_normal((subjects, dims))
    y, s = np.meshgrid(np.arange(1, actions + 1), np.arange(1, subjects + 1), indexing="ij")
    y, s = np.repeat(y.ravel(), repeats), np.repeat(s.ravel(), repeats)
    x = means[y - 1] + offsets[s - 1] + 1.2 * rng.standard_normal((len(y), dims))
    return x.astype(np.float32), y, s


def test_no_test_subject_enters_a_training_set_or_a_fold(rng, monkeypatch):
    """Every ridge solve of the evaluation is observed: its training rows and its validation rows
    belong to the training subjects of the split being fitted; the test rows of a split are
    exactly its other subjects' sequences of the subset."""
    x, y, s = synthetic(rng)
    current, solves, tasks = {}, [], []
    real_task, real_centred = _splits._fit_and_test, _actions._centred

    def task_spy(grams, yy, shares, alphas, task):
        k, name, train_rows, test_rows, folds = task
        current.update(k=k, name=name, test=test_rows)
        tasks.append(task)
        return real_task(grams, yy, shares, alphas, task)

    def centred_spy(gram, train_rows, test_rows, yy):  # every read of the Gram matrix by rows
        solves.append((current["k"], current["name"], train_rows.copy(), test_rows.copy()))
        return real_centred(gram, train_rows, test_rows, yy)

    monkeypatch.setattr(_splits, "_fit_and_test", task_spy)
    monkeypatch.setattr(_actions, "_centred", centred_spy)
    r = split_accuracies(x, y, s, subsets=SUBSETS, n_train=3, workers=1)
    sets = training_sets(s, 3)
    assert r["splits"] == len(sets) == comb(6, 3) and len(tasks) == len(sets) * len(SUBSETS)
    # per task and part (one here): three folds (leave one of three training subjects out), then the split's fit
    assert len(solves) == len(tasks) * (3 + 1)
    final = 0
    for k, name, train_rows, test_rows in solves:
        inside = set(sets[k])
        assert set(s[train_rows]) <= inside and np.isin(y[train_rows], SUBSETS[name]).all()
        if set(s[test_rows]) <= inside:  # a validation fold: one held-out training subject
            assert len(set(s[test_rows])) == 1 and not set(s[test_rows]) & set(s[train_rows])
        else:  # the split's test: every sequence of the subset by the other subjects, nothing else
            final += 1
            expected = np.flatnonzero(np.isin(y, SUBSETS[name]) & ~np.isin(s, sets[k]))
            np.testing.assert_array_equal(test_rows, expected)
            assert set(s[train_rows]) == inside
    assert final == len(tasks)
    for k, name, train_rows, test_rows, folds in tasks:  # the folds cover the training rows, one subject each
        np.testing.assert_array_equal(np.sort(np.concatenate([v for _, v in folds])), train_rows)
        assert not set(s[test_rows]) & set(sets[k])


def test_each_split_is_the_classifier_trained_on_its_subjects_alone(rng):
    """A split's accuracy and alphas are those of :func:`train` given its training rows only, and
    the summary and the confusion are those of the splits."""
    x, y, s = synthetic(rng)
    x[:, 40:] *= 2.0  # two parts (as the body's and the hand's), another scale each
    parts = ((0, 40, 0.6), (40, 60, 0.4))
    r = split_accuracies(x, y, s, subsets=SUBSETS, n_train=3, parts=parts, workers=1)
    for k in (0, 7, 19):
        row = r["per_split"][k]
        for name, acts in SUBSETS.items():
            tr = np.isin(s, row["train"]) & np.isin(y, acts)
            te = ~np.isin(s, row["train"]) & np.isin(y, acts)
            model, _ = train(x[tr], y[tr], s[tr], parts=parts)
            assert row[name] == pytest.approx(np.mean(model.predict(x[te]) == y[te]), abs=1e-12)
            assert tuple(row["alpha"][name]) == model.alpha
    acc = np.array([row["all"] for row in r["per_split"]])
    assert acc.min() < acc.max()  # the splits differ: the test means something
    assert r["summary"]["all"] == pytest.approx({"mean": acc.mean(), "std": acc.std(), "min": acc.min(),
                                                 "max": acc.max()})
    m = np.array(r["confusion"]["all"]["matrix"])
    # each sequence is tested in every split that leaves its subject out: C(5, 3) of the 20
    per_action = np.bincount(y)[1:]
    np.testing.assert_array_equal(m.sum(axis=1), per_action * comb(5, 3))
    assert np.trace(m) / m.sum() == pytest.approx(acc.mean())  # every split tests as many sequences
    assert "standard" not in r["summary"]["all"]  # subjects 1, 3, 5, 7, 9 are no split of six subjects
    again = split_accuracies(x, y, s, subsets=SUBSETS, n_train=3, parts=parts, workers=2)
    assert again == r  # the same in two processes


def test_standard_split_place_and_refusals(rng):
    values = np.array([0.9, 0.95, 0.95, 1.0, 0.8])
    out = _splits._summary(values, 1)
    assert out["standard"] == 0.95 and out["standard_rank"] == 2
    assert (out["splits_above"], out["splits_tied"], out["splits_below"]) == (1, 1, 2)
    assert out["standard_percentile"] == pytest.approx(100 * (2 + 0.5) / 4)
    assert len(training_sets(np.arange(1, 11))) == 252 and (1, 3, 5, 7, 9) in training_sets(range(1, 11))
    x, y, s = synthetic(rng, subjects=10, repeats=1)
    r = split_accuracies(x, y, s, subsets={"all": (1, 2, 3, 4)}, workers=1)
    assert r["splits"] == 252 and r["per_split"][r["summary"]["all"]["standard_rank"] - 1] is not None
    std = next(row for row in r["per_split"] if row["train"] == [1, 3, 5, 7, 9])
    assert r["summary"]["all"]["standard"] == std["all"]
    assert r["summary"]["all"]["splits_above"] == sum(row["all"] > std["all"] for row in r["per_split"])
    with pytest.raises(SDPError, match="more than 5 subjects"):
        training_sets([1, 2, 3, 4, 5])
    x, y, s = synthetic(rng)
    keep = ~((y == 1) & (s == 2))  # subject 2 never performs action 1: ...
    keep &= ~((y == 2) & (s == 2))  # ... nor action 2, so a split training on 1, 3, 4 tests subset A on no one ...
    with pytest.raises(SDPError, match="subset A needs"):
        split_accuracies(x[keep], y[keep], s[keep], subsets={"A": (1, 2)}, n_train=5, workers=1)


def test_cli_refuses_an_unknown_protocol(tmp_path):
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "action", "eval", str(tmp_path), "--splits", "some"],
                       capture_output=True, text=True)
    assert p.returncode == 2 and "--splits" in p.stderr
    from sdp.cli import evaluate_actions

    with pytest.raises(SDPError, match="splits"):
        evaluate_actions(tmp_path, splits="some")


@pytest.mark.slow
def test_cli_every_split_of_a_small_folder(tmp_path, rng):
    """``sdp action eval --splits all --json`` on six subjects: the C(6, 5) splits, each subset's figures."""
    from test_actions import sequence

    raising, lowering = (1, 2, 15), (4, 3, 16)  # AS2: 1 / 4, AS1: 2 / 3, AS3: 15 / 16
    for action in raising + lowering:
        for subject in range(1, 7):
            depth = sequence(1 if action in raising else 2, rng, frames=10, shift=int(rng.integers(-30, 30)))
            t, h, w = depth.shape
            (tmp_path / f"a{action:02d}_s{subject:02d}_e01_sdepth.bin").write_bytes(
                np.array([t, w, h], "<u4").tobytes() + depth.astype("<u4").tobytes())
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "action", "eval", str(tmp_path), "--splits", "all",
                        "--json", "--workers", "1"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    r = json.loads(p.stdout)
    assert r["splits"] == 6 and r["sequences"] == 36 and len(r["per_split"]) == 6
    assert {"AS1", "AS2", "AS3", "all", "mean_AS"} <= set(r["summary"])
    assert r["summary"]["AS1"]["mean"] == 1.0  # raise vs. lower arm: right in every split
    text = action_splits_text(r)
    assert "all 6 splits of 5 training subjects" in text and "\nAS1 " in text and "hardest actions" in text
