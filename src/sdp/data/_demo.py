"""``make demo`` (``sdp demo``): change detection on a simulated office scan, against its known truth.

:func:`run_demo` simulates a Kinect-like camera (:mod:`sdp.data._scene`), takes a reference scan and
one with objects inserted, runs :func:`sdp.detect_changes` with the defaults and the camera's
position, scores it against the truth (and the paper's fixed 80³ grid), and writes the clouds,
the cluster volume's mesh and a picture.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

__all__ = ["run_demo"]


def run_demo(output: str | os.PathLike = "demo-output", *, seed: int = 0, echo: Callable[[str], object] = print):
    """Run the demo, saying what it does through ``echo`` line by line; write into ``output``
    ``reference.ply``, ``current_labelled.ply`` (fields ``change``, ``truth``, ``region``, ``F``),
    ``current_cluster_volume.ply`` and ``changes.png``. Returns the :class:`~sdp.ChangeResult`."""
    from .._core._validate import integer_at_least
    from ..errors import InvalidOptionError
    from ..io._output import new_folder

    seed = integer_at_least("seed", seed, 0)  # before any folder is made
    if not str(output).strip():
        raise InvalidOptionError("give the demo a folder to write into (-o FOLDER), got an empty name")
    with new_folder(output) as out:
        return _run(out, seed=seed, echo=echo)


def _run(out: Path, *, seed: int, echo):
    from ..change._detect import detect_changes
    from ..change._metrics import scores
    from ..io._output import write_mesh, write_points
    from ..options import Coverage, Lattice
    from ..viz._render import render_changes
    from ._scene import INSERTED, office_scene

    echo("Simulating a Kinect-like depth sensor in an office (ray casting, occlusion, depth noise):")
    s = office_scene(seed=seed)
    echo(f"  reference scan {len(s.reference):,} points; current scan {len(s.current):,} points with "
         f"{len(INSERTED)} inserted objects ({s.appeared_truth.sum():,} points on them)")
    # a first call loads the kernels from Numba's cache: the timings printed are the warm ones
    detect_changes(s.reference[::10], s.current[::10], coverage=Coverage(sensor_origin=s.camera))
    r = detect_changes(s.reference, s.current, coverage=Coverage(sensor_origin=s.camera))  # the defaults; the camera is known
    sc = scores(s.appeared_truth, r.appeared, comparable=~r.current_not_comparable)
    every = scores(s.appeared_truth, r.appeared)["kappa"]
    paper = detect_changes(s.reference, s.current, min_region_points=1, lattice=Lattice(grid_size=80),
                           coverage=Coverage(sensor_origin=None, enabled=False))
    kp = scores(s.appeared_truth, paper.appeared)["kappa"]
    echo(f"\nchange detection (the defaults: voxel {r.voxel_size * 1000:.1f} mm from the point spacing, "
         f"the camera's rays):")
    echo(f"  appeared points {r.appeared.sum():,}; not comparable {sc['not_comparable']:,} (the reference's "
         "camera could not see there)")
    echo(f"  on the comparable points: kappa {sc['kappa']:.3f}, precision {sc['precision']:.3f}, "
         f"recall {sc['recall']:.3f}, IoU {sc['iou']:.3f}")
    echo(f"  on every point (not comparable as unchanged): kappa {every:.3f}; the paper's 80³ grid: kappa {kp:.3f}")
    echo("  time (ms): " + ", ".join(f"{k} {v * 1e3:.1f}" for k, v in r.timings.items()))
    echo(f"  {len(r.appeared_regions)} change regions:")
    for g in r.appeared_regions:
        objs = s.object_of_current[r.appeared_labels == g.label]
        best = np.bincount(objs[objs >= 0], minlength=len(INSERTED)).argmax() if (objs >= 0).any() else -1
        name = INSERTED[best].name if best >= 0 else "(no inserted object)"
        echo(f"    {g.n_points:6,} points at ({', '.join(f'{v:.2f}' for v in g.centroid)}) "
             f"size {' x '.join(f'{v:.2f}' for v in g.size)} m  ~ {name}")
    echo(f"  disappeared points {r.disappeared.sum():,}: the surfaces the new objects now hide")
    write_points(out / "reference.ply", s.reference)
    write_points(out / "current_labelled.ply", s.current,
                 {"change": r.current_state, "truth": s.appeared_truth.astype(np.uint8),
                  "region": r.appeared_labels,
                  "F": r.current_field.field(s.current).astype(np.float32)})
    write_mesh(out / "current_cluster_volume.ply", r.current_field.mesh())
    render_changes(out / "changes.png", s.current, r.current_state,
                   title=f"sdp demo: appeared points vermillion, not comparable grey (kappa {sc['kappa']:.3f} "
                         "vs. ground truth on the comparable points)")
    echo(f"\nwrote {out}/reference.ply, current_labelled.ply, current_cluster_volume.ply, changes.png")
    return r
