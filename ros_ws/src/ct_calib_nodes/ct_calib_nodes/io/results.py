"""Solver results <-> metro_msgs, and result files (YAML/JSON with units)."""

from __future__ import annotations

import json
import pathlib

import numpy as np

from ct_calib_nodes.core.error_map import COMPONENT_FIELDS as ERROR_MAP_FIELDS
from ct_calib_nodes.core.geometry import STATIC_PARAM_NAMES, STATIC_PARAM_UNITS, static_to_detector_frame
from ct_calib_nodes.io.atomic import write_text_atomic
from ct_calib_nodes.io.convert import stamp_ns

STATUS_SUCCESS, STATUS_NOT_CONVERGED, STATUS_DEGENERATE, STATUS_INSUFFICIENT, STATUS_FAILED, STATUS_POOR_FIT = range(6)

#: the core results' ``outcome`` word -> metro_msgs/SolveStatus code (one vocabulary everywhere)
OUTCOME_CODES = {"success": STATUS_SUCCESS, "not_converged": STATUS_NOT_CONVERGED, "degenerate": STATUS_DEGENERATE,
                 "insufficient_data": STATUS_INSUFFICIENT, "failed": STATUS_FAILED, "poor_fit": STATUS_POOR_FIT}


def status_code(res) -> int:
    """Map a core result's ``outcome`` to metro_msgs/SolveStatus codes."""
    if res.success:
        return STATUS_SUCCESS
    code = OUTCOME_CODES.get(getattr(res, "outcome", "failed"), STATUS_FAILED)
    return STATUS_FAILED if code == STATUS_SUCCESS else code


def estimate_msg(res, model: str, stamp, frame_id: str = "ct_detector", n_rejected: int = 0):
    from metro_msgs.msg import EstimateStamped  # noqa: PLC0415

    m = EstimateStamped()
    m.header.stamp = stamp
    m.header.frame_id = frame_id
    m.model = model
    m.names = [str(n) for n in res.names]
    m.units = [str(u) for u in res.units]
    m.values = [float(v) for v in res.x]
    cov = getattr(res, "covariance_total", None)
    cov = res.covariance if cov is None else cov
    # unknown covariance (failed solve: NaN) -> empty, as the message documents; never a block of NaNs
    cov = None if cov is None else np.asarray(cov, dtype=float)
    m.covariance = [float(v) for v in cov.ravel()] if cov is not None and cov.size and np.all(np.isfinite(cov)) else []
    s = m.status
    s.code = status_code(res)
    s.message = str(res.message)
    s.iterations = int(getattr(res, "n_iter", 0))
    s.function_evaluations = int(res.nfev)
    s.observations = int(2 * res.n_obs)
    s.rejected = int(n_rejected)
    s.rms_residual = float(res.rms_px) if np.isfinite(res.rms_px) else float("nan")
    s.cost = float(res.cost) if np.isfinite(res.cost) else float("nan")
    s.condition_number = float(res.condition) if np.isfinite(res.condition) else float("inf")
    return m


def geometry_msg(res, srd_reported_m: float, sdd_reported_m: float, detector, stamp, n_rejected=0,
                 campaign_id: str | None = ""):
    from geometry_msgs.msg import Point, Vector3  # noqa: PLC0415
    from metro_msgs.msg import CtGeometry  # noqa: PLC0415

    g = CtGeometry()
    g.header.stamp = stamp
    g.header.frame_id = "ct_detector"
    g.campaign_id = str(campaign_id or "")
    g.static_estimate = estimate_msg(res, "ct_static/ferrucci2020", stamp, n_rejected=n_rejected)
    g.srd_reported_m = float(srd_reported_m)
    g.sdd_reported_m = float(sdd_reported_m)
    if res.geometry is not None:
        s, r, a = res.geometry.source_df_m, res.geometry.stage_df_m, res.geometry.axis_df
        g.source_df = Point(x=float(s[0]), y=float(s[1]), z=float(s[2]))
        g.stage_df = Point(x=float(r[0]), y=float(r[1]), z=float(r[2]))
        g.axis_df = Vector3(x=float(a[0]), y=float(a[1]), z=float(a[2]))
    g.pixel_pitch_m = float(detector.pixel_pitch_m)
    g.image_cols, g.image_rows = int(detector.cols), int(detector.rows)
    return g


