"""CT results -> calibration-history records (io/history.py), without ROS.

Kinds written by the CT cell:

- ``ct_geometry``: the static geometry (13 parameters + terms); quantities are
  the parameters with their standard uncertainties (names of core/geometry.py
  STATIC_PARAM_NAMES, SI units) and ``rms_px``;
- ``ct_error_map``: one error map (mode ``multi`` or ``single``, definition
  ``travel``); quantities ``<component>`` at ``position`` k (0 = the reference
  position, value and u 0 by definition), plus ``srd_reported_m``.

The result JSON keeps the whole result (``to_dict()``, with covariances), and
for live solves the published message (``ros_msg``: type and CDR bytes in
base64) so a restarted node re-publishes exactly what it published.
"""

from __future__ import annotations

import base64
import math
import pathlib

from ct_calib_nodes.io.history import Input, Quantity, SolveRecord

KIND_GEOMETRY = "ct_geometry"
KIND_ERROR_MAP = "ct_error_map"
COMPONENTS = ("positioning_m", "straightness_x_m", "straightness_y_m", "pitch_rad", "yaw_rad", "roll_rad")


def status_word(res) -> str:
    """The one outcome vocabulary: ``success`` only for a usable result."""
    if getattr(res, "success", False):
        return "success"
    word = str(getattr(res, "outcome", "failed") or "failed")
    return "failed" if word == "success" else word


def yaml_inputs(files: dict) -> list:
    """{role: path} of the YAML files -> [Input] with their sha256 (roles get a ``_yaml`` suffix)."""
    return [Input.file(role if role.endswith("_yaml") else role + "_yaml", path) for role, path in files.items() if path]


def _type_hash(type_name: str) -> str:
    try:
        from ct_calib_nodes.io.mcap_io import type_hash  # noqa: PLC0415
        return type_hash(type_name)
    except Exception:  # noqa: BLE001 - no ROS installation: no hash, no check
        return ""


def ros_msg_blob(type_name: str, cdr: bytes) -> dict:
    """The published message as stored: type, RIHS01 type hash (a later message definition with other
    fields must not decode these bytes), CDR bytes in base64."""
    return {"type": type_name, "type_hash": _type_hash(type_name), "cdr_b64": base64.b64encode(bytes(cdr)).decode("ascii")}


def ros_msg_bytes(result: dict, type_name: str) -> bytes | None:
    """The stored CDR bytes of a message of ``type_name``, or None when absent or stored under another
    definition of the type (type hash differs)."""
    blob = (result or {}).get("ros_msg")
    if not blob or blob.get("type") != type_name:
        return None
    stored, now = blob.get("type_hash", ""), _type_hash(type_name)
    if stored and now and stored != now:
        return None
    return base64.b64decode(blob["cdr_b64"])


def geometry_record(res, *, cell: str, source: str, campaign_id=None, inputs=(), data_start_ns=None,
                    data_end_ns=None, final: bool = True, extra: dict | None = None) -> SolveRecord:
    std = getattr(res, "std", None)
    std = [] if std is None else list(std)
    names, units, x = list(res.names), list(res.units), list(res.x)
    q = [Quantity(name=str(n), value=float(v), u=(float(std[i]) if i < len(std) else None), unit=str(u))
         for i, (n, u, v) in enumerate(zip(names, units, x))]
    q.append(Quantity(name="rms_px", value=float(res.rms_px), unit="px"))
    result = {"static": res.to_dict()}
    result.update(extra or {})
    return SolveRecord(cell=cell, kind=KIND_GEOMETRY, status=status_word(res), message=str(res.message),
                       result=result, source=source, campaign_id=campaign_id, final=final,
                       data_start_ns=data_start_ns, data_end_ns=data_end_ns, inputs=list(inputs), quantities=q)


def error_map_record(em, mode: str, *, status: str, message: str, cell: str, source: str, campaign_id=None,
                     inputs=(), data_start_ns=None, data_end_ns=None, final: bool = True, positions=None,
                     extra: dict | None = None) -> SolveRecord:
    q = []
    for i in range(em.k):
        q.append(Quantity(name="srd_reported_m", value=float(em.srd_reported_m[i]), unit="m", position=i))
    for f in COMPONENTS:
        v, u = em.values(f), em.uncertainty(f)
        unit = "m" if f.endswith("_m") else "rad"
        for i in range(em.k):
            q.append(Quantity(name=f, value=float(v[i]), u=None if u is None else float(u[i]), unit=unit, position=i))
    d = em.to_dict()
    if em.covariance is not None:
        d["covariance"] = em.covariance
    result = {"mode": mode, "error_map": d, "positions": list(positions or range(em.k))}
    result.update(extra or {})
    return SolveRecord(cell=cell, kind=KIND_ERROR_MAP, status=status, message=message, result=result, source=source,
                       campaign_id=campaign_id, final=final, data_start_ns=data_start_ns, data_end_ns=data_end_ns,
                       inputs=list(inputs), quantities=q)


