"""Many epochs: the archive, appending, atomicity, the smoother, objects and the command."""

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest

import sdp
from sdp.cli import main
from sdp.cli._series import describe_series, series_files
from sdp.cli._text import series_text
from sdp.data import slope_series
from sdp.distance import PreparedReference
from sdp.distance._reference import subsample
from sdp.timeseries import _archive
from sdp.timeseries._kalman import FilterState, kalman
from sdp.timeseries._objects import Tracker, neighbour_pairs

pytest.importorskip("xarray")
pytest.importorskip("zarr")

CYL = sdp.Cylinder(projection_scale=0.8)


@pytest.fixture(scope="module")
def slope():
    return slope_series(8, 12_000, size=12.0, step_epoch=4, seed=3)


def _digest(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(folder)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def _arrays(ds):
    return {k: ds[k].values for k in ds.variables if k != "time"} | {"time": ds.time.values}


def test_series_measures_the_known_change(slope, tmp_path):
    ds = sdp.series(slope.epochs, output=tmp_path / "s.zarr", cylinder=CYL, registration_error=2 * slope.registration)
    assert ds.sizes["epoch"] == 8 and ds.distance.dims == ("epoch", "point")
    xyz = np.c_[ds.x.values, ds.y.values, ds.z.values]
    truth = slope.truth(xyz)
    zone = slope.zone(xyz, margin=0.8)
    assert np.nanmedian(np.abs(ds.distance.values - truth)) < slope.noise / 2
    assert ds.significant.values[:, zone == 0].mean() < 0.06
    assert ds.significant.values[slope.step_epoch:, zone == 2].mean() > 0.9
    vel = np.nanmedian(ds.velocity.values[:, zone == 1])
    assert abs(vel - slope.creep_rate) < 0.2 * abs(slope.creep_rate)
    onset, kind = ds.onset.values[zone == 2], ds.onset_kind.values[zone == 2]
    assert np.mean((onset == slope.step_epoch) & (kind == 1)) > 0.9
    obj = ds.object.values
    starts = dict(zip(ds.object_id.values.tolist(), ds.object_start.values.tolist()))
    inside = [starts.get(int(obj[slope.step_epoch, p]), -1) == slope.step_epoch for p in np.flatnonzero(zone == 2)]
    assert np.mean(inside) > 0.9
    assert (obj[:, zone == 0] > 0).any(axis=0).mean() < 0.02
    params = ds.attrs["parameters"]
    assert params["used"]["projection_scale"] == pytest.approx(0.8) and ds.attrs["sdp_version"] == sdp.__version__
    assert params["smoother"]["process_noise"] >= 0 and ds.attrs["epochs"][0]["time_source"] == "index"


def test_a_core_point_not_seen_at_an_epoch_is_in_no_object_there(slope, tmp_path):
    """The stepped disk goes unscanned at one epoch after the step: the smoother still gives a
    value there (its guess from the epochs around), but not seen is not changed; the object goes
    on where it is seen again."""
    epochs = list(slope.epochs)
    k = slope.step_epoch + 2
    near = np.hypot(*(epochs[k][:, :2] - slope.step_centre).T) < slope.step_radius + CYL.projection_scale
    epochs[k] = epochs[k][~near]  # the cylinders' reach beyond the disk too
    ds = sdp.series(epochs, output=tmp_path / "s.zarr", cylinder=CYL, registration_error=2 * slope.registration)
    disk = slope.zone(np.c_[ds.x.values, ds.y.values, ds.z.values], margin=0.25 * CYL.projection_scale) == 2
    unseen = ~np.isfinite(ds.distance.values)
    assert disk.sum() >= 5 and unseen[k][disk].all() and np.isfinite(ds.smoothed.values[k][disk]).all()
    assert not (ds.object.values[unseen] > 0).any()
    assert [(ds.object.values[e][disk] > 0).mean() for e in (k - 1, k, k + 1)] == [1.0, 0.0, 1.0]
    # the same object: a change not seen for an epoch has not ended there (it was two objects)
    assert set(ds.object.values[k - 1][disk]) == set(ds.object.values[k + 1][disk])


def test_each_epoch_equals_sdp_distances_on_that_pair(tmp_path):
    rng = np.random.default_rng(4)
    ref = np.c_[rng.uniform(0, 6, (6000, 2)), 0.003 * rng.standard_normal(6000)]
    cur = np.c_[rng.uniform(0.2, 5.8, (6000, 2)), 0.02 + 0.003 * rng.standard_normal(6000)]
    low = np.c_[rng.uniform(-0.5, 6, (6000, 2)), -0.2 + 0.003 * rng.standard_normal(6000)]  # reaches below it
    core = ref[::7]
    pair = sdp.distances(ref, cur, core_points=core, cylinder=CYL)
    cyl = sdp.Cylinder(projection_scale=pair.projection_scale, normal_scale=pair.normal_scale,
                       max_distance=pair.max_distance)
    prep = PreparedReference.prepare(ref, core, cylinder=cyl)
    mine = prep.measure(cur)
    low_pair = sdp.distances(ref, low, core_points=core, cylinder=cyl)
    np.testing.assert_array_equal(prep.measure(low).distance, low_pair.distance)
    np.testing.assert_array_equal(mine.distance, pair.distance)
    np.testing.assert_array_equal(mine.lod, pair.lod)
    ds = sdp.series([ref, cur, low], output=tmp_path / "s.zarr", core_points=core, cylinder=cyl)
    np.testing.assert_allclose(ds.distance.values[1], pair.distance, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(ds.distance.values[2], low_pair.distance, rtol=1e-6, atol=1e-9)
    np.testing.assert_array_equal(ds.significant.values[2], low_pair.significant)
    assert np.all(ds.distance.values[0][np.isfinite(ds.distance.values[0])] == 0)


def test_append_equals_the_full_run(slope, tmp_path, monkeypatch):
    """3 epochs, then 2 (the noise estimated again at 4), then 1 going on from the saved state (lag 2)."""
    import dataclasses

    from sdp.timeseries import _compute

    monkeypatch.setattr(_compute, "DEFAULTS", dataclasses.replace(_compute.DEFAULTS, smoothing_lag=2))
    eps = slope.epochs[:6]
    full = sdp.series(eps, output=tmp_path / "full.zarr", cylinder=CYL, registration_error=0.002)
    sdp.series(eps[:3], output=tmp_path / "a.zarr", cylinder=CYL, registration_error=0.002)
    sdp.series(eps[3:5], output=tmp_path / "a.zarr", append=True)
    grown = sdp.series(eps[5:], output=tmp_path / "a.zarr", append=True, cylinder=CYL, registration_error=0.002)
    a, b = _arrays(full), _arrays(grown)
    assert a.keys() == b.keys()
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert [r["added"] for r in grown.attrs["runs"]] == [3, 2, 1]
    assert sorted(os.listdir(tmp_path)) == ["a.zarr", "full.zarr"]  # nothing left beside the archives


@pytest.mark.slow
def test_appends_one_by_one_equal_the_full_run_with_a_short_lag(slope, tmp_path, monkeypatch):
    """With a lag of 2, appends between powers of two go on from the saved state (rows older than
    the lag final, objects and onsets tracked on); reaching 4 epochs estimates the noise again."""
    import dataclasses

    from sdp.timeseries import _compute

    monkeypatch.setattr(_compute, "DEFAULTS", dataclasses.replace(_compute.DEFAULTS, smoothing_lag=2))
    kw = dict(cylinder=CYL, registration_error=0.002)
    full = sdp.series(slope.epochs[:7], output=tmp_path / "full.zarr", **kw)
    out = tmp_path / "a.zarr"
    sdp.series(slope.epochs[:3], output=out, times=range(3), **kw)
    for k in range(3, 7):
        grown = sdp.series(slope.epochs[k:k + 1], output=out, append=True, times=[k])
    a, b = _arrays(full), _arrays(grown)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    smoother = grown.attrs["parameters"]["smoother"]
    assert smoother["lag"] == 2 and smoother["estimated_from_epochs"] == 4
    assert full.sizes["object_id"] >= 2 and (full.onset.values >= 0).any()


@pytest.mark.slow
def test_three_epochs_estimate_the_noise_from_all_three_and_an_append_to_three_equals_the_full_run(slope, tmp_path):
    """Two epochs hold no second difference: three estimate the process noise from all three
    (not from the first two, 2ⁿ), and an append from two to three runs over the whole series."""
    kw = dict(cylinder=CYL, registration_error=0.002)
    full = sdp.series(slope.epochs[:3], output=tmp_path / "full.zarr", **kw)
    smoother = full.attrs["parameters"]["smoother"]
    assert smoother["estimated_from_epochs"] == 3 and smoother["process_noise"] > 0
    out = tmp_path / "a.zarr"
    sdp.series(slope.epochs[:2], output=out, times=range(2), **kw)
    assert sdp.open_series(out).attrs["parameters"]["smoother"]["process_noise"] == 0  # no second difference yet
    grown = sdp.series(slope.epochs[2:3], output=out, append=True, times=[2])
    a, b = _arrays(full), _arrays(grown)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_the_metadata_written_is_zarrs_own_consolidation(slope, tmp_path):
    """The group's metadata, written once from the arrays' handles after an append, is the one
    ``zarr.consolidate_metadata`` makes from the files (zarr's metadata classes are used directly:
    a zarr that changes them fails here)."""
    import shutil
    import warnings

    import zarr

    out = tmp_path / "s.zarr"
    sdp.series(slope.epochs[:3], output=out, cylinder=CYL, times=range(3))
    sdp.series(slope.epochs[3:4], output=out, append=True, times=[3])
    shutil.copytree(out, tmp_path / "c.zarr")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        zarr.consolidate_metadata(str(tmp_path / "c.zarr"))
    ours, theirs = (json.loads((f / "zarr.json").read_text()) for f in (out, tmp_path / "c.zarr"))
    assert ours == theirs and len(ours["consolidated_metadata"]["metadata"]) > 20


def test_an_append_needs_no_kernel_a_full_run_did_not_compile(slope, tmp_path):
    """``sdp warmup`` runs a full series: an append must find every kernel it calls compiled for
    its argument types (the saved state's arrays contiguous, as a run's), or a fresh install's first
    append would wait for the compiler."""
    import sys

    import numba

    def signatures():
        return {f"{name}.{k}": len(v.signatures) for name, mod in list(sys.modules.items())
                if name.startswith("sdp.") and mod is not None
                for k, v in vars(mod).items() if isinstance(v, numba.core.registry.CPUDispatcher)}

    out = tmp_path / "s.zarr"
    sdp.series(slope.epochs[:5], output=out, cylinder=CYL, times=range(5))
    before = signatures()
    sdp.series(slope.epochs[5:6], output=out, append=True, times=[5])
    after = signatures()
    assert {k: (before.get(k), n) for k, n in after.items() if before.get(k, 0) < n} == {}


def test_a_corrupt_or_missing_state_refuses_the_append_in_one_line(slope, tmp_path, capsys):
    out = tmp_path / "s.zarr"
    sdp.series(slope.epochs[:5], output=out, cylinder=CYL, times=range(5))
    for bad in (b"garbage", b"PK\x03\x04" + b"x" * 50, None):
        if bad is None:
            (out / "state.npz").unlink()
        else:
            (out / "state.npz").write_bytes(bad)
        before = _digest(out)
        with pytest.raises(sdp.SDPError, match="state.npz"):
            sdp.series(slope.epochs[5:6], output=out, append=True, times=[5])
        assert _digest(out) == before and sorted(os.listdir(tmp_path)) == ["s.zarr"]
    f = tmp_path / "e5.ply"
    sdp.write_points(f, slope.epochs[5])
    assert main(["series", str(f), "--append", "-o", str(out), "--times", "5", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "state.npz" in err


def test_interrupted_append_leaves_the_archive_as_it_was(slope, tmp_path, monkeypatch):
    out = tmp_path / "s.zarr"
    sdp.series(slope.epochs[:3], output=out, cylinder=CYL)
    before = _digest(out)
    calls = []
    real = PreparedReference.measure

    def failing(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(self, *args, **kwargs)

    monkeypatch.setattr(PreparedReference, "measure", failing)
    with pytest.raises(KeyboardInterrupt):
        sdp.series(slope.epochs[3:6], output=out, append=True)
    assert _digest(out) == before and sorted(os.listdir(tmp_path)) == ["s.zarr"]
    assert sdp.open_series(out).sizes["epoch"] == 3


@pytest.mark.parametrize("epochs, lag", [(3, None), (19, 2)], ids=["estimating-again", "going-on"])
def test_append_killed_while_writing_is_undone_by_the_next_open(slope, tmp_path, monkeypatch, epochs, lag):
    """An append writes in place behind its journal: killed after some of its writes (no chance to
    roll back), the next open puts the archive back as it was, byte for byte. Going on from a
    saved state 16 epochs on, the journal holds only what the append rewrites."""
    import dataclasses

    from sdp.timeseries import _compute

    if lag:
        monkeypatch.setattr(_compute, "DEFAULTS", dataclasses.replace(_compute.DEFAULTS, smoothing_lag=lag))
    out = tmp_path / "s.zarr"
    sdp.series([slope.epochs[k % 8] for k in range(epochs)], output=out, cylinder=CYL, times=range(epochs))
    before = _digest(out)
    journal = tmp_path / ".s.zarr.journal"

    def killed(*args, **kwargs):  # the rows, time and smoothed arrays are written by now
        raise KeyboardInterrupt

    monkeypatch.setattr(_archive, "write_state", killed)
    monkeypatch.setattr(_archive, "_roll_back", lambda *a: None)  # a kill runs no handler
    with pytest.raises(KeyboardInterrupt):
        sdp.series(slope.epochs[:2], output=out, append=True, times=[epochs, epochs + 1])
    monkeypatch.undo()
    assert _digest(out) != before and journal.is_dir()
    saved = {str(p.relative_to(journal / "saved")) for p in (journal / "saved").rglob("*") if p.is_file()}
    assert not any(p.startswith(("x/", "normal_x/", "ref_mean/")) for p in saved)  # never written by an append
    assert "distance/c.0.0" not in saved and "distance/zarr.json" in saved
    if lag:  # its first chunk row (epochs 0-15) is final
        assert "smoothed/c.0.0" not in saved and "smoothed/c.1.0" in saved and "object/c.0.0" not in saved
    else:  # the smoother estimated again, over every row
        assert "smoothed/c.0.0" in saved
    assert sdp.open_series(out).sizes["epoch"] == epochs
    assert _digest(out) == before and sorted(os.listdir(tmp_path)) == ["s.zarr"]


def test_a_full_disk_while_the_journal_is_made_is_one_line_and_leaves_nothing_beside(slope, tmp_path, monkeypatch):
    """The disk fills while the append's journal is made (before any write to the archive): the
    error names the archive and says it is as it was, and no half-made journal is left beside it
    (it was: ``.s.zarr.journal-PID``, and a bare "No space left on device")."""
    import errno

    out = tmp_path / "s.zarr"
    sdp.series(slope.epochs[:3], output=out, cylinder=CYL, times=range(3))
    before = _digest(out)
    real, calls = _archive._save, []

    def full(src, dst):
        calls.append(1)
        if len(calls) == 5:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(src, dst)

    monkeypatch.setattr(_archive, "_save", full)
    with pytest.raises(_archive.SeriesArchiveError, match=r"s\.zarr: can't write the series archive \(No space left "
                       r"on device; disk full\?\): it is as it was before this append"):
        sdp.series(slope.epochs[3:4], output=out, append=True, times=[3])
    assert sorted(os.listdir(tmp_path)) == ["s.zarr"] and _digest(out) == before


def test_an_export_that_fails_leaves_the_archive_as_it_was(slope, tmp_path, monkeypatch):
    """The exports are written from the archive's new version before its commit: one that fails (a
    full disk) leaves no archive, or the archive as it was before the append, and no export; they
    were written after it, and a failed export left a new archive, or the epochs appended, behind
    an error that said nothing was written."""
    import errno

    from sdp.cli import _series
    from sdp.io import atomic_path

    files = _write_epochs(slope, tmp_path, 4)
    names = sorted(os.listdir(tmp_path))
    out = tmp_path / "s.zarr"
    exports = {"epochs": [(-1, tmp_path / "last.npz")], "points": (tmp_path / "p.csv", None)}

    def full(ds, path, *args):
        with atomic_path(path) as tmp:
            tmp.write_bytes(b"part")
            raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(_series, "_write_points", full)
    with pytest.raises(sdp.SDPError, match=r"p\.csv: can't write \(No space left on device\)"):
        series_files(files[:3], output=out, options={"cylinder": CYL}, exports=exports)
    assert sorted(os.listdir(tmp_path)) == names
    series_files(files[:3], output=out, options={"cylinder": CYL})
    before = _digest(out)
    with pytest.raises(sdp.SDPError, match=r"p\.csv: can't write"):
        series_files(files[3:], output=out, append=True, exports=exports)
    assert _digest(out) == before and sorted(os.listdir(tmp_path)) == sorted([*names, "s.zarr"])
    monkeypatch.undo()
    run = series_files(files[3:], output=out, append=True, exports=exports)
    assert run.summary["epochs"] == 4 and run.dataset.sizes["epoch"] == 4
    assert np.load(tmp_path / "last.npz")["smoothed"].shape == (run.summary["core_points"],)
    assert (len((tmp_path / "p.csv").read_text().splitlines()) - 1) % 4 == 0  # a row per point and epoch


@pytest.mark.slow
def test_an_append_on_a_full_disk_is_one_line_and_leaves_the_archive(slope, tmp_path):
    """A file-size limit stands for a full disk: the append's writes fail part way, in place; the
    journal puts the archive back and the command says so in one line (exit 2)."""
    import subprocess
    import sys

    files = _write_epochs(slope, tmp_path, 4)
    out = tmp_path / "s.zarr"
    assert main(["series", *files[:3], "-o", str(out), "--projection-scale", "0.8", "--quiet"]) == 0
    before = _digest(out)
    limit = ("import resource, signal; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
             "resource.setrlimit(resource.RLIMIT_FSIZE, (4_000, 4_000)); ")
    done = subprocess.run([sys.executable, "-c", limit + "import runpy; runpy.run_module('sdp.cli', run_name="
                           "'__main__', alter_sys=True)", "series", files[3], "--append", "-o", str(out), "--quiet"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stderr.startswith("sdp: error: "), done.stderr[-2000:]
    assert len(done.stderr.strip().splitlines()) == 1 and "as it was before this append" in done.stderr, done.stderr
    assert _digest(out) == before and sorted(os.listdir(tmp_path)) == sorted(["s.zarr", *map(os.path.basename, files)])
    done = subprocess.run([sys.executable, "-c", limit + "import runpy; runpy.run_module('sdp.cli', run_name="
                           "'__main__', alter_sys=True)", "series", *files, "-o", str(tmp_path / "new.zarr"),
                           "--projection-scale", "0.8", "--quiet"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "new.zarr: can't write the series archive" in done.stderr, done.stderr[-2000:]
    assert "nothing was written" in done.stderr and not (tmp_path / "new.zarr").exists()
    assert sorted(os.listdir(tmp_path)) == sorted(["s.zarr", *map(os.path.basename, files)])


@pytest.mark.slow
def test_a_signal_after_the_archive_is_committed_comes_too_late(slope, tmp_path):
    """Ctrl-C right after the archive's commit (a new archive swapped in, an append's journal
    dropped), before the summary: the archive is written, so the command says so (exit 0), not
    "interrupted" over an archive that holds the epoch."""
    import subprocess
    import sys

    files = _write_epochs(slope, tmp_path, 3)
    out = tmp_path / "s.zarr"
    code = ("import os, signal, shutil, sys\n"
            "from pathlib import Path\n"
            "from sdp.timeseries import _archive as A\n"
            "out = Path(sys.argv[-1]); real = shutil.rmtree\n"
            "def rmtree(path, *a, **k):\n"
            "    if Path(path) in (A._siblings(out)[1], A._journal(out)[1]):\n"
            "        os.kill(os.getpid(), signal.SIGINT)\n"
            "    real(path, *a, **k)\n"
            "shutil.rmtree = rmtree\n"
            "from sdp.cli import main\n"
            "sys.exit(main(sys.argv[1:]))\n")
    for args in (["series", *files[:2], "--projection-scale", "0.8"], ["series", files[2], "--append"]):
        p = subprocess.run([sys.executable, "-c", code, *args, "-q", "-o", str(out)], capture_output=True, text=True,
                           timeout=120)
        assert p.returncode == 0 and p.stderr == "", p.stderr[-2000:]
    assert sdp.open_series(out).sizes["epoch"] == 3
    assert sorted(os.listdir(tmp_path)) == sorted(["s.zarr", *map(os.path.basename, files)])


def test_an_append_running_elsewhere_is_neither_rolled_back_nor_joined(slope, tmp_path):
    """While another process appends (its lock held, its journal there, a file replaced), opening
    the archive leaves that journal alone and a second append, or a run replacing the archive, is
    refused in one line; once that process is killed, the next open rolls its append back."""
    import subprocess
    import sys

    out = tmp_path / "s.zarr"
    sdp.series(slope.epochs[:3], output=out, cylinder=CYL, times=range(3))
    before = _digest(out)
    code = ("import os, sys, time; from pathlib import Path; from sdp.timeseries import _archive as A\n"
            "out = Path(sys.argv[1])\n"
            "with A.writing(out):\n"
            "    A._begin(out, A.untouched_by_append(rows=3, rewritten_from=0, epochs_per_chunk=16))\n"
            "    (out / 'part').write_bytes(b'half'); os.replace(out / 'part', out / 'state.npz')\n"
            "    print('ready', flush=True); time.sleep(60)\n")
    other = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline().strip() == "ready"
        assert sdp.open_series(out).sizes["epoch"] == 3
        assert (tmp_path / ".s.zarr.journal").is_dir() and (out / "state.npz").read_bytes() == b"half"
        # Linux names the process holding the lock (/proc/locks)
        holder = rf" \(process {other.pid}\)" if Path("/proc/locks").exists() else ""
        with pytest.raises(_archive.SeriesArchiveError, match=f"another sdp run{holder} is writing"):
            sdp.series(slope.epochs[3:4], output=out, append=True, times=[3])
        with pytest.raises(_archive.SeriesArchiveError, match="another sdp run .*is writing"):  # nor replaced
            sdp.series(slope.epochs[:2], output=out, cylinder=CYL)
    finally:
        other.kill()
        other.wait()
    assert sdp.open_series(out).sizes["epoch"] == 3
    assert _digest(out) == before and sorted(os.listdir(tmp_path)) == ["s.zarr"]


@pytest.mark.slow  # subprocesses, 4–6 s: the whole suite only
def test_append_killed_after_its_commit_is_complete(slope, tmp_path, monkeypatch):
    out = tmp_path / "s.zarr"
    sdp.series(slope.epochs[:3], output=out, cylinder=CYL, times=range(3))
    real = os.rename

    def cut(src, dst):
        real(src, dst)
        if str(dst).endswith(".committed"):  # committed; the journal not removed yet
            raise KeyboardInterrupt

    monkeypatch.setattr(_archive.os, "rename", cut)
    with pytest.raises(KeyboardInterrupt):
        sdp.series(slope.epochs[3:4], output=out, append=True, times=[3])
    monkeypatch.undo()
    assert (tmp_path / ".s.zarr.committed").is_dir()
    ds = sdp.open_series(out)
    assert ds.sizes["epoch"] == 4 and sorted(os.listdir(tmp_path)) == ["s.zarr"]
    full = sdp.series(slope.epochs[:4], output=tmp_path / "full.zarr", cylinder=CYL, times=range(4))
    for name, values in _arrays(full).items():
        np.testing.assert_array_equal(values, _arrays(ds)[name], err_msg=name)


def test_iso_times_keep_their_zone_and_fraction_of_a_second_without_a_warning(slope, tmp_path):
    """A zone offset is applied without NumPy's warning that it represents none, and fractions of a
    second are kept (they were dropped, and two epochs 0.7 s apart were refused as one time)."""
    import warnings

    from sdp.timeseries._compute import parse_times

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        t, kind = parse_times("2024-05-01T08:00+02:00,2024-05-01T06:30Z,2024-05-01T08:00:00.2,2024-05-01T08:00:00.9")
    day = (np.datetime64("2024-05-01") - np.datetime64("1970-01-01")).astype(int)
    assert kind == "date"
    np.testing.assert_allclose((t - day) * 86400, [6 * 3600, 6.5 * 3600, 8 * 3600 + 0.2, 8 * 3600 + 0.9], atol=1e-5)
    with pytest.raises(sdp.InvalidOptionError, match="neither a number nor an ISO date"):
        parse_times("2024-05-01T08:00+2h")
    out = tmp_path / "s.zarr"
    files = _write_epochs(slope, tmp_path, 3)
    times = "2024-05-01T08:00:00.2,2024-05-01T08:00:00.9,2024-05-01T08:00:02"
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        text = series_files(files, output=out, times=times, options={"cylinder": CYL}).summary_text()
    assert "2024-05-01T08:00:00.2 .. 2024-05-01T08:00:02)" in text
    stored = (sdp.open_series(out).time.values - np.datetime64("2024-05-01T08:00")) / np.timedelta64(1, "s")
    np.testing.assert_allclose(stored, [0.2, 0.9, 2.0], atol=1e-5)
    with pytest.raises(sdp.InvalidOptionError, match=r"the time 2024-05-01T08:00:00\.9 \(given\)"):
        series_files(files, output=tmp_path / "t.zarr", times="2024-05-01T08:00:00.2,"
                     "2024-05-01T08:00:00.9,2024-05-01T10:00:00.9+02:00")


def test_append_refuses_other_options_and_repeated_times(slope, tmp_path):
    out = tmp_path / "s.zarr"
    sdp.series(slope.epochs[:3], output=out, cylinder=CYL, times=[10, 11, 12])
    before = _digest(out)
    with pytest.raises(sdp.InvalidOptionError, match="a list of files or clouds, got one path"):
        sdp.series(str(tmp_path / "e0.ply"), output=out, append=True)  # not a list of letters
    with pytest.raises(sdp.InvalidOptionError, match="projection scale 0.5 differs"):
        sdp.series(slope.epochs[3:4], output=out, append=True, cylinder=sdp.Cylinder(projection_scale=0.5),
                   times=[13])
    with pytest.raises(sdp.InvalidOptionError, match="registration error 0.01 differs"):
        sdp.series(slope.epochs[3:4], output=out, append=True, registration_error=0.01, times=[13])
    with pytest.raises(sdp.InvalidOptionError, match="already in the archive"):
        sdp.series(slope.epochs[3:4], output=out, append=True, times=[12])
    with pytest.raises(sdp.InvalidOptionError, match="after the archive's last"):
        sdp.series(slope.epochs[3:4], output=out, append=True, times=[11.5])
    with pytest.raises(sdp.InvalidOptionError, match="core points"):
        sdp.series(slope.epochs[3:4], output=out, append=True, times=[13], core_points=slope.epochs[0][::50])
    for odd in ("no", 1):  # was read as True: appended to, not replaced
        with pytest.raises(sdp.InvalidOptionError, match="append must be True or False"):
            sdp.series(slope.epochs[3:4], output=out, append=odd, times=[13])
    assert _digest(out) == before
    with pytest.raises(sdp.InvalidOptionError, match="time 1"):
        sdp.series(slope.epochs[:3], output=tmp_path / "t.zarr", times=["0", "1", "1"])
    with pytest.raises(sdp.InvalidOptionError, match="mix numbers and dates"):
        sdp.series(slope.epochs[:2], output=tmp_path / "t.zarr", times=["2024-01-01", "3"])
    with pytest.raises(sdp.SDPError, match="no archive to append to"):
        sdp.series(slope.epochs[:2], output=tmp_path / "none.zarr", append=True)
    other = tmp_path / "field.zarr"
    other.mkdir()
    (other / "zarr.json").write_text('{"zarr_format": 3, "node_type": "group", "attributes": {}}')
    with pytest.raises(sdp.SDPError, match="not a series archive"):
        sdp.series(slope.epochs[:2], output=other)
    assert sorted(p.name for p in other.iterdir()) == ["zarr.json"]
    (tmp_path / "folder.zarr").mkdir()  # a folder, as an archive is: not told to choose a file name
    with pytest.raises(sdp.SDPError, match="is an existing directory and not a series archive; choose another"):
        sdp.series(slope.epochs[:2], output=tmp_path / "folder.zarr")
    assert not (tmp_path / "t.zarr").exists()


def test_dates_give_velocities_per_day_and_open_with_xarray(slope, tmp_path):
    xr = pytest.importorskip("xarray")
    out = tmp_path / "d.zarr"
    sdp.series(slope.epochs[:4], output=out, cylinder=CYL, times="2024-05-01,2024-05-03,2024-05-05,2024-05-07")
    ds = xr.open_zarr(out)
    assert np.issubdtype(ds.time.dtype, np.datetime64) and str(ds.time.values[1])[:10] == "2024-05-03"
    # sdp.open_series: Dask's chunks by default, none with chunks=None (the command's), the same values
    lazy, plain = sdp.open_series(out), sdp.open_series(out, chunks=None)
    assert lazy.distance.chunks is not None and plain.distance.chunks is None
    assert all(np.array_equal(lazy[v].values, plain[v].values, equal_nan=True) for v in lazy.variables)
    assert ds.attrs["parameters"]["smoother"]["velocity"] == "per day"
    with pytest.raises(sdp.InvalidOptionError, match="dated and the new epochs' times are numbers .give dates"):
        sdp.series(slope.epochs[4:5], output=out, append=True, times=[5])
    with pytest.raises(sdp.InvalidOptionError, match="times are indices .their files record no date: give times"):
        sdp.series(slope.epochs[4:5], output=out, append=True)


def test_an_archive_counted_by_index_goes_on_counting(slope, tmp_path):
    """LAS files written the same day give the same creation date: the first run counts the epochs
    by index, and an append of one more such file goes on counting (it was refused: a date against
    numbers)."""
    files = [sdp.write_points(tmp_path / f"e{k}.las", e) for k, e in enumerate(slope.epochs[:4])]
    out = tmp_path / "s.zarr"
    sdp.series(files[:3], output=out, cylinder=CYL)
    ds = sdp.series(files[3:], output=out, append=True, cylinder=CYL)
    assert ds.time.values.tolist() == [0.0, 1.0, 2.0, 3.0]
    assert [e["time_source"] for e in ds.attrs["epochs"]] == ["index"] * 4


def test_smoother_recovers_velocity_and_steps():
    rng = np.random.default_rng(0)
    t = np.arange(30.0)
    m = 400
    truth = np.zeros((30, m))
    truth[:, :200] = 0.5 * t[:, None]  # creep
    truth[15:, 200:300] = 20.0  # a step at epoch 15
    z = truth + rng.standard_normal((30, m))
    var = np.ones((30, m))
    sm, vel, ssd, vsd, step, _ = kalman(z, var, t, 1e-6, lag=8, scale=1.0, dt=1.0)
    assert abs(np.median(vel[:, :200]) - 0.5) < 0.05
    assert np.all(step[200:300] == 15) and np.mean(step[300:] >= 0) < 0.02
    assert np.median(np.abs(sm[:15, 200:300])) < 1.0  # the step is not smeared back in time
    assert np.all(ssd > 0) and np.all(vsd > 0)
    one = kalman(z[:, :1], var[:, :1], t, 1e-6, lag=8, scale=1.0, dt=1.0)[0]
    np.testing.assert_array_equal(one[:, 0], sm[:, 0])
    # a steady change faster than the noise (8 deviations an epoch, from the reference or from epoch
    # 10 on) is a rate, learnt, and a gradual onset: not a step at every epoch with no rate
    fast = np.zeros((30, 200))
    fast[:, :100] = 8.0 * t[:, None]
    fast[:, 100:] = 8.0 * np.maximum(t - 10, 0)[:, None]
    sm, vel, *_, step, _ = kalman(fast + rng.standard_normal((30, 200)), np.ones((30, 200)), t, 1e-6, lag=8,
                                  scale=1.0, dt=1.0)
    assert abs(np.median(vel[12:]) - 8.0) < 0.2 and (step < 0).mean() > 0.9  # a few: a step and a rate, by noise


def test_a_step_after_the_first_epoch_an_outlier_and_a_step_at_the_newest_epoch():
    """A step right after the reference is a step, not a rate, also where the epoch after it saw
    nothing; an epoch alone off the series is not carried into the smoothed change; the newest
    epoch's step is taken at once."""
    rng = np.random.default_rng(2)
    t = np.arange(25.0)
    truth = np.zeros((25, 500))
    truth[1:, :100] = 20.0  # a step at epoch 1
    truth[1:, 400:] = 20.0  # the same, epoch 2 not comparable
    truth[24, 300:400] = 20.0  # a step at the newest epoch
    z = truth + rng.standard_normal(truth.shape)
    z[7, 100:200] += 20.0  # one epoch off: an outlier, not a change
    z[0] = 0.0  # the reference against itself
    z[2, 400:] = np.nan
    var = np.ones_like(z)
    var[0] = 1e-6
    sm, vel, ssd, vsd, step, _ = kalman(z, var, t, 1e-6, lag=8, scale=1.0, dt=1.0)
    assert np.all(step[:100] == 1) and np.all(step[100:300] == -1) and np.all(step[300:400] == 24)
    assert np.all(step[400:] == 1)
    for cols in (slice(0, 100), slice(400, 500)):
        assert np.median(np.abs(vel[:, cols])) < 0.1  # no rate made of the step
        assert np.median(np.abs(sm - truth)[:, cols] / ssd[:, cols]) < 1.0
    assert np.max(np.abs(sm[:, 100:200])) < 3.0  # the outlier is not carried into the series
    assert np.median(np.abs(sm[24, 300:400] - 20.0)) < 2.0


def test_the_fixed_lag_smoother_goes_on_from_its_saved_state():
    """Rows older than the lag are final; filtering on from the state saved with 20 epochs gives
    the run over 23 epochs bit for bit, with a step confirmed by the appended epochs."""
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.5, 1.5, 23))
    z = 0.3 * t[:, None] + rng.standard_normal((23, 50))
    z[20:, :10] += 15.0  # a step at epoch 20: confirmed only by epoch 21
    z[5, 40] = np.nan
    var = np.full((23, 50), 1.0)
    kw = dict(lag=4, scale=1.0, dt=1.0)
    full = kalman(z, var, t, 1e-3, **kw)
    part = kalman(z[:20], var[:20], t[:20], 1e-3, **kw)
    assert part[5].epoch == 20 - 1 - 4
    np.testing.assert_array_equal(part[0][:15], full[0][:15])  # final rows
    again = kalman(z[part[5].epoch + 1:], var[part[5].epoch + 1:], t, 1e-3, state=part[5], **kw)
    for a, b in zip(again[:4], full[:4]):
        np.testing.assert_array_equal(a, b[part[5].epoch:])
    np.testing.assert_array_equal(again[4], full[4])
    assert np.all(full[4][:10] == 20) and np.all(part[4][:10] == -1)
    start = FilterState.start(50)
    np.testing.assert_array_equal(kalman(z, var, t, 1e-3, state=start, **kw)[0], full[0])


def test_core_points_drawn_at_random_keep_a_change_in_one_piece():
    """Every third point of a scan as core points (as py4dgeo's users pick them): a changed disk's
    core points are joined in one piece by the default neighbour radius."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(5)
    xyz = np.c_[rng.uniform(0, 20, (20_000, 2)), np.zeros(20_000)][::3]
    i, j, _, _ = neighbour_pairs(xyz)
    disk = np.flatnonzero(np.hypot(xyz[:, 0] - 10, xyz[:, 1] - 10) < 2.4)
    pos = np.full(len(xyz), -1)
    pos[disk] = np.arange(len(disk))
    inside = (pos[i] >= 0) & (pos[j] >= 0)
    graph = coo_matrix((np.ones(inside.sum()), (pos[i[inside]], pos[j[inside]])), shape=(len(disk),) * 2)
    assert connected_components(graph, directed=False)[0] == 1


def test_tracked_objects_split_merge_and_start_when_large():
    """Two changes that meet: the younger object ends where they meet; a set that splits keeps its
    id; a track becomes an object when min_points of its points change together."""
    xyz = np.c_[np.arange(40.0), np.zeros(40), np.zeros(40)]
    tr = Tracker(xyz, min_points=5, radius=1.5)
    sigma, vel, step = np.ones(40), np.zeros(40), np.full(40, -1)
    rows = []
    for k, parts in enumerate([[(0, 3)], [(0, 6)], [(0, 6), (20, 26)], [(0, 12), (14, 26)], [(0, 26)],
                               [(0, 10), (16, 26)]]):
        d = np.zeros(40)
        for a, b in parts:
            d[a:b] = 5.0
        rows.append(tr.add(k, d, sigma, vel, step))
    assert rows[0].max() == 0 and set(rows[1][:6]) == {1}  # 3 points: noise; 6: object 1 from epoch 1
    assert set(rows[2][20:26]) == {2}
    assert set(rows[4][:26]) == {1}  # the two met: the older goes on
    assert set(rows[5][:10]) == {1} and set(rows[5][16:26]) == {1}  # a split keeps the id
    table = tr.table(np.arange(6.0))
    np.testing.assert_array_equal(table["object_start"], [1, 2])
    np.testing.assert_array_equal(table["object_end"], [5, 3])
    np.testing.assert_array_equal(table["object_points"], [26, 12])
    again = Tracker.from_state(xyz, tr.state(), min_points=5)
    d = np.zeros(40)
    d[30:40] = -5.0
    np.testing.assert_array_equal(again.add(6, d, sigma, vel, step), tr.add(6, d, sigma, vel, step))


def test_a_track_of_noise_taken_in_whole_counts_for_the_object_that_takes_it():
    """A track too small to be an object, met by an object's set, is taken in whole: its points
    count for the object and its velocities for the object's mean, from its own first epoch."""
    xyz = np.c_[np.arange(40.0), np.zeros(40), np.zeros(40)]
    tr = Tracker(xyz, min_points=5, radius=1.5)
    sigma, step = np.ones(40), np.full(40, -1, np.int32)
    vel = np.where(np.arange(40) < 4, 1.0, 3.0)
    labels = []
    for k, parts in enumerate([[(0, 4)], [(0, 4), (10, 21)], [(0, 21)]]):
        d = np.zeros(40)
        for a, b in parts:
            d[a:b] = 5.0
        labels.append(tr.add(k, d, sigma, vel, step))
    assert labels[0].max() == 0 and set(labels[1][10:21]) == {1} and labels[1][:4].max() == 0
    assert set(labels[2][:21]) == {1}
    table = tr.table(np.arange(3.0))
    np.testing.assert_array_equal(table["object_points"], [21])
    np.testing.assert_array_equal(table["object_start"], [1])
    # (epoch, point) of the track: 2 × 4 of noise at 1, then 11 and 17 at 3, and 4 more at 1
    assert table["object_mean_velocity"][0] == pytest.approx((8 * 1 + 11 * 3 + 4 * 1 + 17 * 3) / 40)


def _write_epochs(slope, folder: Path, n: int) -> list[str]:
    files = []
    for k in range(n):
        f = folder / f"e{k}.ply"
        sdp.write_points(f, slope.epochs[k])
        files.append(str(f))
    return files


@pytest.mark.slow
def test_command_series_append_info_and_exports(slope, tmp_path, capsys):
    files = _write_epochs(slope, tmp_path, 5)
    out = tmp_path / "s.zarr"
    assert main(["series", *files[:4], "-o", str(out), "--projection-scale", "0.8", "--times", "0,1,2,3",
                 "--registration-error", "0.002", "--json", "--quiet", "--report", str(tmp_path / "r.html")]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["epochs"] == 4 and s["kind"] == "series archive" and str(tmp_path / "r.html") in s["outputs"]
    page = (tmp_path / "r.html").read_text()
    assert "Objects of change" in page and page.count("data:image/png") == 2 and "process noise q" in page
    assert main(["series", files[4], "--append", "-o", str(out), "--times", "4", "--epoch-output",
                 f"4:{tmp_path / 'e4.npz'}", "--points-output", str(tmp_path / "p.csv"), "--points", "0,5"]) == 0
    text = capsys.readouterr().out
    assert "5 epochs" in text and "appended" in text and f"wrote {tmp_path / 'p.csv'}" in text
    assert main(["info", str(out)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["epochs"] == 5 and info["parameters"]["used"]["projection_scale"] == 0.8
    sizes = [o["core_points"] for o in info["largest_objects"]]
    assert len(sizes) >= 2 and sizes == sorted(sizes, reverse=True)  # ids count in the order found; listed by size
    ds = sdp.open_series(out)
    after = ds.isel(epoch=slice(1, None))  # the reference is the first epoch
    measured = float(after.significant.sum() / np.isfinite(after.distance).sum())
    assert info["significant_fraction"] == pytest.approx(measured)
    seen = np.isfinite(ds.distance.values[-1])
    assert info["median_abs_smoothed_last"] == pytest.approx(float(np.median(np.abs(ds.smoothed.values[-1][seen]))))
    with np.load(tmp_path / "e4.npz") as f:
        assert f["distance"].shape == (info["core_points"],) and "velocity" in f.files
    rows = (tmp_path / "p.csv").read_text().splitlines()
    assert rows[0].startswith("point,epoch,time") and len(rows) == 1 + 2 * 5


def test_an_epochs_las_export_keeps_the_core_points_records_and_crs(slope, tmp_path, capsys):
    # the default core points are reference rows: their LAS records (class, GPS time) and CRS go along
    import laspy

    files = []
    for k in range(2):
        header = laspy.LasHeader(point_format=6, version="1.4")
        header.scales, header.offsets = [0.0001] * 3, [630_000, 4_830_000, 0]
        header.vlrs.append(laspy.VLR("LASF_Projection", 2112, "OGC WKT", b'PROJCS["UTM 17N"]\0'))
        header.global_encoding.wkt = True
        las = laspy.LasData(header)
        xyz = slope.epochs[k] + [630_000, 4_830_000, 0]
        las.x, las.y, las.z = xyz.T
        las.classification = np.full(len(xyz), 2, np.uint8)
        las.gps_time = np.arange(len(xyz), dtype=float)
        las.write(str(tmp_path / f"e{k}.laz"))
        files.append(str(tmp_path / f"e{k}.laz"))
    out = tmp_path / "distances1.laz"
    assert main(["series", *files, "-o", str(tmp_path / "s.zarr"), "--projection-scale", "0.8", "--epoch-output",
                 f"1:{out}", "-q"]) == 0
    back, ds = laspy.read(str(out)), sdp.open_series(tmp_path / "s.zarr")
    assert 2112 in [v.record_id for v in back.header.vlrs] and back.header.point_format.id == 6
    assert len(back.points) == ds.sizes["point"] and set(np.asarray(back.classification).tolist()) == {2}
    rows = np.asarray(back.gps_time).astype(int)  # each record is the reference row at its core point
    np.testing.assert_allclose(np.c_[back.x, back.y, back.z], slope.epochs[0][rows] + [630_000, 4_830_000, 0],
                               atol=1e-4)
    np.testing.assert_array_equal(back.distance, ds.distance.values[1])


def test_exports_out_of_range_are_refused_before_the_archive_is_touched(slope, tmp_path, capsys):
    # they were checked once the archive was committed: a replaced archive was lost, an append kept
    files = _write_epochs(slope, tmp_path, 3)
    out = tmp_path / "s.zarr"
    base = ["--projection-scale", "0.8", "--registration-error", "0.002", "--quiet"]
    assert main(["series", *files[:2], "-o", str(out), "--times", "0,1", *base]) == 0
    before = _digest(out)
    for args in (["series", *files[:2], "-o", str(out), "--epoch-output", f"2:{tmp_path / 'e.npz'}"],  # replacing
                 ["series", files[2], "--append", "-o", str(out), "--times", "2", "--epoch-output",
                  f"3:{tmp_path / 'e.npz'}"],
                 ["series", files[2], "--append", "-o", str(out), "--times", "2", "--points-output",
                  str(tmp_path / "p.csv"), "--points", "0,99999"],
                 ["series", *files[:2], "-o", str(tmp_path / "new.zarr"), "--points", "1"],  # ignored: refused
                 ["series", *files[:2], "-o", str(tmp_path / "new.zarr"), "--field-names", "pdal"]):
        assert main([*args, *base]) == 2
        assert "error" in capsys.readouterr().err
        assert _digest(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e0.ply", "e1.ply", "e2.ply", "s.zarr"]


def test_command_append_and_info_import_no_xarray(slope, tmp_path):
    """A job appending an epoch, or summarising an archive, reads and writes it with zarr alone:
    xarray and pandas are a third of a second of its start-up."""
    import subprocess
    import sys

    files = _write_epochs(slope, tmp_path, 4)
    out = str(tmp_path / "s.zarr")
    assert main(["series", *files[:3], "-o", out, "--projection-scale", "0.8", "--quiet"]) == 0
    code = ("import json, sys; from sdp.cli import main; "
            f"rc = main(['series', {files[3]!r}, '--append', '-o', {out!r}, '--quiet']); "
            f"rc += main(['info', {out!r}]); print(rc, 'xarray' in sys.modules, 'pandas' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.stdout.strip().splitlines()[-1] == "0 False False", done.stderr[-2000:]
    info = json.loads("\n".join(done.stdout.strip().splitlines()[:-1]))
    assert info["epochs"] == 4 and info["core_points"] == sdp.open_series(out).sizes["point"]


@pytest.mark.parametrize("args, message", [
    (["missing.ply"], "missing.ply"),
    (["{e0}", "{e1}", "--times", "1,x"], "neither a number nor an ISO date"),
    (["{e0}", "{e1}", "--times", "1,"], "a time is empty"),
    (["{e0}", "{e1}", "--times", "1"], "1 time(s) for 2 epoch(s)"),
    (["{e0}", "--append"], "no archive to append to"),
    (["{e0}", "{e1}", "--reference", "5"], "reference 5"),
    (["{e0}", "{e1}", "--epoch-output", "nope"], "K:FILE"),
    (["{e0}", "{e1}", "--points-output", "p.txt"], ".csv or .parquet"),
    (["{e0}", "{e1}", "{bad}"], "bad.laz: can't read as las"),  # read ahead, on a thread
    (["{e0}", "{one}"], "one.xyz: an epoch has 1 point(s)"),  # the epoch named
    (["{one}", "{e0}"], "one.xyz: can't measure point spacing"),  # the reference named
])
def test_command_bad_input_exits_2(slope, tmp_path, capsys, args, message):
    files = _write_epochs(slope, tmp_path, 2)
    sdp.write_points(tmp_path / "whole.laz", slope.epochs[2])  # cut short: its header counts the points
    (tmp_path / "bad.laz").write_bytes((tmp_path / "whole.laz").read_bytes()[:5000])
    (tmp_path / "one.xyz").write_text("1 2 3\n")
    args = [a.format(e0=files[0], e1=files[1], bad=tmp_path / "bad.laz", one=tmp_path / "one.xyz") for a in args]
    assert main(["series", *args, "-o", str(tmp_path / "x.zarr")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sdp: error:") and message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.zarr").exists()


@pytest.mark.slow
def test_real_epochs_equal_sdp_distance_on_each_pair(shared_data, tmp_path):
    folder = shared_data / "pheno4d_tomato"
    files = [folder / f for f in ("tomato_03-05.xyz", "tomato_03-06.xyz", "tomato_03-08.ply", "tomato_03-10.ply")]
    ds = sdp.series(files, output=tmp_path / "t.zarr", times="2024-03-05,2024-03-06,2024-03-08,2024-03-10")
    used = ds.attrs["parameters"]["used"]
    cyl = sdp.Cylinder(projection_scale=used["projection_scale"], normal_scale=used["normal_scale"],
                       max_distance=used["max_distance"])
    core = np.c_[ds.x.values, ds.y.values, ds.z.values]
    ref = sdp.read_points(files[0])
    for k in (1, 3):  # the tomato grows: new leaves far from the first epoch's surface
        pair = sdp.distances(ref, sdp.read_points(files[k]), core_points=core, cylinder=cyl)
        np.testing.assert_allclose(ds.distance.values[k], pair.distance, rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(ds.significant.values[k], pair.significant)
    assert ds.attrs["epochs"][3]["time_source"] == "given" and ds.sizes["object_id"] >= 1


@pytest.mark.slow
def test_blocks_beyond_memory_give_the_in_memory_numbers(slope, tmp_path, monkeypatch):
    from sdp.timeseries import _compute

    whole = sdp.series(slope.epochs, output=tmp_path / "w.zarr", cylinder=CYL, registration_error=0.002)
    assert whole.sizes["point"] > 256
    monkeypatch.setattr(_compute, "BYTES_PER_VALUE", 10**12)  # smoother blocks of 256 core points, objects streamed
    monkeypatch.setattr(_compute, "_check_smoother", lambda *a: None)  # which would refuse blocks so costly
    blocks = sdp.series(slope.epochs, output=tmp_path / "b.zarr", cylinder=CYL, registration_error=0.002)
    assert blocks.attrs["parameters"]["smoother"]["block_points"] == 256
    a, b = _arrays(whole), _arrays(blocks)
    differ = [name for name in a if not np.array_equal(a[name], b[name], equal_nan=True)]
    assert differ in ([], ["object_mean_velocity"]), differ  # a sum in another order
    np.testing.assert_allclose(a["object_mean_velocity"], b["object_mean_velocity"], rtol=1e-9)
    # columns of two chunks of 64 core points (three columns here), each written once; the measured
    # rows' chunks of 96 points straddle the columns
    monkeypatch.setattr(_archive, "POINT_CHUNK", 64)
    monkeypatch.setattr(_archive, "ROW_CHUNK", 96)
    budget = _compute._smoother_budget(256 * 2**20, whole.sizes["point"])
    monkeypatch.setattr(_compute, "_COLUMN_BYTES", int(budget // (len(slope.epochs) * 150)))
    cols = _arrays(sdp.series(slope.epochs, output=tmp_path / "c.zarr", cylinder=CYL, registration_error=0.002,
                              execution=sdp.Execution(memory_limit="256MB")))  # columns of 150 points: 128
    differ = [name for name in a if not np.array_equal(a[name], cols[name], equal_nan=True)]
    assert differ in ([], ["object_mean_velocity"]), differ
    # an append in columns, going on from the saved state (lag 2): the same numbers again
    import dataclasses

    monkeypatch.setattr(_compute, "DEFAULTS", dataclasses.replace(_compute.DEFAULTS, smoothing_lag=2))
    small = dict(cylinder=CYL, registration_error=0.002, execution=sdp.Execution(memory_limit="256MB"))
    whole = _arrays(sdp.series(slope.epochs[:7], output=tmp_path / "w7.zarr", **small))
    sdp.series(slope.epochs[:6], output=tmp_path / "a.zarr", times=range(6), **small)
    grown = sdp.series(slope.epochs[6:7], output=tmp_path / "a.zarr", append=True, times=[6],
                       execution=sdp.Execution(memory_limit="256MB"))
    assert grown.attrs["runs"][-1]["append"] and grown.attrs["parameters"]["smoother"]["estimated_from_epochs"] == 4
    b = _arrays(grown)
    differ = [name for name in whole if not np.array_equal(whole[name], b[name], equal_nan=True)]
    assert differ == [], differ


def test_smoothing_beyond_the_memory_limit_is_refused_before_any_work(tmp_path):
    # 20 epochs at 200,000 core points ran to 474 MB under --memory-limit 300MB, an append to 610 MB:
    # the end of the run (smoother, objects, archive) takes about 1.5 kB per core point beside the
    # smoother's blocks, which the plan did not count
    from sdp.timeseries import _compute

    rng = np.random.default_rng(0)
    np.save(tmp_path / "core.npy", np.c_[rng.uniform(0, 10, (200_000, 2)), np.zeros(200_000)])
    epochs = [np.c_[rng.uniform(0, 10, (2000, 2)), rng.normal(0, 0.002, 2000)] for _ in range(3)]
    for k, e in enumerate(epochs):
        np.save(tmp_path / f"e{k}.npy", e)
    out = tmp_path / "s.zarr"
    with pytest.raises(sdp.GridTooLargeError, match=r"smoothing 200,000 core points over 3 epochs would need "
                                                    r"5\d\d MB, above the memory limit of 300 MB"):
        sdp.series(epochs, output=out, core_points=tmp_path / "core.npy", execution=sdp.Execution(memory_limit="300MB"))
    assert not out.exists()
    assert _compute.END_CORE_BYTES >= 1000
    # the command says so in one line, exit 2
    assert main(["series", *[str(tmp_path / f"e{k}.npy") for k in range(3)],
                 "-o", str(out), "--core-points", str(tmp_path / "core.npy"), "--memory-limit", "300MB", "-q"]) == 2
    assert not out.exists()


def test_without_the_series_extra_one_line_names_it(slope, tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "xarray", None)
    with pytest.raises(sdp.MissingDependencyError, match=r"pip install 'sdp\[series\]'"):
        sdp.series(slope.epochs[:2], output=tmp_path / "s.zarr")
    assert not (tmp_path / "s.zarr").exists()


def test_times_are_read_from_the_files(slope, tmp_path):
    """LAS adjusted standard GPS time (leap seconds removed), E57 acquisition start, else the
    creation date; an hour apart, as hourly scans are."""
    import datetime as dt

    import laspy

    from sdp.io._time import file_time, gps_to_days

    def gps_of(when):  # GPS seconds of a UTC time after 2017 (18 leap seconds)
        return (when - dt.datetime(1980, 1, 6)).total_seconds() + 18

    noon = dt.datetime(2024, 5, 1, 12)
    days_noon = (noon - dt.datetime(1970, 1, 1)).total_seconds() / 86400
    assert gps_to_days(gps_of(noon)) == pytest.approx(days_noon, abs=1e-9)
    files = []
    for k, xyz in enumerate(slope.epochs[:3]):
        header = laspy.LasHeader(point_format=1, version="1.4")
        header.global_encoding.gps_time_type = laspy.header.GpsTimeType.STANDARD
        header.offsets, header.scales = xyz.min(0), [1e-4] * 3
        las = laspy.LasData(header)
        las.x, las.y, las.z = xyz.T
        las.gps_time = gps_of(noon + dt.timedelta(hours=k)) - 1e9 + np.linspace(0, 60, len(xyz))
        las.write(tmp_path / f"e{k}.laz")
        files.append(tmp_path / f"e{k}.laz")
    t, source = file_time(files[1])
    assert source == "LAS GPS time" and t == pytest.approx(days_noon + 1 / 24 + 30 / 86400, abs=1e-6)
    ds = sdp.series(files, output=tmp_path / "s.zarr", cylinder=CYL)
    assert ds.attrs["epochs"][0]["time_source"] == "file (LAS GPS time)"
    # a file without a time among dated ones, or two files of one time: numbered, and said why
    sdp.write_points(tmp_path / "e.ply", slope.epochs[3])
    text = series_files([*files[:2], tmp_path / "e.ply"], output=tmp_path / "u.zarr",
                        options={"cylinder": CYL}).summary_text()
    assert "index times" in text and f"times: 2 of 3 files record a time, not {tmp_path / 'e.ply'}" in text
    text = series_files([files[0], files[1], files[1]], output=tmp_path / "v.zarr",
                        options={"cylinder": CYL}).summary_text()
    assert "times: two files record the same time 2024-05-01T13:00:30" in text
    with pytest.raises(sdp.InvalidOptionError, match=r"must increase, in the order given \(read from the files"):
        sdp.series(files[::-1], output=tmp_path / "w.zarr", cylinder=CYL)
    hours = (ds.time.values - ds.time.values[0]) / np.timedelta64(1, "h")  # xarray decodes the days
    assert hours == pytest.approx([0, 1, 2], abs=1e-6)
    # week time dates nothing: the header's creation date (a day) instead
    las = laspy.read(files[0])
    las.header.global_encoding.gps_time_type = laspy.header.GpsTimeType.WEEK_TIME
    las.header.creation_date = dt.date(2023, 3, 4)
    las.write(tmp_path / "week.las")
    assert file_time(tmp_path / "week.las") == ((dt.date(2023, 3, 4) - dt.date(1970, 1, 1)).days, "LAS creation date")
    pye57 = pytest.importorskip("pye57")
    e = pye57.E57(str(tmp_path / "a.e57"), mode="w")
    xyz = slope.epochs[0][:1000]
    e.write_scan_raw({"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2]},
                     scan_header=type("H", (), {"acquisitionStart_dateTimeValue": gps_of(noon),
                                                **dict(zip(["xMinimum", "yMinimum", "zMinimum"], xyz.min(0))),
                                                **dict(zip(["xMaximum", "yMaximum", "zMaximum"], xyz.max(0)))})())
    e.close()
    assert file_time(tmp_path / "a.e57") == (pytest.approx(days_noon, abs=1e-9), "E57 acquisition start")
    assert file_time(tmp_path / "missing.laz") is None and file_time(np.zeros((3, 3))) is None


def test_a_full_stdout_after_the_archive_is_written_says_it_was(slope, tmp_path, monkeypatch, capsys):
    """The archive is committed before its summary is printed: a failing stdout then says so."""
    import errno
    import sys

    class Full:
        def write(self, text):
            raise OSError(errno.ENOSPC, "No space left on device")

        def flush(self):
            pass

    files = _write_epochs(slope, tmp_path, 2)
    monkeypatch.setattr(sys, "stdout", Full())
    assert main(["series", *files, "-o", str(tmp_path / "s.zarr")]) == 2
    err = capsys.readouterr().err
    assert "No space left on device; the archive or field store was written before it" in err
    assert describe_series(tmp_path / "s.zarr")["epochs"] == 2


def test_the_alignments_options_are_kept_or_refused(slope, tmp_path):
    """A series aligns each epoch on all its points: LAS classes are refused, not ignored, and
    fix_horizontal is recorded, so an append aligns as the run before it did."""
    with pytest.raises(sdp.InvalidOptionError, match="align_class .* is not available in a series"):
        sdp.series(slope.epochs[:2], output=tmp_path / "c.zarr", align=sdp.Registration(method="density",
                                                                                        align_class=2))
    assert not (tmp_path / "c.zarr").exists()
    ds = sdp.series(slope.epochs[:2], output=tmp_path / "f.zarr", cylinder=CYL,
                    align=sdp.Registration(method="density", fix_horizontal=True))
    assert ds.attrs["parameters"]["given"]["fix_horizontal"] is True
    m, c = np.asarray(ds.attrs["epochs"][1]["alignment"]["matrix"]), slope.epochs[1].mean(axis=0)
    # the horizontal shift is not estimated: the epoch's centroid moves in x and y only by the tilts
    # about its stable part's own centre (micrometres), not by a shift (its noise is a millimetre)
    assert np.abs((m[:3, :3] @ c + m[:3, 3] - c)[:2]).max() < 1e-5


def test_an_epoch_measured_nowhere_is_named(slope, tmp_path):
    """A file of another place or frame (here 1 km off) gets no distance: the summary says so."""
    epochs = [slope.epochs[0], slope.epochs[1] + 1000.0, slope.epochs[2]]
    sdp.series(epochs, output=tmp_path / "s.zarr", cylinder=CYL)
    summary = describe_series(tmp_path / "s.zarr")
    assert summary["unmeasured_epochs"] == [{"epoch": 1, "file": "array 1"}]
    assert "epoch 1 (array 1): no core point has a distance" in series_text(summary)


@pytest.mark.slow
def test_the_reference_noise_shared_by_every_epoch_is_not_averaged_away(tmp_path):
    """Every epoch is measured against the same reference cylinders: their noise is one error
    common to the whole series. Smoothing over 40 epochs of stable ground must keep it, so the
    smoothed change of stable core points is significant about as often as the 95 % bound says,
    not at most of them (the share is ~0.6 when the reference's part is treated as new at each epoch)."""
    rng = np.random.default_rng(5)

    def ground():
        xy = rng.uniform(0, 10, (20_000, 2))
        return np.c_[xy, 0.003 * rng.standard_normal(len(xy))]

    ds = sdp.series([ground() for _ in range(40)], output=tmp_path / "g.zarr",
                    cylinder=sdp.Cylinder(projection_scale=0.5, normal_scale=1.0))
    sm, sd = ds.smoothed.values, ds.smoothed_sigma.values
    share = float((np.abs(sm) > 1.96 * sd).mean())
    assert share < 0.1, share
    ref = ds.ref_spread.values**2 / ds.ref_count.values
    assert np.all(sd[-1] ** 2 >= ref * (1 - 1e-5))  # never below the reference's own variance


def test_process_noise_recovers_the_acceleration_density_it_is_simulated_with():
    from sdp.timeseries._kalman import _root, process_noise

    rng = np.random.default_rng(5)
    epochs, m, q, noise = 16, 20_000, 4e-6, 0.002
    cov = np.linalg.cholesky(q * np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]]))  # white-noise acceleration, unit steps
    x, z = np.zeros((m, 2)), []
    for _ in range(epochs):
        x = x @ np.array([[1.0, 0.0], [1.0, 1.0]]) + rng.standard_normal((m, 2)) @ cov.T
        z.append(x[:, 0] + noise * rng.standard_normal(m))
    z = np.array(z)
    assert process_noise(z, np.full_like(z, noise**2), np.arange(float(epochs))) == pytest.approx(q, rel=0.1)
    assert _root(lambda v: np.cbrt(1e-3 - v), 0.0, 1.0) == pytest.approx(1e-3, rel=1e-9)


def test_series_exports_take_the_names_cloudcompare_reads(slope, tmp_path):
    files = _write_epochs(slope, tmp_path, 3)
    out, las, csv = tmp_path / "s.zarr", tmp_path / "e2.las", tmp_path / "p.csv"
    assert main(["series", *files, "-o", str(out), "--projection-scale", "0.8", "--quiet", "--field-names",
                 "cloudcompare", "--epoch-output", f"2:{las}", "--points-output", str(csv), "--points", "0,1"]) == 0
    back = sdp.read_points(las)
    assert {"M3C2 distance", "distance uncertainty", "significant change", "Nx", "smoothed"} <= set(back.fields)
    np.testing.assert_allclose(back.fields["M3C2 distance"], sdp.open_series(out).distance[2].values, equal_nan=True)
    assert csv.read_text().splitlines()[0].split(",")[6:9] == ["M3C2 distance", "distance uncertainty",
                                                               "significant change"]


def test_an_epoch_without_a_distance_inside_a_creep_keeps_its_rate():
    """A creep at 1 cm per day over uneven epochs, one of them not comparable: the jump before the
    gap is judged with the next comparable epoch (a change of rate, not a step), the gap is
    bridged at the rate, and the rate is measured from the time since the last observation."""
    t = np.array([0.0, 1.0, 3.0, 7.0, 8.0, 15.0])
    z = (-0.01 * t)[:, None].repeat(2, axis=1)
    z[2, 1] = np.nan
    var = np.full(z.shape, (0.0008 / 1.96) ** 2)
    sm, vel, _, _, step, _ = kalman(z, var, t, 1e-10, lag=16, scale=0.0004, dt=1.0)
    assert (step == -1).all(), step  # no step: a gradual change, with or without the gap
    assert abs(sm[2, 1] + 0.03) < 0.002 and np.allclose(vel[1:, 1], -0.01, atol=0.001), (sm[:, 1], vel[:, 1])


def test_the_smoother_going_on_from_a_saved_state_equals_one_run_with_gaps():
    """Jumps judged with the next comparable epoch within the lag: a run going on from the state
    saved by a shorter one gives the full run's rows, gaps and steps and ramps included."""
    rng = np.random.default_rng(5)
    t = np.cumsum(rng.uniform(0.5, 3.0, 14))
    z = np.where(t[:, None] > 9, 0.05, 0.0) + 0.004 * t[:, None] * (np.arange(6) % 2) \
        + 0.0005 * rng.standard_normal((14, 6))
    z[rng.random(z.shape) < 0.25] = np.nan
    var = np.full(z.shape, 0.0005**2)
    full = kalman(z, var, t, 1e-9, lag=3, scale=0.0005, dt=1.0)
    for n in range(5, 14):
        first = kalman(z[:n], var[:n], t[:n], 1e-9, lag=3, scale=0.0005, dt=1.0)
        state = first[5]
        rest = kalman(z[state.epoch + 1:], var[state.epoch + 1:], t, 1e-9, lag=3, scale=0.0005, dt=1.0, state=state)
        r0 = max(state.epoch, 0)
        for a, b in zip(full[:4], rest[:4]):
            np.testing.assert_array_equal(a[r0:], b, err_msg=str(n))
        np.testing.assert_array_equal(full[4], rest[4])


def test_the_area_per_core_point_holds_for_subsampled_and_random_core_points():
    """The object table's areas: a 100 m square's core points, drawn at random or subsampled on
    cubes as the default core points are, add up to its area within 5 % (the nearest neighbour's
    spacing squared read 22 % and 79 % of it)."""
    rng = np.random.default_rng(2)
    dense = np.c_[rng.uniform(0, 100, (300_000, 2)), np.zeros(300_000)]
    for core in (dense[:10_000], dense[subsample(dense, 1.0)]):
        area = neighbour_pairs(core, 0.0)[3]
        assert abs(len(core) * area / 100**2 - 1) < 0.05, len(core) * area


def test_an_onset_runs_over_an_epoch_without_a_distance():
    """Two measured epochs running with significant change make an onset, an epoch between them
    without a distance (a NaN σ) neither breaks nor counts: a gap's core point starts with the rest."""
    xyz = np.c_[np.mgrid[0:5, 0:5].reshape(2, -1).T.astype(float), np.zeros(25)]
    tr = Tracker(xyz, min_points=3)
    none = np.full(25, -1, np.int32)
    for k, change in enumerate([0.0, 0.05, 0.10, 0.15]):
        sigma = np.full(25, 0.001)
        if k == 2:
            sigma[12] = np.nan  # the middle point not seen at epoch 2
        tr.add(k, np.full(25, change), sigma, np.full(25, 0.05), none)
    assert (tr.onset == 1).all() and (tr.onset_kind == 2).all(), tr.onset
    again = Tracker.from_state(xyz, tr.state(), min_points=3)
    assert np.array_equal(again.seen_at, tr.seen_at) and np.array_equal(again.seen_sign, tr.seen_sign)


@pytest.mark.slow  # 5 aligned epochs of 40,000 points: 6 s, the quick tier's longest
def test_an_aligned_epoch_is_aligned_on_its_stable_part(tmp_path):
    """A patch creeping towards the scanner pulls a rigid alignment of the whole epoch with it (a
    tenth of a wall moved 20 mm moved the epoch 2 mm, and the still wall read as change): each
    epoch is aligned again on its points away from the significant core points."""
    rng = np.random.default_rng(2)

    def wall(k):
        x, z = rng.uniform(0, 10, 40_000), rng.uniform(0, 4, 40_000)
        y = rng.normal(0, 0.001, 40_000) + 0.05 * np.sin(x) * np.cos(2 * z)  # a rough wall facing -y
        y[(x < 2) & (z > 2)] -= 0.005 * k  # a tenth of it creeps 5 mm an epoch towards the scanner
        return np.c_[x, y, z]

    ds = sdp.series([wall(k) for k in range(5)], output=tmp_path / "s.zarr",
                    cylinder=sdp.Cylinder(projection_scale=0.3), align="density", orientation=[0, -1, 0])
    x, z = ds.x.values, ds.z.values
    still = ~((x < 2.5) & (z > 1.5))
    last = np.asarray(ds.distance.values[-1], float)
    assert np.nanmedian(np.abs(last[still])) < 0.3e-3  # 2.3 mm when aligned on every point
    assert np.nanmedian(last[(x < 1.5) & (z > 2.5)]) == pytest.approx(0.02, abs=1e-3)  # 12 mm then
    assert ds.attrs["epochs"][4]["alignment"]["stable_points"] > 0.5 * 40_000


def test_summary_names_partial_epochs_and_registration_errors_to_look_at(slope, tmp_path):
    """An epoch raised as a whole (snow: its measured registration error absorbs the change), one
    scanned at 1 % of its points (too few stable places: M3C2's 0) are named, with why."""
    rng = np.random.default_rng(0)
    files = []
    for k in range(6):
        e = slope.epochs[k].copy()
        if k == 2:
            e[:, 2] += 0.3
        if k == 4:
            e = e[rng.random(len(e)) < 0.01]
        sdp.write_points(tmp_path / f"e{k}.ply", e)
        files.append(tmp_path / f"e{k}.ply")
    run = series_files(files, output=tmp_path / "s.zarr", options={"cylinder": CYL})
    text = run.summary_text()
    assert "registration error measured on the stable part of 4 of 5 epochs; 0 on epoch(s) 4: fewer than 100" in text
    assert f"epoch 4 ({files[4]}): measured at " in text and "a partial scan?" in text
    large = run.summary["registration"]["large"]
    assert [e["epoch"] for e in large] == [2] and large[0]["registration_error"] == pytest.approx(0.3, rel=0.6)
    assert f"epoch 2 ({files[2]}): registration error" in text and "epoch 3 (" not in text
    from sdp.viz._report import _epoch_table

    table = _epoch_table(sdp.open_series(tmp_path / "s.zarr").attrs)
    assert table.count("0 (M3C2&#x27;s 0: fewer than 100 stable places)") == 1  # escaped in HTML


def test_a_step_across_a_gap_after_close_epochs_is_a_step():
    """Four epochs an hour apart, then every two days, a 3 cm step at the first of these: the rate
    known from the first hours only made the prediction across the gap too wide for the innovation
    to see the step, which was read as creep (0.006 per day everywhere). The two epochs around the
    gap tell it: a step, and a velocity of 0 within its σ at the flat last epochs."""
    rng = np.random.default_rng(7)
    t = np.array([0, 1 / 24, 2 / 24, 3 / 24, 3, 5, 7, 9])
    sd = 0.0029
    z = np.where(np.arange(8)[:, None] >= 4, 0.03, 0.0) + sd * rng.standard_normal((8, 300))
    z[0] = 0.0  # the reference against itself
    var = np.full(z.shape, sd**2)
    sm, vel, ssd, vsd, step, _ = kalman(z, var, t, 3.5e-9, lag=16, scale=sd, dt=2.0, reference=0)
    assert (step == 4).mean() > 0.95, np.unique(step, return_counts=True)
    assert np.mean(np.abs(vel[-1]) < 1.96 * vsd[-1]) > 0.9 and abs(np.median(vel[-1])) < 0.001
    assert np.median(np.abs(sm[:4])) < 0.001 and np.median(np.abs(sm[4:] - 0.03)) < 0.002


def test_the_reference_epoch_is_pinned_at_zero(tmp_path):
    """Accelerating subsidence: a straight line through the epochs put the reference 5 mm above
    itself, significant, and an object started at the reference. Its distance to itself is exactly
    0: the smoothed change there is 0 ± 0, whichever epoch is the reference."""
    rng = np.random.default_rng(3)
    t = np.arange(8.0)
    z = -0.002 * t[:, None] ** 2 + 0.003 * rng.standard_normal((8, 50))
    for ref in (0, 2):
        zr = z - z[ref]
        zr[ref] = 0.0
        sm, vel, ssd, vsd, step, _ = kalman(zr, np.full(z.shape, 0.003**2), t, 1e-10, lag=4, scale=0.003, dt=1.0,
                                            reference=ref)
        assert np.all(sm[ref] == 0) and np.all(ssd[ref] == 0) and np.all(np.isfinite(vel)) and np.all(vsd > 0)
    s = slope_series(6, 12_000, size=12.0, creep_rate=0.0, step=0.0, seed=3)
    eps = [e - 0.002 * k**2 * s.normal for k, e in enumerate(s.epochs)]
    ds = sdp.series(eps, output=tmp_path / "s.zarr", cylinder=CYL, registration_error=0.002)
    assert np.all(ds.smoothed.values[0] == 0) and np.all(ds.smoothed_sigma.values[0] == 0)
    assert 0 not in ds.object_start.values.tolist() and not (ds.object.values[0] > 0).any()
    assert np.all(ds.smoothed_sigma.values[1:] > 0)


def test_one_epoch_raised_as_a_whole_does_not_set_the_process_noise(tmp_path):
    """Snow on one epoch of eight (+30 cm on every point): it enters three of the six triples the
    process noise is read from at every core point, and made it 10⁹ times larger pooled, so that
    the smoother followed it and the stable slope's velocity swung ±0.23 per epoch around it."""
    s = slope_series(10, 12_000, size=12.0, step_epoch=40, seed=3)  # no step: stable and creeping
    plain = sdp.series(s.epochs, output=tmp_path / "a.zarr", cylinder=CYL, registration_error=0.002)
    epochs = [e.copy() for e in s.epochs]
    epochs[4][:, 2] += 0.3
    ds = sdp.series(epochs, output=tmp_path / "b.zarr", cylinder=CYL, registration_error=0.002)
    q = ds.attrs["parameters"]["smoother"]["process_noise"]
    assert q < 10 * plain.attrs["parameters"]["smoother"]["process_noise"]
    stable = s.zone(np.c_[ds.x.values, ds.y.values, ds.z.values], margin=0.8) == 0
    assert ds.significant.values[4][stable].mean() > 0.99  # measured as it was
    assert np.abs(ds.velocity.values[:, stable]).max() < 0.005  # 0.23 per epoch around it before
    assert not (ds.object.values[:, stable] > 0).any()  # one epoch the next does not confirm: an outlier
