"""CalibrationResult -> metro_msgs/PicmsCalibration (node layer only)."""
from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Point
from metro_msgs.msg import PicmsCalibration, PicmsCameraExtrinsics, SolveStatus

from ..core.calibrate import is_poor_fit


def _pt(v):
    return Point(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def calibration_msg(res, stamp, file_path="") -> PicmsCalibration:
    m = PicmsCalibration()
    m.header.stamp = stamp
    m.header.frame_id = "tracker"
    m.status = SolveStatus(code=SolveStatus.POOR_FIT if is_poor_fit(res) else SolveStatus.SUCCESS, message=res.message)
    m.camera_names = sorted(res.pixels)
    m.pixels = [float(v) for c in m.camera_names for v in res.pixels[c]]
    m.u_pixels = [float(v) for c in m.camera_names for v in res.u_pixels[c]]
    m.p_tracker = _pt(res.p_tracker)
    m.cov_p_tracker = [float(v) for v in np.ravel(res.cov_p_tracker)]
    m.stage_reading = [float(v) for v in res.stage_reading]
    m.p_constellation = _pt(res.p_constellation)
    m.constellation_names = list(res.constellation)
    m.constellation = [_pt(v) for v in res.constellation.values()]
    for name in m.camera_names:
        c = res.cameras[name]
        e = PicmsCameraExtrinsics()
        e.name = name
        e.r_stage_camera = [float(v) for v in np.ravel(c.R_stage_camera)]
        e.p_stage_centre = _pt(c.p_stage_centre)
        e.u_rotation_rad = [float(v) for v in c.u_rotation_rad]
        e.u_p_stage_centre = [float(v) for v in c.u_p_stage_centre]
        e.reprojection_rms_px = float(c.reprojection_rms_px)
        m.cameras.append(e)
    m.r_tracker_stage = [float(v) for v in np.ravel(res.R_tracker_stage)]
    m.p_tracker_stage = _pt(res.p_tracker_stage)
    m.squareness_rad = [float(res.squareness_rad[k]) for k in ("xy", "xz", "yz")]
    m.u_squareness_rad = [float(res.u_squareness_rad[k]) for k in ("xy", "xz", "yz")]
    m.file_path = str(file_path)
    return m


def failure_msg(message: str, stamp, code=SolveStatus.FAILED) -> PicmsCalibration:
    m = PicmsCalibration()
    m.header.stamp = stamp
    m.header.frame_id = "tracker"
    m.status = SolveStatus(code=code, message=message)
    return m
