"""Stage and laser-tracker simulators (pure functions of time; no ROS).

Stage: stepper axes; a commanded target is quantised to the step (`resolution` of
picms_cell.yaml); each axis follows a trapezoidal velocity profile, then rings (a damped
oscillation along the move) and settles. The encoders read the true axis position rounded to
`encoder_resolution_m`, continuously, so ringing is visible in joint_states.

Tracker: readings of one SMR centre at a time, round-robin, each with its own stamp; noise
per axis from the stated uncertainty (15 um + 6 um/m, k = 2, so u = 7.5 um + 3 um/m), and
optional hidden errors (cell.Physics): a length scale (1 + s) about the tracker origin, azimuth
and elevation encoder scale errors, and the SMR*'s centring error in its nest. (A clock lag is
applied by whoever stamps the readings.) A 6-DOF probe-pose reading is also provided.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .cell import CellTruth


@dataclass
class _Move:
    t0: float
    start: np.ndarray
    target: np.ndarray
    durations: np.ndarray        # per axis total time
    vmax: float
    amax: float


def _trap(d: float, vmax: float, amax: float):
    """Duration and position-at-time function of a trapezoidal move of length |d|."""
    D = abs(d)
    if D == 0:
        return 0.0, lambda t: 0.0
    ta = vmax / amax
    if D < vmax * ta:            # triangular
        ta = np.sqrt(D / amax)
        vp = amax * ta
        T = 2 * ta
    else:
        vp = vmax
        T = ta * 2 + (D - vmax * ta) / vmax
    s = np.sign(d)

    def pos(t):
        t = min(max(t, 0.0), T)
        if t < ta:
            x = 0.5 * amax * t * t
        elif t > T - ta:
            x = D - 0.5 * amax * (T - t) ** 2
        else:
            x = 0.5 * amax * ta * ta + vp * (t - ta)
        return s * x
    return T, pos


@dataclass
class StageSim:
    """XYZ stepper stage. `command(target, t)` starts a move; `true_q(t)`, `encoder(t)` read it."""
    resolution_m: float = 6.0e-6
    encoder_resolution_m: float = 1.0e-7
    vmax: float = 0.005            # m/s
    amax: float = 0.02             # m/s^2
    ring_amplitude_m: float = 3.0e-6
    ring_freq_hz: float = 12.0
    ring_tau_s: float = 0.12
    never_settles: bool = False    # bad-input switch: a stage that keeps hunting
    q0: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _moves: list = field(default_factory=list)

    def quantise(self, target) -> np.ndarray:
        return np.round(np.asarray(target, float) / self.resolution_m) * self.resolution_m

    def command(self, target, t: float) -> float:
        """Start a move to `target` (3,) m at time t (s); returns the time the profile ends."""
        tgt = self.quantise(target)
        start = self._nominal(t)
        fns, durs = [], []
        for k in range(3):
            T, f = _trap(tgt[k] - start[k], self.vmax, self.amax)
            fns.append(f)
            durs.append(T)
        self._moves.append((t, start, tgt, np.array(durs), fns))
        return t + max(durs)

    def _nominal(self, t: float) -> np.ndarray:
        q = self.q0.copy()
        for t0, start, tgt, durs, fns in self._moves:
            if t < t0:
                break
            q = np.array([start[k] + fns[k](t - t0) for k in range(3)])
        return q

    def true_q(self, t: float) -> np.ndarray:
        q = self._nominal(t)
        for t0, start, tgt, durs, fns in reversed(self._moves):
            if t < t0:
                continue
            te = t0 + durs.max()
            if t > te:
                d = tgt - start
                n = np.linalg.norm(d)
                if n > 0:
                    dt = t - te
                    q = q + d / n * self.ring_amplitude_m * np.exp(-dt / self.ring_tau_s) \
                        * np.sin(2 * np.pi * self.ring_freq_hz * dt)
            break
        if self.never_settles:
            q = q + 4e-6 * np.sin(2 * np.pi * 1.3 * t) * np.array([1.0, -0.5, 0.3])
        return q

    def encoder(self, t: float) -> np.ndarray:
        return np.round(self.true_q(t) / self.encoder_resolution_m) * self.encoder_resolution_m


def tracker_reading(truth: CellTruth, p_stage, rng, probe: bool = False) -> np.ndarray:
    """One tracker reading (3,) of an SMR centred at p_stage (3,) (stage frame), tracker frame, m.

    `probe`: the reading is of the SMR* (its centring error applies)."""
    ph = truth.physics
    p_t = truth.to_tracker(p_stage)[0]
    if probe:
        p_t = p_t + np.asarray(ph.smr_centring_m, float)
    return tracker_errors(p_t, ph.tracker_scale_ppm, ph.tracker_encoder_ppm) + rng.normal(0.0, truth.tracker_sigma_m(), 3)


def tracker_errors(p_t, scale_ppm: float = 0.0, encoder_ppm=(0.0, 0.0)) -> np.ndarray:
    """What the tracker reads for the true tracker-frame point p_t (3,): its distance meter reads
    (1 + s) times the range, its encoders (1 + e_az) times the azimuth (about z, from x) and
    (1 + e_el) times the elevation (from the xy plane)."""
    p_t = np.asarray(p_t, float)
    e_az, e_el = (float(v) * 1e-6 for v in encoder_ppm)
    s = 1.0 + float(scale_ppm) * 1e-6
    if e_az == 0.0 and e_el == 0.0:
        return p_t * s
    r = np.linalg.norm(p_t)
    az = np.arctan2(p_t[1], p_t[0]) * (1.0 + e_az)
    el = np.arcsin(p_t[2] / r) * (1.0 + e_el)
    return r * s * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def smr_position_stage(truth: CellTruth, name: str, q, probe_smr: str = "smr_star") -> np.ndarray:
    """True stage-frame centre (3,) of SMR `name` with the stage at true position q."""
    if name == probe_smr:
        return np.asarray(truth.smr_star_stage, float)
    return truth.body_point_stage(truth.constellation_stage[name], q)


def probe_pose_reading(truth: CellTruth, q, rng, sigma_rot_rad: float = 2e-5):
    """6-DOF reading of the probe body frame: (R_tracker_body (3, 3), p_tracker_body (3,))."""
    from .camera import rotvec_to_matrix
    R = truth.R_tracker_stage @ truth.probe_body_R_stage @ rotvec_to_matrix(rng.normal(0, sigma_rot_rad, 3))
    p = tracker_reading(truth, truth.probe_point_stage(q), rng)
    return R, p
