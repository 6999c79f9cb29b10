"""Residual functions and analytic Jacobians of the CT projection models.

Two models, each with ONE pure residual function shared by the solvers, the
tests and later analyses:

* :func:`static_residuals` -- stage position k = 1 in {SRF} (eqs 1-3, App. A),
  parameters ``x = [w (13), term parameters...]``.
* :func:`motion_residuals` -- stage position k in {DF} (eqs 8-11, App. B),
  parameters ``m (6)`` on top of a fixed :class:`DetectorFrameGeometry`.

Sign: every residual this project returns or reports is ``observed -
modelled`` in pixels, interleaved per observation ``[u_1, v_1, u_2, v_2, ...]``
(shape (2Q,)); u is the column, v the row coordinate. Only the kernels'
blocked ``evaluate`` / ``residuals`` / ``residuals_blocked`` return the paper's
eq. 3 vector f = modelled - observed, which the solvers minimise (the sign of
f does not change the least-squares problem).

The values reproduce geometry.forward_srf / forward_df exactly (tested); the
Jacobians are chain-rule derivatives of the same expressions (tested
against finite differences).

Observable: the detector reports the centre of the ellipse fitted to each
sphere's shadow, not the projection of the sphere's centre (the paper's model).
Every iso-transmission contour of a sphere is the section of a circular cone
of rays about the source-to-centre line, and for such a section the ellipse
centre E, the centre projection C and the principal point P (foot of the
perpendicular from the source, at distance D) satisfy exactly

    E - P = (1 + (b / D)^2) (C - P)

with b the ellipse's semi-minor axis (Deng et al. 2015; derivation in
doc/ct_core.md). When the observations carry the measured semi-minor axes
(``CentreObservations.minor_axis_px``) both kernels model E, with P and D
from the current geometry; otherwise they model C. The shift is about
1.7e-5 of the distance from P at SRD 364 mm (0.005 px at 300 px): small, but
the same sign everywhere, which biases z_R and the magnification scale.

Pipeline (both models)::

    alpha  --"angle" terms-->  alpha_true  --rotation about the axis-->  point
    point  --central projection from the source-->  xy on the detector [m, {DF}]
    xy     --"image" terms-->  xy_true  --pixel grid-->  (col, row) [px]
"""

from __future__ import annotations

import numpy as np

from .geometry import (DetectorFrameGeometry, DetectorSpec, STATIC_PARAM_NAMES, STATIC_PARAM_UNITS,
                       MOTION_PARAM_NAMES, MOTION_PARAM_UNITS, detector_rotation, motion_rotation,
                       object_rotation, rot_x, rot_y)
from .observations import CentreObservations
from .terms import check_terms


def _drot_x(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[0.0, 0.0, 0.0], [0.0, -s, -c], [0.0, c, -s]])


def _drot_y(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[-s, 0.0, c], [0.0, 0.0, 0.0], [-c, 0.0, -s]])


def _drot_z(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[-s, -c, 0.0], [c, -s, 0.0], [0.0, 0.0, 0.0]])