def static_from_geometry_msg(msg, centres_of_m):
    """CtGeometry -> (w (13,), covariance (13,13) or None, DetectorFrameGeometry, status code)."""
    est = msg.static_estimate
    names = list(est.names)
    if names[:13] != list(STATIC_PARAM_NAMES):
        raise ValueError(f"CtGeometry parameters {names[:13]} are not the static parameters {STATIC_PARAM_NAMES}")
    vals = np.asarray(est.values, dtype=float)
    n = len(vals)
    cov = np.asarray(est.covariance, dtype=float).reshape(n, n) if len(est.covariance) == n * n else None
    w = vals[:13]
    return w, cov, static_to_detector_frame(w, centres_of_m), int(est.status.code)


def error_map_msg(em, mode: str, motions_msgs, stamp, *, campaign_id: str | None = "", geometry_stamp=None,
                  final: bool = True):
    """core.error_map.ErrorMap -> metro_msgs/ErrorMap (all fields, covariance row-major).

    ``campaign_id``: the campaign of the observations; ``geometry_stamp`` (builtin_interfaces/Time): the
    header stamp of the CtGeometry the map rests on; ``final``: the campaign is complete."""
    from geometry_msgs.msg import Vector3  # noqa: PLC0415
    from metro_msgs.msg import ErrorMap  # noqa: PLC0415

    m = ErrorMap()
    m.header.stamp = stamp
    m.header.frame_id = "ct_detector"
    m.campaign_id = str(campaign_id or "")
    if geometry_stamp is not None:
        m.geometry_stamp = geometry_stamp
    m.final = bool(final)
    m.mode = mode
    m.definition = em.definition
    m.notes = [str(n) for n in em.notes]
    m.srd_reported_m = [float(v) for v in em.srd_reported_m]
    nan = np.full(em.k, np.nan)
    for f in ERROR_MAP_FIELDS:
        setattr(m, f, [float(v) for v in em.values(f)])
        u = em.uncertainty(f)
        setattr(m, "u_" + f, [float(v) for v in (nan if u is None else u)])
    t = em.travel_direction_df
    m.travel_direction_df = Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2]))
    m.angle_travel_normal_rad = float(em.angle_travel_normal_rad)
    m.u_angle_travel_normal_rad = float(em.u_angle_travel_normal_rad)
    m.index_repeatability_rad = float(em.index_repeatability_rad or 0.0)
    m.covariance = [] if em.covariance is None else [float(v) for v in np.asarray(em.covariance).ravel()]
    m.motions = list(motions_msgs)
    return m


def error_map_from_msg(msg, name=None):
    """metro_msgs/ErrorMap (live or decoded from a recording) -> core.error_map.ErrorMap."""
    from ct_calib_nodes.core.error_map import ErrorMap  # noqa: PLC0415

    a = lambda f: np.asarray(getattr(msg, f), dtype=float)  # noqa: E731
    k = len(msg.srd_reported_m)
    cov = a("covariance")
    t = msg.travel_direction_df
    rep = float(msg.index_repeatability_rad)
    return ErrorMap(name=name or str(msg.mode), definition=str(msg.definition) or "travel",
                    srd_reported_m=a("srd_reported_m"),
                    **{f: a(f) for f in ERROR_MAP_FIELDS}, **{"u_" + f: a("u_" + f) for f in ERROR_MAP_FIELDS},
                    travel_direction_df=np.array([t.x, t.y, t.z]),
                    angle_travel_normal_rad=float(msg.angle_travel_normal_rad),
                    u_angle_travel_normal_rad=float(msg.u_angle_travel_normal_rad),
                    index_repeatability_rad=rep if rep > 0 else None,
                    covariance=cov.reshape(6 * k, 6 * k) if cov.size == 36 * k * k else None,
                    notes=tuple(str(n) for n in msg.notes))


def _plain(v):
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, (np.floating, float)):
        return float(v) if np.isfinite(v) else str(float(v))
    if isinstance(v, (np.integer,)):
        return int(v)
    return v


def write_json_atomic(path, data: dict) -> pathlib.Path:
    """Write JSON via a temp file and rename: good results are never replaced by a partial file."""
    return write_text_atomic(path, json.dumps(_plain(data), indent=1))


def static_param_table_rows(res):
    """(names, units, values, std) of a static result, for reports."""
    names = list(res.names)
    units = list(res.units) if res.units else list(STATIC_PARAM_UNITS)
    return names, units, np.asarray(res.x), np.asarray(res.std)


__all__ = ["estimate_msg", "geometry_msg", "static_from_geometry_msg", "error_map_msg", "error_map_from_msg", "write_json_atomic",
           "status_code", "stamp_ns"]
