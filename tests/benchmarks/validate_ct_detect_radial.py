"""Radial bias of detected sphere centres, with and without the support tube (issue 14, coarse detector).

Renders helix49 as bags/samples/ct_helix49_384px was made (its truth file: static geometry, the
three stage positions and motions, blur 0.7 px, 50000 quanta, the ellipse-centre bias rendered),
6 projections per position and ``--seeds`` noise/angle seeds, on a ``--pixels``^2 detector of the
same panel (384 px of 1.07 mm by default; 1024 px of 0.401 mm for the fine case), with the CFRP
tube and without it (``tube=None``), and compares every detected centre with the truth:

- radial component (outward from the detector centre) of ``centre_px`` minus the rendered
  silhouette ellipse centre, and of ``centre_corrected_px`` (Deng/Clackdoyle, nominal SDD, the
  detector centre as principal point) minus the projected sphere centre; mean +- standard error,
  a fit a + b rho, mean z;
- the same for the shadows flagged ``on_background_edge`` (edge crossing a tube wall band) and
  the others.

Usage: .venv/bin/python tests/benchmarks/validate_ct_detect_radial.py [--pixels 384] [--seeds 3]
Prints a table, then ONE JSON line.
"""

import argparse
import dataclasses
import json
import os
import sys

import numpy as np
import yaml

HERE = os.path.dirname(__file__)
sys.path.insert(0, os.path.join(HERE, "..", "..", "ros_ws", "src", "ct_calib_nodes"))

from ct_calib_nodes.core import detect as D  # noqa: E402
from ct_calib_nodes.core.geometry import DetectorSpec  # noqa: E402
from ct_calib_nodes.core.phantom import helix49  # noqa: E402
from ct_calib_nodes.core.render import RenderSettings, render_projection  # noqa: E402

TRUTH = os.path.join(HERE, "..", "..", "bags", "samples", "ct_helix49_384px.truth.yaml")
SDD = 1.04821


def run(npx, seeds, tube, settings=None, tube_oversample=1, counts=50000.0, first_seed=0):
    tr = yaml.safe_load(open(TRUTH))
    pitch = 0.00107 * 384 / npx
    det = DetectorSpec(npx, npx, pitch)
    w = np.array(tr["static_w"])
    ref = helix49() if tube else dataclasses.replace(helix49(), tube=None)
    rs = RenderSettings(blur_sigma_px=0.7, oversample=4, tube_oversample=tube_oversample, ellipse_centre_bias=True,
                        touch_gap_px=1.0, flat_field_counts=counts)
    pp = np.array([(npx - 1) / 2.0, (npx - 1) / 2.0])
    raw, cor, rho, zr, edge = [], [], [], [], []
    for seed in range(first_seed, first_seed + seeds):
        rng = np.random.default_rng(100 + seed)
        for k, srd in enumerate(tr["srd_reported_m"]):
            dr = D.shadow_diameter_range_px(ref.diameters_m, ref.centres_of_m, SDD, srd, pitch)
            for j in range(6):
                fr = render_projection(w, np.array(tr["motions"][k]), 2 * np.pi * j / 6 + 0.1 * seed, ref, det, rs,
                                       rng)
                d = D.detect_spheres(fr.image, flat_field_counts=counts, diameter_px_range=dr, sdd_px=SDD / pitch, settings=settings,
                                     principal_point_px=pp)
                t = fr.truth
                dd = np.linalg.norm(d.centre_px[:, None] - t.ellipse_centre_px[None], axis=2)
                jj = dd.argmin(axis=1)
                ok = dd[np.arange(len(jj)), jj] < 0.5
                rv = t.ellipse_centre_px[jj[ok]] - pp
                r = np.linalg.norm(rv, axis=1)
                ur = rv / r[:, None]
                e = np.sum((d.centre_px[ok] - t.ellipse_centre_px[jj[ok]]) * ur, axis=1)
                sr = np.sqrt(np.einsum("ni,nij,nj->n", ur, d.centre_cov_px2[ok], ur))
                raw.append(e)
                cor.append(np.sum((d.centre_corrected_px[ok] - t.centre_px[jj[ok]]) * ur, axis=1))
                rho.append(r)
                zr.append(e / sr)
                edge.append(d.on_background_edge[ok])
    raw, cor, rho, zr, edge = (np.concatenate(a) for a in (raw, cor, rho, zr, edge))

    def stats(sel):
        n = int(sel.sum())
        if n < 3:
            return {"n": n}
        a = np.column_stack([np.ones(n), rho[sel]])
        coef, *_ = np.linalg.lstsq(a, raw[sel], rcond=None)
        res = raw[sel] - a @ coef
        cov = np.linalg.inv(a.T @ a) * res.var()
        return {"n": n, "radial_mean_px": round(float(raw[sel].mean()), 5),
                "radial_se_px": round(float(raw[sel].std() / np.sqrt(n)), 5),
                "radial_mean_z": round(float(zr[sel].mean()), 3),
                "corrected_vs_projected_mean_px": round(float(cor[sel].mean()), 5),
                "corrected_vs_projected_se_px": round(float(cor[sel].std() / np.sqrt(n)), 5),
                "fit_b_per_px": float(f"{coef[1]:.3e}"), "fit_b_se": float(f"{np.sqrt(cov[1, 1]):.1e}")}

    return {"all": stats(np.ones(raw.size, bool)), "band_edge": stats(edge), "others": stats(~edge)}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--pixels", type=int, default=384)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--edge-spread-px", type=float, default=None,
                    help="DetectionSettings.edge_spread_px (default: estimated per frame; 0 = no blur correction)")
    ap.add_argument("--tube-oversample", type=int, default=1,
                    help="RenderSettings.tube_oversample (1: the tube point-sampled outside the sphere boxes, "
                         "pixel-averaged inside them; 4: pixel-averaged everywhere, as a detector integrates)")
    ap.add_argument("--first-seed", type=int, default=0, help="noise/angle seeds first_seed .. first_seed + seeds - 1")
    ap.add_argument("--counts", type=float, default=50000.0, help="open-beam counts per pixel")
    args = ap.parse_args()
    st = D.DetectionSettings(edge_spread_px=args.edge_spread_px)
    out = {"pixels": args.pixels, "seeds": args.seeds, "frames_per_case": 18 * args.seeds,
           "edge_spread_px": args.edge_spread_px,
           "tube_oversample": args.tube_oversample, "counts": args.counts, "first_seed": args.first_seed}
    for name, tube in (("tube", True), ("no_tube", False)):
        out[name] = run(args.pixels, args.seeds, tube, st, args.tube_oversample, args.counts, args.first_seed)
        for part, s in out[name].items():
            if s["n"] >= 3:
                print(f"{name:8s} {part:10s} n={s['n']:5d} radial {s['radial_mean_px']:+.5f} +- {s['radial_se_px']:.5f} px"
                      f" (z {s['radial_mean_z']:+.3f}); Deng-corrected vs projected {s['corrected_vs_projected_mean_px']:+.5f}"
                      f" +- {s['corrected_vs_projected_se_px']:.5f}; b {s['fit_b_per_px']:+.2e} +- {s['fit_b_se']:.1e}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
