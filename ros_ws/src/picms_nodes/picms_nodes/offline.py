"""Offline Pixel Probe calibration from a recording (one .mcap or a rosbag2 directory).

    picms_calibrate_offline RECORDING [--cell picms_cell.yaml] [--out picms_calibration.yaml]
                            [--namespace /cell_b] [--history DB|none] [--force]

The same core as the live node (`core.pipeline`). ``--cell``: given, else ``picms_cell.yaml``
beside the recording (in a rosbag2 directory or next to the .mcap), else the package default.
``--namespace``: the cell's namespace in the recording (a recording made under
``__ns:=/cell_b``); without it the one Pixel Probe cell in the recording is found. Every run, usable
or not, is stored in the calibration history (kind ``picms_calibration``, the recording's content
hash and the cell file's sha256 as inputs; ``--history``, else ``$METRO_HISTORY_DB``, else
``~/.local/share/metro_cell/history.sqlite``; ``none`` = off).
A POOR_FIT calibration (camera chi2/dof >= 4: its model does not explain the data) is not written, as
the live node does not write one: plant software reads that file, and a good one there stays;
``--force`` writes it anyway (its status is in the history and in this command's output).
Exit codes: 0 calibrated and written; 1 no calibration (the reason is printed; an existing output
file is left untouched); 2 bad arguments or unreadable cell file; 3 calibrated but POOR_FIT, not
written (an existing output file is left untouched).
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

from .core.calibrate import POOR_FIT_CHI2, CalibrationError, is_poor_fit
from .core.pipeline import calibrate_recording
from .io.files import calibration_dict, read_cell, write_calibration
from .io.recording import find_namespace, iter_frames, read_recording


def find_cell_file(recording, cell_file=None):
    """The cell file: given, else picms_cell.yaml beside the recording, else the package default."""
    if cell_file:
        return pathlib.Path(cell_file)
    r = pathlib.Path(recording)
    for d in ([r] if r.is_dir() else []) + [r.parent]:
        if (d / "picms_cell.yaml").is_file():
            return d / "picms_cell.yaml"
    from .nodes.picms_calibration import _default_cell  # noqa: PLC0415
    return pathlib.Path(_default_cell())


def run(recording, cell_file=None, out=None, log=print, namespace=None, history="none", force=False):
    """Calibrate from a recording; returns (CalibrationResult or None, summary dict).

    ``history``: database path ("" = the default, "none" = not stored; the library default is none,
    the command line's is the default database). ``force``: write ``out`` even for a POOR_FIT calibration."""
    cell_file = find_cell_file(recording, cell_file)
    cell = read_cell(cell_file)
    t0 = time.perf_counter()
    ns = find_namespace(recording, namespace)
    rec, rep = read_recording(recording, cell, ns)
    summary = {"recording": str(recording), "namespace": ns, "cell_file": str(cell_file), "counts": rep.counts,
               "cameras": sorted(rec.camera_info)}
    try:
        res, prep = calibrate_recording(rec, frames=iter_frames(recording, rep, ns))
    except CalibrationError as exc:
        summary.update(success=False, error=str(exc), problems=rep.problems + rep.read.errors)
        log(f"picms calibration failed: {exc}")
        for p in summary["problems"][:20]:
            log(f"  not used: {p}")
        _store(history, None, str(exc), recording, cell_file, ns, rec, summary, log)
        return None, summary
    summary.update(success=True, message=res.message, frames=prep.n_frames, settled_frames=prep.n_settled_frames,
                   detected=prep.n_detected, skipped=[f"{c} at {s} ns: {r}" for s, c, r in prep.skipped][:20],
                   problems=rep.problems + rep.read.errors, seconds=round(time.perf_counter() - t0, 2))
    for p in summary["problems"][:20]:
        log(f"  not used: {p}")
    summary["poor_fit"] = is_poor_fit(res)
    if out and summary["poor_fit"] and not force:
        summary["not_written"] = (f"POOR_FIT: camera chi2/dof {float(res.chi2_dof):.3g} >= {POOR_FIT_CHI2:g} (the model "
                                  f"does not explain the data); {out} left untouched (--force writes it)")
        log(f"picms calibration not written: {summary['not_written']}")
    elif out:
        write_calibration(res, out)
        summary["written"] = str(out)
    _store(history, res, None, recording, cell_file, ns, rec, summary, log)
    return res, summary


def _store(history, res, message, recording, cell_file, ns, rec, summary, log):
    """Store the run in the calibration history (never fatal: the result files stand without it)."""
    from ct_calib_nodes.io.history import open_history  # noqa: PLC0415

    from .io.picms_history import attach_msg, calibration_record, offline_inputs  # noqa: PLC0415

    if history is None or str(history).lower() in ("none", "off", "false", "0"):
        return
    h = open_history(history or None, logger=log)
    if h is None:
        return
    try:
        r = calibration_record(res, cell=ns, source="offline", inputs=offline_inputs(recording, cell_file, ns),
                               joint_stamps_ns=rec.joint_stamps_ns, message=message,
                               extra={"problems": [str(p) for p in summary.get("problems", [])][:50]})
        attach_msg(r, res, summary.get("written", ""))
        s = h.record(r)
        summary["history"] = {"db": h.path, "id": s.id, "uid": s.uid, "status": s.status}
    except Exception as exc:  # noqa: BLE001
        log(f"calibration history not recorded: {exc}")
    finally:
        h.close()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("recording", help=".mcap file or rosbag2 directory")
    ap.add_argument("--cell", help="picms_cell.yaml (default: beside the recording, else the package's)")
    ap.add_argument("--out", default="picms_calibration.yaml",
                    help="output file (written only on success, and not for a POOR_FIT calibration)")
    ap.add_argument("--force", action="store_true", help="write the output file for a POOR_FIT calibration too")
    ap.add_argument("--namespace", help="the cell's namespace in the recording (default: the one found)")
    ap.add_argument("--history", default="", help="calibration history database (default $METRO_HISTORY_DB or "
                                                  "~/.local/share/metro_cell/history.sqlite; none = off)")
    a = ap.parse_args(argv)
    try:
        res, summary = run(a.recording, a.cell, a.out, log=lambda s: print(s, file=sys.stderr),
                           namespace=a.namespace, history=a.history, force=a.force)
    except (ValueError, FileNotFoundError) as exc:
        print(f"picms_calibrate_offline: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary, default=str))
    if res is None:
        return 1
    d = calibration_dict(res)
    print(json.dumps({"probe_point_pixels": d["probe_point"]["pixels"], "p_tracker": d["probe_point"]["p_tracker"],
                      "chi2_dof": d["quality"]["camera_chi2_dof"]}), file=sys.stderr)
    return 3 if "not_written" in summary else 0


if __name__ == "__main__":
    sys.exit(main())
