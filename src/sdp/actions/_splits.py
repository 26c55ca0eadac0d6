"""Every five-subject split of MSR Action3D: the protocol that cannot be tuned.

The standard cross-subject split (train on subjects 1, 3, 5, 7, 9, test on the others) is one of
the C(10, 5) = 252 ways to choose five training subjects out of ten, and a noisy one: the
configuration (:data:`sdp.actions.PARAMETERS`) was chosen while looking at it. Here the
configuration stays frozen and every split is evaluated: the classifier of
:mod:`sdp.actions._actions` (each part's ``alpha`` by leave-one-subject-out cross-validation
inside the five training subjects) is trained on five subjects and tested on the other five, for
each subset (AS1, AS2, AS3, all 20 actions). The report is the distribution over the splits (mean,
standard deviation, minimum, maximum), the standard split's place in it and the confusion summed
over the splits.

The descriptors are computed once for all sequences and reduced at once to their Gram matrices
(one per part, the body's and the hand's): the ridge classifiers are solved in the dual, so a
split's training, its cross-validation and its test need nothing else (for a test sequence, its
dot products with the training sequences; rows of the test subjects are read only as the test's
rows, never as training or validation data). The 252 splits then cost the classifier alone.

Which rows a split trains, validates and tests on comes from two functions only,
:func:`_split_rows` and :func:`_cv_folds`, called in the parent process before any work is
shared out, so a test can observe every index set the evaluation uses.

References
----------
.. [1] W. Li, Z. Zhang and Z. Liu, "Action recognition based on a bag of 3D points", CVPR
   Workshops 2010 (MSR Action3D, the cross-subject protocol).
.. [2] J. Wang, Z. Liu, Y. Wu and J. Yuan, "Mining actionlet ensemble for action recognition with
   depth cameras", CVPR 2012 (the 252 five-subject splits, mean and spread).
.. [3] O. Oreifej and Z. Liu, "HON4D: Histogram of oriented 4D normals for activity recognition
   from depth sequences", CVPR 2013 (the same: mean and standard deviation over 252 splits).
"""

from __future__ import annotations

import os
import time
from itertools import combinations

import numpy as np

from .._core._validate import integer_at_least
from ..errors import SDPError
from ._actions import (
    ALPHAS,
    PARTS,
    SUBSETS,
    TRAIN_SUBJECTS,
    _choose_alphas,
    _grams,
    _ridge_scores,
    describe_sequences,
    list_sequences,
)

__all__ = ["training_sets", "split_accuracies", "evaluate_splits", "N_TRAIN"]

#: Training subjects per split: five of MSR Action3D's ten, as the standard split.
N_TRAIN = 5


def training_sets(subjects, n_train: int = N_TRAIN) -> list[tuple[int, ...]]:
    """Every choice of ``n_train`` training subjects among the distinct ``subjects`` (sorted
    tuples, in lexicographic order): 252 for ten subjects and five."""
    distinct = sorted({int(v) for v in np.asarray(subjects).ravel()})
    if not 1 <= n_train < len(distinct):
        raise SDPError(f"splits of {n_train} training subjects need more than {n_train} subjects, "
                       f"got {len(distinct)}")
    return list(combinations(distinct, n_train))


def _split_rows(y: np.ndarray, s: np.ndarray, training: tuple[int, ...], actions) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the sequences of ``actions``: those of the ``training`` subjects and the others (the test)."""
    mine = np.isin(y, actions)
    inside = np.isin(s, training)
    return np.flatnonzero(mine & inside), np.flatnonzero(mine & ~inside)


def _cv_folds(s: np.ndarray, train: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Leave-one-subject-out folds (fit rows, validation rows) inside the training rows ``train``."""
    return [(train[s[train] != v], train[s[train] == v]) for v in np.unique(s[train])]


def _plan(y, s, sets, subsets) -> list[tuple]:
    """The tasks of an evaluation, one per (split, subset): (split number, subset, training rows,
    test rows, folds). Refuses, before any work, a split that leaves a subset without test
    sequences or with fewer than two actions to train on."""
    tasks = []
    for k, training in enumerate(sets):
        for name, actions in subsets.items():
            train, test = _split_rows(y, s, training, actions)
            if len(np.unique(y[train])) < 2 or len(test) == 0:
                raise SDPError(f"training subjects {','.join(map(str, training))}: subset {name} needs two actions "
                               "to train on and a test sequence")
            tasks.append((k, name, train, test, _cv_folds(s, train)))
    return tasks


