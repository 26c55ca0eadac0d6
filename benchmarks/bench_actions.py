"""Action recognition on MSR Action3D, the cross-subject protocol (issues 5 and 23).

Train on subjects 1, 3, 5, 7, 9; test on 2, 4, 6, 8, 10; a classifier per subset (AS1, AS2, AS3)
and one for all 20 actions; every choice by cross-validation on the training subjects. Prints,
from one run, the table, the confusion matrix and per-class accuracy of all 20 actions, the
number of configurations compared to choose the pattern (``actions_configurations.tsv``), the
time and the peak memory; writes benchmarks/results/actions.md and the confusion matrix as
benchmarks/results/actions_confusion.png.
"""

from __future__ import annotations

import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from sdp.actions._actions import ActionModel, evaluate_protocol, list_sequences, read_sequence, sequence_descriptor

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "msr_action3d"
RESULTS = ROOT / "benchmarks" / "results"
CONFIGURATIONS = ROOT / "benchmarks" / "actions_configurations.tsv"
NAMES = ("high arm wave", "horizontal arm wave", "hammer", "hand catch", "forward punch", "high throw", "draw x",
         "draw tick", "draw circle", "hand clap", "two hand wave", "side boxing", "bend", "forward kick", "side kick",
         "jogging", "tennis swing", "tennis serve", "golf swing", "pick up & throw")
PUBLISHED = {"Li et al. 2010 (bag of 3D points)": {"AS1": 0.729, "AS2": 0.719, "AS3": 0.792, "mean_AS": 0.747},
             "STOP (Vieira et al. 2012), as tabulated later": {"all": 0.782}}


def n_configurations(path=CONFIGURATIONS) -> int:
    """Configurations compared by cross-validation (numbered rows of the log; repeats and invalid runs have none)."""
    rows = [line.split("\t") for line in path.read_text().splitlines() if line and not line.startswith("#")]
    return sum(1 for r in rows[1:] if r[0].strip())


def confusion(truth, predicted):
    labels = np.unique(truth)
    m = np.zeros((len(labels), len(labels)), int)
    for t, p in zip(np.searchsorted(labels, truth), np.searchsorted(labels, predicted), strict=True):
        m[t, p] += 1
    return labels, m


def confusion_lines(truth, predicted) -> list[str]:
    """The confusion matrix (rows: true action, columns: predicted) and each action's accuracy, as Markdown."""
    labels, m = confusion(truth, predicted)
    head = "| true \\ predicted | " + " | ".join(f"a{v:02d}" for v in labels) + " | accuracy |"
    lines = [head, "|---|" + "---:|" * (len(labels) + 1)]
    for i, v in enumerate(labels):
        cells = " | ".join(str(c) if c else "." for c in m[i])
        lines.append(f"| a{v:02d} {NAMES[v - 1] if v <= len(NAMES) else ''} | {cells} | {m[i, i] / m[i].sum():.0%} |")
    return lines


def confusion_png(path, truth, predicted):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels, m = confusion(truth, predicted)
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
    with tempfile.TemporaryDirectory() as tmp:  # one sequence at a time, by the saved model of all 20 actions
        saved = r["models"]["all"].save(Path(tmp) / "model.npz")
        t1 = time.perf_counter()
        model = ActionModel.load(saved)
        load = time.perf_counter() - t1
    per_sequence, reading = [], []
    for path, *_ in list_sequences(DATA)[1::28]:  # 20 sequences across actions and subjects
        t1 = time.perf_counter()
        depth = read_sequence(path)
        t2 = time.perf_counter()
        model.predict(sequence_descriptor(depth))
        per_sequence.append(time.perf_counter() - t2)
        reading.append(t2 - t1)
    peak = max(resource.getrusage(who).ru_maxrss for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    lines = ["# Action recognition: MSR Action3D, cross-subject\n",
             f"{r['sequences']} sequences; train on subjects 1, 3, 5, 7, 9, test on 2, 4, 6, 8, 10. Classifier "
             "alphas chosen by leave-one-subject-out cross-validation on the training subjects only; the test "
             "subjects are used once per round of choices, with the configuration chosen before (three rounds so "
             "far).\n",
             "| set | test accuracy | cross-validated (training subjects) | alpha (body / hand) | "
             + " | ".join(PUBLISHED) + " |", "|---|---:|---:|---:|" + "---:|" * len(PUBLISHED)]
    for name, acc in r["accuracy"].items():
        cv = r["cv_accuracy"].get(name)
        pub = " | ".join(f"{p[name]:.1%}" if name in p else "" for p in PUBLISHED.values())
        lines.append(f"| {name} | {acc:.1%} | {'' if cv is None else f'{cv:.1%}'} | "
                     f"{' / '.join(f'{a:g}' for a in r['alpha'].get(name, ()))} | {pub} |")
    lines += [f"\nConfigurations compared (features and classifier families, each with its alpha grid), all by "
              f"cross-validation on the training subjects: {n_configurations()} "
              f"(`benchmarks/{CONFIGURATIONS.name}`).",
              "\nAll 20 actions, test subjects: confusion matrix and per-class accuracy\n"]
    lines += confusion_lines(np.array(r["confusion"]["all"]["truth"]), np.array(r["confusion"]["all"]["predicted"]))
    lines.append(f"\nTime: read + describe the training sequences {r['timings']['describe_training']:.1f} s (2 "
                 f"processes), train {r['timings']['train']:.1f} s, read + describe + classify the test sequences "
                 f"{r['timings']['describe_and_test']:.1f} s, total {total:.1f} s. Peak memory (largest process): "
                 f"{peak / 1024:.0f} MiB. One sequence (describe + predict, one process, after the model is "
                 f"loaded in {load:.2f} s): median {1000 * np.median(per_sequence):.0f} ms, max "
                 f"{1000 * max(per_sequence):.0f} ms over {len(per_sequence)} sequences; reading its .mat file "
                 f"{1000 * np.median(reading):.0f} ms more (median). Load average "
                 f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} cores.\n")
    text = "\n".join(lines)
    print(text)
    (RESULTS / "actions.md").write_text(text)
    confusion_png(RESULTS / "actions_confusion.png", np.array(r["confusion"]["all"]["truth"]),
                  np.array(r["confusion"]["all"]["predicted"]))


if __name__ == "__main__":
    main()
