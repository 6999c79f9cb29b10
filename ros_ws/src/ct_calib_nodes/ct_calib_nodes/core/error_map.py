"""Stage error map in the paper's terms (Ferrucci et al. 2020, end of section 3.3).

* Z positioning error = measured dz_R minus the change of the instrument's
  SRD reading (travel).
* X and Y straightness = residuals of a straight-line least-squares fit of
  dx_R and dy_R over the travel. (The extracted paper text says "dy and dz";
  straightness in X and Y can only mean dx and dy, as scenario.py also
  defines it.)
* Pitch, yaw, roll = gamma_X, gamma_Y, gamma_Z (also given in arcseconds).

Uncertainties are propagated linearly. Without static information the
positions are treated as independent: positioning u = u(dz); straightness
u = sqrt(diag((I - H) diag(u^2) (I - H)^T)) with H the hat matrix of the
line fit; angles u = u(gamma). With ``static_sensitivities`` (A_k = d m_k /
d x_static from error_motion) and the static covariance S, the joint
covariance of all positions is built,
``Cov(m_k, m_l) = delta_kl C_k + A_k S A_l^T`` (C_k conditional), and
propagated through the same linear maps. This matters: the static error is
common to all positions and mostly linear in the travel, so the line fit
of the straightness removes most of it, which the independent treatment
cannot know (it overstates the straightness uncertainty many times).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .static_solver import _plain

ARCSEC_PER_RAD = 180.0 * 3600.0 / np.pi


@dataclass(frozen=True)
class ErrorMap:
    """Error map over K stage positions (all arrays of shape (K,)).

    Attributes
    ----------
    srd_reported_m, travel_m : reported SRD and travel from k = 1 [m]
    positioning_m, straightness_x_m, straightness_y_m : [m]
    pitch_rad, yaw_rad, roll_rad : [rad]
    u_positioning_m, u_straightness_x_m, u_straightness_y_m : standard uncertainties [m]
    u_pitch_rad, u_yaw_rad, u_roll_rad : standard uncertainties [rad]
    line_x, line_y : ndarray of shape (2,)
        Intercept [m] and slope [m/m] of the straight-line fits of dx, dy.
    """

    srd_reported_m: np.ndarray
    travel_m: np.ndarray
    positioning_m: np.ndarray
    straightness_x_m: np.ndarray
    straightness_y_m: np.ndarray
    pitch_rad: np.ndarray
    yaw_rad: np.ndarray
    roll_rad: np.ndarray
    u_positioning_m: np.ndarray
    u_straightness_x_m: np.ndarray
    u_straightness_y_m: np.ndarray
    u_pitch_rad: np.ndarray
    u_yaw_rad: np.ndarray
    u_roll_rad: np.ndarray
    line_x: np.ndarray
    line_y: np.ndarray

    @property
    def pitch_arcsec(self) -> np.ndarray:
        return self.pitch_rad * ARCSEC_PER_RAD

    @property
    def yaw_arcsec(self) -> np.ndarray:
        return self.yaw_rad * ARCSEC_PER_RAD

    @property
    def roll_arcsec(self) -> np.ndarray:
        return self.roll_rad * ARCSEC_PER_RAD

    @property
    def u_pitch_arcsec(self) -> np.ndarray:
        return self.u_pitch_rad * ARCSEC_PER_RAD

    @property
    def u_yaw_arcsec(self) -> np.ndarray:
        return self.u_yaw_rad * ARCSEC_PER_RAD

    @property
    def u_roll_arcsec(self) -> np.ndarray:
        return self.u_roll_rad * ARCSEC_PER_RAD

    def as_truth_dict(self) -> dict:
        """Values under the keys of scenario.CampaignTruth.error_map()."""
        return {"positioning_m": self.positioning_m, "straightness_x_m": self.straightness_x_m,
                "straightness_y_m": self.straightness_y_m, "pitch_rad": self.pitch_rad,
                "yaw_rad": self.yaw_rad, "roll_rad": self.roll_rad}

    def uncertainty_dict(self) -> dict:
        """Standard uncertainties under the same keys as :meth:`as_truth_dict`."""
        return {"positioning_m": self.u_positioning_m, "straightness_x_m": self.u_straightness_x_m,
                "straightness_y_m": self.u_straightness_y_m, "pitch_rad": self.u_pitch_rad,
                "yaw_rad": self.u_yaw_rad, "roll_rad": self.u_roll_rad}

    def to_dict(self) -> dict:
        """Plain dict, SI plus arcsecond copies of the angles, for YAML / JSON export."""
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        for a in ("pitch", "yaw", "roll"):
            d[f"{a}_arcsec"] = getattr(self, f"{a}_arcsec")
            d[f"u_{a}_arcsec"] = getattr(self, f"u_{a}_arcsec")
        d["units"] = "SI (m, rad); *_arcsec in arcseconds"
        return _plain(d)


def error_map(srd_reported_m, motions, motion_covariances=None, *, static_sensitivities=None,
              static_covariance=None) -> ErrorMap:
    """Error map from per-position error motions.

    Parameters
    ----------
    srd_reported_m : array_like of shape (K,)
        Instrument-reported SRD at each position [m]; position 0 is k = 1.
    motions : array_like of shape (K, 6)
        dx_R, dy_R, dz_R [m], gamma_X, gamma_Y, gamma_Z [rad] per position
        (row 0 is k = 1, normally zeros).
    motion_covariances : array_like of shape (K, 6, 6), optional
        Covariance of each row (conditional or total, see error_motion.py);
        None gives NaN uncertainties. With ``static_sensitivities`` these
        must be the CONDITIONAL covariances (MotionResult.covariance).
    static_sensitivities : array_like of shape (K, 6, n_s), optional
        MotionResult.static_sensitivity of each position (zeros for a row
        that is k = 1 by definition).
    static_covariance : array_like of shape (n_s, n_s), optional
        StaticResult.covariance.

    Returns
    -------
    ErrorMap
    """
    srd = np.asarray(srd_reported_m, dtype=float)
    m = np.asarray(motions, dtype=float)
    if srd.ndim != 1 or srd.size < 1:
        raise ValueError(f"srd_reported_m must have shape (K,), got {srd.shape}")
    k = srd.size
    if m.shape != (k, 6):
        raise ValueError(f"motions must have shape ({k}, 6), got {m.shape}")
    if not (np.all(np.isfinite(srd)) and np.all(np.isfinite(m))):
        raise ValueError("srd_reported_m or motions contain NaN or inf")
    if motion_covariances is None:
        var = np.full((k, 6), np.nan)
    else:
        c = np.asarray(motion_covariances, dtype=float)
        if c.shape != (k, 6, 6):
            raise ValueError(f"motion_covariances must have shape ({k}, 6, 6), got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError("motion_covariances contain NaN or inf")
        var = np.maximum(np.diagonal(c, axis1=1, axis2=2), 0.0)
    joint = None
    if static_sensitivities is not None or static_covariance is not None:
        if motion_covariances is None or static_sensitivities is None or static_covariance is None:
            raise ValueError("static_sensitivities, static_covariance and motion_covariances go together")
        a_s = np.asarray(static_sensitivities, dtype=float)
        s_cov = np.asarray(static_covariance, dtype=float)
        ns = s_cov.shape[0]
        if s_cov.shape != (ns, ns) or a_s.shape != (k, 6, ns):
            raise ValueError(f"static_sensitivities must be ({k}, 6, n_s) and static_covariance (n_s, n_s), "
                             f"got {a_s.shape} and {s_cov.shape}")
        if not (np.all(np.isfinite(a_s)) and np.all(np.isfinite(s_cov))):
            raise ValueError("static_sensitivities or static_covariance contain NaN or inf")
        flat = a_s.reshape(6 * k, ns)
        joint = flat @ s_cov @ flat.T                       # (6K, 6K), index k*6 + j
        for i in range(k):
            joint[6 * i:6 * i + 6, 6 * i:6 * i + 6] += c[i]
        var = np.maximum(np.diagonal(joint).reshape(k, 6), 0.0)
    travel = srd - srd[0]
    a = np.stack([np.ones(k), travel], axis=1)
    if k >= 2 and np.ptp(travel) > 0:
        hat = a @ np.linalg.pinv(a)
    else:
        hat = np.full((k, k), 1.0 / k)
    resid_op = np.eye(k) - hat

    def detrend(j):
        y = m[:, j]
        line = np.linalg.lstsq(a, y, rcond=None)[0] if k >= 2 and np.ptp(travel) > 0 else np.array([y.mean(), 0.0])
        if joint is None:
            u = np.sqrt(np.einsum("ij,j,ij->i", resid_op, var[:, j], resid_op))
        else:
            cj = joint[j::6, j::6]                           # (K, K) covariance of component j
            u = np.sqrt(np.maximum(np.diag(resid_op @ cj @ resid_op.T), 0.0))
        return resid_op @ y, u, line

    sx, usx, lx = detrend(0)
    sy, usy, ly = detrend(1)
    sd = np.sqrt(var)
    return ErrorMap(
        srd_reported_m=srd, travel_m=travel, positioning_m=m[:, 2] - travel,
        straightness_x_m=sx, straightness_y_m=sy, pitch_rad=m[:, 3].copy(), yaw_rad=m[:, 4].copy(),
        roll_rad=m[:, 5].copy(), u_positioning_m=sd[:, 2], u_straightness_x_m=usx, u_straightness_y_m=usy,
        u_pitch_rad=sd[:, 3], u_yaw_rad=sd[:, 4], u_roll_rad=sd[:, 5], line_x=lx, line_y=ly)
