import numpy as np
import pytest

import sdp


# scikit-learn imported by the test, not at collection (2 s in every xdist worker), and by one worker
@pytest.mark.xdist_group("scikit-learn")
@pytest.mark.parametrize("seed", range(5))
def test_kappa_and_scores_match_scikit_learn(seed):
    from sklearn.metrics import cohen_kappa_score
    from sklearn.metrics import confusion_matrix as sk_confusion
    from sklearn.metrics import f1_score, jaccard_score

    rng = np.random.default_rng(seed)
    truth = rng.random(1000) < 0.2
    pred = np.where(rng.random(1000) < 0.8, truth, rng.random(1000) < 0.5)
    assert sdp.kappa(truth, pred) == pytest.approx(cohen_kappa_score(truth, pred), abs=1e-12)
    np.testing.assert_array_equal(sdp.confusion_matrix(truth, pred), sk_confusion(truth, pred, labels=[0, 1]))
    s = sdp.scores(truth, pred)
    assert s["f1"] == pytest.approx(f1_score(truth, pred))
    assert s["iou"] == pytest.approx(jaccard_score(truth, pred))


def test_kappa_edge_cases():
    assert sdp.kappa([1, 0, 1], [1, 0, 1]) == 1.0
    assert np.isnan(sdp.kappa([0, 0], [0, 0]))
    with pytest.raises(sdp.SDPError, match="same points"):
        sdp.kappa([1, 0], [1])
    assert np.isnan(sdp.scores([0, 0], [0, 0])["precision"])
    # labels are booleans or 0/1: a change state's 2 (not comparable), NaN or text would count as changed
    for bad, says in (([0, 1, 2], "got 2: give a change state's"), ([0.0, np.nan, 1.0], "got nan"),
                      (["no", "yes", "no"], "type")):
        with pytest.raises(sdp.SDPError, match=says):
            sdp.kappa([0, 1, 1], bad)
    assert sdp.kappa(np.array([0.0, 1.0, 1.0]), [False, True, True]) == 1.0
