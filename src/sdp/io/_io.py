"""Reading and writing point clouds and fields, by file extension.

Readers use the field's libraries: pypcd4 (PCD v0.7 ascii / binary / binary_compressed),
plyfile (PLY), laspy with the lazrs backend (LAS/LAZ, scaled integers kept exact), NumPy
(NPY/NPZ, XYZ/TXT/CSV text). Rows whose x, y or z is NaN (sensors' missing returns, e.g. the
organized Kinect PCD files), and points at exactly (0, 0, 0) in organized PCD files (the other
marker of a missing return, e.g. the DLUT laser scans), are dropped and counted; other per-point fields (``label``,
``rgb``, ``intensity``, ``classification``, …) stay aligned with the points kept.

Every reader's library error becomes a one-line :class:`CloudFileError` naming the file
(pydantic's PCD header reports summarized). LAS/LAZ headers are checked first for counts that
cannot fit the file: a corrupt VLR count makes laspy loop for hours, a corrupt chunk-table count
makes lazrs abort the process. ``tests/test_fuzz.py`` feeds cut, bit-flipped and random files of
every format to the readers and to ``sdp change``. :class:`PointSource` reads clouds larger than
memory in row slices, for :mod:`sdp.scale._tiles`.

Outputs: :func:`check_outputs` runs first in every writing command (the folder exists and takes
files; an output is not a directory nor an input, by resolved path or hard link; no two outputs
coincide). Every writer writes through :func:`atomic_path` (a temporary name, renamed), and
:func:`all_or_none` renames all the outputs of a command at its end, or removes them all: a
command writes all its outputs or none, and inputs are never overwritten.
"""

from __future__ import annotations

import os
import tempfile
import warnings
from contextlib import ExitStack, contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .._core._progress import bar
from ..errors import SDPError

__all__ = ["Cloud", "PointSource", "read_points", "write_points", "write_mesh", "CloudFileError", "FORMATS",
           "atomic_path", "check_outputs", "las_scale_offset"]

#: Extension → format name understood by :func:`read_points`.
FORMATS = {".pcd": "pcd", ".ply": "ply", ".las": "las", ".laz": "las", ".xyz": "text", ".txt": "text",
           ".csv": "text", ".pts": "text", ".npy": "npy", ".npz": "npz"}


_LAS_CHUNK = 2_000_000  # points per chunk read (a progress step)
_DEFAULT_VIEWPOINT = np.array([0.0, 0, 0, 1, 0, 0, 0])  # PCL's VIEWPOINT when the sensor pose is unset


class CloudFileError(SDPError, OSError):
    """A point-cloud file can't be read: unknown format, corrupt, empty, or without x/y/z."""


@dataclass
class Cloud:
    """Points read from a file.

    Attributes
    ----------
    xyz : ndarray (n, 3) float64
        World coordinates of the rows kept.
    fields : dict of str to ndarray
        Other per-point fields, aligned with ``xyz``.
    path : Path or None
        The file read.
    n_dropped : int
        Rows left out because x, y or z was NaN or infinite.
    las : object
        The ``laspy.LasData`` of LAS/LAZ input (kept so outputs can keep every dimension),
        else None.
    viewpoint : ndarray (7,) float64 or None
        The sensor's pose from a PCD file's ``VIEWPOINT`` header: translation ``tx ty tz``
        then unit quaternion ``qw qx qy qz`` (PCL writes the grabber's ``sensor_origin_`` and
        ``sensor_orientation_`` there; ``0 0 0 1 0 0 0`` when unset). None for other formats.
    organized : bool
        The file is an organized PCD (HEIGHT > 1: one point per pixel or ray).
    """

    xyz: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    path: Path | None = None
    n_dropped: int = 0
    las: object = None
    viewpoint: np.ndarray | None = None

    organized: bool = False

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def sensor_origin(self) -> np.ndarray | None:
        """Position (3,) of the sensor in the cloud's frame, or None when the file does not say.

        An organized PCD (an image of the sensor's rays) always says: ``viewpoint[:3]``. An
        unorganized PCD says only if its VIEWPOINT is not PCL's default ``0 0 0 1 0 0 0``
        (the header every merged or filtered map carries). Other formats say nothing.
        :func:`sdp.detect_changes` uses it by default (``sensor_origin="auto"``).
        """
        if self.viewpoint is None or not (self.organized or np.any(self.viewpoint != _DEFAULT_VIEWPOINT)):
            return None
        return self.viewpoint[:3].copy()

    def transformed(self, matrix: np.ndarray) -> "Cloud":
        """The cloud moved by a rigid 4×4 ``matrix`` (e.g. :attr:`sdp.Alignment.matrix`), its
        sensor pose with it; fields, path and counts unchanged."""
        from scipy.spatial.transform import Rotation

        m = np.asarray(matrix, dtype=np.float64)
        xyz = self.xyz @ m[:3, :3].T + m[:3, 3]
        viewpoint = None
        if self.viewpoint is not None:
            q = self.viewpoint[3:]  # qw qx qy qz
            turned = Rotation.from_matrix(m[:3, :3]) * Rotation.from_quat([q[1], q[2], q[3], q[0]])
            x, y, z, w = turned.as_quat()
            viewpoint = np.r_[m[:3, :3] @ self.viewpoint[:3] + m[:3, 3], w, x, y, z]
        return replace(self, xyz=np.ascontiguousarray(xyz), viewpoint=viewpoint)


