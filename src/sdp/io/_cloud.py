"""A point cloud read from a file (:class:`Cloud`), the error of a file that can't be read
(:class:`CloudFileError`), and what every reader shares: the formats by extension
(:data:`FORMATS`, :func:`input_format`), the order of a folder's frames (:func:`natural_key`), the
one-line error of a library's failure (:func:`library_error`, :func:`unreadable`; pydantic's PCD header
reports summarized) and the notice of what a file holds that is read otherwise than one might expect
(:func:`notice`).

Kept apart from the readers (one module per format) and from :func:`sdp.io.read_points`, which
dispatches to them, so that every one of them imports it without an import cycle.
"""

from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..errors import SDPError

__all__ = ["Cloud", "CloudFileError", "EmptyCloudError", "ReadNotice", "FORMATS", "input_format", "is_bag",
           "library_error", "natural_key", "notice", "unreadable", "unpacked_colour"]

#: Extension → format name understood by :func:`sdp.io.read_points`.
FORMATS = {".pcd": "pcd", ".ply": "ply", ".las": "las", ".laz": "las", ".xyz": "text", ".txt": "text",
           ".csv": "text", ".pts": "text", ".npy": "npy", ".npz": "npz", ".e57": "e57"}

_DEFAULT_VIEWPOINT = np.array([0.0, 0, 0, 1, 0, 0, 0])  # PCL's VIEWPOINT when the sensor pose is unset


class CloudFileError(SDPError, OSError):
    """A point-cloud file can't be read: unknown format, corrupt, empty, or without x/y/z."""


class EmptyCloudError(CloudFileError):
    """The file holds no point (no row, or none with finite x, y, z): an error, but for a
    stream's frame, which a blinded sensor leaves empty (``read_points(allow_empty=True)``)."""


class ReadNotice(UserWarning):
    """What a reader says of a file it reads otherwise than one might expect (a PLY's vertex list
    properties left out, a LAS file's withheld or noise points compared as any other): a warning
    in Python, one ``sdp:`` line on stderr from the command line (none with ``--quiet``)."""


def notice(message: str) -> None:
    """Say ``message`` (one line, naming the file) as a :class:`ReadNotice`: a reader's word
    reaches Python callers and every command that reads a file, whichever reads it. Called by a
    reader itself, it points at the line that called :func:`sdp.io.read_points`."""
    warnings.warn(message, ReadNotice, stacklevel=4)


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


def library_error(exc: BaseException) -> bool:
    """Whether ``exc`` is a reader library's failure on bad content: any ``Exception``, or a Rust
    panic surfaced by pyo3 (``PanicException`` derives from ``BaseException``), but never
    Ctrl-C, ``SystemExit`` or a closed generator."""
    return isinstance(exc, Exception) or type(exc).__name__ == "PanicException"


