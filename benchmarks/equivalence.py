"""Equivalence of two source trees of sdp, through the command line: a restructuring changed no behaviour.

Runs a fixed list of ``sdp`` command lines (:func:`cases`) once with each of two source trees,
old then new, case by case, and compares per case:

- the exit status of every command of the case;
- its stdout and its stderr, after :func:`normalise` (timings, temporary paths, the source tree's
  path, dates, random HTML ids, progress bars);
- every file left in the case's folder, by the SHA-256 digest of :func:`digest` (raw bytes, except
  PNG: decoded pixels; HTML: normalised text; LAS/LAZ: creation date zeroed).

Each case runs in a fresh temporary folder (its working directory) with::

    python -c "import sys; sys.argv[0]='sdp'; from sdp.cli import run; run()" ARGS...

where ``python`` is the interpreter running this script (use the project's virtualenv) and
``PYTHONPATH`` starts with the tree's ``src`` folder, so that ``import sdp`` resolves to that tree
(checked once at the start: the script refuses to run otherwise); the environment is otherwise
this script's, stdin is ``/dev/null`` and each command has a timeout (:data:`TIMEOUT`, the command
and its Dask workers killed by process group beyond it).

A case may give the new tree other arguments than the old one (``new_args``: a seam renamed on
purpose, e.g. ``sdp align`` taking REFERENCE first) and regular expressions of lines of stdout or
stderr allowed to differ (``expected``; empty unless needed, every allowed difference is printed).
Error cases also require exit status 2 and a one-line stderr in both trees.

Inputs: the real scans of ``../shared/data`` (see its README.md) and small synthetic clouds written
once per run with a fixed seed (:func:`make_inputs`).

Usage::

    .venv/bin/python benchmarks/equivalence.py OLD_SRC NEW_SRC [--data ../shared/data] \\
        [--json results.json] [-k SUBSTRING] [--old-args] [--warmup]

    .venv/bin/python benchmarks/equivalence.py /work/old/src /work/main/src --json equivalence.json

Prints one line per case (``same``, or what differs) and ``N cases: N same, N differ``; exits 1 when
a case differs, 2 when it cannot run. The first command of each kind in a tree whose Numba cache is
cold compiles its kernels (about 15 s each): ``--warmup`` runs ``sdp warmup`` in both trees first.
``--old-args`` gives the new tree the old arguments too (before its renamed seams exist). Running a
tree against itself (OLD_SRC = NEW_SRC; ``new_args`` are then ignored) checks the normalisation:
every case must be ``same``. About 4-5 minutes per tree on a 2-core machine (warm caches).
"""

from __future__ import annotations

import argparse
import difflib
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NoReturn

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: The command every case runs, as the ``sdp`` console script would (``run()`` exits with the status).
PROLOGUE = "import sys; sys.argv[0]='sdp'; from sdp.cli import run; run()"
#: Seconds allowed to one command.
TIMEOUT = 300.0
#: Status and stderr lines an error case must give in both trees.
ERROR_EXIT = 2


# --------------------------------------------------------------------------------------------
# Cases


@dataclass(frozen=True)
class Case:
    """One comparison: ``sdp ARGS`` run in a fresh folder with each tree.

    In arguments, ``{data}`` stands for the real data folder and ``{inputs}`` for the synthetic
    inputs of :func:`make_inputs`; other paths are relative to the case's folder.

    Attributes
    ----------
    name : str
        Short unique name (``-k`` selects on it).
    args : tuple of str
        The command line after ``sdp``, for the old tree (and the new one unless ``new_args``).
    new_args : tuple of str, optional
        The new tree's command line where a seam was renamed on purpose.
    before : tuple of tuple of str
        Commands run first, in the same folder with the same tree (prerequisites such as a field
        file); they are compared like the case's own command.
    copy : tuple of str
        Files of the inputs folder copied into the case's folder first (a case may then name them
        as outputs; their digests show whether they were left alone).
    error : bool
        An error case: both trees must exit with :data:`ERROR_EXIT` and one line on stderr.
    expected : tuple of str
        Regular expressions: a line of stdout or stderr present in one tree only is allowed when
        one of them matches it (``re.search``). Every allowed line is printed.
    """

    name: str
    args: tuple[str, ...]
    new_args: tuple[str, ...] | None = None
    before: tuple[tuple[str, ...], ...] = ()
    copy: tuple[str, ...] = ()
    error: bool = False
    expected: tuple[str, ...] = ()


