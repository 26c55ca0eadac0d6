# The one list of sdp's public names (read by lazy_loader at import, and by static tools).
from . import actions, change, cli, data, distance, fields, io, registration, scale, stream, timeseries, viz
from .change import (
    CHANGED,
    NOT_COMPARABLE,
    UNCHANGED,
    ChangeResult,
    Region,
    confusion_matrix,
    detect_changes,
    footprint_covered,
    kappa,
    scores,
)
from .cli import ChangePlan, FileComparison, FileDistances, compare_files, distance_files, plan_change
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
    WorkerLostError,
)
from .fields import (
    BLOCK,
    DensityField,
    Grid,
    Mesh,
    auto_voxel_size,
    difference,
    extract_surface,
    intersection,
    threshold,
    union,
)
from .io import (
    Cloud,
    CloudFileError,
    PointSource,
    check_outputs,
    read_points,
    write_mesh,
    write_points,
    write_points_streamed,
)
from .options import Coverage, Cylinder, Execution, Lattice, NoiseModel, Outputs, Registration
from .registration import Alignment, align, transform_points
from .scale import FieldStore, build_field_tiled, detect_changes_tiled, distances_tiled
from .stream import FrameChange, watch
from .timeseries import open_series, series
from .viz import change_report, distance_report, render_changes, render_changes_html, render_distances, render_field

__version__: str
