"""JSON that strict parsers read: NaN and infinities become ``null`` (Python's ``json`` writes bare
``NaN``, which JSON does not have), NumPy scalars and arrays become numbers and lists.

References
----------
.. [1] ECMA-404, The JSON Data Interchange Syntax, 2nd ed. (2017): numbers are finite.
"""

from __future__ import annotations

import json
import math

import numpy as np

__all__ = ["dumps"]


def _plain(value):
    """``value`` with NaN/inf as None, NumPy values as Python ones, containers walked."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def dumps(value, *, indent: int | None = 2) -> str:
    """``value`` as strict JSON (no ``NaN``; objects JSON does not know as their ``str``)."""
    return json.dumps(_plain(value), indent=indent, allow_nan=False, default=str)
