"""Iso-surfaces of a field by Lewiner's marching cubes, chunk by chunk over the sparse grid.

References
----------
.. [1] T. Lewiner, H. Lopes, A. W. Vieira, G. Tavares, "Efficient implementation of marching
   cubes' cases with topological guarantees", Journal of Graphics Tools 8(2), 2003.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..errors import SurfaceError
from ._lattice import BLOCK

__all__ = ["Mesh", "extract_surface", "surface_nodes", "surface_vertices", "surface_bytes", "check_surface"]

_CHUNK = 8  # blocks per chunk edge: marching cubes runs on (8·8 + 1)³ nodes at a time

#: Bytes a mesh takes per vertex at the peak of its extraction and writing: the chunks' vertices
#: and faces (about two per vertex), their concatenation, the merge of the seams' copies (keys,
#: sort, inverse), the mesh returned and the PLY writer's records (measured: `sdp mesh` of 1.28 M
#: vertices from a 1 M-point field peaked at 793 MiB from an .sdpf, 855 MiB from a .zarr of 529
#: tiles, where this budget gives 945 and about 910 MB).
BYTES_PER_SURFACE_VERTEX = 500

#: Bytes of one chunk's marching cubes: its dense copy and scikit-image's work arrays on it.
CHUNK_BYTES = 8 * (_CHUNK * BLOCK + 1) ** 3 * 4


class Mesh(NamedTuple):
    """A triangle mesh: ``vertices`` (V, 3) float64 world coordinates, ``faces`` (T, 3) int64."""

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def area(self) -> float:
        """Total surface area (world units squared)."""
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        return float(0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())


def extract_surface(field, *, level: float = 0.0) -> Mesh:
    """The surface F = ``level`` of a field (F = 0: the boundary of the cluster volume).

    Runs ``skimage.measure.marching_cubes(method="lewiner")`` on chunks of 64³ nodes that
    hold allocated blocks (plus a one-node overlap), so memory follows the occupied part of
    the grid; vertices shared by two chunks are merged. Normals point out of the region
    F < level.

    Raises
    ------
    SurfaceError
        ``level`` is outside the field's range, or no surface crosses it.
    """
    nodes, faces = surface_nodes(field, level=level)
    return Mesh(field.grid.to_world(nodes), faces)


def surface_vertices(values: np.ndarray, g_level: float) -> int:
    """About how many vertices the surface G = ``g_level`` has in blocks of node values ``values``
    (m, 512): marching cubes puts one on each edge the level crosses. Counted on the edges inside
    the blocks, a batch at a time, and scaled by 8/7 for those between blocks (within 10 % of the
    merged mesh's count on smooth surfaces)."""
    n = 0
    for s in range(0, len(values), 4096):
        inside = (values[s:s + 4096] > g_level).reshape(-1, BLOCK, BLOCK, BLOCK)
        n += sum(int(np.count_nonzero(np.diff(inside, axis=a))) for a in (1, 2, 3))
    return n * BLOCK // (BLOCK - 1)


def surface_bytes(field, *, level: float = 0.0) -> int:
    """Bytes the surface F = ``level`` of ``field`` takes to extract and write, beyond the field
    itself (:data:`BYTES_PER_SURFACE_VERTEX` per vertex of :func:`surface_vertices`, one chunk's
    work): what ``sdp mesh`` and ``sdp bool`` check against the memory limit before it."""
    n = field.n_blocks
    return surface_vertices(field.blocks.values[:n], field.h - level) * BYTES_PER_SURFACE_VERTEX + CHUNK_BYTES


def check_surface(need: float, cap: int, what: str) -> None:
    """Refuse a mesh whose extraction would need ``need`` bytes in all (the process, the field
    and :func:`surface_bytes`) under the memory limit ``cap``, in one line that gives the
    smallest limit that works."""
    from .._core._memory import format_bytes
    from ..errors import GridTooLargeError
    from ..scale._budget import megabytes

    if need > cap:
        raise GridTooLargeError(f"{what} would need about {format_bytes(need)}, above the memory limit of "
                                f"{format_bytes(cap)}: give --memory-limit {megabytes(need)} or more "
                                "($SDP_MEMORY_LIMIT), or use a larger voxel size")


def merge_seams(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the first of each set of equal vertices of ``v`` (V, 3) (node units: copies on
    chunk and tile seams, same edge, same interpolation) and each vertex's set, as
    ``np.unique(..., axis=0, return_index=True, return_inverse=True)`` gives them, sets in
    lexicographic order; by a lexsort, which holds less than np.unique's rows as records."""
    q = np.round(v * 2**16).astype(np.int64)
    order = np.lexsort(q.T[::-1])
    s = q[order]
    del q
    new = np.empty(len(s), bool)
    new[:1] = True
    np.any(s[1:] != s[:-1], axis=1, out=new[1:])
    del s
    inverse = np.empty(len(order), np.int64)
    inverse[order] = np.cumsum(new) - 1
    return order[new], inverse


def surface_nodes(field, *, level: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`extract_surface`'s vertices in node units of ``field``'s grid (float64, (V, 3)) and
    its faces (T, 3): what a tiled mesh merges on the global lattice (:meth:`sdp.FieldStore.mesh`).

    Marching cubes runs on chunks of ``_CHUNK`` blocks from the grid's origin: a vertex's float32
    coordinates depend on its place in its chunk, so grids whose origins are multiples of
    ``_CHUNK`` blocks apart give the same edge bitwise the same vertex.
    """
    from skimage.measure import marching_cubes

    from .._core._validate import finite

    if not all(hasattr(field, a) for a in ("blocks", "h", "n_blocks")):  # a DensityField (which imports this module)
        raise SurfaceError(f"extract_surface takes a DensityField, got {type(field).__name__}")
    level = finite("level", level)
    if field.n_blocks == 0:
        raise SurfaceError("the field is empty: there is no surface")
    g_level = field.h - level
    values = field.blocks.values
    gmin, gmax = min(0.0, float(values.min())), max(0.0, float(values.max()))
    if not gmin < g_level < gmax:
        raise SurfaceError(f"level {level:g} is outside the field's range F ∈ [{field.h - gmax:.4g}, "
                           f"{field.h - gmin:.4g}]: no surface; choose a level inside it")
    chunks = np.unique(np.floor_divide(field.blocks.keys, _CHUNK), axis=0)
    # a cell on a chunk's low face belongs to the neighbouring chunk: add those neighbours
    shifts = np.array([[i, j, k] for i in (0, -1) for j in (0, -1) for k in (0, -1)])
    chunks = np.unique((chunks[:, None, :] + shifts[None]).reshape(-1, 3), axis=0)
    n = _CHUNK * BLOCK
    verts, faces, offset = [], [], 0
    for c in chunks:
        lo = c * n
        vol = field.blocks.box(lo, np.full(3, n + 1, np.int64))
        if not (vol.min() < g_level < vol.max()):
            continue
        v, f, _, _ = marching_cubes(vol, level=g_level, method="lewiner")
        verts.append(v.astype(np.float64) + lo)
        # scikit-image winds its faces towards the higher values (G, inside the volume): reversed,
        # their normals point out of F < level, as STL requires and viewers and volumes expect
        faces.append(f[:, ::-1] + offset)
        offset += len(v)
    if not verts:
        raise SurfaceError(f"no surface crosses level {level:g}")
    v, f = np.concatenate(verts), np.concatenate(faces)
    verts.clear()
    faces.clear()  # the merge holds one copy of the chunks' surface, not two
    first, inverse = merge_seams(v)  # the copies of vertices on chunk seams
    f = inverse[f]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return v[first], f[keep].astype(np.int64)
