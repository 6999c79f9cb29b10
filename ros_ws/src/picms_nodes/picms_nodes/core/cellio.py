"""The cell as targeting and measurement see it: move, wait for settled readings, grab.

`CellIO` is the protocol (contract with the measurement half, briefs/picms_iface.md): only
what INTERFACES.md gives (frames, CameraInfo intrinsics, encoder readings, tracker SMR
readings, the stage resolution of picms_cell.yaml). `SimCell` implements it in-process on a
simulated clock with the project's simulators (StageSim: quantised moves, trapezoid profile,
ringing; render_frame: true perspective, true lens, blur, noise; tracker readings with their
stated noise). Settling is decided from the encoder readings alone, as a real controller
does: every axis within `settle_tol_m` of its running value for `settle_hold_s`.

`SimCell.truth` and `SimCell.part` are for tests only: no measuring code may read them.
The ROS implementation (`nodes/ros_cell.py`, RosCell) implements the same protocol over the
INTERFACES.md topics.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from .camera import Intrinsics, project
from .cell import CellTruth, Physics
from .instruments import StageSim, smr_position_stage, tracker_reading
from .scenes import PlanarPart


@dataclass
class Settled:
    """One settled stage state and what the instruments gave while settled."""
    q: np.ndarray                                  # (3,) encoder reading, m (mean over the settled window)
    stamp_ns: int
    images: dict = field(default_factory=dict)     # camera name -> 2-D uint8/uint16 frame taken while settled
    tracker: dict = field(default_factory=dict)    # SMR name -> (3,) mean tracker reading while settled, m
    tracker_n: dict = field(default_factory=dict)  # readings averaged per SMR
    q_sd: np.ndarray | None = None                 # (3,) sd of the encoder readings in the window, m (extra)
    windows: dict = field(default_factory=dict)    # camera -> (x0, y0, w, h) rendered window (SimCell, extra)


class SettleTimeout(TimeoutError):
    """The stage did not settle within the timeout (message gives the last motion seen)."""


@runtime_checkable
class CellIO(Protocol):
    camera_names: list
    camera_info: dict                              # camera name -> camera.Intrinsics
    resolution_m: float                            # stage step (picms_cell.yaml)

    def move_and_settle(self, q_target: np.ndarray, *, timeout_s: float = 30.0) -> Settled: ...

    def current(self) -> Settled: ...


def settle_detector(tol_m: float, hold_n: int):
    """A streaming settled test on encoder readings: feed (3,) readings; returns True once the
    last `hold_n` readings all lie within tol_m of the first of them on every axis."""
    buf: list = []

    def feed(q) -> bool:
        q = np.asarray(q, float)
        if buf and np.any(np.abs(q - buf[0]) > tol_m):
            buf.clear()
        buf.append(q)
        if len(buf) > hold_n:
            del buf[0]
            # the window's anchor moved: re-check the remaining readings against the new first
            while len(buf) > 1 and np.any(np.abs(np.array(buf) - buf[0]).max(0) > tol_m):
                del buf[0]
        return len(buf) >= hold_n
    feed.buffer = buf
    return feed


class SimCell:
    """In-process simulated cell on a simulated clock (see module doc).

    truth, rng, part: the cell, the noise generator, the planar part in view (or None).
    physics: render with this Physics instead of truth.physics (e.g. other blur or noise; the
    geometry stays truth's).
    stage: a StageSim (default: the cell's resolution, standard dynamics).
    window_px: render only a (2 w + 1) square window per camera around the true image of X*
    (same physics inside; the rest of the frame is the flat mean background level, no noise).
    Saves ~90 % of the render time in tests; None renders full frames.
    show_smr: draw the SMR* in its nest too (calibration scenes).
    """

    def __init__(self, truth: CellTruth, rng, part: PlanarPart | None = None, *, physics: Physics | None = None,
                 stage: StageSim | None = None, window_px: int | None = None, joint_rate_hz: float = 100.0,
                 tracker_rate_hz: float = 60.0, tracker_window_s: float = 0.5, settle_tol_m: float = 2.5e-7,
                 settle_hold_s: float = 0.3, show_smr: bool = False,
                 constellation: tuple | None = None):
        self.truth = truth
        self.part = part
        self.rng = rng
        self.physics = physics or truth.physics
        self.stage = stage or StageSim(resolution_m=truth.physics.stage_resolution_m)
        self.window_px = window_px
        self.joint_dt = 1.0 / joint_rate_hz
        self.tracker_dt = 1.0 / tracker_rate_hz
        self.tracker_window_s = tracker_window_s
        self.settle_tol_m = settle_tol_m
        self.settle_hold_n = max(2, int(round(settle_hold_s / self.joint_dt)))
        self.show_smr = show_smr
        self.camera_names = [c.name for c in truth.cameras]
        self.camera_info = {c.name: c.info_intrinsics for c in truth.cameras}
        self.resolution_m = float(self.stage.resolution_m)
        self.smr_names = list(constellation or truth.constellation_stage.keys())
        self.t = 0.0
        self.n_moves = 0
        self.n_frames = 0

    # ------------------------------------------------------------------ protocol
    def move_and_settle(self, q_target, *, timeout_s: float = 30.0) -> Settled:
        q_target = np.asarray(q_target, float).reshape(3)
        if not np.all(np.isfinite(q_target)):
            raise ValueError(f"move_and_settle: target is not finite: {q_target}")
        self.t += self.joint_dt
        self.stage.command(q_target, self.t)
        self.n_moves += 1
        return self._settle(timeout_s)

    def current(self) -> Settled:
        return self._settle(30.0)

    # ------------------------------------------------------------------ internals
    def _settle(self, timeout_s: float) -> Settled:
        feed = settle_detector(self.settle_tol_m, self.settle_hold_n)
        t_end = self.t + timeout_s
        readings = []
        last = None
        while self.t <= t_end:
            q = self.stage.encoder(self.t)
            readings.append(q)
            if feed(q):
                break
            last = q
            self.t += self.joint_dt
        else:
            move = np.ptp(np.array(readings[-self.settle_hold_n:]), axis=0) if readings else np.zeros(3)
            raise SettleTimeout(f"stage did not settle within {timeout_s:.1f} s: encoder span over the last "
                                f"{self.settle_hold_n} readings {np.round(move * 1e6, 3).tolist()} um "
                                f"> tolerance {self.settle_tol_m * 1e6:.2f} um (last reading {last})")
        win = np.array(feed.buffer)
        # settled: grab frames now, then collect tracker readings while still settled
        t_grab = self.t
        images, windows = {}, {}
        q_true = self.stage.true_q(t_grab)
        for j, c in enumerate(self.truth.cameras):
            images[c.name], windows[c.name] = self._render(j, q_true)
        self.n_frames += len(images)
        tracker, tn = {}, {}
        if self.smr_names:
            sums = {n: np.zeros(3) for n in self.smr_names}
            k = 0
            t = t_grab
            qs = [win]
            while t < t_grab + self.tracker_window_s:
                name = self.smr_names[k % len(self.smr_names)]
                p = smr_position_stage(self.truth, name, self.stage.true_q(t))
                sums[name] += tracker_reading(self.truth, p, self.rng)
                tn[name] = tn.get(name, 0) + 1
                k += 1
                t += self.tracker_dt
            # encoder readings continue during the tracker window (still settled)
            tt = np.arange(t_grab + self.joint_dt, t, self.joint_dt)
            if tt.size:
                qs.append(np.array([self.stage.encoder(x) for x in tt]))
            win = np.vstack(qs)
            self.t = t
            tracker = {n: sums[n] / tn[n] for n in tn}
        return Settled(q=win.mean(0), stamp_ns=int(round(t_grab * 1e9)), images=images, tracker=tracker,
                       tracker_n=tn, q_sd=win.std(0), windows=windows)

    def _render(self, j: int, q_true):
        from .render import render_frame
        cam = self.truth.cameras[j]
        pose = self.truth.camera_pose_at(j, q_true)
        intr = cam.true_intrinsics
        kw = dict(part=self.part)
        if self.show_smr:
            kw.update(sphere_stage=self.truth.smr_star_stage, nest_axis_stage=self.truth.nest_axis_stage)
        if self.window_px is None:
            return render_frame(pose, intr, self.physics, self.rng, **kw), (0, 0, intr.width, intr.height)
        centre = project(cam.pose, intr, self.truth.probe_point_stage(np.zeros(3)))[0]
        return render_window(pose, intr, self.physics, self.rng, centre, self.window_px, **kw)


def render_window(pose, intr: Intrinsics, physics: Physics, rng, centre_px, half_px: int, **kw):
    """A full-size frame of which only the square window of half-size `half_px` around
    `centre_px` is rendered (same physics: the window is rendered through intrinsics shifted
    by the window origin, with the full frame's vignetting); the rest is the flat background.

    Returns (frame, (x0, y0, w, h)).
    """
    from . import render
    x0 = int(np.clip(round(centre_px[0]) - half_px, 0, intr.width - 1))
    y0 = int(np.clip(round(centre_px[1]) - half_px, 0, intr.height - 1))
    x1 = int(np.clip(round(centre_px[0]) + half_px + 1, x0 + 1, intr.width))
    y1 = int(np.clip(round(centre_px[1]) + half_px + 1, y0 + 1, intr.height))
    K = intr.K.copy()
    K[0, 2] -= x0
    K[1, 2] -= y0
    sub = Intrinsics(K, intr.D, x1 - x0, y1 - y0)
    # the full frame's vignetting, cut to the window (render's cache is keyed by the intrinsics)
    vig_full = render._vignette(intr, physics.vignetting)
    vkey = (sub.width, sub.height, round(float(sub.K[0, 2]), 3), round(float(sub.K[1, 2]), 3), physics.vignetting)
    render._VIGNETTE_CACHE[vkey] = np.ascontiguousarray(vig_full[y0:y1, x0:x1])
    bkey = (sub.width, sub.height, float(sub.K[0, 2]), float(sub.K[1, 2]))
    for k in [k for k in render._BASE_CACHE if k[:4] == bkey]:
        del render._BASE_CACHE[k]
    try:
        win = render.render_frame(pose, sub, physics, rng, **kw)
    finally:
        render._VIGNETTE_CACHE.pop(vkey, None)
        for k in [k for k in render._BASE_CACHE if k[:4] == bkey]:
            del render._BASE_CACHE[k]
    part = kw.get("part")
    level = physics.bright_level if part is None or part.lighting == "bright_field" else part.face_level
    frame = np.full((intr.height, intr.width), int(round(level * (1 - 0.5 * physics.vignetting))), np.uint8)
    frame[y0:y1, x0:x1] = win
    return frame, (x0, y0, x1 - x0, y1 - y0)


__all__ = ["Settled", "CellIO", "SimCell", "SettleTimeout", "settle_detector", "render_window"]
