"""Run a part program on a cell (SimCell offline, RosCell live) and fit the measured points.

Flow (`measure`):
1. Move to the placement reading, settle, find the part in the three full frames
   (`features.find_part`: in-plane rotation, position, plane from the feature heights).
2. Dark field: per feature, the edge band width from free fits on all its planned points in
   those frames (`features.estimate_band_width`); the edge fits then fix it.
3. Per planned point: move X* to the point predicted from the part pose (one move), then
   `targeting.drive_to` with a locator of this module (edge point on a fixed plane PI, or dot
   centre) until the remaining offset is below the stage resolution or no step is left. The
   point is X*(q) + the remaining triangulated offset (stage frame) and, via the constellation
   readings of the same settled state, in the tracker frame. Its covariance (stage frame) is
   the edge fit's (planes from every view and PI) plus the calibrated axes'; the tracker-frame
   covariance is drive_to's.
4. Fits in the frame of the chosen mode (`stage`: tracker-free relative; `tracker`): plane of
   all points, then every feature in that plane (fitting.py), the part pose from the feature
   centres, dot-grid spacings per separation.

Each point keeps the pixels it was found at, the encoder reading, the tracker-frame point and
image crops around its feature pixels, so a measurement can be refitted and re-located offline
(`relocate_points`, `fit_measurement`).
"""
from __future__ import annotations

import json
import math
import pathlib
import time
from dataclasses import dataclass, field

import numpy as np

from ct_calib_nodes.io.atomic import replace_atomically  # standard library only (no ROS)

from . import features, fitting, part_program
from .part_program import PartProgram, PlannedPoint
from .targeting import TargetingError, drive_to

CROP_HALF_PX = 28


@dataclass
class MeasuredPoint:
    feature_id: str
    kind: str
    index: int
    ok: bool
    reason: str
    p_stage: np.ndarray
    cov_stage: np.ndarray
    p_tracker: np.ndarray | None
    cov_tracker: np.ndarray | None
    q: np.ndarray
    pixels: dict
    iterations: int                  # triangulations (locate + triangulate) in drive_to
    moves: int                       # moves incl. the predicting one
    elapsed_s: float
    offsets_um: list = field(default_factory=list)
    crops: dict = field(default_factory=dict)     # camera -> (x0, y0, uint8 array)
    target: dict = field(default_factory=dict)    # the EdgeTarget / dot target (stage frame)


def _stage_views(probe, q):
    """Camera poses in the stage frame at q consistent with targeting's body frame (X* body
    offset removed, so that projections of stage points match drive_to's triangulation)."""
    xs = probe.xstar_stage(q) - probe.xstar_body
    return {c: features.View(c, features.CameraPose(np.asarray(probe.R_stage_camera[c], float),
                                                    np.asarray(probe.p_stage_centre[c], float) + xs),
                             probe.intrinsics[c]) for c in probe.camera_names}


def _target_for(pt: PlannedPoint, spec, R, p, lighting, band_m=None):
    if pt.kind == "dot":
        return {"kind": "dot", "centre": p + R[:, :2] @ pt.xy_part, "diameter": spec.dot_diameter}
    center = p + R[:, :2] @ np.asarray(spec.center) if spec.type == "circle" else None
    return features.EdgeTarget(p + R[:, :2] @ pt.xy_part, R[:, :2] @ pt.tangent_part, R[:, :2] @ pt.normal_part,
                               R[:, 2].copy(), lighting, center, pt.curvature_radius, band_m)


def make_locator(target):
    """A targeting Locator for an EdgeTarget or a dot target; `.last` holds the last fix."""
    def locate(settled, probe):
        views = _stage_views(probe, settled.q)
        if isinstance(target, features.EdgeTarget):
            try:
                ep = features.locate_edge_point(settled.images, views, target)
            except features.LocateError as e:
                raise TargetingError(str(e)) from None
            locate.last = ep
            # isotropic pixel sigma for the triangulation: the fix's in-plane sd in pixels
            out = {}
            for c, px in ep.pixels.items():
                mpp = np.linalg.norm(views[c].pose.p_stage_centre - ep.X) / views[c].intr.f_px
                out[c] = (px[0], px[1], max(math.sqrt(max(np.trace(ep.cov), 0) / 2) / mpp, 0.01))
            return out
        fix = features.locate_dot(settled.images, views, target["centre"], target["diameter"])
        if len(fix.pixels) < 2:
            raise TargetingError("dot seen in fewer than 2 cameras: " + "; ".join(fix.problems))
        locate.last = fix
        return {c: (v[0], v[1], max(fix.u_px[c], 0.01)) for c, v in fix.pixels.items()}
    locate.last = None
    return locate


