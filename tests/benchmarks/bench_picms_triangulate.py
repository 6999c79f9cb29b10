"""Triangulation: our N-view DLT (seed paper eqs 13-16, three views, pixel-weighted, + Gauss-Newton
on the pixel residuals) vs OpenCV's two-view cv2.triangulatePoints on the same data, side by side
in one run: error against the truth and time per point.

Data: cells with random assembly and lenses; points uniform in a 2 mm cube around X*; exact
projections through the true camera model plus Gaussian pixel noise (sigma 0.2 px, about the
edge-fit noise of a 250 um dot); both methods get the same undistorted normalised coordinates
and the same (true) camera poses. OpenCV is run on each of the three camera pairs; the best
pair (the one with the smallest error, chosen with the truth: an optimistic bound for it) and
the mean over pairs are reported. Ends with ONE JSON line.

Ours per point (triangulate, as drive_to calls it) and batched (triangulate_many, the same
method vectorised over points) are both timed.

Usage: python tests/benchmarks/bench_picms_triangulate.py [n_points_per_cell] [n_cells]
"""
import json
import sys
import time

import cv2
import numpy as np

from picms_nodes.core import camera, cell, targeting
from picms_nodes.measure_sim import truth_probe


def main():
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 300
    n_cells = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    sig = 0.2
    e_ours, e_dlt, e_cv_best, e_cv_mean = [], [], [], []
    t_ours = t_dlt = t_cv = t_batch = 0.0
    e_batch = []
    for k in range(n_cells):
        rng = np.random.default_rng(700 + k)
        truth = cell.make_cell(rng, cell.make_physics(rng))
        probe = truth_probe(truth, sigma_px=1e-4)
        x0 = probe.xstar_body
        names = probe.camera_names
        P = rng.uniform(-1e-3, 1e-3, (n, 3))
        px = {c.name: camera.project(c.pose, c.true_intrinsics, P) + rng.normal(0, sig, (n, 2)) for c in truth.cameras}
        # ours: full (DLT + GN), and the DLT alone, per point
        t0 = time.perf_counter()
        ours = np.array([targeting.triangulate(probe, {c: (*px[c][i], sig) for c in names}).offset_stage
                         for i in range(n)])
        t_ours += time.perf_counter() - t0
        t0 = time.perf_counter()
        dlt = np.array([targeting.triangulate(probe, {c: (*px[c][i], sig) for c in names}, refine=False).dlt_point_body
                        for i in range(n)]) - x0
        t_dlt += time.perf_counter() - t0
        t0 = time.perf_counter()
        batch = targeting.triangulate_many(probe, {c: px[c] for c in names}, sig)[0]
        t_batch += time.perf_counter() - t0
        # OpenCV two-view on the same undistorted normalised coordinates, all three pairs, batched
        nrm = {c: probe.intrinsics[c].undistort(px[c]) for c in names}
        Pm = {c: np.hstack([probe.R_stage_camera[c].T, (-probe.R_stage_camera[c].T @ probe.p_stage_centre[c])[:, None]])
              for c in names}
        t0 = time.perf_counter()
        cvp = []
        for a, b in ((0, 1), (0, 2), (1, 2)):
            X = cv2.triangulatePoints(Pm[names[a]], Pm[names[b]], nrm[names[a]].T.copy(), nrm[names[b]].T.copy())
            cvp.append((X[:3] / X[3]).T - x0)
        t_cv += (time.perf_counter() - t0) / 3
        errs = np.array([np.linalg.norm(c - P, axis=1) for c in cvp])      # (3 pairs, n)
        rms_pair = np.sqrt((errs ** 2).mean(1))
        e_cv_best.append(errs[int(np.argmin(rms_pair))])
        e_cv_mean.append(errs.ravel())
        e_ours.append(np.linalg.norm(ours - P, axis=1))
        e_dlt.append(np.linalg.norm(dlt - P, axis=1))
        e_batch.append(np.linalg.norm(batch - P, axis=1))

    def rms(v):
        return round(float(np.sqrt(np.mean(np.concatenate(v) ** 2)) * 1e6), 4)
    npts = n * n_cells
    print(json.dumps({
        "n_points": npts, "n_cells": n_cells, "pixel_sigma_px": sig,
        "rms_3d_err_um": {"ours_dlt3_gn": rms(e_ours), "ours_batched_dlt3_gn": rms(e_batch), "ours_dlt3_only": rms(e_dlt),
                          "cv2_two_view_best_pair": rms(e_cv_best), "cv2_two_view_all_pairs": rms(e_cv_mean)},
        "time_us_per_point": {"ours_dlt3_gn": round(t_ours / npts * 1e6, 1),
                              "ours_batched_dlt3_gn": round(t_batch / npts * 1e6, 2), "ours_dlt3_only": round(t_dlt / npts * 1e6, 1),
                              "cv2_two_view_batched": round(t_cv / npts * 1e6, 2)},
        "note": "loaded 2-core machine; ours_dlt3_gn per point in Python (as targeting calls it: undistortion, "
                "covariance), ours_batched = triangulate_many (numpy, all points at once), cv2 batched"}))


if __name__ == "__main__":
    main()
