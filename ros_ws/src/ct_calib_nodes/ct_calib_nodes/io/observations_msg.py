"""metro_msgs/SphereObservationArray <-> arrays."""

from __future__ import annotations

import numpy as np

from ct_calib_nodes.io.convert import MessageError, stamp_ns

ACCEPTED = 0


def frame_observations(msg, id_to_index: dict) -> tuple:
    """SphereObservationArray -> (stamp_ns, alpha, srd, sphere_index (Q,), uv (Q,2), sigma (Q,), n_rejected,
    minor_axis (Q,) or None, systematic (Q, 2)).

    ``systematic`` is the detector's shared systematic pattern (SphereObservation
    ``systematic_col_px`` / ``systematic_row_px``; zero for messages without those fields or with a
    non-finite value).

    ``minor_axis`` holds the fitted shadow ellipses' semi-minor axes [px] (the solvers then model
    the ellipse centre); None when any accepted observation lacks a finite positive one.

    Only ACCEPTED observations with a known sphere id are returned; raises MessageError on NaN
    values, unknown ids or duplicate ids in one frame.
    """
    alpha, srd = float(msg.rotary_angle_rad), float(msg.srd_reported_m)
    if not (np.isfinite(alpha) and np.isfinite(srd) and srd > 0):
        raise MessageError(f"bad stage reading in observations: alpha={alpha}, srd={srd}")
    idx, uv, sig, minor, sys_, rejected = [], [], [], [], [], 0
    for o in msg.observations:
        if int(o.flag) != ACCEPTED:
            rejected += 1
            continue
        if int(o.sphere_id) not in id_to_index:
            raise MessageError(f"sphere id {o.sphere_id} is not in the reference object")
        c, r, s = float(o.col_px), float(o.row_px), float(o.sigma_px)
        if not (np.isfinite(c) and np.isfinite(r)):
            raise MessageError(f"non-finite centre for sphere {o.sphere_id}")
        idx.append(id_to_index[int(o.sphere_id)])
        uv.append((c, r))
        sig.append(s if np.isfinite(s) and s > 0 else -1.0)
        minor.append(float(o.semi_minor_px))
        sc, sr = float(getattr(o, "systematic_col_px", 0.0)), float(getattr(o, "systematic_row_px", 0.0))
        sys_.append((sc, sr) if np.isfinite(sc) and np.isfinite(sr) else (0.0, 0.0))
    if len(set(idx)) != len(idx):
        raise MessageError("a sphere id appears twice in one frame")
    minor = np.asarray(minor, dtype=float)
    usable = minor.size > 0 and bool(np.all(np.isfinite(minor) & (minor > 0)))
    return (stamp_ns(msg.header.stamp), alpha, srd, np.asarray(idx, dtype=np.int64),
            np.asarray(uv, dtype=float).reshape(-1, 2), np.asarray(sig, dtype=float), rejected,
            minor if usable else None, np.asarray(sys_, dtype=float).reshape(-1, 2))