def _a(command: str) -> tuple[str, ...]:
    """Split a command line written with single spaces (no argument holds a space)."""
    return tuple(command.split())


def cases() -> list[Case]:
    """The cases, in the order they run.

    Real scans: mOSD Kinect pairs (learn0→1 and learn12→13 have appeared objects, learn11→12
    none: benchmarks/results/defaults.md), the DLUT re-scan (needs alignment), Toronto's airborne
    LAZ epochs (README's options), the static grabber sequence and a few MSR Action3D sequences.
    Synthetic npy clouds (:func:`make_inputs`) serve the tiled path, core points, eval's truth and
    the error cases.
    """
    L = "{data}/mosd/learn"
    dlut = "{data}/dlut/A603_reference.pcd {data}/dlut/A603_rescan1.pcd"
    tor = "{data}/als_toronto/TTP_2015.laz {data}/als_toronto/TTP_2023.laz"
    tor_align = "--align density --align-class 2 --fix-horizontal"
    syn = "{inputs}/ref.npy {inputs}/cur.npy"
    grab = "{data}/pcl_kinect/grabber_sequence"
    msr = "{data}/msr_action3d"
    build_l0 = _a(f"build {L}/learn0.pcd -o l0.sdpf")
    train = _a("action train {inputs}/msr -o model.npz")
    c = [
        Case("version", _a("--version")),
        Case("help-change", _a("change --help")),
        # sdp change
        Case("change-mosd-learn0-learn1", _a(f"change {L}/learn0.pcd {L}/learn1.pcd -o out.ply")),
        Case("change-mosd-learn12-learn13", _a(f"change {L}/learn12.pcd {L}/learn13.pcd -o out.ply")),
        Case("change-mosd-learn11-learn12-static", _a(f"change {L}/learn11.pcd {L}/learn12.pcd -o out.ply")),
        Case("change-mosd-json", _a(f"change {L}/learn0.pcd {L}/learn1.pcd -o out.ply --json")),
        Case("change-mosd-both", _a(f"change {L}/learn12.pcd {L}/learn13.pcd -o out.ply --both")),
        Case("change-mosd-grid80", _a(f"change {L}/learn0.pcd {L}/learn1.pcd -o out.ply --grid-size 80")),
        Case("change-mosd-png", _a(f"change {L}/learn12.pcd {L}/learn13.pcd -o out.ply --png out.png")),
        Case("change-dlut-align-density", _a(f"change {dlut} -o out.ply --align density")),
        Case("change-toronto-laz", _a(f"change {tor} -o out.laz --both {tor_align}")),
        Case("change-synthetic-npz-json", _a(f"change {syn} -o out.npz --json")),
        Case("change-synthetic-tiled", _a(f"change {syn} -o out.laz --tiled --voxel-size 0.1 --tile-size 5 --both")),
        Case("change-mosd-report", _a(f"change {L}/learn0.pcd {L}/learn1.pcd -o out.ply --report r.html")),
        # sdp distance
        Case("distance-dlut", _a(f"distance {dlut} -o d.ply")),
        Case("distance-dlut-json-npz", _a(f"distance {dlut} -o d.npz --json")),
        Case("distance-synthetic-core-points", _a(f"distance {syn} -o d.ply --core-points {{inputs}}/core.npy")),
        Case("distance-toronto-png", _a(f"distance {tor} -o d.laz {tor_align} --png d.png")),
        # fields: build, info, mesh, bool
        Case("build-mosd", build_l0),
        Case("build-synthetic-voxel", _a("build {inputs}/ref.npy -o ref.sdpf --voxel-size 0.1")),
        Case("info-field", _a("info l0.sdpf"), before=(build_l0,)),
        Case("info-pcd", _a(f"info {L}/learn0.pcd")),
        Case("info-laz", _a("info {data}/als_toronto/TTP_2015.laz")),
        Case("mesh-field", _a("mesh l0.sdpf -o m.ply"), before=(build_l0,)),
        Case("mesh-cloud-obj", _a("mesh {inputs}/cur.npy -o m.obj --voxel-size 0.1")),
        Case("bool-difference-fields", _a("bool difference cur.sdpf ref.sdpf -o new.sdpf"),
             before=(_a(f"build {L}/learn1.pcd -o cur.sdpf --voxel-size 0.005"),
                     _a(f"build {L}/learn0.pcd -o ref.sdpf --voxel-size 0.005"))),
        Case("bool-union-clouds-stl", _a(f"bool union {syn} -o u.stl")),
        # eval, render
        Case("eval-synthetic", _a("eval c.ply {inputs}/cur_truth.npz --truth-field truth"),
             before=(_a("change {inputs}/ref.npy {inputs}/cur_truth.npz -o c.ply"),)),
        Case("eval-synthetic-json", _a("eval c.ply {inputs}/cur_truth.npz --truth-field truth --json"),
             before=(_a("change {inputs}/ref.npy {inputs}/cur_truth.npz -o c.ply"),)),
        Case("render-cloud-png-html", _a("render c.ply --png c.png --html c.html"),
             before=(_a(f"change {syn} -o c.ply"),)),
        Case("render-field-png", _a("render l0.sdpf --png slices.png"), before=(build_l0,)),
        # align: the restructuring puts REFERENCE first
        Case("align-dlut", _a("align {data}/dlut/A603_rescan1.pcd {data}/dlut/A603_reference.pcd -o T.txt"),
             new_args=_a("align {data}/dlut/A603_reference.pcd {data}/dlut/A603_rescan1.pcd -o T.txt")),
        Case("align-dlut-json",
             _a("align {data}/dlut/A603_rescan1.pcd {data}/dlut/A603_reference.pcd -o T.txt --json"),
             new_args=_a("align {data}/dlut/A603_reference.pcd {data}/dlut/A603_rescan1.pcd -o T.txt --json")),
        Case("align-toronto-ground",
             _a("align {data}/als_toronto/TTP_2023.laz {data}/als_toronto/TTP_2015.laz -o T.txt "
                "--align-class 2 --fix-horizontal"),
             new_args=_a("align {data}/als_toronto/TTP_2015.laz {data}/als_toronto/TTP_2023.laz -o T.txt "
                         "--align-class 2 --fix-horizontal")),
        # watch: the reference is the first frame of the static sequence, the frames the whole folder
        Case("watch-grabber", _a(f"watch {grab}/frame_20121214T142255.814212.pcd {grab}")),
        Case("watch-grabber-json", _a(f"watch {grab}/frame_20121214T142255.814212.pcd {grab} --json")),
        # action: trained on 6 sequences only (the full set takes minutes)
        Case("action-train-small", train),
        Case("action-predict", _a(f"action predict model.npz {msr}/a05_s05_e01_sdepth.mat "
                                  f"{msr}/a02_s05_e02_sdepth.mat"), before=(train,)),
        Case("action-predict-stream", _a(f"action predict model.npz --stream {msr}/a05_s05_e01_sdepth.mat"),
             before=(train,)),
        # errors: status 2 and one line on stderr, nothing written
        Case("error-missing-file", _a("change missing.npy {inputs}/cur.npy -o out.ply"), error=True),
        Case("error-missing-file-distance", _a("distance {inputs}/ref.npy missing.pcd -o d.ply"), error=True),
        Case("error-empty-npy", _a("change {inputs}/empty.npy {inputs}/cur.npy -o out.ply"), error=True),
        Case("error-nan-npy", _a("change {inputs}/ref.npy {inputs}/nan.npy -o out.ply"), error=True),
        Case("error-voxel-size-negative", _a(f"change {syn} -o out.ply --voxel-size -1"), error=True),
        Case("error-grid-size-zero", _a(f"change {syn} -o out.ply --grid-size 0"), error=True),
        Case("error-output-is-input", _a("change ref.ply {inputs}/cur.npy -o ref.ply"), copy=("ref.ply",),
             error=True),
        Case("error-unknown-input-extension", _a("change {inputs}/ref.xyzw {inputs}/cur.npy -o out.ply"),
             error=True),
        Case("error-unknown-output-extension", _a(f"change {syn} -o out.abc"), error=True),
        Case("error-missing-output-option", _a(f"change {syn}"), error=True),
        Case("error-bool-voxel-mismatch", _a("bool difference a.sdpf b.sdpf -o d.sdpf"), error=True,
             before=(_a("build {inputs}/ref.npy -o a.sdpf --voxel-size 0.1"),
                     _a("build {inputs}/cur.npy -o b.sdpf --voxel-size 0.2"))),
    ]
    names = [x.name for x in c]
    assert len(names) == len(set(names)), "case names must be unique"
    return c


