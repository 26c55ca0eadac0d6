"""Tiled change detection (sdp.tiles), streaming input (PointSource) and streamed LAS output."""

import json
import subprocess
import sys

import laspy
import numpy as np
import pytest
from conftest import box_surface, write_las

import sdp
import sdp.scale._session
from sdp.io import CloudFileError, PointSource, write_points, write_points_streamed
from sdp.scale._tiles import detect_changes_tiled

UTM = np.array([630_000.0, 4_830_000.0, 100.0])


def street(rng, boxes, n=120_000, mast=False):
    """A 30 m × 20 m ground with box-shaped objects on it, at UTM-like coordinates; with ``mast``
    a 300 m radio mast too, whose height makes dense grids over the box large (1.6 GB at 0.1 m)."""
    ground = np.c_[rng.uniform(0, 30, n), rng.uniform(0, 20, n), 0.01 * rng.standard_normal(n)]
    objects = [box_surface(rng, lo, hi, 4000) for lo, hi in boxes]
    if mast:
        objects.append(box_surface(rng, [28, 18, 0], [28.3, 18.3, 300], 20_000))
    return np.concatenate([ground, *objects]) + UTM


@pytest.fixture
def epochs(rng):
    ref = street(rng, [([2, 2, 0], [4, 5, 1.5]), ([14, 9.5, 0], [16, 10.5, 2])])
    cur = street(rng, [([2, 2, 0], [4, 5, 1.5]), ([9.5, 15.5, 0], [10.8, 16.8, 1.2]), ([25, 3, 0], [26, 4, 1])])
    cur[[7, 70_000]] = np.nan
    return ref, cur


def regions_of(rs):
    return sorted((r.n_points, round(r.volume, 6), tuple(np.round(r.centroid, 6))) for r in rs)


@pytest.mark.parametrize("min_region_points", [pytest.param(1, marks=pytest.mark.slow), 500])
def test_tiled_equals_untiled(epochs, min_region_points):
    ref, cur = epochs
    a = sdp.detect_changes(ref, cur, min_region_points=min_region_points, lattice=sdp.Lattice(voxel_size=0.1))
    # 4 m tiles: objects straddle tile borders (one sits across a corner of four tiles)
    b = detect_changes_tiled(ref, cur, min_region_points=min_region_points, lattice=sdp.Lattice(voxel_size=0.1),
                             execution=sdp.Execution(tile_size=4.0, scheduler="synchronous"))
    assert isinstance(b, sdp.ChangeResult) and b.tiled and not a.tiled and b.n_tiles >= 35
    assert b.reference_field is None and b.current_field is None
    # a streamed writer's slices of rows, made from the changed rows before any per-point array
    for cloud, state, labels in (("current", a.current_state, a.appeared_labels),
                                 ("reference", a.reference_state, a.disappeared_labels)):
        for start, stop in ((0, 10), (69_990, 70_010), (len(state) - 5, len(state) + 5)):
            got = b.rows(cloud, start, stop)
            np.testing.assert_array_equal(got[0], state[start:stop])
            np.testing.assert_array_equal(got[1], labels[start:stop])
    assert b._current._state is None and b._reference._state is None  # rows alone, until asked
    for role in ("reference", "current"):
        assert b.summary()[role] == a.summary()[role]
    assert b.current_state.dtype == np.uint8 and b.appeared_labels.dtype == np.int32
    assert a.appeared.sum() > 4000 and a.disappeared.sum() > 2000
    np.testing.assert_array_equal(b.appeared, a.appeared)
    np.testing.assert_array_equal(b.disappeared, a.disappeared)
    assert regions_of(b.appeared_regions) == regions_of(a.appeared_regions)
    assert regions_of(b.disappeared_regions) == regions_of(a.disappeared_regions)
    np.testing.assert_array_equal(b.appeared_labels, a.appeared_labels)
    np.testing.assert_array_equal(b.disappeared_labels, a.disappeared_labels)
    np.testing.assert_array_equal(b.current_state, a.current_state)
    assert b.n_dropped_current == 2 and b.summary()["current"]["appeared"] == a.appeared.sum()


