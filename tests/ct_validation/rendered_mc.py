"""Monte Carlo of the CT static calibration on RENDERED frames over random instruments.

Shared by tests/ct_validation/test_rendered_mc.py (reduced, in the test suite) and
tests/benchmarks/validate_ct_rendered_mc.py (the full campaign, printing one JSON line).

Each trial draws an instrument within INTERFACES-style misalignments (detector offsets of a few
mm, tilts up to 0.6 deg, reported SRD 0.3 to 0.7 m, an object pose anywhere about the axis), a
renderer physics the detector was not tuned on (blur 0.4 to 1.0 px, 20k to 60k counts, the
support tube present or absent), CMM errors of the object's true centres (the file keeps the
nominal ones with their stated uncertainty), renders the projections, and runs them through
the same code as the offline solve (detection + identity, accumulator, static solve). The
truth never reaches the solver. Returned per trial: the estimate, its standard uncertainties
and the truth, for the ellipse-centre model (now) and the centre-projection model (before).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ct_calib_nodes.core.ct_pipeline import CampaignAccumulator, FrameProcessor
from ct_calib_nodes.core.detect import FrameError
from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.static_solver import solve_static

DEG = np.pi / 180.0
SDD = 1.04821


@dataclasses.dataclass
class Trial:
    w_true: np.ndarray
    srd_reported_m: float
    physics: dict
    x: np.ndarray | None = None            # ellipse-centre model (the pipeline)
    std: np.ndarray | None = None
    x_centre: np.ndarray | None = None     # centre-projection model (the paper's; the state before)
    std_centre: np.ndarray | None = None
    outcome: str = ""
    message: str = ""
    n_obs: int = 0
    variance_factor: float = np.nan
    noise: dict | None = None


def draw_instrument(rng):
    """(w_true (13,), reported SRD [m], sdd_reported [m])."""
    srd = rng.uniform(0.30, 0.70)
    z_r = srd + rng.uniform(-2e-3, 2e-3)
    w = np.array([
        z_r, rng.uniform(-3e-3, 3e-3), rng.uniform(-3e-3, 3e-3), SDD + rng.uniform(-3e-3, 3e-3),
        rng.uniform(-0.6, 0.6) * DEG, rng.uniform(-0.6, 0.6) * DEG, rng.uniform(-0.6, 0.6) * DEG,
        rng.uniform(-1e-3, 1e-3), rng.uniform(-1e-3, 1e-3), z_r + rng.uniform(-1e-3, 1e-3),
        rng.uniform(-0.5, 0.5) * DEG, rng.uniform(0.0, 2 * np.pi), rng.uniform(-0.5, 0.5) * DEG])
    return w, srd, SDD


def draw_physics(rng):
    return {"blur_sigma_px": float(rng.uniform(0.4, 1.0)), "flat_field_counts": float(rng.uniform(2e4, 6e4)),
            "tube": bool(rng.random() < 0.5)}


def run_trial(seed: int, n_views: int = 72, detector: DetectorSpec | None = None, cmm_u_m: float = 1e-6) -> Trial:
    rng = np.random.default_rng(seed)
    det = detector or DetectorSpec(1024, 1024, 0.0004)
    w, srd, sdd = draw_instrument(rng)
    phys = draw_physics(rng)
    ref_file = helix49(center_uncertainty_m=cmm_u_m)
    true_obj = dataclasses.replace(ref_file, centres_of_m=ref_file.centres_of_m
                                   + rng.normal(0.0, cmm_u_m, ref_file.centres_of_m.shape),
                                   tube=ref_file.tube if phys["tube"] else None)
    settings = RenderSettings(flat_field_counts=phys["flat_field_counts"], blur_sigma_px=phys["blur_sigma_px"])
    trial = Trial(w_true=w, srd_reported_m=srd, physics=phys)
    proc = FrameProcessor(ref_file, det, sdd, phys["flat_field_counts"])
    acc = CampaignAccumulator()
    alphas = np.linspace(0.0, 2 * np.pi, n_views, endpoint=False)
    stamp = 0

    def take(results):
        for fr in results:
            ids, uv, sig, minor = fr.accepted()
            idx = np.searchsorted(ref_file.ids, ids) if len(ids) else np.zeros(0, np.int64)
            acc.add_frame(fr.stamp_ns, fr.alpha_rad, fr.srd_reported_m, idx, uv, sig, 0, minor)

    for a in alphas:
        frame = render_projection(w, np.zeros(6), a, true_obj, det, settings, rng)
        stamp += 100_000_000
        try:
            take(proc.push(stamp, frame.image, "mono16", a, srd))
        except FrameError:
            continue
    take(proc.flush())
    if not acc.positions:
        trial.outcome, trial.message = "no_data", "no frame usable"
        return trial
    obs = acc.positions[0].observations()
    trial.n_obs = obs.n_obs
    res = solve_static(obs, ref_file.centres_of_m, det, srd, sdd, centre_uncertainty_m=ref_file.center_uncertainty_m)
    trial.outcome, trial.message = res.outcome, res.message
    trial.variance_factor = res.variance_factor
    trial.noise = None if res.noise is None else res.noise.to_dict()
    if res.success:
        trial.x, trial.std = res.x, res.std
    before = solve_static(dataclasses.replace(obs, minor_axis_px=None), ref_file.centres_of_m, det, srd, sdd,
                          max_rms_ratio=np.inf)
    if np.all(np.isfinite(before.x)):
        trial.x_centre = before.x
        trial.std_centre = np.sqrt(np.maximum(np.diag(before.normal_inverse), 0.0))
    return trial


def z_scores(trials, which: str = "now") -> np.ndarray:
    """(n_trials, 13) z-scores of the successful trials; rho_Y wrapped."""
    rows = []
    for t in trials:
        x, sd = (t.x, t.std) if which == "now" else (t.x_centre, t.std_centre)
        if x is None or sd is None:
            continue
        err = x[:13] - t.w_true
        err[11] = np.angle(np.exp(1j * err[11]))
        rows.append(err / sd[:13])
    return np.array(rows)
