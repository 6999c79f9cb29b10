"""Static CT geometry at stage position k = 1 (Ferrucci et al. 2020, section 3.1).

Levenberg-Marquardt minimisation of the reprojection error (eq. 3) over all
spheres and all projections, 7 instrument + 6 object-pose parameters (+ the
parameters of any optional terms), with

* a start derived from the data (per-sphere trajectory fits under the
  nominal geometry, then a rigid fit to the calibrated centres), so no
  near-truth start is needed;
* an optional robust loss;
* the parameter covariance from the Jacobian and the residual variance,
  with correlations, and explicit failure for degenerate inputs.

Entry point: :func:`solve_static`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .ct_model import StaticKernel, lm_function, param_names, param_units
from .geometry import DetectorFrameGeometry, DetectorSpec, object_rotation, static_to_detector_frame
from .lm import LOSSES, STOL, correlation_from_covariance, covariance_from_jacobian, levenberg_marquardt
from .noise import (MAX_RMS_RATIO, NoiseModel, assess_fit, axis_normals, axis_weights_sigma, estimate_noise,
                    sandwich_covariance)
from .location_noise import class_factors, location_class, on_cylinder, scaled_sigma
from .observations import CentreObservations
from .terms import check_terms


def _plain(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        return v.item()
    if isinstance(v, dict):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


@dataclass(frozen=True)
class FitResult:
    """The fields every least-squares solve of the CT cell reports (StaticResult, error_motion's
    MotionResult); each documents them in its own terms."""

    x: np.ndarray
    names: tuple
    units: tuple
    covariance: np.ndarray
    correlation: np.ndarray
    normal_inverse: np.ndarray
    variance_factor: float
    residuals_px: np.ndarray
    rms_px: float
    cost: float
    success: bool
    status: int
    message: str
    nfev: int
    njev: int
    n_iter: int
    n_obs: int
    n_views: int


@dataclass(frozen=True)
class StaticResult(FitResult):
    """Solution of the static geometry at k = 1.

    Attributes
    ----------
    x : ndarray of shape (n,)
        Estimate: w (13, geometry.py order) then term parameters.
    names, units : tuple of str, length n
    covariance : ndarray of shape (n, n)
        Total covariance: the observation noise as estimated from the data
        (noise.py: per-axis scale of the reported sigma and a per-projection
        shared shift, sandwich form) plus, when the reference object states
        its centres' uncertainty, their propagation. NaN if the solve failed.
    correlation : ndarray of shape (n, n)
    normal_inverse : ndarray of shape (n, n)
        (J^T W J)^-1; with the true pixel sigma, ``sigma^2 * normal_inverse``
        is the Cramer-Rao bound (when ``sigma_px`` was given it already is).
    variance_factor : float
        Reduced chi-square against the detector's reported sigma (px^2 when
        no sigma_px was given): 1 when the data are as noisy as stated.
    residuals_px : ndarray of shape (Q, 2)
        observed - modelled (col, row) at the estimate [px].
    rms_px : float
        Root mean square of all residual coordinates.
    cost : float
    success : bool
    status : int
        LM status (see lm.LMResult); -10 for a rejected (degenerate) input.
    message : str
    nfev, njev, n_iter : int
    n_obs, n_views, n_spheres : int
    condition : float
        Condition number of the column-scaled weighted Jacobian.
    geometry : DetectorFrameGeometry or None
        The solution in {DF} (eqs 4-7).
    x0 : ndarray of shape (n,)
        Start point used.
    loss : str
    f_scale_px : float or None
    terms : tuple of Term
    centres_of_m : ndarray of shape (N, 3)
        The reference centres the solution refers to.
    weights : ndarray of shape (2Q,)
        Final IRLS / whitening weights.
    outcome : str
        One word for the result, shared by every solver (noise.OUTCOMES):
        "success", "not_converged", "degenerate", "insufficient_data",
        "poor_fit" (converged, but the model does not explain the data;
        ``message`` names the likely cause), "failed".
    noise : NoiseModel or None
        Observation noise estimated from the residuals (noise.py).
    covariance_noise : ndarray of shape (n, n) or None
        The part of ``covariance`` due to the observation noise.
    centre_sensitivity : ndarray of shape (n, 3N) or None
        d x / d (calibrated centres in {OF}), flattened sphere by sphere.
    centre_uncertainty_m : ndarray of shape (N,) or None
        Standard uncertainty of each calibrated centre (per coordinate) used.
    systematic_sensitivity : ndarray of shape (n,) or None
        The solution's shift for the observations' shared systematic pattern at one standard
        deviation (CentreObservations.systematic_px): its outer product is in ``covariance``.
    """

    n_spheres: int
    condition: float
    geometry: DetectorFrameGeometry | None
    x0: np.ndarray
    loss: str
    f_scale_px: float | None
    terms: tuple = ()
    centres_of_m: np.ndarray = field(default=None, repr=False)
    weights: np.ndarray = field(default=None, repr=False)
    outcome: str = "success"
    noise: NoiseModel | None = None
    covariance_noise: np.ndarray | None = field(default=None, repr=False)
    centre_sensitivity: np.ndarray | None = field(default=None, repr=False)
    centre_uncertainty_m: np.ndarray | None = field(default=None, repr=False)
    systematic_sensitivity: np.ndarray | None = field(default=None, repr=False)

    @property
    def w(self) -> np.ndarray:
        """The 13 static parameters."""
        return self.x[:13]

    @property
    def term_params(self) -> np.ndarray:
        """Parameters of the optional terms, shape (p,)."""
        return self.x[13:]

    @property
    def std(self) -> np.ndarray:
        """Standard uncertainties sqrt(diag(covariance)), shape (n,)."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    @property
    def covariance_without_systematic(self) -> np.ndarray:
        """``covariance`` less the shared systematic pattern's ``d d^T`` (for propagation that carries
        the pattern separately, with its correlation across stage positions)."""
        d = self.systematic_sensitivity
        return self.covariance if d is None else self.covariance - np.outer(d, d)

    def strong_correlations(self, threshold: float = 0.9):
        """Parameter pairs with |correlation| >= threshold: list of (name_a, name_b, rho)."""
        c = self.correlation
        out = []
        for i in range(len(self.names)):
            for j in range(i + 1, len(self.names)):
                if abs(c[i, j]) >= threshold:
                    out.append((self.names[i], self.names[j], float(c[i, j])))
        return out

    def to_dict(self) -> dict:
        """Plain-Python dict (lists, floats, str) for YAML / JSON export."""
        g = self.geometry
        return _plain({
            "names": list(self.names), "units": list(self.units), "x": self.x,
            "std": self.std, "covariance": self.covariance, "correlation": self.correlation,
            "variance_factor": self.variance_factor, "rms_px": self.rms_px, "cost": self.cost,
            "success": self.success, **status_fields(self.success, self.outcome, self.status), "message": self.message,
            "nfev": self.nfev, "njev": self.njev, "n_iter": self.n_iter, "n_obs": self.n_obs,
            "n_views": self.n_views, "n_spheres": self.n_spheres, "condition": self.condition,
            "loss": self.loss, "f_scale_px": self.f_scale_px, "outcome": self.outcome,
            "noise": None if self.noise is None else self.noise.to_dict(),
            "std_noise_only": None if self.covariance_noise is None else np.sqrt(np.maximum(np.diag(self.covariance_noise), 0)),
            "std_systematic": None if self.systematic_sensitivity is None else np.abs(self.systematic_sensitivity),
            "terms": [t.name for t in self.terms],
            "strong_correlations": [list(c) for c in self.strong_correlations(0.9)],
            "geometry_df": None if g is None else {
                "source_df_m": g.source_df_m, "stage_df_m": g.stage_df_m,
                "axis_df": g.axis_df, "centres_df_m": g.centres_df_m},
        })


