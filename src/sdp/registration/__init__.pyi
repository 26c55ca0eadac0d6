from ._align import Alignment, align, transform_points
