"""Agreement between predicted and true per-point change labels.

References
----------
.. [1] J. Cohen, "A coefficient of agreement for nominal scales", Educational and
   Psychological Measurement 20(1), 1960.
.. [2] H. Vieira Neto and U. Nehmzow, "Visual novelty detection with automatic scale
   selection", Robotics and Autonomous Systems 55(9), 2007 (kappa bands used by the paper).
"""

from __future__ import annotations

import numpy as np

from ..errors import SDPError

__all__ = ["confusion_matrix", "kappa", "scores"]


def _binary(values, name: str) -> np.ndarray:
    """``values`` as booleans, if they are booleans or numbers 0 and 1; else a one-line error (a
    change state's 2, not comparable, would count as changed; text and NaN would count too)."""
    v = np.asarray(values)
    if v.dtype == bool:
        return v.ravel()
    if v.dtype.kind not in "iuf":
        raise SDPError(f"{name} labels must be booleans or 0/1, got values of type {v.dtype}")
    if v.size and not np.isin(v, (0, 1)).all():
        odd = v[~np.isin(v, (0, 1))].ravel()[0].item()
        raise SDPError(f"{name} labels must be booleans or 0/1, got {odd!r}: give a change state's (state == 1) with "
                       f"comparable=(state != 2), as sdp eval does")
    return v.astype(bool).ravel()


def _labels(truth, predicted) -> tuple[np.ndarray, np.ndarray]:
    t, p = _binary(truth, "truth"), _binary(predicted, "predicted")
    if t.shape != p.shape:
        raise SDPError(f"truth has {t.size} labels and predicted {p.size}: they must label the same points")
    return t, p


def confusion_matrix(truth, predicted) -> np.ndarray:
    """2×2 counts ``[[tn, fp], [fn, tp]]`` (rows: truth, columns: prediction), as scikit-learn."""
    t, p = _labels(truth, predicted)
    return np.bincount(2 * t + p, minlength=4).reshape(2, 2)


def kappa(truth, predicted) -> float:
    """Cohen's kappa κ = (p_o − p_e) / (1 − p_e) of two boolean labelings.

    Equal to ``sklearn.metrics.cohen_kappa_score``; NaN when it is undefined (both labelings
    constant and equal, p_e = 1). Bands used by the paper: < 0.1 none, 0.1–0.4 weak,
    0.4–0.6 clear, > 0.6 strong agreement.
    """
    c = confusion_matrix(truth, predicted).astype(np.float64)
    n = c.sum()
    if n == 0:
        raise SDPError("kappa of zero labels is undefined")
    po = (c[0, 0] + c[1, 1]) / n
    pe = (c[0].sum() * c[:, 0].sum() + c[1].sum() * c[:, 1].sum()) / n**2
    return float("nan") if pe == 1 else float((po - pe) / (1 - pe))


def scores(truth, predicted, *, comparable=None) -> dict[str, float]:
    """Kappa, accuracy, precision, recall, F1 and IoU of the "change" class, and the counts.

    Parameters
    ----------
    truth, predicted : array_like of bool
        One label per point (True: changed).
    comparable : array_like of bool, optional
        Points that could be compared (e.g. ``~result.current_not_comparable``): the scores
        cover these only, and ``not_comparable`` counts the others, as M3C2's users leave
        NaN distances out of their statistics.

    Ratios whose denominator is 0 are NaN.
    """
    t, p = _labels(truth, predicted)
    if comparable is not None and np.asarray(comparable).dtype != bool:  # as truth and predicted: labels, not counts
        raise SDPError(f"comparable must be booleans (True: compared), got {np.asarray(comparable).dtype}")
    keep = np.ones(t.size, bool) if comparable is None else np.asarray(comparable, bool).ravel()
    if keep.shape != t.shape:
        raise SDPError(f"comparable has {keep.size} labels and truth {t.size}: they must label the same points")
    t, p = t[keep], p[keep]
    (tn, fp), (fn, tp) = confusion_matrix(t, p)

    def ratio(a, b):
        return float(a / b) if b else float("nan")

    precision, recall = ratio(tp, tp + fp), ratio(tp, tp + fn)
    return {"kappa": kappa(t, p) if t.size else float("nan"), "accuracy": ratio(tp + tn, tp + tn + fp + fn),
            "precision": precision, "recall": recall, "f1": ratio(2 * tp, 2 * tp + fp + fn),
            "iou": ratio(tp, tp + fp + fn), "tp": int(tp), "fp": int(fp), "fn": int(fn), "tn": int(tn),
            "not_comparable": int((~keep).sum())}