def make_inputs(folder: Path, data: Path) -> None:
    """Write the synthetic inputs into ``folder`` (once per run, the same for both trees).

    A 20 m × 20 m ground sampled every 0.1 m (40,000 points), scanned twice at shifted positions
    with 5 mm noise; the current scan gains a 2 m box across x, y = 10 (a 5 m tile edge, so that
    the tiled case joins a region across tiles) and loses a 3 m pole at (15, 15). Fixed seed:
    the files are the same in every run.
    """
    rng = np.random.default_rng(20261202)
    g = np.arange(0.0, 20.0, 0.1)
    x, y = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))

    def ground(shift: float) -> np.ndarray:
        xs, ys = x + shift, y + shift
        return np.c_[xs, ys, 0.05 * np.sin(xs / 3.0) + 0.005 * rng.standard_normal(len(xs))]

    t = rng.uniform(0, 2 * np.pi, 3000)
    pole = np.c_[15 + 0.3 * np.cos(t), 15 + 0.3 * np.sin(t), rng.uniform(0, 3, len(t))]
    box = rng.uniform((9.0, 9.0, 0.0), (11.0, 11.0, 2.0), (5000, 3))
    ref = np.r_[ground(0.0), pole]
    cur_ground = ground(0.05)
    cur = np.r_[cur_ground, box]
    truth = np.r_[np.zeros(len(cur_ground), np.uint8), np.ones(len(box), np.uint8)]
    folder.mkdir(parents=True, exist_ok=True)
    np.save(folder / "ref.npy", ref)
    np.save(folder / "cur.npy", cur)
    np.savez(folder / "cur_truth.npz", xyz=cur, truth=truth)
    np.save(folder / "core.npy", ref[::37])  # about 1,100 core points
    np.save(folder / "empty.npy", np.zeros((0, 3)))
    np.save(folder / "nan.npy", np.full((100, 3), np.nan))
    shutil.copyfile(folder / "ref.npy", folder / "ref.xyzw")  # a valid cloud under an unknown extension
    with open(folder / "ref.ply", "w") as f:  # an ASCII PLY written here: no reader of sdp's involved
        f.write(f"ply\nformat ascii 1.0\nelement vertex {len(ref)}\nproperty double x\nproperty double y\n"
                "property double z\nend_header\n")
        np.savetxt(f, ref, fmt="%.6f")
    msr = folder / "msr"
    msr.mkdir(exist_ok=True)
    for action in ("a02", "a05"):
        for subject in ("s01", "s02", "s03"):
            name = f"{action}_{subject}_e01_sdepth.mat"
            (msr / name).symlink_to(data / "msr_action3d" / name)