def _fit_and_test(grams, y, shares, alphas, task):
    """One task of :func:`_plan`: the alphas by cross-validation over its folds, then the test
    rows' predicted actions by the parts' ridge classifiers on the training rows, their decision
    values mixed by ``shares``. Returns (split number, subset, predictions, alphas)."""
    k, name, train, test, folds = task
    chosen = _choose_alphas(grams, y, folds, alphas)
    mixed = sum(share * _ridge_scores(gram, train, test, y, a)[1]
                for gram, a, share in zip(grams, chosen, shares, strict=True))
    return k, name, np.unique(y[train])[np.argmax(mixed, axis=1)], tuple(float(a) for a in chosen)


_SHARED: tuple = ()  # a worker's (grams, y, shares, alphas), inherited at the fork


def _init_worker(state):
    global _SHARED
    _SHARED = state
    _one_blas_thread()  # for the worker's life


def _worker_chunk(tasks):
    return [_fit_and_test(*_SHARED, task) for task in tasks]


def _one_blas_thread():
    """A context in which BLAS uses one thread: the solves are a few hundred unknowns, where BLAS
    threads spin more than they compute (10x the CPU time on a loaded 2-core machine); the
    processes share the cores instead."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(1)


def _run(tasks, state, workers: int):
    """The results of :func:`_fit_and_test` for every task, in ``workers`` processes."""
    if workers <= 1 or len(tasks) < 2:
        with _one_blas_thread():
            return [_fit_and_test(*state, task) for task in tasks]
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    chunks = [tasks[i::4 * workers] for i in range(4 * workers)]  # interleaved: the chunks cost alike
    with ProcessPoolExecutor(workers, mp_context=get_context("fork"), initializer=_init_worker,
                             initargs=(state,)) as pool:
        return [r for chunk in pool.map(_worker_chunk, chunks) for r in chunk]


def _summary(values: np.ndarray, standard: int | None) -> dict:
    out = {"mean": float(values.mean()), "std": float(values.std()), "min": float(values.min()),
           "max": float(values.max())}
    if standard is not None:
        v = values[standard]
        above, tied = int(np.sum(values > v)), int(np.sum(values == v)) - 1
        out["standard"] = float(v)
        out["standard_rank"] = above + 1  # 1: the best split; ties share the better rank
        out["splits_above"], out["splits_tied"], out["splits_below"] = above, tied, len(values) - above - tied - 1
        # mid-rank percentile: the share of the other splits below it, ties counting half
        out["standard_percentile"] = float(100.0 * (out["splits_below"] + 0.5 * tied) / max(len(values) - 1, 1))
    return out


def _from_grams(grams, y, s, *, subsets, n_train, alphas, shares, workers) -> dict:
    sets = training_sets(s, n_train)
    tasks = _plan(y, s, sets, subsets)
    results = _run(tasks, (grams, y, tuple(shares), tuple(alphas)), workers)
    accuracy = {name: np.empty(len(sets)) for name in subsets}
    chosen = {name: [None] * len(sets) for name in subsets}
    orders = {name: np.unique(np.asarray(a)) for name, a in subsets.items()}
    confusion = {name: np.zeros((len(a), len(a)), np.int64) for name, a in orders.items()}
    tests = {(k, name): test for k, name, _, test, _ in tasks}
    for k, name, predicted, alpha in results:
        truth = y[tests[k, name]]
        accuracy[name][k] = np.mean(predicted == truth)
        chosen[name][k] = alpha
        order = orders[name]
        np.add.at(confusion[name], (np.searchsorted(order, truth), np.searchsorted(order, predicted)), 1)
    if all(n in subsets for n in ("AS1", "AS2", "AS3")):
        accuracy["mean_AS"] = np.mean([accuracy[n] for n in ("AS1", "AS2", "AS3")], axis=0)
    standard = sets.index(TRAIN_SUBJECTS) if TRAIN_SUBJECTS in sets else None
    return {
        "splits": len(sets),
        "summary": {name: _summary(v, standard) for name, v in accuracy.items()},
        "per_split": [dict({"train": list(t)}, **{name: float(v[k]) for name, v in accuracy.items()},
                           alpha={name: list(chosen[name][k]) for name in subsets}) for k, t in enumerate(sets)],
        "confusion": {name: {"actions": orders[name].tolist(), "matrix": m.tolist(),
                             "accuracy": [float(m[i, i] / m[i].sum()) if m[i].sum() else None for i in range(len(m))]}
                      for name, m in confusion.items()},
    }


def split_accuracies(descriptors: np.ndarray, actions, subjects, *, subsets=None, n_train: int = N_TRAIN,
                     alphas=ALPHAS, parts=None, workers: int = 1) -> dict:
    """Accuracy of the action classifier on every split of the subjects into ``n_train`` training
    subjects and the others, one classifier per subset of actions.

    Parameters
    ----------
    descriptors : (n, d) array
        One descriptor per sequence (:func:`sdp.actions.sequence_descriptor`).
    actions, subjects : (n,) arrays
        Each sequence's action and subject.
    subsets : dict, optional
        Name → actions, a classifier each; default :data:`sdp.actions._actions.SUBSETS` (AS1, AS2,
        AS3, all 20 actions).
    n_train : int
        Training subjects per split (5: the 252 splits of MSR Action3D's ten subjects).
    alphas : sequence of float
        The ridge regularizations among which each part's is chosen, per split, by
        leave-one-subject-out cross-validation inside the split's training subjects.
    parts : tuple, optional
        (first column, end, share) of each part with a classifier of its own (as :func:`train`).
    workers : int
        Processes sharing the splits.

    Returns
    -------
    dict
        ``splits`` (how many), ``summary`` (per subset and ``mean_AS``: mean, std over the
        splits, min, max, and the standard split's accuracy, rank and percentile when its
        training subjects 1, 3, 5, 7, 9 are among the splits), ``per_split`` (training subjects,
        accuracy per subset, chosen alphas) and ``confusion`` (per subset: true action × predicted
        action, summed over the splits, and each action's accuracy).

    References
    ----------
    .. [1] J. Wang et al., "Mining actionlet ensemble for action recognition with depth cameras",
       CVPR 2012.
    """
    x, y, s = np.asarray(descriptors), np.asarray(actions), np.asarray(subjects)
    if x.ndim != 2 or not len(x) == len(y) == len(s):
        raise SDPError(f"descriptors {x.shape}, {len(y)} actions and {len(s)} subjects: one row of each per sequence")
    if parts is None:
        parts = PARTS if x.shape[1] == PARTS[-1][1] else ((0, x.shape[1], 1.0),)
    subsets = dict(SUBSETS if subsets is None else subsets)
    if integer_at_least("n_train", n_train, 1) < 2:  # the choices are cross-validated leaving one subject out
        raise SDPError(f"n_train must be at least 2 (one training subject is left out in turn), got {n_train}")
    _plan(y, s, training_sets(s, n_train), subsets)  # bad splits refused before the Gram matrices
    return _from_grams(_grams(x, np.arange(len(x)), parts), y, s, subsets=subsets, n_train=n_train, alphas=alphas,
                       shares=[p[2] for p in parts], workers=workers)


def evaluate_splits(folder: str | os.PathLike, *, n_train: int = N_TRAIN, workers: int = os.cpu_count() or 1) -> dict:
    """The action classifier on every five-subject split of a folder of ``aXX_sYY_eZZ`` depth
    sequences (MSR Action3D: 252 splits), the configuration frozen (:data:`PARAMETERS`).

    Every sequence is described once (``workers`` processes); the descriptors are reduced to their
    Gram matrices and dropped, and the splits shared among ``workers`` processes. Returns
    :func:`split_accuracies`' dictionary with ``sequences`` and ``timings`` (seconds: describe,
    gram, splits).
    """
    t0 = time.perf_counter()
    rows = list_sequences(folder)
    y, s = np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
    subsets = dict(SUBSETS)
    _plan(y, s, training_sets(s, n_train), subsets)  # every split checked before the first sequence is read
    x = describe_sequences([r[0] for r in rows], workers=workers)
    t1 = time.perf_counter()
    parts = PARTS if x.shape[1] == PARTS[-1][1] else ((0, x.shape[1], 1.0),)
    grams = _grams(x, np.arange(len(x)), parts)
    del x  # 1.4 GB for MSR Action3D: the splits need the Gram matrices only
    t2 = time.perf_counter()
    out = _from_grams(grams, y, s, subsets=subsets, n_train=n_train, alphas=ALPHAS, shares=[p[2] for p in parts],
                      workers=workers)
    t3 = time.perf_counter()
    out["sequences"] = len(rows)
    out["timings"] = {"describe": t1 - t0, "gram": t2 - t1, "splits": t3 - t2}
    return out
