"""Pixel Probe discrepancy engine validation: hidden effects, acquisitions that cannot reveal them, clean controls.

    python tests/benchmarks/picms_discrepancy_validation.py [--clean-seeds 50] [--effect-seeds 6]
        [--first 1000] [--cache DIR] [--jobs 2]

Phase 1 renders every acquisition (random cell per seed: make_physics varies blur, noise, levels,
vignetting, assembly, lens and tracker distance) and detects the disc in every frame, once per
CameraInfo variant; with --cache the detections are kept (pickles) so phase 2 can be re-run.
Phase 2 calibrates each (acquisition, CameraInfo) pair exactly as picms_calibrate_offline does and
runs the discrepancy engine; the engine and the calibration see only the recording.

Acquisitions: `grid` (grid_pattern(), 33 stations, +-6 / +-4 mm travel), `small` (the same grid at
+-1 / +-0.7 mm: too little travel and field for the lens and stage-scale terms; a 1e-3 aspect error
still shows there) and `short`
(a 3 x 3 x 2 grid, 19 stations, with a 4 x faster stage: a 3 x shorter session, too short for the drift)
and `dense` (a 6 x 6 x 3 grid over the same travel, 109 stations, a ~3.5 min session: about 0.6 x the
grid's limit for the stage terms, which the grid's 60 ppm draws straddle; rows `stage_lead_dense`,
`stage_default_dense` and their clean control `clean_dense`), and `reveal`, the stage terms' revealing
acquisition: the 6 x 6 x 3 grid over +-8 / +-5 mm (the widest travel that keeps every disc inside every
field on these cells) with four frames per station, a ~5 min session (rows `stage_lead_reveal`, a lead
error of a fixed size, and `tracker_scale_gross_reveal`; clean control `clean_reveal`; run them on more
seeds with `--first 1006 --clean-seeds 6 --effect-seeds 6 --only clean_reveal stage_lead_reveal
tracker_scale_gross_reveal`). Effects (hidden from the engine; realistic magnitudes):

- lens_radial_k1: lenses with k1 ~ -0.3, CameraInfo D = 0;
- pixel_aspect_error: CameraInfo fy off by 0.8-1.2e-3 relative, either sign, per camera;
- lens_tangential: CameraInfo p1, p2 off by 8e-4 (random direction) per camera;
- stage_axis_scale: stage lead (scale) errors, 60 ppm sd per axis (ball-screw grade C5-C7);
  the differential part is what the cameras see (a common scale is absorbed by the calibration). On
  `grid` about half of these draws fall below the term's limit (~25-40 ppm), so the row
  `stage_lead_coarse` draws 150 ppm sd (rolled screws, C7-C10) on the same acquisition to show it where
  it is visible (+-12 mm of travel takes the disc out of the field at the corners; `reveal` uses +-8 mm);
- stage_lead_reveal: lead errors whose differential part has a fixed rms of 40 ppm over the axes, in a
  random direction (C5-C7 screws, uncompensated), plus a common part of 30 ppm sd: a size the revealing
  acquisition resolves, where the random draws above straddle the limits;
- stage default error motions (stage_errors.StageErrorSpec defaults: scale, straightness,
  pitch/yaw/roll through the Abbe offset): on `grid` and `dense` what shows is the linear part, an
  effective differential axis scale, the truth the top-1 columns compare; on `reveal`
  (`stage_default_reveal`, `--only clean_reveal stage_default_reveal`) the bows and the carriage rotation
  show too, so the summary's `parts` judges the three parts one by one (effective scale, straightness,
  angular motions): above its limit, named anywhere in the findings, sized within 15 %;
  `stage_default_reveal_long` (clean control `clean_reveal_long`) repeats it with 16 frames per station, a ~13 min
  session rendered as it is detected (440 s CPU per recording);
- camera_rotation_drift: each camera mount tilts at 0.1 urad/s (about 7 urad over the grid session);
- principal_point_error (3 px sd in CameraInfo): absorbed by the camera rotation on every acquisition
  of this cell; must be reported as not observable, never named.

Tracker effects (cell.Physics; paired with each seed's clean grid recording: the same frames, detections,
stage readings and tracker noise, only the tracker's errors added; the tracker noise here is 3 um per axis
per station after averaging, over a 12 mm travel):

- tracker_length_scale: 5 ppm sd (weather-station errors of a few K or hPa; tracker scale MPE); the
  cell's travel cannot reveal it (limit ~400 ppm): the engine must report the limit and name nothing.
  `tracker_scale_gross` draws 500-900 ppm, beyond any working tracker (air left uncompensated is
  270 ppm) but below the catalogue's plausibility bound (1000 ppm), only to show the term named and
  sized where it is visible; `tracker_scale_gross_reveal` the same draws on the `reveal` recording
  (more stations, more travel: about a third of the grid's limit);
- tracker_angular_encoder: 2 ppm sd of the angle per encoder (the tracker's angular MPE, ~3 urad, over
  a half turn); not visible over the cell's few mrad;
- smr_centring: 5 um sd per axis (1.5" SMR centring grades +-2.5 to +-12.7 um): absorbed by X*; the
  calibrated X* must sit where the tracker reads the SMR*'s optical centre, and nothing be named;
- tracker_timing_lag: 10-40 ms either sign (unsynchronised clocks): invisible at the settled stations,
  measured from the constellation readings during the moves between them (core/timing_lag.py);
  `tracker_lag_settled` keeps only the readings at settled stations (a tracker triggered per station),
  which cannot reveal it.

Clean controls: the grid acquisition with a rigid stage and the true CameraInfo, on every seed.
Prints one JSON line of figures (per-row details on stderr).
"""
import argparse
import json
import pathlib
import pickle
import sys
import time
from dataclasses import replace
from multiprocessing import Pool

