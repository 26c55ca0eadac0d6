"""Boolean operations on normalized fields (Ricci's constructive solid geometry).

For F = h − G (negative inside): union = min(F1, F2), intersection = max(F1, F2),
difference = max(F1, −F2). Each is one pass over the nodes, linear in their number.

Both fields must share the voxel size: then their nodes coincide (the lattice is global,
see :mod:`sdp.fields._lattice`) and the result is exact at every node, with no resampling. Fields with
different voxel sizes are refused with :class:`~sdp.IncompatibleFieldsError` rather than
resampled, because resampling would blur the finer field silently; build both with the same
``voxel_size=`` (as :func:`sdp.detect_changes` does).

References
----------
.. [1] A. Ricci, "A constructive geometry for computer graphics", The Computer Journal
   16(2), 1973.
"""

from __future__ import annotations

import numpy as np

from .._core._memory import check_memory
from ..errors import IncompatibleFieldsError
from ._density import DensityField
from ._lattice import Grid
from ._volume_kernels import difference_blocks

__all__ = ["union", "intersection", "difference"]


def _difference_values(f1: np.ndarray, f2: np.ndarray) -> np.ndarray:
    return np.maximum(f1, -f2)


_OPS = {"union": np.minimum, "intersection": np.maximum, "difference": _difference_values}


def check_compatible(a: DensityField, b: DensityField) -> None:
    """Raise :class:`IncompatibleFieldsError` unless ``a`` and ``b`` are fields sharing their lattice."""
    for name, f in (("first", a), ("second", b)):
        if not isinstance(f, DensityField):  # points, say: build their field on the other's lattice first
            raise IncompatibleFieldsError(f"the {name} operand is a {type(f).__name__}, not a DensityField: build it "
                                          f"with sdp.DensityField.from_points on the other's voxel size")
    if not np.isclose(a.voxel_size, b.voxel_size, rtol=1e-12, atol=0):
        raise IncompatibleFieldsError(
            f"fields have different voxel sizes ({a.voxel_size!r} and {b.voxel_size!r}): build both "
            "with the same voxel size so their nodes coincide")


def _combine(a: DensityField, b: DensityField, name: str) -> DensityField:
    check_compatible(a, b)
    op = _OPS[name]
    keys = np.unique(np.concatenate([a.global_keys, b.global_keys]), axis=0)
    lo, hi = keys.min(axis=0), keys.max(axis=0)
    grid = Grid(a.voxel_size, lo, tuple(int(v) for v in hi - lo + 1))
    # the result's directory spans both fields' boxes (two clouds far apart: a vast one): refused before allocating
    check_memory(grid.n_blocks_box * 5 + a.nbytes + b.nbytes, f"the block directory of a {grid.shape} grid", None,
                 advice=f"the fields span {np.max(grid.shape) * a.voxel_size:g} units together; combine fields of "
                        "the same place, or build them on a larger voxel size")
    f3 = op(a.h - a.node_values(keys), b.h - b.node_values(keys))
    h3 = float(op(np.float64(a.h), np.float64(b.h)))  # the value far from both clouds
    return DensityField(grid, keys - lo, h3 - f3, h=h3, sigma=a.sigma, truncate=a.truncate, method=name)


def union(a: DensityField, b: DensityField) -> DensityField:
    """Union of two cluster volumes: F = min(F_a, F_b), on the union of both grids.

    Parameters
    ----------
    a, b : DensityField
        Fields with the same voxel size (else :class:`~sdp.IncompatibleFieldsError`).

    Returns
    -------
    DensityField
        Holds the combined F as ``G := h − F`` with h = min(h_a, h_b), the value of F far
        from both clouds, so ``field()``, ``inside()``, ``mesh()`` and ``save()`` all apply;
        flagged ``is_boolean`` (``method="union"``), so ``coarsen()`` and ``accumulate()``,
        which need a density of points, refuse it.
    """
    return _combine(a, b, "union")


def intersection(a: DensityField, b: DensityField) -> DensityField:
    """Intersection: F = max(F_a, F_b). See :func:`union` for parameters and the result, whose h
    here is max(h_a, h_b), the value of F far from both clouds."""
    return _combine(a, b, "intersection")


def difference(a: DensityField, b: DensityField) -> DensityField:
    """Difference a − b: F = max(F_a, −F_b), inside ``a`` and outside ``b``. See :func:`union`; h
    here is max(h_a, −h_b), the value of F far from both clouds.

    Examples
    --------
    >>> import numpy as np
    >>> import sdp
    >>> rng = np.random.default_rng(0)
    >>> a = sdp.DensityField.from_points(rng.normal(0.0, 0.1, (500, 3)), voxel_size=0.05)
    >>> b = sdp.DensityField.from_points(rng.normal([0.6, 0, 0], 0.1, (500, 3)), voxel_size=0.05)
    >>> sdp.difference(a, b).inside([[0, 0, 0], [0.6, 0, 0], [3, 0, 0]]).tolist()  # in a, in b, in neither
    [True, False, False]
    >>> sdp.difference(a, a).inside([[0, 0, 0]]).tolist()  # A − A is empty
    [False]
    """
    return _combine(a, b, "difference")


def difference_on_own_blocks(a: DensityField, b: DensityField) -> np.ndarray:
    """max(F_a, −F_b) at the nodes of ``a``'s blocks, float32 (m, 512).

    Outside ``a``'s blocks F_a = h_a > 0, so the difference volume (F < 0) lies entirely in
    them: change detection needs nothing else.
    """
    check_compatible(a, b)
    shift = a.grid.block_origin - b.grid.block_origin
    return difference_blocks(a.blocks.values, a.blocks.keys, a.h, b.blocks.values, b.blocks.directory, shift, b.h)