def read_points(path: str | os.PathLike, *, format: str | None = None) -> Cloud:
    """Read a point cloud; the format comes from the extension unless ``format`` is given.

    Parameters
    ----------
    path : path-like
        A ``.pcd``, ``.ply``, ``.las``/``.laz``, ``.xyz``/``.txt``/``.csv``/``.pts``, ``.npy``
        or ``.npz`` file (NPZ: arrays ``xyz``, or ``x``, ``y``, ``z``).
    format : {"pcd", "ply", "las", "text", "npy", "npz"}, optional
        Override the extension.

    Raises
    ------
    CloudFileError
        Unknown format, missing file, unreadable content, no x/y/z, or no finite point.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> import sdp
    >>> folder = tempfile.TemporaryDirectory()
    >>> xyz = np.random.default_rng(0).random((100, 3))
    >>> path = sdp.write_points(Path(folder.name) / "cloud.ply", xyz, {"high": xyz[:, 2] > 0.5})
    >>> cloud = sdp.read_points(path)
    >>> bool(np.array_equal(cloud.xyz, xyz)), sorted(cloud.fields), cloud.n_dropped
    (True, ['high'], 0)
    >>> folder.cleanup()
    """
    path = Path(path)
    fmt = _input_format(path, format)
    try:
        xyz, fields, las, *pose = _READERS[fmt](path)  # PCD adds its VIEWPOINT and whether organized
    except CloudFileError:
        raise
    except MemoryError:
        raise CloudFileError(f"{path}: too large to read into memory as {fmt}") from None
    except BaseException as exc:  # libraries raise many types on corrupt input (lazrs: Rust panics)
        if not _library_error(exc):
            raise
        raise _unreadable(path, fmt, exc) from None
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise CloudFileError(f"{path}: expected x, y, z columns, got an array of shape {xyz.shape}")
    finite = np.isfinite(xyz).all(axis=1)
    dropped = int((~finite).sum())
    if dropped:
        xyz = xyz[finite]
        fields = {k: v[finite] for k, v in fields.items()}
    if len(xyz) == 0:
        raise CloudFileError(f"{path}: holds no point with finite x, y, z")
    viewpoint, organized = pose if pose else (None, False)
    return Cloud(np.ascontiguousarray(xyz), fields, path, dropped, las, viewpoint, organized)


