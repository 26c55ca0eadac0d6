"""Clouds larger than memory: :class:`PointSource` reads a file in row slices (for
:mod:`sdp.scale._tiles`), and :func:`write_points_streamed` writes every row of one with new
per-point fields, chunk by chunk, as LAS/LAZ."""

from __future__ import annotations

import itertools
import os
import tempfile
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ._cloud import CloudFileError, input_format, library_error, unreadable
from ._las import (LAS_CHUNK, STANDARD, check_las_counts, check_las_points, las_scale_offset, standard_rules,
                   standard_values, value_range, xyz_only)
from ._output import atomic_path
from ._ply import ply_is_binary, ply_vertices
from ._read import read_points

__all__ = ["PointSource", "write_points_streamed"]


@dataclass(frozen=True)
class PointSource:
    """Rows of a point-cloud file, read slice by slice: a cloud larger than memory.

    LAS/LAZ are sliced by seeking through the LAZ chunk table, NPY through a memory map and
    binary PLY through plyfile's memory map. Picklable (it holds the path, not an open file),
    so Dask tasks on other processes or machines can each read their own slice of a file they
    can reach. Open one with
    :meth:`open`; a format that can't be sliced (PCD, text, NPZ, ASCII PLY) is read once
    and spilled to a ``.npy`` file in ``spill_dir``.

    Attributes
    ----------
    path : Path
        The file read (a ``.npy`` spill for formats that can't be sliced).
    format : str
        ``"las"``, ``"npy"`` or ``"ply"``.
    n_rows : int
        Rows in the file (NaN/Inf rows included: they are dropped where the rows are used).
    lo, hi : tuple of float
        Bounds of the points (from the LAS header, else computed in one streaming pass).
    """

    path: Path
    format: str
    n_rows: int
    lo: tuple
    hi: tuple

    @classmethod
    def open(cls, path: str | os.PathLike, *, format: str | None = None, spill_dir: str | os.PathLike | None = None,
             chunk_size: int = LAS_CHUNK) -> "PointSource":
        """Inspect ``path`` (header, or one pass for the bounds) without keeping its points."""
        path = Path(path)
        fmt = input_format(path, format)
        try:
            if fmt == "las":
                import laspy

                check_las_counts(path)
                with laspy.open(str(path)) as r:
                    h = r.header
                    check_las_points(path, h)
                    lo, hi = np.asarray(h.mins, float), np.asarray(h.maxs, float)
                    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (lo <= hi).all()):
                        raise CloudFileError(f"{path}: the LAS header's bounds {lo.tolist()} … {hi.tolist()} are "
                                             "not a box")
                    if h.are_points_compressed:  # decode the first points: a cut-off LAZ fails here
                        r.read_points(1)
                    return cls(path, fmt, int(h.point_count), tuple(map(float, lo)), tuple(map(float, hi)))
            if fmt == "ply" and ply_is_binary(path):
                v = ply_vertices(path)
                if not {"x", "y", "z"} <= set(v.dtype.names):
                    raise CloudFileError(f"{path}: PLY vertices have no x, y, z (properties: {v.dtype.names})")
                n = len(v)
            elif fmt == "npy":
                a = np.load(path, mmap_mode="r", allow_pickle=False)
                if a.ndim != 2 or a.shape[1] != 3 or a.dtype.kind not in "iuf":
                    raise CloudFileError(f"{path}: expected an (n, 3) array of real numbers, got shape {a.shape} "
                                         f"of {a.dtype}")
                n = len(a)
            else:  # can't slice: read it once, spill the finite points to .npy
                if spill_dir is None:
                    raise CloudFileError(f"{path}: {fmt} files can't be read in slices; convert to LAS/LAZ, NPY or "
                                         "binary PLY (or, in Python, give spill_dir=)")
                fd, tmp = tempfile.mkstemp(suffix=".npy", dir=spill_dir)
                os.close(fd)
                np.save(tmp, read_points(path, format=fmt, fields=False).xyz)
                return cls.open(tmp, format="npy", chunk_size=chunk_size)
        except CloudFileError:
            raise
        except BaseException as exc:  # libraries raise many types on corrupt input (lazrs: Rust panics)
            if not library_error(exc):
                raise
            raise unreadable(path, fmt, exc) from None
        if n == 0:
            raise CloudFileError(f"{path}: holds no point")
        src = cls(path, fmt, n, (np.inf,) * 3, (-np.inf,) * 3)
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for _, xyz in src.chunks(chunk_size):
            ok = np.isfinite(xyz).all(axis=1)
            if ok.any():
                lo, hi = np.minimum(lo, xyz[ok].min(axis=0)), np.maximum(hi, xyz[ok].max(axis=0))
        if not np.isfinite(lo).all():
            raise CloudFileError(f"{path}: holds no point with finite x, y, z")
        return cls(path, fmt, n, tuple(map(float, lo)), tuple(map(float, hi)))

    def read(self, start: int, stop: int) -> np.ndarray:
        """Rows ``start`` … ``stop − 1`` as float64 (m, 3) world coordinates (NaN rows kept).

        Raises
        ------
        CloudFileError
            The file can't be decoded there (cut short, corrupt, changed since it was opened).
        """
        with _decoding(self):
            return self._read(start, stop)

    def _read(self, start: int, stop: int) -> np.ndarray:
        start, stop = max(0, start), min(stop, self.n_rows)
        if stop <= start:
            return np.zeros((0, 3))
        if self.format == "las":  # one decoding path: a single chunk
            return next(self.chunks(stop - start, start, stop))[1]
        if self.format == "npy":
            return np.array(np.load(self.path, mmap_mode="r", allow_pickle=False)[start:stop], dtype=np.float64)
        v = ply_vertices(self.path)[start:stop]
        return np.c_[v["x"], v["y"], v["z"]].astype(np.float64)

    def fields(self, start: int, stop: int, names=None) -> dict[str, np.ndarray]:
        """The other per-point values of rows ``start`` … ``stop − 1`` (those of ``names`` alone,
        if given), as :func:`sdp.read_points` gives them: a binary PLY's scalar vertex properties
        (none for NPY; a LAS file's records are copied whole by :func:`write_points_streamed`)."""
        if self.format != "ply":
            return {}
        with _decoding(self):
            v = ply_vertices(self.path)
            rows = v[max(0, start):min(stop, self.n_rows)]
            return {n: np.asarray(rows[n]) for n in v.dtype.names
                    if n not in ("x", "y", "z") and v.dtype[n].shape == () and v.dtype[n].kind in "biuf"
                    and (names is None or n in names)}

    def chunks(self, size: int = LAS_CHUNK, start: int = 0, stop: int | None = None):
        """Yield ``(first_row, xyz)`` slices of at most ``size`` rows, in order.

        Raises
        ------
        CloudFileError
            The file can't be decoded (cut short, corrupt), naming it.
        """
        yield from _decoded(self, self._chunks(size, start, stop))

    def _chunks(self, size: int, start: int, stop: int | None):
        stop = self.n_rows if stop is None else min(stop, self.n_rows)
        if self.format == "las":  # one open file, sequential decoding
            import laspy

            from ._kernels import scaled_xyz

            with laspy.open(str(self.path), decompression_selection=xyz_only()) as r:
                scale, offset = np.asarray(r.header.scales, float), np.asarray(r.header.offsets, float)
                r.seek(start)
                for s in range(start, stop, size):
                    pts = r.read_points(min(size, stop - s))
                    yield s, scaled_xyz(pts.X, pts.Y, pts.Z, scale, offset)
            return
        for s in range(start, stop, size):
            yield s, self.read(s, min(s + size, stop))


