"""The exceptions sdp raises.

Every error sdp raises on purpose is an :class:`SDPError`. The subclasses also derive from
the matching built-in exception (``ValueError``, ``MemoryError``), so code that already
catches those keeps working.

- :class:`InvalidPointsError` (``ValueError``): a point array of the wrong shape, empty or all
  NaN, of zero extent with ``grid_size``, a bad ``sensor_origin``, or coordinates too far from
  the origin for the voxel (:mod:`sdp._core._validate`);
- :class:`InvalidOptionError` (``ValueError``): an option out of range (:mod:`sdp._core._validate`);
- :class:`GridTooLargeError` (``MemoryError``): a grid or a tile beyond the memory limit;
- :class:`IncompatibleFieldsError`, :class:`SurfaceError` (``ValueError``);
- :class:`FieldFileError` (``OSError``), and :class:`sdp.io.CloudFileError` (``OSError``), which
  turns every reader library's error into one line naming the file;
- :class:`MissingDependencyError` (``ImportError``): an optional extra not installed, raised by
  :func:`require` with the ``pip install 'sdp[EXTRA]'`` to run;
- :class:`WorkerLostError` (``RuntimeError``): Dask workers died running one task more often
  than the scheduler allows.

Rows with a NaN or infinite coordinate are not an error: they are dropped and counted
(``n_dropped``, ``summary()["current"]["dropped"]``, with the rows a file reader dropped before),
and masks still cover every input row. Bad input ends before any work with one line: the
command line prints ``sdp: error: …`` and exits with status 2 (argparse's own errors too),
never a traceback, and leaves no file behind. :func:`sdp.cli.main` also turns SIGTERM into an
exception (``sdp: terminated``, status 143) and Ctrl-C into ``sdp: interrupted`` (130), so
temporary outputs, the tiles' work folder and a half-built field store are removed and a Dask
cluster is closed.
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = [
    "SDPError",
    "InvalidPointsError",
    "GridTooLargeError",
    "IncompatibleFieldsError",
    "SurfaceError",
    "FieldFileError",
    "MissingDependencyError",
    "InvalidOptionError",
    "WorkerLostError",
]


class SDPError(Exception):
    """Base class of every error raised by sdp."""


class InvalidPointsError(SDPError, ValueError):
    """A point cloud can't be used: wrong shape, empty, or no extent to derive a grid from."""


class GridTooLargeError(SDPError, MemoryError):
    """The grid would need more memory than the configured limit; raised before allocating."""


class IncompatibleFieldsError(SDPError, ValueError):
    """Two fields can't be combined (e.g. different voxel sizes), or a Boolean result is given
    where a density of points is needed."""


class SurfaceError(SDPError, ValueError):
    """No iso-surface can be extracted at the requested level."""


class FieldFileError(SDPError, OSError):
    """A saved field can't be read: missing, corrupt, or written by an unknown format version."""


class MissingDependencyError(SDPError, ImportError):
    """An optional dependency is not installed; the message says which extra to install."""


class InvalidOptionError(SDPError, ValueError):
    """An option is out of range: a voxel size, σ, threshold, count, memory limit or folder."""


class WorkerLostError(SDPError, RuntimeError):
    """Dask workers died running a task more often than the scheduler retries it (a tiled run)."""


def require(module: str, extra: str, what: str, *, package: str | None = None) -> ModuleType:
    """Import an optional dependency, or raise :class:`MissingDependencyError` in one line.

    ``module`` is imported by name (``"zarr"``, ``"dask.distributed"``); ``extra`` is the extra
    that installs it, ``what`` the feature that needs it and ``package`` the distribution's name
    when it is not the module's (``scikit-learn`` for ``sklearn``), for the message, e.g.
    ``require("zarr", "tiles", "a field store")`` raises "a field store needs zarr (not installed):
    pip install 'sdp[tiles]'".
    """
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        missing = (exc.name or module).split(".")[0]
        if package and missing == module.split(".")[0]:
            missing = package
        raise MissingDependencyError(f"{what} needs {missing} (not installed): pip install 'sdp[{extra}]'") from None