def _cross3(a, b):
    """Cross product of two 3-vectors (np.cross has a large fixed overhead)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def param_names(terms=()) -> tuple:
    """Names of the static parameter vector ``x`` with the given terms."""
    return STATIC_PARAM_NAMES + tuple(n for t in check_terms(terms) for n in t.param_names)


def param_units(terms=()) -> tuple:
    """Units of the static parameter vector ``x`` with the given terms."""
    return STATIC_PARAM_UNITS + tuple(u for t in check_terms(terms) for u in t.param_units)


def _split_terms(x, terms):
    out, k = [], 13
    for t in terms:
        out.append(x[k:k + t.n_params])
        k += t.n_params
    return out


def _check_x(x, terms):
    x = np.asarray(x, dtype=float)
    n = 13 + sum(t.n_params for t in terms)
    if x.shape != (n,):
        raise ValueError(f"parameter vector must have shape ({n},) for these terms, got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("parameter vector contains NaN or inf")
    return x


def _angle_stage(alpha, term_params, terms, obs, n_total, col0):
    """Apply 'angle' terms. Returns alpha_true (Q,), list of (cols, d_alpha/d_par (Q,p))."""
    alpha = alpha.copy()
    derivs = []
    col = col0
    for t, p in zip(terms, term_params):
        if t.stage == "angle":
            d, dd = t.angle_delta(p, obs.alpha_rad, obs)
            alpha += d
            derivs.append((slice(col, col + t.n_params), np.asarray(dd, dtype=float)))
        col += t.n_params
    return alpha, derivs


def _image_stage(xy, jac_xy, term_params, terms, obs, col0, want_jac):
    """Apply 'image' terms in pipeline order; updates jac_xy (Q, 2, n) in place."""
    col = col0
    for t, p in zip(terms, term_params):
        if t.stage == "image":
            d, d_par, d_xy = t.image_delta(p, xy, obs)
            if want_jac:
                # chain rule: d xy_new = (I + d_xy) d xy ; own parameters added
                jac_xy += np.einsum("qij,qjn->qin", d_xy, jac_xy)
                jac_xy[:, :, col:col + t.n_params] += d_par
            xy = xy + d
        col += t.n_params
    return xy


def _to_pixels(xy, jac_xy, detector: DetectorSpec, want_jac):
    c0, r0 = detector.centre_px
    pitch = detector.pixel_pitch_m
    uv = np.empty_like(xy)
    uv[:, 0] = c0 + xy[:, 0] / pitch
    uv[:, 1] = r0 - xy[:, 1] / pitch
    if want_jac:
        jac_xy *= np.array([1.0 / pitch, -1.0 / pitch])[None, :, None]
    return uv


# --------------------------------------------------------------------------- static model
def _cos_sin_runs(alpha):
    """cos and sin of alpha (Q,), evaluated once per run of equal values (one per projection)."""
    if alpha.size < 2:
        return np.cos(alpha), np.sin(alpha)
    start = np.empty(alpha.size, dtype=bool)
    start[0] = True
    np.not_equal(alpha[1:], alpha[:-1], out=start[1:])
    run = np.cumsum(start) - 1
    a = alpha[start]
    return np.cos(a)[run], np.sin(a)[run]


def lm_function(kernel):
    """A StaticKernel or MotionKernel as levenberg_marquardt's ``fun``: x -> (r, lazy J), with
    J (m, n) the transpose of the kernel's blocked (n, m) Jacobian."""
    def fun(x):
        r, jac = kernel.evaluate(x)
        return r, (lambda: jac().T)
    return fun