# --------------------------------------------------------------------------------------------
# Normalisation and digests

_TIMING_KEY = re.compile(r"seconds|time|timing|latency|(?:^|_)ms(?:_|$)", re.I)
_JSON_ITEM = re.compile(r'(?P<q>"|&quot;)(?P<key>[\w ()-]*?)(?P=q)(?P<sep>\s*:\s*)'
                        r"(?P<value>\{[^{}]*\}|-?\d[\d.eE+-]*|null)")
_TIMING_LINE = re.compile(r"^[ \t]*(?:time|timings|seconds|latency)\b.*$", re.I | re.M)
_NUMBER = re.compile(r"\d[\d,]*(?:\.\d+)?(?:[eE][-+]?\d+)?")
_FIGURE = re.compile(r"(?<![\w.])\d[\d,]*(?:\.\d+)? (ms|s)\b")  # the space: not inside base64 pictures
_DATETIME = re.compile(r"\b\d{4}-\d\d-\d\d[ T]\d\d:\d\d:\d\d(?:\.\d+)?(?: [A-Z]{2,5}\b|[+-]\d\d:?\d\d)?")
_UUID = re.compile(r"\b[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}\b")
_BAR = re.compile(r"\d+%\||\[\d+:\d\d(?::\d\d)?(?:<|,|\])")


