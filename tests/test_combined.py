"""One decision from density and distance (decision="combined") and the level of detection of
sdp.distance._noise (issue 34)."""

import numpy as np
import pytest

import sdp
from sdp.distance._noise import point_distances
from sdp.errors import InvalidOptionError

VOXEL = 0.02  # σ = 4 cm: the density test misses what stands less than about 2σ off a surface


def _floor(rng, n=90000, noise=0.002):
    """3 m × 3 m, 1 point per cm²."""
    return np.c_[rng.random((n, 2)) * 3.0, noise * rng.standard_normal(n)]


def _box(rng, size=0.3, height=0.12, per_cm2=1.0):
    """A box standing on the floor, its top and four sides sampled: the top stands out of the
    floor's kernel (2σ = 8 cm), the lower part of the sides does not."""
    lo, hi = 1.5 - size / 2, 1.5 + size / 2
    n_top, n_side = int(size * size * 1e4 * per_cm2), int(size * height * 1e4 * per_cm2)
    top = np.c_[rng.uniform(lo, hi, (n_top, 2)), np.full(n_top, height)]
    sides = []
    for axis in (0, 1):
        for at in (lo, hi):
            p = np.c_[rng.uniform(lo, hi, n_side), rng.uniform(0, height, n_side)]
            sides.append(np.insert(p, axis, at, axis=1))
    pts = np.concatenate([top, *sides])
    return pts + 0.002 * rng.standard_normal(pts.shape)


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(1)
    ref = _floor(rng)
    cur_floor = _floor(rng)
    inside = (np.abs(cur_floor[:, 0] - 1.5) < 0.15) & (np.abs(cur_floor[:, 1] - 1.5) < 0.15)
    box = _box(rng)
    cur = np.concatenate([cur_floor[~inside], box])
    return ref, cur, np.r_[np.zeros((~inside).sum(), bool), np.ones(len(box), bool)]


def test_the_combined_decision_finds_an_object_down_to_the_old_surface(scene):
    ref, cur, box = scene
    lattice = sdp.Lattice(voxel_size=VOXEL)
    density = sdp.detect_changes(ref, cur, lattice=lattice, decision="density")
    combined = sdp.detect_changes(ref, cur, lattice=lattice, decision="combined")
    low = box & (cur[:, 2] > 0.02) & (cur[:, 2] < 0.06)  # the sides' lower part, 2–6 cm up
    assert density.appeared[low].mean() < 0.5  # hidden in the floor's kernel
    assert combined.appeared[low].mean() > 0.9
    assert combined.appeared[box].mean() > density.appeared[box].mean() + 0.1
    assert combined.appeared[~box].mean() < 0.005  # the floor stays unchanged
    assert combined.current_distance.shape == (len(cur),) and combined.current_lod.shape == (len(cur),)
    assert len(combined.appeared_regions) >= 1
    assert combined.appeared_regions[0].n_points >= 0.8 * box.sum()
    s = combined.summary()
    assert s["decision"] == "combined" and s["current"]["level"]["systematic"] >= 0
    assert density.current_distance is None and "level" not in density.summary()["current"]


def test_density_is_the_point_decision(scene):
    ref, cur, _ = scene
    lattice = sdp.Lattice(voxel_size=VOXEL)
    a = sdp.detect_changes(ref, cur, lattice=lattice, decision="density")
    b = sdp.detect_changes(ref, cur, lattice=lattice, decision="point")
    assert np.array_equal(a.current_state, b.current_state) and a.decision == b.decision == "point"


def test_a_static_pair_is_significant_at_the_promised_level_and_not_changed():
    rng = np.random.default_rng(2)
    ref, cur = _floor(rng), _floor(rng)
    r = sdp.detect_changes(ref, cur, lattice=sdp.Lattice(voxel_size=VOXEL), decision="combined")
    assert r.appeared.mean() <= 0.005 and r.disappeared.mean() <= 0.005
    d, lod = r.current_distance, r.current_lod
    ok = np.isfinite(d)
    assert ok.mean() > 0.95
    assert 0.0 < (np.abs(d[ok]) > lod[ok]).mean() <= 0.07


