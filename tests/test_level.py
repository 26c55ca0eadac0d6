"""The level of detection's systematic part measured on the data (``registration_error="auto"``,
:mod:`sdp.distance._level`)."""

import numpy as np
import pytest

import sdp
from sdp.distance._level import LEVEL_Z, STABLE_REACH, measured_registration_error, stable_part, systematic


@pytest.mark.parametrize("seed", range(4))
def test_the_systematic_part_is_the_smallest_that_keeps_5_percent_beyond(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(50, 3000))
    absd = np.abs(rng.standard_t(3, n)) * 0.003
    random = (0.001 * rng.random(n)) ** 2
    g = rng.uniform(0.5, 2.0, n)

    def share(s):
        return np.count_nonzero(absd > LEVEL_Z * np.sqrt(random + (s * g) ** 2)) / n

    s = systematic(absd, random, g)
    assert s > 0 and share(s) <= 0.05 < share(s * (1 - 1e-9))
    assert systematic(absd * 1e-3, random, g) == 0.0  # fewer than 5 % beyond the random part alone


@pytest.mark.parametrize("seed", range(3))
def test_the_registration_error_is_the_smallest_that_keeps_5_percent_of_the_stable_part_beyond(seed):
    rng = np.random.default_rng(seed)
    n, sigma_p = 20_000, 0.03
    random_sd = 0.001 * rng.uniform(0.5, 3.0, n)  # heteroscedastic: each place its own random part
    d = random_sd * rng.standard_t(4, n) + 0.002 * rng.standard_normal(n)  # plus what is common to the epoch
    moved = rng.random(n) < (0.15, 0.6, 0.9)[seed]  # what moved may be most of the scene
    d[moved] += rng.choice([-1, 1], moved.sum()) * rng.uniform(0.07, 0.3, moved.sum())  # beyond 2σ_p
    step = ~moved & (rng.random(n) < 0.05)
    d[step] += 0.05  # within 2σ_p, but far beyond the noise (a step smaller than the kernel)
    d[rng.random(n) < 0.02] = np.nan  # not comparable
    reg = measured_registration_error(d, random_sd, sigma_p)
    stable = stable_part(d, random_sd, sigma_p)
    with np.errstate(invalid="ignore"):
        assert not (stable & (np.abs(d) > STABLE_REACH * sigma_p)).any()
    assert not (stable & moved).any() and stable[~moved & ~step & np.isfinite(d)].mean() > 0.97
    assert (stable & step).sum() <= 0.02 * step.sum()  # the step's own noise has a t tail too

    def beyond(r):
        return np.count_nonzero(np.abs(d[stable]) > LEVEL_Z * (random_sd[stable] + r)) / stable.sum()

    assert reg > 0 and beyond(reg) <= 0.05 < beyond(reg * (1 - 1e-9))
    assert np.nanmin(np.abs(d[moved])) > LEVEL_Z * (random_sd[moved].max() + reg)  # every change significant
    assert (np.abs(d[step]) > LEVEL_Z * (random_sd[step] + reg)).mean() > 0.95
    quiet = random_sd * rng.standard_normal(n) * 0.5  # within the random part alone: never lowered
    assert measured_registration_error(quiet, random_sd, sigma_p) == 0.0
    assert measured_registration_error(np.full(n, 1.0), random_sd, sigma_p) is None  # nothing stable
    assert measured_registration_error(d[:99], random_sd[:99], sigma_p) is None  # too few to read 5 % from


def wavy_pair(rng, n=60_000, size=6.0):
    """A static scene scanned twice with what M3C2's random part does not see: each epoch's own
    low-frequency error (a tilt and a wave of a few mm, as a sensor's calibration or an alignment
    leaves) over independent noise of 1 mm; a box of 0.3 m stands on it in the second."""
    def epoch():
        xy = rng.uniform(0, size, (n, 2))
        tilt, phase = rng.normal(0, 0.0008, 2), rng.uniform(0, 2 * np.pi)
        z = xy @ tilt + 0.002 * np.sin(xy[:, 0] * 1.3 + phase) + 0.001 * rng.standard_normal(n)
        return np.c_[xy, z]

    a, b = epoch(), epoch()
    box = (b[:, 0] > 2) & (b[:, 0] < 3) & (b[:, 1] > 2) & (b[:, 1] < 3)
    b[box, 2] += 0.3
    return a, b