import numpy as np

from picms_nodes.core import campaign, cell, instruments, pipeline
from picms_nodes.core import picms_discrepancy as pd
from picms_nodes.core.calibrate import assign, calibrate, in_window, settled_windows
from picms_nodes.core.camera import Intrinsics
from picms_nodes.core.instruments import StageSim
from picms_nodes.core.stage_errors import StageErrorSpec

SCALE_ONLY = StageErrorSpec(scale_ppm_sd=60.0, straightness_m_sd=0.0, angular_rad_sd=0.0)
# rolled ball screws (grades C7-C10: 50-210 um per 300 mm, 170-700 ppm) on an economy stage
COARSE_LEAD = StageErrorSpec(scale_ppm_sd=150.0, straightness_m_sd=0.0, angular_rad_sd=0.0)
DRIFT_RAD_PER_S = 1.0e-7
ACQ = {
    "grid": dict(pattern=pd.grid_pattern()),
    "small": dict(pattern=pd.grid_pattern(half_xy_m=0.001, half_z_m=0.0007)),
    "short": dict(pattern=pd.grid_pattern(n_xy=3), fast=True),
    "dense": dict(pattern=pd.grid_pattern(n_xy=6, n_z=3)),
    # the stage terms' revealing acquisition: the dense grid over the widest travel that keeps every disc in
    # every field on every cell (+-8 / +-5 mm: 75 px of margin at the worst corner; +-9 / +-6 mm clips), and four
    # frames per station (averaging the ~0.4 urad of image noise each single frame carries)
    "reveal": dict(pattern=pd.grid_pattern(n_xy=6, n_z=3, half_xy_m=0.008, half_z_m=0.005),
                   frames_per_station=4, dwell_s=2.0),
    # the same travel with 16 frames per station (a ~13 min session; rendered as detected: its frames would not
    # fit in memory): what the default motions' straightness and carriage rotation need (rows
    # `stage_default_reveal_long`, `clean_reveal_long`)
    "reveal_long": dict(pattern=pd.grid_pattern(n_xy=6, n_z=3, half_xy_m=0.008, half_z_m=0.005),
                        frames_per_station=16, dwell_s=6.0, lazy=True),
}
LEAD_FIXED_PPM = 40.0


def fixed_lead(seed):
    """Lead errors of a fixed size in a random direction: the differential part (what the cameras can see)
    has an rms of LEAD_FIXED_PPM over the three axes (ball screws of grades C5-C7, uncompensated); a common
    part (absorbed by the calibration) of 30 ppm sd is added."""
    r = np.random.default_rng([seed, 17])
    d = r.normal(0.0, 1.0, 3)
    d -= d.mean()
    d *= LEAD_FIXED_PPM / np.sqrt(np.mean(d * d))
    s = d + r.normal(0.0, 30.0)
    return dict(stage_error_motions=True, stage_error_spec=StageErrorSpec(
        scale_ppm_sd=0.0, straightness_m_sd=0.0, angular_rad_sd=0.0, scale_ppm=tuple(float(v) for v in s)))