def test_the_level_follows_the_range_law_of_a_depth_camera():
    """Depth noise growing as r² along the rays: the fitted exponent is near 2 and the level
    grows with range."""
    rng = np.random.default_rng(3)
    n = 60000

    def wall(scale):
        xy = rng.uniform(-1, 1, (n, 2))
        z = 1.0 + 1.5 * (xy[:, 0] + 1)  # a floor-like plane seen from 1 m to 4 m
        p = np.c_[xy[:, 0] * z, xy[:, 1], z]
        ray = p / np.linalg.norm(p, axis=1)[:, None]
        return p + ray * (scale * np.linalg.norm(p, axis=1) ** 2 * rng.standard_normal(n))[:, None]

    ref, cur = wall(0.002), wall(0.002)
    pd = point_distances(cur, ref, sigma=0.03, own_origin=np.zeros(3), other_origin=np.zeros(3))
    assert 1.2 <= pd.range_exponent <= 2.0
    r = np.linalg.norm(cur, axis=1)
    ok = np.isfinite(pd.lod)
    near, far = ok & (r < 1.8), ok & (r > 3.5)
    assert np.median(pd.lod[far]) > 2.5 * np.median(pd.lod[near])
    sig = pd.significant[ok].mean()
    assert 0.02 <= sig <= 0.07


def test_a_curved_surface_is_significant_at_the_promised_level():
    """A surface that curves within the cylinder (1 cm waves of 40 cm, σ = 4 cm): the other epoch's
    spread holds the curve across the cylinder, which a point near its axis does not carry, so the
    spreads alone promise 5 % and give about 0.2 %; the stable majority scales the level down to
    its 5 %."""
    rng = np.random.default_rng(4)

    def scan(n=90000):
        xy = rng.uniform(0, 3, (n, 2))
        wave = np.sin(2 * np.pi * xy[:, 0] / 0.4) * np.sin(2 * np.pi * xy[:, 1] / 0.4)
        return np.c_[xy, 0.01 * wave + 0.001 * rng.standard_normal(n)]

    pd = point_distances(scan(), scan(), sigma=0.04)
    ok = np.isfinite(pd.lod)
    assert ok.mean() > 0.95
    assert 0.03 <= pd.significant[ok].mean() <= 0.07


def test_bad_options_are_refused():
    pts = np.random.default_rng(0).random((100, 3))
    with pytest.raises(InvalidOptionError, match="decision"):
        sdp.detect_changes(pts, pts, decision="both")
    with pytest.raises(InvalidOptionError, match="registration_error"):
        point_distances(pts, pts, sigma=0.1, registration_error=-1.0)
    with pytest.raises(InvalidOptionError, match="range_exponent"):
        point_distances(pts, pts, sigma=0.1, range_exponent=3.0)


def test_the_command_writes_distance_and_lod(tmp_path, scene):
    ref, cur, box = scene
    a, b, out = tmp_path / "a.npy", tmp_path / "b.npy", tmp_path / "out.ply"
    np.save(a, ref)
    np.save(b, cur)
    res = sdp.compare_files(a, b, output=out, lattice=sdp.Lattice(voxel_size=VOXEL), decision="combined")
    cloud = sdp.read_points(out)
    assert {"change", "region", "distance", "lod"} <= set(cloud.fields)
    assert (cloud.fields["change"][box] == 1).mean() > 0.8
    assert res.summary["decision"] == "combined"


def test_tiles_take_the_combined_decision_and_density_not_the_cluster_rule():
    from sdp._core._validate import check_tiled_options

    check_tiled_options(decision="density")
    check_tiled_options(decision="combined")
    with pytest.raises(InvalidOptionError, match="--decision cluster is not available with --tiled"):
        check_tiled_options(decision="cluster")
    with pytest.raises(InvalidOptionError, match="--range-noise is not available with --tiled"):
        check_tiled_options(range_noise=0.004)  # tiles follow no sensor's rays
    check_tiled_options(range_noise=sdp.DEFAULTS.range_noise)


