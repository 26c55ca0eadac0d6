"""Visibility along the sensor's rays: new surfaces versus surfaces the other scan never saw.

A density difference says "the other cloud has no point here". For scans taken from known
sensor positions that has several causes, which the other scan's rays tell apart. Each changed
point is compared with the returns of the other scan along its ray (the range image cells
within one cell of the ray's own, in azimuth and elevation about the other scan's origin), with
a band ``b(r) = max(range_noise·r², band_floor·σ)`` of range noise (by default 0.015·r², at
least σ):

- **same surface** (:data:`SAME_SURFACE`): some return near the ray lies at the point's range
  (within [nearest − b, farthest + b] of a cell): range noise or drift of the sensor, not a
  change;
- **seen free** (:data:`SEEN_FREE`): every return near the ray lies farther than r + b: the
  other scan looked through the point's place and found it empty, so the point is new;
- **hidden** (:data:`HIDDEN`): a return near the ray stopped nearer than r − b, none at r: the
  other scan could not see the point's place (unless the point's own scan no longer holds the
  hiding surface where its own sensors could have seen it: then the place changed, whatever
  stood behind it; a hider's place the own sensors could not see either, such as the far face of
  a partition scanned from its other side, says nothing: :func:`gone_only_if_seen`);
- **unobserved** (:data:`UNOBSERVED`): no return near the ray. Inside the other scan's field
  of view and nearer than its farthest return, the ray found nothing in range: the place was
  free (as seen free; a surface that returns nothing is the exception). Outside the field of
  view (the convex hull of the cells with a return), or beyond the sensor's reach: not seen.

A hidden or unobserved point is explained, not a change, when it continues the unchanged
surface around it (it lies on the least-squares plane of its nearest unchanged neighbours,
and that patch is flat; Hoppe et al. [3], :mod:`sdp.change._planes`): that is the table a moved object uncovers, or the
border of a field of view that moved. A point the other scan says nothing of (not comparable)
must also lie within that patch's reach (twice its spread of its centre): farther, the plane
would be extrapolated over ground the other scan never saw. Otherwise (something where the
other scan could not look) it is not comparable (:data:`sdp.change._coverage.NOT_COMPARABLE`):
the other scan says nothing of it.

The other scan's returns come from its range image (:mod:`sdp.change._range_image`: spherical
cells of its angular spacing about its sensor, each with its nearest and farthest return; a
spinning LiDAR's sparse axis bridged between its rings), with a band ``b(r) =
max(range_noise·r², band_floor·σ)`` growing as a triangulation sensor's depth noise [2]. The
plane test is :mod:`sdp.change._planes`.

References
----------
.. [1] J. P. Underwood, D. Gillsjö, T. Bailey, V. Vlaskine, "Explicit 3D change detection using
   ray-tracing in spherical coordinates", ICRA 2013.
.. [2] K. Khoshelham, S. O. Elberink, "Accuracy and resolution of Kinect depth data for indoor
   mapping applications", Sensors 12(2), 2012.
.. [3] H. Hoppe, T. DeRose, T. Duchamp, J. McDonald, W. Stuetzle, "Surface reconstruction from
   unorganized points", SIGGRAPH 1992.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .._core._pinhole import Camera, fit_camera
from .._core._validate import as_sensor_origins
from ..defaults import DEFAULTS
from ..errors import InvalidPointsError
from ._coverage import CHANGED, NOT_COMPARABLE, UNCHANGED
from ._planes import explain_by_planes
from ._range_image import HIDDEN, SAME_SURFACE, SEEN_FREE, UNOBSERVED, RangeImage, sees

__all__ = ["as_sensor_origins", "depth_camera_units", "gone_only_if_seen", "image_camera", "rays_sent",
           "resolve_sensor_origins", "scanner_of_points", "sensor_band", "sensor_poles", "sensor_range_noise",
           "visibility_states"]

def resolve_sensor_origins(sensor_origin, reference, current) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(reference's, current's) sensor origin, each None when unknown.

    ``"auto"``: what each cloud knows (:attr:`sdp.Cloud.sensor_origin`, e.g. an organized
    PCD's VIEWPOINT; :attr:`sdp.Cloud.sensor_origins` of a multi-scan E57, then a (k, 3)
    array whose rows the cloud's :attr:`~sdp.Cloud.scan` indexes; arrays know nothing),
    ``"viewpoint"`` the same refusing a cloud that knows none; ``None`` or ``"none"``: no
    sensor; else a position (3,) for both or one per scan (2, 3), as :func:`as_sensor_origins`,
    or a pair whose unknown entry is None.
    """
    if sensor_origin is None or (isinstance(sensor_origin, str) and sensor_origin == "none"):
        return None, None
    if isinstance(sensor_origin, str):
        if sensor_origin not in ("auto", "viewpoint"):
            raise InvalidPointsError(f"sensor_origin must be 'auto', 'viewpoint', 'none', None or a position, "
                                     f"got {sensor_origin!r}")
        known = [_known_origins(c) for c in (reference, current)]
        if sensor_origin == "viewpoint" and any(o is None for o in known):
            raise InvalidPointsError("sensor_origin='viewpoint': a cloud records no sensor position (organized PCD "
                                     "and E57 files do); give a position or 'auto'")
        if any(o is not None and o.ndim == 2 for o in known):  # several scanners: the cloud's own
            return tuple(None if o is None else o.copy() for o in known)
        sensor_origin = known
    if isinstance(sensor_origin, (list, tuple)) and len(sensor_origin) == 2 and any(o is None for o in sensor_origin):
        return tuple(None if o is None else _one_cloud_origins(o) for o in sensor_origin)
    return as_sensor_origins(sensor_origin)


