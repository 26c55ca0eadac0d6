"""The defaults of sdp, defined once: the Python API, the ``sdp`` command, streams, tiles and
the benchmarks all read them from :data:`DEFAULTS`, a frozen dataclass whose docstring gives
each default's reason (the HTML report quotes it). The library's signatures and the command
line's ``argparse`` defaults are these very objects (``tests/test_defaults.py``), so they
cannot drift apart.

Each default is the best setting measured on real scans (``benchmarks/bench_defaults.py``,
``docs/benchmarks.md``), not the paper's: the paper's parameters stay one option away
(``grid_size=80``).

References
----------
.. [1] A. W. Vieira et al., "Spatial Density Patterns as Representation for Point Cloud
   Comparison and Applications" (σ = 2 voxels, h = 1 + 3·e^(−1/2)).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

__all__ = ["DEFAULTS", "Defaults", "PAPER_GRID_SIZE", "PAPER_SIGMA_VOXELS", "AUTO_SIGMA_VOXELS"]

#: The paper's level of detail: the longest side of the box in 80 segments.
PAPER_GRID_SIZE = 80
#: The paper's σ in voxels: used with a given voxel size or grid size.
PAPER_SIGMA_VOXELS = 2.0
#: σ in voxels on the automatic lattice, where σ comes from the point spacing.
AUTO_SIGMA_VOXELS = 1.5


@dataclass(frozen=True)
class Defaults:
    """One value per option, with the reason it is the default.

    Attributes
    ----------
    voxel_size : str
        ``"auto"``: σ from the clouds' point spacing (:func:`sdp.auto_voxel_size`), because a
        fixed grid is too coarse on real Kinect frames (on the 27 mOSD pairs of
        ``benchmarks/bench_decision.py``: kappa 0.307 at the paper's 80³, 0.665 with the
        automatic voxel).
    sigma_voxels : str
        ``"auto"``: 1.5 voxels on the automatic lattice, the paper's 2 with a given voxel size
        or grid size. With ``voxel_size="auto"`` σ comes from the point spacing and the lattice
        only samples the field: at 1.5 voxels it has 2.4× fewer nodes than at 2 and the
        builds and regions take about 35 % less time, for kappa 0.849 instead of 0.850 on the
        27 mOSD pairs (``benchmarks/bench_speed.py``); at 1 voxel (0.846) an object of the
        simulated office is lost (``tests/test_visibility.py`` fails).
    k : float
        3: the paper's threshold h = 1 + k·e^(−1/2) (a point needs about k neighbours at σ).
    truncate : float
        3: kernels cut at 3σ (e^(−4.5) ≈ 1 % of the peak).
    method : str
        ``"auto"``: G is built by trilinear binning and a separable blur (``"fast"``), within
        1 % of the peak of the exact sum of kernels (``"exact"``) and far faster.
    min_region_points : int
        50: change regions with fewer points are noise or parallax at depth edges (kappa 0.641
        → 0.665 on the 27 mOSD pairs; the static Kinect sequence stays below 0.5 % flagged
        once registered).
    sensor_origin : str
        ``"auto"``: the sensor position a file records (an organized PCD's VIEWPOINT) is used,
        because the visibility test lifts kappa on the mOSD pairs from 0.670 to 0.850
        (``benchmarks/bench_paper.py``); clouds whose files say nothing are compared without it.
    range_noise : float
        0.015 m⁻¹: "the same range" within 0.015·r² (1.5 cm at 1 m), a Kinect's depth noise
        and drift; an E57 file's laser scans take 0 by default (the band's floor, σ, alone:
        24 cm at 4 m would take a 20 cm partition's far face for its near one).
    decision : str
        ``"point"``: Algorithm 1 per point; the paper's cluster rule changes nothing on
        table-top scenes (objects share the table's cluster). ``"combined"`` (density or the
        distance beyond its level, :mod:`sdp.change._combined`) is not the default: on the 27
        mOSD pairs it scores kappa 0.905 against 0.886, for 1.5× the time and 14 false
        positives on one of the three static pairs where the density has none
        (``benchmarks/bench_combined.py``).
    cluster_fraction : float
        0.5: the cluster rule's majority.
    update : str
        ``"window"``: a stream's model learns the last frames and forgets what left the scene.
    window : int
        10 frames in the model (the reference counts as one): a third of a second at 30 Hz.
    decay : float
        0.8 per frame for ``update="decay"``.
    projection_scale : str
        ``"auto"``: M3C2's projection scale d of :func:`sdp.distances` is 4σ of the density
        kernel (a Gaussian of σ holds as many effective points as a cylinder of radius 2σ), so
        the distances and the change masks look at the same neighbourhood.
    normal_scale : str
        ``"auto"``: 2d, raised to 20× the roughness at that scale (Lague et al.), at most 4d.
    max_distance : str
        ``"auto"``: an epoch is looked for up to 12d (48σ) along the normal, so that
        displacements well beyond the kernel's reach are still measured (a 2 m move of a plane
        whose d is 18 cm, in ``benchmarks/bench_distance.py``).
    orientation : tuple
        (0, 0, 1): where no sensor is known, normals point up (+z), as M3C2's do by default: the
        scans without a sensor are mostly airborne or merged maps, in frames with z up.
    registration_error : str
        ``"auto"``: M3C2's ``reg`` measured on the data, the smallest for which at most 5 % of
        the stable part (distances within 2σ_p, which the density test leaves unchanged) lies
        beyond the level (:mod:`sdp.distance._level`). M3C2's own default, 0, leaves 69–83 % of
        a static Kinect pair and 56 % of the aligned Toronto ALS ground "significant"
        (``benchmarks/bench_level.py``).
    range_exponent : str
        ``"auto"``: how the combined decision's level grows with range along the sensor's ray
        is fitted on each pair's stable majority (:mod:`sdp.distance._noise`), because the law
        differs between sensors (2 for a structured-light camera, 0 for a laser scanner) and a
        file rarely says which sensor wrote it.
    correlation_length : None
        Points' errors are taken as independent in the random part; what correlated errors
        add is measured in the systematic part (a depth camera's window of correlated pixels
        depends on its matcher, which no file records).
    smoothing_lag : int
        16 epochs: a series' epoch is smoothed with the 16 after it (the last 16 with all that
        follow), then final, so an appended epoch rewrites 17 rows whatever the series' length.
        A velocity from 16 epochs of noise σ has a standard deviation of σ·√12/16^1.5 = 0.054σ
        per epoch; the whole series would add little for a change that is not steady anyway.
    align_method : str
        ``"density"``: registration on the ridges of the reference's density field, which needs
        no extra and matches GICP on the benchmarks' re-scans (``benchmarks/bench_align_online.py``).
    action_window : int
        40 frames (1.3 s at 30 Hz) classified by a live action stream: about one MSR Action3D
        action.
    action_every : int
        5: a live action stream says its label every 5 frames (6 times a second at 30 Hz).
    field_names : str
        "sdp": outputs name their fields as sdp documents them; "cloudcompare" and "pdal" are
        a flag away for files opened in those tools.
    """

    voxel_size: str = "auto"
    sigma_voxels: str = "auto"
    k: float = 3.0
    truncate: float = 3.0
    method: str = "auto"
    min_region_points: int = 50
    sensor_origin: str = "auto"
    range_noise: float = 0.015
    decision: str = "point"
    cluster_fraction: float = 0.5
    update: str = "window"
    window: int = 10
    decay: float = 0.8
    projection_scale: str = "auto"
    normal_scale: str = "auto"
    max_distance: str = "auto"
    orientation: tuple = (0.0, 0.0, 1.0)
    registration_error: str = "auto"
    range_exponent: str = "auto"
    correlation_length: float | None = None
    smoothing_lag: int = 16
    align_method: str = "density"
    action_window: int = 40
    action_every: int = 5
    field_names: str = "sdp"

    def as_dict(self) -> dict:
        return asdict(self)


#: The defaults in force (read-only).
DEFAULTS = Defaults()
