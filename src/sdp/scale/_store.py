"""Density fields on disk (Zarr), read and written tile by tile: fields larger than memory.

A :class:`FieldStore` holds the same block-sparse field as :class:`sdp.DensityField`, cut into
square columns of ``tile_blocks`` × ``tile_blocks`` blocks (all z). Each tile's block keys
and node values are chunked, compressed Zarr arrays, so a tile is read or written without
touching the others and several processes can write different tiles at once (the tiled build
of :func:`sdp.build_field_tiled` does). Queries, Boolean operations and meshing run tile by
tile on fields read with a one-block margin, so they give the in-memory field's numbers
(tested) with memory bounded by a tile: node values are exact for queries; a mesh keeps each
triangle in the tile that owns its cell and welds the seams; Boolean operations run tile by
tile between any two tilings; change detection against a stored reference gives the appeared
points only (there are no reference points). Values equal the in-memory field's up to the
rounding of each tile grid's origin (tested to a relative 1e-8).

Layout (a Zarr v3 group, a folder conventionally named ``*.zarr``)::

    attrs                  format "sdp-field-store", format_version, voxel_size, sigma, truncate,
                           h, tile_blocks, n_points, n_dropped, method, complete
    tiles/{i}_{j}/keys     int64 (m, 3): global block coordinates of the tile's blocks
    tiles/{i}_{j}/values   float32 (m, 512): G at the 8³ nodes of each block (x-major)

Both arrays are chunked by 256 blocks and compressed.

Atomicity: a store is written under a temporary name beside it (``.NAME.tmp-PID``, its attribute
``complete`` false), marked complete last and renamed into place by :meth:`FieldStore.commit`,
which only then replaces a store already there (renamed away and removed): a build that fails or
is stopped, even by ``kill -9``, leaves the previous store as it was, and :meth:`FieldStore.open`
refuses a store never completed. The next build of the same name removes what a dead one left.
Stores written before the ``complete`` attribute (sdp before this change) have none and open as
before: nothing tells whether they were finished.

References
----------
.. [1] A. Miles et al., "Zarr: chunked, compressed, N-dimensional arrays", https://zarr.dev.
.. [2] K. Museth, "VDB: High-resolution sparse volumes with dynamic topology", ACM Trans.
   Graph. 32(3), 2013 (block-sparse storage).
"""

from __future__ import annotations

import os
import shutil
from contextlib import suppress
from pathlib import Path

import numpy as np

from ..errors import FieldFileError, InvalidOptionError, require
from ..fields._density import DensityField
from ..fields._lattice import BLOCK, Grid

__all__ = ["FieldStore", "STORE_FORMAT_VERSION"]

#: Version of the store layout written by :meth:`FieldStore.create`.
STORE_FORMAT_VERSION = 1
_ROWS_PER_CHUNK = 256  # blocks per Zarr chunk: 512 KiB of node values before compression


def require_zarr():
    """The zarr module (the ``tiles`` extra), or a one-line :class:`~sdp.MissingDependencyError`."""
    return require("zarr", "tiles", "a field store (.zarr)")


