"""Many epochs: distances of each epoch against one reference at fixed core points, appended epoch
by epoch into one Zarr archive, smoothed through time (Kalman), with onsets and 4D objects of change."""

import lazy_loader as _lazy

# the public names are those of __init__.pyi, each loaded when first used
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
