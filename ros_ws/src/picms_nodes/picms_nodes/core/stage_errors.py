"""Geometric error motions of the simulated XYZ stage (never told to the solvers).

A real small precision XYZ stage does not translate rigidly along its travel directions. With
the axes at readings q (m), the carriage (and everything riding on it: cameras, X*, the SMR
constellation) is displaced by A diag(1 + s) q + e_str(q) and rotated by the small rotation
w(q) about the axes' metrology point p_abbe (where the scales read, offset from X*):

    x(b, q) = p_abbe + R(w(q)) (b - p_abbe) + A diag(1 + s) q + e_str(q)

- s: per-axis scale error (ppm level; ball-screw lead / scale calibration);
- e_str: straightness, a bow per axis perpendicular to its travel, quadratic in q_k;
- w(q) = sum_k G[:, k] q_k: pitch / yaw / roll of each axis, linear over the travel, which
  become Abbe errors of G q x (X* - p_abbe) at the probe (X* is the origin);
- squareness stays in A (cell.py), backlash is not modelled, the step quantisation and the
  encoder rounding are in instruments.StageSim.

Default magnitudes (sd, `StageErrorSpec`) are assumptions typical of small precision
ball-screw or linear-motor XYZ stages of 25-100 mm travel as catalogue data state them
(accuracy a few um, straightness ~1-2 um per 25 mm, pitch/yaw ~10-30 urad over the travel):
scale 20 ppm, straightness 1 um at 25 mm from the centre of travel, angular 15 urad (3 arcsec)
per 25 mm of travel on each of the three rotations of each axis, metrology point 60 mm below
and 40 mm beside X*. They are drawn from their own generator seeded from the cell (so the
rest of a seeded cell is unchanged).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import rotvec_to_matrix


@dataclass(frozen=True)
class StageErrorSpec:
    scale_ppm_sd: float = 20.0
    straightness_m_sd: float = 1.0e-6       # bow at `ref_travel_m` from the centre of travel
    angular_rad_sd: float = 1.5e-5          # per `ref_travel_m` of travel, each rotation of each axis
    ref_travel_m: float = 0.025
    abbe_offset_m: tuple = (0.04, 0.0, -0.06)   # metrology point relative to X* (stage frame)
    scale_ppm: tuple | None = None          # explicit per-axis scale errors (ppm) instead of the draw


@dataclass(frozen=True)
class StageErrors:
    scale: np.ndarray          # (3,) dimensionless
    straight: np.ndarray       # (3, 3) column k: displacement per q_k^2 (1/m), perpendicular to axis k
    G: np.ndarray              # (3, 3) column k: rotation vector per m of axis k (rad/m)
    p_abbe: np.ndarray         # (3,) m

    def rotvec(self, q) -> np.ndarray:
        return self.G @ np.asarray(q, float)

    def rotation(self, q) -> np.ndarray:
        return rotvec_to_matrix(self.rotvec(q))

    def translation(self, A, q) -> np.ndarray:
        """Displacement (3,) of a point at p_abbe with the stage at q (m)."""
        q = np.asarray(q, float)
        return np.asarray(A, float) @ (q * (1.0 + self.scale)) + self.straight @ (q * q)

    def point(self, A, b, q) -> np.ndarray:
        """Stage-frame position (3,) of body point b (3,) (given at q = 0) with the stage at q."""
        b = np.asarray(b, float)
        return self.p_abbe + self.rotation(q) @ (b - self.p_abbe) + self.translation(A, q)


def make_stage_errors(seed: int, spec: StageErrorSpec | None = None) -> StageErrors:
    s = spec or StageErrorSpec()
    rng = np.random.default_rng(seed)
    L = s.ref_travel_m
    scale = rng.normal(0.0, s.scale_ppm_sd * 1e-6, 3)      # drawn either way: the rest stays as seeded
    if s.scale_ppm is not None:
        scale = np.asarray(s.scale_ppm, float).reshape(3) * 1e-6
    straight = np.zeros((3, 3))
    for k in range(3):
        perp = [i for i in range(3) if i != k]
        straight[perp, k] = rng.normal(0.0, s.straightness_m_sd, 2) / L ** 2
    G = rng.normal(0.0, s.angular_rad_sd, (3, 3)) / L
    return StageErrors(scale, straight, G, np.asarray(s.abbe_offset_m, float))


def no_stage_errors() -> StageErrors:
    return StageErrors(np.zeros(3), np.zeros((3, 3)), np.zeros((3, 3)), np.zeros(3))