def normalise(text: str, paths: dict[str, str]) -> str:
    """Text with what may differ between two runs of the same code replaced by placeholders.

    Applied to stdout, stderr and HTML outputs, in this order:

    1. paths: each key of ``paths`` (the case's temporary folder, the inputs folder, the source
       tree; longest first) becomes its value (``<TMP>``, ``<INPUTS>``, ``<SRC>``);
    2. progress bars: on a line holding carriage returns, the segments that are tqdm bars
       (``NN%|``, ``[00:01<...``) or blank are dropped: a bar appears only once its step has run
       for a second, so whether it appears at all depends on the machine's load;
    3. date-times ``YYYY-MM-DD HH:MM:SS [ZONE]`` become ``<DATETIME>`` (the HTML report's footer);
    4. UUIDs become ``<UUID>``: plotly names its HTML view's ``div`` with a random ``uuid4``;
    5. timings in JSON: ``"KEY": VALUE`` (also HTML-escaped, ``&quot;``) whose key contains
       ``seconds``, ``time``, ``timing``, ``latency`` (``sdp watch``'s per-frame time) or the token
       ``ms``, and whose value is a number, null or a flat object, becomes ``"KEY": "<T>"``;
    6. timing rows: every number of a line whose label is ``time``, ``timings``, ``seconds`` or
       ``latency`` (``time (ms): read 12.3, ...``) becomes ``<T>``;
    7. timing figures: a number, a space and ``s`` or ``ms`` (``1.69 s``, ``(93.9 ms)``) becomes
       ``<T> s`` / ``<T> ms``.

    Nothing else is touched: any other difference, however small, is a difference.

    Parameters
    ----------
    text : str
        Text as the command wrote it.
    paths : dict of str to str
        Paths to replace, and their placeholders.

    Returns
    -------
    str
        The normalised text.
    """
    for path, placeholder in sorted(paths.items(), key=lambda kv: -len(kv[0])):
        text = text.replace(path, placeholder)
    if "\r" in text:
        lines = []
        for line in text.split("\n"):
            if "\r" in line:
                kept = [seg for seg in line.split("\r") if seg.strip() and not _BAR.search(seg)]
                if not kept:
                    continue
                line = "".join(kept)
            lines.append(line)
        text = "\n".join(lines)
    text = _DATETIME.sub("<DATETIME>", text)
    text = _UUID.sub("<UUID>", text)

    def json_item(m: re.Match) -> str:
        if not _TIMING_KEY.search(m["key"]):
            return m[0]
        return f"{m['q']}{m['key']}{m['q']}{m['sep']}{m['q']}<T>{m['q']}"

    text = _JSON_ITEM.sub(json_item, text)
    text = _TIMING_LINE.sub(lambda m: _NUMBER.sub("<T>", m[0]), text)
    return _FIGURE.sub(lambda m: f"<T> {m[1]}", text)


def digest(path: Path, paths: dict[str, str]) -> tuple[str, str]:
    """SHA-256 of an output file, and the rule used.

    - ``.png``: the decoded pixels (size and RGBA values, by Pillow, or matplotlib without it),
      not the file: the PNG's metadata (matplotlib's version, a date where a backend writes one)
      and its compression are not behaviour;
    - ``.html``/``.htm``: the UTF-8 text after :func:`normalise` (the report holds timings, a
      date and plotly's random ids);
    - ``.las``/``.laz``: the bytes with the header's creation day and year (bytes 90-93) zeroed:
      laspy writes the day the file was made;
    - anything else: the bytes.

    Parameters
    ----------
    path : Path
        The file.
    paths : dict of str to str
        Paths to replace in text outputs (see :func:`normalise`).

    Returns
    -------
    tuple of str
        The hexadecimal digest and the rule's name.
    """
    suffix = path.suffix.lower()
    if suffix == ".png":
        try:
            from PIL import Image

            with Image.open(path) as im:  # as RGBA: what is seen, whatever the PNG's colour type
                rgba = im.convert("RGBA")
                return hashlib.sha256(f"{rgba.size}".encode() + rgba.tobytes()).hexdigest(), "pixels"
        except ImportError:
            import matplotlib.image

            pixels = np.ascontiguousarray(matplotlib.image.imread(path))
            return hashlib.sha256(f"{pixels.dtype} {pixels.shape}".encode() + pixels.tobytes()).hexdigest(), "pixels"
    data = path.read_bytes()
    if suffix in (".html", ".htm"):
        text = normalise(data.decode("utf-8", errors="replace"), paths)
        return hashlib.sha256(text.encode()).hexdigest(), "normalised text"
    if suffix in (".las", ".laz") and data[:4] == b"LASF" and len(data) >= 94:
        return hashlib.sha256(data[:90] + bytes(4) + data[94:]).hexdigest(), "bytes, creation date zeroed"
    return hashlib.sha256(data).hexdigest(), "bytes"


