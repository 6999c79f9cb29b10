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
import pathlib
import sys

import numpy as np

from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.static_solver import solve_static

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))    # tests/: the shared detect_views
from ct_views import detect_views  # noqa: E402

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


def draw_scene(rng, cmm_u_m: float):
    """Renderer physics, the reference object as its file states it, the true object (CMM errors of
    sd ``cmm_u_m`` on the centres; the support tube present or not) and the render settings."""
    phys = draw_physics(rng)
    ref_file = helix49(center_uncertainty_m=cmm_u_m)
    true_obj = dataclasses.replace(ref_file, centres_of_m=ref_file.centres_of_m
                                   + rng.normal(0.0, cmm_u_m, ref_file.centres_of_m.shape),
                                   tube=ref_file.tube if phys["tube"] else None)
    settings = RenderSettings(flat_field_counts=phys["flat_field_counts"], blur_sigma_px=phys["blur_sigma_px"])
    return phys, ref_file, true_obj, settings


def run_trial(seed: int, n_views: int = 72, detector: DetectorSpec | None = None, cmm_u_m: float = 1e-6) -> Trial:
    rng = np.random.default_rng(seed)
    det = detector or DetectorSpec(1024, 1024, 0.0004)
    w, srd, sdd = draw_instrument(rng)
    phys, ref_file, true_obj, settings = draw_scene(rng, cmm_u_m)
    trial = Trial(w_true=w, srd_reported_m=srd, physics=phys)
    alphas = np.linspace(0.0, 2 * np.pi, n_views, endpoint=False)
    views = (((i + 1) * 100_000_000, render_projection(w, np.zeros(6), a, true_obj, det, settings, rng).image, a, srd)
             for i, a in enumerate(alphas))
    acc = detect_views(views, ref_file, det, sdd, phys["flat_field_counts"])
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


#: the instrument parameters (z_R, x_D, y_D, z_D, theta, phi, eta). The object pose is a nuisance
#: and, for helix49, defined only up to its symmetry: turned upside down and relabelled
#: (sphere i <-> 50 - i) the ideal multi-helix is itself turned about Y, so identity may pick
#: either pose; the instrument geometry is the same in both.
INSTRUMENT = slice(0, 7)


def z_scores(trials, which: str = "now") -> np.ndarray:
    """(n_trials, 7) z-scores of the instrument parameters of the successful trials."""
    rows = []
    for t in trials:
        x, sd = (t.x, t.std) if which == "now" else (t.x_centre, t.std_centre)
        if x is None or sd is None:
            continue
        rows.append((x[INSTRUMENT] - t.w_true[INSTRUMENT]) / sd[INSTRUMENT])
    return np.array(rows)