class FieldStore:
    """A density field stored in Zarr, tile by tile (see the module docstring).

    Create one with :meth:`create` (then :meth:`write_tile` and :meth:`commit`), :meth:`from_field`, or
    :func:`sdp.build_field_tiled`; open one with :meth:`open`.
    """

    def __init__(self, path: str | os.PathLike, group, target: Path | None = None):
        self.path = Path(path)
        self._group = group
        self.attrs = dict(group.attrs)
        self._target = target  # where commit() moves a store being written (None: in place)

    # ------------------------------------------------------------------ files
    @classmethod
    def create(cls, path: str | os.PathLike, *, voxel_size: float, sigma: float, truncate: float, h: float,
               tile_blocks: int = 64, method: str = "fast", inputs=()) -> "FieldStore":
        """An empty store to be written at ``path``: it lives under a temporary name beside ``path``
        until :meth:`commit` (which replaces a field store already at ``path``; anything else there,
        a series archive or another Zarr store, is refused here; ``inputs`` are never overwritten).
        :meth:`discard` removes it instead."""
        zarr = require_zarr()

        from ..io._output import refuse_overwrite

        path = Path(path)
        refuse_overwrite(path, inputs)
        if path.exists():
            if not (path / "zarr.json").is_file():
                raise FieldFileError(f"{path}: exists and is not a Zarr store; choose another output name")
            try:
                kind = zarr.open_group(str(path), mode="r").attrs.get("format")
            except Exception:  # zarr raises several types for a damaged store: not ours to replace
                kind = None
            if kind != "sdp-field-store":
                what = "a series archive" if kind == "sdp-series" else "a Zarr store that is not a field store"
                raise FieldFileError(f"{path}: exists and is {what}; choose another output name")
        _remove_leftovers(path)
        tmp = _unfinished(path)[1]
        shutil.rmtree(tmp, ignore_errors=True)
        try:
            group = zarr.open_group(str(tmp), mode="w")
            group.attrs.update({"format": "sdp-field-store", "format_version": STORE_FORMAT_VERSION,
                                "voxel_size": float(voxel_size), "sigma": float(sigma),
                                "truncate": float(truncate), "h": float(h), "tile_blocks": int(tile_blocks),
                                "n_points": 0, "n_dropped": 0, "method": method, "complete": False})
            group.create_group("tiles")
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return cls(tmp, group, path)

    def commit(self) -> "FieldStore":
        """Mark a store from :meth:`create` complete and rename it into place, replacing the store
        that was there (with Ctrl-C and SIGTERM held back meanwhile); returns it, now at its path."""
        if self._target is None:
            return self
        zarr = require_zarr()

        from ..io._output import commit_point

        self._group.attrs["complete"] = True  # last: a store without it was never finished
        target, old = self._target, self._target.parent / f".{self._target.name}.old-{os.getpid()}"
        shutil.rmtree(old, ignore_errors=True)
        with commit_point():
            if target.exists():
                os.rename(target, old)
            os.rename(self.path, target)
        shutil.rmtree(old, ignore_errors=True)
        self.path, self._target = target, None
        self._group = zarr.open_group(str(target), mode="r+")
        self.attrs = dict(self._group.attrs)
        return self

    def discard(self) -> None:
        """Remove a store from :meth:`create` that is not to be committed (what was at its path stays)."""
        if self._target is not None:
            shutil.rmtree(self.path, ignore_errors=True)

    @classmethod
    def open(cls, path: str | os.PathLike) -> "FieldStore":
        """Open a store written by :meth:`create` and :meth:`commit` (read-only use is safe from many
        processes); a store never completed is refused."""
        store = cls._open(path)
        if store.attrs.get("complete") is False:  # stores older than the attribute have none
            raise FieldFileError(f"{store.path}: a field store whose build never completed (stopped or failed); "
                                 f"build it again")
        return store

    @classmethod
    def _open(cls, path: str | os.PathLike) -> "FieldStore":
        """:meth:`open`, a store being written too (the tasks of a tiled build write into it)."""
        zarr = require_zarr()

        path = Path(path)
        if path.is_file():
            raise FieldFileError(f"{path}: a file, not a field store (a .zarr folder, from sdp build -o X.zarr)"
                                 + ("; sdp.DensityField.load reads a .sdpf field" if path.suffix.lower() == ".sdpf"
                                    else ""))
        if not path.exists() and _unfinished(path)[0]:
            raise FieldFileError(f"{path}: no field store yet: a build of it is under way or stopped before its end")
        try:
            group = zarr.open_group(str(path), mode="r+")
        except Exception as exc:  # zarr raises several types for missing or foreign folders
            raise FieldFileError(f"{path}: not a readable sdp field store ({type(exc).__name__}: {exc})") from None
        if group.attrs.get("format") == "sdp-series":
            raise FieldFileError(f"{path}: a series archive (sdp series), not a density field store: `sdp info` "
                                 f"summarises it, sdp.open_series reads it")
        if group.attrs.get("format") is None:
            raise FieldFileError(f"{path}: a Zarr store sdp did not write: neither a field store (sdp build "
                                 f"--tiled) nor a series archive (sdp series)")
        if group.attrs.get("format") != "sdp-field-store" or group.attrs.get("format_version") != STORE_FORMAT_VERSION:
            raise FieldFileError(f"{path}: format {group.attrs.get('format')!r} version "
                                 f"{group.attrs.get('format_version')!r}; this sdp reads sdp-field-store "
                                 f"version {STORE_FORMAT_VERSION}")
        return cls(path, group)

    @classmethod
    def from_field(cls, field: DensityField, path: str | os.PathLike, *, tile_blocks: int = 64) -> "FieldStore":
        """Write an in-memory field to a store, tile by tile."""
        store = cls.create(path, voxel_size=field.voxel_size, sigma=field.sigma, truncate=field.truncate, h=field.h,
                           tile_blocks=tile_blocks, method=field.method)
        try:
            keys = field.global_keys
            for key in np.unique(np.floor_divide(keys[:, :2], tile_blocks), axis=0):
                store.write_tile(tuple(key), field)
            store.set_counts(field.n_points, field.n_dropped)
        except BaseException:
            store.discard()
            raise
        return store.commit()

    def write_tile(self, key, field: DensityField) -> int:
        """Store the blocks of ``field`` that lie in tile ``key`` = (i, j); returns their number."""
        zarr = require_zarr()

        keys = field.global_keys
        mine = np.flatnonzero(np.all(np.floor_divide(keys[:, :2], self.tile_blocks) == key, axis=1))
        mine = mine[np.lexsort(keys[mine].T[::-1])]  # x, y, z order
        name = f"tiles/{int(key[0])}_{int(key[1])}"
        for array, data in (("keys", keys[mine]), ("values", field.blocks.values[mine])):
            out = zarr.create_array(str(self.path), name=f"{name}/{array}", shape=data.shape, dtype=data.dtype,
                                    chunks=(_ROWS_PER_CHUNK, data.shape[1]), overwrite=True)
            out[...] = data
        return len(mine)

    def set_counts(self, n_points: int, n_dropped: int = 0) -> None:
        """Record the number of points the field was built from (and of rows dropped)."""
        self._group.attrs.update({"n_points": int(n_points), "n_dropped": int(n_dropped)})
        self.attrs.update({"n_points": int(n_points), "n_dropped": int(n_dropped)})

    # ------------------------------------------------------------------ properties
    voxel_size = property(lambda self: float(self.attrs["voxel_size"]), doc="Node spacing l (world units).")
    sigma = property(lambda self: float(self.attrs["sigma"]), doc="Kernel σ (world units).")
    truncate = property(lambda self: float(self.attrs["truncate"]), doc="Kernel cut-off in σ.")
    h = property(lambda self: float(self.attrs["h"]), doc="Threshold of F = h − G.")
    tile_blocks = property(lambda self: int(self.attrs["tile_blocks"]), doc="Tile edge in blocks.")
    n_points = property(lambda self: int(self.attrs["n_points"]), doc="Points the field was built from.")

    @property
    def tiles(self) -> list[tuple[int, int]]:
        """The tiles stored, sorted."""
        zarr = require_zarr()

        group = zarr.open_group(str(self.path / "tiles"), mode="r")
        return sorted(tuple(int(v) for v in name.split("_")) for name in group.group_keys())

    @property
    def n_blocks(self) -> int:
        """Blocks stored, over all tiles."""
        return sum(self._tile_keys(t).shape[0] for t in self.tiles)

    def __repr__(self) -> str:
        return (f"FieldStore({str(self.path)!r}, voxel_size={self.voxel_size:g}, sigma={self.sigma:g}, "
                f"h={self.h:.4g}, tiles={len(self.tiles)}, tile_blocks={self.tile_blocks})")

    # ------------------------------------------------------------------ reading
    def _tile_keys(self, key) -> np.ndarray:
        zarr = require_zarr()

        try:
            return zarr.open_array(str(self.path / "tiles" / f"{key[0]}_{key[1]}" / "keys"), mode="r")[...]
        except FileNotFoundError:
            return np.zeros((0, 3), np.int64)

    def read(self, lo=None, hi=None) -> DensityField:
        """The in-memory field of the blocks whose x, y block coordinates lie in [lo, hi)
        (2-vectors; the whole store when omitted, with its count of points: a part has none)."""
        zarr = require_zarr()

        whole = lo is None and hi is None  # the points counted are the whole store's
        lo = np.full(2, np.iinfo(np.int64).min // 2) if lo is None else np.asarray(lo, np.int64)
        hi = np.full(2, np.iinfo(np.int64).max // 2) if hi is None else np.asarray(hi, np.int64)
        t = self.tile_blocks
        keys, values = [np.zeros((0, 3), np.int64)], [np.zeros((0, BLOCK**3), np.float32)]
        for key in self.tiles:
            if np.any(np.asarray(key) * t >= hi) or np.any((np.asarray(key) + 1) * t <= lo):
                continue
            k = self._tile_keys(key)
            rows = np.flatnonzero(np.all((k[:, :2] >= lo) & (k[:, :2] < hi), axis=1))
            if len(rows):
                vals = zarr.open_array(str(self.path / "tiles" / f"{key[0]}_{key[1]}" / "values"), mode="r")
                keys.append(k[rows])
                values.append(vals[...] if len(rows) == len(k) else vals.get_orthogonal_selection((rows, slice(None))))
        keys, values = np.concatenate(keys), np.concatenate(values)
        origin = keys.min(axis=0) if len(keys) else np.zeros(3, np.int64)
        shape = tuple(int(v) for v in (keys.max(axis=0) - origin + 1)) if len(keys) else (1, 1, 1)
        return DensityField(Grid(self.voxel_size, origin, shape), keys - origin, values, h=self.h, sigma=self.sigma,
                            truncate=self.truncate, n_points=self.n_points if whole else 0,
                            n_dropped=int(self.attrs["n_dropped"]), method=self.attrs["method"])

    def tile_field(self, key, *, margin: int = 1) -> DensityField:
        """Tile ``key``'s blocks and those within ``margin`` blocks of it: enough to interpolate
        anywhere in the tile (margin 1) exactly as the whole field would."""
        lo = np.asarray(key, np.int64) * self.tile_blocks - margin
        return self.read(lo, lo + self.tile_blocks + 2 * margin)

    def _by_tile(self, points: np.ndarray):
        """(tile key, indices) of the points of each tile."""
        cell = np.floor(points[:, :2] / (self.voxel_size * BLOCK * self.tile_blocks))
        ok = np.isfinite(cell).all(axis=1)
        cell = np.where(ok[:, None], cell, 0).astype(np.int64)
        keys, inverse = np.unique(cell, axis=0, return_inverse=True)
        order = np.argsort(inverse.ravel(), kind="stable")
        splits = np.cumsum(np.bincount(inverse.ravel(), minlength=len(keys)))[:-1]
        return [(tuple(k), idx[ok[idx]]) for k, idx in zip(keys, np.split(order, splits), strict=True)]

    def density(self, points) -> np.ndarray:
        """G at world positions (n, 3), tile by tile (as :meth:`DensityField.density`)."""
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.full(len(pts), np.nan)
        for key, idx in self._by_tile(pts):
            if len(idx):
                out[idx] = self.tile_field(key).density(pts[idx])
        return out

    def field(self, points) -> np.ndarray:
        """F = h − G at world positions: negative inside the cluster volume."""
        return self.h - self.density(points)

    def mesh(self, *, level: float = 0.0, memory_limit: int | str | None = None):
        """The surface F = ``level``, tile by tile (Lewiner marching cubes, as
        :meth:`DensityField.mesh`); vertices on tile seams are merged.

        Raises
        ------
        GridTooLargeError
            The process, one tile's field and the surfaces of all tiles (merged and written:
            :func:`sdp.fields._surface.surface_bytes`) would exceed ``memory_limit``; counted tile
            by tile, refused before the merge with the limit that would do.
        """
        from .._core._memory import memory_limit as limit
        from .._core._validate import finite
        from ..errors import SurfaceError
        from ..fields._surface import (_CHUNK, BYTES_PER_SURFACE_VERTEX, CHUNK_BYTES, Mesh, check_surface,
                                       merge_seams, surface_nodes, surface_vertices)
        from ._budget import PROCESS_BYTES

        cap, level = limit(memory_limit), finite("level", level)
        n = self.tile_blocks * BLOCK
        verts, faces, offset = [], [], 0
        tile_bytes = surface = 0  # the largest tile's field and work; the surfaces so far
        for key in self.tiles:
            f = self.tile_field(key)
            tile_bytes = max(tile_bytes, f.nbytes + CHUNK_BYTES)
            own = np.all(np.floor_divide(f.global_keys[:, :2], self.tile_blocks) == key, axis=1)  # not its margin
            surface += surface_vertices(f.blocks.values[:f.n_blocks][own], f.h - level) * BYTES_PER_SURFACE_VERTEX
            if PROCESS_BYTES + tile_bytes + surface > cap:
                continue  # refused below: the other tiles counted for the limit that would do, none meshed
            # marching cubes' chunks on one lattice for every tile (its origin a multiple of _CHUNK
            # blocks): a seam edge then gives both tiles bitwise the same vertex, merged exactly; with
            # the tiles' own origins its copies differed in their last bits and rounded apart (open seams)
            shift = f.grid.block_origin - np.floor_divide(f.grid.block_origin, _CHUNK) * _CHUNK
            f = DensityField(Grid(self.voxel_size, f.grid.block_origin - shift,
                                  tuple(int(s) for s in np.asarray(f.grid.shape_blocks) + shift)),
                             f.blocks.keys + shift, f.blocks.values, h=f.h, sigma=f.sigma, truncate=f.truncate)
            try:
                v, tri = surface_nodes(f, level=level)
            except SurfaceError:
                continue
            v += f.grid.block_origin * BLOCK  # global node units: an integer added, exact
            cell = np.floor(v[tri].mean(axis=1)[:, :2]).astype(np.int64)
            keep = np.all(np.floor_divide(cell, n) == key, axis=1)  # triangles of this tile's cells
            used, tri = np.unique(tri[keep], return_inverse=True)  # and their vertices alone, not the margin's
            verts.append(v[used])
            faces.append(tri.reshape(-1, 3) + offset)
            offset += len(used)
        check_surface(PROCESS_BYTES + tile_bytes + surface, cap, f"{self.path}: its surface, tile by tile,")
        if not verts:
            raise SurfaceError(f"no surface crosses level {level:g}")
        v, f = np.concatenate(verts), np.concatenate(faces)
        verts.clear()
        faces.clear()
        first, inverse = merge_seams(v)  # the in-memory merge, in node units of the global lattice
        # every vertex kept is a kept triangle's (above): all the merged ones are used
        return Mesh(v[first] * self.voxel_size, inverse[f])

    def combine(self, other: "FieldStore", operation: str, path: str | os.PathLike) -> "FieldStore":
        """Out-of-core Boolean operation (``"union"``, ``"intersection"`` or ``"difference"``,
        as :mod:`sdp.fields._boolean`), tile by tile, into a new store at ``path``."""
        from ..fields import _boolean as boolean

        if operation not in ("union", "intersection", "difference"):
            raise InvalidOptionError(f"operation must be union, intersection or difference, got {operation!r}")
        op, t = getattr(boolean, operation), self.tile_blocks
        tiles = set(self.tiles)
        for key in other.tiles:  # this store's tiles that the other's tiles overlap
            lo = np.floor_divide(np.asarray(key) * other.tile_blocks, t)
            hi = np.floor_divide((np.asarray(key) + 1) * other.tile_blocks - 1, t)
            tiles |= {(i, j) for i in range(lo[0], hi[0] + 1) for j in range(lo[1], hi[1] + 1)}
        out = None
        try:
            for key in sorted(tiles):
                lo = np.asarray(key, np.int64) * t
                a, b = self.read(lo, lo + t), other.read(lo, lo + t)
                if a.n_blocks + b.n_blocks == 0:
                    continue
                r = op(a, b)
                if out is None:
                    out = FieldStore.create(path, voxel_size=r.voxel_size, sigma=r.sigma, truncate=r.truncate,
                                            h=r.h, tile_blocks=t, method=operation, inputs=(self.path, other.path))
                out.write_tile(key, r)
        except BaseException:
            if out is not None:
                out.discard()
            raise
        return out if out is None else out.commit()


def _unfinished(path: Path) -> tuple[list[Path], Path]:
    """(the unfinished stores of ``path`` that builds left, this process's temporary name for it)."""
    return sorted(path.parent.glob(f".{path.name}.tmp-*")), path.parent / f".{path.name}.tmp-{os.getpid()}"


def _remove_leftovers(path: Path) -> None:
    """Remove what builds of ``path`` whose process is gone left beside it (a ``kill -9``)."""
    from ..timeseries._archive import _alive

    for left in [*path.parent.glob(f".{path.name}.old-*"), *_unfinished(path)[0]]:
        with suppress(ValueError):
            if _alive(int(left.name.rsplit("-", 1)[1])):
                continue
        if left.name.startswith(f".{path.name}.old-") and not path.exists():
            os.rename(left, path)  # stopped between commit's two renames: the previous store put back
        else:
            shutil.rmtree(left, ignore_errors=True)