# rendering jobs: name -> (acquisition, physics overrides, CameraInfo variants); effect seeds only
# except 'clean' which every seed renders
JOBS = {
    "clean": ("grid", {}, ("true", "D0", "aspect", "tangential", "pp")),
    "small": ("small", {}, ("true", "D0", "aspect", "tangential")),
    "stage_scale": ("grid", dict(stage_error_motions=True, stage_error_spec=SCALE_ONLY), ("true",)),
    "stage_scale_small": ("small", dict(stage_error_motions=True, stage_error_spec=SCALE_ONLY), ("true",)),
    "stage_lead_coarse": ("grid", dict(stage_error_motions=True, stage_error_spec=COARSE_LEAD), ("true",)),
    "stage_default": ("grid", dict(stage_error_motions=True), ("true",)),
    "clean_dense": ("dense", {}, ("true",)),
    "stage_scale_dense": ("dense", dict(stage_error_motions=True, stage_error_spec=SCALE_ONLY), ("true",)),
    "stage_default_dense": ("dense", dict(stage_error_motions=True), ("true",)),
    "drift": ("grid", dict(camera_tilt_drift_rad_per_s=DRIFT_RAD_PER_S), ("true",)),
    "drift_fast": ("short", dict(camera_tilt_drift_rad_per_s=DRIFT_RAD_PER_S), ("true",)),
    "clean_reveal": ("reveal", {}, ("true",)),
    "stage_lead_reveal": ("reveal", fixed_lead, ("true",)),
    "stage_default_reveal": ("reveal", dict(stage_error_motions=True), ("true",)),
    "clean_reveal_long": ("reveal_long", {}, ("true",)),
    "stage_default_reveal_long": ("reveal_long", dict(stage_error_motions=True), ("true",)),
}


def job_overrides(job, seed):
    """A rendering job's physics overrides for a seed (a dict, or a function of the seed)."""
    over = JOBS[job][1]
    return over(seed) if callable(over) else over


def _sign(rng):
    return float(rng.choice([-1.0, 1.0]))


# tracker effects: name -> physics overrides drawn from the seed's own generator; derived from the
# seed's clean grid recording (tracker_job), never rendered again
TRACKER_JOBS = {
    "tracker_scale": lambda r: dict(tracker_scale_ppm=float(r.normal(0.0, 5.0))),
    "tracker_scale_gross": lambda r: dict(tracker_scale_ppm=_sign(r) * float(r.uniform(500.0, 900.0))),
    "tracker_encoder": lambda r: dict(tracker_encoder_ppm=tuple(float(v) for v in r.normal(0.0, 2.0, 2))),
    "smr_centring": lambda r: dict(smr_centring_m=tuple(float(v) for v in r.normal(0.0, 5e-6, 3))),
    "tracker_lag": lambda r: dict(tracker_lag_s=_sign(r) * float(r.uniform(0.010, 0.040))),
    "tracker_lag_settled": lambda r: dict(tracker_lag_s=_sign(r) * float(r.uniform(0.010, 0.040))),
    "tracker_scale_gross_reveal": lambda r: dict(tracker_scale_ppm=_sign(r) * float(r.uniform(500.0, 900.0))),
}
# the clean recording a tracker effect is derived from (default: the seed's clean grid)
TRACKER_BASE = {"tracker_scale_gross_reveal": "clean_reveal"}
# rows whose tracker is read only at the settled stations (a tracker triggered per station): the moves that
# reveal a clock lag carry no readings
SETTLED_ONLY = {"tracker_lag_settled"}


def info_variant(truth, kind, seed):
    """CameraInfo as the solver gets it: the true one, or one with a hidden error."""
    rng = np.random.default_rng(seed * 7 + 3)
    out, err = {}, {}
    for c in truth.cameras:
        v = c.info_intrinsics
        K, D = v.K.copy(), v.D.copy()
        if kind == "D0":
            D = np.zeros(5)
            err[c.name] = float(c.true_intrinsics.D[0])
        elif kind == "aspect":
            e = rng.choice([-1, 1]) * rng.uniform(0.8e-3, 1.2e-3)
            K[0, 0] *= 1 + e                      # CameraInfo fx too large by e: the truth is -e ...
            err[c.name] = float(1 / (1 + e) - 1)  # ... relative to CameraInfo's fx
        elif kind == "tangential":
            a = rng.uniform(0, 2 * np.pi)
            D[2] -= 8e-4 * np.cos(a)
            D[3] -= 8e-4 * np.sin(a)
            err[c.name] = [8e-4 * np.cos(a), 8e-4 * np.sin(a)]
        elif kind == "pp":
            K[0, 2] += rng.normal(0, 3.0)
            K[1, 2] += rng.normal(0, 3.0)
        out[c.name] = Intrinsics(K, D, v.width, v.height)
    return out, err


