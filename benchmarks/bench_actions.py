"""Action recognition on MSR Action3D, the cross-subject protocol (issues 5, 23 and 36).

The standard split: train on subjects 1, 3, 5, 7, 9; test on 2, 4, 6, 8, 10; a classifier per
subset (AS1, AS2, AS3) and one for all 20 actions; every choice by cross-validation on the
training subjects. Prints, from one run, the table, the confusion matrix and per-class accuracy
of all 20 actions, the number of configurations compared to choose the pattern
(``actions_configurations.tsv``), the time and the peak memory.

Then every five-subject split (252), the configuration frozen: ``sdp action eval DATA --splits all
--json`` in a child process, its wall time, CPU time and peak memory (the child and its workers,
by ``os.wait4``) and the load before and after; beside the standard split's figures: the mean,
standard deviation, minimum and maximum over the splits and the standard split's rank.

Writes benchmarks/results/actions.md, the confusion matrix as
benchmarks/results/actions_confusion.png and the splits' JSON as
benchmarks/results/actions_splits.json.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
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
    return matrix_lines(*confusion(truth, predicted))


def matrix_lines(labels, m) -> list[str]:
    """A confusion matrix ``m`` of actions ``labels`` and each action's accuracy, as Markdown."""
    labels, m = np.asarray(labels), np.asarray(m)
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


def load_text() -> str:
    return "load average " + ", ".join(f"{v:.1f}" for v in os.getloadavg()) + f" (1, 5, 15 min) on {os.cpu_count()} cores"


def run_all_splits() -> tuple[dict, dict]:
    """``sdp action eval DATA --splits all --json`` in a child process: its result and wall time,
    CPU time (user + system, the child and its workers) and peak memory (largest process)."""
    before = load_text()
    t0 = time.perf_counter()
    child = subprocess.Popen([sys.executable, "-m", "sdp.cli", "action", "eval", str(DATA), "--splits", "all",
                              "--json"], stdout=subprocess.PIPE, text=True)
    out = child.stdout.read()
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - t0
    child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode:
        raise SystemExit(f"sdp action eval --splits all failed ({child.returncode})")
    return json.loads(out), {"wall": wall, "cpu": usage.ru_utime + usage.ru_stime, "peak_mib": usage.ru_maxrss / 1024,
                             "load_before": before, "load_after": load_text()}


def splits_lines(r: dict, run: dict, standard: dict) -> list[str]:
    """The standard split beside the distribution over every five-subject split, as Markdown."""
    lines = [f"\n## Every five-subject split ({r['splits']}), the configuration frozen\n",
             f"`sdp action eval msr_action3d --splits all --json`: {r['sequences']} sequences described once; for "
             f"each of the {r['splits']} choices of five training subjects out of ten, the classifier trained on those "
             "five (each ridge's alpha by leave-one-subject-out cross-validation inside them) and tested on the other "
             "five. Std: over the splits (population). Rank 1 is the best split; percentile: the share of the other "
             "splits below the standard one, ties counting half.\n",
             "| set | standard split (1, 3, 5, 7, 9) | mean over the splits | std | min | max | standard split's rank "
             "(percentile) |", "|---|---:|---:|---:|---:|---:|---:|"]
    for name, v in r["summary"].items():
        # the standard split of the standard run; of the splits' run too, should they ever differ
        cell = f"{standard.get(name, v['standard']):.1%}"
        if name in standard and standard[name] != v["standard"]:
            cell += f" (splits run: {v['standard']:.1%})"
        lines.append(f"| {name} | {cell} | {v['mean']:.1%} | {v['std']:.1%} | "
                     f"{v['min']:.1%} | {v['max']:.1%} | {v['standard_rank']} of {r['splits']} "
                     f"({v['standard_percentile']:.0f} %) |")
    t = r["timings"]
    lines += [f"\nTime: {run['wall']:.0f} s end to end ({run['wall'] / 60:.1f} min; describing the {r['sequences']} "
              f"sequences {t['describe']:.0f} s in 2 processes, their Gram matrices {t['gram']:.0f} s, the "
              f"{r['splits']} splits {t['splits']:.0f} s), CPU time {run['cpu']:.0f} s, peak memory (largest "
              f"process) {run['peak_mib']:.0f} MiB; {run['load_before']} before, {run['load_after']} after.\n",
              f"All 20 actions, test subjects: confusion matrix summed over the {r['splits']} splits (each sequence is "
              "tested in the 126 splits that leave its subject out) and per-class accuracy\n"]
    lines += matrix_lines(r["confusion"]["all"]["actions"], r["confusion"]["all"]["matrix"])
    return lines


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
    lines.append(f"Standard split measured at {load_text()}.")
    splits, run = run_all_splits()
    lines += splits_lines(splits, run, r["accuracy"])
    text = "\n".join(lines)
    print(text)
    (RESULTS / "actions.md").write_text(text)
    (RESULTS / "actions_splits.json").write_text(json.dumps(dict(splits, run=run)) + "\n")
    confusion_png(RESULTS / "actions_confusion.png", np.array(r["confusion"]["all"]["truth"]),
                  np.array(r["confusion"]["all"]["predicted"]))


if __name__ == "__main__":
    main()
