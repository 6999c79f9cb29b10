"""Offline Pixel Probe calibration from a recording (one .mcap or a rosbag2 directory).

    picms_calibrate_offline RECORDING --cell picms_cell.yaml --out picms_calibration.yaml

The same core as the live node (`core.pipeline`). Exit codes: 0 calibrated and written;
1 no calibration (the reason is printed; an existing output file is left untouched);
2 bad arguments or unreadable cell file.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

from .core.calibrate import CalibrationError
from .core.pipeline import calibrate_recording
from .io.files import calibration_dict, read_cell, write_calibration
from .io.recording import iter_frames, read_recording


def run(recording, cell_file, out=None, log=print):
    """Calibrate from a recording; returns (CalibrationResult or None, summary dict)."""
    cell = read_cell(cell_file)
    t0 = time.perf_counter()
    rec, rep = read_recording(recording, cell)
    summary = {"recording": str(recording), "counts": rep.counts, "cameras": sorted(rec.camera_info)}
    try:
        res, prep = calibrate_recording(rec, frames=iter_frames(recording, rep))
    except CalibrationError as exc:
        summary.update(success=False, error=str(exc), problems=rep.problems + rep.read.errors)
        log(f"picms calibration failed: {exc}")
        for p in summary["problems"][:20]:
            log(f"  not used: {p}")
        return None, summary
    summary.update(success=True, message=res.message, frames=prep.n_frames, settled_frames=prep.n_settled_frames,
                   detected=prep.n_detected, skipped=[f"{c} at {s} ns: {r}" for s, c, r in prep.skipped][:20],
                   problems=rep.problems + rep.read.errors, seconds=round(time.perf_counter() - t0, 2))
    for p in summary["problems"][:20]:
        log(f"  not used: {p}")
    if out:
        write_calibration(res, out)
        summary["written"] = str(out)
    return res, summary


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("recording", help=".mcap file or rosbag2 directory")
    ap.add_argument("--cell", required=True, help="picms_cell.yaml")
    ap.add_argument("--out", default="picms_calibration.yaml", help="output file (written only on success)")
    a = ap.parse_args(argv)
    try:
        res, summary = run(a.recording, a.cell, a.out, log=lambda s: print(s, file=sys.stderr))
    except (ValueError, FileNotFoundError) as exc:
        print(f"picms_calibrate_offline: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary, default=str))
    if res is None:
        return 1
    d = calibration_dict(res)
    print(json.dumps({"probe_point_pixels": d["probe_point"]["pixels"], "p_tracker": d["probe_point"]["p_tracker"],
                      "chi2_dof": d["quality"]["camera_chi2_dof"]}), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