def _one_cloud_origins(value) -> np.ndarray:
    """One cloud's sensors given: a position (3,), or one per scan (k, 3) (the cloud's
    :attr:`~sdp.Cloud.scan` indexes its rows)."""
    try:
        o = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InvalidPointsError(f"sensor_origin: expected x, y, z of a sensor, or one row per scan ({exc})") from None
    if o.ndim == 2 and o.shape[0] >= 1 and o.shape[1] == 3:
        o = o[0] if len(o) == 1 else o
    if o.shape != (3,) and not (o.ndim == 2 and o.shape[1] == 3):
        raise InvalidPointsError(f"sensor_origin: expected x, y, z of a sensor (shape (3,)) or one row per scan "
                                 f"(shape (k, 3)), got shape {o.shape}")
    if not np.isfinite(o).all():
        raise InvalidPointsError(f"sensor_origin must be finite, got {o.tolist()}")
    return o.copy()


def _known_origins(cloud) -> np.ndarray | None:
    """What a cloud says of its sensors: None, one position (3,), or (k, 3) for k > 1 scanners."""
    many = getattr(cloud, "sensor_origins", None)
    if many is None:
        return getattr(cloud, "sensor_origin", None)
    many = np.asarray(many, np.float64)
    if not np.isfinite(many).all():
        raise InvalidPointsError(f"the cloud's sensor positions are not finite: {many.tolist()}")
    return many[0] if len(many) == 1 else many


def sensor_poles(cloud, origins) -> np.ndarray | None:
    """The vertical axis of each sensor at ``origins`` ((3,), or (k, 3): as resolved for
    ``cloud``), shaped as ``origins``: the cloud's :attr:`~sdp.Cloud.poles` where those are its
    own scanners (:attr:`~sdp.Cloud.sensors`, moved with it), else None (a position given
    otherwise, a cloud that does not say)."""
    poles, sensors = getattr(cloud, "poles", None), getattr(cloud, "sensors", None)
    if poles is None or sensors is None or origins is None:
        return None
    if not np.array_equal(np.reshape(origins, (-1, 3)), sensors):
        return None
    return poles[0].copy() if np.ndim(origins) == 1 else np.array(poles, np.float64)