# --------------------------------------------------------------------------------------------
# Running


@dataclass(frozen=True)
class Tree:
    """A source tree: its label (``old``/``new``), its ``src`` folder and the environment to run it."""

    label: str
    src: Path
    env: dict[str, str]


@dataclass
class Step:
    """What one command did: arguments, exit status (None: timed out), normalised output, time."""

    argv: list[str]
    exit: int | None
    stdout: str
    stderr: str
    seconds: float


@dataclass
class Run:
    """One case with one tree: its commands, the digests of the files left, and the time taken."""

    folder: Path
    steps: list[Step] = field(default_factory=list)
    files: dict[str, dict[str, str]] = field(default_factory=dict)

    @property
    def seconds(self) -> float:
        """Time taken by the case's commands."""
        return sum(s.seconds for s in self.steps)


def refuse(message: str) -> NoReturn:
    """Say why the comparison cannot run, and exit with status 2."""
    print(f"equivalence: {message}", file=sys.stderr)
    sys.exit(2)


def tree(label: str, src: str) -> Tree:
    """The tree at ``src``, after checking that ``import sdp`` resolves into it there.

    Raises
    ------
    SystemExit
        When ``src`` holds no ``sdp`` package, or ``sdp`` is imported from elsewhere.
    """
    path = Path(src).resolve()
    if not (path / "sdp" / "__init__.py").is_file():
        refuse(f"{src}: no sdp package there (give the folder holding sdp/, e.g. /work/old/src)")
    env = dict(os.environ)
    env["PYTHONPATH"] = str(path) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    out = subprocess.run([sys.executable, "-c", "import sdp; print(sdp.__file__)"], env=env, capture_output=True,
                         text=True, stdin=subprocess.DEVNULL, timeout=120)
    if out.returncode != 0:
        refuse(f"{label}: with PYTHONPATH={path}, import sdp fails: {(out.stderr.strip().splitlines() or ['?'])[-1]}")
    where = out.stdout.strip()
    print(f"{label}: sdp from {where}")
    if not Path(where).resolve().is_relative_to(path):
        refuse(f"{label}: with PYTHONPATH={path}, import sdp comes from {where}, not from that tree")
    return Tree(label, path, env)


