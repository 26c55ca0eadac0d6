import numpy as np
import pytest

import sdp
from sdp import DensityField


def test_ball_surface_has_the_analytic_area(rng):
    # a ball of radius 1 sampled uniformly: G has a plateau inside and falls to half of it
    # at the boundary, where the level set G = plateau/2 must lie
    n = 400_000
    v = rng.normal(size=(n, 3))
    pts = v / np.linalg.norm(v, axis=1)[:, None] * rng.random(n)[:, None] ** (1 / 3)
    f = DensityField.from_points(pts, voxel_size=0.025)
    plateau = np.median(f.density(pts[np.linalg.norm(pts, axis=1) < 0.5]))
    mesh = f.mesh(level=f.h - plateau / 2)
    assert mesh.area == pytest.approx(4 * np.pi, rel=0.02)
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert abs(r.mean() - 1) < 0.01
    assert mesh.faces.max() < len(mesh.vertices)


def test_mesh_spanning_several_chunks_is_merged(rng):
    # a 6 m slab crosses many 64-node chunks: seams must share vertices (closed surface)
    pts = np.c_[rng.uniform(0, 6, 200_000), rng.uniform(0, 1, 200_000), rng.normal(0, 0.01, 200_000)]
    mesh = DensityField.from_points(pts, voxel_size=0.02).mesh()
    edges = np.sort(np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]], mesh.faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).mean() > 0.999  # every edge shared by two triangles: watertight
    assert 12 < mesh.area < 20  # both faces of the 6 m x 1 m slab, widened by the kernel


def test_level_outside_range_raises(rng):
    f = DensityField.from_points(rng.random((200, 3)), voxel_size=0.05)
    with pytest.raises(sdp.SurfaceError, match="outside the field's range"):
        f.mesh(level=-1e6)
    with pytest.raises(sdp.SurfaceError, match="outside"):
        f.mesh(level=f.h + 1)
    lone = DensityField.from_points([[0, 0, 0]], voxel_size=0.05)  # G <= 1 < h: no cluster volume
    with pytest.raises(sdp.SurfaceError):
        lone.mesh()


def test_faces_are_wound_with_their_normals_out_of_the_volume(rng):
    """Right-hand winding points out of F < 0: a ball's mesh has a positive signed volume, and a
    step along each face's normal leaves the volume."""
    p = rng.normal(size=(20_000, 3))
    p /= np.linalg.norm(p, axis=1)[:, None]
    f = DensityField.from_points(p, voxel_size=0.05)
    m = f.mesh()
    a, b, c = (m.vertices[m.faces[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1)[:, None]
    centre = (a + b + c) / 3
    assert np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6 > 0  # the shell's volume, outer minus inner
    assert (f.field(centre + 0.01 * n) > 0).mean() > 0.99


def _sphere_field(voxel=0.05):
    p = np.random.default_rng(1).normal(size=(20_000, 3))
    return DensityField.from_points(p / np.linalg.norm(p, axis=1)[:, None], voxel_size=voxel)


def test_surface_vertices_bound_the_mesh():
    # the budget of sdp mesh counts the edges the level crosses, before marching cubes
    from sdp.fields._surface import surface_vertices

    f = _sphere_field()
    n = len(f.mesh().vertices)
    # the per-vertex bytes have a margin
    assert 0.9 * n <= surface_vertices(f.blocks.values[:f.n_blocks], f.h) <= 1.3 * n


def test_mesh_beyond_the_memory_limit_is_refused_before_writing(tmp_path):
    # sdp mesh and sdp bool to a mesh peaked at 3-4 times --memory-limit, without a word
    from sdp.cli._files import combine_files, mesh_file
    from sdp.fields._surface import surface_bytes
    from sdp.scale._budget import PROCESS_BYTES
    from sdp.scale._store import FieldStore

    f = _sphere_field()
    f.save(tmp_path / "f.sdpf")
    need = PROCESS_BYTES + f.nbytes + surface_bytes(f)
    smallest = f"{-(-need // 2**20)}MB"
    with pytest.raises(sdp.GridTooLargeError, match=rf"f.sdpf: its surface would need about .*, above the memory "
                       rf"limit of 230 MB: give --memory-limit {smallest} or more"):
        mesh_file(tmp_path / "f.sdpf", output=tmp_path / "m.ply", memory_limit="230MB")
    with pytest.raises(sdp.GridTooLargeError, match="the surface of the union would need"):
        combine_files("union", tmp_path / "f.sdpf", tmp_path / "f.sdpf", output=tmp_path / "u.ply",
                      memory_limit="230MB")
    FieldStore.from_field(f, tmp_path / "s.zarr", tile_blocks=3)
    with pytest.raises(sdp.GridTooLargeError, match=r"s.zarr: its surface, tile by tile, would need .* give "
                       r"--memory-limit \d+MB or more"):
        mesh_file(tmp_path / "s.zarr", output=tmp_path / "z.ply", memory_limit="230MB")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f.sdpf", "s.zarr"]
    assert len(mesh_file(tmp_path / "f.sdpf", output=tmp_path / "m.ply", memory_limit=smallest).faces)
