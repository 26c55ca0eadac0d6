"""Compiling the kernels ahead of the first command (``sdp warmup``; ``make install`` runs it).

sdp's hot loops are Numba kernels compiled on first use and cached on disk (``cache=True``,
beside the sources or under ``NUMBA_CACHE_DIR``). Without a warm cache a user's first command
would wait for the compiler (about 15 s for ``sdp change``). :func:`warmup` runs every command's
path once on a small simulated scan, through the same functions and readers the commands use,
so that each kernel is compiled for the argument types real files give it, and cached. It also
writes the bytecode of sdp's own modules (:func:`_write_bytecode`), which an editable install
lacks where Python is told not to write it.

:func:`first_run_note` tells the command line whether a command is about to compile: a small
stamp beside the cache records which commands ran against the present kernels (their sources'
sizes and times, Python's and Numba's versions); a command not in it prints one line on stderr
(a terminal) when Numba starts compiling.

References
----------
.. [1] Numba documentation, "Notes on caching" (``cache=True``, cache invalidation by the source
   file's modification time).
"""

from __future__ import annotations

import importlib.util
import json
import os
import sys
import tempfile
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

__all__ = ["warmup", "first_run", "first_run_note", "record_warm"]

#: Modules holding Numba kernels (their sources key the stamp).
KERNEL_MODULES = ("fields/_kernels", "_core/_kdtree", "fields/_volume_kernels", "scale/_kernels", "io/_kernels",
                  "_core/_points", "actions/_actions", "distance/_distances", "distance/_cells", "fields/_spacing",
                  "change/_range_image", "change/_planes", "_core/_cells", "timeseries/_kalman", "timeseries/_objects",
                  "distance/_noise", "change/_combined", "_core/_disjoint", "_core/_pinhole")
#: Commands whose first run compiles kernels, and what warmup runs for each.
COMMANDS = ("change", "distance", "build", "bool", "mesh", "align", "watch", "action", "series")
_STAMP = "sdp-warm.json"


def _package_dir() -> Path:
    """The folder of the package ``sdp``."""
    return Path(__file__).resolve().parent.parent


def _cache_dir() -> Path:
    """Where Numba writes this package's cache (its ``__pycache__``, or ``NUMBA_CACHE_DIR``)."""
    root = os.environ.get("NUMBA_CACHE_DIR")
    return Path(root) if root else _package_dir() / "__pycache__"


def _key() -> str:
    """The kernels' identity: their sources' sizes and modification times, Python and Numba."""
    parts = [sys.version.split()[0]]
    spec = importlib.util.find_spec("numba")
    if spec is not None and spec.origin:  # numba's version without importing it (0.2 s)
        parts.append(str(Path(spec.origin).parent.stat().st_mtime_ns))
    for name in KERNEL_MODULES:
        st = (_package_dir() / f"{name}.py").stat()
        parts.append(f"{name}:{st.st_size}:{st.st_mtime_ns}")
    return "|".join(parts)


def _read_stamp() -> set[str]:
    try:
        stamp = json.loads((_cache_dir() / _STAMP).read_text())
    except (OSError, ValueError):
        return set()
    return set(stamp.get("commands", [])) if isinstance(stamp, dict) and stamp.get("key") == _key() else set()


def record_warm(commands) -> None:
    """Record that ``commands`` ran against the present kernels (nothing when the cache folder
    is not writable: the note then shows again, harmlessly)."""
    done = _read_stamp() | set(commands)
    path = _cache_dir() / _STAMP
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{_STAMP}.{os.getpid()}")
        tmp.write_text(json.dumps({"key": _key(), "commands": sorted(done)}))
        os.replace(tmp, path)
    except OSError:
        pass


def first_run_note(command: str) -> str | None:
    """One line for stderr when ``command`` has not run against the present kernels (its first
    run compiles them), else None."""
    if command not in COMMANDS or command in _read_stamp():
        return None
    return (f"sdp: first '{command}' since install: compiling its kernels once (about 15 s; "
            "'sdp warmup' compiles them all ahead)")


@contextmanager
def first_run(command: str, *, quiet: bool = False):
    """Around a command: :func:`first_run_note` on stderr when Numba starts compiling (on a
    terminal, unless ``quiet``: like a progress bar), and :func:`record_warm` once it succeeded."""
    note = first_run_note(command)
    if note and not quiet and sys.stderr.isatty():
        from numba.core import event

        class _Note(event.Listener):
            said = False

            def on_start(self, ev):
                if not self.said:
                    self.said = True
                    print(note, file=sys.stderr, flush=True)

            def on_end(self, ev):
                pass

        listener = _Note()
        event.register("numba:compile", listener)
        try:
            yield
        finally:
            event.unregister("numba:compile", listener)
    else:
        yield
    if note:
        record_warm([command])


def _write_bytecode() -> None:
    """Write the bytecode of sdp's modules beside them (``__pycache__``), even where the
    environment asks Python not to (``PYTHONDONTWRITEBYTECODE``, set on some machines): Python
    still reads bytecode there, and compiling sdp's modules at every start costs a command
    about 0.1 s (an editable install has none; pip writes it for a regular install). A folder
    that is not writable is left as it is."""
    import compileall

    compileall.compile_dir(str(_package_dir()), quiet=2, workers=1)


