"""LAS/LAZ files (ASPRS LAS 1.0–1.4), with laspy and the lazrs backend: read (scaled integers to
exact float64), written (a 1 mm grid unless the input's own is kept), and checked before laspy
reads a header.

A LAS/LAZ header is checked first for counts that cannot fit the file: a corrupt VLR count makes
laspy loop for hours, a corrupt chunk-table count makes lazrs abort the process.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np

from .._core._progress import bar
from ._cloud import Cloud, CloudFileError, EmptyCloudError, notice

__all__ = ["LAS_CHUNK", "read_las", "las_point_count", "check_las_counts", "check_las_points", "las_scale_offset",
           "write_las", "xyz_only"]

LAS_CHUNK = 2_000_000  # points per chunk read (a progress step)


def read_las(path, *, fields: bool = True):
    """``(xyz, fields, las)`` of a LAS/LAZ file: world coordinates, every other dimension as a
    field, and the ``laspy.LasData`` (so outputs can keep every dimension); points flagged
    withheld or classified noise are read as any other, with a :func:`~sdp.io._cloud.notice`.
    ``fields=False``: ``(xyz, {}, None)``, without unpacking the other dimensions (they cost as
    much as the decompression) nor a notice."""
    import laspy

    check_las_counts(path)
    keep = laspy.DecompressionSelection.all() if fields else xyz_only()
    with laspy.open(str(path), decompression_selection=keep) as reader, \
            bar(reader.header.point_count, f"reading {Path(path).name}") as pb:
        check_las_points(path, reader.header)
        chunks = []
        for chunk in reader.chunk_iterator(LAS_CHUNK):
            chunks.append(chunk.array)
            pb.update(len(chunk))
        h = reader.header
        if not chunks:
            chunks = [np.zeros(0, h.point_format.dtype())]
        records = np.concatenate(chunks) if len(chunks) > 1 else chunks[0]
    # scaled and offset, float64: large coordinates stay exact; filled in place (np.c_ copies twice)
    xyz = np.empty((len(records), 3))
    for a, (name, scale, offset) in enumerate(zip("XYZ", h.scales, h.offsets)):
        np.multiply(records[name], scale, out=xyz[:, a])
        xyz[:, a] += offset
    if not fields:
        return xyz, {}, None
    las = laspy.LasData(h, points=laspy.ScaleAwarePointRecord(records, h.point_format, h.scales, h.offsets))
    values = {d: np.asarray(las[d]) for d in las.point_format.dimension_names if d not in ("X", "Y", "Z")}
    # withheld ("should be considered deleted") and noise points are compared as any other, as
    # PDAL's readers.las and CloudCompare load them: leaving them out would change every output's
    # rows. Said, as a change found among them may be noise rather than the surface.
    noise = (7, 18) if h.point_format.id >= 6 else (7,)  # 18, high noise, is a class of formats 6-10 only
    withheld = int(np.count_nonzero(values["withheld"])) if "withheld" in values else 0
    noisy = int(np.isin(values["classification"], noise).sum()) if "classification" in values else 0
    if withheld or noisy:
        classes = " ".join(map(str, noise))
        told = [f"{withheld:,} flagged withheld"] * bool(withheld) + \
            [f"{noisy:,} classified noise (class {classes.replace(' ', ' or ')})"] * bool(noisy)
        count, _, rest = " and ".join(told).partition(" ")
        drop = ["-drop_withheld"] * bool(withheld) + [f"-drop_class {classes}"] * bool(noisy)
        notice(f"{path}: {count} point{'' if count == '1' else 's'} {rest}, compared as any other point; to leave "
               f"them out, filter the file first (e.g. las2las {' '.join(drop)})")
    return xyz, values, las


def _standard_dimensions(fields: dict) -> dict:
    """LAS's own ``intensity`` and ``red``, ``green``, ``blue`` (16 bits) from fields of those
    names that hold them: values within [0, 1] (an E57's intensity), or whole numbers within 16
    bits, integers or the floats a text file's columns are read as (8-bit colour spread over 16,
    as the specification asks). Others stay extra dimensions (an ``intensity`` in other units is
    renamed ``input_intensity``)."""
    rules = standard_rules({n: value_range(v) for n, v in fields.items() if n in STANDARD})
    return standard_values(fields, rules)


#: The fields another format's cloud may carry that LAS holds in dimensions of its own.
STANDARD = ("intensity", "red", "green", "blue")


def value_range(v, merged: tuple | None = None) -> tuple | None:
    """(dtype kind, lowest, highest, all finite, all whole) of the values ``v``, merged with an
    earlier part's ``merged`` (a file read chunk by chunk); None for no value."""
    v = np.asarray(v)
    if not v.size:
        return merged
    finite = v.dtype.kind not in "f" or bool(np.isfinite(v).all())
    whole = v.dtype.kind in "biu" or (finite and bool(np.array_equal(v, np.round(v))))
    part = (v.dtype.kind, float(v.min()) if finite else np.nan, float(v.max()) if finite else np.nan, finite, whole)
    if merged is None:
        return part
    kind = merged[0] if merged[0] == part[0] else "f"
    return (kind, min(merged[1], part[1]), max(merged[2], part[2]), merged[3] and part[3], merged[4] and part[4])