def scanner_of_points(cloud, origins, n: int) -> np.ndarray | None:
    """Which of ``origins`` (k, 3) saw each of the ``n`` points of ``cloud`` (its
    :attr:`~sdp.Cloud.scan`), or None for one origin (3,) or none."""
    if origins is None or np.ndim(origins) == 1:
        return None
    scan = getattr(cloud, "scan", None)
    if scan is None or len(scan) != n:
        raise InvalidPointsError(f"{len(origins)} sensor positions but no scan index per point (Cloud.scan)")
    scan = np.asarray(scan, np.int64)
    if len(scan) and (scan.min() < 0 or scan.max() >= len(origins)):
        raise InvalidPointsError(f"a point's scan index is outside the {len(origins)} sensor positions")
    return scan


def visibility_states(points: np.ndarray, changed: np.ndarray, other: np.ndarray, other_origin: npt.ArrayLike,
                            *, sigma: float, range_noise: float = 0.015, band_floor: float = 1.0,
                            cell_factor: float = 1.5, reach: int = 1, plane_points: int = 50,
                            plane_stride: int = 8, plane_bin: float = 2.0, plane_distance: float = 2.0,
                            plane_flatness: float = 1.0,
                            spacing: float | None = None, image: RangeImage | None = None,
                            present=None, other_scan: np.ndarray | None = None,
                            pole: np.ndarray | None = None, gone=None, gone_reach: float = 6.0) -> np.ndarray:
    """What the other scan's view says of each changed point: unchanged, changed or not comparable.

    Parameters
    ----------
    points : ndarray (n, 3) float64
        The cloud whose changes are tested (finite rows): the current cloud for "appeared".
    changed : ndarray of bool (n,)
        The density decision.
    other : ndarray (m, 3) float64
        The cloud they changed against (the reference for "appeared"), seen from ``other_origin``.
    other_origin : array_like (3,) or (k, 3)
        The other scan's sensor position, in the same frame; or the positions of its k scanners
        (a multi-scan E57), with ``other_scan``.
    sigma : float
        The density kernel's σ (world units): the scale of the plane test and of the band's floor.
    range_noise : float
        The band grows as ``range_noise``·r² (per world unit: 1/m for metres). 0.015 m⁻¹ (1.5 cm
        at 1 m) covers a Kinect's depth noise and steps and the drift between its frames
        (about 1.2e-2·r² on the static PCL sequence).
    band_floor : float
        The band is at least ``band_floor``·σ: the density test's own resolution, and the
        constant range noise of laser scanners.
    cell_factor : float
        Range-image cell in units of the angular point spacing.
    reach : int
        Cells on each side of the ray's own cell whose returns are compared.
    plane_points, plane_stride : int
        The plane test fits ``plane_points`` nearest unchanged points taken from every
        ``plane_stride``-th unchanged point (a patch of about ``plane_points``·``plane_stride``
        points). Points in one cube of side ``plane_bin``·σ share the patch nearest to their
        mean (one neighbour query per cube; a patch's radius is about 10σ on Kinect frames. On the
        mOSD pairs kappa moves by < 0.001 from σ to 4σ; on the DLUT re-scans 3σ and more lose a
        62-point piece of a person that σ and 2σ keep).
    plane_distance, plane_flatness : float
        A hidden or unobserved point is explained when it lies within ``plane_distance``·σ of
        that plane and the patch is flat: RMS deviation from its plane below ``plane_flatness``·σ.
    spacing : float, optional
        Angular point spacing of ``other`` (radians); measured when None.
    image : RangeImage, optional
        ``RangeImage.from_points(other, other_origin, cell_factor=cell_factor, spacing=spacing)``
        built beforehand, for many calls against the same scan (:func:`sdp.watch`), or a callable
        that returns it (built when first needed).
    present : callable, optional
        ``present(xyz) -> bool mask``: does the points' own scan still hold something at these
        places (e.g. ``DensityField.inside`` of their own field)? A point hidden from the other
        scan behind a surface that is gone from its own scan (an object taken away, another put
        in its place) is judged as a seen point: by the plane test, else changed
        (:func:`gone_only_if_seen` widens it where the own sensors are known). Without it,
        every hidden point is treated as unseen.
    other_scan : ndarray of int (m,), optional
        With k positions: which scanner saw each point of ``other``. Each scanner's points make
        a range image seen from its position, and a point is judged by every one of them: the
        same surface for one of them: unchanged; else seen through by one of them: changed;
        else (hidden from or outside the view of every one) as a point one scan did not see.
        A point is not comparable only where no scanner of the other epoch could see it.
    pole : ndarray (3,) or (k, 3), optional
        The vertical of the other scan's sensor, or of each of its k scanners
        (:func:`sensor_poles`), about which its range images are laid out; None: their points' own.
    gone : ndarray of bool (m,) or callable, optional
        Which points of ``other`` the density finds gone (inside the other epoch's difference
        volume), or a callable ``gone(rows)`` giving that mask over ``other[rows]`` when the
        plane test first needs it. Every ``plane_stride``-th point of ``other`` is looked at (thinned
        as the unchanged points are): the unchanged points within ``gone_reach``·σ of one found
        gone are no part of a plane test's patch (:mod:`sdp.change._planes`). 6σ: twice the
        kernel's support at ``truncate=3``.

    Returns
    -------
    ndarray of uint8 (n,)
        :data:`sdp.change._coverage.UNCHANGED` where a changed point is explained (seen as the same
        surface, or hidden or unobserved and continuing the unchanged surface) and for the
        points not ``changed``; :data:`~sdp.change._coverage.CHANGED` where the other scan saw through
        the point's place; :data:`~sdp.change._coverage.NOT_COMPARABLE` where it could not see it
        (hidden, or no return near the ray: outside its field of view, or a dropout) and the
        point does not continue the unchanged surface.
    """
    changed = np.asarray(changed, dtype=bool)
    states = changed.astype(np.uint8)  # UNCHANGED / CHANGED
    cand = np.flatnonzero(changed)
    if len(cand) == 0:
        return states
    step = max(1, int(plane_stride))

    def gone_points():
        rows = slice(None, None, step)
        return other[np.flatnonzero(gone(rows) if callable(gone) else gone[rows]) * step]

    plane = dict(plane_points=plane_points, plane_stride=plane_stride, plane_distance=plane_distance * sigma,
                 plane_flatness=plane_flatness * sigma, plane_bin=plane_bin * sigma,
                 gone=None if gone is None else gone_points, gone_reach=gone_reach * sigma)
    if np.ndim(other_origin) == 2:
        return _many_scanners(points, changed, states, cand, other, np.asarray(other_origin, np.float64), other_scan,
                              range_noise=range_noise, floor=band_floor * sigma, cell_factor=cell_factor, reach=reach,
                              present=present, poles=pole, **plane)
    if callable(image):  # built when first needed, shared with whoever else needs it
        image = image()
    if image is None:
        image = RangeImage.from_points(other, other_origin, cell_factor=cell_factor, spacing=spacing, pole=pole)
    query = np.take(points, cand, axis=0)  # a plain gather of rows (fancy indexing takes a slower, general path)
    cls, hider = image.classify(query, range_noise=range_noise, floor=band_floor * sigma, reach=reach, hiders=True)
    states[cand[cls == SAME_SURFACE]] = UNCHANGED
    hidden, missing = cls == HIDDEN, cls == UNOBSERVED
    if present is not None and hidden.any():  # hidden behind what is still there: not seen
        states[cand[hidden]] = np.where(present(hider[hidden]), NOT_COMPARABLE, CHANGED)
    else:
        states[cand[hidden]] = NOT_COMPARABLE
    if missing.any():  # no return: free in range inside the field of view, unseen outside it
        states[cand[missing]] = np.where(image.seen_free(query[missing]), CHANGED, NOT_COMPARABLE)
    return explain_by_planes(points, changed, states, cand[hidden | missing], **plane)


