"""Benchmark: what the location classes (core/location_noise.py) cost the static solve.

The classes add, to every static solve with sigma given, one classification of the observations and a
chi-square test per class; when a class fires, one more LM solve under the new weights. This times
``solve_static`` with ``location_classes=True`` against ``False`` (the obvious alternative: one noise
factor per image axis for everything) on the same observations, in two cases:

* clean: 0.05 px noise everywhere (the classes should not fire: only the test's cost);
* silhouette: 3 x that noise on the spheres whose shadows lie in the object's silhouette band
  (|s| >= 0.8, classified with the true geometry), as the body tube does on independent frames
  (the classes fire: test + refit).

Per case: median wall time of each variant, the extra time, how often the classes fired, and the
spread of the detector tilt phi over the noise draws (what the refit buys). Ends with ONE JSON line.

Run:  cd /work/main && .venv/bin/python tests/benchmarks/bench_location_classes.py [--views 72] [--draws 7]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")   # one BLAS thread for both variants

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "ros_ws", "src", "ct_calib_nodes"))
sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "ct_core"))

from ct_calib_nodes.core.geometry import DetectorSpec  # noqa: E402
from ct_calib_nodes.core.location_noise import N_BINS, location_class  # noqa: E402
from ct_calib_nodes.core.observations import CentreObservations  # noqa: E402
from ct_calib_nodes.core.phantom import helix49  # noqa: E402
from ct_calib_nodes.core.scenario import default_campaign  # noqa: E402
from ct_calib_nodes.core.simulate_obs import simulate_observations  # noqa: E402
from ct_calib_nodes.core.static_solver import solve_static  # noqa: E402

from ct_core_settings import CONTOUR_RADIUS_M, SIGMA_PX  # noqa: E402  (the CT core tests' simulated detector)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--views", type=int, default=72, help="projections per turn")
    ap.add_argument("--draws", type=int, default=7, help="noise draws per case (median time over them)")
    ap.add_argument("--seed", type=int, default=2024)
    args = ap.parse_args()

    detector = DetectorSpec(cols=1024, rows=1024, pixel_pitch_m=0.0004)
    centres = helix49().centres_of_m
    camp = default_campaign()
    alphas = np.linspace(0.0, 2 * np.pi, args.views, endpoint=False)
    rng = np.random.default_rng(args.seed)
    clean = simulate_observations(camp.static_w, centres, detector, alphas, rng, 0.0,
                                  contour_radius_m=CONTOUR_RADIUS_M).obs
    silhouette = (location_class(camp.static_w, centres, clean.sphere_index, clean.alpha_rad) % N_BINS) >= 8
    out = {"benchmark": "location_classes", "views": args.views, "observations": int(clean.n_obs),
           "draws": args.draws, "silhouette_share": round(float(silhouette.mean()), 3)}
    for case, k in (("clean", 1.0), ("silhouette", 3.0)):
        sd = np.where(silhouette, k * SIGMA_PX, SIGMA_PX)
        times = {True: [], False: []}
        phi_err = {True: [], False: []}
        fired = 0
        for _ in range(args.draws):
            uv = clean.uv_px + rng.normal(0.0, 1.0, clean.uv_px.shape) * sd[:, None]
            obs = CentreObservations(uv, clean.sphere_index, clean.alpha_rad, clean.view_index, clean.stamp_ns,
                                     np.full(clean.n_obs, SIGMA_PX), clean.minor_axis_px)
            for on in (False, True):
                t0 = time.perf_counter()
                st = solve_static(obs, centres, detector, camp.srd_reported_m[0], camp.sdd_reported_m,
                                  location_classes=on)
                times[on].append(time.perf_counter() - t0)
                if not st.success:
                    raise SystemExit(f"{case}: solve failed ({st.message})")
                phi_err[on].append(st.x[5] - camp.static_w[5])
                if on and any(f != 1.0 for f in st.noise.location_factor):
                    fired += 1
        t_off, t_on = float(np.median(times[False])), float(np.median(times[True]))
        row = {"without_s": round(t_off, 4), "with_s": round(t_on, 4), "extra_s": round(t_on - t_off, 4),
               "extra_pct": round(100.0 * (t_on / t_off - 1.0), 1), "fired": f"{fired}/{args.draws}",
               "phi_rms_err_urad_without": round(1e6 * float(np.sqrt(np.mean(np.square(phi_err[False])))), 2),
               "phi_rms_err_urad_with": round(1e6 * float(np.sqrt(np.mean(np.square(phi_err[True])))), 2)}
        print(f"{case:10s} {clean.n_obs} obs: without {t_off * 1e3:7.1f} ms, with {t_on * 1e3:7.1f} ms "
              f"(+{row['extra_pct']} %), classes fired {row['fired']}, phi rms error "
              f"{row['phi_rms_err_urad_without']} -> {row['phi_rms_err_urad_with']} urad", flush=True)
        out[case] = row
    print(json.dumps(out))


if __name__ == "__main__":
    main()
