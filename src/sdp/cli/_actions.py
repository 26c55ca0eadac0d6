"""``sdp action`` as functions: train, predict (also on a live stream) and the cross-subject
protocol (:mod:`sdp.actions`)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ..defaults import DEFAULTS
from ..errors import SDPError
from ..io._output import check_outputs

__all__ = ["train_actions", "predict_actions", "stream_actions", "evaluate_actions"]


def train_actions(data_dir, *, output, subjects=None, workers: int = os.cpu_count() or 1):
    """Fit an action classifier on a folder of ``aXX_sYY_eZZ`` depth sequences and save it
    (``sdp action train``); ``subjects``: "1,3,5" or numbers to train on (default all).
    Returns (model, cross-validated accuracy, sequences used)."""
    from ..actions import _actions as actions

    check_outputs([output], [data_dir])
    if Path(output).suffix.lower() != ".npz":
        raise SDPError(f"{output}: an action model is a NumPy .npz file: name it ….npz")
    rows = actions.list_sequences(data_dir)
    if subjects:
        try:
            wanted = {int(v) for v in (subjects.split(",") if isinstance(subjects, str) else subjects)}
        except ValueError:
            raise SDPError(f"--subjects takes subject numbers such as 1,3,5, got {subjects!r}") from None
        rows = [r for r in rows if r[2] in wanted]
    x = actions.describe_sequences([r[0] for r in rows], workers=workers)
    model, cv = actions.train(x, np.array([r[1] for r in rows]), np.array([r[2] for r in rows]))
    model.save(output)
    return model, cv, len(rows)


def predict_actions(model, sequences) -> list[tuple[str, int]]:
    """(sequence, action label) of each depth-sequence file, by a saved model (``sdp action predict``)."""
    from ..actions import _actions as actions

    if not sequences:
        raise SDPError("sdp action predict needs depth sequences, or --stream FRAMES")
    m = actions.ActionModel.load(model)
    return [(str(p), int(m.predict(actions.sequence_descriptor(actions.read_sequence(p)))[0])) for p in sequences]


def stream_actions(model, source, *, window: int = DEFAULTS.action_window, every: int = DEFAULTS.action_every):
    """(frame number from 1, action label) at each report of an :class:`sdp.actions._actions.ActionStream`
    over the frames of ``source`` (``sdp action predict MODEL --stream SOURCE``)."""
    from ..actions import _actions as actions

    stream = actions.ActionStream(actions.ActionModel.load(model), window=window, every=every,
                                  min_frames=min(10, window))
    for frame in actions.read_frames(source):
        label = stream.push(frame)
        if label is not None:
            yield stream.n_frames, label


def evaluate_actions(data_dir, *, splits: str = "standard", workers: int = os.cpu_count() or 1) -> dict:
    """The cross-subject protocol as ``sdp action eval --json`` prints it.

    ``splits="standard"``: train on subjects 1, 3, 5, 7, 9, test on the others
    (:func:`sdp.actions._actions.evaluate_protocol`): accuracy per subset (fractions), ``cv``,
    ``alpha``, ``timings``, ``sequences``. ``splits="all"``: every five-subject training set
    (:func:`sdp.actions.evaluate_splits`): ``protocol``, ``splits``, ``summary`` (per subset: mean,
    std, min, max, the standard split's accuracy, rank and percentile), ``per_split``,
    ``confusion`` (summed over the splits), ``timings``, ``sequences``."""
    if splits not in ("standard", "all"):
        raise SDPError(f"--splits takes standard or all, got {splits!r}")
    if splits == "all":
        from ..actions import _splits

        t0 = time.perf_counter()
        r = _splits.evaluate_splits(data_dir, workers=workers)
        r["timings"]["total"] = time.perf_counter() - t0
        return dict(protocol=f"all {r['splits']} splits of {_splits.N_TRAIN} training subjects", **r)
    from ..actions import _actions as actions

    t0 = time.perf_counter()
    r = actions.evaluate_protocol(data_dir, workers=workers)
    r["timings"]["total"] = time.perf_counter() - t0
    return dict(r["accuracy"], cv=r["cv_accuracy"], alpha=r["alpha"], timings=r["timings"], sequences=r["sequences"])