def command(argv: Sequence[str], cwd: Path, env: dict[str, str], paths: dict[str, str],
            timeout: float = TIMEOUT) -> Step:
    """Run ``sdp ARGV`` in ``cwd``; its process group (Dask workers included) is killed on a timeout."""
    t0 = time.perf_counter()
    # A session of its own, so that a timeout or Ctrl-C here ends the command and its workers, by group id.
    # stdin is /dev/null (at its end at once) rather than a closed descriptor 0, which the command's first
    # open() would take over.
    proc = subprocess.Popen([sys.executable, "-c", PROLOGUE, *argv], cwd=cwd, env=env, stdin=subprocess.DEVNULL,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
        status: int | None = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        status = None
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        raise
    seconds = time.perf_counter() - t0
    text = [normalise(b.decode("utf-8", errors="replace"), paths) for b in (out, err)]
    return Step(list(argv), status, text[0], text[1], seconds)


def substitute(args: Sequence[str], data: Path, inputs: Path) -> list[str]:
    """The arguments with ``{data}`` and ``{inputs}`` replaced by the folders."""
    return [a.replace("{data}", str(data)).replace("{inputs}", str(inputs)) for a in args]


def run_case(case: Case, t: Tree, args: Sequence[str], root: Path, data: Path, inputs: Path) -> Run:
    """``case`` with tree ``t`` and the command line ``args``, in a fresh folder under ``root``: the
    case's commands, then the digests of the files in the folder."""
    folder = Path(tempfile.mkdtemp(prefix=f"{case.name}-{t.label}-", dir=root))
    paths = {str(folder): "<TMP>", str(folder.resolve()): "<TMP>", str(inputs): "<INPUTS>",
             str(inputs.resolve()): "<INPUTS>", str(t.src): "<SRC>"}
    for name in case.copy:
        shutil.copyfile(inputs / name, folder / name)
    r = Run(folder)
    for argv in (*case.before, args):
        r.steps.append(command(substitute(argv, data, inputs), folder, t.env, paths))
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            hexdigest, rule = digest(p, paths)
            r.files[p.relative_to(folder).as_posix()] = {"sha256": hexdigest, "rule": rule}
    return r


# --------------------------------------------------------------------------------------------
# Comparing


def _changed_lines(a: str, b: str) -> tuple[list[str], list[str]]:
    """Lines of ``a`` and of ``b`` that a line diff does not match."""
    la, lb = a.splitlines(), b.splitlines()
    gone, came = [], []
    for op, i1, i2, j1, j2 in difflib.SequenceMatcher(None, la, lb, autojunk=False).get_opcodes():
        if op != "equal":
            gone += la[i1:i2]
            came += lb[j1:j2]
    return gone, came


def compare(case: Case, old: Run, new: Run) -> tuple[list[str], list[str]]:
    """What differs between the two runs of ``case``, and the differences its ``expected`` allows.

    Returns
    -------
    differences : list of str
        Short descriptions (``exit``, ``stdout``, ``stderr``, ``file NAME``, prefixed by
        ``before N`` for a prerequisite command); empty when the runs are the same.
    allowed : list of str
        The lines that differ but match one of ``case.expected``, as ``stream: - line`` (old) or
        ``stream: + line`` (new).
    """
    differences, allowed = [], []
    patterns = [re.compile(p) for p in case.expected]
    for i, (a, b) in enumerate(zip(old.steps, new.steps, strict=True)):
        where = "" if i == len(old.steps) - 1 else f"before {i + 1} "
        if a.exit != b.exit:
            differences.append(f"{where}exit ({_status(a.exit)} / {_status(b.exit)})")
        for stream in ("stdout", "stderr"):
            ta, tb = getattr(a, stream), getattr(b, stream)
            if ta == tb:
                continue
            gone, came = _changed_lines(ta, tb)
            marked = [("-", line) for line in gone] + [("+", line) for line in came]
            if patterns and all(any(p.search(line) for p in patterns) for _, line in marked):
                allowed += [f"{where}{stream}: {sign} {line}" for sign, line in marked]
            else:
                differences.append(f"{where}{stream}")
    for name in sorted(old.files.keys() | new.files.keys()):
        if name not in new.files:
            differences.append(f"file {name} (old only)")
        elif name not in old.files:
            differences.append(f"file {name} (new only)")
        elif old.files[name]["sha256"] != new.files[name]["sha256"]:
            differences.append(f"file {name}")
    if case.error:  # the case's point: both trees refuse, in one line
        for label, r in (("old", old), ("new", new)):
            last = r.steps[-1]
            if last.exit != ERROR_EXIT or len(last.stderr.strip().splitlines()) != 1:
                differences.append(f"{label}: not an error in one line (exit {_status(last.exit)}, "
                                   f"{len(last.stderr.strip().splitlines())} stderr lines)")
    return differences, allowed


def _status(code: int | None) -> str:
    return "timeout" if code is None else str(code)


def _diff(a: str, b: str) -> list[str]:
    return list(difflib.unified_diff(a.splitlines(), b.splitlines(), "old", "new", lineterm="", n=1))[:200]


def _run_json(r: Run) -> dict:
    return {"steps": [vars(s) for s in r.steps], "files": r.files, "seconds": round(r.seconds, 3)}


# --------------------------------------------------------------------------------------------


def selected(all_cases: list[Case], substring: str | None) -> Iterator[Case]:
    """The cases whose name contains ``substring`` (all without one)."""
    return (c for c in all_cases if substring is None or substring in c.name)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the comparison; 0 when every case is the same, 1 when one differs."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("old_src", help="the old tree's src folder (holding sdp/)")
    p.add_argument("new_src", help="the new tree's src folder")
    p.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data",
                   help="the real data (default: ../shared/data beside the repository)")
    p.add_argument("--json", type=Path, help="write every case's details here")
    p.add_argument("-k", dest="substring", help="only the cases whose name contains SUBSTRING")
    p.add_argument("--old-args", action="store_true",
                   help="give the new tree the old arguments too (before its renamed seams exist); "
                        "implied when both trees are the same folder")
    p.add_argument("--warmup", action="store_true",
                   help="run 'sdp warmup' in each tree first (compiles its Numba kernels: about 80 s per cold tree)")
    a = p.parse_args(argv)
    data = a.data.resolve()
    if not (data / "mosd" / "learn").is_dir():
        refuse(f"{a.data}: not the shared data folder (see ../shared/data/README.md)")
    todo = list(selected(cases(), a.substring))
    if not todo:
        refuse(f"no case name contains {a.substring!r}")
    trees = [tree("old", a.old_src), tree("new", a.new_src)]
    # A case's new_args describe the new tree's interface: the same folder twice has only the old one.
    new_args = not (a.old_args or trees[0].src == trees[1].src)
    if trees[0].src == trees[1].src:
        print("the same tree twice: every case must be the same, else the normalisation misses something")
    if not new_args:
        print("the new tree gets the old arguments (new_args ignored)")
    root = Path(tempfile.mkdtemp(prefix="sdp-equivalence-"))
    inputs = root / "inputs"
    make_inputs(inputs, data)
    if a.warmup:
        for t in trees:
            step = command(["warmup", "--quiet"], root, t.env, {})
            print(f"{t.label}: sdp warmup, exit {_status(step.exit)}, {step.seconds:.0f} s")

    width = max(len(c.name) for c in todo)
    print(f"\n{'case':<{width}}  {'old s':>6}  {'new s':>6}  result", flush=True)
    results, kept, n_differ = [], [], 0
    total = {"old": 0.0, "new": 0.0}
    t_start = time.perf_counter()
    for case in todo:
        args = case.new_args if new_args and case.new_args is not None else case.args
        old = run_case(case, trees[0], case.args, root, data, inputs)  # old then new, case by case: same load
        new = run_case(case, trees[1], args, root, data, inputs)
        differences, allowed = compare(case, old, new)
        total["old"] += old.seconds
        total["new"] += new.seconds
        status = "same" if not differences else "differ: " + ", ".join(differences)
        print(f"{case.name:<{width}}  {old.seconds:6.1f}  {new.seconds:6.1f}  {status}", flush=True)
        for line in allowed:
            print(f"{'':<{width}}  allowed: {line}", flush=True)
        if differences:
            n_differ += 1
            kept += [old.folder, new.folder]
        else:
            shutil.rmtree(old.folder)
            shutil.rmtree(new.folder)
        results.append({
            "name": case.name, "old_args": list(case.args), "new_args": list(args),
            "before": [list(b) for b in case.before], "error_case": case.error, "expected": list(case.expected),
            "status": "same" if not differences else "differ", "differences": differences, "allowed": allowed,
            "diffs": {f"step {i + 1} {s}": _diff(getattr(x, s), getattr(y, s))
                      for i, (x, y) in enumerate(zip(old.steps, new.steps, strict=True))
                      for s in ("stdout", "stderr") if getattr(x, s) != getattr(y, s)},
            "old": _run_json(old), "new": _run_json(new)})

    print(f"\ntime in the commands: old {total['old']:.0f} s, new {total['new']:.0f} s "
          f"(wall {time.perf_counter() - t_start:.0f} s)")
    if kept:
        print(f"folders of the cases that differ kept under {root}")
    else:
        shutil.rmtree(root)
    if a.json:
        a.json.write_text(json.dumps({
            "old_src": str(trees[0].src), "new_src": str(trees[1].src), "python": sys.executable,
            "data": str(data), "timeout": TIMEOUT, "normalisation": normalise.__doc__, "digests": digest.__doc__,
            "seconds": {k: round(v, 1) for k, v in total.items()},
            "summary": {"cases": len(todo), "same": len(todo) - n_differ, "differ": n_differ},
            "cases": results}, indent=2) + "\n")
    print(f"{len(todo)} cases: {len(todo) - n_differ} same, {n_differ} differ")
    return 1 if n_differ else 0


if __name__ == "__main__":
    sys.exit(main())
