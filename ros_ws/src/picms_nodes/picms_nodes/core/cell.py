"""Ground truth of a simulated Pixel Probe cell (PiCMS), Gordon and Borenstein 2019.

`make_cell(rng, physics)` returns a `CellTruth`: three cameras in the tetrahedral arrangement
(optical axes converging on the vertex X*, 60 deg between axes, small assembly errors so the
principal rays miss each other by tenths of a millimetre), the XYZ stage (travel directions
with squareness errors; stage frame placed arbitrarily in the tracker frame), the constellation
SMRs fixed to the probe body, the SMR* in its nest at X*, and the laser tracker.

Conventions. The probe body (cameras, constellation) rides on the stage. The stage frame is
the frame INTERFACES.md defines: origin = X* at encoder reading 0, x along the +x travel, y in
the plane of the +x and +y travels, z = x cross y. With the stage at true position q (m, per
axis), a body-fixed point b (given relative to X* at q = 0, in the stage frame) is at
b + A q, where the columns of A are the unit travel directions (upper-triangular in this frame).

Hidden physics (off by default, never told to the solvers):
- `hidden_distortion`: the lenses distort (true D) but CameraInfo carries D = 0.
- `tracker_scale_ppm`: the tracker's lengths are scaled by (1 + s) about its origin.
- `tracker_encoder_ppm` (e_az, e_el): the tracker's azimuth and elevation encoders read (1 + e) times
  the true angles (azimuth about the tracker frame's z axis from its x axis, elevation from its xy plane).
- `smr_centring_m` (3,): the SMR*'s optical centre sits this far (tracker frame) from its sphere
  centre, which is what the cameras see (X*); every tracker reading of the SMR* carries it.
- `tracker_lag_s`: the tracker's stamps run late by this against the cameras' and stage's clock
  (negative: early); a reading stamped t was taken at t - lag.
- `camera_tilt_drift_rad_per_s`, `camera_shift_drift_m_per_s`: each camera mount drifts steadily
  during the session (thermal): it tilts about an axis perpendicular to its optical axis and its
  centre moves, each in a random direction per camera (own generator seeded from the cell), at
  these rates from the session start (t = 0 of `campaign.simulate_session`).
Stage error motions (ON by default, `stage_error_motions`; never told to the solvers): scale,
straightness and pitch/yaw/roll with Abbe offset (core/stage_errors.py) move every body point
and camera as x(b, q) there instead of b + A q.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, field, replace

import numpy as np

from .camera import CameraPose, Intrinsics, rotvec_to_matrix
from .stage_errors import make_stage_errors

SMR_DIAMETER = 0.0127          # m, 0.5 inch SMR*
CAMERA_NAMES = ("camera_1", "camera_2", "camera_3")
CONSTELLATION = ("smr_1", "smr_2", "smr_3", "smr_4", "smr_5")


@dataclass(frozen=True)
class Physics:
    """Simulator physics; `make_physics(rng)` varies it for tests."""
    focal_m: float = 0.018
    pixel_m: float = 2.2e-6
    width: int = 2592
    height: int = 1944
    working_distance_m: float = 0.180      # perspective centre to X* (~22 um/px)
    f_number: float = 5.6
    assembly_rot_rad: float = 1.5e-3       # sd of each camera's mounting rotation
    assembly_pos_m: float = 2.0e-4         # sd of each camera's centre position
    distortion_k1: float = -0.02           # true radial distortion (about 0.01 % at 1 mm)
    hidden_distortion: bool = False        # CameraInfo carries D = 0 (hidden physics)
    intrinsic_error_px: float = 0.0        # sd of CameraInfo cx, cy errors (hidden physics)
    psf_sigma_px: float = 0.7              # lens blur in focus
    bright_level: float = 200.0            # back-light level, DN (8-bit)
    dark_level: float = 12.0               # disc level, DN
    vignetting: float = 0.25               # relative fall-off at the image corner
    full_well_dn: float = 40.0             # electrons per DN: shot noise variance = level / this
    read_noise_dn: float = 1.2
    tracker_sigma_m: float | None = None   # per-axis sd; None: (15 um + 6 um/m * L) / 2
    tracker_scale_ppm: float = 0.0         # hidden physics: tracker length scale error
    tracker_encoder_ppm: tuple = (0.0, 0.0)          # hidden: azimuth, elevation angle-scale errors
    smr_centring_m: tuple = (0.0, 0.0, 0.0)          # hidden: SMR* optical centre off its sphere centre
    tracker_lag_s: float = 0.0             # hidden: tracker stamps late by this (s; negative: early)
    squareness_sd_rad: float = 5e-5
    stage_resolution_m: float = 6.0e-6
    tracker_distance_m: float = 2.4
    stage_error_motions: bool = True       # stage scale / straightness / angular errors (stage_errors.py)
    stage_error_spec: object = None        # stage_errors.StageErrorSpec (None: its defaults)
    camera_tilt_drift_rad_per_s: float = 0.0   # hidden physics: camera mount tilt drift rate
    camera_shift_drift_m_per_s: float = 0.0    # hidden physics: camera centre drift rate


def make_physics(rng, **overrides) -> Physics:
    """Physics with randomised blur, noise, levels and assembly (for tests over many seeds)."""
    p = Physics(
        psf_sigma_px=float(rng.uniform(0.5, 1.4)),
        bright_level=float(rng.uniform(150, 235)),
        dark_level=float(rng.uniform(5, 30)),
        vignetting=float(rng.uniform(0.1, 0.4)),
        full_well_dn=float(rng.uniform(20, 80)),
        read_noise_dn=float(rng.uniform(0.6, 2.5)),
        working_distance_m=float(rng.uniform(0.170, 0.190)),
        distortion_k1=float(rng.uniform(-0.05, 0.05)),
        tracker_distance_m=float(rng.uniform(1.5, 4.0)),
    )
    return replace(p, **overrides)


@dataclass(frozen=True)
class CameraTruth:
    name: str
    pose: CameraPose                 # true pose in the stage frame at q = 0
    true_intrinsics: Intrinsics      # how the simulator projects
    info_intrinsics: Intrinsics      # what CameraInfo says


@dataclass(frozen=True)
class CellTruth:
    physics: Physics
    cameras: tuple
    A_travel: np.ndarray             # (3, 3) columns: unit travel directions in the stage frame
    R_tracker_stage: np.ndarray
    p_tracker_stage: np.ndarray      # stage-frame origin (X* at q = 0) in the tracker frame
    constellation_stage: dict = field(default_factory=dict)   # name -> (3,) body points at q = 0
    smr_star_stage: np.ndarray = field(default_factory=lambda: np.zeros(3))  # SMR* centre (fixed)
    nest_axis_stage: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))
    probe_body_R_stage: np.ndarray = field(default_factory=lambda: np.eye(3))  # 6-DOF target frame
    stage_errors: object = None      # stage_errors.StageErrors or None (rigid translation)
    camera_drift: tuple = ()         # per camera (w (3,) rad/s, v (3,) m/s) in the stage frame, or ()

    def body_point_stage(self, b, q) -> np.ndarray:
        """Stage-frame position (3,) of body point b (3,) with the stage at true position q."""
        if self.stage_errors is not None:
            return self.stage_errors.point(self.A_travel, b, q)
        return np.asarray(b, float) + self.A_travel @ np.asarray(q, float)

    def probe_point_stage(self, q) -> np.ndarray:
        return self.body_point_stage(np.zeros(3), q)

    def to_tracker(self, p_stage) -> np.ndarray:
        """True tracker-frame coordinates (N, 3) of stage-frame points (N, 3) (no scale error)."""
        p = np.atleast_2d(np.asarray(p_stage, float))
        return p @ self.R_tracker_stage.T + self.p_tracker_stage

    def camera_pose_at(self, j: int, q, t_s: float = 0.0) -> CameraPose:
        """True pose of camera j with the stage at q, t_s seconds after the session start (drift)."""
        c = self.cameras[j]
        R, C = c.pose.R_stage_camera, c.pose.p_stage_centre
        if self.camera_drift:
            w, v = self.camera_drift[j]
            R, C = rotvec_to_matrix(np.asarray(w) * t_s) @ R, C + np.asarray(v) * t_s
        if self.stage_errors is not None:
            return CameraPose(self.stage_errors.rotation(q) @ R, self.stage_errors.point(self.A_travel, C, q))
        return CameraPose(R, C + self.A_travel @ np.asarray(q, float))

    def tracker_sigma_m(self) -> float:
        p = self.physics
        if p.tracker_sigma_m is not None:
            return float(p.tracker_sigma_m)
        return 0.5 * (15e-6 + 6e-6 * p.tracker_distance_m)


def _random_rotation(rng) -> np.ndarray:
    q = rng.standard_normal(4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def make_cell(rng, physics: Physics | None = None) -> CellTruth:
    """A simulated cell with random assembly errors and placement (see module doc)."""
    p = physics or Physics()
    f_px = p.focal_m / p.pixel_m
    # tetrahedral arrangement: axes at 60 deg to each other -> 35.26 deg from the symmetry axis
    theta = np.arccos(np.sqrt(2.0 / 3.0))
    az0 = rng.uniform(0, 2 * np.pi)
    cams = []
    for j, name in enumerate(CAMERA_NAMES):
        az = az0 + 2 * np.pi * j / 3
        u = np.array([np.sin(theta) * np.cos(az), np.sin(theta) * np.sin(az), np.cos(theta)])
        z_cam = -u                                           # looks at X* (from above)
        x_cam = np.cross(z_cam, [0.0, 0.0, 1.0])
        x_cam /= np.linalg.norm(x_cam)                       # image +x horizontal
        y_cam = np.cross(z_cam, x_cam)                       # image +y down-ish
        R = np.column_stack([x_cam, y_cam, z_cam]) @ rotvec_to_matrix(rng.normal(0, p.assembly_rot_rad, 3))
        C = u * p.working_distance_m + rng.normal(0, p.assembly_pos_m, 3)
        K = np.array([[f_px * (1 + rng.normal(0, 2e-3)), 0, (p.width - 1) / 2 + rng.normal(0, 8)],
                      [0, 0, (p.height - 1) / 2 + rng.normal(0, 8)], [0, 0, 1.0]])
        K[1, 1] = K[0, 0] * (1 + rng.normal(0, 2e-4))
        D = np.array([p.distortion_k1 * rng.uniform(0.7, 1.3), rng.normal(0, 0.05), rng.normal(0, 2e-5),
                      rng.normal(0, 2e-5), 0.0])
        true_i = Intrinsics(K, D, p.width, p.height)
        Ki = K.copy()
        if p.intrinsic_error_px > 0:
            Ki[0, 2] += rng.normal(0, p.intrinsic_error_px)
            Ki[1, 2] += rng.normal(0, p.intrinsic_error_px)
        info_i = Intrinsics(Ki, np.zeros(5) if p.hidden_distortion else D, p.width, p.height)
        cams.append(CameraTruth(name, CameraPose(R, C), true_i, info_i))
    e = rng.normal(0, p.squareness_sd_rad, 3)
    A = np.array([[1.0, -np.sin(e[0]), np.sin(e[1])],
                  [0.0, np.cos(e[0]), np.sin(e[2])],
                  [0.0, 0.0, 1.0]])
    A[2, 2] = np.sqrt(1 - A[0, 2] ** 2 - A[1, 2] ** 2)
    R_ts = _random_rotation(rng)
    d = rng.standard_normal(3)
    p_ts = d / np.linalg.norm(d) * p.tracker_distance_m
    const = {}
    for k, name in enumerate(CONSTELLATION):
        az = 2 * np.pi * k / len(CONSTELLATION) + rng.uniform(-0.3, 0.3)
        r = rng.uniform(0.08, 0.14)
        const[name] = np.array([r * np.cos(az), r * np.sin(az), rng.uniform(-0.03, 0.12)])
    R_probe = _random_rotation(rng)
    se = None
    # own generators seeded from the cell: the draws above and the caller's stream are unchanged
    seed = int.from_bytes(hashlib.sha256(A.tobytes() + p_ts.tobytes()).digest()[:8], "little")
    if p.stage_error_motions:
        se = make_stage_errors(seed, p.stage_error_spec)
    drift = ()
    if p.camera_tilt_drift_rad_per_s or p.camera_shift_drift_m_per_s:
        drng = np.random.default_rng(seed + 1)
        drift = []
        for c in cams:
            a = drng.uniform(0, 2 * np.pi)                    # tilt axis in the image plane
            w = c.pose.R_stage_camera[:, 0] * np.cos(a) + c.pose.R_stage_camera[:, 1] * np.sin(a)
            d = drng.standard_normal(3)
            drift.append((w * p.camera_tilt_drift_rad_per_s, d / np.linalg.norm(d) * p.camera_shift_drift_m_per_s))
        drift = tuple(drift)
    return CellTruth(p, tuple(cams), A, R_ts, p_ts, const, np.zeros(3),
                     np.array([0.0, 0.0, -1.0]), R_probe, se, drift)


def squareness_truth(A) -> dict:
    """Included angle of each pair of travels minus 90 deg (rad), from travel matrix A (3, 3)."""
    out = {}
    for key, (i, k) in {"xy": (0, 1), "xz": (0, 2), "yz": (1, 2)}.items():
        c = A[:, i] @ A[:, k] / np.linalg.norm(A[:, i]) / np.linalg.norm(A[:, k])
        out[key] = float(np.arccos(np.clip(c, -1, 1)) - np.pi / 2)
    return out


def cell_from_seed(seed: int, vary_physics: bool = False, **overrides) -> CellTruth:
    """The same cell in every process that uses the same seed and overrides (simulator nodes)."""
    rng = np.random.default_rng(int(seed))
    phys = make_physics(rng, **overrides) if vary_physics else replace(Physics(), **overrides)
    return make_cell(rng, phys)
