"""Pictures and the report: PNG and HTML views of changes, distances and fields; one page per
comparison."""

import lazy_loader as _lazy

# the public names are those of __init__.pyi, each loaded when first used
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