def _input_format(path: Path, format: str | None) -> str:
    """The reader's format name for ``path`` (``format`` overrides the extension), once ``path``
    is known to be an existing file; else :class:`CloudFileError` saying what is wrong."""
    names = sorted(set(FORMATS.values()))
    if format is not None:
        if format not in names:
            raise CloudFileError(f"unknown format {format!r}; use one of {', '.join(names)}")
        fmt = format
    else:
        fmt = FORMATS.get(path.suffix.lower())
        if fmt is None:
            raise CloudFileError(f"{path}: unknown point-cloud format {path.suffix or '(no extension)'!r}; use one "
                                 f"of the extensions {', '.join(sorted(FORMATS))} or give the format "
                                 f"({', '.join(names)})")
    if path.is_dir():
        raise CloudFileError(f"{path}: is a directory, not a point-cloud file")
    if not path.exists():
        raise CloudFileError(f"{path}: no such file")
    if not path.is_file():
        raise CloudFileError(f"{path}: not a regular file")
    if not os.access(path, os.R_OK):
        raise CloudFileError(f"{path}: permission denied")
    return fmt


def _one_line(exc: BaseException, limit: int = 200) -> str:
    """A library exception in one line: pydantic's validation errors summarized (pypcd4's PCD
    headers), other messages cut at their first line and at ``limit`` characters."""
    errors = getattr(exc, "errors", None)
    if callable(errors):
        try:
            items = errors()
            parts = [f"{' '.join(str(x) for x in e.get('loc', ())).upper() or 'header'}: {e.get('msg', '')}"
                     for e in items[:3]]
            text = "; ".join(parts) + (f" (and {len(items) - 3} more)" if len(items) > 3 else "")
            return f"header {text}" if text else type(exc).__name__
        except Exception:  # not pydantic after all
            pass
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    text = lines[0] if lines else type(exc).__name__
    return text if len(text) <= limit else text[:limit - 1] + "…"


def _library_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a reader library's failure on bad content: any ``Exception``, or a Rust
    panic surfaced by pyo3 (``PanicException`` derives from ``BaseException``), but never
    Ctrl-C, ``SystemExit`` or a closed generator."""
    return isinstance(exc, Exception) or type(exc).__name__ == "PanicException"


def _unreadable(path, fmt: str, exc: BaseException) -> "CloudFileError":
    """The CloudFileError of a library exception raised while reading ``path``."""
    return CloudFileError(f"{path}: can't read as {fmt} ({type(exc).__name__}: {_one_line(exc)})")


def _read_pcd(path):
    from pypcd4 import PointCloud

    pc = PointCloud.from_path(path)
    names = list(pc.fields)
    if not {"x", "y", "z"} <= set(names):
        raise CloudFileError(f"{path}: PCD fields {names} have no x, y, z")
    data = pc.numpy()
    cols = {n: data[:, i] for i, n in enumerate(names)}
    fields = {n: _pcd_column(pc, n, cols[n]) for n in names if n not in ("x", "y", "z")}
    xyz = np.c_[cols["x"], cols["y"], cols["z"]]
    if pc.metadata.height > 1:  # organized scans mark a missing return by NaN or by (0, 0, 0)
        xyz[~xyz.any(axis=1)] = np.nan
    viewpoint = np.asarray(pc.metadata.viewpoint, dtype=np.float64)
    if viewpoint.shape != (7,) or not np.isfinite(viewpoint).all():
        raise CloudFileError(f"{path}: VIEWPOINT must be 7 finite numbers (tx ty tz qw qx qy qz), "
                             f"got {pc.metadata.viewpoint}")
    return xyz, fields, None, viewpoint, pc.metadata.height > 1


def _pcd_column(pc, name, col):
    """pypcd4 returns a float64 matrix; give each field back its declared type (labels, rgba)."""
    dtype = np.dtype(pc.types[list(pc.fields).index(name)])
    return col.astype(dtype) if dtype.kind in "ui" else col


def _read_ply(path):
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    if "vertex" not in ply:
        raise CloudFileError(f"{path}: PLY file has no vertex element")
    v = ply["vertex"].data
    names = v.dtype.names or ()
    if not {"x", "y", "z"} <= set(names):
        raise CloudFileError(f"{path}: PLY vertices have no x, y, z (properties: {list(names)})")
    fields = {n: np.asarray(v[n]) for n in names if n not in ("x", "y", "z")}
    return np.c_[v["x"], v["y"], v["z"]], fields, None


def _read_las(path):
    import laspy

    _check_las_counts(path)
    with laspy.open(str(path)) as reader, bar(reader.header.point_count, f"reading {Path(path).name}") as pb:
        _check_las(path, reader.header)
        chunks = []
        for chunk in reader.chunk_iterator(_LAS_CHUNK):
            chunks.append(chunk.array)
            pb.update(len(chunk))
        h = reader.header
        records = np.concatenate(chunks) if chunks else np.zeros(0, h.point_format.dtype())
        las = laspy.LasData(h, points=laspy.ScaleAwarePointRecord(records, h.point_format, h.scales, h.offsets))
    xyz = np.c_[las.x, las.y, las.z]  # scaled and offset, float64: large coordinates stay exact
    fields = {d: np.asarray(las[d]) for d in las.point_format.dimension_names if d not in ("X", "Y", "Z")}
    return xyz, fields, las


def _check_las_counts(path) -> None:
    """Refuse a LAS/LAZ whose header counts more (extended) VLRs than the file can hold, before laspy
    reads it: laspy loops over the count, and a corrupt 32-bit count makes that loop run for hours.
    Reads the public header block's fixed fields only (ASPRS LAS 1.0–1.4)."""
    import struct

    size = Path(path).stat().st_size
    with open(path, "rb") as f:
        head = f.read(247)
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
    if head[24:26] == b"\x01\x04" and len(head) >= 247:  # LAS 1.4: extended VLRs at the end
        start, n_evlrs = struct.unpack_from("<QI", head, 235)
        if n_evlrs and (start > size or 60 * n_evlrs > size):
            raise CloudFileError(f"{path}: corrupt LAS header: {n_evlrs:,} extended records do not fit in a file "
                                 f"of {size:,} bytes")


