"""Out-of-core fields: FieldStore (Zarr, tile by tile) against the in-memory DensityField."""

import numpy as np
import pytest
from test_tiles import street

import sdp
from sdp.scale._store import FieldStore
from sdp.scale._tiles import build_field_tiled, detect_changes_tiled


@pytest.fixture
def clouds(rng):
    ref = street(rng, [([2, 2, 0], [4, 5, 1.5]), ([14, 9.5, 0], [16, 10.5, 2])], n=60_000)
    cur = street(rng, [([2, 2, 0], [4, 5, 1.5]), ([9.5, 15.5, 0], [10.8, 16.8, 1.2])], n=60_000)
    return ref, cur


@pytest.mark.slow
def test_store_round_trip_queries_and_mesh(tmp_path, clouds):
    ref, _ = clouds
    f = sdp.DensityField.from_points(ref, voxel_size=0.1)
    store = FieldStore.from_field(f, tmp_path / "f.zarr", tile_blocks=8)  # 6.4 m tiles
    assert len(store.tiles) >= 20 and store.n_blocks == f.n_blocks and store.n_points == len(ref)
    back = FieldStore.open(tmp_path / "f.zarr").read()
    np.testing.assert_array_equal(back.node_values(f.global_keys), f.node_values(f.global_keys))
    q = np.concatenate([ref[::50], ref[::97] + [0.03, -0.04, 0.05]])
    # equal up to the rounding of (p − origin) / l: each tile's grid has its own origin
    np.testing.assert_allclose(store.density(q), f.density(q), rtol=1e-8)
    np.testing.assert_allclose(store.field(q[:5]), f.field(q[:5]), rtol=1e-8)
    a, b = store.mesh(), f.mesh()
    assert len(a.vertices) == len(b.vertices) and len(a.faces) == len(b.faces)
    assert a.area == pytest.approx(b.area, rel=1e-9)


@pytest.mark.slow  # the quick tier keeps lighter tests of the same module
def test_tiled_build_equals_the_whole_field(tmp_path, clouds):
    ref, _ = clouds
    f = sdp.DensityField.from_points(ref, voxel_size=0.1)
    store = build_field_tiled(ref, tmp_path / "t.zarr", lattice=sdp.Lattice(voxel_size=0.1),
                              execution=sdp.Execution(tile_size=5.0, scheduler="synchronous"))
    assert len(store.tiles) >= 20 and store.n_points == len(ref)
    g = store.read()
    assert g.n_blocks == f.n_blocks
    np.testing.assert_allclose(g.node_values(f.global_keys), f.node_values(f.global_keys), rtol=1e-5,
                               atol=1e-5 * float(f.blocks.values.max()))


@pytest.mark.slow
def test_out_of_core_boolean_equals_in_memory(tmp_path, clouds):
    ref, cur = clouds
    fa, fb = (sdp.DensityField.from_points(c, voxel_size=0.1) for c in (ref, cur))
    sa = FieldStore.from_field(fa, tmp_path / "a.zarr", tile_blocks=8)
    sb = FieldStore.from_field(fb, tmp_path / "b.zarr", tile_blocks=5)  # tiles need not match
    for op in ("union", "intersection", "difference"):
        want = getattr(sdp, op)(fa, fb)
        got = sa.combine(sb, op, tmp_path / f"{op}.zarr").read()
        assert got.h == want.h
        np.testing.assert_array_equal(got.node_values(want.global_keys), want.node_values(want.global_keys))
    with pytest.raises(sdp.SDPError, match="overwrite"):
        sa.combine(sb, "union", tmp_path / "a.zarr")


@pytest.mark.slow
def test_changes_against_a_stored_reference(tmp_path, clouds):
    ref, cur = clouds
    want = sdp.detect_changes(ref, cur, lattice=sdp.Lattice(voxel_size=0.1))
    store = FieldStore.from_field(want.reference_field, tmp_path / "ref.zarr", tile_blocks=8)
    got = detect_changes_tiled(store, cur, execution=sdp.Execution(scheduler="synchronous"))
    assert got.n_tiles >= 20 and want.appeared.sum() > 1000
    np.testing.assert_array_equal(got.appeared, want.appeared)
    assert not got.disappeared.any() and got.disappeared.size == len(ref)
    # a store of larger tiles than the run's memory lets it take, far from the origin: the run reads
    # the stored blocks of its own tiles (it read the store's tile of the same key: nothing there)
    far = np.array([634_000.0, 4_831_000.0, 80.0])
    big = FieldStore.from_field(sdp.DensityField.from_points(ref + far, voxel_size=0.1), tmp_path / "big.zarr",
                                tile_blocks=64)
    cut = detect_changes_tiled(big, cur + far, execution=sdp.Execution(scheduler="synchronous", tile_points=20_000))
    assert cut.tile_size < 64 * 8 * 0.1
    np.testing.assert_array_equal(cut.current_state, want.current_state)