def map_status(motions: dict) -> tuple[str, str]:
    """Status of an error map from its positions' MotionResults: success only when all are."""
    bad = [(k, m) for k, m in sorted(motions.items()) if not m.success]
    if not motions:
        return "insufficient_data", "no position solved"
    if bad:
        k, m = bad[0]
        return status_word(m), f"{len(bad)} of {len(motions)} position(s) not usable; position {k + 1}: {m.message}"
    return "success", f"{len(motions)} position(s) solved"


def finite(x) -> bool:
    try:
        return math.isfinite(float(x))
    except (TypeError, ValueError):
        return False


def incomplete_positions(frames_per_position) -> str | None:
    """A warning when stage positions hold different numbers of frames (a recorder that started late,
    frames lost), else None."""
    n = list(frames_per_position)
    if len(n) < 2 or len(set(n)) == 1:
        return None
    full = max(n)
    short = [(k + 1, m) for k, m in enumerate(n) if m < full]
    return (f"incomplete stage positions: frames per position {n}; position(s) "
            + ", ".join(f"{k} ({m} of {full})" for k, m in short)
            + " lack frames (a recorder started late, or frames were lost)")


def campaign_id_of(cell, res) -> str | None:
    """``<cell>@<first frame stamp ns>`` of an offline solve (the id the live nodes give the same campaign:
    io/campaign_guard.py), None without frames."""
    from ct_calib_nodes.io.history import cell_name  # noqa: PLC0415

    stamps = [t for p in res.acc.positions for t in p.stamps_ns] if getattr(res, "acc", None) is not None else []
    return f"{cell_name(cell)}@{min(stamps)}" if stamps else None


def offline_records(res, *, recording, files: dict, cell: str, source: str = "offline", campaign_id=None,
                    recording_hash: str | None = None) -> list:
    """History records of an offline solve (offline.OfflineResult): the static geometry and the
    travel-definition error maps, linked to the recording (path + content hash) and the YAML files;
    the maps name the geometry they rest on (``upstream`` input, filled in by :func:`store_offline`)."""
    rec_input = Input(role="recording", path=str(pathlib.Path(recording).resolve()), sha256=recording_hash)
    if recording_hash is None:
        rec_input = Input.file("recording", recording)
    inputs = [rec_input] + yaml_inputs(files)
    stamps = [t for p in res.acc.positions for t in p.stamps_ns] if res.acc is not None else []
    t0, t1 = (min(stamps), max(stamps)) if stamps else (None, None)
    campaign_id = campaign_id or campaign_id_of(cell, res) or (rec_input.sha256[:16] if rec_input.sha256 else None)
    out = []
    if res.static is not None:
        p0 = res.acc.positions[0]
        out.append(geometry_record(res.static, cell=cell, source=source, campaign_id=campaign_id, inputs=inputs,
                                   data_start_ns=min(p0.stamps_ns), data_end_ns=max(p0.stamps_ns),
                                   extra={"frames": p0.n_frames, "srd_reported_m": p0.srd_reported_m,
                                          "problems": list(res.problems)}))
    for mode, by_def in res.maps.items():
        ks = res.map_positions[mode]
        status, text = map_status({k: res.motions[mode][k] for k in ks[1:]})
        out.append(error_map_record(by_def["travel"], mode, status=status, message=text, cell=cell, source=source,
                                    campaign_id=campaign_id, inputs=list(inputs), data_start_ns=t0,
                                    data_end_ns=t1, positions=ks))
    return out


def store_offline(history, records: list) -> list:
    """Store the records of one offline solve; the maps get the geometry's uid as their upstream input."""
    stored = []
    geo = None
    for r in records:
        if r.kind == KIND_ERROR_MAP and geo is not None:
            r.inputs.append(Input(role="upstream", ref_uid=geo.uid))
        s = history.record(r)
        if r.kind == KIND_GEOMETRY:
            geo = s
        stored.append(s)
    return stored