def _check_las(path, header) -> None:
    """Refuse a LAS/LAZ file without points, or an uncompressed LAS shorter than its header says."""
    n = int(header.point_count)
    if n == 0:
        raise CloudFileError(f"{path}: holds no point (its LAS header counts 0)")
    if not header.are_points_compressed:
        need = int(header.offset_to_point_data) + n * int(header.point_format.size)
        have = Path(path).stat().st_size
        if have < need:
            raise CloudFileError(f"{path}: truncated: the LAS header announces {n:,} points ({need:,} bytes) but the "
                                 f"file holds {have:,} bytes")


def _read_text(path):
    with open(path, encoding="utf-8", errors="replace") as fh:
        sample = fh.read(4096)
    if not sample.strip():
        raise CloudFileError(f"{path}: the file is empty: no point to read")
    delimiter = "," if "," in sample else None
    first = sample.splitlines()[0] if sample else ""
    skip = 0 if _is_numeric_row(first, delimiter) else 1
    with warnings.catch_warnings():  # a header without rows: said below, not as a warning
        warnings.simplefilter("ignore", UserWarning)
        arr = np.loadtxt(path, delimiter=delimiter, skiprows=skip, ndmin=2)
    if arr.size == 0:
        raise CloudFileError(f"{path}: holds a header but no point")
    if arr.shape[1] < 3:
        raise CloudFileError(f"{path}: expected at least 3 columns (x y z), found {arr.shape[1]}")
    names = [n.strip().lower() for n in first.replace(",", " ").split()] if skip else []
    fields = {(names[i] if i < len(names) else f"column{i}"): arr[:, i] for i in range(3, arr.shape[1])}
    return arr[:, :3], fields, None


def _is_numeric_row(line: str, delimiter) -> bool:
    try:
        [float(x) for x in line.split(delimiter) if x.strip()]
        return bool(line.strip())
    except ValueError:
        return False


def _read_npy(path):
    return np.load(path, allow_pickle=False), {}, None


def _read_npz(path):
    with np.load(path, allow_pickle=False) as z:
        if "xyz" in z:
            xyz = z["xyz"]
        elif {"x", "y", "z"} <= set(z.files):
            xyz = np.c_[z["x"], z["y"], z["z"]]
        else:
            raise CloudFileError(f"{path}: NPZ needs an array 'xyz' or arrays 'x', 'y', 'z' (has {z.files})")
        fields = {k: z[k] for k in z.files if k not in ("xyz", "x", "y", "z") and len(z[k]) == len(xyz)}
    return xyz, fields, None


