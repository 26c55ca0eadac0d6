"""Point-cloud files: readers per format, :class:`PointSource` (files in row slices) and outputs
written all or none."""

import lazy_loader as _lazy

# the public names are those of __init__.pyi, each loaded when first used
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
