"""Can a better-posed criterion pick the true member of a degenerate group? (issue 11, proof-table gaps)

    OPENBLAS_NUM_THREADS=1 .venv/bin/python tests/benchmarks/study_ct_discrepancy_top1.py
        [--effects object_thermal_expansion,stage_drift,focal_spot_drift,rotary_radial_runout] [--seeds 12]

Feature-level recordings of validate_ct_discrepancy.py (--mode truth, seeds 1000..): for the engine's first
finding, every member of its reported degenerate group (and the true term) is compared by its first-step delta
BIC and by the held-out chi2 of the 6 time-block folds with that member alone; the paired t statistic over the
folds (5 dof; 2.57 = two-sided 5 %) says whether the top member's held-out gain is significantly larger than the
other's. Reported per effect: top-1, truth inside the reported group, and how often a CV criterion ("prefer the
member whose held-out gain is significantly larger, else report the group") would have named the true term
alone, or a wrong one alone. Progress on stderr; the last stdout line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "ct_discrepancy"))

import numpy as np  # noqa: E402

from campaign import DET, truth_campaign  # noqa: E402
from ct_calib_nodes.core import ct_discrepancy as cd, discrepancy as d  # noqa: E402
from ct_calib_nodes.core.static_solver import solve_static  # noqa: E402

T_CRIT = 2.571   # two-sided 5 %, 5 dof


def fold_chi2(ctx, extra):
    xw = np.hstack([ctx.x0] + extra) if extra else ctx.x0
    out = []
    for f in np.unique(ctx.ds.fold):
        te = ctx.ds.fold == f
        beta = d._fit(ctx.z[~te], xw[~te])
        out.append(float(np.sum((ctx.z[te] - xw[te] @ beta) ** 2)))
    return np.array(out)


def one(effect, seed):
    obs, tr = truth_campaign(seed, effect, 1.0, 72)
    st = solve_static(obs, tr["ref"].centres_of_m, DET, tr["srd"], tr["sdd"])
    ds, ext = cd.build_dataset(obs, st, DET)
    cands = cd.catalogue_candidates(obs, st, DET, ext["span_s"])
    res = d.analyse(ds, cands, max_terms=4)
    if not res["findings"]:
        return {"effect": effect, "seed": seed, "top": None}
    ctx, by = res["context"], {c.id: c for c in cands}
    f0 = res["findings"][0]
    group = [f0["term"], *f0["degenerate_with"]]
    members = group + ([tr["term"]] if tr["term"] not in group else [])
    fc = {g: fold_chi2(ctx, [ctx.wh(by[g].basis)]) for g in members}

    def t_better(a, b):          # > 0: a's held-out chi2 lower than b's
        diff = fc[b] - fc[a]
        sd = diff.std(ddof=1)
        return float(diff.mean() / (sd / np.sqrt(diff.size))) if sd > 0 else 0.0
    # CV criterion: a member is named alone when it beats every other member of the group significantly
    alone = [g for g in group if all(t_better(g, h) > T_CRIT for h in group if h != g)]
    return {"effect": effect, "seed": seed, "top": f0["term"], "true": tr["term"], "group": group,
            "bic": {g: res["limits"][g]["first_delta_bic"] for g in members},
            "t_true_vs_top": None if tr["term"] == f0["term"] else t_better(tr["term"], f0["term"]),
            "cv_alone": alone[0] if alone else None}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--effects", default="object_thermal_expansion,stage_drift,focal_spot_drift,rotary_radial_runout")
    ap.add_argument("--seeds", type=int, default=12)
    a = ap.parse_args()
    summary = {}
    for e in a.effects.split(","):
        rs = []
        for s in range(a.seeds):
            rs.append(one(e, 1000 + s))
            print(json.dumps(rs[-1]), file=sys.stderr, flush=True)
        found = [r for r in rs if r["top"]]
        summary[e] = {"n": len(rs), "found": len(found), "top1": sum(r["top"] == r["true"] for r in found),
                      "truth_in_group": sum(r["true"] in r["group"] for r in found),
                      "group_reported": sum(len(r["group"]) > 1 for r in found),
                      "cv_names_truth_alone": sum(r["cv_alone"] == r["true"] for r in found),
                      "cv_names_wrong_alone": sum(r["cv_alone"] not in (None, r["true"]) for r in found),
                      "t_true_vs_top_when_wrong": [round(r["t_true_vs_top"], 2) for r in found
                                                   if r["t_true_vs_top"] is not None]}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