def rays_sent(cloud) -> bool:
    """Did ``cloud``'s sensor send a ray along every direction of its view
    (:attr:`RangeImage.rays_sent`)? Yes for arrays (as a camera's frames are taken), an organized
    cloud (a PCD image, an organized bag message) and a scan with its grid (an E57's rows and
    columns); no for an unorganized file or message (a rosette scanner, a merged map)."""
    from ..io._cloud import Cloud

    return not isinstance(cloud, Cloud) or bool(cloud.organized) or "row" in cloud.fields


def image_camera(cloud, origin) -> Camera | None:
    """The pinhole camera of ``cloud``'s organized frame seen from one ``origin``
    (:func:`sdp._core._pinhole.fit_camera`: its range image is then the camera's pixels, every
    one a ray its sensor sent, whether it returned or not), or None: no image (an unorganized
    cloud, an array), several scanners, or returns that fit no pinhole camera."""
    image, pixels = getattr(cloud, "image", None), getattr(cloud, "pixels", None)
    if image is None or pixels is None or origin is None or np.ndim(origin) != 1 or len(pixels) != len(cloud.xyz):
        return None
    return fit_camera(cloud.xyz, pixels, image, origin)


def sensor_range_noise(cloud, range_noise: float, *, xyz: np.ndarray | None = None, origin=None) -> float:
    """The range noise of the rays' band for ``cloud``'s sensor (:func:`sensor_band`)."""
    return sensor_band(cloud, range_noise, xyz=xyz, origin=origin)[0]