_END = object()


@contextmanager
def _decoding(source: PointSource):
    """Turn the reader libraries' exceptions in the block into :class:`CloudFileError` naming the file."""
    try:
        yield
    except CloudFileError:
        raise
    except BaseException as exc:  # libraries raise many types on corrupt input (lazrs: Rust panics)
        if not library_error(exc):
            raise
        raise unreadable(source.path, source.format, exc) from None


def _decoded(source: PointSource, iterator):
    """``iterator``'s items, read under :func:`_decoding`."""
    while True:
        with _decoding(source):
            item = next(iterator, _END)
        if item is _END:
            return
        yield item


def write_points_streamed(path: str | os.PathLike, source: PointSource, fields_of, *, inputs=(),
                          chunk_size: int = LAS_CHUNK, drop=()) -> Path:
    """Write every row of ``source`` with extra per-point fields, chunk by chunk, as LAS/LAZ.

    ``fields_of(start, stop)`` returns the fields of rows ``start`` … ``stop − 1`` (a dict of
    arrays). LAS/LAZ input keeps every dimension, VLR, scale and offset, but the extra
    dimensions named in ``drop`` (an earlier run's outputs that this one does not write anew);
    other input gets the scale and offset of :func:`~sdp.io._las.las_scale_offset` (1 mm, finer
    where the first chunk's points lie closer than a centimetre; offset at the centre) and its own
    values (:meth:`PointSource.fields`) as :func:`sdp.write_points` writes them in memory: colour
    and intensity as LAS's where they fit, the others as extra dimensions (but for ``drop`` and the
    fields this output writes anew).
    Memory is bounded by ``chunk_size``; the file is written under a temporary name and renamed,
    and ``inputs`` are never overwritten. LAZ is decoded and encoded on all cores (lazrs'
    parallel backend).
    """
    import copy

    import laspy

    path = Path(path)
    if path.suffix.lower() not in (".las", ".laz"):
        raise CloudFileError(f"{path}: a cloud written chunk by chunk must be .las or .laz")
    with ExitStack() as stack:
        if source.format == "las":
            reader = stack.enter_context(laspy.open(str(source.path), laz_backend=laspy.LazBackend.LazrsParallel))
            header = copy.deepcopy(reader.header)
            stale = [name for name in header.point_format.extra_dimension_names if name in drop]
            if stale:
                header.remove_extra_dims(stale)
            chunks = ((len(c), c) for c in _decoded(source, reader.chunk_iterator(chunk_size)))
        else:
            # the input's own values (a PLY's properties) as in memory: colour and intensity where
            # the whole file's values fit LAS's 16 bits (one pass over them first), others extra
            ranges = {}
            for s in range(0, source.n_rows, chunk_size):
                for name, v in source.fields(s, s + chunk_size, names=STANDARD).items():
                    ranges[name] = value_range(v, ranges.get(name))
            rules = standard_rules(ranges)
            header = laspy.LasHeader(point_format=2 if "red" in rules else 0, version="1.4")
            parts = ((len(xyz), xyz) for _, xyz in source.chunks(chunk_size))
            first = next(parts, None)  # its spacing sets the scale, as the whole cloud's does in memory
            sample = None if first is None else first[1][np.isfinite(first[1]).all(axis=1)]
            header.scales, header.offsets = las_scale_offset(source.lo, source.hi, path, xyz=sample)
            chunks = itertools.chain([] if first is None else [first], parts)
        tmp = stack.enter_context(atomic_path(path, inputs=inputs))
        writer, start = None, 0
        for n, chunk in chunks:
            fields = fields_of(start, start + n)
            if source.format != "las":  # the input's values, but for those this output writes anew
                own = {k: v for k, v in source.fields(start, start + n).items() if k not in fields and k not in drop}
                fields = {**own, **fields}
                standard = standard_values(fields, rules)
            if writer is None:
                for name, v in fields.items():
                    if name not in header.point_format.dimension_names:
                        v = np.asarray(v)
                        dtype = np.uint8 if v.dtype == bool else v.dtype  # as write_las stores them
                        header.add_extra_dim(laspy.ExtraBytesParams(name=name, type=dtype))
                writer = stack.enter_context(laspy.open(str(tmp), mode="w", header=header,
                                                        do_compress=path.suffix.lower() == ".laz",
                                                        laz_backend=laspy.LazBackend.LazrsParallel))
            out = laspy.ScaleAwarePointRecord.zeros(n, header=header)
            if source.format == "las":
                kept = out.array.dtype.names
                for name in chunk.array.dtype.names:
                    if name in kept:  # not a dimension dropped
                        out.array[name] = chunk.array[name]
            else:  # LAS can't hold NaN rows: they are left out
                ok = np.isfinite(chunk).all(axis=1)
                out = out[ok] if not ok.all() else out
                out.x, out.y, out.z = chunk[ok, 0], chunk[ok, 1], chunk[ok, 2]
                fields = {name: np.asarray(v)[ok] for name, v in {**standard, **fields}.items()}
            for name, v in fields.items():
                out[name] = v
            writer.write_points(out)
            start += n
        if writer is not None and source.format == "las" and header.evlrs:  # LAS 1.4's extended records
            writer.write_evlrs(header.evlrs)  # (a WKT CRS) follow the points: the writer adds them when told
    return path
