"""The options that several commands and functions share, as small frozen objects.

Each object groups one concern and is checked once, when it is made, with the same one-line
:class:`sdp.InvalidOptionError` wherever it is used, before any file is read:

- :class:`Lattice`: where a density field lives (voxel or grid size, σ, threshold, build method);
- :class:`Coverage`: where the other scan could see (its sensor, the range noise);
- :class:`Registration`: how the current scan is moved onto the reference first;
- :class:`Cylinder`: the neighbourhoods of the distances (M3C2's projection and normal scales);
- :class:`NoiseModel`: the sensor's noise, which the combined decision's level of detection
  is made of (the systematic part, its growth with range, correlated errors);
- :class:`Execution`: how and where the work runs (memory limit, tiles on Dask, work folder);
- :class:`Outputs`: what a command writes besides its main output (pictures, report, the
  reference's points).

Every default is :data:`sdp.DEFAULTS`; each function documents only what it adds. The command
line maps its flags onto these objects (``sdp change --voxel-size 0.02`` is
``Lattice(voxel_size=0.02)``).

Examples
--------
>>> import sdp
>>> sdp.Lattice(voxel_size=0.02)
Lattice(voxel_size=0.02, grid_size=None, sigma_voxels='auto', k=3.0, h=None, truncate=3.0, method='auto')
>>> sdp.Lattice(voxel_size=-1)
Traceback (most recent call last):
...
sdp.errors.InvalidOptionError: voxel_size must be 'auto' or a positive finite length, got -1
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ._core import _validate as V
from .defaults import DEFAULTS
from .errors import InvalidOptionError

__all__ = ["Lattice", "Coverage", "Registration", "Cylinder", "NoiseModel", "Execution", "Outputs", "as_options"]

PathLike = str | os.PathLike


@dataclass(frozen=True, kw_only=True)
class Lattice:
    """Where a density field lives: the lattice, the kernel and the threshold.

    Attributes
    ----------
    voxel_size : float or "auto"
        Node spacing in world units (metres for sensor data), or ``"auto"``: σ from the clouds'
        point spacing (:func:`sdp.auto_voxel_size`).
    grid_size : int, optional
        The paper's parameterization instead: the longest side of the box holding every cloud
        divided into ``grid_size`` segments (80 in the paper); with a ``voxel_size`` given too,
        refused (one of them sets the lattice).
    sigma_voxels : float or "auto"
        The Gaussian's σ in voxels; ``"auto"``: 1.5 on the automatic lattice, the paper's 2
        with a given voxel or grid size.
    k : float
        Threshold h = 1 + k·e^(−1/2) (a point needs about k neighbours at σ).
    h : float, optional
        The threshold itself (wins over ``k``).
    truncate : float
        Kernels cut at ``truncate``·σ.
    method : {"auto", "fast", "exact"}
        How G is built (:meth:`sdp.DensityField.from_points`).

    References
    ----------
    .. [1] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
       Comparison and Applications" (σ = 2 voxels, h = 1 + 3·e^(−1/2), 80³ grids).
    """

    voxel_size: float | str = DEFAULTS.voxel_size
    grid_size: int | None = None
    sigma_voxels: float | str = DEFAULTS.sigma_voxels
    k: float = DEFAULTS.k
    h: float | None = None
    truncate: float = DEFAULTS.truncate
    method: str = DEFAULTS.method

    def __post_init__(self):
        if self.grid_size is not None:
            V.integer_at_least("grid_size", self.grid_size, 1)
            if self.voxel_size not in (None, "auto"):
                raise InvalidOptionError("give grid_size= or voxel_size=, not both")
        if self.k is None and self.h is None:
            raise InvalidOptionError("the threshold needs k (h = 1 + k·e^-1/2) or h, got neither")
        if self.h is not None and self.k not in (None, DEFAULTS.k):  # h wins: a k given would be ignored
            raise InvalidOptionError("give k or h, not both: h = 1 + k·e^-1/2")
        voxel = V.check_grid_options(voxel_size=None if self.grid_size is not None else self.voxel_size,
                                     sigma_voxels=self.sigma_voxels, k=self.k, h=self.h, truncate=self.truncate)
        # kept as the numbers they were checked as: a string that reads as one ("2") is not passed on
        numbers = {"k": None if self.k is None else V.finite("k", self.k), "truncate": V.positive_finite(
            "truncate", self.truncate), "h": None if self.h is None else V.positive_finite("h", self.h)}
        if voxel is not None:
            numbers["voxel_size"] = voxel
        if self.grid_size is not None:
            numbers["grid_size"] = V.integer_at_least("grid_size", self.grid_size, 1)
        if not isinstance(self.sigma_voxels, str):
            numbers["sigma_voxels"] = V.positive_finite("sigma_voxels", self.sigma_voxels)
        for name, value in numbers.items():
            object.__setattr__(self, name, value)
        if self.method not in ("auto", "exact", "fast"):
            raise InvalidOptionError(f"method must be 'auto', 'exact' or 'fast', got {self.method!r}")

    @property
    def automatic(self) -> bool:
        """Whether the voxel size comes from the point spacing."""
        return self.grid_size is None and self.voxel_size in (None, "auto")

    def keywords(self) -> dict:
        """The keywords of :meth:`sdp.DensityField.from_points` (``grid_size`` or ``voxel_size``)."""
        size = {"grid_size": self.grid_size} if self.grid_size is not None else {"voxel_size": self.voxel_size}
        return dict(size, sigma_voxels=self.sigma_voxels, k=self.k, h=self.h, truncate=self.truncate,
                    method=self.method)


@dataclass(frozen=True, kw_only=True, eq=False)
class Coverage:
    """Where the other scan could see: "not seen" is not "changed".

    Attributes
    ----------
    sensor_origin : "auto", "none", "viewpoint", "X,Y,Z" or array_like (3,) or (2, 3)
        Where the sensor stood, in the clouds' frame. ``"auto"``: what each file records (an
        organized PCD's VIEWPOINT), nothing for arrays; ``"viewpoint"``: the same, refusing
        files that record none; ``"none"`` (or None): no sensor, the other scan's footprint
        decides; one position for both scans, or the reference's and the current's. Changed
        points are followed along the other scan's rays (:func:`sdp.detect_changes`).
    range_noise : float
        "The same range" is within ``range_noise``·r² world units at range r (per metre for
        metres), and at least σ.
    enabled : bool
        False: every point is comparable, as the paper's Algorithm 1.

    References
    ----------
    .. [1] J. P. Underwood et al., "Explicit 3D change detection using ray-tracing in spherical
       coordinates", ICRA 2013.
    """

    sensor_origin: str | np.ndarray | None = DEFAULTS.sensor_origin
    range_noise: float = DEFAULTS.range_noise
    enabled: bool = True

    def __post_init__(self):
        origin = self.sensor_origin
        if origin is None or isinstance(origin, str):
            origin = V.sensor_origin_option("sensor_origin", origin)
        if not isinstance(origin, str):
            V.as_sensor_origins(origin)  # one position or two, finite
            origin = np.array(origin, dtype=np.float64)
            origin.flags.writeable = False
        object.__setattr__(self, "sensor_origin", origin)
        V.nonnegative_finite("range_noise", self.range_noise)
        V.boolean("enabled", self.enabled)
        if isinstance(origin, str) and origin == "none" and self.range_noise != DEFAULTS.range_noise:
            raise InvalidOptionError("range_noise is the sensor rays' band; with sensor_origin none (the footprint "
                                     "decides) it would be ignored")

    @property
    def given(self) -> bool:
        """Whether a sensor position is given (not read from the files, not none)."""
        return not isinstance(self.sensor_origin, str)


@dataclass(frozen=True, kw_only=True)
class Registration:
    """How the current scan is moved onto the reference before a comparison, by :func:`sdp.align`
    (which itself takes the method by name): ``align=`` of :func:`sdp.compare_files`,
    :func:`sdp.distance_files`, :func:`sdp.watch` and :func:`sdp.series`.

    Attributes
    ----------
    method : {"density", "gicp"}
        ``"density"``: point-to-plane Gauss–Newton on the ridges of the reference's density;
        ``"gicp"``: small_gicp's GICP (extra ``align``).
    fix_horizontal : bool
        Density method only: estimate the vertical shift and the tilts, keep x, y and the
        heading (airborne epochs whose ground is flat).
    align_class : str, int or sequence of int, optional
        Estimate the transform on the points of these LAS classes (``"2"``: ground) of both
        scans, then move the whole current scan.
    """

    method: str = DEFAULTS.align_method
    fix_horizontal: bool = False
    align_class: str | int | Sequence[int] | None = None

    def __post_init__(self):
        if self.method not in ("density", "gicp"):
            raise InvalidOptionError(f"method must be 'density' or 'gicp', got {self.method!r}")
        V.check_alignment_options(self.method, fix_horizontal=self.fix_horizontal, align_class=self.align_class)

    @property
    def classes(self) -> list[int] | None:
        """The LAS class numbers of ``align_class`` (None: every point)."""
        return V.check_alignment_options(self.method, fix_horizontal=self.fix_horizontal,
                                         align_class=self.align_class)

    @classmethod
    def of(cls, value: Registration | str | None) -> Registration | None:
        """``value`` as a Registration: None stays None (no alignment), a method name is that
        method with the other defaults."""
        if value is None or isinstance(value, Registration):
            return value
        if isinstance(value, str):
            return cls(method=value)
        raise InvalidOptionError(f"align must be 'density', 'gicp', a Registration or None, got {value!r}")


@dataclass(frozen=True, kw_only=True)
class Cylinder:
    """The neighbourhoods of the signed distances (M3C2's parameters, in world units).

    Attributes
    ----------
    projection_scale : float or "auto"
        Diameter d of the cylinder whose points give each epoch's position along the normal;
        ``"auto"``: 4σ of the density kernel, so distances and change masks look at the same
        neighbourhood.
    normal_scale : float or "auto"
        Diameter D of the neighbourhood of the normal; ``"auto"``: 2d, raised to 20× the
        roughness at that scale, at most 4d.
    max_distance : float or "auto"
        How far along the normal each epoch is looked for; ``"auto"``: 12d. Never less than the
        cylinder's own half-length, 0.75d (the kernel's 3σ, where its weights are cut): a smaller
        value searches that far (M3C2's "max depth" can be shorter than its cylinder; sdp's cylinder
        is the kernel, and the summary gives the reach used).

    References
    ----------
    .. [1] D. Lague, N. Brodu, J. Leroux, "Accurate 3D comparison of complex topography with
       terrestrial laser scanner", ISPRS J. Photogramm. 82 (2013).
    """

    projection_scale: float | str = DEFAULTS.projection_scale
    normal_scale: float | str = DEFAULTS.normal_scale
    max_distance: float | str = DEFAULTS.max_distance

    def __post_init__(self):
        for name in ("projection_scale", "normal_scale", "max_distance"):
            V.auto_or_positive(name, getattr(self, name))


@dataclass(frozen=True, kw_only=True)
class NoiseModel:
    """The sensor's noise, which the level of detection of ``decision="combined"`` is made of
    (:mod:`sdp.distance._noise`): ``lod = 1.96·√(random + (σ_s·(r/r̃)^p)²)`` at range r along
    the point's own sensor's ray (r̃ the median range). What is not given is measured on the
    stable majority of the pair (the points the density left unchanged).

    Attributes
    ----------
    registration_error : float or "auto"
        The systematic part as M3C2's ``reg`` (σ_s = reg/1.96, world units): registration,
        calibration and errors shared by many points; ``"auto"``: the smallest for which at most
        5 % of the stable majority lie beyond the level.
    range_exponent : float or "auto"
        p in [0, 2]: how the systematic part grows along the ray, 2 for a structured-light depth
        camera (σ_z ∝ z²), 0 for a laser scanner; ``"auto"``: fitted on the stable majority where
        the sensor is known (else 0).
    correlation_length : float, optional
        Errors correlated over this length (world units, e.g. a depth camera's matching window
        at its range): a cylinder of diameter d (4σ) then counts at most (d/2ℓ)² independent points;
        None: every point independent, what correlation adds shows in the measured systematic
        part.

    References
    ----------
    .. [1] D. Lague, N. Brodu, J. Leroux (2013), M3C2's level of detection; K. Khoshelham,
       S. O. Elberink (2012), a Kinect's σ_z ∝ z²; C. S. Bretherton et al. (1999), effective
       counts of correlated data.
    """

    registration_error: float | str = DEFAULTS.registration_error
    range_exponent: float | str = DEFAULTS.range_exponent
    correlation_length: float | None = DEFAULTS.correlation_length

    def __post_init__(self):
        object.__setattr__(self, "registration_error",
                           V.auto_or_nonnegative("registration_error", self.registration_error))
        object.__setattr__(self, "range_exponent", V.auto_or_exponent("range_exponent", self.range_exponent))
        if self.correlation_length is not None:  # kept as the number it was checked as
            object.__setattr__(self, "correlation_length",
                               V.positive_finite("correlation_length", self.correlation_length))

    @property
    def given(self) -> dict:
        """The parts given rather than measured (name → value)."""
        return {k: v for k, v in self.arguments().items() if v != getattr(DEFAULTS, k)}

    @classmethod
    def of(cls, value: NoiseModel | None, decision: str) -> NoiseModel:
        """``value`` (None: every part measured) for ``decision``; a model that gives some part is
        refused with a decision that has no level of detection to give it to."""
        value = cls() if value is None else value
        if not isinstance(value, NoiseModel):
            raise InvalidOptionError(f"noise must be a NoiseModel or None, got {value!r}")
        if value.given and decision != "combined":
            raise InvalidOptionError("the noise model (--registration-error, --range-exponent, --correlation-length) "
                                     "is the combined decision's level of detection: give --decision combined")
        return value

    def arguments(self) -> dict:
        """The keywords of :class:`sdp.distance._noise.SurfaceDistances`."""
        return {"registration_error": self.registration_error, "range_exponent": self.range_exponent,
                "correlation_length": self.correlation_length}


@dataclass(frozen=True, kw_only=True)
class Execution:
    """How and where the work runs.

    Attributes
    ----------
    memory_limit : int, float, str, optional
        The whole job's memory (bytes, or ``"2GB"``); default ``$SDP_MEMORY_LIMIT``, else 4 GiB.
        Work that would exceed it is refused before anything is allocated, or taken to tiles.
    tiled : bool
        Work in tiles on Dask even when the clouds fit in memory (extra ``tiles``).
    tile_size : float, optional
        Tile edge in world units (default: from the memory limit and the point density).
    tile_points : int, optional
        Points per tile aimed at, instead of ``tile_size``.
    scheduler : str, optional
        A Dask scheduler's address (``tcp://host:8786``); default: a local cluster.
    workers : int, optional
        Workers of the local cluster (default: the cores).
    workdir : path-like, optional
        Folder for the tiles' intermediate files (default: the system's temporary folder).
    notify : callable, optional
        Called with one line when a run switches to tiles by itself, once the tiles are taken
        (their sizes checked against the memory limit).
    switched : (str, float), optional
        Set by the plans of the commands (:func:`sdp.compare_files`, …), not given: why the run
        switched to tiles by itself (the line ``notify`` gets) and the memory limit it would run
        in memory under (bytes). Tiles that can't fit then name the smaller of that and their own
        minimum as the limit to give.
    """

    memory_limit: int | float | str | None = None
    tiled: bool = False
    tile_size: float | None = None
    tile_points: int | None = None
    scheduler: str | None = None
    workers: int | None = None
    workdir: PathLike | None = None
    notify: Callable[[str], object] | None = field(default=None, compare=False)
    switched: tuple[str, float] | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        from ._core._memory import memory_limit

        memory_limit(self.memory_limit)
        V.boolean("tiled", self.tiled)
        V.check_tile_options(tile_size=self.tile_size, tile_points=self.tile_points, workers=self.workers,
                             workdir=self.workdir, scheduler=self.scheduler)
        # kept as the numbers they were checked as: a string that reads as one ("0.5") is not passed on
        if self.tile_size is not None:
            object.__setattr__(self, "tile_size", V.positive_finite("tile_size", self.tile_size))
        for name in ("tile_points", "workers"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, V.integer_at_least(name, getattr(self, name), 1))
        if self.notify is not None and not callable(self.notify):
            raise InvalidOptionError(f"notify must be a function taking one line of text, got {self.notify!r}")

    def tiles_only(self) -> list[str]:
        """The options given that only tiles use, by their command-line names: in memory a run
        says it leaves them (:meth:`say_in_memory`)."""
        names = {"tile_size": "--tile-size", "tile_points": "--tile-points", "scheduler": "--scheduler",
                 "workers": "--workers", "workdir": "--workdir"}
        return [flag for name, flag in names.items() if getattr(self, name) is not None]

    def say_in_memory(self, tiles: str = "--tiled, or work beyond --memory-limit") -> None:
        """Tell ``notify`` that a run in memory leaves the tiles' options given (a cluster's address
        does not send the work there by itself: the run fits in memory); ``tiles`` says what
        takes a run to tiles."""
        unused = self.tiles_only()
        if unused and self.notify is not None:
            self.notify(f"in memory: {', '.join(unused)} used by tiles only ({tiles})")

    def tile_keywords(self) -> dict:
        """The keywords of a tiled run's session (:class:`sdp.scale._session.Session`), which the
        tiled functions (:func:`sdp.detect_changes_tiled`, …) start."""
        return dict(tile_size=self.tile_size, tile_points=self.tile_points, memory_limit=self.memory_limit,
                    scheduler=self.scheduler, workers=self.workers, workdir=self.workdir, notify=self.notify,
                    switched=self.switched)


@dataclass(frozen=True, kw_only=True)
class Outputs:
    """What a command writes besides its main output (checked with it, written all or none).

    Attributes
    ----------
    both : bool
        ``sdp change``: also the reference's points labelled as disappeared, beside the output
        (``OUT_disappeared.EXT``).
    png : path-like, optional
        A picture: a top-down map for scenes much wider than tall, else three 3-D views.
    html : path-like, optional
        An interactive 3-D view (plotly).
    report : path-like, optional
        One self-contained HTML page: summary, parameters and why, maps, region table, 3-D view.
    aligned : bool
        With a registration, write the current's points where the alignment moved them (default:
        its own coordinates).
    field_names : {"sdp", "cloudcompare", "pdal"}
        ``sdp distance``: the names of the distances' fields in the output: sdp's own, or those
        of CloudCompare's M3C2 plugin or PDAL's ``filters.m3c2`` (:mod:`sdp.distance._names`).
    """

    both: bool = False
    png: PathLike | None = None
    html: PathLike | None = None
    report: PathLike | None = None
    aligned: bool = False
    field_names: str = DEFAULTS.field_names

    def __post_init__(self):
        if self.field_names not in ("sdp", "cloudcompare", "pdal"):
            raise InvalidOptionError(f"field_names must be one of sdp, cloudcompare, pdal, got {self.field_names!r}")
        for name in ("png", "html", "report"):
            V.picture_path(name, getattr(self, name))
        for name in ("both", "aligned"):
            V.boolean(name, getattr(self, name))

    @property
    def pictures(self) -> bool:
        """Whether a picture or a report is asked for (made in memory)."""
        return bool(self.png or self.html or self.report)

    def only(self, command: str, *names: str) -> "Outputs":
        """``self`` if it asks for nothing but the outputs ``names`` that ``command`` writes, else
        a one-line :class:`~sdp.InvalidOptionError` naming the first it would ignore."""
        default = Outputs()
        what = {"both": "the reference's labelled copy", "png": "a PNG picture", "html": "an HTML view",
                "report": "a report", "aligned": "aligned coordinates", "field_names": "other tools' field names"}
        for name, thing in what.items():
            if name not in names and getattr(self, name) != getattr(default, name):
                raise InvalidOptionError(f"{command} does not write {thing} (outputs.{name}): it would be ignored")
        return self


def as_options(cls, value, name: str):
    """``value`` as the options object ``cls`` takes (None: its defaults); anything else (a dict,
    say) refused in one line naming the class to build, rather than failing at its first attribute."""
    if value is None:
        return cls()
    if isinstance(value, cls):
        return value
    raise InvalidOptionError(f"{name} must be an sdp.{cls.__name__} (sdp.{cls.__name__}(...)), "
                             f"got {type(value).__name__}")