_READERS = {"pcd": _read_pcd, "ply": _read_ply, "las": _read_las, "text": _read_text, "npy": _read_npy,
            "npz": _read_npz}


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _same_file(a: Path, b: Path) -> bool:
    """Whether two paths name one file (the same resolved path, or a hard link / bind mount)."""
    try:
        if a.resolve() == b.resolve():
            return True
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def check_outputs(outputs, inputs=()) -> None:
    """Refuse, before any work, outputs that can't be written or would overwrite an input.

    Each output's folder must exist and take new files (tried with a temporary file, so
    read-only mounts and ``/sys`` are caught), the output must not be an existing directory
    (except a ``.zarr`` field store, which is one), must not be one of ``inputs`` (resolved
    paths, hard links too), and no two outputs may be the same file.

    Parameters
    ----------
    outputs : iterable of path-like or None
        Files the command will write (None entries, options not given, are skipped).
    inputs : iterable of path-like
        Files the command reads.

    Raises
    ------
    SDPError
        With a one-line message naming the output and what is wrong.
    """
    seen: list[Path] = []
    ins = [Path(p) for p in inputs if p is not None]
    for out in outputs:
        if out is None:
            continue
        path = Path(out)
        if str(out) == "" or path.name in ("", ".", ".."):
            raise SDPError(f"{str(out)!r}: not a file name for an output")
        parent = path.parent
        if not parent.exists():
            raise SDPError(f"{path}: folder {str(parent)!r} does not exist; create it first")
        if not parent.is_dir():
            raise SDPError(f"{path}: {str(parent)!r} is not a folder")
        if path.is_dir() and not (path.suffix.lower() == ".zarr" and (path / "zarr.json").is_file()):
            raise SDPError(f"{path}: is an existing directory; choose a file name for the output")
        for src in ins:
            if _same_file(path, src):
                raise SDPError(f"{path}: refusing to overwrite an input file; choose another output name")
        for other in seen:
            if _same_file(path, other):
                raise SDPError(f"{path}: given for two outputs; choose a different name for each")
        try:
            fd, probe = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".probe", dir=parent)
        except OSError as exc:
            raise SDPError(f"{path}: can't create files in {str(parent)!r} ({exc.strerror or exc})") from None
        os.close(fd)
        os.unlink(probe)
        if path.exists() and not path.is_dir() and not os.access(path, os.W_OK):
            raise SDPError(f"{path}: exists and is not writable")
        seen.append(path)


def refuse_overwrite(path: str | os.PathLike, inputs=()) -> None:
    """Raise :class:`SDPError` if ``path`` is one of the files ``inputs``."""
    path = Path(path)
    for src in inputs:
        if src is not None and path.exists() and _same_file(path, Path(src)):
            raise SDPError(f"{path}: refusing to overwrite an input file; choose another output name")


_PENDING: ContextVar[list | None] = ContextVar("sdp_pending_outputs", default=None)


@contextmanager
def all_or_none():
    """Within the block, every :func:`atomic_path` (every writer of sdp) keeps its finished file
    under its temporary name; they are all renamed when the block succeeds, all removed when it
    fails: a command writes all its outputs or none (``sdp`` runs each command inside one)."""
    pending: list[tuple[str, Path]] = []
    token = _PENDING.set(pending)
    try:
        yield
        for tmp, path in pending:
            os.replace(tmp, path)
    finally:
        _PENDING.reset(token)
        for tmp, _ in pending:
            Path(tmp).unlink(missing_ok=True)


@contextmanager
def atomic_path(path: str | os.PathLike, *, inputs=()):
    """Yield a temporary path beside ``path``; rename it to ``path`` when the block succeeds
    (inside :func:`all_or_none`: when that block does).

    Refuses to overwrite any of ``inputs``; nothing is left behind on failure.
    """
    path = Path(path)
    refuse_overwrite(path, inputs)
    if path.is_dir():
        raise SDPError(f"{path}: is an existing directory; choose a file name for the output")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    except OSError as exc:
        raise SDPError(f"{path}: can't create files in {str(path.parent)!r} ({exc.strerror or exc})") from None
    pending, deferred = _PENDING.get(), False
    try:
        os.close(fd)
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp made it private; give it a new file's mode
        if pending is not None:
            pending.append((tmp, path))
            deferred = True
        else:
            os.replace(tmp, path)
    finally:
        if not deferred:
            Path(tmp).unlink(missing_ok=True)