def warmup(*, echo: Callable[[str], object] | None = None) -> dict[str, float]:
    """Compile (or load from the cache) the kernels of every command, after writing sdp's
    bytecode; seconds per command (and ``"bytecode"``).

    Each command runs once on a small simulated office scan written to a temporary folder
    (PLY with the camera's position, LAZ, field files), as the command line runs it; the tiled
    path runs on Dask's synchronous scheduler when the ``tiles`` extra is installed, the action
    features when ``actions`` is, a five-epoch series when ``series`` is.

    Parameters
    ----------
    echo : callable, optional
        Called with one line per command done.

    Returns
    -------
    dict of str to float
    """
    import numpy as np

    from .._core._pinhole import fit_camera
    from .._core._points import as_points
    from ..change._detect import detect_changes
    from ..change._range_image import RangeImage
    from ..data._scene import office_scene
    from ..distance._distances import distances
    from ..fields._spacing import kth_in_image
    from ..io._output import all_or_none, write_points
    from ..options import Coverage, Execution, Outputs
    from . import _change as C
    from . import _distance as D
    from . import _files as F

    say = echo or (lambda line: None)
    times: dict[str, float] = {}
    t = time.perf_counter()
    _write_bytecode()
    times["bytecode"] = time.perf_counter() - t
    say(f"bytecode: {times['bytecode']:.1f} s")
    s = office_scene(seed=0, width=96, height=72)
    with tempfile.TemporaryDirectory(prefix="sdp-warmup-") as tmp:
        d = Path(tmp)
        files = {}
        with all_or_none(own=True):  # each step's files are renamed at its end (the command line defers them)
            for ext in ("ply", "laz"):
                for name, xyz in (("ref", s.reference), ("cur", s.current)):
                    files[name, ext] = write_points(d / f"{name}.{ext}", xyz)

        def step(command, fn):
            t = time.perf_counter()
            with all_or_none(own=True):
                fn()
            times[command] = time.perf_counter() - t
            record_warm([command])
            say(f"{command}: {times[command]:.1f} s")

        def change():
            C.compare_files(files["ref", "ply"], files["cur", "ply"], output=d / "c.ply",
                            coverage=Coverage(sensor_origin=s.camera))
            C.compare_files(files["ref", "laz"], files["cur", "laz"], output=d / "c.laz", outputs=Outputs(both=True))
            detect_changes(s.reference, s.current, decision="cluster", coverage=Coverage(sensor_origin=None))
            # an organized frame's view reaches its image's border: a 16 × 12 pinhole image's
            c, r = np.meshgrid(np.arange(16.0), np.arange(12.0))
            frame = np.c_[(c.ravel() - 8) / 10, (r.ravel() - 6) / 10, np.ones(c.size)] * 2.0
            camera = fit_camera(frame, np.arange(c.size), (12, 16), np.zeros(3))
            RangeImage.from_points(frame, np.zeros(3), camera=camera).classify(frame, range_noise=0.01)
            kth_in_image(as_points(frame)._replace(image=(camera.pixels, (12, 16), np.zeros(3))), np.arange(8), 4)
            if importlib.util.find_spec("dask") and importlib.util.find_spec("zarr"):
                C.compare_files(files["ref", "laz"], files["cur", "laz"], output=d / "t.laz",
                                execution=Execution(tiled=True, scheduler="synchronous", workdir=d))

        def distance():
            D.distance_files(files["ref", "laz"], files["cur", "laz"], output=d / "d.laz")
            distances(s.reference, s.current, core_points=s.reference[::7], sensor_origin=np.asarray(s.camera))


        def align():
            F.align_files(files["ref", "ply"], files["cur", "ply"], output=d / "T.txt", method="density")

        def watch():
            frames = d / "frames"
            frames.mkdir()
            with all_or_none(own=True):
                for i in range(2):
                    write_points(frames / f"f{i}.ply", s.current)
            for _ in F.watch_folder(files["ref", "ply"], frames):
                pass

        def action():
            from ..actions._actions import sequence_descriptor

            rng = np.random.default_rng(0)
            depth = np.zeros((6, 48, 64), np.uint16)
            depth[:, 10:40, 20:44] = 2000 + rng.integers(0, 50, (6, 30, 24))
            sequence_descriptor(depth)

        step("change", change)
        step("distance", distance)
        step("build", lambda: F.build_field_file(files["ref", "ply"], output=d / "r.sdpf"))
        step("bool", lambda: F.combine_files("difference", files["cur", "ply"], d / "r.sdpf", output=d / "new.sdpf"))
        step("mesh", lambda: F.mesh_file(d / "new.sdpf", output=d / "new.ply"))
        step("align", align)
        step("watch", watch)
        step("action", action)
        if importlib.util.find_spec("xarray") and importlib.util.find_spec("zarr"):
            from ..timeseries._compute import series

            # five epochs: the smoother estimates its noise from second differences of them
            step("series", lambda: series([s.reference, s.current] * 2 + [s.reference], output=d / "s.zarr"))
    return times
