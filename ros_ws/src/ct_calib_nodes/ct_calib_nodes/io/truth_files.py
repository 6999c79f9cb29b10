"""Files a simulator writes about its own truth: for tests, and a simulated independent reference
measurement (what a laser interferometer and electronic level would give) for report delta plots.
Solvers never read these."""

from __future__ import annotations

import dataclasses
import pathlib

import numpy as np

from ct_calib_nodes.core.scenario import CampaignTruth
from ct_calib_nodes.io.atomic import write_text_atomic
from ct_calib_nodes.io.ct_files import write_yaml


def write_truth(path, truth: CampaignTruth, settings, projections_per_position: int) -> pathlib.Path:
    """Write the simulation truth as YAML (SI units)."""
    settings_dict = {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(settings).items()}
    data = {
        "units": "SI",
        "warning": "simulation truth: for tests and reports only, never an input of a solver",
        "static_w": [float(v) for v in truth.static_w],
        "srd_reported_m": [float(v) for v in truth.srd_reported_m],
        "sdd_reported_m": float(truth.sdd_reported_m),
        "motions": [[float(v) for v in row] for row in truth.motions],
        "travel_direction_df": [float(v) for v in truth.travel_direction_df],
        "stage_errors": None if truth.stage_errors is None else [[float(v) for v in row] for row in truth.stage_errors],
        "stage_errors_columns": ["positioning_m (+ = travelled less than indexed)", "straightness_x_m",
                                 "straightness_y_m", "pitch_rad", "yaw_rad", "roll_rad"],
        "projections_per_position": int(projections_per_position),
        "render_settings": settings_dict,
    }
    return write_yaml(path, data)


def read_truth(path) -> CampaignTruth:
    import yaml  # noqa: PLC0415

    d = yaml.safe_load(pathlib.Path(path).read_text())
    errors = d.get("stage_errors")
    return CampaignTruth(static_w=np.asarray(d["static_w"]), srd_reported_m=np.asarray(d["srd_reported_m"]),
                         motions=np.asarray(d["motions"]), sdd_reported_m=float(d["sdd_reported_m"]),
                         travel_direction_df=np.asarray(d.get("travel_direction_df", [0.0, 0.0, 1.0])),
                         stage_errors=None if errors is None else np.asarray(errors))


def write_reference_error_map(path, truth: CampaignTruth) -> pathlib.Path:
    """The true error map as a reference CSV (format of core.report.read_reference_error_map):
    measured along the stage travel, as a laser interferometer would, with the project's sign."""
    em = truth.error_map("travel")
    cols = ["positioning_m", "straightness_x_m", "straightness_y_m", "pitch_rad", "yaw_rad", "roll_rad"]
    lines = ["# simulated independent reference: the simulator's true stage error map (SI units), measured",
             "# along the stage travel (ISO 230-1 geometry); positioning + = travelled less than indexed",
             "srd_m," + ",".join(cols)]
    for k, srd in enumerate(truth.srd_reported_m):
        lines.append(f"{srd:.9g}," + ",".join(f"{em[c][k]:.9g}" for c in cols))
    return write_text_atomic(path, "\n".join(lines) + "\n")
