"""Per-position stage error motions (Ferrucci et al. 2020, section 3.3, App. B).

For each stage position k the six parameters dx_R, dy_R, dz_R, gamma_X,
gamma_Y, gamma_Z are fitted by Levenberg-Marquardt to the observed centres at
that position, on top of the k = 1 geometry in {DF} (eqs 4-7) from the
static solve. Two modes, as in the paper: all projections ("multi") or a
single projection ("single", the first one, j = 1, unless told otherwise).

Uncertainty: ``covariance`` is CONDITIONAL on the static geometry (the
static parameters taken as exact): the observation noise of this position as
estimated from its own residuals (noise.py: per-axis scale of the detector's
sigma and a per-projection shared shift; in "single" mode the shared shift,
invisible in one projection, comes from a multi-projection solve of the same
position), in sandwich form. ``covariance_total`` adds the static geometry's
noise, propagated linearly, ``A S_noise A^T`` with
``A = d m / d x_static = -(J_m^T W J_m)^-1 J_m^T W J_s`` (implicit-function
theorem at the optimum; J_s by forward differences with steps of 0.1
standard uncertainty of each static parameter), and, when the static result
carries the calibrated centres' uncertainty, their effect ``H U H^T`` with
``H = d m / d C`` through both paths (directly, and through the static
geometry). The static and centre parts are COMMON to all positions;
error_map.joint_motion_covariance builds the joint covariance from
``covariance``, ``static_sensitivity`` and ``centre_sensitivity``.

Entry point: :func:`solve_error_motion`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .ct_model import MotionKernel, lm_function
from .geometry import (MOTION_PARAM_NAMES, MOTION_PARAM_UNITS, DetectorFrameGeometry, DetectorSpec, motion_rotation,
                       static_to_detector_frame)
from .lm import LOSSES, STOL, correlation_from_covariance, covariance_from_jacobian, levenberg_marquardt
from .noise import (MAX_RMS_RATIO, NoiseModel, assess_fit, axis_normals, axis_weights_sigma, estimate_noise,
                    sandwich_covariance)
from .observations import CentreObservations
from .static_solver import FitResult, StaticResult, _plain, status_fields, systematic_response
from .terms import check_terms

MODES = ("multi", "single")


@dataclass(frozen=True)
class MotionResult(FitResult):
    """Error motion of one stage position k relative to k = 1.

    Attributes
    ----------
    x : ndarray of shape (6,)
        dx_R, dy_R, dz_R [m], gamma_X, gamma_Y, gamma_Z [rad], in {DF}.
    names, units : tuple of str
    covariance : ndarray of shape (6, 6)
        Conditional on the static geometry: the observation noise of this
        position (noise.py model, sandwich form).
    covariance_total : ndarray of shape (6, 6) or None
        Including the propagated static-geometry noise and, when known, the
        calibrated centres' uncertainty (None when the static uncertainty was
        not available or not requested).
    correlation : ndarray of shape (6, 6)
        Of ``covariance``.
    normal_inverse : ndarray of shape (6, 6)
    variance_factor : float
    residuals_px : ndarray of shape (Q, 2)
        observed - modelled (col, row) [px].
    rms_px, cost : float
    success : bool
    status : int
    message : str
    nfev, njev, n_iter, n_obs, n_views : int
    mode : str
    condition : float
    x0 : ndarray of shape (6,)
    srd_reported_k_m, srd_reported_1_m : float
    static_sensitivity : ndarray of shape (6, n_static) or None
        A = d m / d x_static; error_map uses it to build the joint covariance
        of all positions (the static error is common to them).
    centre_sensitivity : ndarray of shape (6, 3N) or None
        H = d m / d (calibrated centres), total (direct and through the static geometry).
    outcome : str
        As StaticResult.outcome.
    noise : NoiseModel or None
    systematic_shift : ndarray of shape (6,) or None
        The motion's shift for the observations' shared systematic pattern at one sd
        (CentreObservations.systematic_px), directly and through the static geometry
        (StaticResult.systematic_sensitivity); its outer product is in ``covariance_total``
        and the error map's joint covariance holds it as one more shared input.
    """

    covariance_total: np.ndarray | None
    mode: str
    condition: float
    x0: np.ndarray
    srd_reported_k_m: float
    srd_reported_1_m: float
    static_sensitivity: np.ndarray | None = None
    centre_sensitivity: np.ndarray | None = None
    outcome: str = "success"
    noise: NoiseModel | None = None
    systematic_shift: np.ndarray | None = None

    @property
    def std(self) -> np.ndarray:
        """Conditional standard uncertainties, shape (6,)."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    @property
    def std_total(self) -> np.ndarray | None:
        """Standard uncertainties including the static geometry, shape (6,) or None."""
        if self.covariance_total is None:
            return None
        return np.sqrt(np.maximum(np.diag(self.covariance_total), 0.0))

    def to_dict(self) -> dict:
        """Plain-Python dict for YAML / JSON export."""
        return _plain({
            "names": list(self.names), "units": list(self.units), "x": self.x, "std": self.std,
            "std_total": self.std_total, "covariance": self.covariance,
            "covariance_total": self.covariance_total, "correlation": self.correlation,
            "variance_factor": self.variance_factor, "rms_px": self.rms_px, "cost": self.cost,
            "success": self.success, **status_fields(self.success, self.outcome, self.status), "message": self.message,
            "nfev": self.nfev, "njev": self.njev, "n_iter": self.n_iter, "n_obs": self.n_obs,
            "n_views": self.n_views, "mode": self.mode, "condition": self.condition,
            "srd_reported_k_m": self.srd_reported_k_m, "srd_reported_1_m": self.srd_reported_1_m,
            "outcome": self.outcome, "noise": None if self.noise is None else self.noise.to_dict(),
        })


