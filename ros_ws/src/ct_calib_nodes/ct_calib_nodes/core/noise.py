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

* ``track_corr_u``, ``track_corr_v`` (when the sphere of each observation is
  given: the static solve): correlation of one sphere's errors in
  consecutive projections, lags 1, 2, ... in acquisition order (a shadow
  crossing a holder's edge band keeps its bias for several views). Pooled
  autocorrelation of the whitened within-projection deviations along every
  sphere's track, net of what the calibrated centres' stated errors put
  there (one offset per sphere, correlated at every lag: the centre term of
  the static solve carries it); the run of significantly positive lags from
  lag 1 (more than 2 standard errors) as measured, continued as AR(1)
  beyond, shrunk if needed until a track's correlation matrix is positive
  definite.
  ``track_lag_corr_*`` report the raw estimates (diagnostic, lags 1, 2, ...
  up to the first one not significant).

The noise model is then Cov(r) = diag(f_a^2 sigma_q^2) + tau_a^2 1 1^T per
projection and axis, plus f_a^2 sigma_i sigma_j c_a(l) between observations
of the same sphere l projections apart, and the parameters' covariance is the sandwich
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
    track_lag_corr_u, track_lag_corr_v : tuple of float
        Estimated correlation of a sphere's whitened within-projection residuals l projections
        apart (acquisition order), pooled over spheres, for l = 1, 2, ... up to the first lag not
        significantly positive (at most min(TRACK_MAX_LAG, V / 4)); () when not estimated.
    track_lag_se_u, track_lag_se_v : tuple of float
        Standard error of those estimates under no correlation (1 / sqrt(pairs), widened by the
        scatter of the calibrated centres' errors when their share is taken out), per lag.
    track_corr_u, track_corr_v : tuple of float
        The correlations the covariance uses (lags 1..len), () when none is significant.
    track_sd_inflation : tuple of float
        Per parameter: standard uncertainty with the track correlation over that without it
        (filled by the solver that forms the covariance; () when not formed).
    location_factor : tuple of float
        Static solve only (location_noise.py): the factor on the detector's sigma (both image axes) of
        each location class (|s| bin 0..9 in front of the object's axis, 10..19 behind it); 1 where the
        class is not significantly noisier than the rest; () when no classes were formed.
    location_class_counts : tuple of int
        Observations in each location class.
    chi2_dof_net : float or None
        ``chi2_dof`` net of the expected share of the calibrated centres' stated errors (None when
        none were given); the quality gate judges this one (:func:`assess_fit`).
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
    track_lag_corr_u: tuple = ()
    track_lag_corr_v: tuple = ()
    track_lag_se_u: tuple = ()
    track_lag_se_v: tuple = ()
    track_corr_u: tuple = ()
    track_corr_v: tuple = ()
    track_sd_inflation: tuple = ()
    location_factor: tuple = ()
    location_class_counts: tuple = ()
    chi2_dof_net: float | None = None

    @property
    def view_sd_px(self) -> tuple:
        return (self.view_sd_u_px, self.view_sd_v_px)

    @property
    def track_corr(self) -> tuple:
        return (self.track_corr_u, self.track_corr_v)

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v)
                for k, v in ((k, getattr(self, k)) for k in self.__dataclass_fields__)}


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


#: most lags of the track correlation estimated (and a quarter of the projections at most)
TRACK_MAX_LAG = 24


def _track_table(sphere_index, vid, n_v: int):
    """(spheres, projections) table of observation indices, -1 where a sphere was not observed."""
    sph = np.asarray(sphere_index, dtype=np.int64)
    table = np.full((int(sph.max()) + 1 if sph.size else 0, n_v), -1, dtype=np.int64)
    table[sph, vid] = np.arange(sph.size)
    return table


def track_pairs(sphere_index, view_index, lag: int):
    """Observation pairs (i, j) of the same sphere ``lag`` projections apart in acquisition order.

    The order is that of the projections present (their view indices sorted), so a projection
    missing from the data does not count; a sphere missing from a projection (overlap, out of view)
    leaves the pairs that would involve it out.
    """
    vid, n_v = _view_ids(np.asarray(view_index))
    if lag <= 0 or lag >= n_v:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    table = _track_table(sphere_index, vid, n_v)
    a, b = table[:, :-lag].ravel(), table[:, lag:].ravel()
    keep = (a >= 0) & (b >= 0)
    return a[keep], b[keep]


