"""Benchmark of the CT projection renderer (not collected by pytest).

Renders helix49 (49 spheres + CFRP tube) at the seed paper's first stage
position with the default RenderSettings (oversample 4, blur, counting noise,
mono16) on 1024^2 (0.4 mm) and 2048^2 (0.2 mm, same panel) detectors, and
compares with the obvious alternative: tracing every sub-sample of every pixel
through every sphere (render_projection_bruteforce, same physics). The
brute-force time at 2048^2 is measured on a band of rows and scaled by the
number of rays (its cost is exactly proportional to them); that is marked
"extrapolated" in the output.

Usage:  .venv/bin/python tests/benchmarks/bench_ct_render.py [--frames N]
Prints a table, then ONE JSON line.
"""

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "ros_ws", "src", "ct_calib_nodes"))

from ct_calib_nodes.core.geometry import DetectorSpec  # noqa: E402
from ct_calib_nodes.core.phantom import helix49  # noqa: E402
from ct_calib_nodes.core.render import (  # noqa: E402
    RenderSettings,
    render_projection,
    render_projection_bruteforce,
)
from ct_calib_nodes.core.scenario import default_campaign  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=10)
    args = ap.parse_args()
    camp = default_campaign()
    w = camp.static_w
    ref = helix49()
    settings = RenderSettings()
    rng = np.random.default_rng(7)
    out = {"threads_hint": os.environ.get("OMP_NUM_THREADS", "unset"), "cpu_count": os.cpu_count(),
           "frames": args.frames, "settings": "default (oversample 4, blur 0.7 px, noise, mono16, tube on)"}
    rows = []
    for n, pitch in ((1024, 0.0004), (2048, 0.0002)):
        det = DetectorSpec(n, n, pitch)
        render_projection(w, np.zeros(6), 0.0, ref, det, settings, rng)       # warm-up
        alphas = np.arange(args.frames) * 2 * np.pi / args.frames
        t0 = time.perf_counter()
        for a in alphas:
            fr = render_projection(w, np.zeros(6), a, ref, det, settings, rng)
        dt = (time.perf_counter() - t0) / args.frames
        # agreement with brute force on a noise-free frame (same settings, no noise;
        # tube at the same oversample everywhere so the two are comparable)
        clean = RenderSettings(poisson=False, tube_oversample=settings.oversample)
        band = 64 if n == 2048 else n
        t1 = time.perf_counter()
        if band == n:
            slow = render_projection_bruteforce(w, np.zeros(6), 0.5, ref, det, clean, output="transmission")
            t_slow = time.perf_counter() - t1
            fast = render_projection(w, np.zeros(6), 0.5, ref, det, clean, output="transmission")
            maxdiff = float(np.abs(fast.image - slow.image).max())
            extrap = False
        else:
            band_det = DetectorSpec(n, band, pitch)   # n columns x band rows (full-width band)
            render_projection_bruteforce(w, np.zeros(6), 0.5, ref, band_det, clean, output="transmission")
            t_slow = (time.perf_counter() - t1) * n / band
            maxdiff = None
            extrap = True
        rows.append((n, dt, 1 / dt, fr.n_rays, t_slow, t_slow / dt, maxdiff, extrap))
        out[f"{n}"] = {"fast_s_per_frame": dt, "fast_fps": 1 / dt, "fast_rays": fr.n_rays,
                       "bruteforce_s_per_frame": t_slow, "bruteforce_extrapolated": extrap,
                       "speedup": t_slow / dt, "max_abs_diff_transmission": maxdiff}
    print(f"{'detector':>10} {'s/frame':>9} {'frames/s':>9} {'rays':>10} {'brute s':>9} {'speedup':>8} {'max|dT|':>9}")
    for n, dt, fps, nr, ts, sp, md, ex in rows:
        mds = "n/a" if md is None else f"{md:.1e}"
        print(f"{n:>5}^2    {dt:9.3f} {fps:9.2f} {nr:10d} {ts:9.1f}{'*' if ex else ' '} {sp:8.0f} {mds:>9}")
    print("* extrapolated from a 64-row band")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
