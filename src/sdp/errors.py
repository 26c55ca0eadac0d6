"""The exceptions sdp raises.

Every error sdp raises on purpose is an :class:`SDPError`. The subclasses also derive from
the matching built-in exception (``ValueError``, ``MemoryError``), so code that already
catches those keeps working.
"""

from __future__ import annotations

__all__ = [
    "SDPError",
    "InvalidPointsError",
    "GridTooLargeError",
    "IncompatibleFieldsError",
    "SurfaceError",
    "FieldFileError",
    "MissingDependencyError",
    "InvalidOptionError",
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
