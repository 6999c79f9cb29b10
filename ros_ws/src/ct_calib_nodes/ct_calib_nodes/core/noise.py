"""Noise of the sphere-centre observations, estimated from the data, and the covariance it implies.

The detector reports a standard uncertainty per centre, from its own edge
scatter. On frames from other renderers and real detectors that figure is
off by a factor (measured: residual RMS 1.1-1.7 times it in columns, 1.0-1.1
in rows), and part of the error is shared by every sphere of a projection
(focal-spot jitter, per-projection wobble, a frame-wide shift): a shared
0.02 px per frame on 0.05 px noise barely moves the RMS but, treated as
independent, understates the straightness uncertainty 2.5 times. So each
solve (the static geometry, and every stage position) estimates from its own
residuals, separately for columns (u) and rows (v):

* ``factor_u``, ``factor_v``: the scale of the reported sigma that the
  within-projection scatter supports (a-posteriori variance factor, from
  deviations about each projection's weighted mean residual, so a shared
  per-projection shift does not inflate it);
* ``view_sd_u_px``, ``view_sd_v_px``: the standard deviation of a shift
  shared by all observations of one projection (a per-view variance
  component, moment estimate: the scatter of the per-projection mean
  residuals beyond what the within-projection noise explains).

The noise model is then Cov(r) = diag(f_a^2 sigma_q^2) + tau_a^2 1 1^T per
projection and axis, and the parameters' covariance is the sandwich
``A^-1 (J^T W Cov(r) W J) A^-1`` (A = J^T W J) for the weights W the
estimator used. With a single projection the shared part cannot be seen in
the residuals (it is absorbed by the parameters): it must come from a
multi-projection solve of the same data (``view_sd_px`` argument).

Residual layout is the kernels' BLOCKED one: ``[u_1..u_Q, v_1..v_Q]``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class NoiseModel:
    """Observation noise of one solve, per image axis (u = columns, v = rows).

    Attributes
    ----------
    factor_u, factor_v : float
        Within-projection residual scale relative to the sigma used as
        weights (the detector's reported sigma, or 1 px when it reported none).
    view_sd_u_px, view_sd_v_px : float
        Standard deviation of a shift shared by all observations of a
        projection [px] (0 when not detectable).
    chi2_dof : float
        Sum of squared residuals / reported sigma^2, per degree of freedom
        (1 when the data are as noisy as the detector says).
    within_view_correlation_u, within_view_correlation_v : float
        tau^2 / (tau^2 + (f sigma_median)^2): correlation of two observations
        of the same projection.
    n_views : int
    view_sd_source : str
        "estimated" (from these residuals), "given" (from another solve of
        the same data), or "none".
    sigma_reported : bool
        Whether the detector's per-observation sigma was used.
    """

    factor_u: float
    factor_v: float
    view_sd_u_px: float
    view_sd_v_px: float
    chi2_dof: float
    within_view_correlation_u: float
    within_view_correlation_v: float
    n_views: int
    view_sd_source: str
    sigma_reported: bool

    @property
    def view_sd_px(self) -> tuple:
        return (self.view_sd_u_px, self.view_sd_v_px)

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def _view_ids(view_index):
    """Compact codes 0..V-1 of the projections and V (bincount when the indices are compact)."""
    v = np.asarray(view_index)
    if v.size == 0:
        return v.astype(np.int64), 0
    top = int(v.max())
    if top <= 4 * v.size + 1024:
        present = np.bincount(v, minlength=top + 1) > 0
        codes = np.cumsum(present) - 1
        return codes[v], int(present.sum())
    _, inv = np.unique(v, return_inverse=True)
    return inv, int(inv.max()) + 1


def estimate_noise(residuals, sigma, view_index, n_params: int, view_sd_px=None) -> NoiseModel:
    """Noise model from the residuals of a weighted least-squares fit.

    Parameters
    ----------
    residuals : ndarray of shape (2Q,)
        Blocked residuals [px] at the estimate.
    sigma : ndarray of shape (2Q,) or None
        The sigma used as weights [px] (None: 1 px).
    view_index : ndarray of shape (Q,)
        Projection of each observation.
    n_params : int
        Number of fitted parameters (degrees of freedom).
    view_sd_px : (float, float), optional
        Shared per-projection shift sd (u, v) [px] known from elsewhere; used
        instead of an estimate (needed with a single projection).
    """
    r = np.asarray(residuals, dtype=float)
    q = r.size // 2
    sig = np.ones(2 * q) if sigma is None else np.asarray(sigma, dtype=float)
    vid, n_v = _view_ids(np.asarray(view_index))
    dof_total = max(2 * q - n_params, 1)
    chi2 = float(np.sum((r / sig) ** 2)) / dof_total
    factors, taus = [], []
    for a in range(2):
        ra, sa = r[a * q:(a + 1) * q], sig[a * q:(a + 1) * q]
        w = 1.0 / sa ** 2
        wsum = np.bincount(vid, w, n_v)
        mean = np.bincount(vid, w * ra, n_v) / wsum
        dev = ra - mean[vid]
        # within-projection scatter: n_v means are used up, and about half the parameters
        # (they act on both axes) are paid by each axis
        dof_w = max(q - n_v - 0.5 * n_params, 1.0)
        f2 = float(np.sum(w * dev * dev)) / dof_w if n_v < q else float(np.sum(w * ra * ra)) / max(q - 0.5 * n_params, 1)
        factors.append(np.sqrt(max(f2, 0.0)))
        if view_sd_px is not None:
            taus.append(float(view_sd_px[a]))
        elif n_v >= 5:
            # E[m_v^2] = tau^2 + f^2 / W_v; the fit absorbs a share ~ n_params / (2 n_v) of the
            # projection means' variance, corrected for by the degrees of freedom. The component
            # is kept only when it is significant (more than 2 standard errors of its estimate,
            # sqrt(2 / n_v) times the noise of a projection mean): with none in the data the
            # estimate scatters about 0 and would inflate the covariance by chance.
            excess = mean ** 2 - f2 / wsum
            t2 = float(np.sum(excess)) / max(n_v - 0.5 * n_params, 1.0)
            se = np.sqrt(2.0 / n_v) * float(np.mean(f2 / wsum))
            taus.append(np.sqrt(t2) if t2 > 2.0 * se else 0.0)
        else:
            taus.append(0.0)
    med = float(np.median(sig)) if sig.size else 1.0
    rho = [t * t / (t * t + (f * med) ** 2) if (t > 0 or f > 0) else 0.0 for f, t in zip(factors, taus)]
    source = "given" if view_sd_px is not None else ("estimated" if n_v >= 5 else "none")
    return NoiseModel(factor_u=factors[0], factor_v=factors[1], view_sd_u_px=taus[0], view_sd_v_px=taus[1],
                      chi2_dof=chi2, within_view_correlation_u=rho[0], within_view_correlation_v=rho[1],
                      n_views=n_v, view_sd_source=source, sigma_reported=sigma is not None)


def axis_weights_sigma(sigma, q: int, noise: NoiseModel):
    """The weights' sigma rescaled per axis by the noise model's factors, blocked (2Q,)."""
    sig = np.ones(2 * q) if sigma is None else np.asarray(sigma, dtype=float).copy()
    sig[:q] *= max(noise.factor_u, 1e-12)
    sig[q:] *= max(noise.factor_v, 1e-12)
    return sig


def axis_normals(jac_t, sigma_w):
    """J_a^T W_a J_a for a = u, v (the two halves of the blocked Jacobian), W = 1 / sigma_w^2."""
    k = np.asarray(jac_t, dtype=float)
    q = k.shape[1] // 2
    w = 1.0 / np.asarray(sigma_w, dtype=float) ** 2
    return [(k[:, a * q:(a + 1) * q] * w[a * q:(a + 1) * q]) @ k[:, a * q:(a + 1) * q].T for a in range(2)]


def sandwich_covariance(jac_t, sigma_w, sigma_noise, view_index, noise: NoiseModel, normal_inverse,
                        normals=None):
    """Covariance of a weighted least-squares estimate under the noise model.

    Parameters
    ----------
    jac_t : ndarray of shape (n, 2Q)
        Transposed blocked Jacobian at the estimate.
    sigma_w : ndarray of shape (2Q,)
        Sigma of the weights the estimator used (W = 1 / sigma_w^2).
    sigma_noise : ndarray of shape (2Q,)
        Per-observation independent noise sd under the model [px]
        (f_a times the reported sigma).
    view_index : ndarray of shape (Q,)
    noise : NoiseModel
        Supplies the shared per-projection sd tau_a.
    normal_inverse : ndarray of shape (n, n)
        (J^T W J)^-1.
    normals : [A_u, A_v], optional
        :func:`axis_normals` of the same Jacobian and weights, when already formed.

    Returns
    -------
    ndarray of shape (n, n)
    """
    k = np.asarray(jac_t, dtype=float)
    q = k.shape[1] // 2
    sw, sn = np.asarray(sigma_w, dtype=float), np.asarray(sigma_noise, dtype=float)
    ratio = (sn / sw) ** 2                               # noise variance over the weights' variance
    meat = None
    if normals is not None:
        r_u, r_v = ratio[:q], ratio[q:]
        if np.ptp(r_u) <= 1e-12 * r_u.max() and np.ptp(r_v) <= 1e-12 * r_v.max():
            meat = r_u[0] * normals[0] + r_v[0] * normals[1]     # J^T W (c_a W^-1) W J = c_a A_a
    if meat is None:
        w = 1.0 / sw ** 2
        kw = k * w                                       # J^T W, (n, 2Q)
        meat = (kw * sn ** 2) @ kw.T
    vid, n_v = _view_ids(np.asarray(view_index))
    for a, tau in enumerate(noise.view_sd_px):
        if tau <= 0:
            continue
        block = k[:, a * q:(a + 1) * q] / sw[a * q:(a + 1) * q] ** 2
        s = np.stack([np.bincount(vid, row, n_v) for row in block])      # (n, V) per-view sums
        meat += tau * tau * (s @ s.T)
    return normal_inverse @ meat @ normal_inverse


#: default gate: the residual RMS may be at most this many times what the detector's reported
#: sigma predicts (independent clean recordings came out at 1.1-1.7 times)
MAX_RMS_RATIO = 2.5
#: residuals beyond this many robust standard deviations are gross errors
GROSS_SD = 10.0


def assess_fit(residuals, sigma, view_index, sphere_index, noise: NoiseModel, *,
               max_rms_ratio: float = MAX_RMS_RATIO, max_rms_px: float = 2.0, robust: bool = False):
    """Does the model explain the data? Returns (ok, message naming the likely cause, or a note, or None).

    Three tests, each against what the noise should give:

    * gross errors: residuals beyond GROSS_SD robust sd (median absolute
      deviation) where a Gaussian would give none; concentrated in some
      projections or spheres they are wrong identities or accepted overlaps
      (with a robust loss they are expected and down-weighted: a note only);
    * overall level: RMS of the whitened residuals above ``max_rms_ratio``
      times the reported sigma (only when the detector reported one);
    * absolute level: robust residual scale above ``max_rms_px`` [px].
    """
    r = np.asarray(residuals, dtype=float)
    q = r.size // 2
    sig = np.ones(2 * q) if sigma is None else np.asarray(sigma, dtype=float)
    z = r / sig
    # robust scales from an even subset of ~4000 residuals: pass/fail tests need no more
    step = max(1, r.size // 4096)
    zs = z[::step]
    mad = 1.4826 * float(np.median(np.abs(zs - np.median(zs))))
    rms_z = float(np.sqrt(np.mean(z * z)))
    robust_px = 1.4826 * float(np.median(np.abs(r[::step])))
    rms_px = float(np.sqrt(np.mean(r * r)))
    gross = np.abs(z) > GROSS_SD * max(mad, 1e-12)
    note = None
    if q and gross.sum() > max(3, 0.002 * 2 * q) and rms_z > 2.0 * mad:
        obs = np.flatnonzero(gross[:q] | gross[q:])
        views = np.unique(np.asarray(view_index)[obs])
        spheres = np.unique(np.asarray(sphere_index)[obs])
        n_views = len(np.unique(view_index))
        if robust:
            note = (f"{len(obs)} of {q} centres beyond {GROSS_SD:g} robust sd were down-weighted by the robust "
                    "loss")
            z = np.where(gross, 0.0, z)
        else:
            return False, (f"gross errors: {len(obs)} of {q} centres ({100.0 * len(obs) / q:.1f} %) lie beyond "
                       f"{GROSS_SD:g} robust sd, in {len(views)} of {n_views} projection(s) and {len(spheres)} "
                       f"sphere(s); RMS {rms_px:.3g} px against a robust scale of {robust_px:.3g} px. Likely "
                           "cause: wrong sphere identities (or overlapping shadows accepted as one sphere)")
    if sigma is not None and np.sqrt(noise.chi2_dof if note is None else float(np.mean(z * z))) > max_rms_ratio:
        return False, (f"the model does not explain the data: residuals are {np.sqrt(noise.chi2_dof):.3g} times "
                       f"the detector's stated uncertainty (limit {max_rms_ratio:g}) across the data. Likely "
                       "causes: the reference object mounted otherwise than its file says (upside down?), a "
                       "wrong reference object file, the image orientation (rows or columns mirrored) or the "
                       "rotation direction, or physics the model leaves out (run ct_discrepancy)")
    if robust_px > max_rms_px:
        return False, (f"converged to a poor fit: robust residual scale {robust_px:.3g} px > {max_rms_px:g} px "
                       "(local minimum, wrong identification or wrong nominal inputs)")
    return True, note
