"""Benchmark of sphere detection and identity (not collected by pytest).

Renders helix49 (49 spheres + CFRP tube, default noise) at the first stage
position on a 1024^2 (0.4 mm) and a 2048^2 (0.2 mm, same panel) detector, then
times, on the same frames in the same run:

- ``detect_spheres`` (this project's pipeline: background closing, components,
  ray edges, two-pass ellipse fit, rejection logic);
- the obvious alternative: threshold + connectedComponentsWithStats +
  findContours + cv2.fitEllipse (``baseline_detect(method="contour_ellipse")``);
- ``SphereIdentifier.assign`` per frame (after one ``initialise`` on 4 frames,
  whose time is reported separately);
- per stage of ``detect_spheres`` (flat field, background, candidates, local background,
  edges + fit, rejection, uncertainty): CPU ms per frame with OpenCV on one thread, as in a
  replay worker or the live node's process; 1000 / (CPU ms) is the rate one free core sustains;
- with ``--compare-ref REF``: the same for ``core/detect.py`` as committed at git REF (e.g. the
  main branch before a speed change), loaded side by side in this run so the machine's load
  affects both alike, with a check that both give the same centres and covariances.

Usage:  .venv/bin/python tests/benchmarks/bench_ct_detect.py [--repeat N] [--compare-ref main]
Prints a table, then ONE JSON line.
"""

import argparse
import importlib.util
import json
import os
import platform
import subprocess
import sys
import tempfile
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


DETECT_PATH = "ros_ws/src/ct_calib_nodes/ct_calib_nodes/core/detect.py"


def detect_at(ref):
    """core/detect.py as committed at git ``ref``, imported as a separate module."""
    root = os.path.join(os.path.dirname(__file__), "..", "..")
    src = subprocess.run(["git", "-C", root, "show", f"{ref}:{DETECT_PATH}"], check=True, capture_output=True,
                         text=True).stdout
    tmp = tempfile.NamedTemporaryFile("w", suffix=".py", delete=False)
    tmp.write(src)
    tmp.close()
    name = "ct_calib_nodes.core._detect_at_ref"
    spec = importlib.util.spec_from_file_location(name, tmp.name)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    os.unlink(tmp.name)
    return mod


def cpu_per_frame(fn, frames, repeat):
    """Least CPU seconds per frame over ``repeat`` rounds (the least disturbed by other processes)."""
    fn(frames[0])
    best = np.inf
    for _ in range(repeat):
        c = time.process_time()
        for f in frames:
            fn(f)
        best = min(best, (time.process_time() - c) / len(frames))
    return best


def cpu_pair(fa, fb, frames, repeat):
    """``cpu_per_frame`` of two functions, their rounds interleaved (a, b, a, b, ...) so that a
    change of the machine's load during the run affects both alike."""
    fa(frames[0])
    fb(frames[0])
    best = [np.inf, np.inf]
    for _ in range(repeat):
        for k, fn in enumerate((fa, fb)):
            c = time.process_time()
            for f in frames:
                fn(f)
            best[k] = min(best[k], (time.process_time() - c) / len(frames))
    return best


def stage_profile(images, kw, repeat):
    """CPU ms per frame of each detect_spheres stage (least over ``repeat`` rounds per stage)."""
    best = {}
    for _ in range(repeat):
        tot = {}
        for img in images:
            detect.detect_spheres(img, timing=tot, **kw)
        for k, v in tot.items():
            best[k] = min(best.get(k, np.inf), 1e3 * v / len(images))
    return best


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--compare-ref", default=None, help="git ref whose core/detect.py is timed side by side")
    args = ap.parse_args()
    old = detect_at(args.compare_ref) if args.compare_ref else None
    load0 = os.getloadavg()[0]
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
        kw = dict(flat_field_counts=I0, expected_shape=(n_px, n_px), diameter_px_range=dr)
        nthr = cv2.getNumThreads()
        cv2.setNumThreads(1)
        stages = stage_profile(images, kw, args.repeat)
        cmp_ = {}
        if old is None:
            cpu_new = cpu_per_frame(lambda i: detect.detect_spheres(i, **kw), images, args.repeat)
        else:
            cpu_new, cpu_old = cpu_pair(lambda i: detect.detect_spheres(i, **kw),
                                        lambda i: old.detect_spheres(i, **kw), images, args.repeat)
            same = True
            for i, d in zip(images, dets):
                o = old.detect_spheres(i, **kw)
                same &= (o.centre_px.shape == d.centre_px.shape and np.array_equal(o.centre_px, d.centre_px)
                         and np.allclose(o.centre_cov_px2, d.centre_cov_px2, rtol=1e-9, atol=0.0))
            cmp_ = {"ref": args.compare_ref, "ref_cpu_ms": 1e3 * cpu_old, "speedup": cpu_old / cpu_new,
                    "same_centres_and_covariances": bool(same)}
        cv2.setNumThreads(nthr)
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
            "cpu_ms_one_thread": 1e3 * cpu_new, "one_core_fps": 1.0 / cpu_new,
            "stage_cpu_ms": {k: round(v, 2) for k, v in stages.items()}, **({"compare": cmp_} if cmp_ else {}),
        }
        rows.append((key, 1.0 / t_ours, 1e3 * t_ours, 1.0 / t_base, 1e3 * t_base, 1e3 * t_assign, t_init, n_acc))
    print(f"{'frame':10s} {'detect fps':>10s} {'ms':>7s} {'baseline fps':>13s} {'ms':>7s} "
          f"{'assign ms':>10s} {'init s':>7s} {'accepted':>9s}")
    for r in rows:
        print(f"{r[0]:10s} {r[1]:10.1f} {r[2]:7.2f} {r[3]:13.1f} {r[4]:7.2f} {r[5]:10.2f} {r[6]:7.2f} {r[7]:9.1f}")
    for r in rows:
        o = out[r[0]]
        print(f"{r[0]} CPU ms per frame (one thread): {o['cpu_ms_one_thread']:.1f} = one free core "
              f"{o['one_core_fps']:.1f} frames/s; stages " + " ".join(f"{k} {v:.1f}" for k, v in o["stage_cpu_ms"].items()))
        if "compare" in o:
            c = o["compare"]
            print(f"  {c['ref']}: {c['ref_cpu_ms']:.1f} ms, speed-up {c['speedup']:.2f}, same results "
                  f"{c['same_centres_and_covariances']}")
    out["loadavg_1min_before_after"] = [load0, os.getloadavg()[0]]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