def render_job(args):
    """Phase 1 for one (seed, job): render, detect per CameraInfo variant; a picklable dict."""
    seed, job, cache = args
    path = None if cache is None else pathlib.Path(cache) / f"{job}_{seed}.pkl"
    if path is not None and path.exists():
        return pickle.loads(path.read_bytes())
    acq, _, variants = JOBS[job]
    over = job_overrides(job, seed)
    c0 = time.process_time()
    truth, rec = _session(seed, over, ACQ[acq], render=True)
    windows = settled_windows(rec.joint_stamps_ns, rec.joint_positions)
    out = {"seed": seed, "job": job, "acq": acq, "cell": rec.cell, "tracker": rec.tracker,
           "joint": (rec.joint_stamps_ns, rec.joint_positions), "variants": {}, "truth": truth_summary(truth)}
    if ACQ[acq].get("lazy") and len(variants) > 1:
        raise ValueError(f"{job}: a lazily rendered acquisition's frames can be detected once (one CameraInfo)")
    for kind in variants:
        info, err = info_variant(truth, kind, seed)
        dets = pipeline.detect_settled_frames(rec.frames, info, windows, pipeline.PipelineReport())
        out["variants"][kind] = {"info": info, "err": err, "dets": dets}
    out["render_cpu_s"] = time.process_time() - c0
    if path is not None:
        path.write_bytes(pickle.dumps(out))
    return out


def _truth(seed, over, rng=None):
    rng = np.random.default_rng(seed) if rng is None else rng
    phys = cell.make_physics(rng, distortion_k1=-0.3, stage_error_motions=False)
    return cell.make_cell(rng, replace(phys, **over)), phys


def _session(seed, over, kw, render):
    """The seed's cell with physics overrides `over` and its session (the generator is consumed the same
    way whatever `over` holds, so a tracker effect leaves the frames, stage and tracker noise unchanged)."""
    rng = np.random.default_rng(seed)
    truth, phys = _truth(seed, over, rng)
    kw = dict(kw)
    if kw.pop("fast", False):        # a 4x faster stage and shorter dwell: a short session
        kw.update(stage=StageSim(resolution_m=phys.stage_resolution_m, vmax=0.02, amax=0.1), dwell_s=1.0)
    rec, _ = campaign.simulate_session(truth, rng, mid_move_frames=0, render=render, **{"dwell_s": 1.2, **kw})
    return truth, rec


def tracker_job(base, job):
    """A tracker effect on the seed's clean grid recording `base` (render_job's dict): the tracker stream
    is simulated again with the effect; frames and detections are the clean ones (checked: same stage)."""
    seed = base["seed"]
    over = TRACKER_JOBS[job](np.random.default_rng([seed, 11, list(TRACKER_JOBS).index(job)]))
    truth, rec = _session(seed, over, ACQ[base["acq"]], render=False)
    if not np.array_equal(rec.joint_positions, base["joint"][1]):
        raise RuntimeError(f"seed {seed}: the re-simulated session differs from the clean recording")
    if job in SETTLED_ONLY:
        win = settled_windows(rec.joint_stamps_ns, rec.joint_positions)
        rec.tracker = [r for r in rec.tracker if in_window(r[0], win) >= 0]
    return {**base, "job": job, "acq": base["acq"], "tracker": rec.tracker,
            "variants": {"true": base["variants"]["true"]}, "truth": truth_summary(truth), "render_cpu_s": 0.0}


