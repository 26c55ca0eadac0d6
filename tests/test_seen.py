"""A place the other epoch's sensor could not see gets no distance (:mod:`sdp.distance._seen`)."""

import numpy as np

import sdp


def shadowed_floor(rng, n=60_000):
    """A floor seen from 3 m above its middle; in the second epoch a plate 0.3 m above the floor
    hides part of it from the same sensor (the floor points under it are not returned)."""
    origin = np.array([2.0, 2.0, 3.0])
    floor = np.c_[rng.uniform(0, 4, (n, 2)), 0.001 * rng.standard_normal(n)]
    plate = np.c_[rng.uniform(1.6, 2.4, (n // 25, 2)), 0.3 + 0.001 * rng.standard_normal(n // 25)]
    # where the ray from the sensor to a floor point crosses the plate's height
    t = (3.0 - 0.3) / 3.0
    cross = origin[:2] + t * (floor[:, :2] - origin[:2])
    shadow = np.all((cross > 1.6) & (cross < 2.4), axis=1)
    second = np.r_[floor[~shadow], plate]
    return sdp.Cloud(floor, sensors=origin[None]), sdp.Cloud(second, sensors=origin[None]), shadow


def test_a_hidden_floor_is_not_comparable_where_m3c2_measures_the_plate(tmp_path, capsys):
    rng = np.random.default_rng(3)
    first, second, shadow = shadowed_floor(rng)
    blind = sdp.distances(first, second, sensor_origin=None)  # M3C2: the plate found along the normal
    assert np.nanmedian(blind.distance[shadow]) > 0.25 and blind.level[shadow].max() == 1
    d = sdp.distances(first, second)  # the sensor known: the floor under the plate was not seen
    inner = shadow & np.all(np.abs(first.xyz[:, :2] - 2.0) < 0.3, axis=1)
    assert not d.comparable[inner].any() and d.significant[shadow].mean() < 0.05  # the shadow's rim: measured
    assert d.not_seen == int((~d.comparable & blind.comparable).sum()) >= inner.sum()
    assert d.comparable[~shadow].mean() > 0.99 and d.significant[~shadow].mean() < 0.07
    assert d.summary()["not_seen"] == d.not_seen
    given = sdp.distances(first.xyz, second.xyz, sensor_origin=[2.0, 2.0, 3.0])  # arrays, the sensor given
    assert np.array_equal(given.distance, d.distance, equal_nan=True) and given.not_seen == d.not_seen
    from sdp.cli._main import main

    sdp.write_points(tmp_path / "a.ply", first.xyz)
    sdp.write_points(tmp_path / "b.ply", second.xyz)
    assert main(["distance", str(tmp_path / "a.ply"), str(tmp_path / "b.ply"), "-o", str(tmp_path / "d.ply"),
                 "--sensor-origin", "2,2,3"]) == 0
    assert "its sensor could not see the place" in capsys.readouterr().out


def test_a_series_epoch_knows_what_its_sensor_did_not_see(tmp_path):
    rng = np.random.default_rng(4)
    first, second, shadow = shadowed_floor(rng, n=30_000)
    ds = sdp.series([first, second], output=tmp_path / "s.zarr")
    core = np.c_[ds["x"].values, ds["y"].values, ds["z"].values]
    u = ds.attrs["parameters"]["used"]
    pair = sdp.distances(first, second, core_points=core, cylinder=sdp.Cylinder(
        projection_scale=u["projection_scale"], normal_scale=u["normal_scale"], max_distance=u["max_distance"]))
    under = np.all(np.abs(core[:, :2] - 2.0) < 0.3, axis=1)
    assert under.sum() > 10 and np.isnan(ds["distance"].values[1, under]).all()
    assert np.array_equal(np.isnan(ds["distance"].values[1]), np.isnan(pair.distance))
    assert np.allclose(ds["distance"].values[1], pair.distance, atol=1e-6, equal_nan=True)
