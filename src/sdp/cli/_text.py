"""The text the ``sdp`` commands print, made from the library's results and summaries.

Each function returns the lines (joined, without a final newline) that a command prints when
``--json`` is not given; the JSON is the summary itself.
"""

from __future__ import annotations

import numpy as np

from ..io._bag import frame_kind

__all__ = ["change_text", "coverage_text", "alignment_text", "motion_text", "frame_text", "evaluation_text",
           "written_text", "train_text", "action_eval_text"]


#: Share of a scan's points outside their own cluster volume above which the summary says so (real
#: pairs measured: 0–0.24 %; a dense object beside a sparse room: the whole room, 4.9 %).
_SPARSE = 0.01


def change_text(s: dict, reference, current) -> str:
    """The table of ``sdp change``, from :attr:`sdp.FileComparison.summary`."""
    lines = []
    for role, name, kind in (("reference", reference, "disappeared"), ("current", current, "appeared")):
        c = s[role]
        if c[kind] is None:  # a field store as the reference: only what appeared is found
            lines.append(f"{role:<10} {name}: {c['points']:,} points, {kind} not measured (a field store holds no "
                         "points to test)")
            continue
        lines.append(f"{role:<10} {name}: {c['points']:,} points ({c['dropped']:,} dropped), {c[kind]:,} {kind}, "
                     f"{c['not_comparable']:,} not comparable")
    for role in ("reference", "current"):
        n, out = s[role]["points"], s[role].get("outside_own_volume", 0)
        if n and out >= _SPARSE * n:  # the automatic voxel followed denser points elsewhere
            lines.append(f"{out / n:.1%} of the {role}'s points lie outside its own cluster volume (sparser than the "
                         f"voxel {s['voxel_size']:.4g} assumes): no change can be found at them; a larger --voxel-size "
                         "reaches them")
    if "extents" in s:
        lines.append(f"the reference spans {s['extents'][0]:.4g} units and the current {s['extents'][1]:.4g}: are they "
                     "in the same units (metres and millimetres)? Compared as given")
    lines += [f"the {role}'s message: {s[role]['tf']}" for role in ("reference", "current") if "tf" in s[role]]
    units = s.get("range_units", {})
    if units:
        roles = " and the ".join(units)
        lines.append(f"the {roles}'s points lie farther from the sensor than a depth camera sees in metres: the rays' "
                     f"band taken per {'millimetre' if max(units.values()) < 0.005 else 'centimetre'} "
                     f"({max(s['range_noise'][r] for r in units):.3g}·r²); give --range-noise for another sensor")
    if "alignment" in s:
        lines.append(alignment_text(s["alignment"]))
    lines.append(f"voxel {s['voxel_size']:.4g}, sigma {s['sigma']:.4g}, h {s['h']:.4f}, decision {s['decision']}"
                 + (f", {s['tiles']} tiles of {s['tile_size']:.4g}" if "tiles" in s else ""))
    lines.append(coverage_text(s))
    lines += [level_text(kind, s[role]["level"])
              for role, kind in (("current", "appeared"), ("reference", "disappeared")) if "level" in s[role]]
    for kind in ("appeared", "disappeared"):
        regs = s[f"{kind}_regions"]
        if regs:
            lines.append(f"\n{kind} regions ({len(regs)}; largest 10):")
            lines.append(f"  {'#':>3} {'points':>8}  {'centroid':>30}  {'size':>26}")
            for g in regs[:10]:
                c = " ".join(f"{v:9.3f}" for v in g["centroid"])
                size = " ".join(f"{hi - lo:8.3f}" for lo, hi in zip(g["bbox_min"], g["bbox_max"], strict=True))
                lines.append(f"  {g['label']:>3} {g['n_points']:>8,}  {c}  {size}")
    lines.append("\ntime (ms): " + ", ".join(f"{k} {v * 1e3:.1f}" for k, v in s["timings"].items()))
    lines += [f"wrote {o}" for o in s.get("outputs", [])]
    return "\n".join(lines)


def level_text(kind: str, level: dict) -> str:
    """One line: the combined decision's level of detection of one direction, what was given."""
    given = level.get("given", {})

    def how(name):
        return "given" if name in given else "measured"
    return (f"level ({kind}): systematic {1.96 * level['systematic']:.4g} at 95 % ({how('registration_error')}), "
            f"range exponent {level['range_exponent']:.2f} ({how('range_exponent')})"
            + (f", correlation length {given['correlation_length']:g}" if "correlation_length" in given else ""))