class StaticKernel:
    """The static model (eqs 1-3, App. A) precomputed for one observation set.

    This is the one implementation of the static model: :func:`static_predict`,
    :func:`static_residuals` and :func:`static_residuals_jac` call it, and the
    static solver uses it directly. Everything that does not depend on the
    parameters is computed once (cos/sin of the reported angles when there is
    no "angle" term, the calibrated centre of each observation, the observed
    coordinates), and the Jacobian is built lazily from the forward pass's
    intermediates, so a rejected LM step costs one forward pass and an
    accepted one does not repeat it.

    Layout (BLOCKED, unlike the interleaved public functions): residuals
    ``[u_1 .. u_Q, v_1 .. v_Q]`` (2Q,) [px] and the Jacobian as the
    C-contiguous transpose ``K`` (n, 2Q) [px per parameter unit], so that
    ``J^T J = K K^T`` is one BLAS product over contiguous rows.

    Derivatives in closed form (rotation derivatives as cross products): with
    ``R = Rz(eta) Ry(phi) Rx(theta)`` and ``g = R^T p`` the point in {DF}
    axes, ``dg = g x omega`` for ``dR = R [omega]_x`` (omega = e_x, Rx^T e_y,
    R^T e_z); with ``r = g_xy / g_z`` the image point ``h_z r - h_xy``
    (h = R^T D) then has derivatives that are polynomials in r_x, r_y. The
    object rotation ``Ry Rz Rx(rho)`` gives ``dC = omega x (R_obj C)``
    (omega = R_obj e_x, e_y, Ry e_z).

    Parameters
    ----------
    obs : CentreObservations
    centres_of_m : ndarray of shape (N, 3)
        Sphere centres in {OF} [m].
    detector : DetectorSpec
    terms : sequence of Term
    """

    def __init__(self, obs: CentreObservations, centres_of_m, detector: DetectorSpec, terms=()):
        self.terms = check_terms(terms)
        self.n = 13 + sum(t.n_params for t in self.terms)
        c = np.asarray(centres_of_m, dtype=float)
        if c.ndim != 2 or c.shape[1] != 3:
            raise ValueError(f"centres_of_m must have shape (N, 3), got {c.shape}")
        obs.check_spheres(len(c))
        self.obs = obs
        self.detector = detector
        self.q = obs.n_obs
        self.centres_q = np.ascontiguousarray(c[obs.sphere_index].T)      # (3, Q)
        self.has_angle = any(t.stage == "angle" for t in self.terms)
        self.has_image = any(t.stage == "image" for t in self.terms)
        if not self.has_angle:
            self._ca, self._sa = _cos_sin_runs(obs.alpha_rad)
        self.c0, self.r0 = detector.centre_px
        self.pitch = detector.pixel_pitch_m
        self.observed = np.concatenate([obs.uv_px[:, 0], obs.uv_px[:, 1]])  # (2Q,) blocked
        # squared semi-minor axis [m^2] of each observed shadow ellipse: the model is then the
        # ellipse centre (module docstring); None: the centre projection
        self.b2 = None if obs.minor_axis_px is None else (obs.minor_axis_px * self.pitch) ** 2

    # ------------------------------------------------------------------ layout helpers
    def interleave(self, r_blocked):
        """Blocked (2Q,) -> interleaved (2Q,) ``[u_1, v_1, u_2, ...]``."""
        return np.asarray(r_blocked).reshape(2, -1).T.ravel()

    def blocked_weights(self, per_obs):
        """Per-observation values (Q,) repeated for u and v in blocked order (2Q,)."""
        return np.concatenate([per_obs, per_obs])

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, x):
        """Residuals and a lazy Jacobian at ``x``.

        Parameters
        ----------
        x : array_like of shape (n,)

        Returns
        -------
        r : ndarray of shape (2Q,)
            f = modelled - observed [px] (eq. 3), blocked.
        jac : callable
            ``jac()`` returns K, shape (n, 2Q): d r / d x (transposed, blocked).
        """
        x = _check_x(x, self.terms)
        st = self._forward(x)
        return st["r"], (lambda: self._jacobian(st))

    def residuals(self, x):
        """f = modelled - observed (eq. 3), blocked (2Q,) [px]."""
        return self._forward(_check_x(x, self.terms))["r"]

    def _forward(self, x):
        terms, q = self.terms, self.q
        tpar = _split_terms(x, terms)
        w = x[:13]
        z_r = w[0]
        if self.has_angle:
            alpha, a_derivs = _angle_stage(self.obs.alpha_rad, tpar, terms, self.obs, self.n, 13)
            ca, sa = np.cos(alpha), np.sin(alpha)
        else:
            ca, sa, a_derivs = self._ca, self._sa, []
        b = object_rotation(w[10], w[11], w[12]) @ self.centres_q          # (3, Q) eq. 1 without P
        ax = b[0] + w[7]
        az = b[2] + (w[9] - z_r)
        p = np.empty((3, q))                                               # eq. 2
        np.multiply(ca, ax, out=p[0])
        p[0] += sa * az
        p[1] = b[1] + w[8]
        np.multiply(ca, az, out=p[2])
        p[2] -= sa * ax
        p[2] += z_r
        rdet = detector_rotation(w[4], w[5], w[6])
        rd = rdet.T                                                        # rows: u, v, n axes
        g = rd @ p                                                         # point in {DF} axes, from source
        h = rd @ w[1:4]                                                    # R^T D
        inv = 1.0 / g[2]
        rx = g[0] * inv
        ry = g[1] * inv
        # ellipse centre: E - P = (1 + e)(C - P), e = b^2 / D^2 with D = h_z the source-to-plane
        # distance and C - P = h_z r in {DF} metres
        e = None if self.b2 is None else self.b2 / (h[2] * h[2])
        hz = h[2] if e is None else h[2] * (1.0 + e)
        r = np.empty(2 * q)
        xy = None
        if self.has_image:
            xy = np.empty((q, 2))
            xy[:, 0] = hz * rx - h[0]                                      # App. A, in {DF} [m]
            xy[:, 1] = hz * ry - h[1]
            xy_t = _image_stage(xy, None, tpar, terms, self.obs, 13, False)
            np.multiply(xy_t[:, 0], 1.0 / self.pitch, out=r[:q])
            np.multiply(xy_t[:, 1], -1.0 / self.pitch, out=r[q:])
            r[:q] += self.c0
            r[q:] += self.r0
        else:
            np.multiply(rx, hz / self.pitch, out=r[:q])
            r[:q] += self.c0 - h[0] / self.pitch
            np.multiply(ry, -hz / self.pitch, out=r[q:])
            r[q:] += self.r0 + h[1] / self.pitch
        r -= self.observed
        return dict(x=x, w=w, tpar=tpar, ca=ca, sa=sa, a_derivs=a_derivs, b=b, p=p, rdet=rdet, h=h,
                    inv=inv, rx=rx, ry=ry, xy=xy, r=r, e=e)

    def _jacobian(self, st):
        q, n = self.q, self.n
        w, ca, sa, rx, ry, h = st["w"], st["ca"], st["sa"], st["rx"], st["ry"], st["h"]
        rdet = st["rdet"]
        rd = rdet.T
        if self.has_image:
            su = sv = 1.0              # metric first: image terms chain through xy, pixels last
        else:
            su, sv = 1.0 / self.pitch, -1.0 / self.pitch
        jac = np.empty((n, 2 * q))
        jac[13:] = 0.0
        ju, jv = jac[:, :q], jac[:, q:]
        # D (1..3) and detector angles (4..6): polynomials in (rx, ry), one small product each
        basis = np.empty((6, q))
        np.multiply(rx, ry, out=basis[0])
        np.multiply(rx, rx, out=basis[1])
        np.multiply(ry, ry, out=basis[2])
        basis[3] = rx
        basis[4] = ry
        basis[5] = 1.0
        e = st["e"]
        if e is not None:
            # ellipse centre: J_E = (1 + e) J_C + e (dh_xy - 2 r dh_z) (doc/ct_core.md); the
            # (1 + e) factor goes into the per-observation polynomials and gains below, the
            # extra term is added to the rows of D and of the detector angles
            basis[:5] *= 1.0 + e
            basis[5] = 1.0 + e
        th = w[4]
        omegas = (np.array([1.0, 0.0, 0.0]), np.array([0.0, np.cos(th), -np.sin(th)]), rdet[2].copy())
        cu = np.zeros((6, 6))
        cv = np.zeros((6, 6))
        for j in range(3):             # x = h_z r_x - h_x, h = R^T D: dx/dD_j = rd[2,j] r_x - rd[0,j]
            cu[j, 3], cu[j, 5] = rd[2, j], -rd[0, j]
            cv[j, 4], cv[j, 5] = rd[2, j], -rd[1, j]
        for j, om in enumerate(omegas):
            dh = _cross3(h, om)        # d h / d angle
            # dg = g x om; (dx/dg) . dg = h_z (rx ry, -(1 + rx^2), ry) . om
            cu[3 + j] = h[2] * np.array([om[0], -om[1], 0.0, dh[2] / h[2], om[2], -om[1] - dh[0] / h[2]])
            # y: h_z (1 + ry^2, -rx ry, -rx) . om, plus ry dh_z - dh_y
            cv[3 + j] = h[2] * np.array([-om[1], 0.0, om[0], -om[2], dh[2] / h[2], om[0] - dh[1] / h[2]])
        np.matmul(cu * su, basis, out=ju[1:7])
        np.matmul(cv * sv, basis, out=jv[1:7])
        if e is not None:
            for j in range(6):
                dh = rd[:, j] if j < 3 else _cross3(h, omegas[j - 3])
                ju[1 + j] += (su * e) * (dh[0] - 2.0 * dh[2] * rx)
                jv[1 + j] += (sv * e) * (dh[1] - 2.0 * dh[2] * ry)
        # d(x, y)/dp: mx_j = k (rd[0,j] - rx rd[2,j]), k = h_z / g_z; object position rows = Ry(alpha)^T m
        ku = (h[2] * su) * st["inv"]
        kv = (h[2] * sv) * st["inv"]
        if e is not None:
            ku = ku * (1.0 + e)
            kv = kv * (1.0 + e)
        kur = ku * rx
        kvr = kv * ry
        mx0 = rd[0, 0] * ku - rd[2, 0] * kur
        mx2 = rd[0, 2] * ku - rd[2, 2] * kur
        my0 = rd[1, 0] * kv - rd[2, 0] * kvr
        my2 = rd[1, 2] * kv - rd[2, 2] * kvr
        b = st["b"]
        cr = np.empty((3, q))
        robj = object_rotation(w[10], w[11], w[12])
        om_obj = np.array([robj[:, 0], [0.0, 1.0, 0.0], rot_y(w[11])[:, 2]])
        for jj, m0, m2, kk, kr, row in ((ju, mx0, mx2, ku, kur, 0), (jv, my0, my2, kv, kvr, 1)):
            np.multiply(m0, ca, out=jj[7])
            jj[7] -= m2 * sa
            np.multiply(kk, rd[row, 1], out=jj[8])
            jj[8] -= kr * rd[2, 1]
            np.multiply(m0, sa, out=jj[9])
            jj[9] += m2 * ca
            np.subtract(m2, jj[9], out=jj[0])   # z_R: dp/dz_R = e_z - Ry(alpha) e_z
            # object orientation: d r / d rho_j = omega_j . (b x rm), rm = rows 7..9
            rm = jj[7:10]
            np.multiply(b[1], rm[2], out=cr[0])
            cr[0] -= b[2] * rm[1]
            np.multiply(b[2], rm[0], out=cr[1])
            cr[1] -= b[0] * rm[2]
            np.multiply(b[0], rm[1], out=cr[2])
            cr[2] -= b[1] * rm[0]
            np.matmul(om_obj, cr, out=jj[10:13])
            if st["a_derivs"]:          # angle terms: dp/dalpha = (p_z - z_R, 0, -p_x)
                p = st["p"]
                jal = m0 * (p[2] - w[0]) - m2 * p[0]
                for cols, dd in st["a_derivs"]:
                    jj[cols] = jal[None, :] * dd.T
        if self.has_image:
            jx = np.ascontiguousarray(ju)
            jy = np.ascontiguousarray(jv)
            jxy = np.stack([jx.T, jy.T], axis=1)              # (Q, 2, n)
            _image_stage(st["xy"], jxy, st["tpar"], self.terms, self.obs, 13, True)
            ju[:] = jxy[:, 0, :].T * (1.0 / self.pitch)
            jv[:] = jxy[:, 1, :].T * (-1.0 / self.pitch)
        return jac


