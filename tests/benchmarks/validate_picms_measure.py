"""Validate PiCMS measurements against the simulator's truth over several cells and placements.

    python tests/benchmarks/validate_picms_measure.py [--seeds 1 2 3] [--programs targets flange]
                                                     [--only id,id] [--estimate-band]

Per seed: a cell with varied physics is calibrated from a simulated Appendix-A session (probe
from the calibration only), the part is placed with a random offset (+-0.2 mm), tilt (+-30 mrad)
and in-plane rotation (unknown to the program), and the part program is measured on a SimCell.
Errors against truth: sizes (square sides, diameters, rectangle sides), centre distances of
same-size features and the bolt circle, dot-grid spacing means per category, in the stage
(tracker-free) mode and the tracker mode of the same points; size z-scores (error / stated u);
targeting iterations and moves per point; wall time per point (this machine, loaded, rendering
included). --no-stage-errors simulates a rigid stage (the stage error motions of
core/stage_errors.py are on by default). --estimate-band ignores the flange program's
edge_band_m (the band width is then estimated from the images). Ends by printing ONE JSON line.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace

import numpy as np

from picms_nodes.core import cellio, measure, part_program
from picms_nodes.measure_demo import SCENES, truth_errors
from picms_nodes.measure_report import dimension_table, truth_for_report, truth_value
from picms_nodes.measure_sim import FullFirstFrame, calibrated_cell, config_file, placed_part


def zscores(doc, truth, kind="size"):
    z = []
    for r in dimension_table(doc):
        tv = truth_value(r, truth)
        if r["kind"] == kind and tv is not None and r["u"]:
            z.append((r["value"] - tv) / r["u"])
    return z


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--programs", nargs="+", default=["targets", "flange"])
    ap.add_argument("--only", default=None)
    ap.add_argument("--estimate-band", action="store_true")
    ap.add_argument("--no-stage-errors", action="store_true",
                    help="a rigidly translating stage (no scale / straightness / angular error motions)")
    a = ap.parse_args(argv)
    only = a.only.split(",") if a.only else None
    agg = {}
    for prog_key in a.programs:
        scene, pfile = SCENES[prog_key]
        program = part_program.load(config_file(pfile))
        if a.estimate_band:
            program = replace(program, features=tuple(replace(f, band_m=None) for f in program.features))
        res = {"stage": {"size": [], "dist": [], "grid": [], "z": [], "dz": []},
               "tracker": {"size": [], "dist": [], "grid": [], "z": [], "dz": []},
               "iterations": [], "moves": [], "time_per_point_s": [], "failed_points": 0, "runs": 0, "errors": []}
        for seed in a.seeds:
            t0 = time.perf_counter()
            try:
                truth, probe, cal = calibrated_cell(seed, stage_error_motions=not a.no_stage_errors)
                rng = np.random.default_rng(seed + 1000)
                part = placed_part(scene, rng)
                run = measure.measure(FullFirstFrame(cellio.SimCell(truth, rng, part)), probe, program, only_features=only)
                doc = measure.measurement_document(run, probe, mode="stage")
            except Exception as e:  # noqa: BLE001  (a validation run reports and continues)
                res["errors"].append(f"seed {seed}: {type(e).__name__}: {e}")
                continue
            tr = truth_for_report(part)
            for mode, d in (("stage", doc), ("tracker", doc.get("other_mode", {}))):
                if "features" not in d:
                    continue
                e = truth_errors(d, tr)
                res[mode]["size"] += e["size_err_um"]
                res[mode]["dist"] += e["distance_err_um"]
                res[mode]["grid"] += e["grid_mean_err_um"]
                res[mode]["z"] += zscores(d, tr)
                res[mode]["dz"] += zscores(d, tr, "distance")
            ok = [mp for mp in run.points if mp.ok]
            res["failed_points"] += len(run.points) - len(ok)
            res["iterations"] += [mp.iterations for mp in ok]
            res["moves"] += [mp.moves for mp in ok]
            res["time_per_point_s"] += [mp.elapsed_s for mp in run.points]
            res["runs"] += 1
            print(f"[validate] {prog_key} seed {seed}: {time.perf_counter() - t0:.0f} s, stage sizes "
                  f"{truth_errors(doc, tr)['size_err_um']} um", file=sys.stderr)

        def st(v):
            v = np.abs(np.asarray(v, float))
            return {"n": int(v.size), "median_abs": round(float(np.median(v)), 3) if v.size else None,
                    "max_abs": round(float(v.max()), 3) if v.size else None}

        agg[prog_key] = {
            "runs": res["runs"], "errors": res["errors"], "failed_points": res["failed_points"],
            **{f"{mode}_{k}_err_um": st(res[mode][k]) for mode in ("stage", "tracker") for k in ("size", "dist", "grid")},
            "stage_size_z_rms": round(float(np.sqrt(np.mean(np.square(res["stage"]["z"])))), 2) if res["stage"]["z"] else None,
            "tracker_size_z_rms": round(float(np.sqrt(np.mean(np.square(res["tracker"]["z"])))), 2) if res["tracker"]["z"] else None,
            **{f"{mode}_distance_z_rms": round(float(np.sqrt(np.mean(np.square(res[mode]["dz"])))), 2)
               if res[mode]["dz"] else None for mode in ("stage", "tracker")},
            "iterations_per_point": round(float(np.mean(res["iterations"])), 2) if res["iterations"] else None,
            "moves_per_point": round(float(np.mean(res["moves"])), 2) if res["moves"] else None,
            "time_per_point_s": round(float(np.median(res["time_per_point_s"])), 2) if res["time_per_point_s"] else None,
            "band": "estimated" if a.estimate_band else "program",
        }
    print(json.dumps({"seeds": a.seeds, "only": only, "results": agg}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
