"""Memory sizes and the one memory limit.

Memory is checked against one limit before anything is allocated (:func:`memory_limit`:
``memory_limit=``, ``$SDP_MEMORY_LIMIT``, else 4 GiB). Refusals give both sizes in human units
(``12.3 MB``; binary units, as :func:`parse_bytes` reads them).
"""

from __future__ import annotations

import math
import os
import re

import numpy as np

from ..errors import GridTooLargeError, InvalidOptionError

__all__ = ["format_bytes", "parse_bytes", "memory_limit", "check_memory", "MIN_MEMORY_LIMIT"]

_DEFAULT_MEMORY_LIMIT = 4 * 2**30


_UNITS = {"": 1, "b": 1, "k": 2**10, "kb": 2**10, "kib": 2**10, "m": 2**20, "mb": 2**20,
          "mib": 2**20, "g": 2**30, "gb": 2**30, "gib": 2**30, "t": 2**40, "tb": 2**40, "tib": 2**40}


#: Smallest memory limit accepted: a smaller one is almost surely a size given without its unit.
MIN_MEMORY_LIMIT = 2**20



def format_bytes(nbytes: float) -> str:
    """A byte count for people: ``"512 B"``, ``"12.3 MB"``, ``"4.0 GB"`` (binary units, 1 MB = 2**20
    bytes, as :func:`sdp._core._memory.parse_bytes` reads them)."""
    n = float(nbytes)
    if not math.isfinite(n):
        return "an unbounded amount"
    for unit in ("B", "KB", "MB", "GB", "TB", "PB", "EB"):
        if abs(n) < 1024 or unit == "EB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1024
    raise AssertionError("unreachable")


def parse_bytes(value: int | float | str) -> int:
    """Parse a memory size such as ``2GB``, ``512MiB`` or ``1e9`` into bytes (binary units).

    Raises
    ------
    InvalidOptionError
        Not a positive finite size in a known unit.
    """
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        if not (value > 0 and math.isfinite(value)):
            raise InvalidOptionError(f"a memory limit must be a positive size such as 2GB, got {value!r}")
        return int(value)
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?|[0-9]+\.)\s*([a-zA-Z]*)\s*", str(value))
    if not match or match.group(2).lower() not in _UNITS:
        raise InvalidOptionError(f"can't read memory size {value!r}: use e.g. 2GB, 512MB or a number of bytes")
    return parse_bytes(float(match.group(1)) * _UNITS[match.group(2).lower()])


def memory_limit(limit: int | float | str | None = None) -> int:
    """The memory limit in bytes: ``limit`` if given, else ``$SDP_MEMORY_LIMIT``, else 4 GiB.

    Raises
    ------
    InvalidOptionError
        Unreadable, not positive, or, given as text (the command line, ``$SDP_MEMORY_LIMIT``),
        below 1 MB (:data:`MIN_MEMORY_LIMIT`: most likely a size without its unit).
    """
    source = "the memory limit"
    if limit is None:
        env = os.environ.get("SDP_MEMORY_LIMIT")
        limit, source = (_DEFAULT_MEMORY_LIMIT, source) if env is None else (env, "$SDP_MEMORY_LIMIT")
    try:
        cap = parse_bytes(limit)
    except InvalidOptionError as exc:
        if source == "the memory limit":
            raise
        raise InvalidOptionError(f"{source}: {exc}") from None
    if cap < MIN_MEMORY_LIMIT and isinstance(limit, str):  # numbers (Python) are bytes, taken as given
        raise InvalidOptionError(f"{source} {limit!r} is {format_bytes(cap)}, below the minimum of "
                                 f"{format_bytes(MIN_MEMORY_LIMIT)}: give a size with its unit, e.g. 2GB")
    return cap


def check_memory(nbytes: float, what: str, limit: int | float | str | None, *,
                 advice: str = "use a larger voxel size (or a smaller grid size)",
                 budget: str = "the memory limit") -> None:
    """Raise :class:`GridTooLargeError` if ``nbytes`` exceeds the memory limit.

    The message gives both sizes in human units and says what to change: ``advice``, or
    raising the memory limit (``--memory-limit`` on the command line, ``memory_limit=`` in
    Python, ``$SDP_MEMORY_LIMIT`` for both). ``budget`` names what ``limit`` is (a worker's
    share of the memory limit, for the tiles). A tiled task's share
    (:class:`sdp.scale._budget.TaskShare`) says itself what it is and which limit would hold ``nbytes``.
    """
    cap = memory_limit(limit)
    if not nbytes <= cap:
        if hasattr(limit, "beyond"):  # a task's share, not the limit the user gave
            budget, more = limit.beyond(nbytes)
            raise GridTooLargeError(f"{what} would need {format_bytes(nbytes)}, above {budget}: {advice}, or {more}")
        raise GridTooLargeError(
            f"{what} would need {format_bytes(nbytes)}, above {budget} of {format_bytes(cap)}: "
            f"{advice}, or raise the memory limit (--memory-limit, $SDP_MEMORY_LIMIT)")
