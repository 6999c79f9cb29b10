"""The simulated PiCMS cell end to end: each node in its own process over DDS.

    picms_demo [--out DIR] [--bags DIR] [--seed N] [--dwell S] [--timeout S]

Starts picms_stage_sim, picms_camera_sim, picms_tracker_sim, the MCAP recorder (every PiCMS
topic) and picms_calibration (auto_start), waits for the calibration, stops the rest, then
calibrates the recording offline through the same core and prints both results against the
simulator's truth (rebuilt from the seed; the solvers never see it). Exit 0 when both worked.
"""
from __future__ import annotations

import argparse
import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np

TOPICS = ["/picms/stage/joint_states", "/picms/stage/command", "/picms/tracker/probe_pose", "/picms/calibration",
          "/picms/discrepancy"] + \
    [f"/picms/camera_{k}/{t}" for k in (1, 2, 3) for t in ("image_raw", "camera_info")] + \
    [f"/picms/tracker/smr/{n}" for n in ("smr_1", "smr_2", "smr_3", "smr_4", "smr_5", "smr_star")]


def _exe(pkg, name):
    here = pathlib.Path(sys.argv[0]).resolve().parent
    cand = here.parents[2] / pkg / "lib" / pkg / name if here.name == "picms_nodes" else None
    if cand is not None and cand.is_file():
        return str(cand)
    return str(here / name) if (here / name).is_file() else name


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="simulated PiCMS cell: calibration live and offline")
    ap.add_argument("--out", default="out/picms")
    ap.add_argument("--bags", default="bags")
    ap.add_argument("--seed", type=int, default=8)
    ap.add_argument("--dwell", type=float, default=2.0)
    ap.add_argument("--timeout", type=float, default=300.0)
    ap.add_argument("--pattern", choices=("appendix_a", "grid"), default="appendix_a",
                    help="calibration stations; grid (33) is enough for a discrepancy verdict")
    ap.add_argument("--tracker-lag-ms", type=float, default=0.0, help="hidden: the tracker's stamps run late [ms]")
    a = ap.parse_args(argv)
    stamp = time.strftime("%Y%m%d_%H%M%S")
    out = pathlib.Path(a.out) / stamp
    out.mkdir(parents=True, exist_ok=True)
    bag = pathlib.Path(a.bags) / f"picms_{stamp}.mcap"
    bag.parent.mkdir(parents=True, exist_ok=True)
    calib = out / "picms_calibration.yaml"
    seed = ["-p", f"cell_seed:={a.seed}"]
    cmds = {
        "recorder": [_exe("ct_calib_nodes", "mcap_recorder"), "--ros-args", "-p", f"output:={bag}",
                     "-p", "topics:=[" + ",".join(TOPICS) + "]"],
        "stage": [_exe("picms_nodes", "picms_stage_sim"), "--ros-args"],
        "cameras": [_exe("picms_nodes", "picms_camera_sim"), "--ros-args", *seed],
        "tracker": [_exe("picms_nodes", "picms_tracker_sim"), "--ros-args", *seed,
                    "-p", f"tracker_lag_ms:={a.tracker_lag_ms}"],
    }
    procs = {}
    logs = {}
    try:
        for k, c in cmds.items():
            logs[k] = open(out / f"{k}.log", "wb")
            procs[k] = subprocess.Popen(c, stdout=logs[k], stderr=subprocess.STDOUT, start_new_session=True)
        time.sleep(3.0)
        logs["calibration"] = open(out / "calibration.log", "wb")
        cal = subprocess.Popen([_exe("picms_nodes", "picms_calibration"), "--ros-args", "-p", "auto_start:=true",
                                "-p", "exit_when_done:=true", "-p", "command_subscribers:=2", "-p", f"output_file:={calib}",
                                "-p", f"dwell_s:={a.dwell}", "-p", f"pattern:={a.pattern}"],
                               stdout=logs["calibration"], stderr=subprocess.STDOUT,
                               start_new_session=True)
        try:
            rc = cal.wait(a.timeout)
        except subprocess.TimeoutExpired:
            os.killpg(cal.pid, signal.SIGINT)
            cal.wait(10)
            rc = 3
    finally:
        for k in ("cameras", "tracker", "stage", "recorder"):
            p = procs.get(k)
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(40)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
        for f in logs.values():
            f.close()
    summary = {"live_exit": rc, "calibration_file": str(calib) if calib.is_file() else None, "recording": str(bag)}
    from ..core.camera import rotation_angle_rad
    from ..core.cell import cell_from_seed
    from ..offline import run
    import yaml

    truth = cell_from_seed(a.seed)
    x_true = truth.to_tracker(truth.smr_star_stage)[0]

    def compare(d):
        cams = {}
        for j, c in enumerate(truth.cameras):
            e = d["cameras"][c.name]
            cams[c.name] = {"rot_err_arcsec": round(rotation_angle_rad(np.array(e["R_stage_camera"]), c.pose.R_stage_camera) * 206265, 2),
                            "centre_err_um": round(float(np.linalg.norm(np.array(e["p_stage_centre"]) - c.pose.p_stage_centre)) * 1e6, 1),
                            "reprojection_rms_px": e["reprojection_rms_px"]}
        return {"x_star_err_um": round(float(np.linalg.norm(np.array(d["probe_point"]["p_tracker"]) - x_true)) * 1e6, 2),
                "cameras": cams}

    if calib.is_file():
        summary["live_vs_truth"] = compare(yaml.safe_load(calib.read_text()))
    off = out / "picms_calibration_offline.yaml"
    cell_file = pathlib.Path(__file__).resolve().parents[2] / "config" / "picms_cell.yaml"
    if not cell_file.is_file():
        from .picms_calibration import _default_cell
        cell_file = _default_cell()
    if bag.exists():
        res, s = run(bag, cell_file, off, log=lambda m: None)
        summary["offline"] = {"success": res is not None and "not_written" not in s,
                              **({"error": s.get("error")} if res is None else {}),
                              **({"not_written": s["not_written"]} if "not_written" in s else {})}
        if res is not None and "written" in s:
            summary["offline_vs_truth"] = compare(yaml.safe_load(off.read_text()))
    print(json.dumps(summary, indent=1))
    return 0 if rc == 0 and summary.get("offline", {}).get("success") else 1


if __name__ == "__main__":
    sys.exit(main())
