"""sdp: spatial density patterns for point-cloud comparison.

The package follows the data path, one subpackage per step:

- :mod:`sdp.io`: files to clouds (``(n, 3)`` float64 and per-point fields) and back;
- :mod:`sdp.fields`: a Gaussian density field per cloud on one global lattice, Boolean
  operations on fields, the surface F = 0, field files;
- :mod:`sdp.change`: what appeared and disappeared (masks, coverage, regions, scores);
- :mod:`sdp.distance`: signed distances along the normal with a level of detection;
- :mod:`sdp.registration`: the current scan moved onto the reference first;
- :mod:`sdp.stream`: a stream, frame by frame, against a model field;
- :mod:`sdp.scale`: the same path in tiles on Dask for clouds beyond memory, field stores;
- :mod:`sdp.timeseries`: many epochs against one reference in one archive, smoothed through time;
- :mod:`sdp.viz`: pictures and the one-page report;
- :mod:`sdp.actions`: action recognition from depth sequences;
- :mod:`sdp.cli`: the commands, as Python functions (files in, files out) and as the program;
- :mod:`sdp.data`: simulated scenes with known truth.

Every default is :data:`DEFAULTS` (:mod:`sdp.defaults`); every deliberate error an
:class:`SDPError` (:mod:`sdp.errors`); options shared by several commands are the small objects
of :mod:`sdp.options`. The public names are listed once, in ``__init__.pyi``, and each is
imported on first use (scikit-image's ``lazy_loader``): ``import sdp`` loads no extra and costs
milliseconds.

References
----------
.. [1] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
   Comparison and Applications".
"""

import os as _os

import lazy_loader as _lazy

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
__version__ = "0.1.0"  # the one place it is written: pyproject.toml reads it (dynamic version)


def _numba_cache() -> None:
    """Numba caches the kernels beside the sources, else under the user's ``~/.cache``, and
    stops with a traceback ("no locator available") when it can write neither: an install shared
    read-only, used by a service account without a home. There, a folder of the temporary
    directory, per user, holds the cache (an explicit ``NUMBA_CACHE_DIR`` is kept). Set before
    Numba is imported: it reads the variable once."""
    if _os.environ.get("NUMBA_CACHE_DIR") or _os.access(_os.path.dirname(__file__), _os.W_OK):
        return
    home = _os.path.expanduser("~")
    cache = _os.path.join(home, ".cache")
    if home != "~" and _os.access(cache if _os.path.isdir(cache) else home, _os.W_OK):
        return
    import tempfile

    _os.environ["NUMBA_CACHE_DIR"] = _os.path.join(tempfile.gettempdir(), f"sdp-numba-cache-{_os.getuid()}")


_numba_cache()
