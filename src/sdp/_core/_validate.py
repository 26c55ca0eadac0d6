"""Checks of the options shared by the Python API and the command line.

One set of functions refuses bad options before any work starts: the Python entry points
(:meth:`sdp.DensityField.from_points`, :func:`sdp.detect_changes` through it,
:func:`sdp.detect_changes_tiled`, :func:`sdp.build_field_tiled`, :func:`sdp.align`) call them
with their keyword names (``voxel_size``), the command line with its flags (``--voxel-size``,
through :func:`cli_type`). Every refusal is an :class:`~sdp.errors.InvalidOptionError` (an
:class:`~sdp.SDPError` and a ``ValueError``) with a one-line message, or a
:class:`~sdp.GridTooLargeError` / :class:`~sdp.InvalidPointsError` where the grid, not the
option alone, is at fault.

What is refused: voxel size, σ in voxels, ``truncate`` and ``h`` not positive and finite; ``k``
not finite, or giving h ≤ 0; a tile size not positive; workers, grid size or window below 1;
``min_region_points`` below 0; a memory limit given as text (``--memory-limit``,
``$SDP_MEMORY_LIMIT``) below 1 MB (a smaller one is a size without its unit); a ``--workdir``
that is not an existing writable folder. A kernel reaching more than 2¹⁶ voxels is a mistake
long before memory runs out (:func:`kernel_reach`), and one point's kernel cube must fit the
memory limit (σ = 1000 voxels would need 808 GB: :func:`check_kernel`).

Precision (:func:`check_lattice`): beyond 2⁴⁰ ≈ 1.1·10¹² voxels from the world origin (max
|coordinate| / voxel size), float64 keeps less than 1/4096 of a voxel and masks would change
silently (1e12 m offsets at a 1 cm voxel), so such a grid is an :class:`~sdp.InvalidPointsError`;
a voxel so large that the grid's corners overflow float64 (1e308) is an
:class:`~sdp.errors.InvalidOptionError`. The tiled path runs the same checks on the files'
bounds, and also refuses tiles whose points or block directory exceed a task's share of the
memory limit, all before the buckets are written or a local Dask cluster is started.
"""

from __future__ import annotations

import argparse
import math
import numbers
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import InvalidOptionError, InvalidPointsError, SDPError

__all__ = ["boolean", "path_like", "positive_finite", "finite", "nonnegative_finite", "integer_at_least",
           "auto_or_positive", "auto_or_exponent", "auto_or_nonnegative", "memory_size", "existing_folder",
           "check_threshold", "check_grid_options", "check_tile_options", "check_workdir", "cli_type",
           "sensor_origin_option", "class_numbers", "check_alignment_options", "check_tiled_options", "direction",
           "as_sensor_origins", "picture_path", "check_orientation"]