def standard_rules(ranges: dict) -> dict:
    """For each of :data:`STANDARD` whose values (their :func:`value_range`) fit LAS's 16 bits,
    how to write them: ``("unit", 65535)`` for values within [0, 1], else ``("scale", factor)``
    (257 spreads 8-bit colour over 16 bits); the colour only when all three channels fit. An
    ``intensity`` that does not fit maps to None (kept as the extra dimension ``input_intensity``)."""
    def rule(r, colour):
        if r is None or r[0] not in "uif" or not r[3] or r[1] < 0 or r[2] > 65535:
            return None
        if r[0] == "f" and r[2] <= 1:
            return ("unit", 65535)
        if r[0] == "f" and not r[4]:
            return None
        return ("scale", 257 if colour and r[2] <= 255 else 1)

    out = {}
    if "intensity" in ranges:
        out["intensity"] = rule(ranges["intensity"], False)
    rgb = [rule(ranges.get(c), True) if c in ranges else None for c in ("red", "green", "blue")]
    if all(c is not None for c in rgb):
        out.update(zip(("red", "green", "blue"), rgb))
    return out


def standard_values(fields: dict, rules: dict) -> dict:
    """The LAS dimensions :func:`standard_rules` gave, taken out of ``fields`` (an ``intensity``
    that does not fit renamed ``input_intensity`` there)."""
    out = {}
    for name, r in rules.items():
        if r is None:  # an intensity in other units
            fields["input_intensity"] = fields.pop(name)
            continue
        v = np.asarray(fields.pop(name))
        out[name] = np.round(v * 65535).astype(np.uint16) if r[0] == "unit" else v.astype(np.uint16) * r[1]
    return out


def xyz_only():
    """laspy's decompression selection of x, y, z alone: LAZ point formats 6-10 store the other
    dimensions in layers of their own, which lazrs then skips (most of the decoding where a file
    carries colour, intensity or GPS time); other formats decompress whole."""
    import laspy

    return laspy.DecompressionSelection.XY_RETURNS_CHANNEL | laspy.DecompressionSelection.Z


def check_las_counts(path) -> None:
    """Refuse a LAS/LAZ whose header counts more (extended) VLRs than the file can hold, before laspy
    reads it: laspy loops over the count, and a corrupt 32-bit count makes that loop run for hours.
    Reads the public header block's fixed fields only (ASPRS LAS 1.0–1.4)."""
    import struct

    size = Path(path).stat().st_size
    with open(path, "rb") as f:
        head = f.read(255)
    if head[:4] != b"LASF":
        raise CloudFileError(f"{path}: can't read as las (no LASF signature: not a LAS/LAZ file)")
    if len(head) < 227:
        raise CloudFileError(f"{path}: can't read as las (truncated: the header holds {len(head)} of 227 bytes)")
    header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
    if offset > size:
        raise CloudFileError(f"{path}: truncated: the LAS header puts the points at byte {offset:,}, the file holds "
                             f"{size:,} bytes")
    if header_size + 54 * n_vlrs > offset:
        raise CloudFileError(f"{path}: corrupt LAS header: {n_vlrs:,} records do not fit before the point data")
    if offset + 8 <= size and bool(head[104] & 0x80 or head[104] & 0x40):  # LAZ: its chunk table
        # lazrs allocates the table's entries before reading them: a corrupt count aborts the process
        with open(path, "rb") as f:
            f.seek(offset)
            (table,) = struct.unpack("<q", f.read(8))
            if 0 < table and table + 8 <= size:
                f.seek(table)
                _, n_chunks = struct.unpack("<II", f.read(8))
                if n_chunks > size:
                    raise CloudFileError(f"{path}: corrupt LAZ chunk table ({n_chunks:,} chunks in a file of "
                                         f"{size:,} bytes)")
    if head[24:26] == b"\x01\x04" and len(head) >= 255:  # LAS 1.4: a 64-bit count beside the legacy one
        (legacy,), (count,) = struct.unpack_from("<I", head, 107), struct.unpack_from("<Q", head, 247)
        if legacy and legacy != count:  # legacy 0: more than 2**32 points, or a format it can't name
            raise CloudFileError(f"{path}: corrupt LAS header: it counts {legacy:,} points and {count:,}")
    if head[24:26] == b"\x01\x04" and len(head) >= 247:  # LAS 1.4: extended VLRs at the end
        start, n_evlrs = struct.unpack_from("<QI", head, 235)
        if n_evlrs and (start > size or 60 * n_evlrs > size):
            raise CloudFileError(f"{path}: corrupt LAS header: {n_evlrs:,} extended records do not fit in a file "
                                 f"of {size:,} bytes")