def coverage_text(s: dict) -> str:
    """One line: how each direction decided what the other scan saw (sensor rays or footprint)."""
    origins = s.get("sensor_origin", {})

    def one(kind, other):
        how = s["coverage"][kind]
        if how == "sensor rays":
            o = origins[other]
            if isinstance(o[0], (list, tuple)):  # several scanners (a multi-scan E57)
                return f"{kind}: the {other}'s sensor rays ({len(o)} scanners)"
            return f"{kind}: the {other}'s sensor rays (origin {', '.join(f'{v:.4g}' for v in o)})"
        if how == "not measured":
            return f"{kind}: not measured"
        if how != "footprint":
            return f"{kind}: off"
        frame = s.get(other, {}).get("frame")
        kind_of = {"world": "a world frame", "body": "a robot's body frame"}.get(frame_kind(frame))
        why = f": {frame!r} is {kind_of}" if kind_of else ""
        return f"{kind}: the {other}'s footprint (no sensor position known{why})"
    return "coverage: " + "; ".join((one("appeared", "reference"), one("disappeared", "current")))


def alignment_text(al: dict) -> str:
    """Two lines from :meth:`sdp.Alignment.summary`: the shift of the current scan's centroid and
    the rotation about it (roll, pitch, yaw about x, y, z, and the total angle); the overlap,
    residual and time. Lengths in metres, as :mod:`sdp.viz._render` labels them."""
    residual = (f"residual {al['rmse']:.4g} m (RMS)" if al["rmse"] is not None and np.isfinite(al["rmse"]) else
                "no residual (a field holds no points to measure it to)")
    text = (f"aligned current onto reference ({al['method']}): {motion_text(al)}\n"
            f"  inside the reference's volume {al['inside_before']:.1%} → {al['inside_after']:.1%}, "
            f"{residual}, {al['seconds']:.2f} s")
    return text + "".join(f"\n  {w}" for w in alignment_warnings(al))


def alignment_warnings(al: dict) -> list[str]:
    """What an alignment (:meth:`sdp.Alignment.summary`) may have got wrong, each a sentence: it
    started from almost no overlap (a guess), its surfaces do not coincide after it (a residual
    beyond the kernel σ: it has most likely failed), directions it did not refine at the finest level."""
    out = []
    if al.get("diverged"):
        out.append("the estimate moved the surfaces apart (less of the scan inside the reference's volume than at the "
                   "start): the initial pose was kept; --align gicp, or scans moved closer, may find it")
    if al["inside_before"] < LOW_OVERLAP:  # both methods refine a pose: from no overlap they find any
        out.append(f"the scans barely overlapped before ({al['inside_before']:.1%} of the current inside the "
                   "reference's volume): a registration from so little overlap is a guess; check it")
    if al["rmse"] is not None and al.get("sigma") and al["rmse"] > al["sigma"]:
        out.append(f"the residual exceeds the kernel σ = {al['sigma']:.4g} m the surfaces are compared with: they do "
                   "not coincide, and the registration has most likely failed (move the scans closer first)")
    if al.get("kept"):
        out.append(f"not refined at the finest level, the scene pinning them less than 1 % as firmly as the best "
                   f"direction: {', '.join(al['kept'])} (as the coarser levels left them, the initial pose if they "
                   "did too); where the scans may differ in those, --align gicp estimates all six")
    return out


#: Share of the current's points inside the reference's volume before an alignment below which the
#: summary says the result is a guess: GICP and the density alignment refine an overlap they start
#: from (a camera turned away from the reference's scene, 0 %, got a 90° roll and "no change").
LOW_OVERLAP = 0.05


def motion_text(al: dict) -> str:
    """The motion of :meth:`sdp.Alignment.summary` as a person reads it: "shift (dx, dy, dz) m at
    the current scan's centroid, rotation A° (roll R°, pitch P°, yaw Y°, about x, y, z)"."""
    def num(v, digits):  # no "-0.000" for what rounds to zero
        return f"{round(v, digits) + 0.0:.{digits}f}"

    r = al["rotation"]
    shift = ", ".join(num(v, 3) for v in al["shift"])
    return (f"shift ({shift}) m of the current scan's centroid, rotation {num(r['angle'], 4)}° about it "
            f"(roll {num(r['roll'], 4)}°, pitch {num(r['pitch'], 4)}°, yaw {num(r['yaw'], 4)}°: about x, y, z)")


