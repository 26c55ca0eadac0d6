"""The commands: files in, files out, as Python functions (``compare_files``, …) and as the ``sdp``
program (:func:`main`, :func:`run`)."""

import lazy_loader as _lazy

# the public names are those of __init__.pyi, each loaded when first used
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