def static_predict(x, obs: CentreObservations, centres_of_m, detector: DetectorSpec, terms=(),
                   want_jac: bool = False):
    """Modelled centre projections at k = 1 and optionally their Jacobian.

    Parameters
    ----------
    x : array_like of shape (13 + p,)
        Static parameters w (geometry.py order) followed by the terms' parameters.
    obs : CentreObservations
        Supplies sphere_index, alpha_rad (and stamp_ns for terms that need it).
    centres_of_m : ndarray of shape (N, 3)
        Sphere centres in {OF} [m].
    detector : DetectorSpec
    terms : sequence of Term
    want_jac : bool

    Returns
    -------
    uv_px : ndarray of shape (Q, 2)
    jac : ndarray of shape (Q, 2, 13 + p) or None
        d (col, row) / d x [px per parameter unit].
    """
    kern = StaticKernel(obs, centres_of_m, detector, terms)
    r, jac = kern.evaluate(x)
    q = kern.q
    uv = (r + kern.observed).reshape(2, q).T.copy()
    if not want_jac:
        return uv, None
    return uv, jac().reshape(kern.n, 2, q).transpose(2, 1, 0)


def static_residuals(x, obs: CentreObservations, centres_of_m, detector: DetectorSpec, terms=()):
    """THE residual function of the static model: observed - modelled.

    Returns
    -------
    ndarray of shape (2Q,) [px], interleaved (u_1, v_1, u_2, v_2, ...).
    """
    kern = StaticKernel(obs, centres_of_m, detector, terms)
    return -kern.interleave(kern.residuals(x))