def truth_summary(truth):
    s = {"k1": [float(c.true_intrinsics.D[0]) for c in truth.cameras]}
    ph = truth.physics
    x = truth.to_tracker(truth.smr_star_stage)[0]
    s.update(tracker_scale_ppm=ph.tracker_scale_ppm, tracker_encoder_ppm=list(ph.tracker_encoder_ppm),
             smr_centring_m=list(ph.smr_centring_m), tracker_lag_s=ph.tracker_lag_s,
             # X* where an error-free tracker puts it, and where this tracker reads the SMR*'s optical centre
             x_star_tracker=x.tolist(), x_star_tracker_read=instruments.tracker_errors(
                 x + np.asarray(ph.smr_centring_m), ph.tracker_scale_ppm, ph.tracker_encoder_ppm).tolist())
    se = truth.stage_errors
    if se is not None:
        A = truth.A_travel
        # what the cameras see of the error motions, to first order: the SMR* in the body frame moves by
        # -(A diag(s) q + straightness) + (G q) x p_abbe; the linear part in the travel axes, diagonal:
        lin = np.linalg.inv(A) @ (A @ np.diag(se.scale) + _skew(se.p_abbe) @ se.G)
        eff = np.diag(lin)
        off = ~np.eye(3, dtype=bool)
        # the default motions' three parts in the catalogue's display units: the effective differential scale
        # (ppm), the bows (um at 25 mm from the centre of travel, rms over the 6) and the angular motions
        # (urad per 25 mm of travel, rms over the 9)
        s.update(stage_scale=se.scale.tolist(), stage_eff_scale=eff.tolist(),
                 stage_parts={"stage_axis_scale": _rms(eff - eff.mean()) * 1e6,
                              "stage_straightness": _rms(se.straight[off]) * 0.025 ** 2 * 1e6,
                              "stage_angular": _rms(se.G) * 0.025 * 1e6})
    if truth.camera_drift:
        s["drift_cam"] = [(c.pose.R_stage_camera.T @ w).tolist() for c, (w, _v) in zip(truth.cameras, truth.camera_drift)]
    return s


def _skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


# (job, CameraInfo variant) -> (case, expected term (None: clean), reveals?)
CASES = {
    ("clean", "true"): ("clean", None, True),
    ("clean", "D0"): ("lens_radial_k1", "lens_radial_k1", True),
    ("small", "D0"): ("lens_radial_k1", "lens_radial_k1", False),
    ("clean", "aspect"): ("pixel_aspect_error", "pixel_aspect_error", True),
    ("small", "aspect"): ("pixel_aspect_error", "pixel_aspect_error", False),
    ("clean", "tangential"): ("lens_tangential", "lens_tangential", True),
    ("small", "tangential"): ("lens_tangential", "lens_tangential", False),
    ("stage_scale", "true"): ("stage_axis_scale", "stage_axis_scale", True),
    ("stage_scale_small", "true"): ("stage_axis_scale", "stage_axis_scale", False),
    ("stage_lead_coarse", "true"): ("stage_lead_coarse", "stage_axis_scale", True),
    ("stage_default", "true"): ("stage_default", "stage_axis_scale", True),
    ("clean_dense", "true"): ("clean_dense", None, True),
    ("stage_scale_dense", "true"): ("stage_lead_dense", "stage_axis_scale", True),
    ("stage_default_dense", "true"): ("stage_default_dense", "stage_axis_scale", True),
    ("clean_reveal", "true"): ("clean_reveal", None, True),
    ("stage_lead_reveal", "true"): ("stage_lead_reveal", "stage_axis_scale", True),
    ("stage_default_reveal", "true"): ("stage_default_reveal", "stage_axis_scale", True),
    ("clean_reveal_long", "true"): ("clean_reveal_long", None, True),
    ("stage_default_reveal_long", "true"): ("stage_default_reveal_long", "stage_axis_scale", True),
    ("tracker_scale_gross_reveal", "true"): ("tracker_scale_gross_reveal", "tracker_length_scale", True),
    ("drift", "true"): ("camera_rotation_drift", "camera_rotation_drift", True),
    ("drift_fast", "true"): ("camera_rotation_drift", "camera_rotation_drift", False),
    ("clean", "pp"): ("principal_point_error", "principal_point_error", False),
    ("small", "true"): ("clean_small", None, True),
    ("tracker_scale", "true"): ("tracker_length_scale", "tracker_length_scale", False),
    ("tracker_scale_gross", "true"): ("tracker_scale_gross", "tracker_length_scale", True),
    ("tracker_encoder", "true"): ("tracker_angular_encoder", "tracker_angular_encoder", False),
    ("smr_centring", "true"): ("smr_centring", "smr_centring", False),
    ("tracker_lag", "true"): ("tracker_timing_lag", "tracker_timing_lag", True),
    ("tracker_lag_settled", "true"): ("tracker_timing_lag", "tracker_timing_lag", False),
}


CLEAN_CASES = ("clean", "clean_small", "clean_dense", "clean_reveal", "clean_reveal_long")


