"""Pixel Probe calibrations -> calibration-history records (ct_calib_nodes/io/history.py), without ROS.

Kind ``picms_calibration``, stored by the live node (``source`` live) and by
``picms_calibrate_offline`` (offline), linked to their inputs as the CT cell's solves are: the
recording (path + content hash) or the live topics (with their stamp range), and
``picms_cell.yaml`` (sha256). Status in the one outcome vocabulary: ``success``, ``poor_fit``
(camera fit chi2/dof >= 4: residuals well beyond the stated uncertainties, the same rule as the
published message), ``failed`` (no calibration; the reason in ``message``).

Quantities (what ``ct_history compare`` / ``trend`` read), SI units, u = standard uncertainty:

- ``x_star_col_<camera>``, ``x_star_row_<camera>`` [px]: x_j*, the image of X*;
- ``p_tracker_x|y|z`` [m]: X* in the tracker frame (u from the diagonal of its covariance);
- ``p_constellation_x|y|z`` [m]: X* in the constellation frame (what survives a re-measurement of
  the constellation: the key trend of the probe point);
- ``centre_x|y|z_<camera>`` [m]: perspective centre in the stage frame relative to X*;
- ``rotvec_x|y|z_<camera>`` [rad]: R_stage_camera as a rotation vector; no u (the stated
  uncertainties are small rotations about the stage axes, not of these components), so never
  flagged: camera rotation changes show in x_j* and the centres;
- ``squareness_xy|xz|yz`` [rad], ``tracker_sigma_m`` [m], ``camera_chi2_dof`` [1].

The result JSON keeps ``picms_calibration.yaml``'s content (``calibration``) and, when ROS message
support is importable, the ``metro_msgs/PicmsCalibration`` message (``ros_msg``) so the live node
re-publishes the latest valid calibration, live or offline, at start.
"""
from __future__ import annotations

import math
import pathlib

import numpy as np

from ct_calib_nodes.io.history import Input, Quantity, SolveRecord, cell_name

from ..core.calibrate import is_poor_fit

KIND = "picms_calibration"
MSG_TYPE = "metro_msgs/msg/PicmsCalibration"


def status_of(res) -> str:
    if res is None or not getattr(res, "success", True):
        return "failed"
    return "poor_fit" if is_poor_fit(res) else "success"


def quantities(res) -> list:
    q = []
    for cam in sorted(res.pixels):
        for i, ax in enumerate(("col", "row")):
            q.append(Quantity(f"x_star_{ax}_{cam}", float(res.pixels[cam][i]), float(res.u_pixels[cam][i]), "px"))
    cov = np.asarray(res.cov_p_tracker, float).reshape(3, 3)
    covc = np.asarray(res.cov_p_constellation, float).reshape(3, 3)
    for i, ax in enumerate("xyz"):
        q.append(Quantity(f"p_tracker_{ax}", float(res.p_tracker[i]), math.sqrt(max(cov[i, i], 0.0)), "m"))
    for i, ax in enumerate("xyz"):
        q.append(Quantity(f"p_constellation_{ax}", float(res.p_constellation[i]), math.sqrt(max(covc[i, i], 0.0)), "m"))
    from ..core.camera import matrix_to_rotvec  # noqa: PLC0415
    for cam in sorted(res.cameras):
        c = res.cameras[cam]
        for i, ax in enumerate("xyz"):
            q.append(Quantity(f"centre_{ax}_{cam}", float(c.p_stage_centre[i]), float(c.u_p_stage_centre[i]), "m"))
        rv = matrix_to_rotvec(c.R_stage_camera)
        for i, ax in enumerate("xyz"):
            q.append(Quantity(f"rotvec_{ax}_{cam}", float(rv[i]), None, "rad"))
    for k in ("xy", "xz", "yz"):
        q.append(Quantity(f"squareness_{k}", float(res.squareness_rad[k]), float(res.u_squareness_rad[k]), "rad"))
    q.append(Quantity("tracker_sigma_m", float(res.tracker_sigma_m), None, "m"))
    q.append(Quantity("camera_chi2_dof", float(res.chi2_dof), None, "1"))
    return q


#: key quantities for ``ct_history trend`` (every camera's x_j* and centre are added by name)
TREND_KEYS = ("p_constellation_x", "p_constellation_y", "p_constellation_z", "p_tracker_x", "p_tracker_y",
              "p_tracker_z", "squareness_xy", "squareness_xz", "squareness_yz")


def campaign_id_of(cell: str, joint_stamps_ns) -> str | None:
    """``<cell>@<first stage reading stamp ns>`` (as the CT cell forms its campaign ids)."""
    t = np.asarray(joint_stamps_ns)
    return f"{cell_name(cell)}@{int(t.min())}" if t.size else None


