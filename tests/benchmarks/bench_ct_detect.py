"""Benchmark of sphere detection and identity (not collected by pytest).

Renders helix49 (49 spheres + CFRP tube, default noise) at the first stage
position on a 1024^2 (0.4 mm) and a 2048^2 (0.2 mm, same panel) detector, then
times, on the same frames in the same run:

- ``detect_spheres`` (this project's pipeline: background closing, components,
  ray edges, two-pass ellipse fit, rejection logic);
- the obvious alternative: threshold + connectedComponentsWithStats +
  findContours + cv2.fitEllipse (``baseline_detect(method="contour_ellipse")``);
- ``SphereIdentifier.assign`` per frame (after one ``initialise`` on 4 frames,
  whose time is reported separately).

Usage:  .venv/bin/python tests/benchmarks/bench_ct_detect.py [--repeat N]
Prints a table, then ONE JSON line.
"""

import argparse
import json
import os
import platform
import sys
import time

import cv2
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "ros_ws", "src", "ct_calib_nodes"))

from ct_calib_nodes.core import detect, identify  # noqa: E402
from ct_calib_nodes.core.geometry import DetectorSpec  # noqa: E402
from ct_calib_nodes.core.phantom import helix49  # noqa: E402
from ct_calib_nodes.core.render import RenderSettings, render_projection  # noqa: E402
from ct_calib_nodes.core.scenario import default_static_truth  # noqa: E402

SDD = 1.04821
SRD = 0.364
I0 = 50000.0


def timeit(fn, frames, repeat):
    fn(frames[0])                                   # warm-up
    t = time.perf_counter()
    n = 0
    for _ in range(repeat):
        for f in frames:
            fn(f)
            n += 1
    return (time.perf_counter() - t) / n


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--frames", type=int, default=6)
    args = ap.parse_args()
    ref = helix49()
    w = default_static_truth(SRD)
    rng = np.random.default_rng(0)
    out = {"cpu_count": os.cpu_count(), "cv2_threads": cv2.getNumThreads(), "python": platform.python_version(),
           "opencv": cv2.__version__}
    rows = []
    for n_px, pitch in ((1024, 0.0004), (2048, 0.0002)):
        det = DetectorSpec(n_px, n_px, pitch)
        alphas = np.linspace(0, 2 * np.pi, args.frames, endpoint=False)
        frames = [render_projection(w, np.zeros(6), a, ref, det, RenderSettings(), rng) for a in alphas]
        images = [f.image for f in frames]
        dr = (3e-3 * SDD / (SRD + 0.04) / pitch, 3e-3 * SDD / (SRD - 0.04) / pitch)

        def ours(img):
            return detect.detect_spheres(img, flat_field_counts=I0, expected_shape=(n_px, n_px),
                                         diameter_px_range=dr)

        def base(img):
            return detect.baseline_detect(img, method="contour_ellipse", flat_field_counts=I0)

        t_ours = timeit(ours, images, args.repeat)
        t_base = timeit(base, images, args.repeat)
        dets = [ours(i) for i in images]
        n_acc = float(np.mean([len(d) for d in dets]))
        idf = identify.SphereIdentifier(ref.ids, ref.centres_of_m, ref.diameters_m, det, SDD)
        sel = np.arange(0, args.frames, max(1, args.frames // 4))[:4]
        t0 = time.perf_counter()
        res = idf.initialise([dets[i].centre_px for i in sel], alphas[sel], SRD)
        t_init = time.perf_counter() - t0
        pairs = list(zip([d.centre_px for d in dets], alphas))
        t_assign = timeit(lambda p: idf.assign(p[0], p[1]), pairs, args.repeat)
        key = f"{n_px}x{n_px}"
        out[key] = {
            "detect_fps": 1.0 / t_ours, "detect_ms": 1e3 * t_ours,
            "baseline_threshold_cc_fitEllipse_fps": 1.0 / t_base, "baseline_ms": 1e3 * t_base,
            "identity_assign_ms": 1e3 * t_assign, "identity_initialise_s": t_init,
            "identity_initialise_ok": bool(res.success), "spheres_accepted_per_frame": n_acc,
        }
        rows.append((key, 1.0 / t_ours, 1e3 * t_ours, 1.0 / t_base, 1e3 * t_base, 1e3 * t_assign, t_init, n_acc))
    print(f"{'frame':10s} {'detect fps':>10s} {'ms':>7s} {'baseline fps':>13s} {'ms':>7s} "
          f"{'assign ms':>10s} {'init s':>7s} {'accepted':>9s}")
    for r in rows:
        print(f"{r[0]:10s} {r[1]:10.1f} {r[2]:7.2f} {r[3]:13.1f} {r[4]:7.2f} {r[5]:10.2f} {r[6]:7.2f} {r[7]:9.1f}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