def static_residuals_jac(x, obs: CentreObservations, centres_of_m, detector: DetectorSpec, terms=()):
    """Residuals observed - modelled (2Q,) [px] and their analytic Jacobian (2Q, 13 + p), interleaved.

    The Jacobian is a Fortran-ordered view; ``J.T @ J`` is then a fast BLAS product.
    """
    kern = StaticKernel(obs, centres_of_m, detector, terms)
    r, jac = kern.evaluate(x)
    k = jac()
    q = kern.q
    jt = np.empty((kern.n, q, 2))
    jt[:, :, 0] = -k[:, :q]
    jt[:, :, 1] = -k[:, q:]
    return -kern.interleave(r), jt.reshape(kern.n, 2 * q).T


# --------------------------------------------------------------------------- error-motion model
def motion_names() -> tuple:
    return MOTION_PARAM_NAMES


def motion_units() -> tuple:
    return MOTION_PARAM_UNITS


class MotionKernel:
    """Precomputed parts of the error-motion model for one observation set.

    The sphere-centre offsets from the stage point after rotation about the
    k = 1 axis, ``e = Rot(r_1, alpha) (C_i - R_1)``, do not depend on the
    motion parameters (eqs 9-11 give ``C_ijk = R_k + G Rot(r_1, alpha)
    (C_i - R_1)`` with ``G = Rx Ry Rz(gamma)``), so they are computed once.

    Parameters
    ----------
    geom : DetectorFrameGeometry
    obs : CentreObservations
    detector : DetectorSpec
    terms : sequence of Term
        Applied with fixed parameters ``term_params`` (from the static solve).
    term_params : array_like of shape (p,)
    """

    def __init__(self, geom: DetectorFrameGeometry, obs: CentreObservations, detector: DetectorSpec,
                 terms=(), term_params=()):
        self.terms = check_terms(terms)
        tp = np.asarray(term_params, dtype=float).reshape(-1)
        if tp.size != sum(t.n_params for t in self.terms):
            raise ValueError(f"term_params must have {sum(t.n_params for t in self.terms)} values, got {tp.size}")
        self.tpar = _split_terms(np.concatenate([np.zeros(13), tp]), self.terms)
        self.obs = obs
        self.detector = detector
        self.source = np.asarray(geom.source_df_m, dtype=float)
        self.stage = np.asarray(geom.stage_df_m, dtype=float)
        axis = np.asarray(geom.axis_df, dtype=float)
        axis = axis / np.linalg.norm(axis)
        centres = np.asarray(geom.centres_df_m, dtype=float)
        obs.check_spheres(len(centres))
        alpha, _ = _angle_stage(obs.alpha_rad, self.tpar, self.terms, obs, 0, 0)
        # Rodrigues per sphere, then per observation: e = c a + s (r x a) + (1 - c)(r . a) r
        a_s = centres - self.stage                                   # (N, 3)
        ra = np.cross(axis, a_s)[obs.sphere_index].T                 # (3, Q)
        ar = (a_s @ axis)[obs.sphere_index]                          # (Q,)
        at = a_s[obs.sphere_index].T                                 # (3, Q)
        c, s = _cos_sin_runs(alpha)
        self.e_t = at * c + ra * s + np.outer(axis, ar * (1.0 - c))  # (3, Q)
        self.e = self.e_t.T
        self.q = obs.n_obs
        self.has_image = any(t.stage == "image" for t in self.terms)
        self.c0, self.r0 = detector.centre_px
        self.pitch = detector.pixel_pitch_m
        self.observed = np.concatenate([obs.uv_px[:, 0], obs.uv_px[:, 1]])  # (2Q,) blocked
        # ellipse centre (module docstring): E - P = (1 + e)(C - P), e = (b / D)^2 with the source
        # fixed here, so a constant factor on the magnification of each observation
        self.ellipse_gain = (None if obs.minor_axis_px is None
                             else 1.0 + (obs.minor_axis_px * self.pitch / self.source[2]) ** 2)

    def _check_m(self, m):
        m = np.asarray(m, dtype=float)
        if m.shape != (6,) or not np.all(np.isfinite(m)):
            raise ValueError(f"motion must be 6 finite values, got shape {m.shape}")
        return m

    def evaluate(self, m):
        """Residuals and a lazy Jacobian at ``m``, BLOCKED as in :class:`StaticKernel`.

        Returns
        -------
        r : ndarray of shape (2Q,)
            f = modelled - observed ``[u_1 .. u_Q, v_1 .. v_Q]`` [px] (eq. 3).
        jac : callable
            ``jac()`` returns K, shape (6, 2Q): d r / d m (transposed, blocked).
        """
        st = self._forward(self._check_m(m))
        return st["r"], (lambda: self._jacobian(st))

    def residuals_blocked(self, m):
        """f = modelled - observed (eq. 3), blocked (2Q,) [px]."""
        return self._forward(self._check_m(m))["r"]

    def _forward(self, m):
        q = self.q
        pe = motion_rotation(m[3], m[4], m[5]) @ self.e_t          # (3, Q) rotated offsets
        s = self.source
        base = self.stage + m[:3] - s                              # eqs 8-11, relative to the source
        dx = pe[0] + base[0]
        dy = pe[1] + base[1]
        dz = pe[2] + base[2]
        mag = -s[2] / dz
        if self.ellipse_gain is not None:
            mag = mag * self.ellipse_gain                          # every Jacobian row is linear in mag
        r = np.empty(2 * q)
        xy = None
        if self.has_image:
            xy = np.empty((q, 2))
            xy[:, 0] = s[0] + dx * mag                              # App. B
            xy[:, 1] = s[1] + dy * mag
            xy_t = _image_stage_fixed(xy, None, self.tpar, self.terms, self.obs)
            np.multiply(xy_t[:, 0], 1.0 / self.pitch, out=r[:q])
            np.multiply(xy_t[:, 1], -1.0 / self.pitch, out=r[q:])
            r[:q] += self.c0
            r[q:] += self.r0
        else:
            np.multiply(dx, mag, out=r[:q])
            r[:q] *= 1.0 / self.pitch
            r[:q] += self.c0 + s[0] / self.pitch
            np.multiply(dy, mag, out=r[q:])
            r[q:] *= -1.0 / self.pitch
            r[q:] += self.r0 - s[1] / self.pitch
        r -= self.observed
        return dict(m=m, pe=pe, dx=dx, dy=dy, dz=dz, mag=mag, xy=xy, r=r)

    def _jacobian(self, st):
        q = self.q
        m, pe, mag = st["m"], st["pe"], st["mag"]
        su, sv = (1.0, 1.0) if self.has_image else (1.0 / self.pitch, -1.0 / self.pitch)
        jac = np.empty((6, 2 * q))
        ju, jv = jac[:, :q], jac[:, q:]
        # d(x, y)/dp = (mag, 0, -dx mag/dz), (0, mag, -dy mag/dz)
        w = mag / st["dz"]
        np.multiply(mag, su, out=ju[0])
        ju[1] = 0.0
        np.multiply(st["dx"], -su, out=ju[2])
        ju[2] *= w
        jv[0] = 0.0
        np.multiply(mag, sv, out=jv[1])
        np.multiply(st["dy"], -sv, out=jv[2])
        jv[2] *= w
        # G = Rx Ry Rz(gamma): d(G e)/d gamma_j = omega_j x (G e), omega = e_x, Rx e_y, Rx Ry e_z;
        # d r / d gamma_j = omega_j . (G e x m_r), m_r = the rows above
        gx, gy = m[3], m[4]
        om = np.array([[1.0, 0.0, 0.0], rot_x(gx)[:, 1], (rot_x(gx) @ rot_y(gy))[:, 2]])
        cr = np.empty((3, q))
        np.multiply(pe[1], ju[2], out=cr[0])
        np.multiply(pe[2], ju[0], out=cr[1])
        cr[1] -= pe[0] * ju[2]
        np.multiply(pe[1], ju[0], out=cr[2])
        np.negative(cr[2], out=cr[2])
        np.matmul(om, cr, out=ju[3:6])
        np.multiply(pe[1], jv[2], out=cr[0])
        cr[0] -= pe[2] * jv[1]
        np.multiply(pe[0], jv[2], out=cr[1])
        np.negative(cr[1], out=cr[1])
        np.multiply(pe[0], jv[1], out=cr[2])
        np.matmul(om, cr, out=jv[3:6])
        if self.has_image:
            jxy = np.stack([ju.T, jv.T], axis=1)                  # (Q, 2, 6)
            _image_stage_fixed(st["xy"], jxy, self.tpar, self.terms, self.obs)
            ju[:] = jxy[:, 0, :].T * (1.0 / self.pitch)
            jv[:] = jxy[:, 1, :].T * (-1.0 / self.pitch)
        return jac

    def predict(self, m, want_jac=False):
        """(col, row) (Q, 2) [px] and optionally d/dm (Q, 2, 6)."""
        r, jac = self.evaluate(m)
        uv = (r + self.observed).reshape(2, self.q).T.copy()
        if not want_jac:
            return uv, None
        return uv, jac().reshape(6, 2, self.q).transpose(2, 1, 0).copy()

    def residuals(self, m):
        """observed - modelled, interleaved (2Q,) [px]."""
        return -self.residuals_blocked(m).reshape(2, -1).T.ravel()

    def residuals_jac(self, m):
        """Residuals observed - modelled (2Q,) and their Jacobian (2Q, 6), interleaved."""
        r, jac = self.evaluate(m)
        q = self.q
        return -r.reshape(2, q).T.ravel(), -jac().reshape(6, 2, q).transpose(2, 1, 0).reshape(2 * q, 6)


def _image_stage_fixed(xy, jac, tpar, terms, obs):
    """Image terms with fixed parameters: only the chain rule through xy."""
    for t, p in zip(terms, tpar):
        if t.stage == "image":
            d, _, d_xy = t.image_delta(p, xy, obs)
            if jac is not None:
                jac += np.einsum("qij,qjn->qin", d_xy, jac)
            xy = xy + d
    return xy


def motion_residuals(m, obs: CentreObservations, geom: DetectorFrameGeometry, detector: DetectorSpec,
                     terms=(), term_params=()):
    """THE residual function of the error-motion model (eqs 8-11): observed - modelled.

    Parameters
    ----------
    m : array_like of shape (6,)
        dx_R, dy_R, dz_R [m], gamma_X, gamma_Y, gamma_Z [rad] of position k.
    obs : CentreObservations
        Observations at position k.
    geom : DetectorFrameGeometry
        The k = 1 geometry (geometry.static_to_detector_frame of the static solution).
    detector : DetectorSpec
    terms, term_params
        Optional terms with their (fixed) values from the static solve.

    Returns
    -------
    ndarray of shape (2Q,) [px]
    """
    return MotionKernel(geom, obs, detector, terms, term_params).residuals(m)
