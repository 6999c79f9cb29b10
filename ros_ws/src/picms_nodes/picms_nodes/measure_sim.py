"""Simulated PiCMS measurement sessions for the demo, the validation script and the tests.

`calibrated_cell(seed)`: a simulated cell (varied physics), its Pixel Probe calibration from a
simulated Appendix-A session (the same pipeline as picms_calibrate_offline) and the Probe built
from that calibration only. `FullFirstFrame`: a SimCell whose first settled state renders full
frames (part finding needs the whole part) and later ones only a window around X* (targeting
needs only the feature near X*): the renderer's cost, not the measurement, is what it saves.
Truth (for comparisons only) stays in the returned objects; the measuring code sees the Probe,
the part program and the cell's images and readings.
"""
from __future__ import annotations

import pathlib

import numpy as np

from .core import camera, campaign, cell, cellio, scenes, targeting
from .core.pipeline import calibrate_recording
from .io.files import calibration_dict

CONFIG = pathlib.Path(__file__).resolve().parents[1] / "config"


def config_file(name: str) -> pathlib.Path:
    p = CONFIG / name
    if p.is_file():
        return p
    try:
        from ament_index_python.packages import get_package_share_directory
        return pathlib.Path(get_package_share_directory("picms_nodes")) / "config" / name
    except Exception:       # noqa: BLE001 (not installed: source tree only)
        return p


def calibrated_cell(seed: int, **physics_overrides):
    """(truth, probe, calibration dict) of a freshly calibrated simulated cell."""
    rng = np.random.default_rng(seed)
    truth = cell.make_cell(rng, cell.make_physics(rng, **physics_overrides))
    rec, _ = campaign.simulate_session(truth, rng)
    res, _ = calibrate_recording(rec)
    cal = calibration_dict(res)
    probe = targeting.Probe.from_calibration_yaml(cal, rec.camera_info)
    return truth, probe, cal


class FullFirstFrame:
    """CellIO wrapper of a SimCell: full frames until the first settle, then a window."""

    def __init__(self, sim: cellio.SimCell, window_px: int = 100):
        self.sim = sim
        self.window_px = window_px
        sim.window_px = None
        self.camera_names = sim.camera_names
        self.camera_info = sim.camera_info
        self.resolution_m = sim.resolution_m

    def move_and_settle(self, q_target, *, timeout_s: float = 30.0):
        s = self.sim.move_and_settle(q_target, timeout_s=timeout_s)
        self.sim.window_px = self.window_px
        return s

    def current(self):
        s = self.sim.current()
        self.sim.window_px = self.window_px
        return s


def placed_part(scene: str, rng, *, offset_m=2e-4, tilt_rad=0.03):
    """A part placed near the placement reading 0 (random offset, tilt, in-plane rotation)."""
    pos = rng.uniform(-offset_m, offset_m, 3)
    tilt = rng.uniform(-tilt_rad, tilt_rad, 2)
    rot = float(rng.uniform(-np.pi, np.pi))
    return scenes.make_part(scene, pos, tilt, rot)


def truth_probe(truth, sigma_px: float = 0.05) -> targeting.Probe:
    """A Probe made from a simulated cell's TRUE geometry (cameras, stage squareness, tracker
    orientation), with image points of stated sd `sigma_px`: for triangulation tests and benchmarks
    that leave the calibration out. Never for a measurement (it is truth)."""
    names = [c.name for c in truth.cameras]
    return targeting.Probe(
        camera_names=names, intrinsics={c.name: c.true_intrinsics for c in truth.cameras},
        R_stage_camera={c.name: c.pose.R_stage_camera for c in truth.cameras},
        p_stage_centre={c.name: c.pose.p_stage_centre for c in truth.cameras},
        u_rotation_rad={n: np.zeros(3) for n in names}, u_p_stage_centre={n: np.zeros(3) for n in names},
        xstar_px={c.name: camera.project(c.pose, c.true_intrinsics, np.zeros(3))[0] for c in truth.cameras},
        u_xstar_px={n: np.full(2, sigma_px) for n in names},
        squareness=np.array(list(cell.squareness_truth(truth.A_travel).values())), u_squareness=np.zeros(3),
        p_constellation=np.zeros(3), cov_p_constellation=np.zeros((3, 3)), constellation={},
        R_tracker_stage=truth.R_tracker_stage)