def unreadable(path, fmt: str, exc: BaseException) -> "CloudFileError":
    """The CloudFileError of a library exception raised while reading ``path``."""
    if "allow_pickle" in str(exc):  # NumPy's advice to unpickle: not something sdp does with a file
        return CloudFileError(f"{path}: can't read as {fmt} (not an array of numbers: random bytes or pickled "
                              "Python objects, which sdp does not load)")
    return CloudFileError(f"{path}: can't read as {fmt} ({type(exc).__name__}: {_one_line(exc)})")


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
    sensors : ndarray (k, 3) float64 or None
        Where each scanner stood (an E57 file's scan poses; one row per scan), in the cloud's
        frame; the ``scan`` field (:attr:`scan`) says which of them saw each point. None when
        the file records no scanner this way.
    poles : ndarray (k, 3) float64 or None
        Each scanner's vertical axis (a unit vector, rows as :attr:`sensors`), in the cloud's
        frame: an E57 scan's pose turns its scanner's z into the file's frame. Its range image is
        laid out about it (:meth:`sdp.change._range_image.RangeImage.from_points`). None when
        the file does not say (a bag's messages, a Cartesian scan without a pose).
    range_noise : float or None
        The range noise its sensor's kind implies, per r² (the rays' band,
        :func:`sdp.change._visibility.sensor_range_noise`): 0 for an E57 or LAS/LAZ file's laser
        scans, whose noise is millimetres at any range; None when the format says nothing of its
        sensor.
    image : tuple of int or None
        An organized cloud's (height, width): the sensor's image, one ray per pixel.
    pixels : ndarray of int64 (n,) or None
        With ``image``: the pixel (row · width + column) of each row kept, ascending, the others
        being the rays that returned nothing (:func:`sdp._core._pinhole.fit_camera`).
    frame : str or None
        The coordinate frame the points are in: a ROS bag message's ``header.frame_id`` (without
        a leading ``/``), or the root frame its bag's ``/tf`` moved it into. None for files,
        which do not name theirs.
    tf : str or None
        What a bag's ``/tf`` did with a message (:mod:`sdp.io._tf`): ``"moved from 'camera' into
        'map' with /tf"``, or why it left it in its frame. None without ``/tf``.
    """

    xyz: np.ndarray
    fields: dict[str, np.ndarray] = field(default_factory=dict)
    path: Path | None = None
    n_dropped: int = 0
    las: object = None
    viewpoint: np.ndarray | None = None

    organized: bool = False
    sensors: np.ndarray | None = None
    range_noise: float | None = None
    image: tuple | None = None
    pixels: np.ndarray | None = field(default=None, repr=False)
    frame: str | None = None
    tf: str | None = None
    poles: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.xyz)

    @property
    def sensor_origin(self) -> np.ndarray | None:
        """Position (3,) of the sensor in the cloud's frame, or None when the file does not say.

        An organized PCD (an image of the sensor's rays) always says: ``viewpoint[:3]``. An
        unorganized PCD says only if its VIEWPOINT is not PCL's default ``0 0 0 1 0 0 0``
        (the header every merged or filtered map carries). Other formats say nothing.
        :func:`sdp.detect_changes` uses it by default (``sensor_origin="auto"``). A cloud of one
        scanner (:attr:`sensors` of one row) says where it stood; one of several says None here
        (see :attr:`sensor_origins`).
        """
        if self.sensors is not None:
            return self.sensors[0].copy() if len(self.sensors) == 1 else None
        if self.viewpoint is None or not (self.organized or np.any(self.viewpoint != _DEFAULT_VIEWPOINT)):
            return None
        return self.viewpoint[:3].copy()

    @property
    def scan(self) -> np.ndarray | None:
        """Which scanner (row of :attr:`sensors`) saw each point (n,), or None without :attr:`sensors`."""
        if self.sensors is None:
            return None
        scan = self.fields.get("scan")
        return np.zeros(len(self.xyz), np.int64) if scan is None else np.asarray(scan, np.int64)

    @property
    def sensor_origins(self) -> np.ndarray | None:
        """Every scanner's position (k, 3): :attr:`sensors`, else :attr:`sensor_origin` as one
        row, else None."""
        if self.sensors is not None:
            return self.sensors.copy()
        one = self.sensor_origin
        return None if one is None else one[None, :]

    def transformed(self, matrix: np.ndarray) -> "Cloud":
        """The cloud moved by a rigid 4×4 ``matrix`` (e.g. :attr:`sdp.Alignment.matrix`), its
        sensor poses with it; fields, path and counts unchanged."""
        from scipy.spatial.transform import Rotation

        m = np.asarray(matrix, dtype=np.float64)
        xyz = self.xyz @ m[:3, :3].T + m[:3, 3]
        viewpoint = None
        if self.viewpoint is not None:
            q = self.viewpoint[3:]  # qw qx qy qz
            turned = Rotation.from_matrix(m[:3, :3]) * Rotation.from_quat([q[1], q[2], q[3], q[0]])
            x, y, z, w = turned.as_quat()
            viewpoint = np.r_[m[:3, :3] @ self.viewpoint[:3] + m[:3, 3], w, x, y, z]
        sensors = None if self.sensors is None else self.sensors @ m[:3, :3].T + m[:3, 3]
        poles = None if self.poles is None else self.poles @ m[:3, :3].T
        return replace(self, xyz=np.ascontiguousarray(xyz), viewpoint=viewpoint, sensors=sensors, poles=poles)


def unpacked_colour(fields: dict) -> dict:
    """``fields`` with PCL's packed colour (``rgb``: 0x00RRGGBB, or ``rgba``: 0xAARRGGBB, in the
    four bytes of a float32 or uint32, as PCD files and ``PointCloud2`` messages hold it [1]_)
    as ``red``, ``green``, ``blue`` (uint8), which every output writes as colour (LAS colour,
    PLY's properties); other fields as they are.

    References
    ----------
    .. [1] PCL, "The PCD (Point Cloud Data) file format", pointclouds.org (the ``rgb`` field).
    """
    for packed in ("rgb", "rgba"):
        v = fields.get(packed)
        if v is not None and "red" not in fields and np.asarray(v).dtype.itemsize == 4 and np.ndim(v) == 1:
            bits = np.ascontiguousarray(v).view(np.uint32)
            rest = {k: x for k, x in fields.items() if k != packed}
            return {**rest, "red": ((bits >> 16) & 255).astype(np.uint8),
                    "green": ((bits >> 8) & 255).astype(np.uint8), "blue": (bits & 255).astype(np.uint8)}
    return fields


def natural_key(path: Path) -> list:
    """The sort key of a file in natural name order, the order of a folder's frames (``frame2``
    before ``frame10``, which a plain sort puts after ``frame1``): digits compare as numbers."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", Path(path).name)]