def write_points(path: str | os.PathLike, xyz: np.ndarray, fields: dict[str, np.ndarray] | None = None, *,
                 like: Cloud | None = None, inputs=()) -> Path:
    """Write points with per-point scalar fields as PLY, LAS/LAZ or NPZ (by extension).

    LAS/LAZ output made from LAS/LAZ input (``like``) keeps every input dimension, scale and
    offset, and adds ``fields`` as extra dimensions; other LAS output gets a 1 mm scale (coarser
    only for clouds wider than ±2,147 km: :func:`las_scale_offset`) and an offset at the cloud's
    centre, so large coordinates stay exact. The file is written
    under a temporary name and renamed; ``inputs`` are never overwritten.

    Examples
    --------
    >>> import tempfile
    >>> from pathlib import Path
    >>> import numpy as np
    >>> import sdp
    >>> folder = tempfile.TemporaryDirectory()
    >>> xyz = np.random.default_rng(0).random((1000, 3)) * 100 + [500_000, 4_000_000, 0]  # UTM-like
    >>> path = sdp.write_points(Path(folder.name) / "labelled.laz", xyz, {"change": np.ones(1000, np.uint8)})
    >>> cloud = sdp.read_points(path)  # LAS keeps 1 mm: coordinates within half of it
    >>> bool(np.abs(cloud.xyz - xyz).max() <= 0.0005), int(cloud.fields["change"].sum())
    (True, 1000)
    >>> folder.cleanup()
    """
    path = Path(path)
    fields = dict(fields or {})
    ext = path.suffix.lower()
    if ext not in (".ply", ".las", ".laz", ".npz"):
        raise CloudFileError(f"{path}: can't write {ext or 'files without extension'}; use .ply, .las, .laz or .npz")
    with atomic_path(path, inputs=inputs) as tmp:
        if ext == ".ply":
            from plyfile import PlyData, PlyElement

            cols = [("x", xyz[:, 0]), ("y", xyz[:, 1]), ("z", xyz[:, 2])] + list(fields.items())
            arr = np.empty(len(xyz), dtype=[(n, _ply_type(v)) for n, v in cols])
            for n, v in cols:
                arr[n] = v
            PlyData([PlyElement.describe(arr, "vertex")]).write(str(tmp))
        elif ext == ".npz":
            np.savez_compressed(tmp, xyz=xyz, **fields)
        else:
            _write_las(tmp, xyz, fields, like, compressed=ext == ".laz")
    return path


def _ply_type(v: np.ndarray) -> str:
    v = np.asarray(v)
    if v.dtype == bool:
        return "u1"
    return v.dtype.str.lstrip("<>=|") if v.dtype.kind in "uif" else "f8"


