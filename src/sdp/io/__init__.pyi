from ._io import (
    FORMATS,
    Cloud,
    CloudFileError,
    PointSource,
    all_or_none,
    atomic_path,
    check_outputs,
    read_points,
    refuse_overwrite,
    write_mesh,
    write_points,
    write_points_streamed,
)