@pytest.mark.parametrize("tile_size", [10.0, 0.7])
def test_the_combined_decision_in_tiles_equals_memory(scene, monkeypatch, tile_size):
    """Tiles wider than the scene: the same calibration sample, the same states. Tiles of 0.7 m (the
    box across four of them): every tile's sample calibrates one level, so with that level fixed
    the components joined across the tiles are memory's."""
    from sdp.distance import _noise
    from sdp.scale._tiles import detect_changes_tiled

    ref, cur, box = scene
    if tile_size < 1:  # (p, r̃, c, σ_s): the random part alone
        monkeypatch.setattr(_noise, "fit_level", lambda *a, **k: (0.0, 1.0, 1.0, 0.0))
    lattice = sdp.Lattice(voxel_size=VOXEL)
    memory = sdp.detect_changes(ref, cur, lattice=lattice, decision="combined")
    tiled = detect_changes_tiled(ref, cur, lattice=lattice, decision="combined",
                                 execution=sdp.Execution(scheduler="synchronous", tile_size=tile_size))
    assert tile_size > 1 or tiled.n_tiles >= 16
    density = sdp.detect_changes(ref, cur, lattice=lattice, decision="density")
    assert memory.appeared[box].sum() > density.appeared[box].sum() + 100  # the distance completed the box
    assert memory.appeared[~box].mean() < 0.005  # and left the floor
    np.testing.assert_array_equal(tiled.appeared, memory.appeared)
    np.testing.assert_array_equal(tiled.disappeared, memory.disappeared)
    assert [r.n_points for r in tiled.appeared_regions] == [r.n_points for r in memory.appeared_regions]
    assert [r.volume for r in tiled.appeared_regions] == pytest.approx([r.volume for r in memory.appeared_regions])
    assert tiled.summary()["decision"] == "combined" and tiled.current_distance is None
    if tile_size > 1:  # one tile: memory's sample, memory's level, in the summary
        assert tiled.summary()["current"]["level"] == memory.summary()["current"]["level"]


def test_a_combined_regions_volume_is_the_space_it_fills_not_its_point_count(scene):
    """The box sampled four times as densely fills the same space: its region's volume (its cells
    of 1.5σ) stays within 25 %, and within a factor of two of the box's own 0.3 × 0.3 × 0.12 m."""
    ref, cur, box = scene
    dense = np.concatenate([cur[~box], _box(np.random.default_rng(7), per_cm2=4.0)])
    lattice = sdp.Lattice(voxel_size=VOXEL)
    volumes = [sdp.detect_changes(ref, c, lattice=lattice, decision="combined").appeared_regions[0].volume
               for c in (cur, dense)]
    assert volumes[1] == pytest.approx(volumes[0], rel=0.25)
    assert 0.5 < volumes[0] / (0.3 * 0.3 * 0.12) < 2.0


@pytest.mark.slow
def test_the_command_takes_the_combined_decision_to_tiles(scene, tmp_path):
    from sdp.cli import main

    ref, cur, box = scene
    a, b = tmp_path / "a.npy", tmp_path / "b.npy"
    np.save(a, ref)
    np.save(b, cur)
    common = ["--voxel-size", str(VOXEL), "--decision", "combined", "--quiet"]
    assert main(["change", str(a), str(b), "-o", str(tmp_path / "m.laz"), *common]) == 0
    assert main(["change", str(a), str(b), "-o", str(tmp_path / "t.laz"), *common, "--tiled", "--tile-size", "10",
                 "--scheduler", "synchronous"]) == 0
    memory, tiled = (sdp.read_points(tmp_path / f"{k}.laz").fields for k in ("m", "t"))
    np.testing.assert_array_equal(tiled["change"], memory["change"])
    assert (tiled["change"][box] == 1).mean() > 0.8 and "distance" not in tiled and "distance" in memory


def _decide(cur, ref, states, found, present=None):
    from sdp.change._combined import combine_decision
    from sdp.change._coverage import UNCHANGED
    from sdp.distance._noise import SurfaceDistances

    sd = SurfaceDistances(cur, ref, sigma=2 * VOXEL, stable=states == UNCHANGED)
    present = (lambda p: np.ones(len(p), bool)) if present is None else present
    idx = np.flatnonzero(found)
    changed = combine_decision(sd, states, directed=False, present=present, found=idx,
                               found_regions=np.zeros(len(idx), np.int64))[0]
    return changed, sd