def sensor_band(cloud, range_noise: float, *, xyz: np.ndarray | None = None, origin=None) -> tuple[float, float]:
    """(The range noise of the rays' band for ``cloud``'s sensor, the metres per unit it took):
    ``range_noise`` as given, except the default (a depth camera's, growing as r², per metre) where
    the cloud's format says what its sensor's is (:attr:`sdp.Cloud.range_noise`: an E57 or
    LAS/LAZ file's laser scans, millimetres at any range, whose band the floor σ bounds alone; at 4 m the
    default's 24 cm would take a partition's far face, 20 cm on, for its near one), or where the
    points (``xyz``, seen from one ``origin``) lie too far for a depth camera in metres: then per
    millimetre or centimetre (:func:`depth_camera_units`)."""
    own = getattr(cloud, "range_noise", None)
    if range_noise != DEFAULTS.range_noise:
        return float(range_noise), 1.0
    if own is not None:
        return float(own), 1.0
    units = depth_camera_units(xyz, origin) if xyz is not None and origin is not None and np.ndim(origin) == 1 \
        else 1.0
    return float(range_noise) * units, units


#: A depth camera sees no farther than about 10 m (a Kinect v1 4–8 m, ToF and stereo cameras up to
#: 10 m): a median range beyond 3 × that is not in metres.
_DEPTH_REACH = 30.0