def frame_text(frame) -> str:
    """One line per :class:`sdp.FrameChange` of ``sdp watch``: counts, latency, the largest regions."""
    s = frame.summary()
    if frame.empty:
        return f"{frame.name}: {s['points']:,} points, none finite: nothing compared, the model unchanged"
    where = "; ".join(f"{g['n_points']:,} at ({', '.join(f'{v:.2f}' for v in g['centroid'])})"
                      for g in s["regions"][:3])
    text = (f"{frame.name}: {s['points']:,} points, {frame.n_appeared:,} appeared in {len(frame.regions)} regions, "
            f"{s['not_comparable']:,} not comparable ({frame.latency * 1e3:.1f} ms){': ' + where if where else ''}")
    if frame.overlap is not None and frame.overlap < LOW_OVERLAP:  # as alignment_text says of a pair
        text += (f" (registered with {frame.overlap:.1%} of the frame inside the model: its pose, and what the "
                 "model learns from it, are a guess)")
    if frame.pose_kept:
        text += (" (its registration moved it away from the model: the previous frame's pose was kept; a camera "
                 "turning fast is followed by --align gicp)")
    return text


def evaluation_text(e) -> str:
    """The lines of ``sdp eval`` from a :class:`sdp.cli.Evaluation`."""
    sc = e.scores
    return "\n".join((f"{e.points:,} points ({sc['not_comparable']:,} not comparable, left out); changed: "
                      f"predicted {e.predicted:,}, true {e.true:,} of the comparable",
                      "  ".join(f"{k} {v:.4f}" for k, v in sc.items() if isinstance(v, float)),
                      "  ".join(f"{k} {v:,}" for k, v in sc.items() if isinstance(v, int))))


def written_text(thing, path) -> str:
    """What was written to ``path``: a mesh's size and area, else the field's (or store's) repr."""
    from ..fields._surface import Mesh

    if isinstance(thing, Mesh):
        return (f"{len(thing.vertices):,} vertices, {len(thing.faces):,} triangles, area {thing.area:.4g}\n"
                f"wrote {path}")
    return f"{thing!r}\nwrote {path}"


def train_text(model, cv: float, n_sequences: int, path) -> str:
    """The lines of ``sdp action train``."""
    alphas = " / ".join(f"{a:g}" for a in model.alpha)
    return (f"{n_sequences} sequences, {len(model.classes)} actions; alpha {alphas} (body / hand), "
            f"leave-one-subject-out accuracy {cv:.3f}\nwrote {path}")


def action_eval_text(summary: dict) -> str:
    """The lines of ``sdp action eval`` from :func:`sdp.cli.evaluate_actions`."""
    lines = []
    for name, acc in summary.items():
        if name in ("cv", "alpha", "timings", "sequences"):
            continue
        cv = summary["cv"].get(name)
        lines.append(f"{name:8s} {acc:.3f}" + (f"   (cross-validated on training subjects {cv:.3f})" if cv else ""))
    lines.append("time (s): " + ", ".join(f"{k} {v:.1f}" for k, v in summary["timings"].items()))
    return "\n".join(lines)


def action_splits_text(s: dict) -> str:
    """The lines of ``sdp action eval --splits all`` from :func:`sdp.cli.evaluate_actions`."""
    lines = [f"{s['sequences']} sequences, {s['protocol']}: test accuracy over the splits",
             f"{'':8s} {'mean':>6s} {'std':>6s} {'min':>6s} {'max':>6s}   standard split (1,3,5,7,9)"]
    for name, v in s["summary"].items():
        place = (f"   {v['standard']:.3f}: rank {v['standard_rank']} of {s['splits']}, percentile "
                 f"{v['standard_percentile']:.0f}" if "standard" in v else "")
        lines.append(f"{name:8s} {v['mean']:6.3f} {v['std']:6.3f} {v['min']:6.3f} {v['max']:6.3f}{place}")
    worst = sorted((acc, a) for a, acc in zip(s["confusion"]["all"]["actions"], s["confusion"]["all"]["accuracy"],
                                              strict=True) if acc is not None)[:3] if "all" in s["confusion"] else []
    if worst:
        lines.append("hardest actions (all 20, summed over the splits): "
                     + ", ".join(f"a{a:02d} {acc:.0%}" for acc, a in worst))
    lines.append("time (s): " + ", ".join(f"{k} {v:.1f}" for k, v in s["timings"].items()))
    return "\n".join(lines)


