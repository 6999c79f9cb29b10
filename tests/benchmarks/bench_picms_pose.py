"""Camera poses: joint Gauss-Newton / GLS (ours) vs OpenCV solvePnP (iterative) per camera,
on the same rendered calibration session, side by side in one run; plus rendering and disc
detection per 5 MP frame. Ends with ONE JSON line.

Usage: python tests/benchmarks/bench_picms_pose.py [n_seeds]
"""
import json
import sys
import time

import numpy as np

from picms_nodes.core import camera, campaign, cell, pipeline, render
from picms_nodes.core.calibrate import solve_cameras, solvepnp_pose, travel_matrix
from picms_nodes.core.detect import detect_disc


def main():
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 3
    t_gls, t_pnp, e_gls, e_pnp, c_gls, c_pnp, t_render, t_detect = [], [], [], [], [], [], [], []
    t_cold = []
    for seed in range(n):
        rng = np.random.default_rng(500 + seed)
        c = cell.make_cell(rng, cell.make_physics(rng))
        for j, cam in enumerate(c.cameras):
            t0 = time.perf_counter()
            render.render_frame(cam.pose, cam.true_intrinsics, c.physics, rng, sphere_stage=c.smr_star_stage)
            t_cold.append(time.perf_counter() - t0)     # first frame of a camera: background maps built
            for _ in range(3):
                t0 = time.perf_counter()
                img = render.render_frame(cam.pose, cam.true_intrinsics, c.physics, rng, sphere_stage=c.smr_star_stage)
                t1 = time.perf_counter()
                detect_disc(img, cam.info_intrinsics)
                t2 = time.perf_counter()
                t_render.append(t1 - t0)
                t_detect.append(t2 - t1)
        rec, st = campaign.simulate_session(c, rng)
        res, _ = pipeline.calibrate_recording(rec)
        d = res.design
        U, obs, cov = d["U"], d["obs"], d["obs_cov"]
        dq = -U
        reps = 5
        t0 = time.perf_counter()
        for _ in range(reps):
            pnp = [solvepnp_pose(U, obs[j]) for j in range(3)]
        t_pnp.append((time.perf_counter() - t0) / reps / 3)
        t0 = time.perf_counter()
        for _ in range(reps):
            # the joint fit re-estimates the squareness with the poses (U depends on it)
            sol = solve_cameras(lambda e: -(dq @ np.linalg.inv(travel_matrix(d["sq"])).T @ travel_matrix(e).T), 3,
                                d["sq"], d["cov_U"], obs, cov, pnp, d["sq_prior"])
        t_gls.append((time.perf_counter() - t0) / reps / 3)
        for j, cn in enumerate(d["cameras"]):
            ct = c.cameras[j].pose
            R, C = sol[0][j]
            e_gls.append(camera.rotation_angle_rad(R, ct.R_stage_camera) * 206265)
            e_pnp.append(camera.rotation_angle_rad(pnp[j][0], ct.R_stage_camera) * 206265)
            c_gls.append(np.linalg.norm(C - ct.p_stage_centre) * 1e6)
            c_pnp.append(np.linalg.norm(pnp[j][1] - ct.p_stage_centre) * 1e6)
        print(f"seed {seed}: rot err GLS {np.round(e_gls[-3:], 2)} arcsec, solvePnP {np.round(e_pnp[-3:], 2)}", flush=True)
    med = lambda a: float(np.median(a))
    print(json.dumps({"n_seeds": n, "pose_ms_per_camera_joint_gls": med(t_gls) * 1e3,
                      "pose_ms_per_camera_solvepnp": med(t_pnp) * 1e3,
                      "rot_err_arcsec_median_gls": med(e_gls), "rot_err_arcsec_median_solvepnp": med(e_pnp),
                      "centre_err_um_median_gls": med(c_gls), "centre_err_um_median_solvepnp": med(c_pnp),
                      "render_ms_per_5MP_frame": med(t_render) * 1e3, "render_ms_first_frame_of_a_camera": med(t_cold) * 1e3, "detect_ms_per_frame": med(t_detect) * 1e3,
                      "machine": "2 shared cores, loaded by other jobs"}))


if __name__ == "__main__":
    main()
