"""picms_cell.yaml (read) and picms_calibration.yaml (write), keys as INTERFACES.md fixes them.

Writing is atomic (temporary file, then rename), and only a successful calibration is ever
written: a failed run never touches a good file.
"""
from __future__ import annotations

import pathlib

import numpy as np
import yaml

from ct_calib_nodes.io.atomic import replace_atomically

from ..core.calibrate import CalibrationResult


def read_cell(path) -> dict:
    """picms_cell.yaml as a dict, checked. Raises ValueError naming what is missing."""
    p = pathlib.Path(path)
    try:
        d = yaml.safe_load(p.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"cannot read picms_cell.yaml at {p}: {exc}") from exc
    if not isinstance(d, dict):
        raise ValueError(f"{p}: not a YAML mapping")
    tr = d.get("tracker")
    if not isinstance(tr, dict) or not isinstance(tr.get("constellation"), list) or not tr.get("probe_smr"):
        raise ValueError(f"{p}: tracker.constellation (list) and tracker.probe_smr are required")
    res = (d.get("stage") or {}).get("resolution")
    if res is None or not float(res) > 0:
        raise ValueError(f"{p}: stage.resolution (m, > 0) is required")
    return d


def _l(a, nd=9):
    return np.round(np.asarray(a, float), nd).tolist()


def calibration_dict(res: CalibrationResult) -> dict:
    """The picms_calibration.yaml content (INTERFACES.md keys, plus documented extras)."""
    cams = {}
    for name, c in sorted(res.cameras.items()):
        cams[name] = {"R_stage_camera": _l(c.R_stage_camera, 12), "p_stage_centre": _l(c.p_stage_centre),
                      "u_rotation_rad": _l(c.u_rotation_rad, 12), "u_p_stage_centre": _l(c.u_p_stage_centre, 10),
                      "reprojection_rms_px": round(float(c.reprojection_rms_px), 5)}
    return {
        "units": "SI",
        "probe_point": {
            "pixels": {k: _l(v, 5) for k, v in sorted(res.pixels.items())},
            "u_pixels": {k: _l(v, 5) for k, v in sorted(res.u_pixels.items())},
            "pixel_definition": "image of the SMR* centre (silhouette cone axis), raw pixels, OpenCV convention",
            "p_tracker": _l(res.p_tracker), "stage_reading": _l(res.stage_reading),
            "cov_p_tracker": _l(res.cov_p_tracker, 16),
            "p_constellation": _l(res.p_constellation), "cov_p_constellation": _l(res.cov_p_constellation, 16),
            "constellation": {k: _l(v) for k, v in res.constellation.items()},
        },
        "cameras": cams,
        "stage": {"R_tracker_stage": _l(res.R_tracker_stage, 12), "p_tracker_stage": _l(res.p_tracker_stage),
                  "squareness_rad": {k: float(np.round(v, 10)) for k, v in res.squareness_rad.items()},
                  "u_squareness_rad": {k: float(np.round(v, 10)) for k, v in res.u_squareness_rad.items()},
                  "tracker_vs_encoder_scale_ppm": _l(res.scale_ppm, 2),
                  "u_tracker_vs_encoder_scale_ppm": _l(res.u_scale_ppm, 2)},
        "quality": {"tracker_sigma_m": float(res.tracker_sigma_m), "rigid_fit_rms_m": float(res.rigid_fit_rms_m),
                    "camera_chi2_dof": float(res.chi2_dof), "n_stations": int(res.n_stations),
                    "message": res.message},
    }


def write_calibration(res: CalibrationResult, path) -> pathlib.Path:
    """Write picms_calibration.yaml atomically; refuse a failed result (nothing is written)."""
    if not res.success:
        raise ValueError(f"calibration failed ({res.message}): {path} left untouched")
    def write(tmp):
        with open(tmp, "w") as fh:
            yaml.safe_dump(calibration_dict(res), fh, sort_keys=False, width=120)
    return replace_atomically(path, write)