def _rms(v):
    return float(np.sqrt(np.mean(np.square(v))))


def true_magnitude(acq, variant, term, span_s):
    t, err = acq["truth"], acq["variants"][variant]["err"]
    if term == "lens_radial_k1":
        return _rms(t["k1"])
    if term == "pixel_aspect_error":
        return _rms(list(err.values()))
    if term == "lens_tangential":
        return _rms([np.hypot(*v) for v in err.values()])
    if term == "stage_axis_scale":
        s = np.array(t["stage_eff_scale"])
        return _rms(s - s.mean()) * 1e6
    if term == "camera_rotation_drift":
        return _rms([np.linalg.norm(np.array(w)[:2]) * span_s for w in t["drift_cam"]]) * 1e6
    if term == "tracker_length_scale":
        return abs(t["tracker_scale_ppm"])
    if term == "tracker_angular_encoder":
        return _rms(t["tracker_encoder_ppm"])
    if term == "smr_centring":
        return _rms(t["smr_centring_m"]) * 1e6
    if term == "tracker_timing_lag":
        return abs(t["tracker_lag_s"]) * 1e3
    return None


def analyse_one(acq, variant):
    case, expect, reveals = CASES[(acq["job"], variant)]
    v = acq["variants"][variant]
    c0 = time.process_time()
    stamps, pos = acq["joint"]
    res = calibrate(assign(settled_windows(stamps, pos), v["dets"], acq["tracker"]), v["info"], acq["cell"])
    out = pd.run(res, v["info"], motion={"joint_stamps_ns": stamps, "joint_positions": pos, "tracker": acq["tracker"],
                                         "constellation": acq["cell"]["tracker"]["constellation"]})
    t_ns = res.design["t_ns"]
    span = (t_ns[-1] - t_ns[0]) * 1e-9
    f0 = out["findings"][0] if out["findings"] else None
    lim = out["detection_limits"].get(expect) if expect else None
    fl = out["noise_floor"]["independent_sd"]
    # the calibrated X* against where this tracker reads the SMR*'s optical centre (z per axis)
    xz = (np.asarray(res.p_tracker) - acq["truth"]["x_star_tracker_read"]) / np.sqrt(np.diag(res.cov_p_tracker))
    return {"seed": acq["seed"], "case": case, "acq": acq["acq"], "reveals": reveals, "expect": expect,
            "adequate": out["adequate"], "top1": f0["term"] if f0 else None,
            "terms": [f["term"] for f in out["findings"]] + [u["axis"] for u in out["unexplained"]],
            "degenerate_with": f0["degenerate_with"] if f0 else [],
            "est": f0["magnitude"] if f0 else None, "est_u": f0.get("magnitude_u") if f0 else None,
            "sigma": f0["significance_sigma"] if f0 else None,
            "true": true_magnitude(acq, variant, expect, span) if expect else None,
            "limit": None if lim is None else lim["limit"], "cannot_see": None if lim is None else lim.get("cannot_see"),
            "held_out_before": out["fit_before"]["held_out_rms"], "held_out_after": out["fit_after"]["held_out_rms"],
            "floor_px": float(np.hypot(fl["u"], fl["v"]) / np.sqrt(2)), "session_s": span,
            "x_star_z": xz.tolist(), "cpu_s": time.process_time() - c0,
            # every finding's size, and for a composite effect (the default stage motions) each part's truth and
            # detection limit: the parts are judged one by one (parts_summary)
            "found": {f["term"]: [f["magnitude"], f.get("magnitude_u"), f["degenerate_with"]] for f in out["findings"]},
            "parts": {k: {"true": v_, "limit": (out["detection_limits"].get(k) or {}).get("limit")}
                      for k, v_ in acq["truth"].get("stage_parts", {}).items()} if case.startswith("stage_default")
            else {}}


