"""Point-cloud files: readers per format, :class:`PointSource` (files in row slices) and outputs
written all or none.

One private module per format, each with its reader and its writer: ``_pcd`` (pypcd4),
``_ply`` (plyfile), ``_las`` (laspy with lazrs; header checks before laspy reads), ``_text``
(XYZ/TXT/CSV/PTS), ``_numpy`` (NPY/NPZ). ``_cloud`` holds what they share (:class:`Cloud`,
:class:`CloudFileError`, :data:`FORMATS`, the one-line error of a library's failure);
``_read`` holds :func:`read_points` (dispatch by extension), ``_output`` the output transaction
(:func:`check_outputs`, :func:`atomic_path`, :func:`all_or_none`) and :func:`write_points` /
:func:`write_mesh`, ``_source`` :class:`PointSource` and :func:`write_points_streamed`.
Imports run one way: ``_cloud`` ← formats ← ``_read``, ``_output`` ← ``_source``.
"""

import lazy_loader as _lazy

# the public names are those of __init__.pyi, each loaded when first used
__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)