def distance_text(s: dict, reference, current) -> str:
    """The table of ``sdp distance``."""
    n = max(s["core_points"], 1)
    lines = [f"{reference} → {current}: signed distance along the normal ({s['orientation']})",
             f"  core points      {s['core_points']:>12,}"
             + (f"  (and {s['core_points_dropped']:,} row{'s' if s['core_points_dropped'] != 1 else ''} holding "
                f"NaN or Inf, left out)"
                if s.get("core_points_dropped") else ""),
             f"  with a distance  {s['comparable']:>12,}  ({s['comparable'] / n:.1%}; the others: "
             + (f"no normal ({s['no_normal']:,}), " if s.get("no_normal") else "") + "an epoch has too few points "
             "near" + (f", or its sensor could not see the place ({s['not_seen']:,})" if s.get("not_seen")
                       else "")
             + (f", or the current's surface only touches the cylinder off its axis: none of its own at the "
                f"core point, a step edge or a gap in its sampling ({s['off_axis']:,})" if s.get("off_axis") else "")
             + ", not comparable)",
             f"  significant      {s['significant']:>12,}  ({s['significant_positive']:,} +, "
             f"{s['significant_negative']:,} −; |distance| > level of detection at 95 %)",
             f"  median distance  {s['median_distance']:>12.4g}  (5–95 %: {s['distance_p05']:.4g} … "
             f"{s['distance_p95']:.4g})",
             f"  median LoD95     {s['median_lod']:>12.4g}  (registration error {s['registration_error']:.4g}"
             + (f", {s['registration_source']})" if s.get("registration_source", "given") != "given" else ")"),
             f"  scales           projection d = {s['projection_scale']:.4g}, normal D = {s['normal_scale']:.4g}, "
             f"searched ±{s['max_distance']:.4g} along the normal",
             f"  time             {s['timings'].get('total', 0):.2f} s"]
    if s.get("input_normals"):
        lines.append(f"  the core points' own normals ({', '.join(s['input_normals'])}) were not used: kept as given "
                     "beside the normals measured along, estimated at the normal scale")
    if "alignment" in s:
        lines.append(alignment_text(s["alignment"]))
    lines += [f"wrote {path}" for path in s.get("outputs", [])]
    return "\n".join(lines)


def _registration_text(p: dict, r: dict | None) -> str:
    if p["registration_error"] != "auto":
        return str(p["registration_error"])
    if not r or not r["auto_epochs"]:  # an archive written before the records said which epochs fell back
        return "measured on each epoch's stable part (0 where fewer than 100 places are stable)"
    back = r["fell_back"]
    text = f"measured on the stable part of {r['auto_epochs'] - len(back)} of {r['auto_epochs']} epochs"
    if back:
        shown = ", ".join(str(e["epoch"]) for e in back[:8]) + (", …" if len(back) > 8 else "")
        text += f"; 0 on epoch(s) {shown}: fewer than 100 stable places"
    return text


def series_text(s: dict) -> str:
    """The summary of ``sdp series`` / ``sdp info ARCHIVE.zarr`` as text."""
    p = s["parameters"]["used"]
    sm = s["parameters"].get("smoother", {})
    last = s["runs"][-1] if s["runs"] else {}
    lines = [f"{s['path']}: {s['epochs']} epochs ({', '.join(s['time_source'])} times, {s['first_time']} .. "
             f"{s['last_time']}) at {s['core_points']:,} core points against {s['reference']}",
             f"  scales: projection {p['projection_scale']:.4g}, normal {p['normal_scale']:.4g}, search "
             f"{p['max_distance']:.4g}; registration error " + _registration_text(p, s.get("registration")),
             f"  significant: {100 * s['significant_fraction']:.1f} % of the (epoch, core point) measured after "
             f"the reference; smoother: process "
             f"noise {sm.get('process_noise', float('nan')):.3g}, velocity {sm.get('velocity', '')}",
             f"  objects of change: {s['objects']}"]
    for e in s.get("unmeasured_epochs", []):
        lines.append(f"  epoch {e['epoch']} ({e['file']}): no core point has a distance; is it of the same place, in "
                     "the same frame?")
    for e in s.get("partial_epochs", []):
        lines.append(f"  epoch {e['epoch']} ({e['file']}): measured at {e['comparable']:,} core points, the median "
                     f"epoch at {e['median']:,}: a partial scan? Objects through it may break there")
    for e in (s.get("registration") or {}).get("large", []):
        lines.append(f"  epoch {e['epoch']} ({e['file']}): registration error {e['registration_error']:.4g} measured, "
                     f"over 3 times the others' median {e['median_others']:.3g} and its random part "
                     f"{e['random_sd']:.3g}: it moved as a whole (misaligned, or changed everywhere, which this "
                     "error hides); give --registration-error or --align")
    for o in s["largest_objects"][:5]:
        lines.append(f"    #{o['id']}: epochs {o['start']}..{o['end']}, {o['core_points']} core points, "
                     f"peak {o['peak_change']:+.4g}, mean velocity {o['mean_velocity']:+.4g}")
    if last:
        tiled = last.get("tiled")
        where = f" in {tiled['tiles']} tiles on Dask" if tiled else ""
        lines.append(f"  this run: {last['added']} epoch(s) {'appended' if last['append'] else 'measured'}{where} in "
                     f"{last['timings'].get('total', 0):.2f} s")
        if last.get("times_note"):
            lines.append(f"  times: {last['times_note']}")
    lines += [f"wrote {o}" for o in s.get("outputs", [])[1:]]  # the exports (the archive is named above)
    return "\n".join(lines)
