"""Which physics pushes the body tube's silhouette spheres outward? (issue 14, study; not a test)

Re-renders independent recordings (tests/ct_validation/ct_indep_gen.py, same seeds: same instrument,
object, CMM draw and noise stream) with one of its physics switched, solves each with ct_offline_solve
(as validate_ct_indep.py does) and prints, next to the recording as drawn (kept by
``validate_ct_indep.py --keep``), the detection errors' scale about the image centre per image axis
(study_ct_coverage_decomposition.study_case): all spheres, the silhouette ones (|s| >= 0.8), the inner
ones (|s| < 0.7), in ppm, and the 7 instrument z-scores.

Modes: ``drawn`` (as drawn, re-detected by the current code), ``mono`` (one beam energy: no beam
hardening), ``mono_sharp`` (also a 0.3 px PSF core and no tail), ``notail`` (the PSF's tail off),
``noheel`` (the open beam's gain gradient off).

    .venv/bin/python tests/benchmarks/study_ct_tube_bias_physics.py --mode mono --seeds 7224,7226,7228 \
        --kept /tmp/ct512b --work /tmp/tubebias_mono

Ends with ONE JSON line. Measured: ct_detect.md, "Coverage: where the excess comes from".
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parent / "ct_validation")]

import ct_indep_check as ck  # noqa: E402
import ct_indep_gen as gen  # noqa: E402
import study_ct_coverage_decomposition as sd  # noqa: E402
import study_ct_location_bias as lb  # noqa: E402


MODES = ("drawn", "mono", "mono_sharp", "notail", "noheel")


def switch_physics(mode: str) -> None:
    """drawn: as drawn, re-detected by the current code; mono: one beam energy; mono_sharp: also a
    0.3 px PSF core and no tail; notail: the PSF's tail off (core as drawn); noheel: a flat open beam's
    gain gradient off (the radial fall-off as drawn)."""
    if mode not in MODES:
        raise SystemExit(f"unknown mode {mode!r}")
    if mode in ("mono", "mono_sharp"):
        gen.BEAM_WEIGHTS = np.array([0.0, 1.0, 0.0])      # the middle energy only
    changes = {"mono_sharp": {"tail_fraction": 0.0, "psf_sigma_px": 0.3}, "notail": {"tail_fraction": 0.0},
               "noheel": {"heel": 0.0}}.get(mode)
    if changes:
        draw = gen.draw_case

        def switched(*a, **k):
            case = draw(*a, **k)
            for key, v in changes.items():
                setattr(case["phys"], key, v)
            return case
        gen.draw_case = switched


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mode", required=True, choices=MODES)
    ap.add_argument("--seeds", required=True, help="comma-separated; 512 px, 36 views as validate_ct_indep.py")
    ap.add_argument("--kept", required=True, help="validate_ct_indep.py --keep directory holding these seeds as drawn")
    ap.add_argument("--work", required=True, help="new directory for the re-rendered recordings")
    ap.add_argument("--dump", help="also write the JSON to this file")
    args = ap.parse_args()
    switch_physics(args.mode)
    work = pathlib.Path(args.work)
    out = {"mode": args.mode, "cases": []}
    for s in (int(v) for v in args.seeds.split(",")):
        if not (work / "solved" / f"scan_{s}" / "results.json").exists():
            ck.run_case(s, work, cols=512, n_views=36)
        row = {"seed": s}
        for label, w in (("as_drawn", pathlib.Path(args.kept)), (args.mode, work)):
            c = lb.case_detections(w, s)
            if c is None:
                row[label] = None
                continue
            r = sd.study_case(c)
            row[label] = {k: np.round(r[k], 4).tolist() for k in ("k_ppm", "k_silhouette_ppm", "k_inner_ppm", "z", "z_det")}
            row[label]["err_det"] = r["err_det"]
            row[label]["sd_det"] = r["sd_det"]
            row["tube"] = r["tube"]
            print(f"seed {s} {label:10s} k {row[label]['k_ppm']} silhouette {row[label]['k_silhouette_ppm']} "
                  f"inner {row[label]['k_inner_ppm']} z {row[label]['z']}", flush=True)
        out["cases"].append(row)
    if args.dump:
        pathlib.Path(args.dump).write_text(json.dumps(out))
    print(json.dumps(out))


if __name__ == "__main__":
    main()