def summarise(rows):
    clean = [r for r in rows if r["case"] == "clean"]
    # 'down to the noise floor': the held-out rms after the findings is within 25 % of the clean control's
    # (same cell and renderer settings, the grid acquisition): the held-out folds refit the calibration without
    # a fifth of the stations, so even a clean recording's held-out rms sits above the neighbour-difference floor
    clean_ho = {r["seed"]: r["held_out_before"] for r in clean}
    # a dense-grid row is compared with the seed's dense clean control (its own acquisition)
    clean_ho_acq = {(r["seed"], r["acq"]): r["held_out_before"] for r in rows if r["case"] in CLEAN_CASES}

    def ref_ho(r):
        return clean_ho_acq.get((r["seed"], r["acq"] if r["acq"] in ("dense", "reveal", "reveal_long") else "grid"))

    def at_floor(r):
        return ref_ho(r) is not None and r["held_out_after"] <= 1.25 * ref_ho(r)
    out = {"clean_seeds": len(clean), "clean_false_alarms": sum(not r["adequate"] for r in clean),
           "clean_x_star_z_rms": _rms([z for r in clean for z in r["x_star_z"]]) if clean else None,
           "clean_false_alarm_rate": sum(not r["adequate"] for r in clean) / max(len(clean), 1),
           "clean_false_alarm_terms": sorted({t for r in clean for t in r["terms"]}),
           "clean_held_out_median_px": float(np.median(list(clean_ho.values()))) if clean_ho else None,
           "effects": {}, "cannot_reveal": {}}
    for name in CLEAN_CASES[1:]:
        cc = [r for r in rows if r["case"] == name]
        out[f"{name}_false_alarms"] = f"{sum(not r['adequate'] for r in cc)}/{len(cc)}"
    for case in sorted({r["case"] for r in rows} - set(CLEAN_CASES)):
        rr = [r for r in rows if r["case"] == case and r["reveals"]]
        if rr:
            ok = [r for r in rr if r["top1"] == r["expect"] and r["true"] and abs(r["est"] - r["true"]) <= 0.15 * r["true"]]
            out["effects"][case] = {
                "n": len(rr), "detected": sum(not r["adequate"] for r in rr),
                "top1_correct": sum(r["top1"] == r["expect"] for r in rr),
                "top1_degenerate_flagged": sum(bool(r["degenerate_with"]) for r in rr if r["top1"] == r["expect"]),
                "within_15pct": len(ok),
                "rel_err_max": max((abs(r["est"] - r["true"]) / r["true"] for r in rr
                                    if r["top1"] == r["expect"] and r["true"]), default=None),
                "true_median": float(np.median([r["true"] for r in rr])) if rr[0]["true"] is not None else None,
                "est_median": float(np.median([r["est"] for r in rr if r["est"] is not None])) if any(r["est"] for r in rr) else None,
                "limit_median": float(np.median([r["limit"] for r in rr if r["limit"]])) if any(r["limit"] for r in rr) else None,
                "held_out_before_median_px": float(np.median([r["held_out_before"] for r in rr])),
                "held_out_after_median_px": float(np.median([r["held_out_after"] for r in rr])),
                "held_out_after_at_floor": sum(at_floor(r) for r in rr),
                "held_out_after_over_clean_median": float(np.median([r["held_out_after"] / ref_ho(r)
                                                                     for r in rr if ref_ho(r)] or [np.nan])),
                "top1_terms": sorted({str(r["top1"]) for r in rr}),
                # the size's error in its own stated uncertainty (the 15 % goal needs an effect ~7 u large)
                "est_z": [round((r["est"] - r["true"]) / r["est_u"], 2) for r in rr
                          if r["top1"] == r["expect"] and r["true"] and r.get("est_u")],
            }
        if rr and rr[0].get("parts"):
            out["effects"][case]["parts"] = parts_summary(rr)
        rn = [r for r in rows if r["case"] == case and not r["reveals"]]
        if rn:
            out["cannot_reveal"][case] = {
                "n": len(rn), "acq": rn[0]["acq"],
                "false_names": sum(r["top1"] is not None and r["top1"] != r["expect"] for r in rn),
                "named_correctly": sum(r["top1"] == r["expect"] for r in rn),
                "true_median": None if rn[0]["true"] is None else float(np.median([r["true"] for r in rn])),
                "limit_median": float(np.median([r["limit"] for r in rn if r["limit"]])) if any(r["limit"] for r in rn) else None,
                "not_observable": sum(r["limit"] is None for r in rn),
                "cannot_see": sorted({r["cannot_see"] for r in rn if r["cannot_see"]}),
                "limit_above_true": sum(r["limit"] is not None and r["true"] is not None and r["limit"] > r["true"]
                                        for r in rn),
                "x_star_z_rms": _rms([z for r in rn for z in r["x_star_z"]]),
            }
    return out


