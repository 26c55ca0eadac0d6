"""Writing outputs: all of a command's or none, never over an input.

:func:`check_outputs` runs first in every writing command (the folder exists and takes files;
an output is not a directory nor an input, by resolved path or hard link; no two outputs
coincide). Every writer writes through :func:`atomic_path` (a temporary name, renamed), and
:func:`all_or_none` renames all the outputs of a command at its end, or removes them all: a
command writes all its outputs or none, and inputs are never overwritten. :func:`write_points`
and :func:`write_mesh` pick the format's writer by file extension.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import tempfile
import threading
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

import numpy as np

from ..errors import InvalidPointsError, SDPError
from ._cloud import Cloud, CloudFileError
from ._las import write_las
from ._numpy import write_npz
from ._ply import write_ply, write_ply_mesh

__all__ = ["WRITTEN_AS", "check_format", "check_outputs", "refuse_overwrite", "all_or_none", "atomic_path",
           "new_folder",
           "write_points", "write_mesh"]


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


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
            advice = (" and not a series archive; choose another output name" if path.suffix.lower() == ".zarr"
                      else "; choose a file name for the output")
            raise SDPError(f"{path}: is an existing directory{advice}")
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


#: The extensions each kind of output is written as, by its writer: :func:`write_points`,
#: :func:`write_mesh`, a density field (:meth:`sdp.DensityField.save`, or a field store in tiles).
WRITTEN_AS = {"points": (".ply", ".las", ".laz", ".npz"), "mesh": (".ply", ".obj", ".stl"), "field": (".sdpf", ".zarr")}
_WHAT = {"points": "points", "mesh": "a mesh", "field": "a density field"}


def check_format(path: str | os.PathLike | None, *kinds: str) -> None:
    """Refuse an output whose extension no writer of ``kinds`` (keys of :data:`WRITTEN_AS`) writes:
    before any work, so that a command does not compute and then fail to write (None: not given).

    Raises
    ------
    CloudFileError
        One line naming the output and the extensions that do.
    """
    if path is None:
        return
    ext = Path(path).suffix.lower()
    allowed = [x for kind in kinds for x in WRITTEN_AS[kind]]
    if ext not in allowed:
        allowed = list(dict.fromkeys(allowed))
        raise CloudFileError(f"{path}: can't write {' or '.join(_WHAT[k] for k in kinds)} as "
                             f"{ext or 'a file without extension'}; use {', '.join(allowed[:-1])} or {allowed[-1]}")


def refuse_overwrite(path: str | os.PathLike, inputs=()) -> None:
    """Raise :class:`SDPError` if ``path`` is one of the files ``inputs``."""
    path = Path(path)
    for src in inputs:
        if src is not None and path.exists() and _same_file(path, Path(src)):
            raise SDPError(f"{path}: refusing to overwrite an input file; choose another output name")


_PENDING: ContextVar[list | None] = ContextVar("sdp_pending_outputs", default=None)
#: What to undo when the command fails (:func:`new_folder`), after its temporary files are removed.
_UNDO: ContextVar[list | None] = ContextVar("sdp_undo_outputs", default=None)
#: What the outermost :func:`all_or_none` calls once its outputs are committed.
_ON_COMMIT: ContextVar = ContextVar("sdp_on_commit", default=None)


_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: Commits under way in the main thread, and what a signal handler left to do after them (:func:`defer`).
_committing = 0
_deferred: list = []


def defer(action) -> bool:
    """For a program's signal handler: if a commit is under way, keep ``action`` to run when it is
    over (if it succeeds) and return True; else False. Masking the signals holds them back only
    from the main thread: the system may hand a process's signal to another thread (Zarr's event
    loop, a thread pool), and Python then runs the handler in the main thread all the same, in the
    middle of the renames."""
    if _committing and _main_thread():
        _deferred.append(action)
        return True
    return False


@contextmanager
def _held():
    """Ctrl-C and SIGTERM held back for the block (in the main thread; elsewhere a no-op); what a
    handler deferred meanwhile (:func:`defer`) runs after it."""
    global _committing
    if not _main_thread():
        yield
        return
    held = signal.pthread_sigmask(signal.SIG_BLOCK, _SIGNALS)
    _committing += 1
    try:
        yield
    finally:
        _committing -= 1
        signal.pthread_sigmask(signal.SIG_SETMASK, held)
        actions = [] if _committing else _deferred[:]
        if not _committing:
            _deferred.clear()
    for action in actions:
        action()


@contextmanager
def all_or_none(*, on_commit=None, stop=None, own: bool = False):
    """Within the block, every :func:`atomic_path` (every writer of sdp) keeps its finished file
    under its temporary name; they are all renamed when the block succeeds, all removed when it
    fails: a command writes all its outputs or none (``sdp`` runs each command inside one).

    Nested in another, the block hands its files to the outer one: a function that writes its
    outputs as one (:func:`sdp.compare_files`) commits nothing before the command around it has
    also printed its summary (stdout on a full disk fails the command, and nothing is written).
    ``own=True`` commits the block's files at its own end all the same (steps whose files the
    next step reads, as in ``sdp warmup``).

    The renames run with Ctrl-C and SIGTERM held back (:func:`defer`), then ``on_commit()``:
    a signal arriving meanwhile is delivered after both, when the command is complete, and the
    program can tell it came too late to stop anything. ``stop()``, called first, raises if the
    command is to stop rather than commit: a signal came whose exception a library swallowed (a
    destructor's, a callback's, reported as "Exception ignored") while the command went on."""
    if _PENDING.get() is not None and not own:
        yield
        return
    pending: list[tuple[str, Path]] = []
    undo: list = []
    token, hook, undo_token = _PENDING.set(pending), _ON_COMMIT.set(on_commit), _UNDO.set(undo)
    committed = False
    try:
        yield
        with _held():
            if stop is not None:
                stop()
            for tmp, path in pending:
                os.replace(tmp, path)
            committed = True
            if on_commit is not None:
                on_commit()
    finally:
        _PENDING.reset(token)
        _ON_COMMIT.reset(hook)
        _UNDO.reset(undo_token)
        for tmp, _ in pending:
            Path(tmp).unlink(missing_ok=True)
        for step in () if committed else reversed(undo):
            step()


@contextmanager
def new_folder(path: str | os.PathLike):
    """Make the folder ``path`` (and its missing parents) for a command's outputs; the folders
    made are removed again, when empty, if the block fails or, inside :func:`all_or_none`, if
    the command does (after its temporary files are gone)."""
    path = Path(path)
    made = [p for p in (path, *path.parents) if not p.exists()]  # innermost first
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SDPError(f"{path}: can't create the folder ({exc.strerror or exc})") from None

    def remove():
        for folder in made:
            with contextlib.suppress(OSError):  # not empty: something else wrote there meanwhile
                folder.rmdir()

    undo = _UNDO.get()
    if undo is not None:
        undo.append(remove)
    try:
        yield path
    except BaseException:
        if undo is None:
            remove()
        raise


@contextmanager
def commit_point():
    """The block is a commit that cannot wait for the end of the command (a series archive's,
    swapped in or its journal dropped before the summary is printed): it runs with Ctrl-C and
    SIGTERM held back, then tells the command around it (:func:`all_or_none`'s ``on_commit``)
    that its output is committed, so that a signal from then on comes too late to stop anything
    rather than reporting as not written what was."""
    with _held():
        yield
        hook = _ON_COMMIT.get()
        if hook is not None:
            hook()


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
        # the suffix in lower case, as the writers match it (a library choosing by extension, or
        # completing one, sees the format's usual name)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix.lower(), dir=path.parent)
    except OSError as exc:
        raise SDPError(f"{path}: can't create files in {str(path.parent)!r} ({exc.strerror or exc})") from None
    pending, deferred = _PENDING.get(), False
    try:
        os.close(fd)
        try:
            yield Path(tmp)
        except SDPError as exc:  # a writer's message may name the temporary file: name the output
            raise type(exc)(str(exc).replace(str(tmp), str(path))) from None
        except OSError as exc:  # a full disk, a quota: said of the output, not of its temporary name
            raise SDPError(f"{path}: can't write ({exc.strerror or exc})") from None
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

    ``xyz``: (n, 3) points, or a :class:`~sdp.Cloud` (its points, and ``like`` itself).
    ``like``: the cloud the points are (as many rows, in order): its dimensions are kept, and
    ``fields`` added (they win on a name). LAS/LAZ output made from LAS/LAZ input keeps every
    input dimension, scale and offset; from other input, its per-point fields (an E57's colour,
    intensity, row and column; a PCD's label) become LAS colour and intensity where they are
    those, else extra dimensions, and no colour is written where there was none. Other LAS
    output gets a scale of 1 mm, finer where the points lie closer than a centimetre apart (a
    tenth of their median spacing), coarser only for clouds wider than ±2,147 km
    (:func:`~sdp.io._las.las_scale_offset`), and an offset at the cloud's centre, so large
    coordinates stay exact. The file is written under a temporary name and renamed; ``inputs``
    are never overwritten.

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
    ext = path.suffix.lower()
    check_format(path, "points")
    if isinstance(xyz, Cloud):  # a cloud as read: its points, with its dimensions
        like = xyz if like is None else like
        xyz = xyz.xyz
    if fields is not None and not isinstance(fields, dict):
        raise InvalidPointsError(f"{path}: fields must be a dict of name to per-point values, got "
                                 f"{type(fields).__name__}")
    xyz, fields = _checked_points(path, xyz, fields)
    if like is not None and (not isinstance(like, Cloud) or len(like.xyz) != len(xyz)):
        raise InvalidPointsError(f"{path}: like= is the Cloud these points are, row for row "
                                 f"({len(xyz):,} points), got {type(like).__name__}"
                                 + (f" of {len(like.xyz):,}" if isinstance(like, Cloud) else ""))
    if like is not None and like.fields and (like.las is None or ext not in (".las", ".laz")):  # LAS: its records
        kept = {k: v for k, v in like.fields.items() if len(v) == len(xyz) and k not in fields}
        if kept:
            fields = {**_checked_points(path, xyz, kept)[1], **fields}
    with atomic_path(path, inputs=inputs) as tmp:
        if ext == ".ply":
            write_ply(tmp, xyz, fields)
        elif ext == ".npz":
            write_npz(tmp, xyz, fields)
        else:
            write_las(tmp, xyz, fields, like, compressed=ext == ".laz")
    return path


_PLY_NAME = re.compile(r"\S+\Z")
_LAS_NAME_BYTES = 32  # an extra-bytes record's name field (ASPRS LAS 1.4, table 24)


def _checked_points(path: Path, xyz, fields) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """``xyz`` as (n, 3) float64 and ``fields`` as 1-D arrays of n real values (or booleans), with
    names every format takes; else an :class:`~sdp.InvalidPointsError` naming the output."""
    try:
        xyz = np.asarray(xyz)
    except Exception as exc:
        raise InvalidPointsError(f"{path}: points are not an array ({exc})") from None
    if xyz.ndim != 2 or xyz.shape[1] != 3 or xyz.dtype.kind not in "iuf":
        raise InvalidPointsError(f"{path}: points must be an (n, 3) array of real numbers, got shape {xyz.shape} "
                                 f"of {xyz.dtype}")
    checked = {}
    for name, values in dict(fields or {}).items():
        v = np.asarray(values)
        if not isinstance(name, str) or not name.isprintable() or not name.strip() or name.lower() in ("x", "y", "z"):
            raise InvalidPointsError(f"{path}: field name {name!r}: a printable name other than x, y, z")
        if path.suffix.lower() == ".ply" and not _PLY_NAME.match(name):  # the header splits at spaces
            raise InvalidPointsError(f"{path}: field name {name!r}: PLY names have no space")
        if path.suffix.lower() in (".las", ".laz") and (not name.isascii() or len(name) > _LAS_NAME_BYTES):
            raise InvalidPointsError(f"{path}: field name {name!r}: LAS names are ASCII, at most {_LAS_NAME_BYTES} "
                                     "characters")
        if v.ndim != 1 or len(v) != len(xyz) or v.dtype.kind not in "biuf":
            raise InvalidPointsError(f"{path}: field {name!r} must hold one real number per point ({len(xyz):,}), "
                                     f"got shape {v.shape} of {v.dtype}")
        checked[name] = v
    return np.asarray(xyz, np.float64), checked


def write_mesh(path: str | os.PathLike, mesh, *, inputs=()) -> Path:
    """Write a :class:`sdp.Mesh` as PLY, OBJ or STL (by extension), atomically. PLY and OBJ keep
    64-bit coordinates; STL, whose coordinates are 32-bit, is refused where rounding them would move
    a vertex by more than 1 % of the median edge (coordinates far from the origin: UTM)."""
    path = Path(path)
    ext = path.suffix.lower()
    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    check_format(path, "mesh")
    with atomic_path(path, inputs=inputs) as tmp:
        if ext == ".ply":
            write_ply_mesh(tmp, v, f)
        elif ext == ".obj":  # every digit of a double: UTM coordinates keep their millimetres
            with open(tmp, "w") as fh:
                np.savetxt(fh, v, fmt="v %.17g %.17g %.17g")
                np.savetxt(fh, f + 1, fmt="f %d %d %d")
        else:  # binary STL: an 80-byte header, the triangle count, then normal, corners, attribute
            tri = v[f]
            # STL holds 32-bit floats: far from the origin they round by more than the mesh's detail
            edge = float(np.median(np.linalg.norm(tri[:, 1] - tri[:, 0], axis=1))) if len(f) else 0.0
            rounding = float(np.abs(tri.astype(np.float32).astype(np.float64) - tri).max()) if len(f) else 0.0
            if rounding > 0.01 * edge:
                raise CloudFileError(f"{path}: STL holds 32-bit floats, which move these vertices (up to "
                                     f"{np.abs(v).max():.4g} from the origin) by {rounding:.3g}, "
                                     f"{rounding / max(edge, 1e-300):.0%} of the mesh's median edge: write "
                                     f".ply or .obj (64-bit), or move the cloud near the origin first")
            normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
            rec = np.zeros(len(f), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
            rec["n"], rec["v"] = normals, tri
            with open(tmp, "wb") as fh:
                fh.write(b"sdp mesh".ljust(80, b" "))
                fh.write(np.uint32(len(f)).tobytes())
                fh.write(rec.tobytes())
    return path
