"""Where does the static geometry's remaining under-coverage come from? (issue 14.2, study; not a test)

On independent 512 px recordings the 7 instrument parameters' z-scores have sd ~1.15 each (the sum of
their squares ~9 against 7). This splits each instrument parameter's error (estimate - truth) into

* the calibrated centres' (CMM) part: the same solve on perfect detections (the true ellipse centres),
  in units of that part of the stated u (the solver's centre sensitivity times center_uncertainty);
* the detection part: the rest, in units of the detection part of the stated u (total minus CMM in
  quadrature), and, for the same detection errors, in units of three alternative covariances formed
  at the estimate with the solver's weights: independent observations (variance factor), and
  cluster-robust sandwiches with the projections (views) or the spheres as clusters (CR1 small-sample
  factor G/(G-1) (N-1)/(N-p), the usual one: an uncorrected or over-corrected sandwich shifts the sd by
  10-25 % with 36 clusters and 13 parameters);

and fits each recording's detection errors (truth-scored) as a scale about the image centre, per image
axis (e = k (uv - centre)), overall and for the spheres on the object's silhouette (|s| >= 0.8) and
inside it (|s| < 0.7): a magnification-like bias lies in the Jacobian's column space, so no estimate
from the residuals can see it.

    .venv/bin/python tests/benchmarks/study_ct_coverage_decomposition.py --keep DIR [--seeds a-b] [--keep DIR2 --seeds c-d]

Reads what ``validate_ct_indep.py --keep DIR`` kept (uses study_ct_location_bias.case_detections). Prints
a table, then ONE JSON line. Measured figures: ct_detect.md, "Coverage: where the excess comes from".
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent / "ct_validation")]

import ct_indep_gen as gen  # noqa: E402
import study_ct_location_bias as lb  # noqa: E402
from ct_calib_nodes.core.ct_model import StaticKernel  # noqa: E402
from ct_calib_nodes.core.geometry import DetectorSpec  # noqa: E402
from ct_calib_nodes.core.location_noise import N_CLASSES, location_class  # noqa: E402
from ct_calib_nodes.core.observations import CentreObservations  # noqa: E402

NAMES = lb.NAMES


def _cluster_cov(jw, rw, a_inv, ids):
    """CR1 cluster-robust sandwich A^-1 (sum_g s_g s_g^T) A^-1 with s_g = sum of J_w^T r_w over cluster g."""
    u, inv = np.unique(ids, return_inverse=True)
    s = np.zeros((len(u), jw.shape[1]))
    np.add.at(s, inv, jw * rw[:, None])
    g, n, p = len(u), len(rw), jw.shape[1]
    return a_inv @ (s.T @ s) @ a_inv * (g / (g - 1)) * ((n - 1) / (n - p))


def _scale(e, d, m):
    """Least-squares scale k per axis of errors e against offsets d over mask m [ppm]."""
    return [float(np.sum(e[m, j] * d[m, j]) / np.sum(d[m, j] ** 2)) * 1e6 for j in (0, 1)]


def study_case(case):
    a, t = case["a"], case["truth"]
    uv, e_det = a[:, 0:2], a[:, 0:2] - a[:, 7:9]
    r1 = lb.solve(case, uv)                                          # as the offline tool solves
    rp = lb.solve(case, a[:, 7:9], location_classes=False)           # perfect detections: the CMM part
    u_cmm = gen.load_reference()[3]
    var_cmm = ((rp.centre_sensitivity * np.repeat(u_cmm, 3)) ** 2).sum(1)[:7]
    sd = r1.std[:7]
    sd_det = np.sqrt(np.maximum(sd ** 2 - var_cmm, 1e-300))
    err = (r1.x - case["w"])[:7]
    err_cmm = (rp.x - case["w"])[:7]
    err_det = err - err_cmm
    # alternative covariances of the detection part at the estimate, with the solver's final weights
    obs = CentreObservations(uv, a[:, 2].astype(int), a[:, 3], a[:, 4].astype(int), sigma_px=a[:, 5],
                             minor_axis_px=a[:, 6])
    det = DetectorSpec(int(t["cols"]), int(t["rows"]), float(t["pitch_m"]))
    r, jac = StaticKernel(obs, case["c_file"], det, ()).evaluate(r1.x)
    jt = jac().T
    nz = r1.noise
    lf = np.array(nz.location_factor) if nz.location_factor else np.ones(N_CLASSES)
    cls = location_class(r1.x[:13], case["c_file"], obs.sphere_index, obs.alpha_rad)
    w = 1.0 / (np.r_[a[:, 5] * nz.factor_u, a[:, 5] * nz.factor_v] * np.tile(lf[cls], 2))
    jw, rw = jt * w[:, None], r * w
    a_inv = np.linalg.pinv(jw.T @ jw)
    covs = {"independent": a_inv * (rw @ rw) / (len(rw) - jt.shape[1]),
            "views": _cluster_cov(jw, rw, a_inv, np.tile(obs.view_index, 2)),
            "spheres": _cluster_cov(jw, rw, a_inv, np.tile(obs.sphere_index, 2))}
    out = {"seed": case["seed"], "tube": bool(case["tube"]), "z": (err / sd).tolist(),
           "z_cmm": (err_cmm / np.sqrt(var_cmm)).tolist(), "z_det": (err_det / sd_det).tolist(),
           "cmm_share": (var_cmm / sd ** 2).tolist()}
    for k, c in covs.items():
        out[f"z_det_{k}"] = (err_det / np.sqrt(np.diag(c)[:7])).tolist()
    centre = np.array([(t["cols"] - 1) / 2, (t["rows"] - 1) / 2])
    d = uv - centre
    s_abs = np.abs(a[:, 9])
    out["err_det"] = err_det.tolist()
    out["sd_det"] = sd_det.tolist()
    out["mean_error_px"] = e_det.mean(0).tolist()     # the detection errors' common shift (cols, rows)
    out["k_ppm"] = _scale(e_det, d, np.ones(len(a), bool))
    out["k_silhouette_ppm"] = _scale(e_det, d, s_abs >= 0.8)
    out["k_inner_ppm"] = _scale(e_det, d, s_abs < 0.7)
    return out


def _summary(rows, key):
    v = np.array([r[key] for r in rows])
    ok = np.all(np.isfinite(v), axis=1) & np.all(np.abs(v) < 1e3, axis=1)   # a CMM-dominated u can leave ~0 detection part
    v = v[ok]
    return {"n": int(ok.sum()), "mean": np.round(v.mean(0), 2).tolist(), "sd": np.round(v.std(0, ddof=1), 2).tolist(),
            "sum_z2": round(float((v ** 2).sum(1).mean()), 2)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", action="append", required=True, help="validate_ct_indep.py --keep directory (repeatable)")
    ap.add_argument("--seeds", action="append", required=True, help="first-last, one per --keep")
    ap.add_argument("--dump", help="write the per-recording rows (JSON) to this file")
    args = ap.parse_args()
    rows = []
    for keep, seeds in zip(args.keep, args.seeds):
        lo, hi = (int(v) for v in seeds.split("-"))
        for s in range(lo, hi + 1):
            c = lb.case_detections(pathlib.Path(keep), s)
            if c is not None:
                rows.append(study_case(c))
                print(f"seed {s} tube {rows[-1]['tube']!s:5s} z {np.round(rows[-1]['z'], 2)}", flush=True)
    if args.dump:
        pathlib.Path(args.dump).write_text(json.dumps(rows))
    summary = {"cases": len(rows), "tube_cases": sum(r["tube"] for r in rows), "names": NAMES}
    print(f"\n{'z-scores over ' + str(len(rows)) + ' recordings':58s} " + " ".join(f"{n:>6s}" for n in NAMES) + "  sum z^2")
    for key, label in (("z", "total (the solver's u)"), ("z_cmm", "CMM part / its u"), ("z_det", "detection part / its u"),
                       ("z_det_independent", "detection part / independent-noise u"),
                       ("z_det_views", "detection part / cluster-by-view sandwich u"),
                       ("z_det_spheres", "detection part / cluster-by-sphere sandwich u")):
        s = _summary(rows, key)
        summary[key] = s
        print(f"{label:46s} mean " + " ".join(f"{v:+6.2f}" for v in s["mean"]))
        print(f"{'':46s}   sd " + " ".join(f"{v:6.2f}" for v in s["sd"]) + f"  {s['sum_z2']:.2f}  (n {s['n']})")
    summary["cmm_share_median"] = np.round(np.median([r["cmm_share"] for r in rows], 0), 2).tolist()
    print("CMM share of each parameter's variance (median):", summary["cmm_share_median"])
    for tube in (True, False):
        sub = [r for r in rows if r["tube"] == tube]
        if not sub:
            continue
        key = "tube" if tube else "no_tube"
        summary[key] = {k: {"mean": np.round(np.mean([r[k] for r in sub], 0), 1).tolist(),
                            "sd": np.round(np.std([r[k] for r in sub], 0), 1).tolist()}
                        for k in ("k_ppm", "k_silhouette_ppm", "k_inner_ppm")}
        summary[key]["z"] = _summary(sub, "z")
        print(f"{key}: {len(sub)} recordings; detection scale k (cols, rows) [ppm] overall {summary[key]['k_ppm']}, "
              f"silhouette |s| >= 0.8 {summary[key]['k_silhouette_ppm']}, inner |s| < 0.7 {summary[key]['k_inner_ppm']}; "
              f"z mean {summary[key]['z']['mean']}, sd {summary[key]['z']['sd']}")
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