def las_scale_offset(lo, hi, path=None) -> tuple[np.ndarray, np.ndarray]:
    """Scale and offset of LAS integer coordinates for points in the box [lo, hi].

    The offset is a whole number near the box's centre; the scale (per axis) the finest of
    0.001, 0.01, 0.1, 1, … whose 32-bit integers reach both ends of the box (so 1 mm unless
    the cloud spans more than ±2,147 km).

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
    scales = np.empty(3)
    for axis in range(3):
        scale = 0.001
        while half[axis] / scale > limit:
            scale *= 10
        scales[axis] = scale
    return scales, offset


def _write_las(tmp: Path, xyz, fields, like: Cloud | None, compressed: bool):
    import laspy

    if like is not None and like.las is not None and len(like.las.points) == len(xyz) and like.n_dropped == 0:
        las = like.las
    else:
        header = laspy.LasHeader(point_format=3, version="1.4")
        header.scales, header.offsets = las_scale_offset(xyz.min(axis=0), xyz.max(axis=0), tmp)
        las = laspy.LasData(header)
        las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for name, v in fields.items():
        v = np.asarray(v)
        dtype = np.uint8 if v.dtype == bool else (v.dtype if v.dtype.kind in "uif" else np.float64)
        if name not in las.point_format.dimension_names:
            las.add_extra_dim(laspy.ExtraBytesParams(name=name, type=dtype))
        las[name] = v.astype(dtype)
    las.write(str(tmp), laz_backend=laspy.LazBackend.Lazrs if compressed else None)


def write_mesh(path: str | os.PathLike, mesh, *, inputs=()) -> Path:
    """Write a :class:`sdp.Mesh` as PLY, OBJ or STL (by extension), atomically."""
    path = Path(path)
    ext = path.suffix.lower()
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    if ext not in (".ply", ".obj", ".stl"):
        raise CloudFileError(f"{path}: can't write a mesh as {ext or 'no extension'}; use .ply, .obj or .stl")
    with atomic_path(path, inputs=inputs) as tmp:
        if ext == ".ply":
            from plyfile import PlyData, PlyElement

            verts = np.rec.fromarrays(v.T, names="x,y,z")
            faces = np.empty(len(f), dtype=[("vertex_indices", "i4", (3,))])
            faces["vertex_indices"] = f
            PlyData([PlyElement.describe(verts, "vertex"), PlyElement.describe(faces, "face")]).write(str(tmp))
        elif ext == ".obj":
            with open(tmp, "w") as fh:
                np.savetxt(fh, v, fmt="v %.9g %.9g %.9g")
                np.savetxt(fh, f + 1, fmt="f %d %d %d")
        else:
            tri = v[f]
            normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
            rec = np.zeros(len(f), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
            rec["n"], rec["v"] = normals, tri
            with open(tmp, "wb") as fh:
                fh.write(b"sdp mesh".ljust(80, b" "))
                fh.write(np.uint32(len(f)).tobytes())
                fh.write(rec.tobytes())
    return path


# ---------------------------------------------------------------------------- streaming input
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
             chunk_size: int = _LAS_CHUNK) -> "PointSource":
        """Inspect ``path`` (header, or one pass for the bounds) without keeping its points."""
        path = Path(path)
        fmt = _input_format(path, format)
        try:
            if fmt == "las":
                import laspy

                _check_las_counts(path)
                with laspy.open(str(path)) as r:
                    h = r.header
                    _check_las(path, h)
                    lo, hi = np.asarray(h.mins, float), np.asarray(h.maxs, float)
                    if not (np.isfinite(lo).all() and np.isfinite(hi).all() and (lo <= hi).all()):
                        raise CloudFileError(f"{path}: the LAS header's bounds {lo.tolist()} … {hi.tolist()} are "
                                             "not a box")
                    if h.are_points_compressed:  # decode the first points: a cut-off LAZ fails here
                        r.read_points(1)
                    return cls(path, fmt, int(h.point_count), tuple(map(float, lo)), tuple(map(float, hi)))
            if fmt == "ply" and _ply_is_binary(path):
                v = _ply_vertices(path)
                if not {"x", "y", "z"} <= set(v.dtype.names):
                    raise CloudFileError(f"{path}: PLY vertices have no x, y, z (properties: {v.dtype.names})")
                n = len(v)
            elif fmt == "npy":
                a = np.load(path, mmap_mode="r", allow_pickle=False)
                if a.ndim != 2 or a.shape[1] != 3:
                    raise CloudFileError(f"{path}: expected an (n, 3) array, got shape {a.shape}")
                n = len(a)
            else:  # can't slice: read it once, spill the finite points to .npy
                if spill_dir is None:
                    raise CloudFileError(f"{path}: {fmt} files can't be read in slices; convert to LAS/LAZ, NPY or "
                                         "binary PLY (or, in Python, give spill_dir=)")
                fd, tmp = tempfile.mkstemp(suffix=".npy", dir=spill_dir)
                os.close(fd)
                np.save(tmp, read_points(path, format=fmt).xyz)
                return cls.open(tmp, format="npy", chunk_size=chunk_size)
        except CloudFileError:
            raise
        except BaseException as exc:  # libraries raise many types on corrupt input (lazrs: Rust panics)
            if not _library_error(exc):
                raise
            raise _unreadable(path, fmt, exc) from None
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
        v = _ply_vertices(self.path)[start:stop]
        return np.c_[v["x"], v["y"], v["z"]].astype(np.float64)

    def chunks(self, size: int = _LAS_CHUNK, start: int = 0, stop: int | None = None):
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

            with laspy.open(str(self.path)) as r:
                scale, offset = np.asarray(r.header.scales, float), np.asarray(r.header.offsets, float)
                r.seek(start)
                for s in range(start, stop, size):
                    pts = r.read_points(min(size, stop - s))
                    yield s, scaled_xyz(pts.X, pts.Y, pts.Z, scale, offset)
            return
        for s in range(start, stop, size):
            yield s, self.read(s, min(s + size, stop))


def _ply_vertices(path):
    from plyfile import PlyData

    return PlyData.read(str(path), mmap=True)["vertex"].data


def _ply_is_binary(path) -> bool:
    with open(path, "rb") as f:
        head = f.read(200).split(b"\n")
    return any(line.startswith(b"format binary") for line in head)


_END = object()


@contextmanager
def _decoding(source: PointSource):
    """Turn the reader libraries' exceptions in the block into :class:`CloudFileError` naming the file."""
    try:
        yield
    except CloudFileError:
        raise
    except BaseException as exc:  # libraries raise many types on corrupt input (lazrs: Rust panics)
        if not _library_error(exc):
            raise
        raise _unreadable(source.path, source.format, exc) from None