def _failed(obs, mode, x0, srd_k, srd_1, message, outcome="insufficient_data"):
    nan = np.full((6, 6), np.nan)
    return MotionResult(x=x0, names=MOTION_PARAM_NAMES, units=MOTION_PARAM_UNITS, covariance=nan,
                        covariance_total=None, correlation=nan, normal_inverse=nan, variance_factor=np.nan,
                        residuals_px=np.full((obs.n_obs, 2), np.nan), rms_px=np.nan, cost=np.nan, success=False,
                        status=-10, message=message, nfev=0, njev=0, n_iter=0, n_obs=obs.n_obs,
                        n_views=obs.n_views, mode=mode, condition=np.inf, x0=x0, srd_reported_k_m=srd_k,
                        srd_reported_1_m=srd_1, outcome=outcome)


def solve_error_motion(obs_k: CentreObservations, static, detector: DetectorSpec, srd_reported_k_m: float,
                       srd_reported_1_m: float, *, mode: str = "multi", view_index: int | None = None,
                       include_static_uncertainty: bool = True, loss: str = "linear",
                       f_scale_px: float | None = None, x0=None, terms=(), term_params=(),
                       max_iter: int = 100, max_rms_px: float = 2.0, cond_limit: float = 1e10,
                       max_rms_ratio: float = MAX_RMS_RATIO, view_sd_px=None) -> MotionResult:
    """Solve the error motion of stage position k (section 3.3).

    Parameters
    ----------
    obs_k : CentreObservations
        Observed centres at position k.
    static : StaticResult or DetectorFrameGeometry
        The k = 1 solution. With a StaticResult its terms (with their fitted
        values) are applied and its covariance can be propagated; with a bare
        DetectorFrameGeometry the result is conditional on it and ``terms`` /
        ``term_params`` may be given explicitly.
    detector : DetectorSpec
    srd_reported_k_m, srd_reported_1_m : float
        Instrument-reported SRD at position k and at k = 1 [m]; their
        difference is the nominal travel, used for the start point only.
    mode : {"multi", "single"}
        All projections, or one projection (``view_index``, default the
        first one: the paper's j = 1).
    include_static_uncertainty : bool
        Compute ``covariance_total`` (needs a successful StaticResult).
    loss, f_scale_px
        Robust loss as in solve_static (f_scale default 2.5 robust sigma).
    x0 : array_like of shape (6,), optional
        Start; default: the nominal travel along the source -> stage
        direction in {DF}, no rotation.
    max_rms_px, max_rms_ratio : float
        Quality gate, as in solve_static (noise.assess_fit).
    view_sd_px : (float, float), optional
        Shared per-projection shift sd (u, v) [px]; default: estimated from
        the residuals (multi), or from a multi solve of ``obs_k`` (single).

    Returns
    -------
    MotionResult
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    if loss not in LOSSES:
        raise ValueError(f"unknown loss {loss!r}; choose one of {LOSSES}")
    if not isinstance(obs_k, CentreObservations):
        raise ValueError(f"obs_k must be a CentreObservations, got {type(obs_k).__name__}")
    if not isinstance(detector, DetectorSpec):
        raise ValueError(f"detector must be a DetectorSpec, got {type(detector).__name__}")
    for name, v in (("srd_reported_k_m", srd_reported_k_m), ("srd_reported_1_m", srd_reported_1_m)):
        if np.ndim(v) != 0 or not np.isfinite(float(v)) or float(v) <= 0:
            raise ValueError(f"{name} must be a positive finite scalar, got {v!r}")
    srd_k, srd_1 = float(srd_reported_k_m), float(srd_reported_1_m)
    static_res = None
    if isinstance(static, StaticResult):
        if not static.success or static.geometry is None:
            raise ValueError(f"the static solution did not succeed: {static.message}")
        static_res = static
        geom = static.geometry
        terms, term_params = static.terms, static.term_params
    elif isinstance(static, DetectorFrameGeometry):
        geom = static
        terms = check_terms(terms)
    else:
        raise ValueError(f"static must be a StaticResult or DetectorFrameGeometry, got {type(static).__name__}")
    obs = obs_k
    if mode == "single":
        if obs_k.n_obs == 0:
            obs = obs_k
        elif view_index is None:
            obs = obs_k.first_view()
        else:
            obs = obs_k.select(obs_k.view_index == int(view_index))
    obs.check_spheres(len(geom.centres_df_m))

    direction = geom.stage_df_m - geom.source_df_m
    direction = direction / np.linalg.norm(direction)
    if x0 is None:
        start = np.concatenate([(srd_k - srd_1) * direction, np.zeros(3)])
    else:
        start = np.asarray(x0, dtype=float)
        if start.shape != (6,) or not np.all(np.isfinite(start)):
            raise ValueError(f"x0 must be 6 finite values, got shape {start.shape}")

    n_sph = obs.n_spheres_seen
    if n_sph < 4:
        return _failed(obs, mode, start, srd_k, srd_1,
                       f"too few spheres: {n_sph} distinct spheres observed in {mode} mode, need at least 4")
    seen = np.unique(obs.sphere_index)
    pts = geom.centres_df_m[seen] - geom.centres_df_m[seen].mean(axis=0)
    sv = np.linalg.svd(pts, compute_uv=False)
    if sv[1] <= 1e-6 * sv[0]:
        return _failed(obs, mode, start, srd_k, srd_1, "degenerate: the observed spheres are collinear",
                       outcome="degenerate")

    # blocked order (all u, then all v) with a lazy Jacobian; interleaved again for the result
    kern = MotionKernel(geom, obs, detector, terms, term_params)
    sigma = None if obs.sigma_px is None else np.concatenate([obs.sigma_px, obs.sigma_px])
    fun = lm_function(kern)
    res = levenberg_marquardt(fun, None, start, sigma=sigma, max_iter=max_iter, stol=STOL, chord_test=True)
    nfev, njev, nit = res.nfev, res.njev, res.n_iter
    if loss != "linear":
        rw = res.residuals if sigma is None else res.residuals / sigma
        if f_scale_px is None:
            f = 2.5 * max(1.4826 * float(np.median(np.abs(rw - np.median(rw)))), 1e-12)
        else:
            f = float(f_scale_px) if sigma is None else float(f_scale_px) / float(np.median(obs.sigma_px))
        res = levenberg_marquardt(fun, None, res.x, sigma=sigma, loss=loss, f_scale=f, max_iter=max_iter, stol=STOL)
        nfev, njev, nit = nfev + res.nfev, njev + res.njev, nit + res.n_iter
    if not (np.all(np.isfinite(res.x)) and np.all(np.isfinite(res.residuals))):
        return _failed(obs, mode, start, srd_k, srd_1, f"the solve diverged: {res.message}", outcome="failed")
    if view_sd_px is None and mode == "single" and obs_k.n_views > 1:
        # the shift shared by one projection's observations is absorbed by the motion in one
        # projection: take its size from the multi-projection solve of the same position
        multi = solve_error_motion(obs_k, static, detector, srd_k, srd_1, mode="multi",
                                   include_static_uncertainty=False, x0=res.x, terms=terms, term_params=term_params)
        if multi.noise is not None:
            view_sd_px = multi.noise.view_sd_px
    q = obs.n_obs
    r, jac = kern.evaluate(res.x)
    jt = jac()
    # net of the calibrated centres' stated errors when the static solution carries them (their
    # term is in the map's joint covariance); dx_R, dy_R, dz_R move every centre alike, so their
    # columns are each observation's derivatives with respect to its own sphere's position
    u_c = None if static_res is None else static_res.centre_uncertainty_m
    centres = {} if u_c is None else dict(sphere_index=obs.sphere_index, centre_jac=jt[0:3],
                                          centre_var=np.asarray(u_c, dtype=float) ** 2)
    noise = estimate_noise(r, sigma, obs.view_index, 6, view_sd_px=view_sd_px, track=False, **centres)
    w = 1.0 / axis_weights_sigma(sigma, q, noise) if loss == "linear" else res.weights
    normals = axis_normals(jt, 1.0 / w)
    cov = covariance_from_jacobian(jt.T, r, w, cond_limit=cond_limit, normal=normals[0] + normals[1])
    cov_cond = sandwich_covariance(jt, 1.0 / w, axis_weights_sigma(sigma, q, noise), obs.view_index, noise,
                                   cov.normal_inverse, normals=normals)
    success, message = res.success, res.message
    outcome = "success" if success else "not_converged"
    if cov.rank_deficient:
        success, outcome = False, "degenerate"
        d = cov.weakest_direction
        top = np.argsort(-np.abs(d))[:3]
        message = (f"degenerate: Jacobian condition {cov.condition:.3g} exceeds {cond_limit:.3g}; undetermined "
                   "combination ~ " + " ".join(f"{d[i]:+.2f}*{MOTION_PARAM_NAMES[i]}" for i in top))
    else:
        ok, why = assess_fit(r, sigma, obs.view_index, obs.sphere_index, noise, max_rms_ratio=max_rms_ratio,
                             max_rms_px=max_rms_px, robust=loss != "linear")
        if ok and why:
            message = f"{message}; {why}"
        elif not ok:
            success, outcome = False, "poor_fit"
            message = why + f" [solver: {message}]"

    cov_total = sens = centre_sens = d_sys = None
    if include_static_uncertainty and static_res is not None and success:
        sens = _static_sensitivity(res.x, jt.T, w, cov.normal_inverse, static_res, obs, detector)
        d_static = static_res.systematic_sensitivity
        # the noise part (or the total without the systematic, which d_sys carries below)
        s_noise = (static_res.covariance_without_systematic if static_res.covariance_noise is None
                   else static_res.covariance_noise)
        cov_total = cov_cond + sens @ s_noise @ sens.T
        # the shared systematic pattern moves this position's centres and the static geometry alike
        d_direct = systematic_response(obs, jt, w, cov.normal_inverse)
        if d_direct is not None or d_static is not None:
            d_sys = (0.0 if d_direct is None else d_direct) + (0.0 if d_static is None else sens @ d_static)
            cov_total = cov_total + np.outer(d_sys, d_sys)
        if static_res.centre_sensitivity is not None and static_res.centre_uncertainty_m is not None:
            direct = _direct_centre_sensitivity(res.x, jt.T, w, cov.normal_inverse, kern, static_res, obs)
            centre_sens = direct + sens @ static_res.centre_sensitivity
            u2 = np.repeat(np.asarray(static_res.centre_uncertainty_m, dtype=float) ** 2, 3)
            cov_total = cov_total + (centre_sens * u2) @ centre_sens.T
    return MotionResult(
        x=res.x, names=MOTION_PARAM_NAMES, units=MOTION_PARAM_UNITS, covariance=cov_cond,
        covariance_total=cov_total, correlation=correlation_from_covariance(cov_cond),
        normal_inverse=cov.normal_inverse, variance_factor=noise.chi2_dof,
        residuals_px=-res.residuals.reshape(2, -1).T, rms_px=float(np.sqrt(np.mean(res.residuals ** 2))),
        cost=res.cost, success=bool(success), status=res.status, message=message, nfev=nfev, njev=njev,
        n_iter=nit, n_obs=obs.n_obs, n_views=obs.n_views, mode=mode, condition=cov.condition, x0=start,
        srd_reported_k_m=srd_k, srd_reported_1_m=srd_1, static_sensitivity=sens, centre_sensitivity=centre_sens,
        outcome=outcome, noise=noise, systematic_shift=d_sys)


def _direct_centre_sensitivity(m, jac, weights, normal_inverse, kern: MotionKernel, static_res: StaticResult, obs):
    """-(J_m^T W J_m)^-1 J_m^T W d r / d C_OF with the static geometry held: shape (6, 3N).

    A sphere's centre enters position k as point = R_k + G Rot(r_1, alpha) (C_DF - R_1) with
    C_DF = R_det^T (R_obj C_OF + P - D) (eqs 7, 10-11), so d r_q / d C_OF =
    (d r_q / d point) G Rot(r_1, alpha_q) R_det^T R_obj, and d r / d point is the Jacobian's
    dx_R, dy_R, dz_R columns.
    """
    from .ct_model import _angle_stage  # noqa: PLC0415
    from .geometry import detector_rotation, object_rotation, rot_axis_angle  # noqa: PLC0415

    w_static = static_res.x
    n_sph = len(static_res.centres_of_m)
    r_df_of = detector_rotation(*w_static[4:7]).T @ object_rotation(*w_static[10:13])
    g = motion_rotation(m[3], m[4], m[5])
    alpha, _ = _angle_stage(obs.alpha_rad, kern.tpar, kern.terms, obs, 0, 0)
    views, inv = np.unique(alpha, return_inverse=True)
    rots = rot_axis_angle(static_res.geometry.axis_df, views)           # (V, 3, 3)
    chain = np.einsum("ij,vjk,kl->vil", g, rots, r_df_of)[inv]          # (Q, 3, 3) d point / d C_OF
    q = obs.n_obs
    w2 = np.asarray(weights, dtype=float) ** 2
    b = np.zeros((6, n_sph, 3))
    for a in range(2):
        rows = slice(a * q, (a + 1) * q)
        jp = jac[rows, 0:3]                                              # d r / d point (Q, 3)
        dc = np.einsum("qi,qij->qj", jp, chain)                          # d r / d C_OF (Q, 3)
        jw = jac[rows] * w2[rows, None]                                  # (Q, 6)
        for c in range(3):
            prod = jw * dc[:, c][:, None]
            for j in range(6):
                b[j, :, c] += np.bincount(obs.sphere_index, prod[:, j], n_sph)
    return -normal_inverse @ b.reshape(6, 3 * n_sph)


def _static_sensitivity(m, jac, weights, normal_inverse, static_res: StaticResult, obs, detector):
    """A = d m / d x_static at the optimum, shape (6, n_static)."""
    xs = static_res.x
    sd = static_res.std
    nfree = len(xs)
    k0 = MotionKernel(static_res.geometry, obs, detector, static_res.terms, xs[13:])
    r0 = k0.residuals_blocked(m)
    js = np.empty((len(r0), nfree))
    # Forward differences with a step of 0.1 sd: over a tenth of a standard deviation the model
    # is linear: central differences (twice the cost) agreed to 1.5e-6 of the largest entry and
    # to 6 digits in the propagated standard deviations (position k = 19 of the default campaign).
    for i in range(nfree):
        h = max(0.1 * sd[i], 1e-12)
        xp = xs.copy()
        xp[i] += h
        g = static_to_detector_frame(xp[:13], static_res.centres_of_m)
        k = MotionKernel(g, obs, detector, static_res.terms, xp[13:])
        js[:, i] = (k.residuals_blocked(m) - r0) / h
    w = np.asarray(weights, dtype=float)
    jm = jac * w[:, None]
    return -normal_inverse @ (jm.T @ (js * w[:, None]))