def las_point_count(path) -> int | None:
    """The point count a LAS/LAZ header records (its fixed fields alone, a few microseconds), or
    None if ``path`` is not a LAS/LAZ file."""
    import struct

    with open(path, "rb") as f:
        head = f.read(255)
    if head[:4] != b"LASF" or len(head) < 111:
        return None
    (legacy,) = struct.unpack_from("<I", head, 107)
    if head[24:26] >= b"\x01\x04" and len(head) >= 255 and not legacy:  # LAS 1.4: the 64-bit count
        (legacy,) = struct.unpack_from("<Q", head, 247)
    return int(legacy)


def check_las_points(path, header) -> None:
    """Refuse a LAS/LAZ file without points, or an uncompressed LAS shorter than its header says."""
    n = int(header.point_count)
    if n == 0:
        raise EmptyCloudError(f"{path}: holds no point (its LAS header counts 0)")
    if not header.are_points_compressed:
        need = int(header.offset_to_point_data) + n * int(header.point_format.size)
        have = Path(path).stat().st_size
        if have < need:
            raise CloudFileError(f"{path}: truncated: the LAS header announces {n:,} points ({need:,} bytes) but the "
                                 f"file holds {have:,} bytes")
        evlrs = int(getattr(header, "start_of_first_evlr", 0) or 0)
        end = evlrs if evlrs >= need else have  # LAS 1.4 puts extended records after the points
        if end - need >= int(header.point_format.size):
            raise CloudFileError(f"{path}: the LAS header announces {n:,} points, the file holds "
                                 f"{(end - int(header.offset_to_point_data)) // int(header.point_format.size):,}")
    else:
        _check_laz_chunks(path, header, n)


def _check_laz_chunks(path, header, n: int) -> None:
    """Refuse a LAZ whose header count disagrees with its chunk table: the table lists each chunk's
    points (variable chunks) or holds chunks of a fixed size, only the last one shorter."""
    import lazrs

    vlr = next((v for v in header.vlrs if getattr(v, "record_id", None) == 22204), None)
    if vlr is None:
        return  # laspy reports a LAZ without its laszip record
    with open(path, "rb") as f:
        f.seek(int(header.offset_to_point_data))
        try:
            laz = lazrs.LazVlr(vlr.record_data)
            table = lazrs.read_chunk_table(f, laz)
        except Exception:  # a table that can't be read: laspy says so when it reads the points
            return
    if not table:
        return
    size = int(laz.chunk_size())
    if size == 0xFFFFFFFF:  # variable chunks: the table counts every point
        stored = sum(int(c) for c, _ in table)
        if stored != n:
            raise CloudFileError(f"{path}: the LAS header announces {n:,} points, the LAZ chunk table {stored:,}")
    elif not (len(table) - 1) * size < n <= len(table) * size:
        raise CloudFileError(f"{path}: the LAS header announces {n:,} points, the LAZ chunk table holds "
                             f"{len(table):,} chunks of {size:,}")


