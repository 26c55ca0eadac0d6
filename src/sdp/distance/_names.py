"""The names other tools give the distances' fields, so that a file opens where people look.

``sdp distance`` writes its own names by default (:data:`sdp.distance._distances.DISTANCE_FIELDS`).
People who compare with M3C2 open the result in CloudCompare or run PDAL pipelines, whose
plugins name the same quantities otherwise, and whose tools (colour scales, filters, QGIS's
"PDAL Compare", built on PDAL's ``filters.m3c2``) look for those names:

- ``cloudcompare``: the qM3C2 plugin's scalar fields ``M3C2 distance``, ``distance uncertainty``
  (the level of detection), ``significant change``, ``STD_cloud1``/``STD_cloud2``,
  ``Npoints_cloud1``/``Npoints_cloud2``, and the normals as ``Nx``/``Ny``/``Nz``;
- ``pdal``: ``filters.m3c2``'s dimensions ``m3c2_distance``, ``m3c2_uncertainty``,
  ``m3c2_significant``, ``m3c2_std_dev1``/``m3c2_std_dev2``, ``m3c2_count1``/``m3c2_count2``,
  and PDAL's ``NormalX``/``NormalY``/``NormalZ``.

The counts (``n1``, ``n2``) are sdp's effective counts ``(Σw)²/Σw²`` of its Gaussian-weighted
cylinders, not whole numbers: what a hard cylinder (CloudCompare's, PDAL's) holding that many
points would give for the spread of the mean.

Every name is at most 32 characters, the length of a LAS extra-bytes name (ASPRS LAS 1.4 R15,
"Extra Bytes" VLR), so a LAS/LAZ output keeps them whole.

References
----------
.. [1] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
   terrestrial laser scanner", ISPRS J. Photogramm. 82 (2013) (M3C2).
.. [2] CloudCompare, qM3C2 plugin documentation (https://www.cloudcompare.org/doc/wiki/index.php/M3C2_(plugin)).
.. [3] PDAL, ``filters.m3c2`` (PDAL 2.10, https://pdal.io/en/latest/stages/filters.m3c2.html).
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidOptionError

__all__ = ["FIELD_NAMES", "rename_fields", "check_field_names"]

#: Field name → its name in each convention ("sdp": as written by default).
FIELD_NAMES = {
    "cloudcompare": {"distance": "M3C2 distance", "lod": "distance uncertainty", "significant": "significant change",
                     "spread1": "STD_cloud1", "spread2": "STD_cloud2", "n1": "Npoints_cloud1", "n2": "Npoints_cloud2",
                     "normal_x": "Nx", "normal_y": "Ny", "normal_z": "Nz"},
    "pdal": {"distance": "m3c2_distance", "lod": "m3c2_uncertainty", "significant": "m3c2_significant",
             "spread1": "m3c2_std_dev1", "spread2": "m3c2_std_dev2", "n1": "m3c2_count1", "n2": "m3c2_count2",
             "normal_x": "NormalX", "normal_y": "NormalY", "normal_z": "NormalZ"},
}


def check_field_names(convention: str) -> str:
    """``convention`` if it is ``"sdp"``, ``"cloudcompare"`` or ``"pdal"``, else a one-line
    :class:`~sdp.InvalidOptionError`."""
    if convention != "sdp" and convention not in FIELD_NAMES:
        raise InvalidOptionError(f"field_names must be one of sdp, {', '.join(FIELD_NAMES)}, got {convention!r}")
    return convention


def rename_fields(fields: dict[str, np.ndarray], convention: str, *, path=None) -> dict[str, np.ndarray]:
    """``fields`` under the names of ``convention`` (fields it does not name keep theirs). For a
    PLY ``path``, whose property names hold no space, spaces become underscores
    (``M3C2_distance``, as CloudCompare writes its scalar fields to PLY)."""
    names = {} if check_field_names(convention) == "sdp" else FIELD_NAMES[convention]
    ply = path is not None and str(path).lower().endswith(".ply")
    return {(names.get(k, k).replace(" ", "_") if ply else names.get(k, k)): v for k, v in fields.items()}
