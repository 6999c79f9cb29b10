"""One calibration path for every front door (node, offline MCAP, tests).

`calibrate_recording(rec)` takes a `campaign.Recording` (what INTERFACES.md gives), keeps
frames and tracker readings from settled periods only, detects the disc in every settled
frame, and calls `calibrate.calibrate`. Frames that cannot be used are listed with the reason.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .calibrate import CalibrationError, CalibrationResult, assign, calibrate, in_window, settled_windows
from .detect import DetectionError, detect_disc


@dataclass
class PipelineReport:
    n_frames: int = 0
    n_settled_frames: int = 0
    n_detected: int = 0
    skipped: list = field(default_factory=list)      # (stamp_ns, camera, reason)
    windows: list = field(default_factory=list)


def detect_settled_frames(frames, camera_info, windows, report: PipelineReport):
    """Detections [(stamp_ns, camera, DiscDetection)] of frames inside settled windows.

    frames: iterable of (stamp_ns, camera, image); images are dropped after detection.
    """
    out = []
    for stamp, cam, img in frames:
        report.n_frames += 1
        if in_window(stamp, windows) < 0:
            continue
        report.n_settled_frames += 1
        intr = camera_info.get(cam)
        if intr is None:
            report.skipped.append((stamp, cam, "no CameraInfo for this camera"))
            continue
        try:
            out.append((stamp, cam, detect_disc(img, intr)))
            report.n_detected += 1
        except DetectionError as exc:
            report.skipped.append((stamp, cam, str(exc)))
    return out


def calibrate_detections(rec, detections, report: PipelineReport | None = None) -> CalibrationResult:
    """Calibrate from detections [(stamp_ns, camera, DiscDetection)] made as frames arrived
    (live node); only those inside settled windows are used."""
    report = report or PipelineReport()
    windows = settled_windows(rec.joint_stamps_ns, rec.joint_positions)
    report.windows = windows
    if not windows:
        raise CalibrationError("the stage never settled: no period without motion in joint_states "
                               f"({len(rec.joint_stamps_ns)} readings)")
    dets = [d for d in detections if in_window(d[0], windows) >= 0]
    if not dets:
        raise CalibrationError("no disc found in any settled frame")
    return calibrate(assign(windows, dets, rec.tracker), rec.camera_info, rec.cell)


def calibrate_recording(rec, frames=None) -> tuple[CalibrationResult, PipelineReport]:
    """Calibrate from a Recording (frames may be given as a separate iterable, e.g. streamed)."""
    report = PipelineReport()
    windows = settled_windows(rec.joint_stamps_ns, rec.joint_positions)
    report.windows = windows
    if not windows:
        raise CalibrationError("the stage never settled: no period without motion in joint_states "
                               f"({len(rec.joint_stamps_ns)} readings)")
    dets = detect_settled_frames(rec.frames if frames is None else frames, rec.camera_info, windows, report)
    no_info = sorted({c for _, c, r in report.skipped if r.startswith("no CameraInfo")})
    if no_info:
        raise CalibrationError(f"CameraInfo missing for {no_info}: their images cannot be undistorted "
                               "(intrinsic calibration K, D required)")
    if not dets:
        why = sorted({r for _, _, r in report.skipped})
        raise CalibrationError(f"no disc found in any settled frame ({report.n_settled_frames} settled of "
                               f"{report.n_frames} frames); reasons: {why}")
    stations = assign(windows, dets, rec.tracker)
    return calibrate(stations, rec.camera_info, rec.cell), report
