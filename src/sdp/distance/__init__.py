"""Signed distances along the normal with their level of detection (M3C2's answer, from the
density kernel)."""

import lazy_loader as _lazy

# the public names are those of __init__.pyi, each loaded when first used
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