def run_error_map_trial(seed: int, n_positions: int = 7, n_views: int = 36,
                        detector: DetectorSpec | None = None, cmm_u_m: float = 1e-6) -> dict:
    """A random instrument stepped through ``n_positions`` stage positions (stage errors shaped
    like the paper's, along a travel slightly oblique to the detector normal), rendered, solved
    like the offline tool, and the positioning error compared with the truth: the slope of
    (measured - true) against the travel, with its standard uncertainty from the map's joint
    covariance. A scale error in the static geometry (the bias this issue is about) shows as a
    slope beyond its uncertainty."""
    from ct_calib_nodes.core.ct_pipeline import (campaign_error_map, solve_campaign_position,  # noqa: PLC0415
                                                 static_result_from_estimate)
    from ct_calib_nodes.core.geometry import detector_rotation  # noqa: PLC0415
    from ct_calib_nodes.core.scenario import paper_like_stage_errors, stage_motions  # noqa: PLC0415

    rng = np.random.default_rng(seed)
    det = detector or DetectorSpec(1024, 1024, 0.0004)
    w, srd0, sdd = draw_instrument(rng)
    srd0 = min(srd0, 0.55)
    w[0] = srd0 + rng.uniform(-2e-3, 2e-3)
    w[9] = w[0] + rng.uniform(-1e-3, 1e-3)
    phys, ref_file, true_obj, settings = draw_scene(rng, cmm_u_m)
    srd = srd0 + np.linspace(0.0, 0.72 - srd0, n_positions)
    travel = srd - srd[0]
    travel_df = detector_rotation(w[4], w[5], w[6]).T @ np.array([0.0, 0.0, 1.0])
    errors = paper_like_stage_errors(travel) * np.array([rng.uniform(0.2, 1.0)] * 3 + [1.0] * 3)
    motions = stage_motions(travel, travel_df, errors)
    alphas = np.linspace(0.0, 2 * np.pi, n_views, endpoint=False)
    views = (((k * n_views + i + 1) * 100_000_000, render_projection(w, motions[k], a, true_obj, det, settings, rng).image,
              a, srd[k]) for k in range(n_positions) for i, a in enumerate(alphas))
    acc = detect_views(views, ref_file, det, sdd, phys["flat_field_counts"])
    out = {"seed": seed, "physics": phys, "srd_m": srd.tolist(), "ok": False}
    st = solve_static(acc.positions[0].observations(), ref_file.centres_of_m, det, srd[0], sdd,
                      centre_uncertainty_m=ref_file.center_uncertainty_m)
    if not st.success or len(acc.positions) != n_positions:
        out["message"] = f"static: {st.message}; {len(acc.positions)} positions"
        return out
    published = static_result_from_estimate(st.x, st.covariance, ref_file.centres_of_m,
                                            obs=acc.positions[0].observations(), detector=det,
                                            centre_uncertainty_m=ref_file.center_uncertainty_m)
    res = {k: solve_campaign_position(acc, k, published, det) for k in range(1, n_positions)}
    em, ks = campaign_error_map(acc, res, published)
    if len(ks) != n_positions:
        out["message"] = "not every position solved: " + "; ".join(r.message for r in res.values() if not r.success)
        return out
    err = em.positioning_m - errors[:, 0]
    cov = em.covariance[0::6, 0::6]                      # positioning block (K, K)
    a = np.stack([np.ones_like(travel), travel], axis=1)
    h = np.linalg.pinv(a)                                 # LS line: intercept, slope
    slope = float((h @ err)[1])
    u_slope = float(np.sqrt((h @ cov @ h.T)[1, 1]))
    out.update(ok=True, positioning_error_um=(err * 1e6).tolist(), u_positioning_um=(em.u_positioning_m * 1e6).tolist(),
               slope_um_per_m=slope * 1e6, u_slope_um_per_m=u_slope * 1e6, z_slope=slope / u_slope,
               max_abs_z=float(np.max(np.abs(err[1:] / em.u_positioning_m[1:]))))
    # every component of the map against the truth, in units of its stated u (positions 2..K; the first is
    # the reference, 0 by definition except the straightness, a deviation from the fitted line), and the
    # chi-square of each component's K errors under the map's joint covariance (pseudo-inverse: the line
    # removed from the straightness takes 2 degrees of freedom, the reference position 1 from the others)
    out.update(zip(("component_z", "component_chi2_dof"), _component_z(em, errors)))
    # the single-projection map (the paper's second mode: the first projection of each position) on the
    # same frames, its per-projection shared shift taken from the multi-projection solve
    res_s = {k: solve_campaign_position(acc, k, published, det, mode="single", multi=res[k])
             for k in range(1, n_positions)}
    em_s, ks_s = campaign_error_map(acc, res_s, published, name="single")
    if len(ks_s) == n_positions:
        out.update(zip(("single_component_z", "single_component_chi2_dof"), _component_z(em_s, errors)))
    return out


def _component_z(em, errors):
    """Each map component against the truth in units of its stated u (positions 2..K) and the
    chi-square of its K errors under the map's joint covariance (pseudo-inverse: the line removed
    from the straightness takes 2 degrees of freedom, the reference position 1 from the others)."""
    comps = ("positioning", "straightness_x", "straightness_y", "pitch", "yaw", "roll")
    units = ("m", "m", "m", "rad", "rad", "rad")
    z, chi2 = {}, {}
    for c, (name, unit) in enumerate(zip(comps, units)):
        e = getattr(em, f"{name}_{unit}") - errors[:, c]
        u = getattr(em, f"u_{name}_{unit}")
        z[name] = (e[1:] / u[1:]).tolist()
        cc = em.covariance[c::6, c::6]
        pinv = np.linalg.pinv(cc, rcond=1e-10, hermitian=True)
        chi2[name] = [float(e @ pinv @ e), int(np.linalg.matrix_rank(cc, tol=1e-10 * np.max(np.diag(cc))))]
    return z, chi2