def test_only_what_the_density_keeps_lets_the_distance_complete_a_component():
    """Rule 4: a patch raised 15 mm (below the density's reach, beyond the level) is kept only if
    it holds a point the density's own decision keeps; a stray density point (its region below
    min_region_points, dropped by that decision) does not keep it."""
    from sdp.change._coverage import CHANGED, UNCHANGED

    rng = np.random.default_rng(3)
    ref, cur = _floor(rng, n=40000), _floor(rng, n=40000)
    patch = (np.abs(cur[:, 0] - 1.5) < 0.2) & (np.abs(cur[:, 1] - 1.5) < 0.2)
    cur[patch, 2] += 0.015
    states = np.full(len(cur), UNCHANGED, np.int8)
    stray = np.flatnonzero(patch)[0]
    states[stray] = CHANGED  # the density marked one point of the patch
    dropped, _ = _decide(cur, ref, states, found=np.zeros(len(cur), bool))
    kept, _ = _decide(cur, ref, states, found=states == CHANGED)
    assert kept[patch].mean() > 0.8  # the distance completes the patch
    assert not dropped.any()  # seeded by a stray only: nothing
    assert kept[~patch].mean() < 0.005


def test_a_density_region_in_cells_that_do_not_touch_is_kept_whole():
    """The density's volume joins points farther apart than two cells of 1.5σ (a sparse scan):
    its region of 60 points in three groups of 20, three cells apart, is one region of the
    combined decision, not three strays below min_region_points (on the Toronto pair the
    combined decision had lost the density's 61 appeared points so)."""
    from sdp.change._combined import combine_decision
    from sdp.change._coverage import CHANGED, UNCHANGED
    from sdp.distance._noise import SurfaceDistances

    rng = np.random.default_rng(4)
    ref, floor = _floor(rng, n=40000), _floor(rng, n=40000)
    cell = 1.5 * 2 * VOXEL
    groups = [np.c_[rng.uniform(0, 0.3 * cell, (20, 2)) + [1.0 + 3 * cell * g, 1.0], np.full(20, 0.5)]
              for g in range(3)]
    cur = np.concatenate([floor, *groups])
    states = np.full(len(cur), UNCHANGED, np.int8)
    states[len(floor):] = CHANGED
    found = np.arange(len(floor), len(cur))
    sd = SurfaceDistances(cur, ref, sigma=2 * VOXEL, stable=states == UNCHANGED)
    changed, regions, labels = combine_decision(sd, states, directed=False,
                                                present=lambda p: np.ones(len(p), bool), found=found,
                                                found_regions=np.zeros(len(found), np.int64))
    assert changed[found].all() and len(regions) == 1 and regions[0].n_points == changed.sum()
    assert (labels[found] == 0).all() and changed.sum() < len(found) + 100


def test_components_holding_one_density_region_are_joined():
    """Four components: 0 and 1 hold points of density region 0, 2 a point in no region (-1), 3
    nothing: regions 0, 0, 1, 2, numbered in the components' order."""
    from sdp.change._combined import joined_by_regions

    joined = joined_by_regions(np.array([0, 1, 1, 2]), np.array([0, 0, 0, -1]), 4)
    assert joined.tolist() == [0, 0, 1, 2]
    assert joined_by_regions(np.zeros(0, np.int64), np.zeros(0, np.int64), 2).tolist() == [0, 1]