def test_store_errors(tmp_path):
    (tmp_path / "plain").mkdir()
    (tmp_path / "plain" / "notes.txt").write_text("keep me")
    with pytest.raises(sdp.FieldFileError, match="not a readable sdp field store"):
        FieldStore.open(tmp_path / "nothing.zarr")
    with pytest.raises(sdp.FieldFileError, match="not a Zarr store"):
        FieldStore.create(tmp_path / "plain", voxel_size=0.1, sigma=0.2, truncate=3, h=2.8)
    assert (tmp_path / "plain" / "notes.txt").read_text() == "keep me"
    import zarr

    zarr.open_group(str(tmp_path / "other.zarr"), mode="w").create_array("a", shape=(3,), dtype="f4")
    with pytest.raises(sdp.FieldFileError, match="a Zarr store sdp did not write: neither a field store"):
        FieldStore.open(tmp_path / "other.zarr")
    zarr.open_group(str(tmp_path / "series.zarr"), mode="w").attrs.update({"format": "sdp-series"})
    with pytest.raises(sdp.FieldFileError, match="a series archive .sdp series., not a density field store"):
        FieldStore.open(tmp_path / "series.zarr")
    for other, says in (("series.zarr", "is a series archive"), ("other.zarr", "is a Zarr store that is not a field")):
        with pytest.raises(sdp.FieldFileError, match=says):  # replaced before: a whole series lost
            FieldStore.create(tmp_path / other, voxel_size=0.1, sigma=0.2, truncate=3, h=2.8)
    assert (tmp_path / "series.zarr" / "zarr.json").is_file() and (tmp_path / "other.zarr" / "a").exists()
    from sdp.cli import combine_files

    FieldStore.create(tmp_path / "s.zarr", voxel_size=0.1, sigma=0.2, truncate=3, h=2.8).commit()
    np.save(tmp_path / "c.npy", np.random.default_rng(0).random((100, 3)))
    with pytest.raises(sdp.SDPError, match="combines with another one into a .zarr output"):
        combine_files("union", tmp_path / "s.zarr", tmp_path / "c.npy", output=tmp_path / "u.sdpf")
    assert not (tmp_path / "u.sdpf").exists()


@pytest.mark.slow
def test_cli_field_store(tmp_path, clouds):
    from test_tiles import run, write_las

    ref, cur = clouds
    a, b = write_las(tmp_path / "a.laz", ref), write_las(tmp_path / "b.laz", cur)
    built = run("build", a, "-o", tmp_path / "a.zarr", "--voxel-size", "0.1", "--tile-size", "6", "--workers", "1")
    assert built.returncode == 0, built.stderr
    assert run("mesh", tmp_path / "a.zarr", "-o", tmp_path / "a.ply").returncode == 0
    stored = run("change", tmp_path / "a.zarr", b, "-o", tmp_path / "s.laz", "--json")
    direct = run("change", a, b, "-o", tmp_path / "d.laz", "--voxel-size", "0.1", "--json")
    assert stored.returncode == 0 and direct.returncode == 0, stored.stderr
    import json

    s, d = json.loads(stored.stdout), json.loads(direct.stdout)
    assert s["current"]["appeared"] == d["current"]["appeared"] > 1000 and s["tiles"] >= 12
    # no reference points: what disappeared is not measured, not "none"
    assert s["reference"]["disappeared"] is None and s["coverage"]["disappeared"] == "not measured"
    assert "disappeared not measured" in run("change", tmp_path / "a.zarr", b, "-o", tmp_path / "t.laz").stdout
    both = run("change", tmp_path / "a.zarr", b, "-o", tmp_path / "x.laz", "--both")
    assert both.returncode == 2 and "reference points" in both.stderr
    # what the tiles can't do is refused before any work, as with --tiled, not ignored
    for extra, says in ((["--report", tmp_path / "r.html"], "--png/--html/--report is not available with a .zarr"),
                        (["--align", "density"], "--align is not available"),
                        (["--sensor-origin", "0,0,10"], "--sensor-origin is not available"),
                        (["--voxel-size", "0.2"], "the field store's"),
                        (["-o", tmp_path / "x.ply"], "give -o OUT.laz")):
        out = [] if "-o" in extra else ["-o", tmp_path / "x.laz"]
        p = run("change", tmp_path / "a.zarr", b, *out, *extra)
        assert p.returncode == 2 and says in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert not any(tmp_path.glob("x.*")) and not (tmp_path / "r.html").exists()


def _boundary_edges(mesh) -> int:
    t = mesh.faces
    edges = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    return int((np.unique(edges, axis=0, return_counts=True)[1] == 1).sum())


def test_store_mesh_closes_its_seams(tmp_path):
    # 3-block tiles left 14 seam vertices unmerged (copies 1e-16 m apart rounded apart): an open mesh
    rng = np.random.default_rng(1)
    p = rng.normal(size=(20_000, 3))
    f = sdp.DensityField.from_points(p / np.linalg.norm(p, axis=1)[:, None], voxel_size=0.05)
    want = f.mesh()
    assert _boundary_edges(want) == 0
    got = FieldStore.from_field(f, tmp_path / "s.zarr", tile_blocks=3).mesh()
    assert _boundary_edges(got) == 0
    assert (len(got.vertices), len(got.faces)) == (len(want.vertices), len(want.faces))
    assert got.area == pytest.approx(want.area, rel=1e-8)