@pytest.mark.slow
def test_tiled_regions_join_across_many_tiles(rng):
    """Regions labelled tile by tile and joined across the faces equal the whole volume's, for
    objects over many tiles: a wall along x, a staircase along the diagonal, a ring around a
    tile corner (its halves meet again in another tile), at the smallest tiles the halo allows."""
    stairs = [([8 + i, 8 + i, 0], [9.2 + i, 9.2 + i, 0.8]) for i in range(8)]
    ring = [([20, 4, 0], [26, 4.4, 1]), ([20, 9.6, 0], [26, 10, 1]), ([20, 4, 0], [20.4, 10, 1]),
            ([25.6, 4, 0], [26, 10, 1])]
    ref = street(rng, [])
    cur = street(rng, [([1, 1, 0], [19, 1.5, 1.2]), *stairs, *ring])
    a = sdp.detect_changes(ref, cur, min_region_points=1, lattice=sdp.Lattice(voxel_size=0.1))
    b = detect_changes_tiled(ref, cur, min_region_points=1, lattice=sdp.Lattice(voxel_size=0.1),
                             execution=sdp.Execution(tile_size=2.4, scheduler="synchronous"))
    assert b.n_tiles >= 100 and b.tile_size == pytest.approx(2.4)
    np.testing.assert_array_equal(b.appeared, a.appeared)
    big = [r for r in a.appeared_regions if r.n_points > 2000]
    assert len(big) == 3 and all(r.size[0] > 5 for r in big)  # the wall, the stairs, the ring: over tiles
    assert regions_of(b.appeared_regions) == regions_of(a.appeared_regions)
    np.testing.assert_array_equal(b.appeared_labels, a.appeared_labels)


@pytest.mark.slow
def test_tiled_on_dask_clusters(epochs):
    from dask.distributed import LocalCluster

    ref, cur = epochs
    a = detect_changes_tiled(ref, cur, lattice=sdp.Lattice(voxel_size=0.1),
                             execution=sdp.Execution(tile_size=8.0, scheduler="synchronous"))
    b = detect_changes_tiled(ref, cur, lattice=sdp.Lattice(voxel_size=0.1),
                             execution=sdp.Execution(tile_size=8.0, workers=2))  # its own local cluster
    with LocalCluster(n_workers=1, threads_per_worker=1, dashboard_address=None) as cluster:  # "a remote one"
        c = detect_changes_tiled(ref, cur, lattice=sdp.Lattice(voxel_size=0.1),
                                 execution=sdp.Execution(tile_size=8.0, scheduler=cluster.scheduler_address))
    for r in (b, c):
        np.testing.assert_array_equal(a.current_state, r.current_state)
        np.testing.assert_array_equal(a.reference_state, r.reference_state)
    assert {"bucket", "compare", "regions", "read", "build_reference", "detect"} <= set(b.timings)


def test_tiled_refuses_a_tile_above_the_memory_limit(epochs):
    ref, cur = epochs
    with pytest.raises(sdp.GridTooLargeError, match="memory limit"):
        detect_changes_tiled(ref, cur, lattice=sdp.Lattice(voxel_size=0.01),
                             execution=sdp.Execution(tile_size=30, memory_limit="20MB", scheduler="synchronous"))


@pytest.mark.slow
def test_point_source_slices_equal_the_whole_file(tmp_path, rng):
    xyz = rng.uniform(0, 10, (250_000, 3)) + UTM
    whole = {}
    for name in ("c.laz", "c.npy", "c.ply"):
        path = tmp_path / name
        if name.endswith(".laz"):
            write_las(path, xyz)
        elif name.endswith(".npy"):
            np.save(path, xyz)
        else:
            write_points(path, xyz)
        whole[name] = sdp.read_points(path).xyz
        src = PointSource.open(path)
        assert src.n_rows == len(xyz)
        np.testing.assert_allclose(src.lo, whole[name].min(axis=0), atol=1e-3)
        np.testing.assert_array_equal(src.read(123_456, 123_460), whole[name][123_456:123_460])
        parts = [c for _, c in src.chunks(70_000, start=10, stop=200_010)]
        assert [len(c) for c in parts] == [70_000, 70_000, 60_000]
        np.testing.assert_array_equal(np.concatenate(parts), whole[name][10:200_010])
    (tmp_path / "bad.laz").write_bytes(b"LASF" + b"\0" * 50)
    with pytest.raises(CloudFileError, match="bad.laz"):
        PointSource.open(tmp_path / "bad.laz")
    with pytest.raises(CloudFileError, match="slices"):
        PointSource.open(write_points(tmp_path / "c.npz", xyz))


