"""What the commands share: which files are fields or stores, the sensor positions from the files,
the registration of the current scan, the pictures."""

from __future__ import annotations

import dataclasses

from pathlib import Path

import numpy as np

from ..errors import SDPError
from ..options import Registration

__all__ = ["is_store", "is_field", "disappeared_path", "sensor_origins", "same_frame", "align_clouds",
           "check_picture_extras", "pictures"]


def is_store(path) -> bool:
    return Path(path).suffix.lower() == ".zarr"


def is_field(path) -> bool:
    return Path(path).suffix.lower() == ".sdpf"


def disappeared_path(output) -> Path:
    """Where ``both=True`` writes the reference's labelled points: ``OUT_disappeared.EXT`` beside ``OUT.EXT``."""
    out = Path(output)
    return out.with_name(out.stem + "_disappeared" + out.suffix)


def sensor_origins(choice, ref_scan, cur_scan, alignment=None):
    """``sensor_origin=`` of :func:`sdp.detect_changes` from a checked ``--sensor-origin``
    (:func:`sdp._core._validate.sensor_origin_option`): ``auto``/``none`` as they are, ``viewpoint``
    as ``auto`` once both files (name, Cloud) record a position, a position for both scans
    (the current's moved by ``alignment``)."""
    if isinstance(choice, str):
        if choice == "viewpoint":
            for name, c in (ref_scan, cur_scan):
                if c.sensor_origins is None:
                    raise SDPError(f"{name}: the file records no sensor position (organized PCD and E57 files do); "
                                   "give --sensor-origin X,Y,Z or auto")
            return "auto"
        return choice
    cur_xyz = choice if alignment is None else alignment.apply(np.array([choice]))[0]
    return np.array([choice, cur_xyz], dtype=np.float64)


def same_frame(ref, cur, names) -> None:
    """Refuse (:class:`sdp.InvalidPointsError`, one line) two clouds that name different coordinate
    frames (:attr:`sdp.io.Cloud.frame`: a bag message's ``header.frame_id``): a cloud in ``map``
    against one in a camera's frame would be compared as if both were in one. A cloud that names
    none (a file) is taken to be in the other's frame; registering one onto the other (``--align``)
    puts them in one, so the caller skips this then."""
    if ref.frame is not None and cur.frame is not None and ref.frame != cur.frame:
        from ..errors import InvalidPointsError

        raise InvalidPointsError(f"{names[0]} is in frame {ref.frame!r}, {names[1]} in frame {cur.frame!r}: the "
                                 "points would be compared as if in one frame; give --align density (or gicp) to "
                                 "register them, or clouds in one frame (a bag's /tf, when it holds the "
                                 "transforms, moves its messages into map)")


def align_clouds(ref, cur, names, registration: Registration):
    """:func:`sdp.align` of the current Cloud onto the reference (a Cloud, or a DensityField),
    estimated on the points of the registration's LAS classes of both when given."""
    from ..fields._density import DensityField
    from ..registration._align import align

    ref_xyz = ref if isinstance(ref, DensityField) else ref.xyz
    cur_xyz = cur.xyz
    classes, align_class = registration.classes, registration.align_class
    if classes is not None:
        if isinstance(ref, DensityField):
            raise SDPError("--align-class needs the reference's points, not a field")
        picked = []
        for cloud, name in zip((ref, cur), names, strict=True):
            if "classification" not in cloud.fields:
                raise SDPError(f"{name}: no 'classification' field for --align-class (LAS/LAZ files have one)")
            keep = np.isin(cloud.fields["classification"], classes)
            if keep.sum() < 3:
                shown = align_class if isinstance(align_class, str) else ",".join(map(str, classes))
                raise SDPError(f"{name}: {int(keep.sum())} points of class {shown}: too few to align on")
            picked.append(cloud.xyz[keep])
        ref_xyz, cur_xyz = picked
    al = align(ref_xyz, cur_xyz, method=registration.method, fix_horizontal=registration.fix_horizontal)
    # the shift said is the whole scan's, not that of the classes it was estimated on
    return al if classes is None else dataclasses.replace(al, centre=cur.xyz.mean(axis=0))


def alignment_summary(alignment, registration: Registration) -> dict:
    """:meth:`sdp.Alignment.summary` with what the command asked of it, which the transform does not
    record: ``align_class`` (the LAS class numbers it was estimated on; None: every point) and
    ``fix_horizontal``."""
    return {**alignment.summary(), "align_class": registration.classes,
            "fix_horizontal": bool(registration.fix_horizontal)}


def check_picture_extras(*, png=None, html=None, report=None) -> None:
    """Before any work: the extras the asked-for pictures need (one-line :class:`sdp.MissingDependencyError`)."""
    from ..errors import require

    if png:
        require("matplotlib", "plots", "--png (a PNG)")
    if html:
        require("plotly", "plots", "--html (an HTML view)")
    if report:
        from ..viz._report import require_extras

        require_extras()


def pictures(png, html, xyz, changed, title, regions=()) -> list[str]:
    """Write the ``png`` / ``html`` pictures of changed points that were asked for (a map outlines ``regions``)."""
    if not (png or html):
        return []
    from ..viz._render import render_changes, render_changes_html

    written = []
    if png:
        render_changes(png, xyz, changed, title=title, regions=regions)
        written.append(str(png))
    if html:
        render_changes_html(html, xyz, changed, title=title)
        written.append(str(html))
    return written


def read_input(path, *, format: str | None = None, topic: str | None = None):
    """The Cloud of an input: a point-cloud file, or with ``topic`` one message of a ROS bag
    (:func:`sdp.io._bag.bag_message`: ``TOPIC`` its first, ``TOPIC:N`` its N-th)."""
    from ..io._bag import bag_message, is_bag, topic_needed
    from ..io._read import read_points

    if is_bag(path):
        if not Path(path).exists():
            raise SDPError(f"{path}: no such file or folder")
        if topic is None:
            raise topic_needed(path)
        return bag_message(path, topic)
    return read_points(path, format=format)