def depth_camera_units(xyz: np.ndarray, origin) -> float:
    """Metres per unit of a depth camera's points ``xyz`` seen from ``origin``: 1, unless their
    median range exceeds :data:`_DEPTH_REACH` (no depth camera sees that far in metres: the
    default band, ``range_noise``·r² per metre, would be wider than half the range itself):
    millimetres (0.001) from a median range of 300 (a depth image's own unit, kept when its
    pixels become points), centimetres (0.01) below."""
    if not len(xyz):
        return 1.0
    step = max(1, len(xyz) // 2_000)
    r = float(np.median(np.linalg.norm(xyz[::step] - np.asarray(origin, np.float64), axis=1)))
    if not r > _DEPTH_REACH:
        return 1.0
    return 1e-3 if r >= 10 * _DEPTH_REACH else 1e-2


def gone_only_if_seen(present, own: np.ndarray, own_origin, own_scan=None, *, range_noise: float, floor: float,
                      image=None, other_origin=None, pole=None):
    """``present`` (:func:`visibility_states`) widened: a hider the point's own scan does not hold
    is gone only where that scan's sensors could have seen its place (the same surface there, seen
    through it, or no return inside their view); where they could not (hidden behind something,
    or outside their view: an unchanged object's far side, which a scanner on the other side saw),
    nothing says it is gone, and the point stays not comparable. ``own``: the points' own scan,
    seen from ``own_origin`` ((3,), or (k, 3) with ``own_scan``; None: ``present`` as it is);
    ``image``: its range image from a single origin, or a callable returning it; ``pole``: the
    own sensors' verticals, as ``own_origin`` (:func:`sensor_poles`), or None. A point's own
    sensor where the other's stood (a fixed camera) saw the hider's place: the point itself lies
    behind it on that ray, so ``present`` is returned as it is."""
    if present is None or own_origin is None:
        return present
    if other_origin is not None and np.shape(own_origin) == np.shape(other_origin) == (3,) \
            and np.allclose(own_origin, other_origin, rtol=0.0, atol=1e-9 * (1.0 + np.abs(own_origin).max())):
        return present
    origins = np.asarray(own_origin, np.float64)
    cache = {}

    def images():
        if "images" not in cache:
            if origins.ndim == 1:
                one = image() if callable(image) else image
                cache["images"] = [one if one is not None else RangeImage.from_points(own, origins, pole=pole)]
            else:
                cache["images"] = [RangeImage.from_points(own[own_scan == j], o, pole=None if pole is None else pole[j])
                                   for j, o in enumerate(origins) if (own_scan == j).any()]
        return cache["images"]

    def still_there(xyz):
        there = np.asarray(present(xyz), bool).copy()
        gone = np.flatnonzero(~there)
        if gone.size:
            query, seen = xyz[gone], np.zeros(gone.size, bool)
            for img in images():
                seen |= sees(img, query, range_noise=range_noise, floor=floor)
            there[gone[~seen]] = True
        return there

    return still_there


def _many_scanners(points, changed, states, cand, other, origins, other_scan, *, range_noise, floor, cell_factor,
                   reach, present, poles=None, **plane) -> np.ndarray:
    """:func:`visibility_states` against k scanners: each point takes the most informative answer
    of any scanner (0 same surface, 1 seen through, 2 unseen but changed: a free ray in view or
    a hider gone, 3 unseen), so the answer of one scanner is that of :func:`visibility_states`
    (``poles``: each scanner's vertical (k, 3), or None)."""
    if other_scan is None or len(other_scan) != len(other):
        raise InvalidPointsError(f"{len(origins)} sensor positions need the scanner of each point (other_scan)")
    query = points[cand]
    rank = np.full(len(cand), 3, np.int8)
    for j, origin in enumerate(origins):
        mine = other[other_scan == j]
        if len(mine) == 0 or not (rank > 0).any():
            continue
        image = RangeImage.from_points(mine, origin, cell_factor=cell_factor, pole=None if poles is None else poles[j])
        cls, hider = image.classify(query, range_noise=range_noise, floor=floor, reach=reach, hiders=True)
        r = np.full(len(cand), 3, np.int8)
        r[cls == SAME_SURFACE] = 0
        r[cls == SEEN_FREE] = 1
        hidden, missing = cls == HIDDEN, cls == UNOBSERVED
        if present is not None and hidden.any():
            r[hidden] = np.where(present(hider[hidden]), 3, 2)
        if missing.any():
            r[missing] = np.where(image.seen_free(query[missing]), 2, 3)
        np.minimum(rank, r, out=rank)
    states[cand[rank == 0]] = UNCHANGED
    states[cand[rank == 3]] = NOT_COMPARABLE
    return explain_by_planes(points, changed, states, cand[rank >= 2], **plane)