def test_auto_keeps_the_levels_promise_where_m3c2s_random_part_does_not():
    rng = np.random.default_rng(5)
    a, b = wavy_pair(rng)
    box = (np.abs(a[:, 0] - 2.5) < 0.3) & (np.abs(a[:, 1] - 2.5) < 0.3)  # the box's top, clear of its edges
    far = (np.abs(a[:, 0] - 2.5) > 1.0) | (np.abs(a[:, 1] - 2.5) > 1.0)  # clear of the box's cylinders
    core = np.r_[a[far][::20], a[box][::5]]
    on_box = np.r_[np.zeros(len(a[far][::20]), bool), np.ones(len(a[box][::5]), bool)]
    m3c2 = sdp.distances(a, b, core_points=core, registration_error=0)
    auto = sdp.distances(a, b, core_points=core)
    assert m3c2.significant[~on_box].mean() > 0.3  # the random part alone: the waves read as change
    assert 0.03 <= auto.significant[~on_box].mean() <= 0.07
    assert auto.significant[on_box].all()
    assert auto.registration_source == "measured on the stable part" and auto.registration_error > 0
    assert np.allclose(auto.lod - m3c2.lod, LEVEL_Z * auto.registration_error, equal_nan=True)
    assert auto.summary()["registration_source"] == "measured on the stable part"
    given = sdp.distances(a, b, core_points=core, registration_error=0.001)
    assert given.registration_source == "given" and given.registration_error == 0.001
    few = sdp.distances(a, b, core_points=core[:60])  # too few places to read a 5 % share from: M3C2's level
    assert few.registration_error == 0.0 and few.registration_source.startswith("M3C2's 0")
    assert np.array_equal(few.lod, sdp.distances(a, b, core_points=core[:60], registration_error=0).lod, equal_nan=True)


def test_a_series_measures_each_epochs_registration_error(tmp_path):
    rng = np.random.default_rng(6)
    a, b = wavy_pair(rng, n=30_000)
    epochs = [a, b, wavy_pair(rng, n=30_000)[0]]
    ds = sdp.series(epochs, output=tmp_path / "s.zarr")
    sdp.series(epochs[:2], output=tmp_path / "a.zarr")
    grown = sdp.series(epochs[2:], output=tmp_path / "a.zarr", append=True)  # each epoch's own: as the full run
    for name in ("distance", "lod", "significant", "registration_error", "smoothed", "smoothed_sigma"):
        assert np.array_equal(ds[name].values, grown[name].values, equal_nan=True), name
    reg = ds["registration_error"].values
    assert reg[0] == 0.0 and (reg[1:] > 0).all()  # the reference against itself: nothing to add
    assert [e["registration_source"] for e in ds.attrs["epochs"][1:]] == ["measured on the stable part"] * 2
    p = sdp.distance.PreparedReference.prepare(a, np.c_[ds["x"].values, ds["y"].values, ds["z"].values],
                                      cylinder=sdp.Cylinder(projection_scale=float(ds.attrs["parameters"]["used"]
                                                                                   ["projection_scale"])))
    one = p.measure(b)
    assert one.registration_error == pytest.approx(reg[1], rel=1e-6)
    assert np.allclose(ds["lod"].values[1], one.lod, rtol=1e-6, equal_nan=True)


def test_the_command_says_where_the_registration_error_came_from(tmp_path, capsys):
    from sdp.cli._main import main

    a, b = wavy_pair(np.random.default_rng(7), n=20_000)
    sdp.write_points(tmp_path / "a.ply", a)
    sdp.write_points(tmp_path / "b.ply", b)
    assert main(["distance", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "-o", str(tmp_path / "d.ply")]) == 0
    assert "measured on the stable part" in capsys.readouterr().out
    assert main(["distance", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "-o", str(tmp_path / "e.ply"),
                 "--registration-error", "0.003"]) == 0
    text = capsys.readouterr().out
    assert "(registration error 0.003)" in text and "stable part" not in text