@pytest.mark.slow
def test_on_airborne_lidar_the_combined_decision_keeps_what_the_density_finds(shared_data):
    """Toronto 2015 → 2023, the ground aligned: the density alone finds 61 appeared points in
    regions whose points lie more than two cells of 1.5σ apart; the combined decision keeps every
    point the density marks, in both directions (it had dropped them all as strays)."""
    a, b = (sdp.read_points(shared_data / "als_toronto" / f"TTP_{y}.laz") for y in (2015, 2023))
    ground = [c.xyz[c.fields["classification"] == 2] for c in (a, b)]
    m = sdp.align(*ground, fix_horizontal=True).matrix
    moved = b.xyz @ m[:3, :3].T + m[:3, 3]
    density = sdp.detect_changes(a.xyz, moved)
    combined = sdp.detect_changes(a.xyz, moved, decision="combined")
    assert density.appeared.sum() > 50
    for kind in ("appeared", "disappeared"):
        assert not (getattr(density, kind) & ~getattr(combined, kind)).any()
    assert combined.disappeared.sum() > density.disappeared.sum()


@pytest.mark.parametrize("far", [False, True])  # True: a patch 100 km away, so the cells are in a hash table
def test_growing_from_the_seeds_decides_as_measuring_everywhere_does(far):
    """The components grown cell ring by cell ring from what the density keeps are the rule's:
    every point changed by density, or by distance (beyond 3.29/1.96 × its level, inside its own
    volume), in a 26-connected component of changed cells that holds a kept point (rules 2–4,
    written out here over distances measured everywhere), with the cells in a dense table or in
    a hash table."""
    from sdp.change._combined import DECISION_FACTOR
    from sdp.change._coverage import CHANGED, UNCHANGED

    rng = np.random.default_rng(5)
    ref, cur = _floor(rng, n=60000), _floor(rng, n=60000)
    for x, y, dz in ((0.6, 0.6, 0.015), (1.6, 1.5, 0.02), (2.4, 2.3, 0.012), (1.0, 2.4, 0.03)):
        cur[(np.abs(cur[:, 0] - x) < 0.15) & (np.abs(cur[:, 1] - y) < 0.15), 2] += dz
    if far:
        ref, cur = (np.concatenate([c, _floor(rng, n=3000) / 3.0 + [1e5, 0, 0]]) for c in (ref, cur))
    states = np.full(len(cur), UNCHANGED, np.int8)
    states[(np.abs(cur[:, 0] - 1.6) < 0.03) & (np.abs(cur[:, 1] - 1.5) < 0.03)] = CHANGED  # a kept seed
    states[(np.abs(cur[:, 0] - 2.4) < 0.01) & (np.abs(cur[:, 1] - 2.3) < 0.01)] = CHANGED  # a stray
    states[rng.choice(len(cur), 20, replace=False)] = CHANGED  # strays on the floor
    found = (states == CHANGED) & (np.abs(cur[:, 0] - 1.6) < 0.03)
    found |= (states == CHANGED) & (np.abs(cur[:, 0] - 1.0) < 0.5) & (cur[:, 1] > 2.3)  # none there: no seed
    present = cur[:, 0] < 2.0  # the patch at x = 2.4 is not matter of its own epoch
    grown, sd = _decide(cur, ref, states, found, present=lambda p: p[:, 0] < 2.0)
    assert (sd._dims[0] == 0) == far  # the kind of table the cells are in

    pd = sd.everywhere()
    with np.errstate(invalid="ignore"):
        beyond = np.abs(pd.distance) > DECISION_FACTOR * pd.lod
    changed = (states == CHANGED) | ((states == UNCHANGED) & beyond & present)
    labels, counts = _cell_components(pd.cells, pd.cell_index, changed)
    seeded = np.zeros(len(counts), bool)
    seeded[labels[found]] = True
    rule = changed & seeded[np.maximum(labels, 0)]
    assert rule.sum() > 300 and np.array_equal(grown, rule)