# --------------------------------------------------------------------------- inputs
#: outcome word -> metro_msgs/SolveStatus code: the one status vocabulary (io/results.py OUTCOME_CODES)
OUTCOME_CODES = {"success": 0, "not_converged": 1, "degenerate": 2, "insufficient_data": 3, "failed": 4,
                 "poor_fit": 5}


def status_fields(success: bool, outcome: str, lm_status: int) -> dict:
    """Result-file status keys: ``status`` (outcome word), ``status_code`` (SolveStatus code), and the
    optimiser's own code under ``lm_status`` (never next to ``success`` as ``status``)."""
    word = "success" if success else (outcome if outcome in OUTCOME_CODES and outcome != "success" else "failed")
    return {"status": word, "status_code": OUTCOME_CODES[word], "lm_status": int(lm_status)}


def _check_inputs(obs, centres_of_m, detector, srd_m, sdd_m):
    if not isinstance(obs, CentreObservations):
        raise ValueError(f"obs must be a CentreObservations, got {type(obs).__name__}")
    if not isinstance(detector, DetectorSpec):
        raise ValueError(f"detector must be a DetectorSpec, got {type(detector).__name__}")
    c = np.asarray(centres_of_m, dtype=float)
    if c.ndim != 2 or c.shape[1] != 3 or c.shape[0] < 1:
        raise ValueError(f"centres_of_m must have shape (N, 3), got {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("centres_of_m contains NaN or inf")
    obs.check_spheres(len(c))
    for name, v in (("srd_reported_m", srd_m), ("sdd_reported_m", sdd_m)):
        if not (np.isscalar(v) or np.ndim(v) == 0) or not np.isfinite(float(v)) or float(v) <= 0:
            raise ValueError(f"{name} must be a positive finite scalar, got {v!r}")
    if float(sdd_m) <= float(srd_m):
        raise ValueError(f"sdd_reported_m ({sdd_m}) must exceed srd_reported_m ({srd_m})")
    return c, float(srd_m), float(sdd_m)


def _degeneracy(obs, centres, n_params):
    """(reason, outcome) when the static problem cannot be solved, or None."""
    seen = np.flatnonzero(np.bincount(obs.sphere_index, minlength=len(centres)))
    if obs.n_obs * 2 < n_params + 1:
        return (f"too few observations: {obs.n_obs} centres (2 coordinates each) for {n_params} parameters",
                "insufficient_data")
    if seen.size < 4:
        return f"too few spheres: {seen.size} distinct spheres observed, need at least 4", "insufficient_data"
    if obs.n_views < 3:
        return f"too few projections: {obs.n_views}, need at least 3 for the static solve", "insufficient_data"
    p = centres[seen] - centres[seen].mean(axis=0)
    sv = np.linalg.svd(p, compute_uv=False)
    if sv[1] <= 1e-6 * sv[0]:
        return "degenerate reference object: the observed spheres are collinear", "degenerate"
    return None


def _object_angles(r: np.ndarray):
    """(rho_X, rho_Y, rho_Z) with r = Ry(rho_Y) Rz(rho_Z) Rx(rho_X)."""
    rz = np.arcsin(np.clip(r[1, 0], -1.0, 1.0))
    rx = np.arctan2(-r[1, 2], r[1, 1])
    ry = np.arctan2(-r[2, 0], r[0, 0])
    return rx, ry, rz


def _kabsch(a, b):
    """Rotation r and translation t minimising |r a_i + t - b_i|^2, a, b (N, 3)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    h = (a - ca).T @ (b - cb)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cb - r @ ca


def initial_guess(obs: CentreObservations, centres_of_m, detector: DetectorSpec, srd_reported_m: float,
                  sdd_reported_m: float, terms=()):
    """Start point derived from the data and nominal values only.

    Instrument: nominal (z_R = reported SRD, detector centred at the stated
    SDD, no tilt). Object pose: each sphere's k = 1, alpha = 0 position in
    {SRF} is fitted from its own trajectory under the nominal geometry (a
    2 x 2 linear least-squares problem per sphere:
    ``t (-s X + c Z' + z_R) = c X + s Z'``, ``t = u / SDD``, then
    ``Y = mean(v p_z / SDD)``), and the pose is the rigid (Kabsch) fit of
    those positions to the calibrated centres.

    Returns
    -------
    x0 : ndarray of shape (13 + p,)
    n_used : int
        Number of spheres whose trajectory entered the rigid fit.
    """
    terms = check_terms(terms)
    c0, r0 = detector.centre_px
    pitch = detector.pixel_pitch_m
    t = (obs.uv_px[:, 0] - c0) * pitch / sdd_reported_m
    tv = (r0 - obs.uv_px[:, 1]) * pitch / sdd_reported_m
    ca, sa = np.cos(obs.alpha_rad), np.sin(obs.alpha_rad)
    z_r = srd_reported_m
    a1 = -t * sa - ca           # coefficient of X
    a2 = t * ca - sa            # coefficient of Z'
    b = -t * z_r
    idx = obs.sphere_index
    n = len(centres_of_m)
    s11 = np.bincount(idx, a1 * a1, n)
    s12 = np.bincount(idx, a1 * a2, n)
    s22 = np.bincount(idx, a2 * a2, n)
    b1 = np.bincount(idx, a1 * b, n)
    b2 = np.bincount(idx, a2 * b, n)
    cnt = np.bincount(idx, minlength=n)
    det = s11 * s22 - s12 ** 2
    ok = (cnt >= 3) & (det > 1e-12 * np.maximum(s11 * s22, 1e-300))
    safe = np.where(ok, det, 1.0)
    xs = (s22 * b1 - s12 * b2) / safe
    zs = (s11 * b2 - s12 * b1) / safe
    pz = -sa * xs[idx] + ca * zs[idx] + z_r
    ys = np.bincount(idx, tv * pz, n) / np.maximum(cnt, 1)
    c1 = np.stack([xs, ys, zs + z_r], axis=1)
    w = np.zeros(13)
    w[0] = z_r
    w[3] = sdd_reported_m
    if ok.sum() >= 3:
        r, tr = _kabsch(centres_of_m[ok], c1[ok])
        w[7:10] = tr
        w[10:13] = _object_angles(r)
    else:
        w[9] = z_r
    x0 = np.concatenate([w] + [t_.x0() for t_ in terms])
    return x0, int(ok.sum())


def _centre_sensitivity(jac, weights, x, obs: CentreObservations, normal_inverse, n_spheres: int) -> np.ndarray:
    """d x / d (calibrated centres in {OF}) at the optimum, shape (n, 3 N), sphere by sphere.

    Implicit function theorem: dx = -(J^T W J)^-1 J^T W (d r / d C) dC. A centre enters the
    model only through its own observations, as C_SRF = R_obj C_OF + P (eq. 1), so
    d r / d C_i = (d r / d P) R_obj on the rows of sphere i: the Jacobian's x_P, y_P, z_P columns.
    """
    from scipy.sparse import csr_matrix  # noqa: PLC0415

    jac = np.asarray(jac)                                 # (2Q, n) blocked
    w2 = np.asarray(weights, dtype=float) ** 2
    n, m = jac.shape[1], jac.shape[0]
    rows_sphere = np.concatenate([obs.sphere_index, obs.sphere_index])
    # Z (2Q, 3N): row q holds d r_q / d P in the three columns of its sphere; B^T = Z^T W J
    z = csr_matrix((np.ascontiguousarray(jac[:, 7:10]).ravel(),
                    (np.repeat(np.arange(m), 3), (3 * rows_sphere[:, None] + np.arange(3)).ravel())),
                   shape=(m, 3 * n_spheres))
    b = np.asarray(z.T @ (jac * w2[:, None])).reshape(n_spheres, 3, n).transpose(0, 2, 1)    # (N, n, 3)
    r_obj = object_rotation(x[10], x[11], x[12])
    b = b @ r_obj                                        # (N, n, 3): d r / d C_OF = (d r / d P) R_obj
    return -normal_inverse @ b.transpose(1, 0, 2).reshape(n, 3 * n_spheres)


def static_uncertainty(x, kern: StaticKernel, obs: CentreObservations, sigma, n_spheres: int,
                       centre_uncertainty_m=None, cond_limit: float = 1e10, weights=None, evaluated=None):
    """Uncertainty of a static estimate from the data it rests on (the same numbers whoever asks).

    At ``x``: the noise model from the residuals (noise.py; with the correlation of each sphere's
    errors along its track), weights = the reported sigma
    rescaled per axis (or the ``weights`` the estimator used: a robust fit's final IRLS
    weights, or the reported sigma's when no per-axis refit was needed), the sandwich
    covariance of the observation noise, and, with ``centre_uncertainty_m``, the sensitivity to
    the calibrated centres and their contribution.

    ``evaluated`` = (f (2Q,), J (2Q, n)) at ``x`` if already known (the solver's last LM
    iterate), else the kernel is evaluated.

    With ``obs.systematic_px`` (a pattern shared by every observation, one sd), the solution's
    linear response to it, ``d = (J^T W J)^-1 J^T W s`` (:func:`systematic_response`), and its
    outer product, added to the covariance.

    Returns
    -------
    (CovarianceInfo, NoiseModel, cov_noise (n, n), centre_sensitivity (n, 3N) or None, covariance (n, n),
    systematic_sensitivity (n,) or None)
    """
    if evaluated is None:
        r, jac = kern.evaluate(x)
        jt = jac()                                        # (n, 2Q)
    else:
        r, jt = evaluated[0], np.asarray(evaluated[1]).T
    q = obs.n_obs
    u_c = None
    if centre_uncertainty_m is not None:
        u_c = np.broadcast_to(np.asarray(centre_uncertainty_m, dtype=float), (n_spheres,))
        if not np.all(np.isfinite(u_c)) or np.any(u_c < 0):
            raise ValueError(f"centre_uncertainty_m must be >= 0, scalar or shape ({n_spheres},)")
    noise = estimate_noise(r, sigma, obs.view_index, kern.n, sphere_index=obs.sphere_index, centre_jac=jt[7:10],
                           centre_var=None if u_c is None else u_c ** 2)
    sig_model = axis_weights_sigma(sigma, q, noise)
    w = 1.0 / sig_model if weights is None else np.asarray(weights, dtype=float)
    normals = axis_normals(jt, 1.0 / w)
    cov = covariance_from_jacobian(jt.T, r, w, cond_limit=cond_limit, normal=normals[0] + normals[1])
    cov_noise = sandwich_covariance(jt, 1.0 / w, sig_model, obs.view_index, noise,
                                    cov.normal_inverse, normals=normals, sphere_index=obs.sphere_index)
    if noise.track_corr_u or noise.track_corr_v:
        # diagnostic: how much the correlation along the sphere tracks widens each uncertainty
        without = sandwich_covariance(jt, 1.0 / w, sig_model, obs.view_index, noise,
                                      cov.normal_inverse, normals=normals)
        with np.errstate(invalid="ignore", divide="ignore"):
            infl = np.sqrt(np.diag(cov_noise) / np.diag(without))
        noise = replace(noise, track_sd_inflation=tuple(float(v) for v in infl))
    d_sys = systematic_response(obs, jt, w, cov.normal_inverse)
    total = cov_noise if d_sys is None else cov_noise + np.outer(d_sys, d_sys)
    if u_c is None:
        return cov, noise, cov_noise, None, total, d_sys
    sens = _centre_sensitivity(jt.T, w, x, obs, cov.normal_inverse, n_spheres)
    return cov, noise, cov_noise, sens, total + (sens * np.repeat(u_c ** 2, 3)) @ sens.T, d_sys


def systematic_response(obs: CentreObservations, jt, weights, normal_inverse):
    """(n,) linear response of a weighted least-squares solution to the observations' shared
    systematic pattern ``obs.systematic_px`` (one sd; None when there is none): with residuals
    model - observed, observed + s moves the solution by ``(J^T W J)^-1 J^T W s``. ``jt`` (n, 2Q)
    and ``weights`` (2Q,) in blocked order (all columns, then all rows)."""
    s = obs.systematic_px
    if s is None or not np.any(s):
        return None
    sb = np.concatenate([s[:, 0], s[:, 1]])
    w2 = np.asarray(weights, dtype=float) ** 2
    return normal_inverse @ (np.asarray(jt) @ (w2 * sb))


#: hypotheses tried when a fit fails: (description, what to check, transform of (obs, detector))
def _orientation_variants(obs: CentreObservations, detector: DetectorSpec):
    uv = obs.uv_px
    yield ("the image columns mirrored", "check the image orientation (column direction, +X)",
           replace(obs, uv_px=np.column_stack([detector.cols - 1 - uv[:, 0], uv[:, 1]])))
    yield ("the image rows mirrored", "check the image orientation (row direction, row 0 = top)",
           replace(obs, uv_px=np.column_stack([uv[:, 0], detector.rows - 1 - uv[:, 1]])))
    yield ("the rotation reversed", "check the rotation direction (+alpha about +Y, right-hand rule)",
           replace(obs, alpha_rad=-obs.alpha_rad))


def _orientation_hint(obs, centres, detector, srd, sdd, terms, noise, max_rms_ratio) -> str | None:
    """When a fit fails: does the data fit a mirrored image or a reversed rotation instead?"""
    best = None
    for what, check, variant in _orientation_variants(obs, detector):
        try:
            r = solve_static(variant, centres, detector, srd, sdd, terms=terms, max_rms_ratio=max_rms_ratio,
                             _orientation_check=False)
        except ValueError:
            continue
        if r.noise is not None and r.noise.chi2_dof < 0.25 * noise.chi2_dof and (best is None or
                                                                             r.noise.chi2_dof < best[0]):
            best = (r.noise.chi2_dof, what, check, r.success)
    if best is None:
        return None
    chi2, what, check, ok = best
    return (f"{check}: the data fit {what} {'well' if ok else 'much better'} (residuals "
            f"{np.sqrt(chi2):.3g} instead of {np.sqrt(noise.chi2_dof):.3g} times the stated uncertainty)")


COARSE_MIN_VIEWS = 90     # coarse-to-fine only from this many projections on
COARSE_VIEWS = 20         # projections in the coarse subset (evenly spaced in acquisition order)


def _coarse_views(obs: CentreObservations):
    """An even subset of ~COARSE_VIEWS projections for the coarse stage, or None if not worth it."""
    if obs.n_obs == 0:
        return None
    present = np.zeros(int(obs.view_index.max()) + 1, dtype=bool)
    present[obs.view_index] = True
    views = np.flatnonzero(present)
    if views.size < COARSE_MIN_VIEWS:
        return None
    keep = np.zeros_like(present)
    keep[views[np.round(np.linspace(0, views.size, COARSE_VIEWS, endpoint=False)).astype(int)]] = True
    return obs.select(keep[obs.view_index])


def _failed(obs, centres, terms, x0, message, status=-10, outcome="insufficient_data"):
    n = x0.size
    nan = np.full((n, n), np.nan)
    return StaticResult(
        x=x0, names=param_names(terms), units=param_units(terms), covariance=nan, correlation=nan,
        normal_inverse=nan, variance_factor=np.nan, residuals_px=np.full((obs.n_obs, 2), np.nan),
        rms_px=np.nan, cost=np.nan, success=False, status=status, message=message, nfev=0, njev=0,
        n_iter=0, n_obs=obs.n_obs, n_views=obs.n_views, n_spheres=obs.n_spheres_seen, condition=np.inf,
        geometry=None, x0=x0, loss="linear", f_scale_px=None, terms=tuple(terms), centres_of_m=centres,
        weights=None, outcome=outcome)


def solve_static(obs: CentreObservations, centres_of_m, detector: DetectorSpec, srd_reported_m: float,
                 sdd_reported_m: float, *, terms=(), loss: str = "linear", f_scale_px: float | None = None,
                 x0=None, max_iter: int = 100, max_rms_px: float = 2.0, cond_limit: float = 1e10,
                 max_rms_ratio: float = MAX_RMS_RATIO, centre_uncertainty_m=None,
                 location_classes: bool = True, _orientation_check: bool = True) -> StaticResult:
    """Solve the static geometry at stage position k = 1 (section 3.1, eq. 3).

    Parameters
    ----------
    obs : CentreObservations
        All observed centres at k = 1 (any number of projections >= 3).
    centres_of_m : array_like of shape (N, 3)
        Calibrated sphere centres in {OF} [m].
    detector : DetectorSpec
        Size and pixel pitch (from ct_instrument.yaml).
    srd_reported_m : float
        Instrument-reported source-to-rotation-axis distance at k = 1 [m].
    sdd_reported_m : float
        Stated source-to-detector distance [m].
    terms : sequence of Term
        Optional model terms (terms.py), estimated with the geometry.
    loss : {"linear", "huber", "soft_l1", "cauchy", "arctan"}
        Robust loss. A robust solve first runs the linear loss, then
        refines with the robust one.
    f_scale_px : float, optional
        Soft threshold of the robust loss [px]. Default: 2.5 times the
        robust (MAD) standard deviation of the linear-loss residuals. With
        ``obs.sigma_px`` given, it is divided by the median sigma.
    x0 : array_like of shape (13 + p,), optional
        Start point; default :func:`initial_guess` (from the data).
    max_iter : int
    max_rms_px : float
        A converged fit whose robust residual scale exceeds this [px] is
        reported as a poor fit (wrong local minimum or wrong identification).
    max_rms_ratio : float
        A converged fit whose residual RMS exceeds this many times the
        detector's reported sigma is a poor fit (noise.assess_fit also
        refuses gross errors: wrong identities); the message names the
        likely cause.
    centre_uncertainty_m : float or array_like of shape (N,), optional
        Standard uncertainty of each calibrated centre coordinate [m]
        (reference_object.yaml ``center_uncertainty``); propagated into the
        covariance.
    cond_limit : float
        Condition number above which the problem is declared degenerate.
    location_classes : bool
        Weight observations by their location class (location_noise.py: where the sphere sits
        relative to the object's axis) when a class is significantly noisier than the rest.

    Returns
    -------
    StaticResult
    """
    centres, srd, sdd = _check_inputs(obs, centres_of_m, detector, srd_reported_m, sdd_reported_m)
    terms = check_terms(terms)
    if loss not in LOSSES:
        raise ValueError(f"unknown loss {loss!r}; choose one of {LOSSES}")
    n_par = 13 + sum(t.n_params for t in terms)
    coarse = _coarse_views(obs) if x0 is None else None
    if x0 is None:
        start, n_used = initial_guess(obs if coarse is None else coarse, centres, detector, srd, sdd, terms)
        if coarse is not None and n_used < 3:          # too thin a subset to start from: use all views
            coarse = None
            start, n_used = initial_guess(obs, centres, detector, srd, sdd, terms)
    else:
        start = np.asarray(x0, dtype=float)
        if start.shape != (n_par,) or not np.all(np.isfinite(start)):
            raise ValueError(f"x0 must be {n_par} finite values, got shape {start.shape}")
        n_used = None
    reason = _degeneracy(obs, centres, n_par)
    if reason is not None:
        return _failed(obs, centres, terms, start, *reason[:1], outcome=reason[1])
    if n_used is not None and n_used < 3:
        return _failed(obs, centres, terms, start,
                       f"cannot initialise: only {n_used} spheres have a usable trajectory (>= 3 views)")

    # The kernel works in blocked order (all u, then all v) with the Jacobian as
    # the transpose of a C-contiguous (n, 2Q) array; results are interleaved below.
    kern = StaticKernel(obs, centres, detector, terms)
    sigma = None if obs.sigma_px is None else kern.blocked_weights(obs.sigma_px)
    fun = lm_function(kern)

    nfev = njev = nit = 0
    if coarse is not None:
        # Coarse to fine: converge on an even subset of the views first (20 of them: a small
        # fraction of the cost per iteration), then the full problem starts within a few standard deviations of its
        # optimum and needs one Gauss-Newton step. The result is the full-data optimum either way
        # (same convergence tests); a failed coarse fit falls back to the data-derived start.
        ck = StaticKernel(coarse, centres, detector, terms)
        sigma_c = None if coarse.sigma_px is None else ck.blocked_weights(coarse.sigma_px)
        cres = levenberg_marquardt(lm_function(ck), None, start, sigma=sigma_c, max_iter=max_iter, stol=STOL)
        nfev, njev, nit = cres.nfev, cres.njev, cres.n_iter
        if cres.success and np.all(np.isfinite(cres.x)):
            start_full = cres.x
        else:
            start_full = start
    else:
        start_full = start
    res = levenberg_marquardt(fun, None, start_full, sigma=sigma, max_iter=max_iter, stol=STOL, chord_test=True)
    nfev, njev, nit = nfev + res.nfev, njev + res.njev, nit + res.n_iter
    f_used = None
    if loss != "linear":
        rw = res.residuals if sigma is None else res.residuals / sigma
        robust_sd = 1.4826 * float(np.median(np.abs(rw - np.median(rw))))
        if f_scale_px is None:
            f = 2.5 * max(robust_sd, 1e-12)
            f_used = f if sigma is None else f * float(np.median(obs.sigma_px))
        else:
            if not (np.isfinite(f_scale_px) and f_scale_px > 0):
                raise ValueError(f"f_scale_px must be > 0, got {f_scale_px}")
            f_used = float(f_scale_px)
            f = f_used if sigma is None else f_used / float(np.median(obs.sigma_px))
        res = levenberg_marquardt(fun, None, res.x, sigma=sigma, loss=loss, f_scale=f, max_iter=max_iter, stol=STOL)
        nfev, njev, nit = nfev + res.nfev, njev + res.njev, nit + res.n_iter

    q = obs.n_obs
    # Location classes (location_noise.py): observations whose sphere sits where the object's support
    # biases its shadow (the body tube's wall band along the silhouette) are noisier than the detector
    # says; a class significantly noisier than the rest gets its own factor on the detector's sigma
    # and the fit is redone with it (the noise model below then works on the rescaled sigma).
    loc = None
    if (location_classes and sigma is not None and loss == "linear" and res.success
            and np.all(np.isfinite(res.x)) and on_cylinder(centres)):
        cls = location_class(res.x[:13], centres, obs.sphere_index, obs.alpha_rad)
        fac = class_factors(res.residuals, sigma, cls)
        if np.any(fac != 1.0):
            sigma = scaled_sigma(sigma, cls, fac)
            res_l = levenberg_marquardt(fun, None, res.x, sigma=sigma, max_iter=max_iter, stol=STOL, chord_test=True)
            nfev, njev, nit = nfev + res_l.nfev, njev + res_l.njev, nit + res_l.n_iter
            if res_l.success:
                res = res_l
        loc = (cls, fac)
    # Noise from the data (noise.py): per-axis scale of the reported sigma and a per-projection
    # shared shift. The fit is redone once with the sigma rescaled per axis (so columns and rows
    # get their measured relative weights) and the covariance is the sandwich under that model.
    noise = estimate_noise(res.residuals, sigma, obs.view_index, n_par)
    fit_weights = None if loss == "linear" else res.weights
    if loss == "linear" and res.success and np.all(np.isfinite(res.x)):
        if abs(noise.factor_u / max(noise.factor_v, 1e-300) - 1.0) > 0.1:
            # columns and rows noisier than stated by different factors: refit with those weights
            sigma_fit = axis_weights_sigma(sigma, q, noise)
            res2 = levenberg_marquardt(fun, None, res.x, sigma=sigma_fit, max_iter=max_iter, stol=STOL)
            nfev, njev, nit = nfev + res2.nfev, njev + res2.njev, nit + res2.n_iter
            if res2.success:
                res = res2
        else:
            # within 10 % of each other: the reported sigma's relative weights stand (the efficiency
            # lost is below 0.3 %); the covariance uses the weights the estimate was made with
            fit_weights = np.ones(2 * q) / (1.0 if sigma is None else sigma)
    if not (np.all(np.isfinite(res.x)) and np.all(np.isfinite(res.residuals))):
        return _failed(obs, centres, terms, start, f"the solve diverged: {res.message}", status=res.status,
                       outcome="failed")
    # the last LM iterate's Jacobian is at res.x unless the chord test stopped it (then it is one
    # small step away): reuse it only in the first case
    at_x = res.status != 4 or "chord" not in res.message
    unc = static_uncertainty(res.x, kern, obs, sigma, len(centres), centre_uncertainty_m, cond_limit,
                             weights=fit_weights, evaluated=(res.residuals, res.jac) if at_x else None)
    cov, noise, cov_noise, centre_sens, covariance, d_sys = unc
    if loc is not None:
        cls, fac = loc
        noise = replace(noise, location_factor=tuple(float(v) for v in fac),
                        location_class_counts=tuple(int(v) for v in np.bincount(cls, minlength=fac.size)))
    u_c = None if centre_sens is None else np.broadcast_to(np.asarray(centre_uncertainty_m, float), (len(centres),))
    r2 = -res.residuals.reshape(2, -1).T                 # observed - modelled
    rms = float(np.sqrt(np.mean(res.residuals ** 2)))
    success, message = res.success, res.message
    names = param_names(terms)
    outcome = "success" if success else ("failed" if res.status == -1 else "not_converged")
    if cov.rank_deficient:
        success, outcome = False, "degenerate"
        d = cov.weakest_direction
        top = np.argsort(-np.abs(d))[:3]
        combo = " ".join(f"{d[i]:+.2f}*{names[i]}" for i in top)
        message = (f"degenerate geometry: Jacobian condition {cov.condition:.3g} exceeds {cond_limit:.3g}; "
                   f"undetermined combination ~ {combo}")
    # Does the model explain the data? A fit that does not is a poor fit whatever else the solver
    # says (a wrong start can end degenerate or at the iteration limit too), and the message says why.
    ok, why = assess_fit(res.residuals, sigma, obs.view_index, obs.sphere_index, noise,
                         max_rms_ratio=max_rms_ratio, max_rms_px=max_rms_px, robust=loss != "linear")
    if ok and why and success:
        message = f"{message}; {why}"
    elif not ok:
        hint = (_orientation_hint(obs, centres, detector, srd, sdd, terms, noise, max_rms_ratio)
                if _orientation_check else None)
        success, outcome = False, "poor_fit"
        message = why + ("; " + hint if hint else "") + f" [solver: {message}]"
    geom = static_to_detector_frame(res.x[:13], centres)
    return StaticResult(
        x=res.x, names=names, units=param_units(terms), covariance=covariance,
        correlation=correlation_from_covariance(covariance), normal_inverse=cov.normal_inverse,
        variance_factor=noise.chi2_dof, residuals_px=r2, rms_px=rms, cost=res.cost,
        success=bool(success), status=res.status, message=message, nfev=nfev, njev=njev, n_iter=nit,
        n_obs=obs.n_obs, n_views=obs.n_views, n_spheres=obs.n_spheres_seen, condition=cov.condition,
        geometry=geom, x0=start, loss=loss, f_scale_px=f_used, terms=terms, centres_of_m=centres,
        weights=kern.interleave(res.weights), outcome=outcome, noise=noise, covariance_noise=cov_noise,
        centre_sensitivity=centre_sens, centre_uncertainty_m=u_c, systematic_sensitivity=d_sys)
