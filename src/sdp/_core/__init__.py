"""Shared internals: option checks, point arrays, threads, progress bars, nearest neighbours."""

import lazy_loader as _lazy

# the public names are those of __init__.pyi, each loaded when first used
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
