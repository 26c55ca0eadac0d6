"""M3C2's step edge: no distance where the current's surface only touches the cylinder off its axis."""

import numpy as np
import pytest

import sdp
from sdp.cli._text import distance_text
from sdp.distance._reference import STATE_ARRAYS, PreparedReference

NOISE = 0.003
D = 0.2  # projection scale: σ_p = 5 cm
SIGMA = D / 4
DENSITY = 10_000  # points per m²: about 300 effective points in a cylinder, so its rim weighs enough


def patch(rng, lo, hi, noise=NOISE):
    """Points spread evenly over the box ``lo``–``hi`` (one of its sides of zero width), with noise."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    area = np.prod([s for s in hi - lo if s > 0])
    n = int(DENSITY * area)
    return lo + rng.random((n, 3)) * (hi - lo) + noise * rng.standard_normal((n, 3))


def door_scene(rng):
    """A wall (the plane y = 0, x −1…2, z 0…2.5) with a doorway x 0…1, z 0…2: (the wall, the
    door leaf closed in it, the leaf swung open by 90° about its hinge x = 0, into y < 0)."""
    wall = np.concatenate([patch(rng, (-1, 0, 0), (0, 0, 2.5)), patch(rng, (1, 0, 0), (2, 0, 2.5)),
                           patch(rng, (0, 0, 2), (1, 0, 2.5))])
    closed = patch(rng, (0.005, 0, 0), (0.995, 0, 1.995))
    swung = patch(rng, (0, -0.99, 0), (0, -0.005, 1.995))
    return wall, closed, swung


def door_distances(rng, **kwargs):
    wall, closed, swung = door_scene(rng)
    ref = np.concatenate([wall, closed])
    cur = np.concatenate([wall + NOISE * rng.standard_normal(wall.shape), swung])
    core = ref[::10]
    d = sdp.distances(ref, cur, core_points=core, cylinder=sdp.Cylinder(projection_scale=D), registration_error=0,
                      orientation=(0, 1, 0), **kwargs)
    on_leaf = np.zeros(len(ref), bool)
    on_leaf[len(wall):] = True
    return ref, cur, core, d, on_leaf[::10]


def test_a_door_swung_open_leaves_its_closed_leaf_without_a_distance(rng):
    _, _, core, d, on_leaf = door_distances(rng)
    x, z = core[:, 0], core[:, 2]
    inside = on_leaf & (np.minimum(x, 1 - x) > 1.5 * SIGMA) & (2 - z > 1.5 * SIGMA)
    # the frame at the cylinder's rim gave these a small distance (significant) where there is no surface
    assert inside.sum() > 1000
    assert not d.comparable[inside].any()
    assert (d.level[inside] == -1).all()
    # counted apart, and the summary says why
    s = d.summary()
    assert s["off_axis"] == int(d.off_axis.sum()) > 0
    assert d.off_axis[inside & np.isfinite(d.n2)].any()
    assert "off its axis" in distance_text(s, "night1", "night2")
    # the wall around stays measured, ≈ 0 (beside the hinge the open leaf lies in its cylinders)
    wall = ~on_leaf
    assert d.comparable[wall].all() and not d.off_axis[wall].any()
    away = wall & ((np.abs(x) > 3 * SIGMA) | (z > 2 + 3 * SIGMA))
    assert np.abs(d.distance[away]).max() < 0.005


def test_the_wall_behind_a_door_swung_open_is_measured(rng):
    """Where the leaf's axis meets another surface (the wall of the room behind), that surface answers."""
    wall, closed, swung = door_scene(rng)
    behind = patch(rng, (-0.5, -1.5, 0), (1.5, -1.5, 2.5))
    ref = np.concatenate([wall, closed])
    cur = np.concatenate([wall, swung, behind])
    core = closed[::10]
    d = sdp.distances(ref, cur, core_points=core, cylinder=sdp.Cylinder(projection_scale=D), registration_error=0,
                      orientation=(0, 1, 0))
    middle = (np.abs(core[:, 0] - 0.5) < 0.3) & (core[:, 2] < 1.7)
    assert d.comparable[middle].all() and np.allclose(d.distance[middle], -1.5, atol=0.01)


def test_an_unchanged_table_edge_stays_measured(rng):
    """Both epochs hold the same half-disc at the edge: the same centroid across the axis."""
    top = patch(rng, (0, 0, 0.75), (1, 1, 0.75))
    again = patch(rng, (0, 0, 0.75), (1, 1, 0.75))
    edge = top[(top[:, 0] > 1 - SIGMA) | (top[:, 1] > 1 - SIGMA)]
    d = sdp.distances(top, again, core_points=edge, cylinder=sdp.Cylinder(projection_scale=D), registration_error=0)
    assert d.comparable.all() and not d.off_axis.any()
    assert np.abs(d.distance).max() < 0.003  # noise / √n: a fraction of a millimetre
    assert d.significant.mean() < 0.1  # within the level, as M3C2 promises (5 %)


