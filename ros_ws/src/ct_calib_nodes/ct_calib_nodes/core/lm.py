"""A small dense Levenberg-Marquardt solver with robust losses and covariance.

Nielsen's damping update with More's diagonal scaling (D = running maximum of
the column norms of J), normal equations solved by Cholesky of the 13 x 13
(or so) matrix J^T J: the problems here are tall and thin (tens of
thousands of residuals, a dozen parameters), so forming J^T J is the cheap
part and the cost per iteration is one residual+Jacobian evaluation.

Robust losses follow scipy.optimize.least_squares' definitions
(rho(z), z = (r / f_scale)^2) and are applied by iteratively reweighting
residuals and Jacobian with sqrt(rho'(z)) (the "IRLS" form, which drops the
rho'' term of the Gauss-Newton Hessian, as scipy does for rho'' < 0).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LOSSES = ("linear", "huber", "soft_l1", "cauchy", "arctan")


def loss_rho(z: np.ndarray, loss: str):
    """rho(z) and rho'(z) of scipy's robust losses, z = (r / f_scale)^2 >= 0."""
    if loss == "linear":
        return z, np.ones_like(z)
    if loss == "huber":
        small = z <= 1.0
        sz = np.sqrt(z)
        return np.where(small, z, 2.0 * sz - 1.0), np.where(small, 1.0, 1.0 / np.maximum(sz, 1e-300))
    if loss == "soft_l1":
        t = 1.0 + z
        return 2.0 * (np.sqrt(t) - 1.0), 1.0 / np.sqrt(t)
    if loss == "cauchy":
        return np.log1p(z), 1.0 / (1.0 + z)
    if loss == "arctan":
        return np.arctan(z), 1.0 / (1.0 + z * z)
    raise ValueError(f"unknown loss {loss!r}; choose one of {LOSSES}")


@dataclass(frozen=True)
class LMResult:
    """Outcome of :func:`levenberg_marquardt`.

    Attributes
    ----------
    x : ndarray of shape (n,)
    residuals : ndarray of shape (m,)
        Unweighted residuals at x.
    jac : ndarray of shape (m, n)
        Unweighted Jacobian at x.
    weights : ndarray of shape (m,)
        Final IRLS weights sqrt(rho'(z)) times the whitening 1/sigma (ones for
        the linear loss without sigma).
    cost : float
        0.5 f^2 sum rho((r / (sigma f))^2) at x.
    nfev, njev, n_iter : int
    status : int
        1 ftol (actual or predicted decrease), 2 xtol, 3 gtol, 4 stol, 0 max_iter, -1 non-finite start,
        -2 damping overflow, -3 stalled (the damping grew until the step vanished without a decrease:
        not a minimum, whatever the step tolerance says).
    message : str
    success : bool
    normal : ndarray of shape (n, n) or None
        J^T W J at x (W = weights^2), the matrix the covariance needs.
    """

    x: np.ndarray
    residuals: np.ndarray
    jac: np.ndarray
    weights: np.ndarray
    cost: float
    nfev: int
    njev: int
    n_iter: int
    status: int
    message: str
    success: bool
    normal: np.ndarray | None = None


STOL = 0.02   # default statistical stopping tolerance of the CT solvers [standard deviations]


def levenberg_marquardt(fun, fun_jac, x0, *, sigma=None, loss="linear", f_scale=1.0, max_iter=100,
                        ftol=1e-10, xtol=1e-10, gtol=1e-10, mu0=1e-7, stol=None,
                        chord_test=False) -> LMResult:
    """Minimise 0.5 sum rho((r_i(x) / (sigma_i f))^2) f^2 by Levenberg-Marquardt.

    Parameters
    ----------
    fun : callable
        ``x -> r`` (m,); or, when ``fun_jac`` is None, ``x -> (r, jac)`` with
        ``jac()`` returning J (m, n) at the same x (lazy: called only for
        accepted points, so a model can reuse its forward pass).
    fun_jac : callable x -> (r (m,), J (m, n)), or None
    x0 : array_like of shape (n,)
    sigma : ndarray of shape (m,) or None
        Standard deviation of each residual (whitening); None means 1.
    loss : str
        One of :data:`LOSSES`.
    f_scale : float
        Soft threshold of the robust loss, in units of the whitened residual.
    max_iter : int
    ftol, xtol, gtol : float
        Relative cost decrease, relative scaled step and scaled gradient
        (cosine) tolerances.
    mu0 : float
        Initial damping relative to max(diag(J^T J)).
    stol : float, optional
        Statistical tolerance: converged when the Gauss-Newton step still
        available is shorter than ``stol`` standard deviations of the
        estimate (Mahalanobis length in the covariance s^2 (J^T W J)^-1,
        s^2 = 2 cost / (m - n)). Stopping there moves the estimate by at most
        stol sigma; 0.02 changes its uncertainty by 0.02 % in quadrature.
    chord_test : bool
        With ``stol`` and no weights/robust loss: after an accepted step that
        the quadratic model predicted to 5 %, test ``stol`` with the previous
        Jacobian before computing a new one (simplified Gauss-Newton); if it
        passes, the returned ``jac``/``normal`` are the previous point's.
    """
    if loss not in LOSSES:
        raise ValueError(f"unknown loss {loss!r}; choose one of {LOSSES}")
    if not (np.isfinite(f_scale) and f_scale > 0):
        raise ValueError(f"f_scale must be > 0, got {f_scale}")
    x = np.array(x0, dtype=float)
    if fun_jac is None:
        lazy = fun
    else:
        def lazy(x_):
            return fun(x_), (lambda: fun_jac(x_)[1])
    inv_sig = None if sigma is None else 1.0 / np.asarray(sigma, dtype=float)

    plain = loss == "linear" and inv_sig is None
    ones = None

    def weigh(r):
        nonlocal ones
        if plain:                              # ordinary least squares: no per-residual weights
            if ones is None or ones.size != r.size:
                ones = np.ones_like(r)
            return 0.5 * float(r @ r), ones
        rw = r if inv_sig is None else r * inv_sig
        z = (rw / f_scale) ** 2
        rho, rho1 = loss_rho(z, loss)
        cost = 0.5 * f_scale ** 2 * float(np.sum(rho))
        sw = np.sqrt(rho1)
        if inv_sig is not None:
            sw = sw * inv_sig
        return cost, sw

    # nfev counts residual evaluations: fun_jac re-evaluates them, a lazy Jacobian does not
    extra = 0 if fun_jac is None else 1
    r, jac_at = lazy(x)
    jac = jac_at()
    nfev = njev = 1
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(jac))):
        return LMResult(x, r, jac, np.ones_like(r), np.inf, nfev, njev, 0, -1,
                        "residuals or Jacobian not finite at the start point", False)
    cost, sw = weigh(r)
    scaled = loss != "linear" or inv_sig is not None
    dof = max(r.size - x.size, 1)
    chord = stol is not None and chord_test and not scaled

    def gn_sq(chol, grad):
        """grad^T A^-1 grad from the Cholesky factor of A."""
        y = np.linalg.solve(chol, grad)
        return float(y @ y)

    def within_stol(gn2, cost_):
        """The Gauss-Newton step of squared A-norm gn2 is shorter than stol sd (s^2 = 2 cost / dof)."""
        return stol is not None and gn2 * dof <= stol ** 2 * 2.0 * cost_

    def normal(r, jac, sw):
        if scaled:
            jw = jac * sw[:, None]
            return jw.T @ jw, jw.T @ (r * sw)
        return jac.T @ jac, jac.T @ r

    a, g = normal(r, jac, sw)
    dscale = np.sqrt(np.maximum(np.diag(a), 1e-300))
    mu = mu0 * float(np.max(np.diag(a)) / np.max(dscale ** 2))
    nu = 2.0
    status, message = 0, "maximum number of iterations reached"
    it = 0
    for it in range(1, max_iter + 1):
        # scaled gradient test: max_i |g_i| / (||J_i|| ||r||)
        rn = np.sqrt(2.0 * cost) if cost > 0 else 0.0
        if rn == 0.0 or np.max(np.abs(g) / (dscale * rn)) <= gtol:
            status, message = 3, "gradient tolerance reached"
            break
        # predicted decrease of the undamped (Gauss-Newton) step, 0.5 g^T A^-1 g: when even that
        # is below ftol * cost, no step can gain more (MINPACK's ftol test uses the predicted
        # decrease too). Saves the last residual + Jacobian evaluation of a converged fit.
        # With stol: stop when that step, in the metric of the estimate's own covariance
        # s^2 A^-1 (s^2 = 2 cost / (m - n)), is shorter than stol standard deviations.
        try:
            chol_a = np.linalg.cholesky(a)           # also serves the chord test below
        except np.linalg.LinAlgError:
            chol_a = None
        if chol_a is not None:
            gn2 = gn_sq(chol_a, g)                   # g^T A^-1 g = 2 x predicted decrease
            if 0.5 * gn2 <= ftol * cost:
                status, message = 1, "predicted cost decrease below ftol"
                break
            if within_stol(gn2, cost):
                status, message = 4, f"remaining step below {stol:g} standard deviations"
                break
        rejected = 0
        while True:
            lhs = a + mu * np.diag(dscale ** 2)
            try:
                cf = np.linalg.cholesky(lhs)
                step = -np.linalg.solve(cf.T, np.linalg.solve(cf, g))
            except np.linalg.LinAlgError:
                step = -np.linalg.lstsq(lhs, g, rcond=None)[0]
            if np.linalg.norm(dscale * step) <= xtol * (np.linalg.norm(dscale * x) + xtol):
                if rejected:
                    # the step only became that small because the damping grew after failed
                    # trials: the model promises a decrease the function does not deliver here
                    status, message = -3, (f"stalled: the damping grew through {rejected} rejected steps "
                                           "until the step vanished, with no decrease (not a minimum)")
                else:
                    status, message = 2, "step tolerance reached"
                break
            x_new = x + step
            r_new, jac_new = lazy(x_new)
            nfev += 1
            cost_new, sw_new = weigh(r_new) if np.all(np.isfinite(r_new)) else (np.inf, None)
            pred = 0.5 * float(step @ (mu * dscale ** 2 * step - g))
            ratio = (cost - cost_new) / pred if pred > 0 else -1.0
            if ratio > 0:
                break
            mu *= nu
            nu *= 2.0
            rejected += 1
            if mu > 1e30:
                status, message = -2, "damping overflow: no decrease found"
                break
        if status in (2, -2, -3):
            break
        decrease = cost - cost_new
        x, r, cost, sw = x_new, r_new, cost_new, sw_new
        if chord:
            # Simplified (chord) Gauss-Newton test before paying for a new Jacobian: the quadratic
            # model predicted this step's decrease to 5 % (the Jacobian hardly changed over it)
            # and the step still available from x with the PREVIOUS J^T J and gradient J^T r(x)
            # is below stol sd. The covariance then uses J at the previous point, one small step
            # away: sds and correlations agree with those of J at x to ~3e-4 (tested).
            if chol_a is not None and abs(ratio - 1.0) <= 0.05 and within_stol(gn_sq(chol_a, jac.T @ r), cost):
                status, message = 4, f"remaining step below {stol:g} standard deviations (chord test)"
                break
        jac = jac_new()
        njev += 1
        nfev += extra
        a, g = normal(r, jac, sw)
        dscale = np.maximum(dscale, np.sqrt(np.maximum(np.diag(a), 1e-300)))
        mu *= max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3)
        nu = 2.0
        if decrease <= ftol * cost:
            status, message = 1, "relative cost decrease below ftol"
            break
    return LMResult(x=x, residuals=r, jac=jac, weights=sw, cost=cost, nfev=nfev, njev=njev,
                    n_iter=it, status=status, message=message, success=status > 0, normal=a)


@dataclass(frozen=True)
class CovarianceInfo:
    """Covariance of a least-squares estimate.

    Attributes
    ----------
    covariance : ndarray of shape (n, n)
        s^2 (J_w^T J_w)^-1 with s^2 = the residual variance factor.
    normal_inverse : ndarray of shape (n, n)
        (J_w^T J_w)^-1: the covariance per unit variance of the whitened
        residuals. With known sigma it IS the Cramer-Rao bound.
    variance_factor : float
        s^2 = sum(w r)^2 / (m - n) (reduced chi-square; in px^2 when no
        sigma is given).
    condition : float
        Condition number of the column-scaled J_w.
    rank_deficient : bool
    weakest_direction : ndarray of shape (n,)
        Unit parameter-space direction (in column-scaled units) with the
        smallest singular value.
    """

    covariance: np.ndarray
    normal_inverse: np.ndarray
    variance_factor: float
    condition: float
    rank_deficient: bool
    weakest_direction: np.ndarray


def covariance_from_jacobian(jac, residuals, weights=None, cond_limit=1e10, normal=None) -> CovarianceInfo:
    """Parameter covariance from the Jacobian and the residual variance.

    Parameters
    ----------
    jac : ndarray of shape (m, n)
    residuals : ndarray of shape (m,)
    weights : ndarray of shape (m,) or None
        Multiplies rows (whitening and robust IRLS weights).
    cond_limit : float
        Condition number (of the column-scaled weighted Jacobian) above
        which the problem is declared rank deficient.
    normal : ndarray of shape (n, n), optional
        J^T W J if already known (e.g. ``LMResult.normal``); skips forming it.
    """
    rw = residuals if weights is None else residuals * weights
    m, n = jac.shape
    if normal is None:
        jw = jac if weights is None else jac * weights[:, None]
        a = jw.T @ jw
    else:
        a = np.asarray(normal, dtype=float)
    col = np.sqrt(np.maximum(np.diag(a), 1e-300))
    an = a / np.outer(col, col)
    evals, evecs = np.linalg.eigh(an)
    evals = np.maximum(evals, 0.0)
    cond = float(np.sqrt(evals[-1] / evals[0])) if evals[0] > 0 else np.inf
    rank_def = not (cond < cond_limit)
    with np.errstate(divide="ignore"):
        inv_e = np.where(evals > evals[-1] * 1e-300, 1.0 / evals, 0.0)
    an_inv = (evecs * inv_e) @ evecs.T
    ninv = an_inv / np.outer(col, col)
    dof = max(m - n, 1)
    s2 = float(rw @ rw) / dof
    return CovarianceInfo(covariance=s2 * ninv, normal_inverse=ninv, variance_factor=s2,
                          condition=cond, rank_deficient=rank_def, weakest_direction=evecs[:, 0].copy())


def correlation_from_covariance(cov: np.ndarray) -> np.ndarray:
    """Correlation matrix (n, n) of a covariance matrix (zeros where a variance is 0)."""
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        c = cov / np.outer(sd, sd)
    c[~np.isfinite(c)] = 0.0
    return c
