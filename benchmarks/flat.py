"""The benchmarks' configurations as flat keyword dicts (one per table row, easy to print and
vary), mapped onto sdp's option objects (:mod:`sdp.options`) at the call.

``flat.detect_changes(ref, cur, voxel_size=0.02, sensor_origin=o)`` is
``sdp.detect_changes(ref, cur, lattice=sdp.Lattice(voxel_size=0.02), coverage=sdp.Coverage(sensor_origin=o))``.
"""

from __future__ import annotations

import sdp

_GROUPS = {
    "lattice": (sdp.Lattice, {"voxel_size": "voxel_size", "grid_size": "grid_size", "sigma_voxels": "sigma_voxels",
                              "k": "k", "h": "h", "truncate": "truncate", "method": "method"}),
    "coverage": (sdp.Coverage, {"sensor_origin": "sensor_origin", "range_noise": "range_noise",
                                "coverage": "enabled"}),
    "cylinder": (sdp.Cylinder, {"projection_scale": "projection_scale", "normal_scale": "normal_scale",
                                "max_distance": "max_distance"}),
    "execution": (sdp.Execution, {"tiled": "tiled", "tile_size": "tile_size", "tile_points": "tile_points",
                                  "scheduler": "scheduler", "workers": "workers", "workdir": "workdir"}),
}


def options(groups: tuple[str, ...], flat: dict) -> dict:
    """``flat``'s keywords of ``groups`` gathered into their option objects; the rest as given."""
    out = dict(flat)
    for group in groups:
        cls, names = _GROUPS[group]
        picked = {names[k]: out.pop(k) for k in list(out) if k in names}
        if picked:
            out[group] = cls(**picked)
    return out


def detect_changes(reference, current, **flat):
    return sdp.detect_changes(reference, current, **options(("lattice", "coverage"), flat))


def watch(reference, frames, **flat):
    return sdp.watch(reference, frames, **options(("lattice", "coverage"), flat))


def distances(reference, current, **flat):
    return sdp.distances(reference, current, **options(("cylinder",), flat))