def _track_correlation(z, table, known=None):
    """Lag correlations of whitened deviations z along sphere tracks: (raw, se, used), each a tuple.

    ``table``: :func:`_track_table`; ``known``: (offset columns (3, Q), stated variance (Q,)) of
    the calibrated centres, whose expected share is taken out. raw: the pooled estimates at lags
    1, 2, ... up to the first one not significantly positive (at most L = min(TRACK_MAX_LAG, V / 4));
    se: their standard errors with no correlation (1 / sqrt(pairs), widened by the scatter of the
    centres' actual errors about their stated variance); used: the model the covariance takes: the run of
    significantly positive estimates from lag 1 (> 2 se) as measured, continued to lag L as AR(1)
    (each lag the previous times the run's last ratio, or times the lag-1 value for a run of one),
    shrunk if needed until the correlation matrix of a track is positive definite; () when lag 1 is
    not significant.
    """
    n_v = table.shape[1]
    max_lag = min(TRACK_MAX_LAG, n_v // 4)
    seen = table >= 0
    at = np.maximum(table, 0)
    zt = np.where(seen, np.asarray(z)[at], 0.0)
    zt2 = zt * zt
    if known is not None:                        # (zc (3, Q), var (Q,)): sd-weighted offset columns
        kt = np.where(seen, (known[0] * np.sqrt(known[1]))[:, at], 0.0)     # (3, spheres, views)
    raw, se = [], []
    for lag in range(1, max_lag + 1):
        n_pairs = int(np.count_nonzero(seen[:, :-lag] & seen[:, lag:]))
        if n_pairs < 20:
            break
        # sums of squares over the pairs only (a term whose partner is missing is zero in the product)
        den = np.sqrt(float(np.sum(zt2[:, :-lag] * seen[:, lag:])) * float(np.sum(zt2[:, lag:] * seen[:, :-lag])))
        num = float(np.sum(zt[:, :-lag] * zt[:, lag:]))
        var_known = 0.0
        if known is not None:
            # less the part the stated centre errors put in on average; their actual draw scatters
            # about it (Gaussian quadratic form: variance 2 sum_s |M_s|_F^2, M_s the sphere's
            # symmetrised lag product of its offset columns), which widens the standard error
            m = np.einsum("asv,bsv->sab", kt[:, :, :-lag], kt[:, :, lag:])
            num -= float(np.trace(m, axis1=1, axis2=2).sum())
            var_known = 2.0 * float(np.sum((0.5 * (m + m.transpose(0, 2, 1))) ** 2))
        raw.append(num / den if den > 0 else 0.0)
        se.append(np.sqrt(1.0 / n_pairs + (var_known / den ** 2 if den > 0 else 0.0)))
        if raw[-1] <= 2.0 * se[-1]:
            break                                 # the first lag not significantly positive ends the run
    run = len(raw) - 1 if raw and raw[-1] <= 2.0 * se[-1] else len(raw)
    if run == 0:
        return tuple(raw), tuple(se), ()
    used = list(raw[:run])
    ratio = min(used[-1] / used[-2] if run >= 2 else used[0], 0.9)
    while len(used) < max_lag and used[-1] * ratio > 1e-3:
        used.append(used[-1] * ratio)
    used = np.array(used)
    # a track's correlation matrix (Toeplitz) is positive definite at every length when the spectral
    # density 1 + 2 sum_l c_l cos(l w) is positive: shrink until it is (> 0.05) on a fine grid
    cosines = np.cos(np.outer(np.linspace(0.0, np.pi, 513), np.arange(1, used.size + 1)))
    for _ in range(30):
        if 1.0 + 2.0 * float((cosines @ used).min()) > 0.05:
            break
        used = used * 0.9
    return tuple(raw), tuple(se), tuple(float(c) for c in used)


def estimate_noise(residuals, sigma, view_index, n_params: int, view_sd_px=None,
                   sphere_index=None, centre_jac=None, centre_var=None, track: bool = True) -> NoiseModel:
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
    sphere_index : ndarray of shape (Q,), optional
        Sphere of each observation: with it (and at least 8 projections) the correlation of
        a sphere's errors in consecutive projections is estimated (``track_corr_*``).
    centre_jac : ndarray of shape (3, 2Q), optional
        The residuals' derivatives with respect to the object position (x_P, y_P, z_P), i.e. to an
        offset of each observation's own sphere centre.
    centre_var : ndarray of shape (N,), optional
        Stated variance of each calibrated centre coordinate [m^2]. With ``centre_jac``, the
        per-axis factors, the per-projection shift and the track correlation are estimated net of
        what these errors put into the residuals (the same offset in every view of a sphere,
        correlated at every lag; the centre-uncertainty term carries it, so it is not counted
        twice).
    """
    r = np.asarray(residuals, dtype=float)
    q = r.size // 2
    sig = np.ones(2 * q) if sigma is None else np.asarray(sigma, dtype=float)
    vid, n_v = _view_ids(np.asarray(view_index))
    dof_total = max(2 * q - n_params, 1)
    chi2 = float(np.sum((r / sig) ** 2)) / dof_total
    factors, taus, lag_raw, lag_used, lag_se, table = [], [], [], [], [], None
    e_tot = None
    for a in range(2):
        ra, sa = r[a * q:(a + 1) * q], sig[a * q:(a + 1) * q]
        w = 1.0 / sa ** 2
        wsum = np.bincount(vid, w, n_v)
        mean = np.bincount(vid, w * ra, n_v) / wsum
        dev = ra - mean[vid]
        # within-projection scatter: n_v means are used up, and about half the parameters
        # (they act on both axes) are paid by each axis
        dof_w = max(q - n_v - 0.5 * n_params, 1.0)
        ss = float(np.sum(w * dev * dev)) if n_v < q else float(np.sum(w * ra * ra))
        cmm_m2 = np.zeros(n_v)
        if centre_jac is not None and centre_var is not None and sphere_index is not None and n_v < q:
            # net of the calibrated centres' stated errors: sphere s's error puts the same offset
            # jc_i . dc_s into each of its observations, one per projection, so within a projection
            # they are independent with variance a_i = |jc_i|^2 u_s^2. Their expected share of the
            # weighted within-projection scatter, sum w a - sum_v (sum_v w^2 a) / W_v, scaled like
            # the noise's by the fit's share (dof_w / (q - n_v)), is taken out: the centre-uncertainty
            # term of the covariance carries it, and counted in the factor too it was counted twice
            # (rendered Monte Carlo at 0.4 mm pixels, 1 um CMM errors: factors up to 1.97 and
            # instrument z sd 0.46-0.94; ct_core.md "Uncertainty model"). At least a ninth of the raw
            # scatter is kept (a reference file that overstates its centres' uncertainty cannot
            # drive the factor to zero).
            jc = np.asarray(centre_jac, dtype=float)[:, a * q:(a + 1) * q]
            a_i = np.sum(jc * jc, axis=0) * np.asarray(centre_var, dtype=float)[np.asarray(sphere_index)]
            cmm_m2 = np.bincount(vid, w * w * a_i, n_v) / wsum ** 2       # E[mean_v^2] from the centres
            e_cmm = float(np.sum(w * a_i)) - float(np.sum(cmm_m2 * wsum))
            e_tot = (e_tot or 0.0) + float(np.sum(w * a_i))
            ss = max(ss - e_cmm * dof_w / max(q - n_v, 1), ss / 9.0)
        f2 = ss / dof_w if n_v < q else ss / max(q - 0.5 * n_params, 1)
        factors.append(np.sqrt(max(f2, 0.0)))
        if track and sphere_index is not None and n_v >= 8 and f2 > 0:
            if table is None:
                table = _track_table(sphere_index, vid, n_v)
            known = None
            if centre_jac is not None and centre_var is not None:
                # what the calibrated centres' stated errors put into each track (per sphere, the
                # same offset in every view: correlated at every lag), whitened like the residuals
                zc = np.asarray(centre_jac, dtype=float)[:, a * q:(a + 1) * q] / sa
                known = (zc, np.asarray(centre_var, dtype=float)[np.asarray(sphere_index)])
            raw, se, used = _track_correlation(dev / sa, table, known)
        else:
            raw, se, used = (), (), ()
        lag_se.append(se)
        lag_raw.append(raw)
        lag_used.append(used)
        if view_sd_px is not None:
            taus.append(float(view_sd_px[a]))
        elif n_v >= 5:
            # E[m_v^2] = tau^2 + f^2 / W_v; the fit absorbs a share ~ n_params / (2 n_v) of the
            # projection means' variance, corrected for by the degrees of freedom. The component
            # is kept only when it is significant (more than 2 standard errors of its estimate,
            # sqrt(2 / n_v) times the noise of a projection mean): with none in the data the
            # estimate scatters about 0 and would inflate the covariance by chance.
            excess = mean ** 2 - f2 / wsum - cmm_m2
            t2 = float(np.sum(excess)) / max(n_v - 0.5 * n_params, 1.0)
            se = np.sqrt(2.0 / n_v) * float(np.mean(f2 / wsum))
            taus.append(np.sqrt(t2) if t2 > 2.0 * se else 0.0)
        else:
            taus.append(0.0)
    med = float(np.median(sig)) if sig.size else 1.0
    # the whole chi-square net of the centres' expected share (the fit's share taken as for the noise)
    chi2_net = None if e_tot is None else max(chi2 - e_tot / (2 * q), chi2 / 9.0)
    rho = [t * t / (t * t + (f * med) ** 2) if (t > 0 or f > 0) else 0.0 for f, t in zip(factors, taus)]
    source = "given" if view_sd_px is not None else ("estimated" if n_v >= 5 else "none")
    return NoiseModel(factor_u=factors[0], factor_v=factors[1], view_sd_u_px=taus[0], view_sd_v_px=taus[1],
                      chi2_dof=chi2, within_view_correlation_u=rho[0], within_view_correlation_v=rho[1],
                      n_views=n_v, view_sd_source=source, sigma_reported=sigma is not None,
                      track_lag_corr_u=lag_raw[0], track_lag_corr_v=lag_raw[1],
                      track_lag_se_u=lag_se[0], track_lag_se_v=lag_se[1],
                      track_corr_u=lag_used[0], track_corr_v=lag_used[1], chi2_dof_net=chi2_net)


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
                        normals=None, sphere_index=None):
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
    sphere_index : ndarray of shape (Q,), optional
        Sphere of each observation: needed for the noise model's track correlation (ignored
        without it).

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
    if sphere_index is not None and any(noise.track_corr):
        table = _track_table(sphere_index, vid, n_v)
        for a, corr in enumerate(noise.track_corr):
            if not corr:
                continue
            sl = slice(a * q, (a + 1) * q)
            g = k[:, sl] * (sn[sl] / sw[sl] ** 2)        # J^T W times the noise sd, per observation
            for lag, c in enumerate(corr, start=1):
                i, j = table[:, :-lag].ravel(), table[:, lag:].ravel()
                keep = (i >= 0) & (j >= 0)
                cross = g[:, i[keep]] @ g[:, j[keep]].T
                meat += c * (cross + cross.T)
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
    # with stated centre uncertainties, net of their expected share (the data may scatter by that much)
    c2, net = noise.chi2_dof, ""
    if noise.chi2_dof_net is not None:
        c2, net = noise.chi2_dof_net, " (net of the calibrated centres' stated uncertainty)"
    if note is not None:
        c2 = float(np.mean(z * z)) * (c2 / max(noise.chi2_dof, 1e-300))
    if sigma is not None and np.sqrt(c2) > max_rms_ratio:
        return False, (f"the model does not explain the data: residuals are {np.sqrt(c2):.3g} times "
                       f"the detector's stated uncertainty{net} (limit {max_rms_ratio:g}) across the data. Likely "
                       "causes: the reference object mounted otherwise than its file says (upside down?), a "
                       "wrong reference object file, the image orientation (rows or columns mirrored) or the "
                       "rotation direction, or physics the model leaves out (run ct_discrepancy)")
    if robust_px > max_rms_px:
        return False, (f"converged to a poor fit: robust residual scale {robust_px:.3g} px > {max_rms_px:g} px "
                       "(local minimum, wrong identification or wrong nominal inputs)")
    return True, note