def test_the_floor_under_a_pallet_set_down_reads_its_top_or_nothing(rng):
    """Core points on the floor where a 1 m pallet now stands, farther than 1.5σ_p from its sides
    (nearer, the cylinder straddles the step at its own resolution): its top, 1 m up, or no
    distance, never a small significant value from its sides."""
    floor, again = patch(rng, (0, 0, 0), (4, 4, 0)), patch(rng, (0, 0, 0), (4, 4, 0))

    def under(p):
        return (np.abs(p[:, 0] - 2) < 0.5) & (np.abs(p[:, 1] - 2) < 0.5)

    sides = [patch(rng, (1.5, 1.5, 0), (2.5, 1.5, 1)), patch(rng, (1.5, 2.5, 0), (2.5, 2.5, 1)),
             patch(rng, (1.5, 1.5, 0), (1.5, 2.5, 1)), patch(rng, (2.5, 1.5, 0), (2.5, 2.5, 1))]
    pallet = np.concatenate([patch(rng, (1.5, 1.5, 1), (2.5, 2.5, 1)), *sides])
    cur = np.concatenate([again[~under(again)], pallet])
    core = floor[under(floor)][::5]
    d = sdp.distances(floor, cur, core_points=core, cylinder=sdp.Cylinder(projection_scale=D), registration_error=0)
    inside = 0.5 - np.abs(core[:, :2] - 2).max(axis=1)  # how far from the pallet's sides
    ok = d.comparable & (inside > 1.5 * SIGMA)
    assert ok.sum() > 1000 and np.allclose(d.distance[ok], 1.0, atol=0.02)
    assert d.summary()["off_axis"] > 0
    assert d.comparable[inside > 4 * SIGMA].all()  # beyond the sides' reach: the top


def test_series_epochs_find_the_same_places_off_the_axis(rng):
    ref, cur, core, d, _ = door_distances(rng)
    prepared = PreparedReference.prepare(ref, core, cylinder=sdp.Cylinder(projection_scale=D), orientation=(0, 1, 0))
    e = prepared.measure(cur, registration_error=0)
    assert np.array_equal(e.off_axis, d.off_axis) and np.array_equal(e.distance, d.distance, equal_nan=True)
    # an archive's state kept before the reference's centroid: no place found off the axis, as it measured then
    arrays, scalars = prepared.state()
    old = PreparedReference.from_state({k: arrays[k] for k in STATE_ARRAYS[:6]}, scalars)
    assert not old.measure(cur, registration_error=0).off_axis.any()


@pytest.mark.slow  # tiles / an archive: the full suite's
def test_tiles_find_the_same_places_off_the_axis(rng):
    ref, cur, core, _, _ = door_distances(rng)
    d = sdp.distances(ref, cur, cylinder=sdp.Cylinder(projection_scale=D), registration_error=0,
                      orientation=(0, 1, 0))
    t = sdp.distances_tiled(ref, cur, cylinder=sdp.Cylinder(projection_scale=D), registration_error=0,
                            orientation=(0, 1, 0),
                            execution=sdp.Execution(tile_size=1.0, scheduler="synchronous"))
    assert t.tiles > 1 and t.summary()["off_axis"] == d.summary()["off_axis"] > 0
    assert np.array_equal(t.off_axis, d.off_axis)


@pytest.mark.slow  # tiles / an archive: the full suite's
def test_an_archive_without_the_references_centroid_is_appended_to(tmp_path):
    """An archive written before the reference's centroid across the axis was kept: appended to,
    its epochs measured as it measured them (no place off the axis)."""
    import json
    import shutil

    from sdp.data import slope_series

    s = slope_series(5, 4000, size=6.0, step_epoch=4, seed=3)
    out = tmp_path / "old.zarr"
    cyl = sdp.Cylinder(projection_scale=0.5)
    sdp.series(s.epochs[:3], output=out, cylinder=cyl, registration_error=0.002)
    meta = json.loads((out / "zarr.json").read_text())
    for name in ("ref_across_x", "ref_across_y", "ref_across_z", "ref_across_var"):
        shutil.rmtree(out / name)
        del meta["consolidated_metadata"]["metadata"][name]
    (out / "zarr.json").write_text(json.dumps(meta))
    grown = sdp.series(s.epochs[3:], output=out, append=True)
    assert grown.sizes["epoch"] == 5 and "ref_across_var" not in grown
    assert np.isfinite(grown.distance.values[3:]).mean() > 0.9