def _number(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (numbers.Real, str, np.ndarray)):
        raise InvalidOptionError(f"{name} must be a number, got {value!r}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InvalidOptionError(f"{name} must be a number, got {value!r}") from None


def positive_finite(name: str, value) -> float:
    """``value`` as a float if it is a positive finite number, else :class:`InvalidOptionError`.

    Parameters
    ----------
    name : str
        How the caller spells the option (``"voxel_size"``, ``"--voxel-size"``); used in the message.
    value : float or str
        The option's value.

    Returns
    -------
    float
    """
    v = _number(name, value)
    if not (v > 0 and math.isfinite(v)):
        raise InvalidOptionError(f"{name} must be a positive finite number, got {value!r}")
    return v


def finite(name: str, value) -> float:
    """``value`` as a float if it is finite (any sign), else :class:`InvalidOptionError`."""
    v = _number(name, value)
    if not math.isfinite(v):
        raise InvalidOptionError(f"{name} must be a finite number, got {value!r}")
    return v


def nonnegative_finite(name: str, value) -> float:
    """``value`` as a float if it is finite and ≥ 0, else :class:`InvalidOptionError`."""
    v = finite(name, value)
    if v < 0:
        raise InvalidOptionError(f"{name} must be a finite number >= 0, got {value!r}")
    return v


def boolean(name: str, value) -> bool:
    """``value`` if it is True or False (NumPy's too), else :class:`InvalidOptionError`: a string
    ``"false"`` or a 0/1 would otherwise read as Python's truth of it."""
    if not isinstance(value, (bool, np.bool_)):
        raise InvalidOptionError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def path_like(name: str, value) -> None:
    """Refuse a ``value`` (not None) that is not a path: a str or an ``os.PathLike``."""
    if value is not None and not isinstance(value, (str, os.PathLike)):
        raise InvalidOptionError(f"{name} must be a file path, got {value!r}")


def integer_at_least(name: str, value, minimum: int) -> int:
    """``value`` as an int if it is a whole number ≥ ``minimum``, else :class:`InvalidOptionError`."""
    try:
        v = float(value) if not isinstance(value, bool) else math.nan
    except (TypeError, ValueError):
        v = math.nan
    if not (math.isfinite(v) and v == int(v) and v >= minimum):
        raise InvalidOptionError(f"{name} must be a whole number of at least {minimum}, got {value!r}")
    return int(v)


_FLOAT32_MAX = float(np.finfo(np.float32).max)


def check_threshold(k: float | None, h: float | None, *, names: tuple[str, str] = ("k", "h")) -> None:
    """Refuse a threshold that is not a positive finite density: ``h`` given directly, or
    h = 1 + k·e^(−1/2) from ``k``."""
    if h is not None:
        value, name = positive_finite(names[1], h), names[1]
    elif k is not None:
        kv = finite(names[0], k)
        value, name = 1.0 + kv * math.exp(-0.5), f"h = 1 + {names[0]}·e^-1/2"
        if not value > 0:
            raise InvalidOptionError(f"{names[0]} = {k!r} gives a threshold h = 1 + k·e^-1/2 ≤ 0: no density is "
                                     "below it; use k > -1.65")
    else:
        return
    if value > _FLOAT32_MAX:  # fields hold densities as float32: F = h − G would overflow
        raise InvalidOptionError(f"{name} = {value:.3g} is beyond the densities' float32 range (3.4e38)")


def check_grid_options(*, voxel_size=None, sigma_voxels: float | str = "auto", k: float | None = 3,
                       h: float | None = None, truncate: float = 3.0, memory_limit=None) -> float | None:
    """Check the options of a density field before anything is read or allocated.

    Parameters
    ----------
    voxel_size : float, "auto" or None
        A length must be positive and finite; ``"auto"`` and None (decided later) pass.
    sigma_voxels : float or "auto"
        A positive finite number, or ``"auto"`` (:func:`sdp.fields._spacing.resolve_sigma_voxels`).
    truncate : float
        A positive finite number.
    k, h : float or None
        See :func:`check_threshold`.
    memory_limit : int, float, str or None
        See :func:`sdp._core._memory.memory_limit`.

    Returns
    -------
    float or None
        The voxel size as a float, or None when it is ``"auto"`` or not given.
    """
    from ._memory import memory_limit as _limit

    auto_or_positive("sigma_voxels", sigma_voxels)
    positive_finite("truncate", truncate)
    check_threshold(k, h)
    _limit(memory_limit)
    if voxel_size is None or (isinstance(voxel_size, str) and voxel_size == "auto"):
        return None
    try:
        return positive_finite("voxel_size", voxel_size)
    except InvalidOptionError:
        raise InvalidOptionError(f"voxel_size must be 'auto' or a positive finite length, got {voxel_size!r}") from None


def check_workdir(name: str, workdir) -> None:
    """Refuse a work folder that does not exist, is not a folder, or can't be written."""
    if workdir is None:
        return
    path_like(name, workdir)
    path = Path(workdir)
    if not path.exists():
        raise InvalidOptionError(f"{name} {str(path)!r}: no such folder")
    if not path.is_dir():
        raise InvalidOptionError(f"{name} {str(path)!r}: not a folder")
    try:  # a folder created and removed: the test that holds on /proc, read-only mounts and full disks
        os.rmdir(tempfile.mkdtemp(prefix=".sdp-probe-", dir=path))
    except OSError as exc:
        raise InvalidOptionError(f"{name} {str(path)!r}: can't create folders there ({exc.strerror or exc})") from None


def existing_folder(name: str, value) -> str:
    """``value`` unchanged if it names a writable folder (:func:`check_workdir`)."""
    check_workdir(name, value)
    return value


def check_tile_options(*, tile_size=None, tile_points=None, workers=None, workdir=None,
                       min_region_points=None, scheduler=None) -> None:
    """Check the options of a tiled run (:func:`sdp.detect_changes_tiled`, :func:`sdp.build_field_tiled`)
    before a work folder is made or a cluster started."""
    if tile_size is not None:
        positive_finite("tile_size", tile_size)
    if tile_points is not None:
        integer_at_least("tile_points", tile_points, 1)
    if workers is not None:
        integer_at_least("workers", workers, 1)
    if min_region_points is not None:
        integer_at_least("min_region_points", min_region_points, 0)
    if scheduler is not None and not isinstance(scheduler, str):
        raise InvalidOptionError(f"scheduler must be an address such as tcp://host:8786, got {scheduler!r}")
    check_workdir("workdir", workdir)


#: What each picture option writes, by the names its file may end with.
PICTURE_SUFFIXES = {"png": (".png",), "html": (".html", ".htm"), "report": (".html", ".htm")}


def picture_path(name: str, value) -> None:
    """Refuse a picture ``value`` (``png``, ``html`` or ``report``, by ``name``) whose name says
    another format: a PNG written into ``x.jpg`` or a page into ``x.pdf`` opens as neither."""
    if value is None:
        return
    path_like(name, value)
    suffixes = PICTURE_SUFFIXES[name]
    if Path(os.fspath(value)).suffix.lower() not in suffixes:
        raise InvalidOptionError(f"{name} {os.fspath(value)!r}: writes {'a PNG' if name == 'png' else 'HTML'}; "
                                 f"name it {' or '.join('…' + x for x in suffixes)}")


def auto_or_nonnegative(name: str, value) -> float | str:
    """``"auto"``, or ``value`` as a finite float ≥ 0 (an error added to a tolerance)."""
    if isinstance(value, str) and value.strip().lower() == "auto":
        return "auto"
    try:
        return nonnegative_finite(name, value)
    except InvalidOptionError:
        raise InvalidOptionError(f"{name} must be 'auto' or a finite number ≥ 0, got {value!r}") from None


def auto_or_exponent(name: str, value) -> float | str:
    """``"auto"``, or ``value`` as a float in [0, 2] (how a sensor's noise grows with range)."""
    if isinstance(value, str) and value.strip().lower() == "auto":
        return "auto"
    try:
        p = finite(name, value)
    except InvalidOptionError:
        p = -1.0
    if not 0 <= p <= 2:
        raise InvalidOptionError(f"{name} must be 'auto' or in [0, 2], got {value!r}")
    return p


def auto_or_positive(name: str, value) -> float | str:
    """``"auto"``, or ``value`` as a positive finite float (a voxel size)."""
    if isinstance(value, str) and value.strip().lower() == "auto":
        return "auto"
    try:
        return positive_finite(name, value)
    except InvalidOptionError:
        raise InvalidOptionError(f"{name} must be 'auto' or a positive finite number, got {value!r}") from None


def memory_size(name: str, value) -> str:
    """``value`` unchanged once :func:`sdp._core._memory.memory_limit` accepts it (e.g. ``"2GB"``)."""
    from ._memory import memory_limit

    memory_limit(value)  # its messages say what a memory limit is
    return value


def sensor_origin_option(name: str, value) -> str | np.ndarray:
    """The ``--sensor-origin`` of ``sdp change`` / ``sdp watch`` (:func:`sdp.compare_files`):
    ``"auto"``, ``"none"`` (also None), ``"viewpoint"``, or a position ``"X,Y,Z"`` (or three
    numbers) returned as an ndarray (3,) of finite floats."""
    if value is None:
        return "none"
    if isinstance(value, str) and value in ("auto", "none", "viewpoint"):
        return value
    try:
        xyz = [float(v) for v in (value.split(",") if isinstance(value, str) else np.ravel(value))]
    except (TypeError, ValueError):
        xyz = []
    if len(xyz) != 3 or not np.isfinite(xyz).all():
        raise InvalidOptionError(f"{name} must be auto, none, viewpoint or X,Y,Z (finite numbers), got {value!r}")
    return np.array(xyz, dtype=np.float64)


def direction(name: str, value) -> np.ndarray:
    """A unit vector (3,) from three finite numbers, not all zero: ``"X,Y,Z"`` or array-like
    (an ``orientation``); scaled before its norm so that 1e308 components do not overflow.

    Raises
    ------
    InvalidOptionError
        Not three finite numbers, or all zero.
    """
    try:
        xyz = np.array([float(v) for v in (value.split(",") if isinstance(value, str) else np.ravel(value))])
    except (TypeError, ValueError):
        xyz = np.zeros(0)
    if xyz.shape != (3,) or not np.isfinite(xyz).all() or not xyz.any():
        shown = value if isinstance(value, str) else np.asarray(value).tolist() if np.ndim(value) else value
        raise InvalidOptionError(f"{name} must be three finite numbers X,Y,Z, not all zero; got {shown!r}")
    xyz = xyz / np.abs(xyz).max()
    return xyz / np.linalg.norm(xyz)


def check_orientation(orientation, *, sensor_given: bool, names=("orientation", "sensor_origin")) -> None:
    """Refuse an ``orientation`` beside a sensor given (a position, or the files' own): the normals
    face the sensor wherever one is known, so the orientation would be ignored."""
    if orientation is not None and sensor_given:
        raise InvalidOptionError(f"{names[0]} points the normals where no sensor is known; with {names[1]} given "
                                 "it would be ignored: give one of them")


def as_sensor_origins(sensor_origin) -> tuple[np.ndarray, np.ndarray]:
    """(reference's, current's) sensor origin from one position (3,) or two (2, 3).

    Raises
    ------
    InvalidPointsError
        Not numbers, wrong shape, or not finite.
    """
    try:
        o = np.asarray(sensor_origin, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidPointsError(f"sensor_origin: expected x, y, z of the sensor, or two such rows "
                                 f"(reference's, current's) ({exc})") from None
    if o.shape == (3,):
        o = np.stack([o, o])
    if o.shape != (2, 3):
        raise InvalidPointsError(f"sensor_origin: expected x, y, z of the sensor (shape (3,)) or one row per "
                                 f"scan (shape (2, 3): reference's, current's), got shape {o.shape}")
    if not (np.isfinite(o).all() and np.abs(o).max() < _MAX_POSITION):
        raise InvalidPointsError(f"sensor_origin must be finite and within ±{_MAX_POSITION:.0e}, got {o.tolist()}")
    return o[0].copy(), o[1].copy()


_MAX_POSITION = 1e12  # a sensor's coordinates: ranges and angles from farther overflow (1e12 m: beyond any scene)


def class_numbers(name: str, value) -> list[int]:
    """LAS class numbers from ``"2"``, ``"2,9"``, an int or a sequence of ints (``--align-class``):
    0 to 255, the classes LAS 1.4 can record."""
    parts = value.split(",") if isinstance(value, str) else [value] if np.ndim(value) == 0 else list(value)
    if all(isinstance(c, str) or (isinstance(c, numbers.Integral) and not isinstance(c, bool)) for c in parts):
        try:
            classes = [int(c) for c in parts]
        except ValueError:
            classes = None
        if classes is not None and all(0 <= c <= 255 for c in classes):
            return classes
    raise InvalidOptionError(f"{name} takes LAS class numbers (0 to 255) such as 2 or 2,9, got {value!r}")


def check_alignment_options(method: str | None, *, fix_horizontal: bool = False, align_class=None) -> list[int] | None:
    """Check how a scan is to be aligned (``sdp align``, ``sdp change --align``) before any file is
    read; returns the class numbers of ``align_class`` (None: all points).

    ``fix_horizontal`` and ``align_class`` need a ``method``; ``fix_horizontal`` works with the
    density alignment only.
    """
    boolean("fix_horizontal", fix_horizontal)
    classes = align_class is not None and not (isinstance(align_class, str) and align_class == "")
    if (fix_horizontal or classes) and not method:
        raise InvalidOptionError("--fix-horizontal and --align-class choose how to align: give --align density too")
    if fix_horizontal and method != "density":
        raise InvalidOptionError("--fix-horizontal works with the density alignment only")
    return class_numbers("--align-class", align_class) if classes else None


def check_tiled_options(*, grid_size=None, align=None, sensor_origin="auto", decision="point",
                        pictures: bool = False, range_noise=None, why: str = "with --tiled") -> None:
    """Refuse the options of ``sdp change`` that a comparison in tiles does not have (``--tiled``,
    or ``why`` they are taken): tiles follow no sensor's rays, so a range noise given is one too."""
    from ..defaults import DEFAULTS

    given_sensor = not (isinstance(sensor_origin, str) and sensor_origin in ("auto", "none"))
    noise_given = range_noise is not None and range_noise != DEFAULTS.range_noise
    for flag, bad in (("--grid-size", grid_size is not None), ("--align", align), ("--sensor-origin", given_sensor),
                      ("--range-noise", noise_given),
                      (f"--decision {decision}", decision == "cluster"),
                      ("--png/--html/--report", pictures)):
        if bad:
            raise InvalidOptionError(f"{flag} is not available {why}")


def cli_type(check: Callable, *args) -> Callable[[str], object]:
    """An argparse ``type=`` callable running ``check("value", text, *args)``, with its
    :class:`SDPError` turned into ``argparse.ArgumentTypeError`` (argparse names the flag; the
    ``sdp`` parser prints that one line and exits with status 2)."""
    def convert(text: str):
        try:
            return check("value", text, *args)
        except SDPError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    convert.__name__ = getattr(check, "__name__", "value")
    return convert