def las_scale_offset(lo, hi, path=None, *, xyz=None) -> tuple[np.ndarray, np.ndarray]:
    """Scale and offset of LAS integer coordinates for points in the box [lo, hi].

    The offset is a whole number near the box's centre; the scale (per axis) a power of ten: 1 mm,
    or finer where the points (``xyz``, if given) lie closer together, a tenth of their median
    spacing (:func:`coordinate_scale`), so that rounding moves a point by at most a twentieth of
    it and neighbours stay apart (a millimetre-sized plant in metres, a small part scanned); then
    coarser only as the 32-bit integers must reach both ends of the box (1 mm reaches ±2,147 km).

    Raises
    ------
    CloudFileError
        The box is not finite (``path`` names the file in the message).
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise CloudFileError(f"{path or 'LAS output'}: can't write non-finite coordinates as LAS")
    offset = np.floor((lo + hi) / 2)
    half = np.maximum(hi - offset, offset - lo)
    limit = 2**31 - 2  # one unit of margin for rounding
    finest = 0.001 if xyz is None else coordinate_scale(xyz)
    scales = np.empty(3)
    for axis in range(3):
        scale = finest
        while half[axis] / scale > limit:
            scale *= 10
        scales[axis] = scale
    return scales, offset


def coordinate_scale(xyz: np.ndarray, *, sample: int = 2_000) -> float:
    """The largest power of ten at most a tenth of the median distance from a point of ``xyz``
    to its nearest other point (measured on ``sample`` of them), and at most 1 mm: the LAS
    scale those points need (1 mm for scans whose points lie a centimetre or more apart). Only
    the first :data:`LAS_CHUNK` rows are looked at, as a streamed writer sees its first chunk:
    the same scale either way, and bounded work for large clouds."""
    from ..fields._spacing import kth_neighbour_distance

    xyz = np.asarray(xyz, np.float64)[:LAS_CHUNK]
    if len(xyz) < 2:
        return 0.001
    queries = xyz[np.linspace(0, len(xyz) - 1, min(sample, len(xyz))).astype(np.int64)]
    d = kth_neighbour_distance(xyz, queries, 2)  # the query itself is its first
    d = d[d > 0]
    if not d.size:
        return 0.001
    return float(min(0.001, 10.0 ** math.floor(math.log10(float(np.median(d)) / 10.0))))


def write_las(tmp: Path, xyz, fields, like: Cloud | None, compressed: bool):
    """Write points to ``tmp`` as LAS (LAZ if ``compressed``), ``fields`` as extra dimensions;
    the points of ``like`` (LAS/LAZ input of as many rows, none dropped) keep its every
    dimension, scale and offset, at the coordinates ``xyz`` (moved by an alignment: the offset
    moves too where the scale's 32-bit integers would not reach them), other points get
    :func:`las_scale_offset`."""
    import laspy

    fields = dict(fields)
    if like is not None and like.las is not None and len(like.las.points) == len(xyz) and like.n_dropped == 0:
        # a copy: the caller's cloud keeps its records (no extra dimension of this output added to them)
        las = laspy.LasData(copy.deepcopy(like.las.header), points=like.las.points.copy())
        if not np.array_equal(xyz, like.xyz):  # moved (an alignment): the records at the new coordinates
            lo, hi = xyz.min(axis=0), xyz.max(axis=0)
            reach = (2**31 - 2) * np.asarray(las.header.scales)
            if np.any(np.maximum(hi - las.header.offsets, las.header.offsets - lo) > reach):
                las.header.offsets = np.floor((lo + hi) / 2)
            las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    else:
        standard = _standard_dimensions(fields)  # colour and intensity a non-LAS input carries
        # colour only where there is some: a format without it, rather than zeros that read as black
        header = laspy.LasHeader(point_format=2 if "red" in standard else 0, version="1.4")
        lo, hi = (xyz.min(axis=0), xyz.max(axis=0)) if len(xyz) else (np.zeros(3), np.zeros(3))  # none: a valid file
        header.scales, header.offsets = las_scale_offset(lo, hi, tmp, xyz=xyz)
        las = laspy.LasData(header)
        las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        for name, v in standard.items():
            las[name] = v
    for name, v in fields.items():
        v = np.asarray(v)
        dtype = np.uint8 if v.dtype == bool else (v.dtype if v.dtype.kind in "uif" else np.float64)
        if name not in las.point_format.dimension_names:
            las.add_extra_dim(laspy.ExtraBytesParams(name=name, type=dtype))
        las[name] = v.astype(dtype)
    try:
        las.write(str(tmp), laz_backend=laspy.LazBackend.Lazrs if compressed else None)
    except RuntimeError as exc:  # lazrs's own error: what its writes met (a full disk) is not kept
        if type(exc).__name__ != "LazrsError":
            raise
        raise CloudFileError(f"{tmp}: can't write ({exc}: a full disk or a file-size limit?)") from None
