"""Action recognition on MSR Action3D, the cross-subject protocol (issue 5).

Train on subjects 1, 3, 5, 7, 9; test on 2, 4, 6, 8, 10; a classifier per subset (AS1, AS2, AS3)
and one for all 20 actions; every choice by cross-validation on the training subjects. Prints
the table, writes benchmarks/results/actions.md and the confusion matrix of all 20 actions
(benchmarks/results/actions_confusion.png), with the time and the peak memory.
"""

from __future__ import annotations

import resource
import time
from pathlib import Path

import numpy as np

from sdp.actions import evaluate_protocol

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "msr_action3d"
RESULTS = ROOT / "benchmarks" / "results"
PUBLISHED = {"Li et al. 2010 (bag of 3D points)": {"AS1": 0.729, "AS2": 0.719, "AS3": 0.792, "mean_AS": 0.747},
             "STOP (Vieira et al. 2012), as tabulated later": {"all": 0.782}}


def confusion_png(path, truth, predicted):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = np.unique(truth)
    m = np.zeros((len(labels), len(labels)), int)
    for t, p in zip(np.searchsorted(labels, truth), np.searchsorted(labels, predicted), strict=True):
        m[t, p] += 1
    fig, ax = plt.subplots(figsize=(8, 7), dpi=110, layout="constrained")
    ax.imshow(m / m.sum(axis=1, keepdims=True), cmap="Blues", vmin=0, vmax=1)
    for (i, j), v in np.ndenumerate(m):
        if v:
            ax.text(j, i, v, ha="center", va="center", fontsize=7, color="w" if i == j else "k")
    names = [f"a{v:02d}" for v in labels]
    ax.set_xticks(range(len(labels)), names, rotation=90)
    ax.set_yticks(range(len(labels)), names)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(f"MSR Action3D, all 20 actions, cross-subject: accuracy {np.trace(m) / m.sum():.1%}")
    fig.savefig(path)
    plt.close(fig)


def main():
    if not DATA.is_dir():
        print(f"skipped: {DATA} not found")
        return
    t0 = time.perf_counter()
    r = evaluate_protocol(DATA, workers=2)
    total = time.perf_counter() - t0
    peak = max(resource.getrusage(who).ru_maxrss for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    lines = ["# Action recognition: MSR Action3D, cross-subject\n",
             f"{r['sequences']} sequences; train on subjects 1, 3, 5, 7, 9, test on 2, 4, 6, 8, 10. Classifier "
             "alpha chosen by leave-one-subject-out cross-validation on the training subjects only; the test "
             "subjects are used once.\n",
             "| set | test accuracy | cross-validated (training subjects) | alpha | "
             + " | ".join(PUBLISHED) + " |", "|---|---:|---:|---:|" + "---:|" * len(PUBLISHED)]
    for name, acc in r["accuracy"].items():
        cv = r["cv_accuracy"].get(name)
        pub = " | ".join(f"{p[name]:.1%}" if name in p else "" for p in PUBLISHED.values())
        lines.append(f"| {name} | {acc:.1%} | {'' if cv is None else f'{cv:.1%}'} | "
                     f"{r['alpha'].get(name, '')} | {pub} |")
    lines.append(f"\nTime: read + describe {r['timings']['read_and_describe']:.1f} s (2 processes), train + test "
                 f"{r['timings']['train_and_test']:.1f} s, total {total:.1f} s. Peak memory (largest process): "
                 f"{peak / 1024:.0f} MiB.\n")
    text = "\n".join(lines)
    print(text)
    (RESULTS / "actions.md").write_text(text)
    confusion_png(RESULTS / "actions_confusion.png", np.array(r["confusion"]["all"]["truth"]),
                  np.array(r["confusion"]["all"]["predicted"]))


if __name__ == "__main__":
    main()