def _crops(settled, pixels, half=CROP_HALF_PX):
    out = {}
    for c, px in pixels.items():
        img = settled.images.get(c)
        if img is None:
            continue
        x0 = int(np.clip(round(px[0]) - half, 0, img.shape[1] - 1))
        y0 = int(np.clip(round(px[1]) - half, 0, img.shape[0] - 1))
        out[c] = (x0, y0, np.array(img[y0:y0 + 2 * half + 1, x0:x0 + 2 * half + 1]))
    return out


def measure_point(cell, probe, target, *, start=None, max_iter=4, keep_crops=True, progress=None):
    """Predict-move then drive_to for one target; a MeasuredPoint (not yet tagged)."""
    t0 = time.perf_counter()
    moves = 0
    X = target["centre"] if isinstance(target, dict) else target.point
    s = start
    if s is None or np.linalg.norm(X - probe.xstar_stage(s.q)) > 2 * cell.resolution_m:
        q_now = s.q if s is not None else cell.current().q
        dq = probe.move_for(X - probe.xstar_stage(q_now))
        res = cell.resolution_m
        s = cell.move_and_settle(np.round((q_now + dq) / res) * res)
        moves += 1
    loc = make_locator(target)
    r = drive_to(cell, probe, loc, start=s, max_iter=max_iter, progress=progress)
    cov = r.cov_stage
    if isinstance(loc.last, features.EdgePoint) and r.ok:
        cov = loc.last.cov + probe.cov_xstar_stage(r.q)
    tgt = ({"kind": "dot", "centre": np.asarray(target["centre"]).tolist(), "diameter": target["diameter"]}
           if isinstance(target, dict) else
           {"kind": "edge", **{k: (np.asarray(v).tolist() if isinstance(v, np.ndarray) else v)
                               for k, v in target.__dict__.items()}})
    return MeasuredPoint("", "", -1, bool(r.ok), r.reason, np.asarray(r.p_stage, float), np.asarray(cov, float),
                         None if r.p_tracker is None else np.asarray(r.p_tracker, float),
                         None if r.cov_tracker is None else np.asarray(r.cov_tracker, float),
                         np.asarray(r.q, float), r.pixels, len(r.iterations), moves + r.n_moves,
                         time.perf_counter() - t0, [it["offset_norm"] * 1e6 for it in r.iterations],
                         _crops(r.settled, r.pixels) if keep_crops and r.pixels else {}, tgt), r.settled


@dataclass
class MeasurementRun:
    program: PartProgram
    part_pose: features.PartPose
    band_widths: dict
    points: list                      # MeasuredPoint
    elapsed_s: float
    problems: list


