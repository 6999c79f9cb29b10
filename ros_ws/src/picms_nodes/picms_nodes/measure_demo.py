"""Simulated PiCMS measurement: calibrate a cell, measure a part program, write the report.

    picms_measure_demo [--out DIR] [--seed N] [--program targets|flange|PATH] [--mode stage|tracker]
                       [--only id,id]

1. A simulated cell (varied physics, seed) is calibrated from a simulated Appendix-A session
   through the same pipeline as picms_calibrate_offline; the Probe is built from that
   calibration (picms_calibration.yaml is written beside the results).
2. The part (chrome targets or flange, placed with a random offset, tilt and in-plane
   rotation) is measured by `core.measure` on a SimCell (full frames for part finding, then
   a window around X*).
3. measurement.json (+ crops), report.md and plots; the report compares with the simulator's
   truth (used here only, never by the measurement).
Prints one JSON summary line. Exit 0 when the measurement was written.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np
import yaml

from .core import cellio, measure, part_program
from .measure_report import truth_for_report, write_report
from .measure_sim import FullFirstFrame, calibrated_cell, config_file, placed_part

SCENES = {"targets": ("chrome_targets", "part_program_targets.yaml"),
          "flange": ("flange", "part_program_flange.yaml")}


def truth_errors(doc, truth) -> dict:
    """Errors of sizes, centre distances and grid spacings against truth (m)."""
    from .measure_report import dimension_table, truth_value
    sizes, dists = [], []
    for r in dimension_table(doc):
        tv = truth_value(r, truth)
        if tv is None:
            continue
        (sizes if r["kind"] == "size" else dists).append(r["value"] - tv)
    grid = [sp["mean"] - sp["nominal"] for g in doc.get("dot_grids", []) for sp in g["spacings"]]
    return {"size_err_um": [round(x * 1e6, 3) for x in sizes], "distance_err_um": [round(x * 1e6, 3) for x in dists],
            "grid_mean_err_um": [round(x * 1e6, 3) for x in grid]}


def run_demo(out: pathlib.Path, seed: int, program_key: str, mode: str = "stage", only=None, log=print) -> dict:
    t0 = time.perf_counter()
    truth, probe, cal = calibrated_cell(seed)
    t_cal = time.perf_counter() - t0
    out.mkdir(parents=True, exist_ok=True)
    (out / "picms_calibration.yaml").write_text(yaml.safe_dump(cal, sort_keys=False))
    if program_key in SCENES:
        scene, pfile = SCENES[program_key]
        ppath = config_file(pfile)
    else:
        ppath = pathlib.Path(program_key)
        scene = None
    program = part_program.load(ppath)
    scene = scene or program.part
    rng = np.random.default_rng(seed + 1000)
    part = placed_part(scene, rng)
    sim = cellio.SimCell(truth, rng, part)
    cellw = FullFirstFrame(sim)

    def progress(d):
        if d.get("event") == "point":
            log(f"[picms] {d['n']}/{d['of']} {d['feature']}[{d['index']}] "
                f"{'ok' if d['ok'] else 'FAILED ' + d['reason']} in {d['iterations']} triangulations, "
                f"{d['moves']} moves, {d['elapsed_s']:.2f} s")
        else:
            log(f"[picms] {d.get('message', d)}")

    t1 = time.perf_counter()
    run = measure.measure(cellw, probe, program, progress=progress, only_features=only)
    t_meas = time.perf_counter() - t1
    doc = measure.measurement_document(run, probe, mode=mode, calibration=cal)
    mpath = measure.write_json_atomic(doc, out / "measurement.json")
    measure.write_crops(run, out / "measurement.crops.npz")
    truth_d = truth_for_report(part)
    errs = truth_errors(doc, truth_d)
    other = doc.get("other_mode", {})
    errs_other = truth_errors(other, truth_d) if "features" in other else {}
    extra = ("## Against the simulator's truth (demo only)\n\n"
             f"Cell seed {seed}; part placed at offset {np.round(part.p_stage_part * 1e6, 1).tolist()} um, "
             f"in-plane rotation {np.degrees(np.arctan2(part.R_stage_part[1, 0], part.R_stage_part[0, 0])):.2f} deg "
             f"(unknown to the program). Calibration {t_cal:.0f} s, measurement {t_meas:.0f} s "
             f"({len(run.points)} points; wall time on this machine, rendering included).\n\n"
             f"- {mode} mode: size errors {errs['size_err_um']} um; centre distances {errs['distance_err_um']} um; "
             f"grid spacing means {errs['grid_mean_err_um']} um\n"
             f"- {'tracker' if mode == 'stage' else 'stage'} mode (same points): size errors "
             f"{errs_other.get('size_err_um')} um; centre distances {errs_other.get('distance_err_um')} um; grid "
             f"{errs_other.get('grid_mean_err_um')} um\n")
    rpath = write_report(doc, out, truth=truth_d, title=f"PiCMS measurement: {program.part} (simulated cell, seed {seed})",
                         extra_md=extra)
    summary = {"measurement": str(mpath), "report": str(rpath), "points": len(run.points),
               "ok": sum(mp.ok for mp in run.points), "calibration_s": round(t_cal, 1),
               "measurement_s": round(t_meas, 1), "time_per_point_s": doc["summary"]["time_per_point_s"],
               "iterations_mean": doc["summary"]["iterations_mean"], "mode": mode, **errs,
               "other_mode": errs_other}
    return summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/picms_measure")
    ap.add_argument("--seed", type=int, default=8)
    ap.add_argument("--program", default="targets", help="targets, flange, or a part_program.yaml")
    ap.add_argument("--mode", choices=("stage", "tracker"), default="stage")
    ap.add_argument("--only", default=None, help="comma-separated feature ids (a shorter run)")
    a = ap.parse_args(argv)
    out = pathlib.Path(a.out) / time.strftime("%Y%m%d_%H%M%S")
    try:
        s = run_demo(out, a.seed, a.program, a.mode, a.only.split(",") if a.only else None)
    except (part_program.PartProgramError, OSError) as e:
        print(f"picms_measure_demo: {e}", file=sys.stderr)
        return 2
    print(json.dumps(s))
    return 0


if __name__ == "__main__":
    sys.exit(main())
