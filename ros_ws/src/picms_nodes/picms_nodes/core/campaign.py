"""A simulated calibration session as a recording: only what INTERFACES.md gives.

`Recording` holds the raw data a solver may use (frames with stamps, CameraInfo intrinsics,
stage joint_states, tracker readings with their own stamps, picms_cell.yaml contents).
`simulate_session` drives the simulated stage through the Appendix A pattern (X* at the
reference, then +-X, +-Y, +-Z), renders frames while settled and some during moves, and
returns the recording with the truth kept apart.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .camera import Intrinsics
from .cell import CAMERA_NAMES, CellTruth
from .instruments import StageSim, smr_position_stage, tracker_reading
from .render import render_frame


@dataclass
class Recording:
    """Raw data of a session. Stamps in ns. Frames as (stamp_ns, camera_name, image)."""
    cell: dict
    camera_info: dict = field(default_factory=dict)            # camera name -> Intrinsics
    frames: list = field(default_factory=list)
    joint_stamps_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    joint_positions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    tracker: list = field(default_factory=list)                # (stamp_ns, smr name, (3,) m)


def default_cell_yaml(resolution_m: float = 6.0e-6) -> dict:
    return {"units": "SI",
            "tracker": {"constellation": ["smr_1", "smr_2", "smr_3", "smr_4", "smr_5"],
                        "probe_smr": "smr_star", "probe_smr_diameter": 0.0127},
            "stage": {"resolution": resolution_m}}


def appendix_a_pattern(step_xy_m: float = 0.006, step_z_m: float = 0.004) -> np.ndarray:
    """Stage targets (N, 3): reference 0, then +-X, +-Y, +-Z (paper, Appendix A.1)."""
    pts = [np.zeros(3)]
    for k, s in ((0, step_xy_m), (1, step_xy_m), (2, step_z_m)):
        for sign in (1, -1):
            q = np.zeros(3)
            q[k] = sign * s
            pts.append(q)
    return np.array(pts)


@dataclass
class SessionTruth:
    truth: CellTruth
    station_q_true: np.ndarray       # (N, 3) true stage positions at the stations
    x_star_px: dict                  # camera -> (2,) true image of X* (true intrinsics)


def simulate_session(truth: CellTruth, rng, *, pattern=None, dwell_s: float = 2.5,
                     frames_per_station: int = 1, tracker_rate_hz: float = 60.0,
                     joint_rate_hz: float = 50.0, mid_move_frames: int = 2,
                     stage: StageSim | None = None, render=True, settle_wait_s: float = 0.8, lazy: bool = False):
    """Run the calibration session on the simulated cell; return (Recording, SessionTruth).

    Frames are rendered `settle_wait_s` after each move ends (then every 0.3 s) and, for the
    first `mid_move_frames` moves, once in the middle of the move (a recording made by real
    software has such frames). Tracker readings go round-robin over the constellation and the
    SMR* all the time (moving or not).

    lazy: ``rec.frames`` is a one-pass generator that renders each frame as it is read (the same frames
    and noise draws, if nothing else draws from ``rng`` first), so a long session need not fit in memory
    (16 frames per station of a 109-station session are ~20 GB of images).
    """
    pattern = appendix_a_pattern() if pattern is None else np.asarray(pattern, float)
    st = stage or StageSim(resolution_m=truth.physics.stage_resolution_m)
    cell = default_cell_yaml(st.resolution_m)
    names = list(cell["tracker"]["constellation"]) + [cell["tracker"]["probe_smr"]]
    rec = Recording(cell=cell, camera_info={c.name: c.info_intrinsics for c in truth.cameras})
    t = 0.5
    frame_times = []        # (t, settled?)
    q_true = []
    for i, target in enumerate(pattern):
        t_end = st.command(target, t)
        if i > 0 and i <= mid_move_frames and t_end - t > 0.2:
            frame_times.append(0.5 * (t + t_end))
        for k in range(frames_per_station):
            frame_times.append(t_end + settle_wait_s + 0.3 * k)
        q_true.append(st.quantise(target))
        t = t_end + dwell_s
    t_stop = t
    # joint_states continuously, plus one reading at each frame's stamp (INTERFACES: an image
    # and the stage reading that belongs to it carry the identical stamp)
    ts = np.unique(np.concatenate([np.arange(0.0, t_stop, 1.0 / joint_rate_hz), np.round(np.array(frame_times) * 1e9) / 1e9]))
    rec.joint_stamps_ns = np.round(ts * 1e9).astype(np.int64)
    rec.joint_positions = np.array([st.encoder(x) for x in ts])
    # tracker: round-robin, own stamps
    tt = np.arange(0.01, t_stop, 1.0 / tracker_rate_hz)
    for k, x in enumerate(tt):
        name = names[k % len(names)]
        p = smr_position_stage(truth, name, st.true_q(x), cell["tracker"]["probe_smr"])
        probe = name == cell["tracker"]["probe_smr"]
        stamp = int(round((x + truth.physics.tracker_lag_s) * 1e9))     # hidden clock lag
        rec.tracker.append((stamp, name, tracker_reading(truth, p, rng, probe=probe)))
    def frames():
        for x in frame_times:
            q = st.true_q(x)
            stamp = int(round(x * 1e9))
            for j, cam in enumerate(truth.cameras):
                if render:
                    img = render_frame(truth.camera_pose_at(j, q, x), cam.true_intrinsics, truth.physics, rng,
                                       sphere_stage=truth.smr_star_stage, nest_axis_stage=truth.nest_axis_stage)
                else:
                    img = None
                yield stamp, cam.name, img
    if lazy:
        rec.frames = frames()
    else:
        rec.frames.extend(frames())
    from .camera import project
    xs = {c.name: project(c.pose, c.true_intrinsics, truth.smr_star_stage)[0] for c in truth.cameras}
    return rec, SessionTruth(truth, np.array(q_true), xs)
