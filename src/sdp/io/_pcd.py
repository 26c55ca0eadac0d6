"""PCD files (PCL's format), read with pypcd4: v0.7 ascii, binary and binary_compressed.

Organized files (HEIGHT > 1: one point per pixel or ray) mark a missing return by NaN or by a
point at exactly (0, 0, 0); both become NaN here, dropped and counted by
:func:`sdp.io.read_points`. The header's VIEWPOINT (the sensor's pose) is returned with the
points. A field of COUNT c > 1 becomes c fields (``normal__0000``, …); PCL's ``_`` padding fields
are left out. sdp writes no PCD.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._cloud import CloudFileError, unpacked_colour

__all__ = ["pcd_image", "read_pcd"]


def read_pcd(path):
    """``(xyz, fields, None, viewpoint, organized)`` of a PCD file (x, y, z as float64, missing
    returns of an organized file as NaN; other fields in their declared integer types, a packed
    ``rgb``/``rgba`` as ``red``, ``green``, ``blue``: :func:`~sdp.io._cloud.unpacked_colour`)."""
    from pypcd4 import PointCloud

    _check_header_columns(path)
    pc = PointCloud.from_path(path)
    _pcl_columns(pc)
    padding = _padding(pc, _header(path)[0].get("FIELDS", []))
    names = [n for n in pc.fields if n not in padding]
    if not {"x", "y", "z"} <= set(names):
        raise CloudFileError(f"{path}: PCD fields {names} have no x, y, z")
    data = pc.numpy(names)
    _check_count(path, pc, len(data))
    cols = {n: data[:, i] for i, n in enumerate(names)}
    fields = {n: _pcd_column(pc, n, cols[n]) for n in names if n not in ("x", "y", "z")}
    for packed in ("rgb", "rgba"):  # its four bytes as stored (pypcd4's float64 copy would not keep them)
        if packed in fields and pc.pc_data.dtype[packed].itemsize == 4 and pc.pc_data.dtype[packed].shape == ():
            fields[packed] = np.ascontiguousarray(pc.pc_data[packed])
    fields = unpacked_colour(fields)
    xyz = np.c_[cols["x"], cols["y"], cols["z"]]
    if pc.metadata.height > 1:  # organized scans mark a missing return by NaN or by (0, 0, 0)
        xyz[~xyz.any(axis=1)] = np.nan
    viewpoint = np.asarray(pc.metadata.viewpoint, dtype=np.float64)
    if viewpoint.shape != (7,) or not np.isfinite(viewpoint).all():
        raise CloudFileError(f"{path}: VIEWPOINT must be 7 finite numbers (tx ty tz qw qx qy qz), "
                             f"got {pc.metadata.viewpoint}")
    return xyz, fields, None, viewpoint, pc.metadata.height > 1


_HEADER_END = b"DATA"


def pcd_image(path) -> tuple[int, int] | None:
    """(HEIGHT, WIDTH) of an organized PCD file's header, or None."""
    entries, _ = _header(path)
    try:
        return int(entries["HEIGHT"][0]), int(entries["WIDTH"][0])
    except (KeyError, IndexError, ValueError):
        return None


def _header(path) -> tuple[dict[str, list[str]], int]:
    """The header's lines by keyword, and the byte where the data starts (after the DATA line)."""
    entries: dict[str, list[str]] = {}
    with open(path, "rb") as f:
        for _ in range(64):  # a PCD header has 10 lines and comments
            line = f.readline()
            if not line:
                break
            words = line.decode("ascii", "replace").split()
            if words and not words[0].startswith("#"):
                entries[words[0].upper()] = words[1:]
            if line.startswith(_HEADER_END):
                return entries, f.tell()
    return entries, -1


def _check_header_columns(path) -> None:
    """Refuse a header whose FIELDS, SIZE, TYPE and COUNT do not name as many columns (pypcd4
    fails on them with an IndexError that names nothing)."""
    entries, _ = _header(path)
    lengths = {k: len(entries[k]) for k in ("FIELDS", "SIZE", "TYPE", "COUNT") if k in entries}
    if len(set(lengths.values())) > 1:
        told = ", ".join(f"{k} {n}" for k, n in lengths.items())
        raise CloudFileError(f"{path}: corrupt PCD header: FIELDS, SIZE, TYPE and COUNT must list as many columns "
                             f"(got {told})")


def _check_count(path, pc, rows: int) -> None:
    """Refuse a file holding another number of points than its header announces (POINTS, and
    WIDTH × HEIGHT), or a binary one with bytes beyond them: a count that disagrees with the
    data means a cut or corrupt file, and reading what is there would answer silently wrong."""
    meta = pc.metadata
    if meta.width * meta.height != meta.points:
        raise CloudFileError(f"{path}: corrupt PCD header: WIDTH × HEIGHT = {meta.width * meta.height:,}, "
                             f"POINTS {meta.points:,}")
    if rows != meta.points:
        raise CloudFileError(f"{path}: the PCD header announces {meta.points:,} points, the file holds {rows:,}")
    if str(getattr(meta.data, "value", meta.data)) == "binary":
        _, start = _header(path)
        record = sum(int(s) * int(c) for s, c in zip(meta.size, meta.count))
        extra = Path(path).stat().st_size - start - meta.points * record
        if start >= 0 and extra > 0:
            raise CloudFileError(f"{path}: the PCD header announces {meta.points:,} points, the file holds "
                                 f"{extra:,} bytes more")


def _pcl_columns(pc) -> None:
    """Put back, in place, the values of binary_compressed fields of COUNT c > 1 as PCL stores
    them. PCL (``PCDWriter::writeBinaryCompressed``) writes such a field's column whole, each
    point's c values together ([p0v0, p0v1, …, p1v0, …]); pypcd4 reads it as c columns of n values
    one after the other, which scrambles the values across points. Joined in pypcd4's order, its
    sub-columns are that column: reshaped (n, c), sub-column k is column k."""
    meta = pc.metadata
    if str(getattr(meta.data, "value", meta.data)) in ("ascii", "binary") or len(pc.pc_data) == 0:
        return
    for name, count in zip(meta.fields, meta.count):
        if count > 1:
            subs = [f"{name}__{k:04d}" for k in range(count)]
            column = np.concatenate([pc.pc_data[s] for s in subs]).reshape(len(pc.pc_data), count)
            for k, s in enumerate(subs):
                pc.pc_data[s] = column[:, k]


def _padding(pc, fields: list[str]) -> set[str]:
    """pypcd4's names of the header's ``_`` fields: PCL's padding (bytes that align the next
    field, e.g. ``FIELDS x y z _ rgb _``), which PCL and CloudCompare skip. pypcd4 names each
    after a random string, so kept they would be junk dimensions named anew at every read."""
    meta = pc.metadata
    if len(fields) != len(meta.fields):
        return set()
    skip = set()
    for given, name, count in zip(fields, meta.fields, meta.count):
        if given == "_":
            skip.update([name] if count == 1 else [f"{name}__{k:04d}" for k in range(count)])
    return skip


def _pcd_column(pc, name, col):
    """pypcd4 returns a float64 matrix; give each field back its declared type (labels, rgba)."""
    dtype = np.dtype(pc.types[list(pc.fields).index(name)])
    return col.astype(dtype) if dtype.kind in "ui" else col