def measure(cell, probe, program: PartProgram, *, progress=None, max_iter=4, keep_crops=True,
            only_features=None) -> MeasurementRun:
    """Run a part program (see module doc). progress(dict) is called per point."""
    t0 = time.perf_counter()
    res = cell.resolution_m
    s0 = cell.move_and_settle(np.round(np.asarray(program.origin_at_stage, float) / res) * res)
    views0 = _stage_views(probe, s0.q)
    # X* in the stage frame at s0 in the views' convention (targeting's body frame)
    origin = probe.xstar_stage(s0.q) - probe.xstar_body
    pose = features.find_part(s0.images, views0, program, origin)
    if progress:
        progress({"event": "part_found", "message": pose.message})
    R, p = pose.R_stage_part, pose.p_stage_part
    plan = [pt for pt in part_program.plan(program) if only_features is None or pt.feature_id in only_features]
    bands, problems = {}, []
    if program.lighting == "dark_field":
        for f in program.features:
            if f.band_m is not None:
                bands[f.id] = (f.band_m, 0.0, 0)
                continue
            tg = [_target_for(pt, f, R, p, program.lighting) for pt in plan if pt.feature_id == f.id and pt.kind == "edge"]
            if tg:
                try:
                    bands[f.id] = features.estimate_band_width(s0.images, views0, tg)
                except features.LocateError as e:
                    problems.append(f"{f.id}: {e}")
    points = []
    s = s0
    for k, pt in enumerate(plan):
        spec = program.feature(pt.feature_id)
        band = bands.get(spec.id, (None,))[0]
        target = _target_for(pt, spec, R, p, program.lighting, band)
        mp, s_new = measure_point(cell, probe, target, start=s, max_iter=max_iter, keep_crops=keep_crops)
        mp.feature_id, mp.kind, mp.index = pt.feature_id, pt.kind, pt.index
        if s_new is not None:
            s = s_new
        if not mp.ok:
            problems.append(f"{pt.feature_id}[{pt.index}]: {mp.reason}")
        points.append(mp)
        if progress:
            progress({"event": "point", "n": k + 1, "of": len(plan), "feature": pt.feature_id, "index": pt.index,
                      "ok": mp.ok, "p_stage": mp.p_stage.tolist(), "p_tracker": None if mp.p_tracker is None
                      else mp.p_tracker.tolist(), "iterations": mp.iterations, "moves": mp.moves,
                      "elapsed_s": mp.elapsed_s, "reason": mp.reason})
    return MeasurementRun(program, pose, bands, points, time.perf_counter() - t0, problems)