def test_streamed_las_output_keeps_every_dimension(tmp_path, rng):
    xyz = rng.uniform(0, 10, (50_000, 3)) + UTM
    src = PointSource.open(write_las(tmp_path / "in.laz", xyz))
    out = write_points_streamed(tmp_path / "out.laz", src, lambda s, e: {"change": (np.arange(s, e) % 3 == 0)
                                                                         .astype(np.uint8)}, chunk_size=7_000)
    a, b = laspy.read(str(tmp_path / "in.laz")), laspy.read(str(out))
    np.testing.assert_array_equal(a.X, b.X)
    np.testing.assert_array_equal(a.intensity, b.intensity)
    np.testing.assert_array_equal(b.change, np.arange(len(xyz)) % 3 == 0)
    with pytest.raises(sdp.SDPError, match="overwrite"):
        write_points_streamed(tmp_path / "in.laz", src, lambda s, e: {}, inputs=(tmp_path / "in.laz",))
    assert laspy.read(str(tmp_path / "in.laz")).header.point_count == len(xyz)


def test_streamed_las_output_keeps_the_extended_records(tmp_path, rng):
    # LAS 1.4 may hold its CRS (OGC WKT) in an extended record after the points
    from laspy.vlrs.vlrlist import VLRList

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.global_encoding.wkt = True
    header.evlrs = VLRList([laspy.VLR("LASF_Projection", 2112, "OGC WKT", b'PROJCS["WGS 84 / UTM 17N"]\0')])
    las = laspy.LasData(header)
    las.x, las.y, las.z = (rng.random((3, 5000)) * 10).tolist()
    las.write(str(tmp_path / "in.laz"))
    out = write_points_streamed(tmp_path / "out.laz", PointSource.open(tmp_path / "in.laz"),
                                lambda s, e: {"change": np.zeros(e - s, np.uint8)}, chunk_size=2_000)
    evlrs = laspy.read(str(out)).header.evlrs
    assert [v.record_id for v in evlrs] == [2112] and "UTM 17N" in evlrs[0].string


