"""Moment axis ratio of single round sphere shadows vs diameter, blur and sub-pixel phase (not collected).

Why the detector refused isolated small shadows as "merged" on the independent renderer's frames
(ct_detect.md, "Small shadows"). One 3 mm steel sphere's shadow, D px across, at a random sub-pixel
phase, integrated on 8 x 8 samples per pixel, in the physics of

- ``project``: core/render.py (one attenuation ``MU_STEEL_100KEV_PER_M``, Gaussian blur), and
- ``indep``: tests/ct_validation/ct_indep_gen.py (its three-energy beam, its PSF: Gaussian core and an
  exponential tail of 4 % at 6 px),

with relative noise 0 / 1 % / 3 % of the open beam; thresholded at the detector's ``segment_depth`` (the
component under the centre), then the binary moment axis ratio (the former merged-shadow screen) and
the depth-weighted one (``core/detect._merged_by_moments``). Also two equal shadows whose gap is
-2..2 px (their blobs joined), to show the margin to merged pairs.

Usage: .venv/bin/python tests/benchmarks/measure_ct_small_blob_moments.py [--phases N]
Prints a table, then ONE JSON line.
"""

import argparse
import json
import os
import sys

import cv2
import numpy as np

HERE = os.path.dirname(__file__)
sys.path.insert(0, os.path.join(HERE, "..", "..", "ros_ws", "src", "ct_calib_nodes"))
sys.path.insert(0, os.path.join(HERE, "..", "ct_validation"))

from ct_calib_nodes.core import detect  # noqa: E402
from ct_calib_nodes.core.render import MU_STEEL_100KEV_PER_M  # noqa: E402
import ct_indep_gen as gen  # noqa: E402

RADIUS_M = 1.5e-3
N_FINE = 8


def shadow(discs, model, blur, noise, rng, size=40):
    """Transmission image of spheres (col, row, diameter px) in one model's physics."""
    f = (np.arange(size * N_FINE) + 0.5) / N_FINE
    x, y = np.meshgrid(f, f)
    chord = np.zeros_like(x)                                      # [m]
    for cx, cy, d in discs:
        r2 = ((x - cx) ** 2 + (y - cy) ** 2) / (0.5 * d) ** 2
        chord += 2 * RADIUS_M * np.sqrt(np.clip(1 - r2, 0, None))
    if model == "project":
        t = np.exp(-MU_STEEL_100KEV_PER_M * chord)
    else:
        t = np.exp(-np.multiply.outer(chord, gen.MU_STEEL)) @ gen.BEAM_WEIGHTS
    t = t.reshape(size, N_FINE, size, N_FINE).mean(axis=(1, 3))
    if model == "project":
        t = cv2.GaussianBlur(t, (0, 0), blur, borderType=cv2.BORDER_REPLICATE)
    else:
        k = gen._psf_kernel(gen.Physics(psf_sigma_px=blur))
        t = cv2.filter2D(t, -1, k, borderType=cv2.BORDER_REPLICATE)
    return t + rng.normal(0, noise, t.shape)


def ratios(t):
    """Binary and depth-weighted moment axis ratio of the thresholded component under the centre,
    and its equivalent diameter."""
    mask = (t < 1 - detect.DetectionSettings().segment_depth).astype(np.uint8)
    n, lab = cv2.connectedComponents(mask)
    big = np.bincount(lab.ravel())[1:].argmax() + 1
    blob = lab == big
    rb = detect._moment_axis_ratio(cv2.moments(blob.view(np.uint8), binaryImage=True))
    rg = detect._moment_axis_ratio(cv2.moments(np.where(blob, np.maximum(1 - t, 0), 0).astype(np.float32)))
    return rb, rg, 2 * np.sqrt(blob.sum() / np.pi)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--phases", type=int, default=200)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    rng = np.random.default_rng(a.seed)
    lim = detect.DetectionSettings().max_axis_ratio
    out = {"single": [], "pairs": []}
    print(f"{'model':8s} {'D':>4s} {'blur':>4s} {'noise':>5s} {'bin p50':>7s} {'bin max':>7s} {'>lim':>6s} "
          f"{'(max-1)D^1.5':>12s} {'depth max':>9s} {'kept now':>8s}")
    for model in ("project", "indep"):
        for noise in (0.0, 0.01, 0.03):
            for d in (6.0, 7.0, 8.0, 10.0, 12.0, 16.0):
                for blur in (0.3, 0.55, 0.8, 1.1):
                    r = np.array([ratios(shadow([(20 + rng.uniform(-.5, .5), 20 + rng.uniform(-.5, .5), d)],
                                                model, blur, noise, rng)) for _ in range(a.phases)])
                    de = r[:, 2]
                    refused = (r[:, 0] > lim) & ((r[:, 0] > 1 + detect._PIXELATION_AXIS_COEF * de ** -1.5)
                                                 | (r[:, 1] > lim))
                    row = dict(model=model, d=d, blur=blur, noise=noise,
                               bin_p50=round(float(np.median(r[:, 0])), 3), bin_max=round(float(r[:, 0].max()), 3),
                               frac_over=round(float(np.mean(r[:, 0] > lim)), 3),
                               coef=round(float(np.max((r[:, 0] - 1) * de ** 1.5)), 2),
                               depth_max=round(float(r[:, 1].max()), 3),
                               frac_refused_now=round(float(refused.mean()), 3))
                    out["single"].append(row)
                    print(f"{model:8s} {d:4.0f} {blur:4.2f} {noise:5.2f} {row['bin_p50']:7.3f} {row['bin_max']:7.3f} "
                          f"{row['frac_over']:6.3f} {row['coef']:12.2f} {row['depth_max']:9.3f} "
                          f"{1 - row['frac_refused_now']:8.3f}")
    print(f"{'pairs':8s} {'D':>4s} {'gap':>4s} {'blur':>4s} {'bin min':>7s} {'depth min':>9s} {'refused':>7s}")
    for d in (6.0, 7.0, 8.0, 10.0):
        for gap in (-2.0, -1.0, 0.0, 1.0, 2.0):
            for blur in (0.3, 1.1):
                rs = []
                for _ in range(max(10, a.phases // 10)):
                    th, c0 = rng.uniform(0, np.pi), 20 + rng.uniform(-.5, .5, 2) - 0.5 * (d + gap)
                    c1 = c0 + (d + gap) * np.array([np.cos(th), np.sin(th)])
                    rs.append(ratios(shadow([(*c0, d), (*c1, d)], "indep", blur, 0.01, rng)))
                rs = np.array(rs)
                joined = rs[:, 2] > 1.3 * d           # one blob (else the pair is two blobs: not this screen's)
                if not joined.any():
                    continue
                rj = rs[joined]
                refused = (rj[:, 0] > lim) & ((rj[:, 0] > 1 + detect._PIXELATION_AXIS_COEF * rj[:, 2] ** -1.5)
                                              | (rj[:, 1] > lim))
                row = dict(d=d, gap=gap, blur=blur, joined=int(joined.sum()), bin_min=round(float(rj[:, 0].min()), 3),
                           depth_min=round(float(rj[:, 1].min()), 3), frac_refused=round(float(refused.mean()), 3))
                out["pairs"].append(row)
                print(f"{'indep':8s} {d:4.0f} {gap:4.0f} {blur:4.2f} {row['bin_min']:7.3f} {row['depth_min']:9.3f} "
                      f"{row['frac_refused']:7.3f}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
