"""sdp: spatial density patterns for point-cloud comparison.

The data path, one module per step: points → :class:`DensityField` (:mod:`sdp.field` on the
sparse grid of :mod:`sdp.grid`) → Boolean operations (:mod:`sdp.boolean`) → change masks
(:mod:`sdp.change`), where the other epoch could see (:mod:`sdp.coverage`, :mod:`sdp.visibility`)
→ regions (:mod:`sdp.regions`) → scores (:mod:`sdp.metrics`) and files
(:mod:`sdp.io`) and pictures (:mod:`sdp.render`; one page per comparison: :mod:`sdp.htmlreport`);
surfaces by :mod:`sdp.surface`, parameters from the data by :mod:`sdp.params`. Clouds beyond
memory: the same path in tiles on Dask
(:mod:`sdp.tiles`), reading files in slices (:class:`PointSource`) and keeping fields on disk
(:mod:`sdp.store`, Zarr). Files to files, as the ``sdp`` commands: :mod:`sdp.pipeline`
(:func:`compare_files` chooses memory or tiles by itself). Every default is :data:`DEFAULTS`
(:mod:`sdp.defaults`).

``import sdp`` needs only the core dependencies. The tiles and the field store need the
``tiles`` extra (Dask, Zarr), the
pictures of :mod:`sdp.render` ``plots`` (matplotlib, plotly), GICP ``align`` (small_gicp): each
is imported when first used, and a missing one raises :class:`MissingDependencyError` naming its
``pip install 'sdp[EXTRA]'``.

``import sdp`` imports only :mod:`sdp.defaults` and :mod:`sdp.errors`; every other public name
loads its module on first use (a module ``__getattr__``, as scikit-image's lazy loading): 27 ms
instead of 1.27 s, and a command loads only the modules it needs.

References
----------
.. [1] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
   Comparison and Applications".
"""

import sys
import types
from importlib import import_module
from typing import TYPE_CHECKING

from .defaults import DEFAULTS, Defaults
from .errors import (
                     FieldFileError,
                     GridTooLargeError,
                     IncompatibleFieldsError,
                     InvalidOptionError,
                     InvalidPointsError,
                     MissingDependencyError,
                     SDPError,
                     SurfaceError,
                     WorkerLostError,
)

# The rest is imported when first used (as scikit-image does): ``import sdp`` then costs
# milliseconds, and a command loads only the modules it needs (Numba, SciPy, Dask, …).
_LAZY = {name: module for module, names in {
    "align": ("Alignment", "align", "transform_points"),
    "boolean": ("difference", "intersection", "union"),
    "change": ("ChangeResult", "detect_changes"),
    "coverage": ("CHANGED", "NOT_COMPARABLE", "UNCHANGED", "footprint_covered"),
    "distance": ("Distances", "distances"),
    "field": ("DensityField", "threshold"),
    "grid": ("BLOCK", "Grid"),
    "htmlreport": ("change_report", "distance_report"),
    "io": ("CloudFileError", "PointSource", "check_outputs", "read_points", "write_mesh", "write_points",
           "write_points_streamed"),
    "metrics": ("confusion_matrix", "kappa", "scores"),
    "online": ("FrameChange", "watch"),
    "params": ("auto_voxel_size",),
    "pipeline": ("ChangePlan", "FileComparison", "FileDistances", "compare_files", "distance_files", "plan_change"),
    "regions": ("Region",),
    "render": ("render_changes", "render_changes_html", "render_distances", "render_field"),
    "store": ("FieldStore",),
    "surface": ("Mesh", "extract_surface"),
    "tiles": ("TiledChanges", "build_field_tiled", "detect_changes_tiled", "distances_tiled"),
}.items() for name in names}


def __getattr__(name: str):
    """A public name, or a submodule (``sdp.tiles``), imported on first use."""
    module = _LAZY.get(name)
    if module is None:
        try:
            return import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = getattr(import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


class _Package(types.ModuleType):
    """``sdp`` itself: importing the submodule ``sdp.align`` must not hide the function
    ``sdp.align`` (Python binds a submodule on its package once imported)."""

    def __setattr__(self, name, value):
        if not (isinstance(value, types.ModuleType) and name in _LAZY):
            super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


if TYPE_CHECKING:  # what static tools and IDEs read
    from .align import Alignment, align, transform_points
    from .boolean import difference, intersection, union
    from .change import ChangeResult, detect_changes
    from .coverage import CHANGED, NOT_COMPARABLE, UNCHANGED, footprint_covered
    from .distance import Distances, distances
    from .field import DensityField, threshold
    from .grid import BLOCK, Grid
    from .htmlreport import change_report, distance_report
    from .io import (
                     CloudFileError,
                     PointSource,
                     check_outputs,
                     read_points,
                     write_mesh,
                     write_points,
                     write_points_streamed,
    )
    from .metrics import confusion_matrix, kappa, scores
    from .online import FrameChange, watch
    from .params import auto_voxel_size
    from .pipeline import ChangePlan, FileComparison, FileDistances, compare_files, distance_files, plan_change
    from .regions import Region
    from .render import render_changes, render_changes_html, render_distances, render_field
    from .store import FieldStore
    from .surface import Mesh, extract_surface
    from .tiles import TiledChanges, build_field_tiled, detect_changes_tiled, distances_tiled


__all__ = [
    "DensityField", "threshold", "Grid", "BLOCK",
    "union", "intersection", "difference",
    "DEFAULTS", "Defaults",
    "detect_changes", "ChangeResult", "Region",
    "distances", "Distances",
    "UNCHANGED", "CHANGED", "NOT_COMPARABLE", "footprint_covered",
    "detect_changes_tiled", "distances_tiled", "TiledChanges", "build_field_tiled", "FieldStore",
    "compare_files", "plan_change", "FileComparison", "ChangePlan", "distance_files", "FileDistances",
    "align", "Alignment", "transform_points",
    "watch", "FrameChange",
    "extract_surface", "Mesh",
    "auto_voxel_size",
    "read_points", "write_points", "write_mesh", "PointSource", "write_points_streamed", "check_outputs",
    "render_changes", "render_changes_html", "render_distances", "render_field",
    "change_report", "distance_report",
    "kappa", "confusion_matrix", "scores",
    "SDPError", "InvalidPointsError", "GridTooLargeError", "IncompatibleFieldsError", "SurfaceError",
    "FieldFileError", "CloudFileError", "MissingDependencyError", "InvalidOptionError",
    "WorkerLostError",
]
__version__ = "0.1.0"  # the one place it is written: pyproject.toml reads it (dynamic version)
