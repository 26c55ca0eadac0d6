from ._cloud import FORMATS, Cloud, CloudFileError, ReadNotice
from ._output import all_or_none, atomic_path, check_outputs, refuse_overwrite, write_mesh, write_points
from ._read import read_points
from ._source import PointSource, write_points_streamed
