"""sdp: spatial density patterns for point-cloud comparison.

The data path, one module per step: points → :class:`DensityField` (:mod:`sdp.field` on the
sparse grid of :mod:`sdp.grid`) → Boolean operations (:mod:`sdp.boolean`) → change masks
(:mod:`sdp.change`), where the other epoch could see (:mod:`sdp.coverage`, :mod:`sdp.visibility`)
→ regions (:mod:`sdp.regions`) → scores (:mod:`sdp.metrics`) and files
(:mod:`sdp.io`) and pictures (:mod:`sdp.render`); surfaces by :mod:`sdp.surface`, parameters
from the data by :mod:`sdp.params`. Clouds beyond memory: the same path in tiles on Dask
(:mod:`sdp.tiles`), reading files in slices (:class:`PointSource`) and keeping fields on disk
(:mod:`sdp.store`, Zarr). Files to files, as the ``sdp`` commands: :mod:`sdp.pipeline`
(:func:`compare_files` chooses memory or tiles by itself). Every default is :data:`DEFAULTS`
(:mod:`sdp.defaults`).

``import sdp`` needs only the core dependencies. The tiles and the field store need the
``tiles`` extra (Dask, Zarr), :mod:`sdp.actions`' classifier ``actions`` (scikit-learn), the
pictures of :mod:`sdp.render` ``plots`` (matplotlib, plotly), GICP ``align`` (small_gicp): each
is imported when first used, and a missing one raises :class:`MissingDependencyError` naming its
``pip install 'sdp[EXTRA]'``.

References
----------
.. [1] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
   Comparison and Applications".
"""

from .align import Alignment, align, transform_points
from .boolean import difference, intersection, union
from .change import ChangeResult, detect_changes
from .coverage import CHANGED, NOT_COMPARABLE, UNCHANGED, footprint_covered
from .defaults import DEFAULTS, Defaults
from .distance import Distances, distances
from .errors import (
                     FieldFileError,
                     GridTooLargeError,
                     IncompatibleFieldsError,
                     InvalidOptionError,
                     InvalidPointsError,
                     MissingDependencyError,
                     SDPError,
                     SurfaceError,
)
from .field import DensityField, threshold
from .grid import BLOCK, Grid
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
    "kappa", "confusion_matrix", "scores",
    "SDPError", "InvalidPointsError", "GridTooLargeError", "IncompatibleFieldsError", "SurfaceError",
    "FieldFileError", "CloudFileError", "MissingDependencyError", "InvalidOptionError",
]
__version__ = "0.1.0"  # the one place it is written: pyproject.toml reads it (dynamic version)