@pytest.mark.parametrize("intensity", [np.uint16, np.float32])
def test_streamed_ply_output_keeps_its_properties_as_in_memory(tmp_path, rng, intensity):
    # a binary PLY's colour, intensity and other properties, written chunk by chunk as a tiled run
    # writes them, equal what the in-memory writer makes of the whole file
    from plyfile import PlyData, PlyElement

    n = 20_000
    v = np.empty(n, [("x", "f8"), ("y", "f8"), ("z", "f8"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                     ("intensity", intensity), ("quality", "f4"), ("change", "u1")])
    for c in ("x", "y", "z"):
        v[c] = rng.uniform(0, 10, n)
    for c in ("red", "green", "blue", "change"):
        v[c] = rng.integers(0, 256, n)
    # a float intensity beyond [0, 1] in a later chunk only: the whole file's values decide, as in memory
    v["intensity"] = rng.integers(0, 1000, n) if intensity == np.uint16 else np.r_[rng.random(n - 10), np.full(10, 7.5)]
    v["quality"] = rng.random(n)
    PlyData([PlyElement.describe(v, "vertex")]).write(str(tmp_path / "in.ply"))
    new = {"change": lambda s, e: np.arange(s, e) % 3 == 0}
    streamed = write_points_streamed(tmp_path / "streamed.laz", PointSource.open(tmp_path / "in.ply"),
                                     lambda s, e: {k: f(s, e) for k, f in new.items()}, chunk_size=3_000)
    cloud = sdp.read_points(tmp_path / "in.ply")
    whole = write_points(tmp_path / "whole.laz", cloud.xyz, {**cloud.fields, "change": new["change"](0, n)})
    a, b = laspy.read(str(streamed)), laspy.read(str(whole))
    assert a.point_format.id == b.point_format.id == 2
    assert list(a.point_format.dimension_names) == list(b.point_format.dimension_names)
    for name in b.point_format.dimension_names:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    np.testing.assert_array_equal(a.red, v["red"].astype(np.uint16) * 257)
    assert ("input_intensity" in a.point_format.extra_dimension_names) == (intensity == np.float32)


def run(*args):
    return subprocess.run([sys.executable, "-m", "sdp.cli", *map(str, args)], capture_output=True, text=True)


@pytest.mark.slow
def test_cli_switches_to_tiles_by_itself(tmp_path, rng):
    ref = street(rng, [([2, 2, 0], [4, 5, 1.5]), ([14, 9.5, 0], [16, 10.5, 2])], mast=True)
    cur = street(rng, [([2, 2, 0], [4, 5, 1.5]), ([9.5, 15.5, 0], [10.8, 16.8, 1.2]), ([25, 3, 0], [26, 4, 1])],
                 mast=True)
    a, b = write_las(tmp_path / "a.laz", ref), write_las(tmp_path / "b.laz", cur)
    small = run("change", a, b, "-o", tmp_path / "small.laz", "--voxel-size", "0.1", "--both", "--json")
    big = run("change", a, b, "-o", tmp_path / "big.laz", "--voxel-size", "0.1", "--both", "--memory-limit", "1GB",
              "--workers", "1", "--tile-size", "6")
    assert small.returncode == 0 and big.returncode == 0, big.stderr
    assert "comparing in tiles" in big.stderr and "tiles of 6.4" in big.stdout
    for suffix in ("", "_disappeared"):
        x, y = laspy.read(str(tmp_path / f"small{suffix}.laz")), laspy.read(str(tmp_path / f"big{suffix}.laz"))
        np.testing.assert_array_equal(x.change, y.change)
        np.testing.assert_array_equal(x.region >= 0, y.region >= 0)
        np.testing.assert_array_equal(x.intensity, y.intensity)
    assert json.loads(small.stdout)["current"]["appeared"] == laspy.read(str(tmp_path / "big.laz")).change.sum()
    bad = run("change", a, b, "-o", tmp_path / "x.laz", "--tiled", "--align", "gicp")
    assert bad.returncode == 2 and "--align is not available with --tiled" in bad.stderr


def test_a_memory_limit_the_job_cannot_meet_is_refused_at_once_with_the_smallest_that_works(tmp_path, epochs):
    import re

    ref, cur = epochs
    work = tmp_path / "work"
    work.mkdir()
    with pytest.raises(sdp.GridTooLargeError, match=r"can't hold this job.*give --memory-limit \d+MB or more") as err:
        detect_changes_tiled(ref, cur, lattice=sdp.Lattice(voxel_size=0.1),
                             execution=sdp.Execution(memory_limit="1MB", workers=2, workdir=work))
    assert list(work.iterdir()) == []  # no bucket, no folder left behind
    smallest = int(re.search(r"--memory-limit (\d+)MB", str(err.value)).group(1))
    assert 700 < smallest < 1100  # the command and two worker processes, before any data
    with pytest.raises(sdp.GridTooLargeError, match=f"give --memory-limit {smallest}MB"):
        detect_changes_tiled(ref, cur, lattice=sdp.Lattice(voxel_size=0.1),
                             execution=sdp.Execution(memory_limit=f"{smallest - 1}MB", workers=2, workdir=work))
    # in this process (one task at a time): the command alone, and the smallest tiles fit
    one = detect_changes_tiled(ref, cur, lattice=sdp.Lattice(voxel_size=0.1),
                               execution=sdp.Execution(memory_limit="600MB", scheduler="synchronous", workdir=work))
    assert one.n_tiles > 4 and one.tile_size < 15  # tiles sized from the share
    assert one.summary()["current"]["appeared"] > 4000
    assert list(work.iterdir()) == []


def test_a_job_that_came_to_tiles_is_refused_with_the_smallest_limit_that_runs(tmp_path, rng, monkeypatch):
    # 10,000 points each at 200MB went to tiles, whose smallest need 1007MB, and were refused with
    # that (after the notice of tiles), though 250MB ran in memory
    import math

    from sdp.scale._budget import untiled_point_bytes

    a, b = tmp_path / "a.npy", tmp_path / "b.npy"
    for path in (a, b):
        np.save(path, rng.uniform(0, 10, (10_000, 3)) * [1, 1, 0.01])
    monkeypatch.setattr(sdp.scale._session, "_connect", lambda *_: pytest.fail("a cluster for a refused job"))
    in_memory = math.ceil(untiled_point_bytes(20_000) / 2**20)
    said = []
    with pytest.raises(sdp.GridTooLargeError, match=f"can't hold this job.*in memory it would need .*; give "
                                                    f"--memory-limit {in_memory}MB or more$"):
        sdp.compare_files(a, b, output=tmp_path / "c.laz", lattice=sdp.Lattice(voxel_size=0.05),
                          execution=sdp.Execution(memory_limit="200MB", workers=2, notify=said.append))
    assert said == []  # the tiles were not taken: no word of them
    assert not sdp.plan_change(a, b, lattice=sdp.Lattice(voxel_size=0.05),
                               execution=sdp.Execution(memory_limit=f"{in_memory}MB")).tiled
    assert not (tmp_path / "c.laz").exists()


@pytest.mark.slow
def test_cli_refuses_tiles_under_a_tiny_memory_limit_before_any_worker(tmp_path, epochs, monkeypatch, capsys):
    import sdp.scale._tiles
    from sdp.cli._main import main

    cur = epochs[1][np.isfinite(epochs[1]).all(axis=1)]
    a, b = write_las(tmp_path / "a.laz", epochs[0]), write_las(tmp_path / "b.laz", cur)
    work = tmp_path / "work"
    work.mkdir()
    args = ["change", a, b, "-o", tmp_path / "c.laz", "--tiled", "--memory-limit", "1MB", "--workdir", work]
    r = run(*args)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "give --memory-limit" in r.stderr, r.stderr
    assert list(work.iterdir()) == [] and not (tmp_path / "c.laz").exists()

    # refused before a Dask cluster starts (it used to start one and run minutes of worker errors)
    def no_cluster(*_, **__):
        raise AssertionError("a Dask cluster was started for a job its memory limit refuses")

    monkeypatch.setattr(sdp.scale._session, "_connect", no_cluster)
    capsys.readouterr()
    assert main([str(x) for x in args]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "give --memory-limit" in err, err
    assert list(work.iterdir()) == [] and not (tmp_path / "c.laz").exists()


@pytest.mark.parametrize("workers, separate", [(1, True), (2, True), (7, True), (2, False)])
def test_the_shares_of_a_job_add_up_to_its_limit(workers, separate):
    from sdp.scale._budget import WORKER_BYTES, JobBudget

    for limit in (2**30, 2 * 2**30, 64 * 2**30):
        plan = JobBudget(limit, workers, separate=separate)
        assert plan.client + workers * plan.worker <= limit  # the command and every worker, within the limit
        assert plan.task == plan.worker - (WORKER_BYTES if separate else 0)
        for task in (0, 10 * 2**20, 3 * 2**30):
            smallest = JobBudget(plan.smallest(task), workers, separate=separate)
            assert smallest.task >= task - workers and JobBudget(plan.smallest(task) - 2 * workers, workers,
                                                                 separate=separate).task < task


def test_face_nodes_are_grouped_whatever_their_range():
    from sdp.change._regions import _node_key

    rng = np.random.default_rng(5)
    for span in (1_000, 2**40):  # packed into one int64, or compared as bytes
        nodes = rng.integers(-span, span, (20_000, 3))
        nodes[10_000:] = nodes[rng.permutation(10_000)]
        key = np.sort(_node_key(nodes))
        assert np.count_nonzero(key[1:] == key[:-1]) == len(nodes) - len(np.unique(nodes, axis=0))


def test_cells_beyond_their_keys_reach_are_refused_before_any_tile_with_advice_for_tiles():
    """The combined decision and the distances place their cells from the clouds' corner, so that
    every tile's are memory's; two patches 100 km apart at σ = 2 cm are more than 2**21 cells
    apart: refused before a tile is read, saying what works in tiles (not "compare in tiles")."""
    from sdp.scale._tiles import distances_tiled

    rng = np.random.default_rng(0)
    patch = np.c_[rng.random((2000, 2)), np.zeros(2000)]
    ref = np.concatenate([patch, patch + [1e5, 0, 0]])
    cur = ref + 0.001 * rng.standard_normal(ref.shape)
    execution = sdp.Execution(scheduler="synchronous", tile_size=10.0)
    with pytest.raises(sdp.InvalidOptionError, match="use decision='point'"):
        detect_changes_tiled(ref, cur, lattice=sdp.Lattice(voxel_size=0.01), decision="combined", execution=execution)
    with pytest.raises(sdp.InvalidOptionError, match="larger projection scale"):
        distances_tiled(ref, cur, cylinder=sdp.Cylinder(projection_scale=0.05, normal_scale=0.1), execution=execution)
    assert detect_changes_tiled(ref, cur, lattice=sdp.Lattice(voxel_size=0.01), execution=execution).n_tiles >= 2