# ------------------------------------------------------------------------------ fitting
def fit_measurement(program: PartProgram, points: list, *, mode="stage", R_tracker_stage=None,
                    part_R_stage=None) -> dict:
    """measurement.json content (INTERFACES keys + documented extras) from measured points.

    mode: 'stage' uses p_stage / cov_stage, 'tracker' p_tracker / cov_tracker.
    part_R_stage: the part-finding rotation (hint for the in-plane axes)."""
    if mode not in ("stage", "tracker"):
        raise ValueError(f"mode: 'stage' or 'tracker', got {mode!r}")
    plan = {(pt.feature_id, pt.index): pt for pt in part_program.plan(program)}
    Rh = np.eye(3) if part_R_stage is None else np.asarray(part_R_stage, float)
    if mode == "tracker":
        if R_tracker_stage is None:
            raise ValueError("tracker mode needs R_tracker_stage for the axis hints")
        Rh = np.asarray(R_tracker_stage, float) @ Rh
    use = []
    for mp in points:
        P = mp.p_stage if mode == "stage" else mp.p_tracker
        C = mp.cov_stage if mode == "stage" else mp.cov_tracker
        if mp.ok and P is not None and np.all(np.isfinite(P)) and (mp.feature_id, mp.index) in plan:
            use.append((mp, np.asarray(P, float), np.asarray(C, float)))
    if len(use) < 3:
        raise fitting.FitError(f"only {len(use)} usable points in {mode} mode")
    allP = np.array([u[1] for u in use])
    plane = fitting.fit_plane(allP, up=Rh[:, 2], x_hint=Rh[:, 0])
    feats_out, grids_out, centres_nom, centres_meas, cen3 = [], [], [], [], {}
    for spec in program.features:
        if spec.type == "plane":
            continue
        sel = [u for u in use if u[0].feature_id == spec.id]
        if not sel:
            continue
        P = np.array([u[1] for u in sel])
        C = np.array([u[2] for u in sel])
        xy = plane.to_2d(P)
        c2 = plane.cov_2d(C)
        pts = [plan[(u[0].feature_id, u[0].index)] for u in sel]
        try:
            if spec.type in ("square", "rectangle"):
                fit = fitting.fit_rectangle(xy, [pt.side for pt in pts], cov2d=c2, angle0=spec.rotation,
                                            nominal=(spec.size[0], spec.size[0]) if spec.type == "square" else spec.size,
                                            square=spec.type == "square")
            elif spec.type == "circle":
                fit = fitting.fit_circle(xy, cov2d=c2, nominal_diameter=spec.size[0])
            elif spec.type == "dot_grid":
                rc = np.array([pt.grid_rc for pt in pts])
                g = fitting.fit_grid(xy, rc, spec.pitch, c2)
                spac = fitting.grid_spacings(xy, rc, spec.pitch, cov2d=c2)
                grids_out.append({"id": spec.id, "_xy": xy, "_rc": rc, "spacings": [
                    {k: v for k, v in d.items()} for d in spac],
                    "grid_scale": g["scale"], "grid_rms": g["rms"], "n_dots": len(xy),
                    "n_planned": spec.rows * spec.cols})
                centres_nom.append(spec.center)
                centres_meas.append(g["center"])
                cen3[spec.id] = g["center"]
                continue
        except fitting.FitError as e:
            feats_out.append({"id": spec.id, "type": spec.type, "error": str(e), "n_points": len(sel)})
            continue
        centres_nom.append(spec.center)
        centres_meas.append(fit.center)
        cen3[spec.id] = fit.center
        fp = fitting.fit_plane(P, up=plane.normal, x_hint=np.cos(fit.angle) * plane.e1 + np.sin(fit.angle) * plane.e2) \
            if len(P) >= 3 else None
        size = float(fit.size.mean()) if spec.type == "square" else (fit.size.tolist() if spec.type == "rectangle"
                                                                      else float(fit.size[0]))
        u_size = (fit.u("size") / 2 * 2 if spec.type == "square" else
                  [fit.u("sx"), fit.u("sy")] if spec.type == "rectangle" else fit.u("diameter"))
        d = {"id": spec.id, "type": spec.type, "_center2d": fit.center, "size": size, "u_size": u_size,
             "form_rms": fit.form_rms, "form_max": fit.form_max, "n_points": len(sel), "_P": P,
             "mean_dev_ideal": float(np.mean(fit.dev_ideal)), "rms_dev_ideal": float(np.sqrt(np.mean(fit.dev_ideal ** 2))),
             "deviations": fit.residuals.tolist(), "deviations_ideal": fit.dev_ideal.tolist(),
             "chi2_dof": fit.chi2_dof, "u_center": [fit.u("cx"), fit.u("cy")],
             "nominal": list(spec.size) if spec.type != "square" else spec.size[0]}
        if spec.type == "square":
            d["sides"] = fit.size.tolist()
            d["u_sides"] = [fit.u("sx"), fit.u("sy")]
            d["u_size"] = fit.u("size")
        if fp is not None:
            d["fixed_angles_rad"] = fitting.fixed_angles(fp.R).tolist()
            d["flatness"] = fp.flatness
        feats_out.append(d)
    if not centres_meas:
        raise fitting.FitError("no feature could be fitted")
    R_fp, p_fp, ang, resid = fitting.fit_part_pose(plane, np.array(centres_nom), np.array(centres_meas))

    def to_part(P3):
        return (np.atleast_2d(P3) - p_fp) @ R_fp

    for d in feats_out:
        if "_P" in d:
            d["points_part"] = to_part(d.pop("_P")).tolist()
            d["center_part"] = to_part(plane.to_3d(d.pop("_center2d")))[0, :2].tolist()
    for g in grids_out:
        xy = g.pop("_xy")
        g.pop("_rc")
        g["centres_part"] = to_part(plane.to_3d(xy))[:, :2].tolist()
    return {"part": program.part, "mode": mode, "frame": mode, "u_scope": U_SCOPE.get(mode, ""),
            "R_frame_part": R_fp.tolist(), "p_frame_part": p_fp.tolist(),
            "plane": {"normal": plane.normal.tolist(), "fixed_angles_rad": fitting.fixed_angles(R_fp).tolist(),
                      "flatness": plane.flatness, "rms": plane.rms, "n_points": plane.n},
            "features": feats_out, "dot_grids": grids_out,
            "pose_fit_residuals_m": np.asarray(resid).tolist()}


# What the stated u of each mode includes (written into measurement.json and the report).
U_SCOPE = {
    "stage": ("u includes the pixel noise of each located edge point, the calibrated X* pixels and the "
              "calibrated squareness; it does NOT include the stage's scale, straightness or pitch/yaw/roll "
              "(Abbe) errors, nor thermal drift: add the stage's stated accuracy over the part's extent"),
    "tracker": ("u includes the tracker reading noise (calibrated sigma), the calibrated X* in the constellation "
                "frame and the remaining offset; not the tracker's scale error"),
}


