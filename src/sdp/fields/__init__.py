"""Density fields on one global lattice: the lattice, the sparse blocks, building G, Boolean
operations, the surface F = 0 and field files."""

import lazy_loader as _lazy

# the public names are those of __init__.pyi, each loaded when first used
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