def parts_summary(rr):
    """A composite effect's parts one by one: of the recordings where a part is above its detection limit, on
    how many it is named (anywhere in the findings) and sized within 15 %; and where it is named below it."""
    out = {}
    for term in rr[0]["parts"]:
        def rel_err(r):
            return (r["found"][term][0] - r["parts"][term]["true"]) / r["parts"][term]["true"]
        above = [r for r in rr if r["parts"][term]["limit"] and r["parts"][term]["true"] > r["parts"][term]["limit"]]
        named = [r for r in above if term in r["found"]]
        rel = [rel_err(r) for r in named]
        out[term] = {"n": len(rr), "above_limit": len(above), "named": len(named),
                     "within_15pct": sum(abs(e) <= 0.15 for e in rel),
                     # not named, but listed as indistinguishable from a finding that stands in for it
                     "alternative_only": sum(any(term in f[2] for f in r["found"].values())
                                             for r in above if r not in named),
                     "rel_err": [round(e, 3) for e in rel],
                     "named_below_limit": sum(term in r["found"] for r in rr if r not in above),
                     # the limit is the worst direction's (90 % power): a draw in a better direction shows below it
                     "rel_err_below_limit": [round(rel_err(r), 3) for r in rr if r not in above and term in r["found"]],
                     "true_median": float(np.median([r["parts"][term]["true"] for r in rr])),
                     "limit_median": float(np.median([r["parts"][term]["limit"] for r in rr
                                                      if r["parts"][term]["limit"]] or [np.nan]))}
    return out


def _analyse_task(args):
    acq, variant = args
    return analyse_one(acq, variant)


def analyse_all(acqs, a):
    tasks = [(acq, v) for acq in sorted(acqs, key=lambda x: (x["seed"], x["job"])) for v in acq["variants"]
             if (acq["job"], v) in CASES and (a.only is None or v == "true" or CASES[(acq["job"], v)][0] in a.only)]
    rows = []
    with Pool(a.jobs) as pool:                  # one calibration + analysis per task, in task order
        for r in pool.imap(_analyse_task, tasks, chunksize=1):
            rows.append(r)
            print(json.dumps(r, default=float), file=sys.stderr, flush=True)
    out = summarise(rows)
    out.update(render_cpu_s_per_acquisition=float(np.mean([x["render_cpu_s"] for x in acqs])),
               analysis_cpu_s_median=float(np.median([r["cpu_s"] for r in rows])))
    return out


def job_list(a):
    jobs = []
    for s in range(a.first, a.first + a.effect_seeds):
        jobs += [(s, j) for j in JOBS if a.only is None or j in a.only or j == "clean"]
    return jobs + [(s, "clean") for s in range(a.first + a.effect_seeds, a.first + a.clean_seeds)]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--clean-seeds", type=int, default=50)
    ap.add_argument("--effect-seeds", type=int, default=6)
    ap.add_argument("--first", type=int, default=1000)
    ap.add_argument("--cache", default=None, help="directory for phase-1 detections (re-used when present)")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--render-only", action="store_true")
    ap.add_argument("--only", nargs="+", default=None, choices=sorted(set(JOBS) | set(TRACKER_JOBS) | {c[0] for c in CASES.values()}),
                    help="effect rows to run (the clean controls always run; CameraInfo rows by case name)")
    a = ap.parse_args()
    if a.cache:
        pathlib.Path(a.cache).mkdir(parents=True, exist_ok=True)
    jobs = [(s, j, a.cache) for s, j in job_list(a)]
    t0 = time.perf_counter()
    with Pool(a.jobs) as pool:
        acqs = []
        for r in pool.imap_unordered(render_job, jobs):
            acqs.append(r if not a.render_only else {"seed": r["seed"], "job": r["job"]})
            print(f"rendered {r['job']} {r['seed']} ({len(acqs)}/{len(jobs)}, {time.perf_counter() - t0:.0f} s)",
                  file=sys.stderr, flush=True)
    if a.render_only:
        return
    for x in acqs:                  # the truth summary afresh (detections cached by an older version lack keys)
        x["truth"] = truth_summary(_truth(x["seed"], job_overrides(x["job"], x["seed"]))[0])
    base = {(x["seed"], x["job"]): x for x in acqs}
    acqs += [tracker_job(base[(s, TRACKER_BASE.get(j, "clean"))], j) for s in range(a.first, a.first + a.effect_seeds)
             for j in TRACKER_JOBS if (s, TRACKER_BASE.get(j, "clean")) in base and (a.only is None or j in a.only)]
    print(json.dumps(analyse_all(acqs, a), default=float))


if __name__ == "__main__":
    main()