# ------------------------------------------------------------------------------ files
def point_record(mp: MeasuredPoint) -> dict:
    f = lambda a: None if a is None else np.asarray(a, float).tolist()  # noqa: E731
    return {"feature": mp.feature_id, "kind": mp.kind, "index": mp.index, "ok": mp.ok, "reason": mp.reason,
            "p_stage": f(mp.p_stage), "cov_stage": f(mp.cov_stage), "p_tracker": f(mp.p_tracker),
            "cov_tracker": f(mp.cov_tracker), "q": f(mp.q),
            "pixels": {c: list(map(float, v[:2])) for c, v in mp.pixels.items()},
            "iterations": mp.iterations, "moves": mp.moves, "elapsed_s": mp.elapsed_s,
            "offsets_um": mp.offsets_um, "target": mp.target}


def point_from_record(d: dict) -> MeasuredPoint:
    g = lambda a: None if a is None else np.asarray(a, float)  # noqa: E731
    return MeasuredPoint(d["feature"], d["kind"], int(d["index"]), bool(d["ok"]), d.get("reason", ""),
                         g(d["p_stage"]), g(d["cov_stage"]), g(d.get("p_tracker")), g(d.get("cov_tracker")),
                         g(d["q"]), {c: tuple(v) for c, v in (d.get("pixels") or {}).items()},
                         int(d.get("iterations", 0)), int(d.get("moves", 0)), float(d.get("elapsed_s", 0.0)),
                         list(d.get("offsets_um", [])), {}, d.get("target") or {})


def measurement_document(run: MeasurementRun, probe, *, mode="stage", calibration: dict | None = None) -> dict:
    """The full measurement.json: the fit in `mode` and, as extras, the other mode's fit, the raw
    points, the part finding, timing (see doc/picms_measure.md)."""
    doc = fit_measurement(run.program, run.points, mode=mode, R_tracker_stage=probe.R_tracker_stage,
                          part_R_stage=run.part_pose.R_stage_part)
    other = "tracker" if mode == "stage" else "stage"
    try:
        doc["other_mode"] = fit_measurement(run.program, run.points, mode=other, R_tracker_stage=probe.R_tracker_stage,
                                            part_R_stage=run.part_pose.R_stage_part)
    except (fitting.FitError, ValueError) as e:
        doc["other_mode"] = {"error": str(e)}
    its = [mp.iterations for mp in run.points if mp.ok]
    doc.update({
        "part_finding": {"R_stage_part": run.part_pose.R_stage_part.tolist(),
                         "p_stage_part": run.part_pose.p_stage_part.tolist(), "message": run.part_pose.message},
        "band_width_m": {k: {"width": v[0], "se": v[1], "n": v[2]} for k, v in run.band_widths.items()},
        "points": [point_record(mp) for mp in run.points],
        "summary": {"n_points": len(run.points), "n_ok": sum(mp.ok for mp in run.points),
                    "iterations_mean": float(np.mean(its)) if its else None,
                    "moves_mean": float(np.mean([mp.moves for mp in run.points])) if run.points else None,
                    "time_per_point_s": float(np.mean([mp.elapsed_s for mp in run.points])) if run.points else None,
                    "elapsed_s": run.elapsed_s},
        "problems": run.problems,
        "program": run.program.source,
        "program_yaml": run.program.raw,
    })
    if calibration is not None:
        doc["probe"] = {"calibration": calibration, "camera_info": {
            c: {"K": np.asarray(i.K).tolist(), "D": np.asarray(i.D).tolist(), "width": i.width, "height": i.height}
            for c, i in probe.intrinsics.items()}}
    return doc


def write_json_atomic(doc: dict, path) -> pathlib.Path:
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)

    def write(tmp):
        with open(tmp, "w") as fh:
            json.dump(doc, fh, indent=1, default=_json_default)
    return replace_atomically(path, write)


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def write_crops(run: MeasurementRun, path) -> pathlib.Path:
    """Image crops of every point (npz, atomically): keys p{k}_{camera} (uint8) and
    p{k}_{camera}_xy (x0, y0), k = index in measurement.json's points."""
    path = pathlib.Path(path)
    arrays = {}
    for k, mp in enumerate(run.points):
        for c, (x0, y0, a) in mp.crops.items():
            arrays[f"p{k}_{c}"] = a
            arrays[f"p{k}_{c}_xy"] = np.array([x0, y0])
    return replace_atomically(path, lambda tmp: np.savez_compressed(tmp, **arrays), suffix=".tmp.npz")