def calibration_record(res, *, cell: str, source: str, inputs=(), joint_stamps_ns=(), message: str | None = None,
                       extra: dict | None = None) -> SolveRecord:
    """A record of a calibration (``res`` a CalibrationResult) or of a failure (``res`` None, ``message`` why)."""
    from .files import calibration_dict  # noqa: PLC0415

    t = np.asarray(joint_stamps_ns, dtype=np.int64)
    status = status_of(res)
    result = {"calibration": calibration_dict(res)} if res is not None else {"error": str(message or "failed")}
    result.update(extra or {})
    return SolveRecord(cell=cell, kind=KIND, status=status, source=source,
                       message=str(message if message is not None else res.message), result=result,
                       campaign_id=campaign_id_of(cell, t), final=True,
                       data_start_ns=int(t.min()) if t.size else None, data_end_ns=int(t.max()) if t.size else None,
                       inputs=list(inputs), quantities=quantities(res) if res is not None else [])


def offline_inputs(recording, cell_file, namespace: str = "/") -> list:
    rec = Input.file("recording", recording)
    rec.detail = {"namespace": namespace}
    return [rec, Input.file("picms_cell_yaml", pathlib.Path(cell_file))]


def attach_msg(rec: SolveRecord, res, file_path: str = "", stamp_ns: int | None = None) -> SolveRecord:
    """Add the PicmsCalibration message to a record when ROS message support is importable (the live node
    re-publishes it at start); silently nothing otherwise."""
    if res is None:
        return rec
    try:
        from builtin_interfaces.msg import Time  # noqa: PLC0415
        from rclpy.serialization import serialize_message  # noqa: PLC0415

        from ct_calib_nodes.io.ct_history import ros_msg_blob  # noqa: PLC0415

        from .calibration_msg import calibration_msg  # noqa: PLC0415
    except ImportError:
        return rec
    import time  # noqa: PLC0415
    t = int(stamp_ns if stamp_ns is not None else time.time_ns())     # the message's stamp: when computed
    msg = calibration_msg(res, Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000), file_path)
    rec.result["ros_msg"] = ros_msg_blob(MSG_TYPE, serialize_message(msg))
    return rec


# ------------------------------------------------------------------------------ measurements
MEASUREMENT_KIND = "picms_measurement"
MEASUREMENT_TREND_KEYS = ("flatness", "n_ok")


def _u(v):
    return None if v is None or not np.isfinite(float(v)) else float(v)


def measurement_quantities(doc: dict) -> list:
    """The trendable figures of a measurement.json (SI, u = stated standard uncertainty):
    ``size_<feature>`` (circle diameter, square mean side) [m], ``side_x|y_<feature>`` (squares),
    ``size_x|y_<feature>`` (rectangles), ``form_rms_<feature>`` [m], ``spacing_<grid>_<k>`` (mean
    spacing at k pitches) [m], ``flatness`` [m] (of the part plane), ``n_ok`` [1]."""
    q = []
    for f in doc.get("features", []):
        fid = f.get("id")
        if "error" in f or "size" not in f:
            continue
        if f["type"] == "rectangle":
            for i, ax in enumerate("xy"):
                q.append(Quantity(f"size_{ax}_{fid}", float(f["size"][i]), _u(f["u_size"][i]), "m"))
        else:
            q.append(Quantity(f"size_{fid}", float(f["size"]), _u(f.get("u_size")), "m"))
        if f["type"] == "square":
            for i, ax in enumerate("xy"):
                q.append(Quantity(f"side_{ax}_{fid}", float(f["sides"][i]), _u(f["u_sides"][i]), "m"))
        q.append(Quantity(f"form_rms_{fid}", float(f["form_rms"]), None, "m"))
    for g in doc.get("dot_grids", []):
        for s in g.get("spacings", []):      # no u: the spacings share dots, so their mean's u is not sd/sqrt(n)
            q.append(Quantity(f"spacing_{g['id']}_{s['k']}", float(s["mean"]), None, "m"))
    if "plane" in doc:
        q.append(Quantity("flatness", float(doc["plane"]["flatness"]), None, "m"))
    if "summary" in doc:
        q.append(Quantity("n_ok", float(doc["summary"]["n_ok"]), None, "1"))
    return q


def measurement_record(doc: dict | None, *, cell: str, source: str, inputs=(), message: str = "",
                       campaign_id: str | None = None) -> SolveRecord:
    """A record of a measurement (``doc`` the measurement.json content without its raw points) or of a
    failed one (``doc`` None, ``message`` why). Status: ``success`` when every planned point was
    measured and every feature fitted, ``poor_fit`` when some were not (the result still stands for
    what was measured), ``failed`` when there is no result."""
    if doc is None:
        return SolveRecord(cell=cell, kind=MEASUREMENT_KIND, status="failed", source=source,
                           message=str(message or "failed"), result={"error": str(message or "failed")},
                           campaign_id=campaign_id, final=True, inputs=list(inputs))
    s = doc.get("summary", {})
    complete = s.get("n_ok") == s.get("n_points") and not any("error" in f for f in doc.get("features", []))
    result = {k: v for k, v in doc.items() if k not in ("points", "probe")}
    return SolveRecord(cell=cell, kind=MEASUREMENT_KIND, status="success" if complete else "poor_fit", source=source,
                       message=message or f"{doc.get('part', '?')}: {s.get('n_ok')}/{s.get('n_points')} points",
                       result=result, campaign_id=campaign_id, final=True, inputs=list(inputs),
                       quantities=measurement_quantities(doc))