def _cell_components(cells, cell_index, changed):
    """(label per point, -1 if not changed; points per component) of the 26-connected cells
    that hold a changed point, by SciPy (pairs of cells less than 2 apart, then a graph's
    components)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    labels = np.full(len(cells), -1, np.int64)
    hit = np.unique(cells[changed])
    pairs = cKDTree(cell_index[hit]).query_pairs(1.8, output_type="ndarray")  # √3 < 1.8 < 2
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(hit.size, hit.size))
    n, comp = connected_components(graph, directed=False)
    of_cell = np.full(len(cell_index), -1, np.int64)
    of_cell[hit] = comp
    labels[changed] = of_cell[cells[changed]]
    return labels, np.bincount(labels[changed], minlength=n)


def test_a_stream_decides_as_the_pair_does(scene):
    """``sdp.watch(decision="combined")`` against a fixed model (``update="none"``) marks the
    frame's points as ``detect_changes`` marks the current's: the box down to the floor."""
    ref, cur, box = scene
    lattice = sdp.Lattice(voxel_size=VOXEL)
    pair = sdp.detect_changes(ref, cur, lattice=lattice, decision="combined")
    density, combined = (next(sdp.watch(ref, [cur], lattice=lattice, update="none", decision=dec))
                         for dec in ("point", "combined"))
    assert np.array_equal(combined.appeared, pair.appeared)
    assert combined.appeared[box].mean() > density.appeared[box].mean() + 0.1
    assert [r.n_points for r in combined.regions] == [r.n_points for r in pair.appeared_regions]
    with pytest.raises(InvalidOptionError, match="decision"):
        next(sdp.watch(ref, [cur], decision="cluster"))
    with pytest.raises(InvalidOptionError, match="combined"):
        next(sdp.watch(pair.reference_field, [cur], decision="combined"))


def test_a_given_noise_model_sets_the_level_in_memory_streams_and_tiles(scene):
    """``noise=sdp.NoiseModel(...)``: a given systematic part is the level's (σ_s = reg/1.96), and
    one far above the box's height leaves the distance nothing to mark, so the combined decision
    is the density's, in memory, in a stream and in tiles; errors correlated over a length widen
    the random part; the model is refused where no level takes it."""
    from sdp.scale._tiles import detect_changes_tiled

    ref, cur, box = scene
    lattice = sdp.Lattice(voxel_size=VOXEL)
    density = sdp.detect_changes(ref, cur, lattice=lattice)
    huge = sdp.NoiseModel(registration_error=0.5, range_exponent=0)
    r = sdp.detect_changes(ref, cur, lattice=lattice, decision="combined", noise=huge)
    level = r.summary()["current"]["level"]
    assert level["systematic"] == pytest.approx(0.5 / 1.96) and level["range_exponent"] == 0
    assert level["given"] == {"registration_error": 0.5, "range_exponent": 0.0}
    assert np.array_equal(r.appeared, density.appeared) and np.nanmin(r.current_lod) >= 0.5
    stream = next(sdp.watch(ref, [cur], lattice=lattice, update="none", decision="combined", noise=huge))
    tiled = detect_changes_tiled(ref, cur, lattice=lattice, decision="combined", noise=huge,
                                 execution=sdp.Execution(scheduler="synchronous", tile_size=10.0))
    assert np.array_equal(stream.appeared, density.appeared) and np.array_equal(tiled.appeared, density.appeared)
    assert tiled.summary()["reference"]["level"]["given"] == level["given"]
    measured = sdp.detect_changes(ref, cur, lattice=lattice, decision="combined")
    assert measured.appeared[box].sum() > density.appeared[box].sum() + 100 and "given" not in \
        measured.summary()["current"]["level"]
    corr = sdp.NoiseModel(correlation_length=4 * VOXEL, registration_error=0, range_exponent=0)
    plain = sdp.NoiseModel(registration_error=0, range_exponent=0)
    lods = [sdp.detect_changes(ref, cur, lattice=lattice, decision="combined", noise=n).current_lod
            for n in (plain, corr)]
    ok = np.isfinite(lods[0])
    assert (lods[1][ok] >= lods[0][ok]).all() and np.median(lods[1][ok] / lods[0][ok]) > 1.05
    for call in (lambda: sdp.detect_changes(ref, cur, noise=huge), lambda: next(sdp.watch(ref, [cur], noise=huge)),
                 lambda: detect_changes_tiled(ref, cur, noise=huge)):
        with pytest.raises(InvalidOptionError, match="give --decision combined"):
            call()
    for bad, match in ((dict(range_exponent=2.5), "range_exponent"), (dict(range_exponent="x"), "range_exponent"),
                       (dict(registration_error=-1), "registration_error"),
                       (dict(correlation_length=0), "correlation_length")):
        with pytest.raises(InvalidOptionError, match=match):
            sdp.NoiseModel(**bad)


def test_the_commands_take_the_noise_model(tmp_path, scene, capsys):
    """``sdp change`` and ``sdp watch`` take ``--registration-error``, ``--range-exponent`` and
    ``--correlation-length`` with ``--decision combined`` (the summary's level says what was
    given), and refuse them in one line, exit 2, with another decision, before writing anything."""
    from sdp.cli import main

    ref, cur, _ = scene
    a, b, frames = tmp_path / "a.npy", tmp_path / "b.npy", tmp_path / "frames"
    np.save(a, ref)
    np.save(b, cur)
    frames.mkdir()
    np.save(frames / "f0.npy", cur)
    given = ["--registration-error", "0.5", "--range-exponent", "0", "--correlation-length", "0.08"]
    assert main(["change", str(a), str(b), "-o", str(tmp_path / "c.npz"), "--voxel-size", str(VOXEL),
                 "--decision", "combined", *given, "--json"]) == 0
    import json
    level = json.loads(capsys.readouterr().out)["current"]["level"]
    assert level["given"] == {"registration_error": 0.5, "range_exponent": 0.0, "correlation_length": 0.08}
    assert main(["change", str(a), str(b), "-o", str(tmp_path / "e.npz"), "--voxel-size", str(VOXEL),
                 "--decision", "combined", "--range-exponent", "0"]) == 0
    text = capsys.readouterr().out
    assert "range exponent 0.00 (given)" in text and "at 95 % (measured)" in text
    assert main(["watch", str(a), str(frames), "--voxel-size", str(VOXEL), "--decision", "combined", *given]) == 0
    capsys.readouterr()
    for cmd in (["change", str(a), str(b), "-o", str(tmp_path / "d.npz")], ["watch", str(a), str(frames)]):
        assert main([*cmd, "--range-exponent", "2"]) == 2
        err = capsys.readouterr().err.strip()
        assert "give --decision combined" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "d.npz").exists()
    with pytest.raises(SystemExit) as exit_:  # argparse's own check
        main(["change", str(a), str(b), "-o", str(tmp_path / "d.npz"), "--decision", "combined",
              "--range-exponent", "3"])
    assert exit_.value.code == 2 and "--range-exponent" in capsys.readouterr().err


def test_distances_measured_in_parts_equal_those_measured_at_once(scene):
    """A cell's distance does not depend on which cells were measured before it: some points
    first (as the decision does), then every point, equals every point at once."""
    from sdp.distance._noise import SurfaceDistances

    ref, cur, box = scene
    kw = dict(sigma=2 * VOXEL, own_origin=np.array([1.5, 1.5, 3.0]), other_origin=np.array([1.5, 1.5, 3.0]),
              stable=~box)
    parts = SurfaceDistances(cur, ref, **kw)
    some = np.flatnonzero(box)[::3]
    d_some, lod_some = parts.at(some)
    whole = SurfaceDistances(cur, ref, **kw).everywhere()
    later = parts.everywhere()
    assert np.array_equal(later.distance, whole.distance, equal_nan=True)
    assert np.array_equal(later.lod, whole.lod, equal_nan=True)
    assert np.array_equal(d_some, whole.distance[some], equal_nan=True)
    assert np.array_equal(lod_some, whole.lod[some], equal_nan=True)
    assert np.isfinite(whole.distance).mean() > 0.95 and whole.range_exponent >= 0


def test_the_distances_memory_is_checked_before_any_work():
    """The combined decision's cells and arrays count against the memory limit, before the
    fields are built: refused in one line where the density alone fits."""
    rng = np.random.default_rng(6)
    ref, cur = _floor(rng), _floor(rng)
    lattice = sdp.Lattice(voxel_size=VOXEL)
    sdp.detect_changes(ref, cur, lattice=lattice, decision="point", memory_limit="20MB")
    with pytest.raises(sdp.GridTooLargeError, match="combined decision's distances .* decision='point'"):
        sdp.detect_changes(ref, cur, lattice=lattice, decision="combined", memory_limit="20MB")