def _small_field():
    return sdp.DensityField.from_points(np.random.default_rng(0).random((2000, 3)) * 3, voxel_size=0.1)


def test_an_unfinished_store_is_refused(tmp_path):
    # a store left by kill -9 mid-build opened, meshed and answered G = 0 where its tiles were missing
    store = FieldStore.create(tmp_path / "f.zarr", voxel_size=0.1, sigma=0.2, truncate=3, h=2.8)
    store.write_tile((0, 0), _small_field())
    assert not (tmp_path / "f.zarr").exists()  # written under a temporary name beside it
    with pytest.raises(sdp.FieldFileError, match="no field store yet: a build of it is under way or stopped"):
        FieldStore.open(tmp_path / "f.zarr")
    with pytest.raises(sdp.FieldFileError, match="never completed") as err:
        FieldStore.open(store.path)
    assert len(str(err.value).splitlines()) == 1
    store.commit()
    assert FieldStore.open(tmp_path / "f.zarr").n_blocks > 0 and not any(tmp_path.glob(".f.zarr.*"))
    # what a dead build left is removed by the next build of the same name
    import subprocess
    import sys

    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    left = tmp_path / f".f.zarr.tmp-{int(gone.stdout)}"
    left.mkdir()
    FieldStore.from_field(_small_field(), tmp_path / "f.zarr")
    assert not left.exists()


def test_a_failed_rebuild_keeps_the_store(tmp_path, monkeypatch):
    # a rebuild over a store removed it first: stopped or failed, it left none
    field = _small_field()
    FieldStore.from_field(field, tmp_path / "f.zarr", tile_blocks=1)

    def fail(self, key, f):
        raise sdp.SDPError("disk full")

    monkeypatch.setattr(FieldStore, "write_tile", fail)
    with pytest.raises(sdp.SDPError, match="disk full"):
        FieldStore.from_field(field, tmp_path / "f.zarr", tile_blocks=2)
    with pytest.raises(sdp.SDPError, match="disk full"):
        build_field_tiled(field.global_keys * 0.8 + 0.05, tmp_path / "f.zarr", lattice=sdp.Lattice(voxel_size=0.1),
                          execution=sdp.Execution(scheduler="synchronous", workdir=tmp_path))
    back = FieldStore.open(tmp_path / "f.zarr")
    assert back.tile_blocks == 1 and back.n_blocks == field.n_blocks and back.n_points == 2000
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.zarr"]


def test_a_store_written_before_the_complete_mark_opens(tmp_path):
    import zarr

    FieldStore.from_field(_small_field(), tmp_path / "f.zarr")
    group = zarr.open_group(str(tmp_path / "f.zarr"), mode="r+")
    del group.attrs["complete"]  # as sdp wrote stores before the mark
    assert FieldStore.open(tmp_path / "f.zarr").n_points == 2000


def test_store_small_faults(tmp_path):
    field = _small_field()
    store = FieldStore.from_field(field, tmp_path / "f.zarr", tile_blocks=2)
    assert store.read().n_points == 2000  # was 0 for the whole store
    assert store.read([0, 0], [2, 2]).n_points == 0  # a part has no count of its own
    with pytest.raises(sdp.InvalidOptionError, match="got 'xor'"):
        store.combine(store, "xor", tmp_path / "x.zarr")
    field.save(tmp_path / "f.sdpf")
    with pytest.raises(sdp.FieldFileError, match="a file, not a field store.*DensityField.load"):
        FieldStore.open(tmp_path / "f.sdpf")  # said FileExistsError: File exists


def test_cli_refuses_or_says_what_a_store_or_field_ignores(tmp_path, capsys):
    from sdp.cli import main

    def at(name):
        return str(tmp_path / name)

    field = _small_field()
    FieldStore.from_field(field, tmp_path / "a.zarr")
    field.save(tmp_path / "a.sdpf")
    for args, says in ((["bool", "union", at("a.zarr"), at("a.zarr"), "-o", at("u.zarr"), "-k", "20"],
                        "a field sets the lattice"),  # was accepted, and ignored
                       (["render", at("a.zarr"), "--png", at("r.png")], "a field store (.zarr) is not rendered"),
                       (["render", at("a.sdpf"), "--png", at("r.png"), "--field", "x"], "give no --field")):
        assert main(args) == 2
        err = capsys.readouterr().err
        assert says in err and len(err.strip().splitlines()) == 1, err
    assert not any(tmp_path.glob("u.zarr")) and not any(tmp_path.glob("r.png"))
    np.save(tmp_path / "c.npy", np.random.default_rng(0).random((500, 3)))
    assert main(["build", str(tmp_path / "c.npy"), "-o", str(tmp_path / "c.sdpf"), "--voxel-size", "0.1",
                 "--tile-size", "3", "--workers", "3"]) == 0
    assert "in memory: --tile-size, --workers used by tiles only (a .zarr output)" in capsys.readouterr().err