def is_bag(path) -> bool:
    """A ROS 1 bag file (``.bag``), or a ROS 2 bag: a folder holding ``metadata.yaml``, or one of
    its ``.db3`` / ``.mcap`` files (arrays and clouds are not)."""
    if not isinstance(path, (str, os.PathLike)):
        return False
    p = Path(path)
    if p.is_dir():
        return (p / "metadata.yaml").is_file()
    return p.suffix.lower() in (".bag", ".db3", ".mcap")  # missing too: the reader says so


def input_format(path: Path, format: str | None) -> str:
    """The reader's format name for ``path`` (``format`` overrides the extension), once ``path``
    is known to be an existing file; else :class:`CloudFileError` saying what is wrong."""
    names = sorted(set(FORMATS.values()))
    if format is None and is_bag(path):  # commands other than change and watch: say where its messages go
        raise CloudFileError(f"{path}: no such file or folder" if not path.exists() else
                             f"{path}: a ROS bag, not a point-cloud file: sdp change and sdp watch read its "
                             "PointCloud2 messages (--topic TOPIC:N), sdp series all of them as one epoch (--topic "
                             "TOPIC)")
    if path.is_dir():
        raise CloudFileError(f"{path}: is a folder, not a point-cloud file")
    if format is None and path.suffix.lower() == ".sdpf":
        raise CloudFileError(f"{path}: a density field (sdp build), not a point cloud; sdp watch, bool, mesh and "
                             "render read fields")
    if format is not None:  # a format name or an extension, in any case: "PLY", "laz", ".xyz"
        fmt = FORMATS.get("." + format.lower().lstrip("."), format.lower())
        if fmt not in names:
            raise CloudFileError(f"unknown format {format!r}; use one of {', '.join(names)}")
    else:
        fmt = FORMATS.get(path.suffix.lower())
        if fmt is None:
            raise CloudFileError(f"{path}: unknown point-cloud format {path.suffix or '(no extension)'!r}; use one "
                                 f"of the extensions {', '.join(sorted(FORMATS))} or give the format "
                                 f"({', '.join(names)})")
    if not path.exists():
        raise CloudFileError(f"{path}: no such file")
    if not path.is_file():
        raise CloudFileError(f"{path}: not a regular file")
    if not os.access(path, os.R_OK):
        raise CloudFileError(f"{path}: permission denied")
    return fmt
