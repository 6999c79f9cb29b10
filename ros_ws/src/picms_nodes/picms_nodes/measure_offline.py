"""Recompute a PiCMS measurement offline from what it recorded.

    picms_measure_offline MEASUREMENT.json --out NEW.json [--mode stage|tracker]
                          [--program part_program.yaml] [--relocate] [--report DIR]
                          [--history DB|none] [--namespace /cell]

MEASUREMENT.json is a measurement written by `measure` (demo, node): besides the INTERFACES.md
keys it holds every point (encoder reading, stage- and tracker-frame point, covariances, the
pixels it was found at, its target definition), the calibration used and the CameraInfo
intrinsics; the image crops around every point's feature pixels sit beside it
(MEASUREMENT.crops.npz). Without --relocate the recorded points are refitted (e.g. in the other
mode); with --relocate every point is located again in its recorded crops with the current
locators (edge point on PI, dot centroid) and triangulated at its recorded encoder reading.
Points that cannot be read or located are listed and left out; nothing is written when the
fit fails (an existing output stays). The recompute, or its failure, is stored in the
calibration history (kind ``picms_measurement``, source offline; io/picms_history.py). Exit 0 written, 1 not written, 2 bad arguments.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import sys

import numpy as np

from .core import features, fitting, measure, part_program, targeting
from .core.camera import Intrinsics


class _Settled:
    def __init__(self, q, images):
        self.q = np.asarray(q, float)
        self.images = images


def probe_from_doc(doc: dict) -> targeting.Probe:
    pr = doc.get("probe")
    if not pr:
        raise ValueError("measurement has no 'probe' (calibration and CameraInfo) block: cannot re-locate")
    info = {c: Intrinsics(np.array(v["K"]), np.array(v["D"]), int(v["width"]), int(v["height"]))
            for c, v in pr["camera_info"].items()}
    return targeting.Probe.from_calibration_yaml(pr["calibration"], info)


def relocate(doc: dict, crops_path, probe) -> tuple[list, list]:
    """Points located again in their recorded crops: (MeasuredPoint list, problems)."""
    z = np.load(crops_path)
    pts, problems = [], []
    for k, rec in enumerate(doc["points"]):
        mp = measure.point_from_record(rec)
        t = rec.get("target") or {}
        imgs = {}
        for c, intr in probe.intrinsics.items():
            key = f"p{k}_{c}"
            if key in z:
                a = z[key]
                x0, y0 = (int(v) for v in z[key + "_xy"])
                full = np.full((intr.height, intr.width), np.median(a), dtype=a.dtype)
                full[y0:y0 + a.shape[0], x0:x0 + a.shape[1]] = a
                imgs[c] = full
        if len(imgs) < 2 or mp.q is None:
            problems.append(f"point {k} ({mp.feature_id}[{mp.index}]): crops in {len(imgs)} camera(s)")
            continue
        try:
            if t.get("kind") == "dot":
                target = {"centre": np.asarray(t["centre"], float), "diameter": float(t["diameter"])}
            else:
                target = features.EdgeTarget(**{k2: (np.asarray(v, float) if isinstance(v, list) else v)
                                                for k2, v in t.items() if k2 != "kind"})
            loc = measure.make_locator(target)
            px = loc(_Settled(mp.q, imgs), probe)
            tri = targeting.triangulate(probe, px, q=mp.q)
        except (targeting.TargetingError, ValueError, TypeError, KeyError) as e:
            problems.append(f"point {k} ({mp.feature_id}[{mp.index}]): {e}")
            continue
        mp.p_stage = probe.xstar_stage(mp.q) + tri.offset_stage
        mp.cov_stage = (loc.last.cov if isinstance(loc.last, features.EdgePoint) else tri.cov) + probe.cov_xstar_stage(mp.q)
        mp.pixels = {c: tuple(v[:2]) for c, v in px.items()}
        pts.append(mp)
    return pts, problems


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("measurement", help="measurement.json written by a PiCMS measurement")
    ap.add_argument("--out", required=True)
    ap.add_argument("--mode", choices=("stage", "tracker"), default=None, help="default: the recorded mode")
    ap.add_argument("--program", default=None, help="part_program.yaml (default: the one recorded)")
    ap.add_argument("--relocate", action="store_true", help="re-locate every point in its recorded image crops")
    ap.add_argument("--crops", default=None, help="crops file (default: MEASUREMENT.crops.npz)")
    ap.add_argument("--report", default=None, help="write report.md and plots into this directory")
    ap.add_argument("--history", default="", help="calibration history database (default $METRO_HISTORY_DB or "
                                                  "~/.local/share/metro_cell/history.sqlite; none = off)")
    ap.add_argument("--namespace", default="/", help="the cell (namespace) the measurement is stored under")
    a = ap.parse_args(argv)
    path = pathlib.Path(a.measurement)
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError, RecursionError) as e:      # RecursionError: nesting too deep to decode
        print(f"cannot read {path}: {e}", file=sys.stderr)
        return 2
    bad = _shape_problem(doc)
    if bad:
        print(f"{path}: not a usable measurement document: {bad}", file=sys.stderr)
        return 2
    try:
        prog_src = a.program or (doc.get("program_yaml") or doc.get("program"))
        program = part_program.load(prog_src if isinstance(prog_src, (dict, str)) else "")
    except part_program.PartProgramError as e:
        print(f"part program: {e}", file=sys.stderr)
        return 2
    mode = a.mode or doc.get("mode", "stage")
    problems = []
    pts = []
    for k, rec in enumerate(doc.get("points", [])):
        try:
            pts.append(measure.point_from_record(rec))
        except (KeyError, TypeError, ValueError) as e:
            problems.append(f"point {k}: unreadable record ({e})")
    try:
        probe = probe_from_doc(doc) if (a.relocate or mode == "tracker") else None
    except (ValueError, KeyError, TypeError, IndexError, targeting.TargetingError) as e:
        print(f"probe: {e}", file=sys.stderr)
        return 1
    if a.relocate:
        crops = pathlib.Path(a.crops) if a.crops else path.with_suffix(".crops.npz")
        if not crops.is_file():
            print(f"no crops file {crops}", file=sys.stderr)
            return 1
        pts, p2 = relocate(doc, crops, probe)
        problems += p2
    R_ts = np.asarray(doc.get("probe", {}).get("calibration", {}).get("stage", {}).get("R_tracker_stage", np.eye(3)), float)
    try:
        new = measure.fit_measurement(program, pts, mode=mode, R_tracker_stage=R_ts,
                                      part_R_stage=np.asarray(doc.get("part_finding", {}).get("R_stage_part", np.eye(3))))
    except (fitting.FitError, ValueError) as e:
        print(f"fit failed, nothing written: {e}", file=sys.stderr)
        for p in problems:
            print(f"  not used: {p}", file=sys.stderr)
        _store(a, None, f"fit failed: {e}", path, None)
        return 1
    keep = {k: doc[k] for k in ("part_finding", "band_width_m", "probe", "program", "program_yaml") if k in doc}
    new.update(keep)
    new["points"] = [measure.point_record(mp) for mp in pts]
    new["summary"] = {"n_points": len(doc.get("points", [])), "n_ok": sum(mp.ok for mp in pts),
                      "recomputed_from": str(path), "relocated": bool(a.relocate)}
    new["problems"] = problems
    measure.write_json_atomic(new, a.out)
    if a.report:
        from .measure_report import write_report
        write_report(new, a.report, title=f"PiCMS measurement (offline recompute): {program.part}")
    for p in problems:
        print(f"  not used: {p}")
    out = {"written": a.out, "mode": mode, "points": len(pts), "problems": len(problems)}
    hist = _store(a, new, "", path, a.out)
    if hist:
        out["history"] = hist
    print(json.dumps(out))
    return 0


def _matrix3(value, what):
    try:
        m = np.asarray(value, float)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{what} is not a 3 x 3 matrix ({e})") from None
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise ValueError(f"{what} is not a finite 3 x 3 matrix (shape {m.shape})")
    return m


def _shape_problem(doc):
    """What makes ``doc`` unusable as a measurement document (wrong JSON types), or None."""
    if not isinstance(doc, dict):
        return f"a JSON object expected, got {type(doc).__name__}"
    for key, typ in (("points", list), ("probe", dict), ("part_finding", dict)):
        if key in doc and not isinstance(doc[key], typ):
            return f"{key!r} must be a JSON {'array' if typ is list else 'object'}, got {type(doc[key]).__name__}"
    cal = doc.get("probe", {}).get("calibration", {})
    if not isinstance(cal, dict) or not isinstance(cal.get("stage", {}), dict):
        return "'probe.calibration.stage' must be a JSON object"
    try:
        if "R_tracker_stage" in cal.get("stage", {}):
            _matrix3(cal["stage"]["R_tracker_stage"], "probe.calibration.stage.R_tracker_stage")
        if "R_stage_part" in doc.get("part_finding", {}):
            _matrix3(doc["part_finding"]["R_stage_part"], "part_finding.R_stage_part")
    except ValueError as e:
        return str(e)
    return None


def _store(a, doc, message, src, written):
    """The recompute (or its failure) in the calibration history, kind picms_measurement, source
    offline, linked to the input measurement.json and the one written. Never fatal."""
    from ct_calib_nodes.io.history import Input, open_history  # noqa: PLC0415

    from .io.picms_history import measurement_record  # noqa: PLC0415

    if str(a.history).lower() in ("none", "off", "false", "0"):
        return None
    h = open_history(a.history or None, logger=lambda m: print(m, file=sys.stderr))
    if h is None:
        return None
    try:
        inputs = [Input.file("measurement_json", src)] + ([Input.file("measurement_json_out", written)] if written else [])
        plain = json.loads(json.dumps(doc, default=measure._json_default)) if doc is not None else None
        s = h.record(measurement_record(plain, cell=a.namespace, source="offline", inputs=inputs, message=message))
        return {"db": h.path, "id": s.id, "uid": s.uid, "status": s.status}
    except Exception as exc:  # noqa: BLE001 - the result file stands without its history
        print(f"calibration history not recorded: {exc}", file=sys.stderr)
        return None
    finally:
        h.close()


if __name__ == "__main__":
    sys.exit(main())
