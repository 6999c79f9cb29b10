"""Truth scenarios for the simulated CT cell.

Simulators and tests draw their ground truth from here: a misaligned
instrument, a reference-object pose and stage error motions shaped like the
seed paper's Figs 7-12 (positioning error growing to about 0.5 mm over
360 mm of travel, parabolic straightness of tens of micrometres, angular
errors of tens of arcseconds). Nothing in this module is ever handed to a
solver: solvers see only what a recording carries.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .geometry import detector_rotation, rot_x, rot_y

ARCSEC = np.pi / (180.0 * 3600.0)   # [rad] per arcsecond
DEG = np.pi / 180.0                 # [rad] per degree


@dataclass(frozen=True)
class CampaignTruth:
    """Ground truth of one simulated calibration campaign.

    The stage is modelled as a machine, not through the error map's formulas:
    it travels along a true unit direction ``travel_direction_df`` (in {DF});
    at reading change s it sits at ``(s - p(s)) t + e_x(s) x' + e_y(s) y'`` with
    p the positioning error (positive: travelled LESS than indexed, the paper's
    sign, section 4.1), e_x, e_y the straightness deviations perpendicular to t
    (x' the {DF} X axis projected on the plane perpendicular to t, y' = t x x';
    their least-squares line over the positions is zero), and it turns by the
    angular errors. The true error maps below follow from that construction
    by hand (no call into error_map.py), so a mistake there cannot hide in the
    test truth.

    Attributes
    ----------
    static_w : ndarray of shape (13,)
        True static parameters at stage position k = 1 (see geometry.py).
    srd_reported_m : ndarray of shape (K,)
        Source-to-rotation-axis distance the instrument reports at each
        stage position [m] (what /ct/stage/joint_states carries).
    motions : ndarray of shape (K, 6)
        True error-motion parameters of each position relative to k = 1:
        dx_R, dy_R, dz_R [m], gamma_X, gamma_Y, gamma_Z [rad]. Row 0 is zero.
    sdd_reported_m : float
        Source-to-detector distance the instrument software states [m].
    travel_direction_df : ndarray of shape (3,)
        True unit travel direction of the stage in {DF}.
    stage_errors : ndarray of shape (K, 6)
        positioning p, straightness e_x, e_y [m], pitch, yaw, roll [rad] as built.
    """

    static_w: np.ndarray
    srd_reported_m: np.ndarray
    motions: np.ndarray
    sdd_reported_m: float = 1.04821
    travel_direction_df: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    stage_errors: np.ndarray | None = None
    notes: dict = field(default_factory=dict)

    @property
    def travel_m(self) -> np.ndarray:
        """Reported travel from k = 1 [m], shape (K,)."""
        return self.srd_reported_m - self.srd_reported_m[0]

    @property
    def angle_travel_normal_rad(self) -> float:
        """True angle between the stage travel and the detector normal [rad]."""
        return float(np.arccos(abs(self.travel_direction_df[2])))

    def error_map(self, definition: str = "travel") -> dict:
        """True error map, dict of arrays of shape (K,) under error_map.COMPONENT_FIELDS' names.

        ``"travel"`` (ISO 230-1 geometry): the stage errors as built. ``"detector"``
        (the paper's section 3.3): reading change minus dz_R, and the residuals of
        straight-line fits (numpy.polyfit) of dx_R, dy_R against the reading change.
        """
        if self.stage_errors is None:
            raise ValueError("this truth has no stage_errors (built by hand without a stage model)")
        e = self.stage_errors
        keys = ("positioning_m", "straightness_x_m", "straightness_y_m", "pitch_rad", "yaw_rad", "roll_rad")
        if definition == "travel":
            return {k: e[:, j].copy() for j, k in enumerate(keys)}
        if definition != "detector":
            raise ValueError(f"definition must be 'travel' or 'detector', got {definition!r}")
        s = self.travel_m
        d = self.motions[:, :3]

        def resid(y):
            return y - np.polyval(np.polyfit(s, y, 1), s)

        vals = (s - d[:, 2], resid(d[:, 0]), resid(d[:, 1]), e[:, 3], e[:, 4], e[:, 5])
        return {k: np.asarray(v, dtype=float).copy() for k, v in zip(keys, vals)}


def default_static_truth(srd_reported_m: float = 0.364, sdd_reported_m: float = 1.04821) -> np.ndarray:
    """A realistically misaligned instrument and object pose at k = 1.

    The true SRD is 1.2 mm longer than reported, the detector is 1.6 mm
    further than stated and offset by (1.3, -0.9) mm, tilted by
    (0.35, -0.6, 0.25) degrees; the object sits 0.4 mm off axis, 0.7 mm low,
    turned 17 degrees about Y and tilted by a few tenths of a degree.

    Returns
    -------
    ndarray of shape (13,)
    """
    z_r = srd_reported_m + 1.2e-3
    return np.array([
        z_r, 1.3e-3, -0.9e-3, sdd_reported_m + 1.6e-3,
        0.35 * DEG, -0.60 * DEG, 0.25 * DEG,
        0.4e-3, -0.7e-3, z_r - 0.3e-3,
        0.3 * DEG, 17.0 * DEG, -0.2 * DEG,
    ])


def _detrended(s, y):
    """y minus its least-squares line over the sample points s (a pure straightness shape)."""
    return y - np.polyval(np.polyfit(s, y, 1), s)


def paper_like_stage_errors(travel_m: np.ndarray) -> np.ndarray:
    """Stage errors shaped like the seed paper's Figs 7-12, in the ISO 230-1 geometry.

    Parameters
    ----------
    travel_m : ndarray of shape (K,)
        Reported travel from k = 1 [m] (0 at k = 1).

    Returns
    -------
    ndarray of shape (K, 6)
        positioning [m] (positive: the stage travels less than indexed, growing to
        +0.5 mm over the travel as in the paper's Fig. 7), X / Y straightness [m]
        (parabolas of 18 and -12 um, least-squares line removed over the given
        positions), pitch, yaw, roll [rad]; all zero at k = 1 except the
        straightness, which is a deviation from the fitted line.
    """
    t = np.asarray(travel_m, dtype=float)
    span = max(float(t[-1]), 1e-9)
    s = t / span                                         # 0 .. 1 over the travel
    positioning = 0.50e-3 * s ** 1.4                     # grows to +0.5 mm (travels less)
    if t.size >= 2 and np.ptp(t) > 0:
        ex = _detrended(t, 18e-6 * 4 * s * (1 - s))      # 18 um parabola
        ey = _detrended(t, -12e-6 * 4 * s * (1 - s))     # -12 um parabola
    else:
        ex = ey = np.zeros_like(t)
    pitch = 15 * ARCSEC * np.sin(np.pi * s)              # up to 15 arcsec
    yaw = 40 * ARCSEC * s - 10 * ARCSEC * np.sin(2 * np.pi * s)
    roll = -12 * ARCSEC * s ** 2
    return np.stack([positioning, ex, ey, pitch, yaw, roll], axis=1)


def stage_motions(travel_m, travel_direction_df, stage_errors) -> np.ndarray:
    """Error motions (K, 6) in {DF} of a stage moving along ``travel_direction_df`` with these errors.

    Displacement ``(s - p) t + e_x x' + e_y y'`` relative to k = 1 (x' = {DF} X projected
    perpendicular to t, y' = t x x'), angles as given.
    """
    s = np.asarray(travel_m, dtype=float)
    t = np.asarray(travel_direction_df, dtype=float)
    t = t / np.linalg.norm(t)
    e = np.asarray(stage_errors, dtype=float)
    xp = np.array([1.0, 0.0, 0.0]) - t[0] * t
    xp /= np.linalg.norm(xp)
    yp = np.cross(t, xp)
    d = (s - e[:, 0])[:, None] * t + e[:, 1:2] * xp + e[:, 2:3] * yp
    d -= d[0]
    out = np.concatenate([d, e[:, 3:]], axis=1)
    out[0, 3:] = 0.0
    return out


def default_campaign(n_positions: int = 19, step_m: float = 0.020,
                     srd_first_m: float = 0.364, sdd_reported_m: float = 1.04821,
                     guide_misalignment_rad=(0.05 * DEG, -0.03 * DEG)) -> CampaignTruth:
    """The paper's campaign: stage stepped by ``step_m`` from ``srd_first_m``.

    The default is 19 positions, 364 mm to 724 mm in 20 mm steps. The stage
    runs along the source -> rotation-axis line ({SRF} Z) turned by
    ``guide_misalignment_rad`` (about {SRF} X, then Y): the tilted detector sees
    that travel about 0.7 degrees from its normal, so the detector-frame
    positioning (the paper's) and the positioning along the travel (ISO
    230-1) differ by ~27 um over 360 mm.
    """
    if n_positions < 1:
        raise ValueError(f"n_positions must be >= 1, got {n_positions}")
    srd = srd_first_m + step_m * np.arange(n_positions)
    w = default_static_truth(srd_first_m, sdd_reported_m)
    t = srd - srd[0]
    gx, gy = guide_misalignment_rad
    travel_srf = rot_y(gy) @ rot_x(gx) @ np.array([0.0, 0.0, 1.0])
    travel_df = detector_rotation(w[4], w[5], w[6]).T @ travel_srf
    errors = paper_like_stage_errors(t)
    return CampaignTruth(
        static_w=w,
        srd_reported_m=srd,
        motions=stage_motions(t, travel_df, errors),
        sdd_reported_m=sdd_reported_m,
        travel_direction_df=travel_df / np.linalg.norm(travel_df),
        stage_errors=errors,
    )