def _decoded(source: PointSource, iterator):
    """``iterator``'s items, read under :func:`_decoding`."""
    while True:
        with _decoding(source):
            item = next(iterator, _END)
        if item is _END:
            return
        yield item


def write_points_streamed(path: str | os.PathLike, source: PointSource, fields_of, *, inputs=(),
                          chunk_size: int = _LAS_CHUNK) -> Path:
    """Write every row of ``source`` with extra per-point fields, chunk by chunk, as LAS/LAZ.

    ``fields_of(start, stop)`` returns the fields of rows ``start`` … ``stop − 1`` (a dict of
    arrays). LAS/LAZ input keeps every dimension, VLR, scale and offset; other input gets the
    scale and offset of :func:`las_scale_offset` (1 mm, offset at the centre). Memory is bounded
    by ``chunk_size``; the file is written under a temporary name and renamed, and ``inputs``
    are never overwritten. LAZ is decoded and encoded on all cores (lazrs' parallel backend).
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
            chunks = ((len(c), c) for c in _decoded(source, reader.chunk_iterator(chunk_size)))
        else:
            header = laspy.LasHeader(point_format=3, version="1.4")
            header.scales, header.offsets = las_scale_offset(source.lo, source.hi, path)
            chunks = ((len(xyz), xyz) for _, xyz in source.chunks(chunk_size))
        tmp = stack.enter_context(atomic_path(path, inputs=inputs))
        writer, start = None, 0
        for n, chunk in chunks:
            fields = fields_of(start, start + n)
            if writer is None:
                for name, v in fields.items():
                    if name not in header.point_format.dimension_names:
                        header.add_extra_dim(laspy.ExtraBytesParams(name=name, type=np.asarray(v).dtype))
                writer = stack.enter_context(laspy.open(str(tmp), mode="w", header=header,
                                                        do_compress=path.suffix.lower() == ".laz",
                                                        laz_backend=laspy.LazBackend.LazrsParallel))
            out = laspy.ScaleAwarePointRecord.zeros(n, header=header)
            if source.format == "las":
                for name in chunk.array.dtype.names:
                    out.array[name] = chunk.array[name]
            else:  # LAS can't hold NaN rows: they are left out
                ok = np.isfinite(chunk).all(axis=1)
                out = out[ok] if not ok.all() else out
                out.x, out.y, out.z = chunk[ok, 0], chunk[ok, 1], chunk[ok, 2]
                fields = {name: np.asarray(v)[ok] for name, v in fields.items()}
            for name, v in fields.items():
                out[name] = v
            writer.write_points(out)
            start += n
    return path
