"""Monte Carlo of the Pixel Probe calibration over seeds with varied physics (simulator truth).

Each seed: a new cell (assembly, placement, lens, blur, noise, levels, tracker distance),
a rendered Appendix A session, the full pipeline. Prints per-seed lines, then ONE JSON line:
X* error and z-scores, x_j* errors, camera pose errors and z-scores, solvePnP beside the
joint GLS, timing. Usage: python tests/benchmarks/validate_picms_calibration.py [n_seeds]
       python tests/benchmarks/validate_picms_calibration.py --repeat [n]   (one cell, n noise seeds)
"""
import json
import sys
import time

import numpy as np

from picms_nodes.core import camera, campaign, cell, pipeline


def run(seed, fixed_cell=None, **phys):
    rng = np.random.default_rng(1000 + seed)
    c = fixed_cell if fixed_cell is not None else cell.make_cell(rng, cell.make_physics(rng, **phys))
    t0 = time.perf_counter()
    rec, st = campaign.simulate_session(c, rng)
    t1 = time.perf_counter()
    res, rep = pipeline.calibrate_recording(rec)
    t2 = time.perf_counter()
    out = {"seed": seed, "sim_s": t1 - t0, "cal_s": t2 - t1, "chi2_dof": res.chi2_dof}
    x_true = c.to_tracker(c.smr_star_stage)[0]
    e = res.p_tracker - x_true
    out["xstar_err_um"] = float(np.linalg.norm(e) * 1e6)
    out["xstar_z"] = (e / np.sqrt(np.diag(res.cov_p_tracker))).tolist()
    out["px_err"] = [float(v) for cn in res.pixels for v in (res.pixels[cn] - st.x_star_px[cn])]
    out["px_z"] = [float(v) for cn in res.pixels for v in (res.pixels[cn] - st.x_star_px[cn]) / res.u_pixels[cn]]
    out["rot_err_as"], out["c_err_um"], out["pnp_rot_err_as"], out["pnp_c_err_um"], out["c_z"], out["rot_z"] = [], [], [], [], [], []
    for j, cn in enumerate(sorted(res.cameras)):
        cr, ct = res.cameras[cn], c.cameras[j]
        out["rot_err_as"].append(camera.rotation_angle_rad(cr.R_stage_camera, ct.pose.R_stage_camera) * 206265)
        out["pnp_rot_err_as"].append(camera.rotation_angle_rad(cr.pnp_R_stage_camera, ct.pose.R_stage_camera) * 206265)
        dc = cr.p_stage_centre - ct.pose.p_stage_centre
        out["c_err_um"].append(float(np.linalg.norm(dc) * 1e6))
        out["pnp_c_err_um"].append(float(np.linalg.norm(cr.pnp_p_stage_centre - ct.pose.p_stage_centre) * 1e6))
        out["c_z"] += (dc / cr.u_p_stage_centre).tolist()
        rv = camera.matrix_to_rotvec(ct.pose.R_stage_camera.T @ cr.R_stage_camera)
        out["rot_z"] += (cr.R_stage_camera @ rv / cr.u_rotation_rad).tolist()
    sq_t = cell.squareness_truth(c.A_travel)
    out["sq_z"] = [(res.squareness_rad[k] - sq_t[k]) / res.u_squareness_rad[k] for k in sq_t]
    out["x_star"] = res.p_tracker.tolist()
    out["pixels"] = [float(v) for cn in sorted(res.pixels) for v in res.pixels[cn]]
    out["u_pixels"] = [float(v) for cn in sorted(res.pixels) for v in res.u_pixels[cn]]
    out["u_x_star"] = np.sqrt(np.diag(res.cov_p_tracker)).tolist()
    out["centres"] = [float(v) for cn in sorted(res.cameras) for v in res.cameras[cn].p_stage_centre]
    out["rotvecs"] = [float(v) for cn in sorted(res.cameras)
                      for v in camera.matrix_to_rotvec(res.cameras[cn].R_stage_camera)]
    return out


def repeatability(n):
    """One cell (fixed assembly and physics), n re-calibrations with fresh noise: the spread."""
    c = cell.make_cell(np.random.default_rng(7), cell.make_physics(np.random.default_rng(7)))
    rows = []
    for s in range(n):
        r = run(s, fixed_cell=c)
        rows.append(r)
        print(json.dumps({"rep": s, "xstar_err_um": round(r["xstar_err_um"], 3)}), flush=True)
    sd = lambda k: np.std(np.array([r[k] for r in rows]), axis=0, ddof=1)
    print(json.dumps({
        "mode": "repeatability", "n": n,
        "x_star_sd_um_per_axis": (sd("x_star") * 1e6).round(2).tolist(),
        "x_star_stated_u_um": (np.array(rows[0]["u_x_star"]) * 1e6).round(2).tolist(),
        "x_star_err_um_median": float(np.median([r["xstar_err_um"] for r in rows])),
        "pixels_sd_px": sd("pixels").round(4).tolist(), "pixels_stated_u_px": np.round(rows[0]["u_pixels"], 4).tolist(),
        "camera_centre_sd_um": (sd("centres") * 1e6).round(2).tolist(),
        "camera_rot_sd_arcsec": (sd("rotvecs") * 206265).round(2).tolist(),
        "machine": "2 shared cores, loaded"}))


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "--repeat":
        repeatability(int(sys.argv[2]) if len(sys.argv) > 2 else 10)
        return
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 10
    rows = []
    for s in range(n):
        r = run(s)
        rows.append(r)
        print(json.dumps({k: (np.round(v, 4).tolist() if isinstance(v, (list, float)) else v) for k, v in r.items()
                          if k not in ("x_star", "pixels", "u_pixels", "u_x_star", "centres", "rotvecs")}), flush=True)
    cat = lambda k: np.concatenate([np.atleast_1d(r[k]) for r in rows])
    rms = lambda a: float(np.sqrt(np.mean(np.square(a))))
    print(json.dumps({
        "n_seeds": n,
        "xstar_err_um_median": float(np.median(cat("xstar_err_um"))), "xstar_err_um_max": float(cat("xstar_err_um").max()),
        "xstar_z_rms": rms(cat("xstar_z")), "px_err_abs_median": float(np.median(np.abs(cat("px_err")))),
        "px_z_rms": rms(cat("px_z")),
        "rot_err_as_median": float(np.median(cat("rot_err_as"))), "rot_err_as_max": float(cat("rot_err_as").max()),
        "rot_z_rms": rms(cat("rot_z")),
        "c_err_um_median": float(np.median(cat("c_err_um"))), "c_err_um_max": float(cat("c_err_um").max()),
        "c_z_rms": rms(cat("c_z")), "sq_z_rms": rms(cat("sq_z")), "chi2_dof_median": float(np.median(cat("chi2_dof"))),
        "pnp_rot_err_as_median": float(np.median(cat("pnp_rot_err_as"))), "pnp_c_err_um_median": float(np.median(cat("pnp_c_err_um"))),
        "sim_s_per_session_median": float(np.median(cat("sim_s"))), "cal_s_median": float(np.median(cat("cal_s"))),
        "machine": "2 shared cores, loaded",
    }))


if __name__ == "__main__":
    main()
