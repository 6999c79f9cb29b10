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

from .geometry import detector_rotation

ARCSEC = np.pi / (180.0 * 3600.0)   # [rad] per arcsecond
DEG = np.pi / 180.0                 # [rad] per degree


@dataclass(frozen=True)
class CampaignTruth:
    """Ground truth of one simulated calibration campaign.

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
    """

    static_w: np.ndarray
    srd_reported_m: np.ndarray
    motions: np.ndarray
    sdd_reported_m: float = 1.04821
    notes: dict = field(default_factory=dict)

    @property
    def travel_m(self) -> np.ndarray:
        """Reported travel from k = 1 [m], shape (K,)."""
        return self.srd_reported_m - self.srd_reported_m[0]

    def error_map(self) -> dict:
        """True error map in the paper's terms (section 3.3, end).

        Returns a dict of arrays of shape (K,): ``positioning_m`` (dz minus
        reported travel), ``straightness_x_m`` and ``straightness_y_m``
        (residuals of a straight-line fit of dx and dy over the travel),
        ``pitch_rad``, ``yaw_rad``, ``roll_rad`` (gamma_X, gamma_Y, gamma_Z).
        """
        from .error_map import error_map  # noqa: PLC0415 - the one definition of the error map

        return {k: v.copy() for k, v in error_map(self.srd_reported_m, self.motions).as_truth_dict().items()}


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


def paper_like_motions(travel_m: np.ndarray) -> np.ndarray:
    """Stage error motions shaped like the seed paper's Figs 7-12.

    Parameters
    ----------
    travel_m : ndarray of shape (K,)
        Reported travel from k = 1 [m] (0 at k = 1).

    Returns
    -------
    ndarray of shape (K, 6)
        dx, dy, dz [m] (dz includes the travel itself) and gamma_X, gamma_Y,
        gamma_Z [rad], all zero at k = 1.
    """
    t = np.asarray(travel_m, dtype=float)
    span = max(float(t[-1]), 1e-9)
    s = t / span                                         # 0 .. 1 over the travel
    positioning = 0.50e-3 * s ** 1.4                     # grows to 0.5 mm
    dx = 25e-6 * s + 18e-6 * 4 * s * (1 - s)             # slope + 18 um parabola
    dy = -8e-6 * s - 12e-6 * 4 * s * (1 - s)             # slope - 12 um parabola
    pitch = 15 * ARCSEC * np.sin(np.pi * s)              # up to 15 arcsec
    yaw = 40 * ARCSEC * s - 10 * ARCSEC * np.sin(2 * np.pi * s)
    roll = -12 * ARCSEC * s ** 2
    out = np.stack([dx, dy, t + positioning, pitch, yaw, roll], axis=1)
    out[0] = 0.0
    return out


def default_campaign(n_positions: int = 19, step_m: float = 0.020,
                     srd_first_m: float = 0.364, sdd_reported_m: float = 1.04821) -> CampaignTruth:
    """The paper's campaign: stage stepped by ``step_m`` from ``srd_first_m``.

    The default is 19 positions, 364 mm to 724 mm in 20 mm steps.
    """
    if n_positions < 1:
        raise ValueError(f"n_positions must be >= 1, got {n_positions}")
    srd = srd_first_m + step_m * np.arange(n_positions)
    w = default_static_truth(srd_first_m, sdd_reported_m)
    motions = paper_like_motions(srd - srd[0])
    # The stage runs along the source -> rotation-axis line ({SRF} Z), which
    # the tilted detector sees slightly oblique: in {DF} the travel has a
    # small X and Y component (millimetres over the travel). The straightness
    # fit removes this linear part; the scenario keeps it for realism.
    z_srf_in_df = detector_rotation(w[4], w[5], w[6]).T @ np.array([0.0, 0.0, 1.0])
    t = srd - srd[0]
    motions[:, 0] += t * z_srf_in_df[0]
    motions[:, 1] += t * z_srf_in_df[1]
    motions[:, 2] += t * (z_srf_in_df[2] - 1.0)
    return CampaignTruth(
        static_w=w,
        srd_reported_m=srd,
        motions=motions,
        sdd_reported_m=sdd_reported_m,
    )
