"""Where on the object do the detected sphere centres go wrong, and what does it do to the geometry?

Reads recordings kept by ``validate_ct_indep.py --keep DIR`` (recordings/, truth/, solved/: the offline
solve's results.json and results.mcap) and, for every accepted detection, its error against the true
ellipse centre in units of its stated sigma (the truth only scores, as in tests/ct_validation/
ct_indep_check.py). Then:

* the errors binned by the sphere's lateral position |s| relative to the object's axis (|s| = 1 at the
  object's side as seen from the source), in front of / behind the axis, with and without the body tube;
* the same detections solved in-process without and with the location classes (core/location_noise.py),
  and with perfect detections (the true ellipse centres) and the file's centres: the calibrated centres'
  (CMM) part of each instrument parameter's error alone, against the part of the stated sd it makes.

    .venv/bin/python tests/benchmarks/study_ct_location_bias.py --keep DIR [--seeds 7200-7221]

Prints the tables, then one JSON line of the z-score summaries (ct_detect.md, "Location classes").
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parent / "ct_validation")]

import ct_indep_check as ck  # noqa: E402
import ct_indep_gen as gen  # noqa: E402
from ct_calib_nodes.core.geometry import DetectorSpec  # noqa: E402
from ct_calib_nodes.core.observations import CentreObservations  # noqa: E402
from ct_calib_nodes.core.static_solver import solve_static  # noqa: E402

NAMES = ["z_R", "x_D", "y_D", "z_D", "theta", "phi", "eta"]


def case_detections(work, seed):
    """Per accepted detection of one kept case: observation fields, error vs truth, lateral position."""
    truth = json.loads((work / "truth" / f"{seed}.json").read_text())
    out = work / "solved" / f"scan_{seed}"
    st = json.loads((out / "results.json").read_text())["static"]
    if not st or st["outcome"] != "success":
        return None
    ids, c_file = gen.load_reference()[:2]
    id_index = {int(i): k for k, i in enumerate(ids)}
    w = np.array(truth["w"])
    inst = gen.instrument_from(w, truth)
    _, _, kind = ck.labelling(np.array(st["x"]), w, c_file)
    legit = np.arange(len(ids))[::-1] if kind == "upside_down" else np.arange(len(ids))
    c_true = np.array(truth["centres_true_of_m"])
    alphas = np.array([v["alpha"] for v in truth["views"]])
    rows = []
    for jv, (alpha, obs) in enumerate(ck.read_detections(out / "results.mcap")):
        j = int(np.argmin(np.abs(ck._wrap(alphas - alpha))))
        cr = np.array(truth["views"][j]["centre_px"])
        m, t = inst.object_to_srf(truth["views"][j]["alpha"])
        c_srf = c_true @ m.T + t
        ad = m @ np.array([0.0, 1.0, 0.0])
        d = c_srf - t - np.outer((c_srf - t) @ ad, ad)
        for sid, flag, col, row, s, b, _ in obs:
            if flag != 0 or sid not in id_index:
                continue
            k = id_index[sid]
            kk = legit[k]
            e_true = inst.ellipse_centre_px(cr[kk], b)
            rows.append((col, row, k, alpha, jv, s, b, *e_true, d[kk, 0] / np.linalg.norm(d[kk]), np.sign(d[kk, 2])))
    a = np.array(rows, float)
    phys = truth["physics"]
    tube = ("'tube': True" in phys) if isinstance(phys, str) else bool(phys["tube"])
    return dict(seed=seed, truth=truth, w=w, c_file=c_file, c_true=c_true, tube=tube, kind=kind, a=a)


def solve(case, uv, **kw):
    a, t = case["a"], case["truth"]
    obs = CentreObservations(uv, a[:, 2].astype(int), a[:, 3], a[:, 4].astype(int), sigma_px=a[:, 5],
                             minor_axis_px=a[:, 6])
    det = DetectorSpec(int(t["cols"]), int(t["rows"]), float(t["pitch_m"]))
    return solve_static(obs, case["c_file"], det, float(t["srd_reported_m"]), float(t["sdd_reported_m"]),
                        centre_uncertainty_m=gen.load_reference()[3], **kw)


def binned(cases):
    print("column / row error over the stated sigma, by lateral position |s| (outward: away from the axis)")
    for tube in (True, False):
        a = np.vstack([c["a"] for c in cases if c["tube"] == tube] or [np.zeros((0, 11))])
        if not len(a):
            continue
        e = a[:, 0:2] - a[:, 7:9]
        zc, zr = e[:, 0] / a[:, 5], e[:, 1] / a[:, 5]
        s, side = a[:, 9], a[:, 10]
        print("with the tube" if tube else "without the tube", len(a))
        for lo, hi in zip([0, 0.3, 0.6, 0.8, 0.9, 0.95], [0.3, 0.6, 0.8, 0.9, 0.95, 1.0]):
            for sd_, name in ((-1, "front"), (1, "back")):
                q = (np.abs(s) >= lo) & (np.abs(s) < hi) & (side == sd_)
                if q.sum() < 20:
                    continue
                out = zc[q] * np.sign(s[q])
                print(f"  |s| {lo:.2f}-{hi:.2f} {name:5s} n {q.sum():5d}  column z outward {out.mean():+.2f} "
                      f"+- {out.std() / np.sqrt(q.sum()):.2f}, sd {zc[q].std():.2f};  row z {zr[q].mean():+.2f}, "
                      f"sd {zr[q].std():.2f}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", required=True, help="validate_ct_indep.py --keep directory")
    ap.add_argument("--seeds", default="7200-7221", help="first-last")
    a = ap.parse_args()
    lo, hi = (int(v) for v in a.seeds.split("-"))
    work = pathlib.Path(a.keep)
    cases = [c for c in (case_detections(work, s) for s in range(lo, hi + 1)) if c is not None]
    binned(cases)
    z = {"before": [], "after": [], "cmm_only": []}
    for c in cases:
        uv = c["a"][:, 0:2]
        r0, r1 = solve(c, uv, location_classes=False), solve(c, uv)
        rp = solve(c, c["a"][:, 7:9], location_classes=False)          # perfect detections, file centres
        g = rp.centre_sensitivity
        cmm_sd = np.sqrt(((g * np.repeat(gen.load_reference()[3], 3)) ** 2).sum(1))
        z["before"].append(((r0.x - c["w"]) / r0.std)[:7])
        z["after"].append(((r1.x - c["w"]) / r1.std)[:7])
        z["cmm_only"].append(((rp.x - c["w"]) / cmm_sd)[:7])
    summary = {"cases": len(cases), "tube_cases": sum(c["tube"] for c in cases)}
    for k, v in z.items():
        v = np.array(v)
        summary[k] = {"mean": dict(zip(NAMES, np.round(v.mean(0), 2).tolist())),
                      "sd": dict(zip(NAMES, np.round(v.std(0, ddof=1), 2).tolist())),
                      "sum_z2_mean": round(float((v ** 2).sum(1).mean()), 2) if k != "cmm_only" else None}
        print(k, summary[k])
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
