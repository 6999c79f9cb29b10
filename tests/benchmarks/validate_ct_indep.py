"""Static CT calibration on recordings from an INDEPENDENT renderer (issue 14 items 1-3).

For >= 20 random instruments (detector offsets of a few mm, tilts up to 0.6 deg, SRD 0.3-0.7 m, SDD
1.0-1.3 m, any object pose about the axis, the object leaning up to --object-tilt-deg) and varied
physics (PSF core 0.3-1.1 px + exponential tail, 12k-50k counts, heel + fall-off of the open beam, read
noise, beam hardening, tube on/off, a support rod at any tilt, a PMMA plate, mono16 or 32FC1), rendered by
tests/ct_validation/ct_indep_gen.py (no project code), each recording goes through the user's command
``scripts/ros2run ct_calib_nodes ct_offline_solve REC`` and is compared with the truth by
tests/ct_validation/ct_indep_check.py. Two cases run at a time (a process pool on the 2 cores).

    .venv/bin/python tests/benchmarks/validate_ct_indep.py [--n 24] [--views 30] [--cols 384] [--seed0 7000]
                       [--object-tilt-deg 0.5] [--cases-out FILE.jsonl] [--keep DIR] [--summarise FILE.jsonl]
    # a solver change on the same frames: run once with --keep DIR --cases-out CASES.jsonl, then
    .venv/bin/python tests/benchmarks/validate_ct_indep.py --summarise CASES.jsonl --keep DIR --resolve

Prints one JSON line: per-parameter z-score mean and sd (instrument: all cases; object pose: cases where the
solver kept the file's labelling), the pixel-level discrepancy of the fitted geometry, detections (visible
found, false, misidentified, centre errors vs reported sigma, radial component), variance factors, CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")     # two cases at a time on 2 cores: one BLAS thread each
import numpy as np  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent / "ct_validation"), str(HERE.parent)]

import ct_indep_check as ck  # noqa: E402


def _one(args):
    seed, work, cols, views, tilt = args
    try:
        return ck.run_case(seed, work, cols=cols, n_views=views, object_tilt_deg=tilt)
    except Exception as exc:  # a crash of one case is a finding, not the end of the campaign
        return {"seed": seed, "outcome": "crashed", "message": f"{type(exc).__name__}: {exc}"[-2000:]}


def _track_summary(ok):
    """The static solve's correlation along sphere tracks (noise.py): lag-1 estimates, how often the
    covariance took it, and how much it widened the instrument uncertainties."""
    tr = [c["track"] for c in ok if "track" in c]
    if not tr:
        return None
    lag1 = np.array([[t["lag1_u"] if t["lag1_u"] is not None else np.nan,
                      t["lag1_v"] if t["lag1_v"] is not None else np.nan] for t in tr], float)
    infl = np.array([t["sd_inflation_instrument"] for t in tr], float)
    return {"n": len(tr), "lag1_u_median": round(float(np.nanmedian(lag1[:, 0])), 3),
            "lag1_u_range": [round(float(np.nanmin(lag1[:, 0])), 3), round(float(np.nanmax(lag1[:, 0])), 3)],
            "lag1_v_median": round(float(np.nanmedian(lag1[:, 1])), 3),
            "lag1_v_range": [round(float(np.nanmin(lag1[:, 1])), 3), round(float(np.nanmax(lag1[:, 1])), 3)],
            "used_u": int(sum(t["lags_used_u"] > 0 for t in tr)), "used_v": int(sum(t["lags_used_v"] > 0 for t in tr)),
            "sd_inflation_instrument_median": [round(float(v), 3) for v in np.median(infl, axis=0)],
            "sd_inflation_instrument_max": [round(float(v), 3) for v in infl.max(axis=0)]}


def summarise(cases):
    ok = [c for c in cases if c.get("outcome") == "success"]
    names = ck.gen.PARAM_NAMES
    z = np.array([[np.nan if v is None else v for v in c["z"]] for c in ok], float).reshape(-1, 13)
    zs = {}
    for i, n in enumerate(names):
        col = z[:, i][np.isfinite(z[:, i])]
        zs[n] = {"n": int(col.size), "mean": round(float(col.mean()), 3) if col.size else None,
                 "sd": round(float(col.std(ddof=1)), 3) if col.size > 1 else None,
                 "max_abs": round(float(np.abs(col).max()), 2) if col.size else None}
    det = {k: int(sum(c["detection"][k] for c in ok)) for k in
           ("frames", "visible", "found_visible", "close", "found_close", "accepted", "false", "misidentified")}
    by_gap = {}
    for c in ok:
        for k, (n, f) in c["detection"]["by_gap"].items():
            by_gap[k] = [by_gap.get(k, [0, 0])[0] + n, by_gap.get(k, [0, 0])[1] + f]
    reasons = {}
    for c in ok:
        for k, n in c["detection"]["missed_reasons"].items():
            reasons[k] = reasons.get(k, 0) + n
    radial = np.array([c["detection"]["radial_mean_px"] for c in ok if "radial_mean_px" in c["detection"]])

    def pooled_radial(sel):
        sel = [c for c in sel if "n_err" in c["detection"]]
        n = np.array([c["detection"]["n_err"] for c in sel], float)
        if not n.size:
            return None
        m = np.array([c["detection"]["radial_mean_px"] for c in sel])
        se = np.array([c["detection"]["radial_sem_px"] for c in sel])
        return [round(float(n @ m / n.sum()), 5), round(float(np.sqrt(n ** 2 @ se ** 2) / n.sum()), 5), int(n.sum())]
    eos = np.array([c["detection"]["err_over_sigma_rms"] for c in ok if "err_over_sigma_rms" in c["detection"]])
    px = [c["pixel"] for c in ok]
    return {
        "cases": len(cases), "success": len(ok),
        "failed": [{"seed": c["seed"], "outcome": c["outcome"], "message": c.get("message", "")[:300]}
                   for c in cases if c.get("outcome") != "success"],
        "z": zs,
        "chi2_instrument_mean": round(float(np.mean([c["chi2_instrument"] for c in ok])), 2) if ok else None,
        "labelling": {k: [c["seed"] for c in ok if c["labelling"] == k] for k in ("file", "upside_down", "wrong")},
        "label_shifts_of_wrong": [c["label_shift"] for c in ok if c["labelling"] == "wrong"],
        "pixel": {"max_px": round(max(p["max_px"] for p in px), 4), "rms_px_median": round(float(np.median([p["rms_px"] for p in px])), 4),
                  "sd_rms_px_median": round(float(np.median([p["sd_rms_px"] for p in px])), 4),
                  "rms_z_median": round(float(np.median([p["rms_z"] for p in px])), 2),
                  "rms_z_max": round(max(p["rms_z"] for p in px), 2),
                  "max_abs_z_max": round(max(p["max_abs_z"] for p in px), 2)} if px else None,
        "detection": dict(det, missed_visible_reasons=reasons, close_by_gap_found=by_gap,
                          clear_gap_px=ck.CLEAR_GAP_PX, found_visible_fraction=round(det["found_visible"] / max(det["visible"], 1), 4),
                          found_close_fraction=round(det["found_close"] / max(det["close"], 1), 4),
                          cases_with_missed_visible=int(sum(c["detection"]["found_visible"] < c["detection"]["visible"] for c in ok)),
                          err_over_sigma_rms_median=np.round(np.median(eos, axis=0), 2).tolist() if ok else None,
                          radial_mean_px_median=round(float(np.median(radial)), 4) if ok else None,
                          radial_pooled_px_tube=pooled_radial([c for c in ok if c["physics"]["tube"]]),
                          radial_pooled_px_no_tube=pooled_radial([c for c in ok if not c["physics"]["tube"]]),
                          radial_mean_px_range=[round(float(radial.min()), 4), round(float(radial.max()), 4)] if ok else None),
        "track_correlation": _track_summary(ok),
        "variance_factor": {"median": round(float(np.median([c["variance_factor"] for c in ok])), 2),
                            "range": [round(min(c["variance_factor"] for c in ok), 2),
                                      round(max(c["variance_factor"] for c in ok), 2)]} if ok else None,
        "cpu_generate_s_median": round(float(np.median([c["cpu_generate_s"] for c in cases if "cpu_generate_s" in c])), 1),
        "cpu_solve_s_median": round(float(np.median([c["cpu_solve_s"] for c in cases if "cpu_solve_s" in c])), 1),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=24)
    ap.add_argument("--views", type=int, default=30)
    ap.add_argument("--cols", type=int, default=384)
    ap.add_argument("--seed0", type=int, default=7000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--object-tilt-deg", type=float, default=0.5,
                    help="the object (body tube) leans off the rotation axis by up to this about X and Z")
    ap.add_argument("--cases-out", help="append every case's figures to this file as it finishes (JSON lines)")
    ap.add_argument("--summarise", metavar="CASES_JSONL", help="only summarise the cases of an earlier run")
    ap.add_argument("--keep", help="work in this directory and keep the recordings, truth and results "
                                   "(with --summarise: evaluate the results kept there again)")
    ap.add_argument("--resolve", action="store_true",
                    help="with --summarise and --keep: run the solver again on the kept recordings (the current "
                         "code; same frames, so a before/after comparison of a solver change) before evaluating")
    a = ap.parse_args()
    if a.summarise:
        cases = [json.loads(line) for line in open(a.summarise) if line.strip()]
        if a.keep:                               # evaluate the kept outputs again (the same solves)
            work = pathlib.Path(a.keep)
            for c in cases:
                out = work / "solved" / f"scan_{c['seed']}"
                if a.resolve and (work / "recordings" / f"scan_{c['seed']}").exists():
                    proc = ck.run_solver(work / "recordings" / f"scan_{c['seed']}", out)
                    if proc.returncode != 0:
                        c.update(outcome="no_result", message=f"exit {proc.returncode}: {proc.stderr[-500:]}")
                        continue
                if (out / "results.json").exists():
                    c.update(ck.evaluate(out, json.loads((work / "truth" / f"{c['seed']}.json").read_text())))
        print(json.dumps(dict(summarise(cases), n_views=a.views, cols=a.cols)))
        return
    load0, t0 = open("/proc/loadavg").read().split()[:3], time.monotonic()
    cases = []
    with tempfile.TemporaryDirectory(prefix="ct_indep_") as tmp:
        work = a.keep or tmp
        jobs = [(a.seed0 + i, work, a.cols, a.views, a.object_tilt_deg) for i in range(a.n)]
        with ProcessPoolExecutor(a.workers) as pool:
            for case in pool.map(_one, jobs):
                cases.append(case)
                if a.cases_out:
                    with open(a.cases_out, "a") as f:
                        f.write(json.dumps(case) + "\n")
    out = summarise(cases)
    out.update(n_views=a.views, cols=a.cols, seed0=a.seed0, object_tilt_deg=a.object_tilt_deg, wall_s=round(time.monotonic() - t0, 1),
               loadavg_start=load0, loadavg_end=open("/proc/loadavg").read().split()[:3])
    print(json.dumps(out))


if __name__ == "__main__":
    main()
