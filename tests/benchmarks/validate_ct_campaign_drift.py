"""Validation of the campaign-long analysis (ct_discrepancy.campaign_drift) at feature level (issue 11).

    OPENBLAS_NUM_THREADS=1 .venv/bin/python tests/benchmarks/validate_ct_campaign_drift.py [--clean 40]
        [--seeds 12] [--drifts 300,600] [--positions 4] [--views 48]

Each campaign (tests/ct_discrepancy/campaign.truth_multi_campaign): one random misaligned instrument, the stage
stepped 40 mm towards the detector between ``--positions`` positions with a few um / arcsec of true error motions,
one turn of ``--views`` projections per position, ``--gap`` s between scans (default 600), centre noise 0.005-0.03
px (half with a per-projection shared shift, stated sigma off by 0.6-1.6x). Hidden: the focal spot drifting
linearly over the WHOLE campaign by ``--drifts`` um across the beam (random direction). run_positions judges every
position and the campaign (``--rendered``: 1024^2 frames with random blur, counts and support tube through
detection + identity, campaign.render_multi_campaign); reported: false alarms on clean campaigns, detection of the
drift, whether every miss came with a detection limit above the truth, estimated / true, and the z-scores of the
estimated drift vector (est - true) / u. Progress on stderr; the last stdout line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "ct_discrepancy"))

import numpy as np  # noqa: E402

from campaign import DET, render_multi_campaign, truth_multi_campaign  # noqa: E402
from ct_calib_nodes.core import ct_discrepancy as cd  # noqa: E402


def one(seed, drift_um, n_positions, views, gap_s=600.0, rendered=False):
    make = render_multi_campaign if rendered else truth_multi_campaign
    pos, tr = make(seed, n_positions=n_positions, n_views=views, focal_drift_um=drift_um, gap_s=gap_s)
    t0 = time.process_time()
    out = cd.run_positions(pos, tr["ref"].centres_of_m, DET, tr["sdd"])
    cpu = time.process_time() - t0
    c = out["campaign"]
    f = {x["term"]: x for x in c["findings"]}
    lat = f.get("focal_spot_drift")
    true_vec = tr["focal_rate_m_per_s"][:2] * (c["span_s"] if c["performed"] else 0.0) * 1e6
    rec = {"seed": seed, "drift_um": drift_um, "physics": tr["physics"], "n_positions_found": len(pos),
           "per_scan_um": tr["per_scan_um"], "sigma_px": tr["physics"].get("sigma_px"),
           "named": [x["term"] for x in c["findings"]], "unexplained": [u["axis"] for u in c["unexplained"]],
           "positions_inadequate": out["inadequate_positions"],
           "limit_um": c["detection_limits"].get("focal_spot_drift", {}).get("limit"),
           "true_between_first_last_um": float(np.linalg.norm(true_vec)), "cpu_s": cpu}
    if lat is not None:
        est = np.array([p["value"] for p in lat["parameters"]]) * 1e6
        u = np.array([p["u"] for p in lat["parameters"]]) * 1e6
        rec.update(est_um=float(lat["magnitude"]),
                   ratio=float(lat["magnitude"] / max(rec["true_between_first_last_um"], 1e-9)),
                   z=((est - true_vec) / u).tolist())
    return rec


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--clean", type=int, default=40)
    ap.add_argument("--seeds", type=int, default=12)
    ap.add_argument("--drifts", default="300,600")
    ap.add_argument("--positions", type=int, default=4)
    ap.add_argument("--views", type=int, default=48)
    ap.add_argument("--gap", type=float, default=600.0, help="seconds between the positions' scans")
    ap.add_argument("--start", type=int, default=7000)
    ap.add_argument("--rendered", action="store_true", help="render 1024^2 frames and detect (render_multi_campaign)")
    a = ap.parse_args()
    recs = []
    for i in range(a.clean):
        recs.append(one(a.start + i, 0.0, a.positions, a.views, a.gap, a.rendered))
        print(json.dumps(recs[-1]), file=sys.stderr, flush=True)
    for d in [float(x) for x in a.drifts.split(",") if x]:
        for i in range(a.seeds):
            recs.append(one(a.start + 1000 + i, d, a.positions, a.views, a.gap, a.rendered))
            print(json.dumps(recs[-1]), file=sys.stderr, flush=True)
    clean = [r for r in recs if r["drift_um"] == 0]
    summary = {"rendered": a.rendered, "positions": a.positions, "views": a.views, "gap_s": a.gap, "clean": len(clean),
               "clean_false_alarms": sum(bool(r["named"] or r["unexplained"]) for r in clean),
               "clean_per_position_false_alarms": sum(len(r["positions_inadequate"]) for r in clean),
               "clean_limit_um_median": float(np.median([r["limit_um"] for r in clean])) if clean else None,
               "cpu_s_median": float(np.median([r["cpu_s"] for r in recs]))}
    for d in sorted({r["drift_um"] for r in recs} - {0.0}):
        rs = [r for r in recs if r["drift_um"] == d]
        hit = [r for r in rs if "focal_spot_drift" in r["named"]]
        miss = [r for r in rs if "focal_spot_drift" not in r["named"]]
        z = np.concatenate([r["z"] for r in hit]) if hit else np.zeros(0)
        summary[f"drift_{d:g}um"] = {
            "n": len(rs), "named": len(hit),
            "wrong_names": sum(bool(set(r["named"]) - {"focal_spot_drift"}) for r in rs),
            "misses_with_limit_above_truth": sum(r["limit_um"] > r["true_between_first_last_um"] for r in miss),
            "per_scan_um": float(np.median([r["per_scan_um"] for r in rs])),
            "per_position_named": sum(bool(r["positions_inadequate"]) for r in rs),
            "ratio_median": float(np.median([r["ratio"] for r in hit])) if hit else None,
            "ratio_range": [float(min(r["ratio"] for r in hit)), float(max(r["ratio"] for r in hit))] if hit else None,
            "z_sd": float(np.std(z)) if z.size else None, "z_mean": float(np.mean(z)) if z.size else None,
            "limit_um_median": float(np.median([r["limit_um"] for r in rs]))}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
