"""Benchmark of the CT geometry solver core (not a test; prints figures).

Static solve, 49 spheres x 360 projections, 13 parameters: our LM with the
analytic Jacobian against scipy.optimize.least_squares with a 2-point
finite-difference Jacobian, method "lm" (MINPACK) and method "trf" (the
default), side by side (and MINPACK with our analytic Jacobian, to separate
what the Jacobian buys from what the coarse-to-fine start buys), on the same data, same start and the same residual
function: the fastest one we have (ct_model.StaticKernel.residuals, built
once outside the timed call, so the baseline does not pay for the set-up our
timing includes). Same tolerances in the sense that all three must reach the
same cost (printed). Then the per-position error-motion solve (multi and
single), and how the cost grows with the number of projections. Ends with
ONE JSON line.

Run:  cd /work/main && .venv/bin/python tests/benchmarks/bench_ct_solver.py [--repeat N]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

# One BLAS thread for every contender (set before numpy loads OpenBLAS; override by exporting it).
# With OpenBLAS's default threads on this 2-core machine, scipy's 'trf' (an SVD of the 31408 x 13
# Jacobian per iteration) took 63-129 ms instead of ~35 ms and varied 10x from run to run: the
# idle workers spin and fight the main thread. Comparing against that would flatter us.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "ros_ws", "src", "ct_calib_nodes"))

from scipy.optimize import least_squares  # noqa: E402

from ct_calib_nodes.core.ct_model import StaticKernel, static_residuals  # noqa: E402
from ct_calib_nodes.core.error_motion import solve_error_motion  # noqa: E402
from ct_calib_nodes.core.geometry import DetectorSpec  # noqa: E402
from ct_calib_nodes.core.scenario import default_campaign  # noqa: E402
from ct_calib_nodes.core.phantom import helix49  # noqa: E402
from ct_calib_nodes.core.simulate_obs import simulate_observations  # noqa: E402
from ct_calib_nodes.core.static_solver import COARSE_VIEWS, initial_guess, solve_static  # noqa: E402


def median_time(fn, repeat):
    ts = []
    out = None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)), out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    det = DetectorSpec(1024, 1024, 0.0004)
    cen = helix49().centres_of_m
    camp = default_campaign()
    w = camp.static_w
    srd1, sdd = camp.srd_reported_m[0], camp.sdd_reported_m
    alphas = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    rng = np.random.default_rng(2024)
    # what the pipeline gives the solver: silhouette-ellipse centres with their semi-minor axes
    sim = simulate_observations(w, cen, det, alphas, rng, 0.05, contour_radius_m=1.1e-3)
    obs = sim.obs

    # ---- static: ours (includes the data-derived start and the covariance)
    t_ours, res = median_time(lambda: solve_static(obs, cen, det, srd1, sdd), args.repeat)
    x0, _ = initial_guess(obs, cen, det, srd1, sdd)
    # ---- static: scipy baseline, same residual function, same start, FD Jacobian
    kern = StaticKernel(obs, cen, det)
    fun = kern.residuals          # blocked order; the order is irrelevant to least_squares
    t_res_kern, _ = median_time(lambda: fun(x0), 21)
    t_res_plain, _ = median_time(lambda: static_residuals(x0, obs, cen, det), 21)
    t_scipy, sres = median_time(lambda: least_squares(fun, x0, method="lm", jac="2-point", x_scale="jac"),
                                max(3, args.repeat // 2))
    t_trf, tres = median_time(lambda: least_squares(fun, x0, method="trf", jac="2-point", x_scale="jac"),
                              max(3, args.repeat // 2))
    jac_an = lambda x: kern.evaluate(x)[1]().T       # noqa: E731 - our analytic Jacobian, for scipy
    t_lm_an, ares = median_time(lambda: least_squares(fun, x0, method="lm", jac=jac_an, x_scale="jac"),
                                max(3, args.repeat // 2))
    # ours ends with per-axis weights from the noise model: compare the unweighted cost at our estimate
    our_plain_cost = 0.5 * float(np.sum(kern.residuals(res.x) ** 2))
    d_cost = abs(our_plain_cost - sres.cost) / sres.cost
    print(f"static solve, {obs.n_obs} centres ({cen.shape[0]} spheres x 360 projections, overlaps removed), 13 params")
    print(f"{'solver':42s} {'median ms':>10s} {'nfev':>6s} {'njev':>6s} {'cost':>12s}")
    print(f"{'ours: LM + analytic Jacobian (+start,+cov)':42s} {t_ours * 1e3:10.1f} {res.nfev:6d} {res.njev:6d} {our_plain_cost:12.6f}")
    print(f"{'scipy least_squares lm, 2-point FD jac':42s} {t_scipy * 1e3:10.1f} {sres.nfev:6d} {'-':>6s} {sres.cost:12.6f}")
    print(f"{'scipy least_squares trf (default), 2-point':42s} {t_trf * 1e3:10.1f} {tres.nfev:6d} {tres.njev:6d} {tres.cost:12.6f}")
    print(f"{'scipy least_squares lm, OUR analytic jac':42s} {t_lm_an * 1e3:10.1f} {ares.nfev:6d} {ares.njev:6d} {ares.cost:12.6f}")
    print(f"speed-up x{t_scipy / t_ours:.1f} vs lm, x{t_trf / t_ours:.1f} vs trf; relative cost difference {d_cost:.2e}")
    print(f"(ours: nfev/njev count {res.nfev} evaluations, the first ones on the {COARSE_VIEWS}-view coarse subset)")
    print(f"baseline residual evaluation: {t_res_kern * 1e3:.2f} ms (precomputed kernel; "
          f"static_residuals() with set-up per call: {t_res_plain * 1e3:.2f} ms)")
    err_sd = (res.x - w) / res.std
    print("static error / reported sd:", np.array2string(err_sd, precision=2))

    # ---- error motion (position k = 19), multi and single, with and without static propagation
    k = len(camp.srd_reported_m) - 1
    simk = simulate_observations(w, cen, det, alphas, rng, 0.05, motion=camp.motions[k], contour_radius_m=1.1e-3)
    argsk = (simk.obs, res, det, camp.srd_reported_m[k], srd1)
    t_mc, mres = median_time(lambda: solve_error_motion(*argsk, include_static_uncertainty=False), args.repeat)
    t_mt, _ = median_time(lambda: solve_error_motion(*argsk), args.repeat)
    t_s, sres1 = median_time(lambda: solve_error_motion(*argsk, mode="single", include_static_uncertainty=False),
                             args.repeat)
    print(f"\nerror motion, position k={k + 1}: {simk.obs.n_obs} centres")
    print(f"  multi, conditional covariance      {t_mc * 1e3:7.1f} ms (nfev {mres.nfev})")
    print(f"  multi, + static propagation        {t_mt * 1e3:7.1f} ms")
    print(f"  single projection ({sres1.n_obs} centres)    {t_s * 1e3:7.1f} ms (nfev {sres1.nfev})")

    # ---- scaling with the number of projections
    scaling = []
    print("\nscaling of the static solve with the number of projections")
    print(f"{'projections':>11s} {'centres':>8s} {'median ms':>10s} {'ms/1000 centres':>16s}")
    for m in (30, 90, 180, 360, 720):
        a = np.linspace(0, 2 * np.pi, m, endpoint=False)
        s = simulate_observations(w, cen, det, a, rng, 0.05, contour_radius_m=1.1e-3)
        t, r = median_time(lambda: solve_static(s.obs, cen, det, srd1, sdd), args.repeat)
        scaling.append({"projections": m, "centres": s.obs.n_obs, "ms": round(t * 1e3, 2)})
        print(f"{m:11d} {s.obs.n_obs:8d} {t * 1e3:10.1f} {t * 1e6 / s.obs.n_obs:16.2f}")
    out = {
        "openblas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
        "static_n_centres": obs.n_obs, "static_ours_ms": round(t_ours * 1e3, 2),
        "static_scipy_fd_ms": round(t_scipy * 1e3, 2), "speedup": round(t_scipy / t_ours, 1),
        "static_scipy_trf_fd_ms": round(t_trf * 1e3, 2), "static_scipy_lm_analytic_jac_ms": round(t_lm_an * 1e3, 2), "speedup_vs_trf": round(t_trf / t_ours, 1),
        "cost_rel_diff": float(f"{d_cost:.3g}"),
        "cost_rel_diff_trf": float(f"{abs(our_plain_cost - tres.cost) / tres.cost:.3g}"),
        "baseline_residual_ms": round(t_res_kern * 1e3, 3), "static_nfev": res.nfev, "static_njev": res.njev,
        "motion_multi_ms": round(t_mc * 1e3, 2), "motion_multi_with_static_cov_ms": round(t_mt * 1e3, 2),
        "motion_single_ms": round(t_s * 1e3, 2), "scaling": scaling,
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
