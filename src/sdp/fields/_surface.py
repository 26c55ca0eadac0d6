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

__all__ = ["Mesh", "extract_surface", "surface_nodes"]

_CHUNK = 8  # blocks per chunk edge: marching cubes runs on (8·8 + 1)³ nodes at a time


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
    # merge the copies of vertices on chunk seams (same edge, same interpolation)
    q = np.round(v * 2**16).astype(np.int64)
    _, first, inverse = np.unique(q, axis=0, return_index=True, return_inverse=True)
    f = inverse.ravel()[f]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    return v[first], f[keep].astype(np.int64)
