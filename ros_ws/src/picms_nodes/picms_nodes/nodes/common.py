"""Pieces the PiCMS nodes share: the simulated cell's parameters and topic names."""
from __future__ import annotations

from ..core.cell import cell_from_seed

# Relative names (INTERFACES.md's /picms/... in the root namespace): `--ros-args -r __ns:=/cell_b`
# moves the whole cell, as for the CT cell.
IMAGE_TOPIC = "picms/{}/image_raw"
INFO_TOPIC = "picms/{}/camera_info"
JOINTS_TOPIC = "picms/stage/joint_states"
COMMAND_TOPIC = "picms/stage/command"
SMR_TOPIC = "picms/tracker/smr/{}"
POSE_TOPIC = "picms/tracker/probe_pose"
CALIBRATION_TOPIC = "picms/calibration"
DISCREPANCY_TOPIC = "picms/discrepancy"
SERVICE = "picms/run_calibration"

# every simulator node builds the same cell from these (same seed -> same truth in each process)
CELL_PARAMS = {
    "cell_seed": (8, "seed of the simulated cell (assembly, placement); all simulator nodes must agree [-]"),
    "vary_physics": (False, "randomise blur, noise, levels, lens, distances from the seed [-]"),
    # hidden physics: off by default; the solvers are never told
    "hidden_distortion": (False, "hidden: lenses distort but CameraInfo carries D = 0 [-]"),
    "distortion_k1": (-0.02, "true radial distortion k1 of the lenses [-]"),
    "tracker_scale_ppm": (0.0, "hidden: tracker length-scale error [ppm]"),
}


def truth_from_params(p: dict):
    return cell_from_seed(int(p["cell_seed"]), bool(p["vary_physics"]),
                          hidden_distortion=bool(p["hidden_distortion"]),
                          distortion_k1=float(p["distortion_k1"]),
                          tracker_scale_ppm=float(p["tracker_scale_ppm"]))
