"""`sdp warmup` compiles ahead what the commands use; a first run that must compile says so."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import sdp
from sdp.cli import _warmup as warmup

SDP = str(Path(sys.executable).with_name("sdp"))

# runs one command in-process and prints how many kernels Numba compiled for it
COUNT_COMPILES = """
import sys
from numba.core import event
from sdp.cli._main import main
compiled = []
class Listener(event.Listener):
    def on_start(self, ev):
        pass
    def on_end(self, ev):
        compiled.append(ev.data["dispatcher"].py_func.__qualname__)
event.register("numba:compile", Listener())
status = main(sys.argv[1:])
print(status, sorted(set(compiled)))
"""


def test_first_run_note_until_the_command_ran(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    note = warmup.first_run_note("change")
    assert note is not None and "compiling" in note and "sdp warmup" in note and "\n" not in note
    warmup.record_warm(["change"])
    assert warmup.first_run_note("change") is None
    assert warmup.first_run_note("distance") is not None  # its kernels are others
    assert warmup.first_run_note("eval") is None  # compiles nothing
    (tmp_path / "sdp-warm.json").write_text('{"key": "older kernels", "commands": ["distance"]}')
    assert warmup.first_run_note("distance") is not None


def test_the_stamp_keys_every_module_with_kernels():
    # a kernel module left out of the key would keep an old stamp after its kernels changed
    root = Path(sdp.__file__).parent
    with_kernels = {str(p.relative_to(root).with_suffix("")) for p in root.rglob("*.py")
                    if "nb.njit" in p.read_text(encoding="utf-8")}
    assert with_kernels == set(warmup.KERNEL_MODULES)


def test_the_note_shows_on_a_terminal_when_numba_compiles(tmp_path, monkeypatch):
    import io

    import numba

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    err = Terminal()
    monkeypatch.setattr(sys, "stderr", err)
    with warmup.first_run("change"):
        pass  # nothing compiled: nothing said
    assert err.getvalue() == "" and warmup.first_run_note("change") is None  # recorded as run
    (tmp_path / "sdp-warm.json").unlink()
    with warmup.first_run("change"):
        numba.njit(lambda x: x + 1)(1)  # compiles
        numba.njit(lambda x: x + 2)(1)
    assert err.getvalue().count("compiling its kernels once") == 1
    (tmp_path / "sdp-warm.json").unlink()
    with warmup.first_run("change", quiet=True):
        numba.njit(lambda x: x + 3)(1)
    assert err.getvalue().count("compiling") == 1


@pytest.mark.slow
def test_after_warmup_the_commands_compile_nothing(tmp_path, rng):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache")}
    done = subprocess.run([SDP, "warmup"], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    assert "change:" in done.stdout and "distance:" in done.stdout
    # clouds the warmup never saw, in another format and size
    floor = np.c_[rng.uniform(0, 2, (30_000, 2)), 0.002 * rng.standard_normal(30_000)]
    box = rng.uniform([0.8, 0.8, 0.0], [1.2, 1.2, 0.3], (3_000, 3))
    ref, cur = tmp_path / "ref.laz", tmp_path / "cur.laz"
    sdp.write_points(ref, floor)
    sdp.write_points(cur, np.concatenate([floor, box]))
    commands = [["change", str(ref), str(cur), "-o", str(tmp_path / "c.ply")],
                ["distance", str(ref), str(cur), "-o", str(tmp_path / "d.laz")],
                ["series", str(ref), str(cur), str(ref), str(cur), str(cur), "--times", "0,1,2,3,4", "-o",
                 str(tmp_path / "s.zarr")]]
    learn = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "mosd" / "learn"
    if learn.is_dir():  # a real Kinect pair, with its sensor's VIEWPOINT
        commands.append(["change", str(learn / "learn0.pcd"), str(learn / "learn1.pcd"), "-o",
                         str(tmp_path / "k.ply")])
    for command in commands:
        done = subprocess.run([sys.executable, "-c", COUNT_COMPILES, *command], env=env, capture_output=True,
                              text=True, timeout=300)
        assert done.stdout.strip().splitlines()[-1] == "0 []", (command, done.stdout, done.stderr)
        assert "compiling" not in done.stderr


def test_warmup_writes_bytecode_where_python_would_not(tmp_path, monkeypatch):
    import importlib.util

    module = tmp_path / "kernel_module.py"
    module.write_text("VALUE = 1\n")
    monkeypatch.setattr(sys, "dont_write_bytecode", True)  # as PYTHONDONTWRITEBYTECODE=1 sets it
    monkeypatch.setattr(warmup, "_package_dir", lambda: tmp_path)
    warmup._write_bytecode()
    assert Path(importlib.util.cache_from_source(str(module))).is_file()


def test_numba_caches_in_the_temporary_folder_where_it_can_write_nowhere_else(monkeypatch, tmp_path):
    """A read-only install used without a writable home: Numba would stop with a traceback."""
    import os
    import tempfile

    import sdp

    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "none"))  # no such folder: ~/.cache can't be made
    monkeypatch.setattr(os, "access", lambda path, mode: False)
    sdp._numba_cache()
    assert os.environ["NUMBA_CACHE_DIR"] == os.path.join(tempfile.gettempdir(), f"sdp-numba-cache-{os.getuid()}")
    monkeypatch.setenv("NUMBA_CACHE_DIR", "/somewhere")  # one given is kept
    sdp._numba_cache()
    assert os.environ["NUMBA_CACHE_DIR"] == "/somewhere"
