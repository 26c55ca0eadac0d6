"""Disjoint sets (union–find) on an integer ``parent`` array, shared by the volumes' components
(:mod:`sdp.fields._volume_kernels`), the joins of :mod:`sdp.change._combined` and the 4D objects
of :mod:`sdp.timeseries._objects`.

A set's root is its smallest member (:func:`union` hangs the larger root under the smaller), so
numbering the roots while walking the members in order numbers the sets by their first member.

The kernels are inlined into their callers' compiled code, and Numba's cache checks only the
caller's own source file: after editing this module, touch the callers (or clear their
``__pycache__``) so that their cached kernels are compiled again.

References
----------
.. [1] R. E. Tarjan and J. van Leeuwen, "Worst-case analysis of set union algorithms",
   *J. ACM* 31(2), 245–281, 1984 (path halving).
"""

from __future__ import annotations

import numba as nb

__all__ = ["find", "union"]


@nb.njit(cache=True, inline="always")
def find(parent, a):
    """The root of ``a``'s set (its smallest member), halving the path on the way."""
    while parent[a] != a:
        parent[a] = parent[parent[a]]
        a = parent[a]
    return a


@nb.njit(cache=True, inline="always")
def union(parent, a, b):
    """The sets of ``a`` and ``b`` joined under the smaller root."""
    ra, rb = find(parent, a), find(parent, b)
    if ra < rb:
        parent[rb] = ra
    elif rb < ra:
        parent[ra] = rb
