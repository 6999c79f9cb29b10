"""Stage error map (Ferrucci et al. 2020, end of section 3.3; sign from section 4.1).

Sign, everywhere in this project: the paper's (section 4.1). "A positive
positioning error corresponds to the sample stage travelling LESS than its
indexed displacement", i.e. the measured position lies towards the source:
``positioning = reading change - measured displacement``. ISO 230-2 tabulates
the positioning deviation as actual minus target position, the negative of
this.

Two definitions of positioning and straightness, selected by ``definition``:

``"travel"`` (default; ISO 230-1 geometry, what a laser interferometer aligned
    with the axis measures): the stage's own travel direction t is fitted as the
    least-squares line through the measured displacements d_k (dx_R, dy_R, dz_R
    in {DF}) against the reading change s_k. Positioning = s_k - (d_k - d_1) . t.
    X / Y straightness = deviations of d_k from that line perpendicular to t,
    resolved along the {DF} X axis projected on the plane perpendicular to t
    (x') and y' = t x x'. The angle between t and the detector normal is
    reported: with sub-degree detector tilts the two definitions of positioning
    differ by s (1 - cos angle), tens of micrometres over 360 mm.
``"detector"`` (the paper's section 3.3, kept for comparison with the paper):
    positioning = s_k - (dz_R,k - dz_R,1), along the detector normal; X / Y
    straightness = residuals of straight-line least-squares fits of dx_R and
    dy_R against s_k.

Angles (both definitions): pitch, yaw, roll = gamma_X, gamma_Y, gamma_Z of eq. 9,
rotations about the {DF} axes.

Yaw and the rotary table's zero: the stage turns a full revolution at every
position, and a rotary indexing error on returning to zero is a rotation about
the rotation axis that no single campaign can tell from gamma_Y (paper, section
4.3). The reported yaw therefore contains the difference of the index errors of
position k and of position 1. When the instrument states its indexing
repeatability (``index_repeatability_rad``), u(yaw) includes it (variance
2 s^2, covariance s^2 between positions k, l > 1); when it does not, u(yaw)
covers the measurement noise only and the map says so (``notes``).

Uncertainties are propagated linearly from the covariance of the motions,
which may be per position (K, 6, 6) or joint over all positions (6K, 6K):
the static geometry is common to every position, so its uncertainty is
correlated across positions; :func:`joint_motion_covariance` builds that
matrix. The map is a smooth function of the motions; its Jacobian is taken by
central differences (the map is linear in the angles and nearly linear in the
displacements).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

ARCSEC_PER_RAD = 180.0 * 3600.0 / np.pi

#: the six components of a map, in the order of :attr:`ErrorMap.covariance`
COMPONENT_FIELDS = ("positioning_m", "straightness_x_m", "straightness_y_m", "pitch_rad", "yaw_rad", "roll_rad")
DEFINITIONS = ("travel", "detector")

DEFINITION_TEXT = {
    "travel": ("ISO 230-1 geometry: positioning = reading change - displacement along the fitted travel "
               "direction (positive: the stage travelled less than indexed, towards the source; Ferrucci "
               "et al. 2020 section 4.1 sign, the negative of ISO 230-2's actual - target); X/Y straightness "
               "= deviations from the fitted travel line perpendicular to it"),
    "detector": ("Ferrucci et al. 2020 section 3.3, detector frame: positioning = reading change - dz_R along "
                 "the detector normal (positive: travelled less than indexed); X/Y straightness = residuals "
                 "of straight-line fits of dx_R / dy_R against the reading change"),
}
YAW_NOTE = ("yaw contains the rotary table's zero-index error at each position relative to position 1 "
            "(not separable from gamma_Y in one campaign; Ferrucci et al. 2020 section 4.3)")


def _arr(x, name, k=None, allow_nan=True):
    a = np.array(x, dtype=float)
    if a.ndim != 1 or (k is not None and a.shape[0] != k):
        raise ValueError(f"{name} must have shape ({'K' if k is None else k},), got {a.shape}")
    if np.any(np.isinf(a)) or (not allow_nan and np.any(np.isnan(a))):
        raise ValueError(f"{name} contains {'inf' if allow_nan else 'NaN or inf'}")
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class ErrorMap:
    """Stage error map over K positions, one definition (module docstring).

    The same type holds a solved map (with uncertainties) and an independent
    reference (laser interferometer, electronic level: NaN where a component
    was not measured, no uncertainties).

    Attributes
    ----------
    name : str
        Label, e.g. "multi", "single", "reference", "truth".
    definition : str
        "travel" (ISO 230-1 geometry) or "detector" (the paper's).
    srd_reported_m : ndarray of shape (K,)
        Instrument-reported SRD of each position [m]; position 0 is k = 1.
    positioning_m, straightness_x_m, straightness_y_m : ndarray of shape (K,)
        [m], sign as in the module docstring.
    pitch_rad, yaw_rad, roll_rad : ndarray of shape (K,)
        gamma_X, gamma_Y, gamma_Z [rad].
    u_positioning_m, ..., u_roll_rad : ndarray of shape (K,) or None
        Standard uncertainties (k = 1); None when unknown (references).
    travel_direction_df : ndarray of shape (3,)
        Fitted unit travel direction in {DF} (NaN when not fitted).
    angle_travel_normal_rad, u_angle_travel_normal_rad : float
        Angle between the travel direction and the detector normal [rad].
    index_repeatability_rad : float or None
        Rotary indexing repeatability included in u(yaw) (None: unknown, not included).
    covariance : ndarray of shape (6K, 6K) or None
        Joint covariance of all components, index ``6 k + c`` with c in
        :data:`COMPONENT_FIELDS` order (SI units).
    notes : tuple of str
        Caveats every consumer must see (definition, yaw).
    """

    name: str
    definition: str
    srd_reported_m: np.ndarray
    positioning_m: np.ndarray
    straightness_x_m: np.ndarray
    straightness_y_m: np.ndarray
    pitch_rad: np.ndarray
    yaw_rad: np.ndarray
    roll_rad: np.ndarray
    u_positioning_m: np.ndarray | None = None
    u_straightness_x_m: np.ndarray | None = None
    u_straightness_y_m: np.ndarray | None = None
    u_pitch_rad: np.ndarray | None = None
    u_yaw_rad: np.ndarray | None = None
    u_roll_rad: np.ndarray | None = None
    travel_direction_df: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    angle_travel_normal_rad: float = np.nan
    u_angle_travel_normal_rad: float = np.nan
    index_repeatability_rad: float | None = None
    covariance: np.ndarray | None = field(default=None, repr=False)
    notes: tuple = ()

    def __post_init__(self):
        if self.definition not in DEFINITIONS:
            raise ValueError(f"definition must be one of {DEFINITIONS}, got {self.definition!r}")
        srd = _arr(self.srd_reported_m, "srd_reported_m", allow_nan=False)
        k = srd.size
        if k == 0:
            raise ValueError("srd_reported_m must not be empty")
        object.__setattr__(self, "srd_reported_m", srd)
        for f in COMPONENT_FIELDS:
            object.__setattr__(self, f, _arr(getattr(self, f), f, k))
            u = getattr(self, "u_" + f)
            if u is not None:
                u = _arr(u, "u_" + f, k)
                if np.any(u < 0):
                    raise ValueError(f"u_{f} must be non-negative")
                object.__setattr__(self, "u_" + f, u)
        t = np.asarray(self.travel_direction_df, dtype=float).reshape(-1)
        if t.shape != (3,):
            raise ValueError(f"travel_direction_df must have shape (3,), got {t.shape}")
        object.__setattr__(self, "travel_direction_df", t)
        if self.covariance is not None:
            c = np.asarray(self.covariance, dtype=float)
            if c.shape != (6 * k, 6 * k):
                raise ValueError(f"covariance must have shape ({6 * k}, {6 * k}), got {c.shape}")
            object.__setattr__(self, "covariance", c)
        object.__setattr__(self, "notes", tuple(str(n) for n in self.notes))

    @classmethod
    def reference(cls, name, srd_reported_m, definition: str = "travel", **components) -> "ErrorMap":
        """An independent reference map: given components in SI units, the others NaN."""
        srd = np.asarray(srd_reported_m, dtype=float)
        unknown = set(components) - set(COMPONENT_FIELDS)
        if unknown:
            raise ValueError(f"unknown components {sorted(unknown)}; expected some of {COMPONENT_FIELDS}")
        vals = {f: components.get(f, np.full(srd.shape, np.nan)) for f in COMPONENT_FIELDS}
        return cls(name=str(name), definition=definition, srd_reported_m=srd, **vals)

    # ------------------------------------------------------------------ access
    @property
    def k(self) -> int:
        return int(self.srd_reported_m.size)

    @property
    def travel_m(self) -> np.ndarray:
        """Reading change from position 1 [m], shape (K,)."""
        return self.srd_reported_m - self.srd_reported_m[0]

    @property
    def has_uncertainty(self) -> bool:
        return self.u_positioning_m is not None

    def values(self, comp: str) -> np.ndarray:
        """One component (a name of :data:`COMPONENT_FIELDS`), SI units."""
        if comp not in COMPONENT_FIELDS:
            raise ValueError(f"unknown component {comp!r}")
        return getattr(self, comp)

    def uncertainty(self, comp: str) -> np.ndarray | None:
        """Standard uncertainty of one component (k = 1), or None."""
        if comp not in COMPONENT_FIELDS:
            raise ValueError(f"unknown component {comp!r}")
        return getattr(self, "u_" + comp)

    @property
    def definition_text(self) -> str:
        return DEFINITION_TEXT[self.definition]

    @property
    def pitch_arcsec(self) -> np.ndarray:
        return self.pitch_rad * ARCSEC_PER_RAD

    @property
    def yaw_arcsec(self) -> np.ndarray:
        return self.yaw_rad * ARCSEC_PER_RAD

    @property
    def roll_arcsec(self) -> np.ndarray:
        return self.roll_rad * ARCSEC_PER_RAD

    def as_truth_dict(self) -> dict:
        """Values under the keys of scenario.CampaignTruth.error_map()."""
        return {f: self.values(f) for f in COMPONENT_FIELDS}

    def uncertainty_dict(self) -> dict:
        """Standard uncertainties under the same keys (NaN arrays when unknown)."""
        nan = np.full(self.k, np.nan)
        return {f: (nan if self.uncertainty(f) is None else self.uncertainty(f)) for f in COMPONENT_FIELDS}

    def to_dict(self) -> dict:
        """Plain dict (SI, plus arcsecond copies of the angles) for YAML / JSON export."""
        d = {"name": self.name, "definition": self.definition, "definition_text": self.definition_text,
             "sign": "positive = the stage travelled less than its indexed displacement (towards the source)",
             "srd_reported_m": self.srd_reported_m.tolist(), "travel_m": self.travel_m.tolist()}
        for f in COMPONENT_FIELDS:
            d[f] = self.values(f).tolist()
            u = self.uncertainty(f)
            d["u_" + f] = None if u is None else u.tolist()
        for a in ("pitch", "yaw", "roll"):
            d[f"{a}_arcsec"] = (getattr(self, f"{a}_rad") * ARCSEC_PER_RAD).tolist()
            u = getattr(self, f"u_{a}_rad")
            d[f"u_{a}_arcsec"] = None if u is None else (u * ARCSEC_PER_RAD).tolist()
        d["travel_direction_df"] = self.travel_direction_df.tolist()
        d["angle_travel_normal_rad"] = float(self.angle_travel_normal_rad)
        d["u_angle_travel_normal_rad"] = float(self.u_angle_travel_normal_rad)
        d["index_repeatability_rad"] = self.index_repeatability_rad
        d["covariance_order"] = "index 6 k + c, c in " + ", ".join(COMPONENT_FIELDS)
        d["covariance"] = None if self.covariance is None else self.covariance.tolist()
        d["notes"] = list(self.notes)
        d["units"] = "SI (m, rad); *_arcsec in arcseconds"
        return d


# ---------------------------------------------------------------------------------------------
def joint_motion_covariance(conditional, static_sensitivities=None, static_covariance=None,
                            shared_sensitivities=None, shared_covariance=None) -> np.ndarray:
    """Joint covariance (6K, 6K) of the motions of K positions.

    ``Cov(m_k, m_l) = delta_kl C_k + A_k S A_l^T + B_k U B_l^T``: C_k the
    conditional covariance of position k (its own noise), A_k = d m_k / d x_static
    with S the static covariance (the static estimate is common to all
    positions), and optionally any other shared input (e.g. the reference
    object's calibrated centres) with sensitivities B_k and covariance U.

    Parameters
    ----------
    conditional : array_like of shape (K, 6, 6)
    static_sensitivities : array_like of shape (K, 6, n_s), optional
    static_covariance : array_like of shape (n_s, n_s), optional
    shared_sensitivities : array_like of shape (K, 6, n_u), optional
    shared_covariance : array_like of shape (n_u, n_u), optional
    """
    c = np.asarray(conditional, dtype=float)
    if c.ndim != 3 or c.shape[1:] != (6, 6):
        raise ValueError(f"conditional must have shape (K, 6, 6), got {c.shape}")
    k = c.shape[0]
    joint = np.zeros((6 * k, 6 * k))
    for a_s, s_cov, what in ((static_sensitivities, static_covariance, "static"),
                             (shared_sensitivities, shared_covariance, "shared")):
        if a_s is None and s_cov is None:
            continue
        if a_s is None or s_cov is None:
            raise ValueError(f"{what}_sensitivities and {what}_covariance go together")
        a_s = np.asarray(a_s, dtype=float)
        s_cov = np.asarray(s_cov, dtype=float)
        n = s_cov.shape[0]
        if s_cov.shape != (n, n) or a_s.shape != (k, 6, n):
            raise ValueError(f"{what}_sensitivities must be ({k}, 6, n) and {what}_covariance (n, n), got "
                             f"{a_s.shape} and {s_cov.shape}")
        flat = a_s.reshape(6 * k, n)
        joint += flat @ s_cov @ flat.T
    for i in range(k):
        joint[6 * i:6 * i + 6, 6 * i:6 * i + 6] += c[i]
    if not np.all(np.isfinite(joint)):
        raise ValueError("motion covariance contains NaN or inf")
    return joint


def _line_fit(s, y):
    """Least-squares line y ~ a + b s; returns (a, b, residuals). y of shape (K,) or (K, n)."""
    a = np.stack([np.ones_like(s), s], axis=1)
    coef = np.linalg.lstsq(a, y, rcond=None)[0]
    return coef[0], coef[1], y - a @ coef


def _map_values(srd, motions, definition):
    """Map components (K, 6) and the fitted unit travel direction (3,) from motions (K, 6).

    The travel direction is fitted whatever the definition (it is reported with
    both); NaN when the readings do not change.
    """
    s = srd - srd[0]
    d = motions[:, :3] - motions[0, :3]
    out = np.empty((len(s), 6))
    out[:, 3:] = motions[:, 3:]
    if len(s) < 2 or np.ptp(s) <= 0:
        out[:, 0] = s - d[:, 2]
        out[:, 1:3] = 0.0
        return out, np.full(3, np.nan)
    _, b, resid = _line_fit(s, d)
    t_dir = b / np.linalg.norm(b)
    if definition == "detector":
        out[:, 0] = s - d[:, 2]
        out[:, 1] = resid[:, 0]          # the line fits of dx and dy separately are the columns
        out[:, 2] = resid[:, 1]
        return out, t_dir
    xp = np.array([1.0, 0.0, 0.0]) - t_dir[0] * t_dir
    xp /= np.linalg.norm(xp)
    yp = np.cross(t_dir, xp)
    out[:, 0] = s - d @ t_dir
    out[:, 1] = resid @ xp
    out[:, 2] = resid @ yp
    return out, t_dir


def _angle_to_normal(t_dir) -> float:
    return float(np.arccos(min(abs(t_dir[2]), 1.0))) if np.all(np.isfinite(t_dir)) else np.nan


def error_map(srd_reported_m, motions, motion_covariance=None, *, definition: str = "travel",
              name: str = "multi", index_repeatability_rad: float | None = None) -> ErrorMap:
    """Error map from per-position error motions.

    Parameters
    ----------
    srd_reported_m : array_like of shape (K,)
        Instrument-reported SRD at each position [m]; position 0 is k = 1.
    motions : array_like of shape (K, 6)
        dx_R, dy_R, dz_R [m], gamma_X, gamma_Y, gamma_Z [rad] per position in
        {DF} (row 0 is k = 1, normally zeros).
    motion_covariance : array_like of shape (K, 6, 6) or (6K, 6K), optional
        Per-position covariances (positions independent) or the joint
        covariance of all positions (:func:`joint_motion_covariance`). None
        gives a map without uncertainties.
    definition : {"travel", "detector"}
        See the module docstring.
    name : str
    index_repeatability_rad : float, optional
        Standard uncertainty of the rotary table's zero index [rad]; included in u(yaw).

    Returns
    -------
    ErrorMap
    """
    if definition not in DEFINITIONS:
        raise ValueError(f"definition must be one of {DEFINITIONS}, got {definition!r}")
    srd = np.asarray(srd_reported_m, dtype=float)
    m = np.asarray(motions, dtype=float)
    if srd.ndim != 1 or srd.size < 1:
        raise ValueError(f"srd_reported_m must have shape (K,), got {srd.shape}")
    k = srd.size
    if m.shape != (k, 6):
        raise ValueError(f"motions must have shape ({k}, 6), got {m.shape}")
    if not (np.all(np.isfinite(srd)) and np.all(np.isfinite(m))):
        raise ValueError("srd_reported_m or motions contain NaN or inf")
    if index_repeatability_rad is not None and not (np.isfinite(index_repeatability_rad)
                                                    and index_repeatability_rad >= 0):
        raise ValueError(f"index_repeatability_rad must be >= 0, got {index_repeatability_rad}")
    vals, t_dir = _map_values(srd, m, definition)
    angle = _angle_to_normal(t_dir)
    notes = [DEFINITION_TEXT[definition], YAW_NOTE]
    cov_y = u = None
    u_angle = np.nan
    if motion_covariance is not None:
        c = np.asarray(motion_covariance, dtype=float)
        if c.shape == (k, 6, 6):
            c = joint_motion_covariance(c)
        elif c.shape != (6 * k, 6 * k):
            raise ValueError(f"motion_covariance must have shape ({k}, 6, 6) or ({6 * k}, {6 * k}), got {c.shape}")
        if not np.all(np.isfinite(c)):
            raise ValueError("motion_covariance contains NaN or inf")
        # Jacobian of (map components, travel angle) w.r.t. the motions: identity for the
        # angles, central differences for the displacements
        lin = np.zeros((6 * k + 1, 6 * k))
        for i in range(k):
            for j in range(3, 6):
                lin[6 * i + j, 6 * i + j] = 1.0
            for j in range(3):
                h = 1e-7
                mp, mm = m.copy(), m.copy()
                mp[i, j] += h
                mm[i, j] -= h
                vp, tp = _map_values(srd, mp, definition)
                vm, tm = _map_values(srd, mm, definition)
                dv = (vp - vm) / (2 * h)
                dv[:, 3:] = 0.0
                lin[:6 * k, 6 * i + j] = dv.ravel()
                lin[6 * k, 6 * i + j] = (_angle_to_normal(tp) - _angle_to_normal(tm)) / (2 * h)
        full = lin @ c @ lin.T
        cov_y = full[:6 * k, :6 * k].copy()
        u_angle = float(np.sqrt(max(full[6 * k, 6 * k], 0.0))) if np.isfinite(angle) else np.nan
        if index_repeatability_rad is not None and k > 1:
            s2 = float(index_repeatability_rad) ** 2
            yaw = np.arange(1, k) * 6 + 4
            cov_y[np.ix_(yaw, yaw)] += s2 * (np.ones((k - 1, k - 1)) + np.eye(k - 1))
        u = np.sqrt(np.maximum(np.diag(cov_y), 0.0)).reshape(k, 6)
    if index_repeatability_rad is None:
        notes.append("u(yaw) covers the measurement only: the rotary indexing repeatability is unknown "
                     "(give it in the instrument file to include it)")
    else:
        notes.append(f"u(yaw) includes a rotary indexing repeatability of "
                     f"{index_repeatability_rad * ARCSEC_PER_RAD:.3g} arcsec")
    kw = {}
    if u is not None:
        kw = {"u_" + f: u[:, j] for j, f in enumerate(COMPONENT_FIELDS)}
    return ErrorMap(name=str(name), definition=definition, srd_reported_m=srd,
                    **{f: vals[:, j] for j, f in enumerate(COMPONENT_FIELDS)}, **kw,
                    travel_direction_df=t_dir, angle_travel_normal_rad=angle, u_angle_travel_normal_rad=u_angle,
                    index_repeatability_rad=index_repeatability_rad, covariance=cov_y, notes=tuple(notes))
