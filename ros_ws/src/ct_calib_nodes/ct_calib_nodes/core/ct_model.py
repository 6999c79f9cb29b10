"""Residual functions and analytic Jacobians of the CT projection models.

Two models, each with ONE pure residual function shared by the solvers, the
tests and later analyses:

* :func:`static_residuals` -- stage position k = 1 in {SRF} (eqs 1-3, App. A),
  parameters ``x = [w (13), term parameters...]``.
* :func:`motion_residuals` -- stage position k in {DF} (eqs 8-11, App. B),
  parameters ``m (6)`` on top of a fixed :class:`DetectorFrameGeometry`.

Residuals are ``modelled - observed`` in pixels, interleaved per observation
as in eq. 3: ``[u_1, v_1, u_2, v_2, ...]`` (shape (2Q,)); u is the column,
v the row coordinate.

The values reproduce geometry.forward_srf / forward_df exactly (tested); the
Jacobians are chain-rule derivatives of the same expressions (tested
against finite differences).

Pipeline (both models)::

    alpha  --"angle" terms-->  alpha_true  --rotation about the axis-->  point
    point  --central projection from the source-->  xy on the detector [m, {DF}]
    xy     --"image" terms-->  xy_true  --pixel grid-->  (col, row) [px]
"""

from __future__ import annotations

import numpy as np

from .geometry import (DetectorFrameGeometry, DetectorSpec, STATIC_PARAM_NAMES, STATIC_PARAM_UNITS,
                       MOTION_PARAM_NAMES, MOTION_PARAM_UNITS, detector_rotation, motion_rotation,
                       object_rotation, rot_x, rot_y, rot_z)
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
    terms = check_terms(terms)
    x = _check_x(x, terms)
    n = x.size
    tpar = _split_terms(x, terms)
    w = x[:13]
    z_r, dvec = w[0], w[1:4]
    r_obj = object_rotation(w[10], w[11], w[12])
    c1 = centres_of_m @ r_obj.T + w[7:10]                  # (N, 3) eq. 1
    idx = obs.sphere_index
    alpha, a_derivs = _angle_stage(obs.alpha_rad, tpar, terms, obs, n, 13)
    ca, sa = np.cos(alpha), np.sin(alpha)
    a = c1[idx]
    ax, ay, az = a[:, 0], a[:, 1], a[:, 2] - z_r
    p = np.empty_like(a)                                   # eq. 2
    p[:, 0] = ca * ax + sa * az
    p[:, 1] = ay
    p[:, 2] = -sa * ax + ca * az + z_r
    rdet = detector_rotation(w[4], w[5], w[6])
    g = p @ rdet                                           # R^T p: point in {DF} axes, from source
    h = dvec @ rdet                                        # R^T D
    inv = 1.0 / g[:, 2]
    rx, ry = g[:, 0] * inv, g[:, 1] * inv
    xy = np.empty((len(idx), 2))
    xy[:, 0] = h[2] * rx - h[0]                            # App. A, intersection in {DF}
    xy[:, 1] = h[2] * ry - h[1]
    if not want_jac:
        xy = _image_stage(xy, None, tpar, terms, obs, 13, False)
        return _to_pixels(xy, None, detector, False), None

    # Component-wise chain rule: jx[k], jy[k] = d x / d x_k, d y / d x_k (Q,),
    # contiguous rows, combined at the end into the (n, Q, 2) layout whose
    # transpose is the interleaved (2Q, n) Jacobian.
    q = len(idx)
    jx = np.empty((n, q))
    jy = np.empty((n, q))
    jx[13:] = 0.0                                          # term columns not set below stay zero
    jy[13:] = 0.0
    rd = rdet.T                                            # rows: u, v, n axes in {SRF}
    k = h[2] * inv
    # d(x, y) / d p: mx[j] = dx/dp_j, my[j] = dy/dp_j, each (Q,)
    mx = [k * (rd[0, j] - rx * rd[2, j]) for j in range(3)]
    my = [k * (rd[1, j] - ry * rd[2, j]) for j in range(3)]
    # z_R: dp/dz_R = (-sin a, 0, 1 - cos a)
    omc = 1.0 - ca
    jx[0] = mx[2] * omc - mx[0] * sa
    jy[0] = my[2] * omc - my[0] * sa
    # D: x = h_z r_x - h_x with h = R^T D
    for j in range(3):
        jx[1 + j] = rx * rd[2, j] - rd[0, j]
        jy[1 + j] = ry * rd[2, j] - rd[1, j]
    # detector angles: R = Rz(eta) Ry(phi) Rx(theta)
    th, ph, et = w[4], w[5], w[6]
    d_r = (rot_z(et) @ rot_y(ph) @ _drot_x(th),
           rot_z(et) @ _drot_y(ph) @ rot_x(th),
           _drot_z(et) @ rot_y(ph) @ rot_x(th))
    for j, dr in enumerate(d_r):
        dg = p @ dr
        dh = dvec @ dr
        jx[4 + j] = k * (dg[:, 0] - rx * dg[:, 2]) + (rx * dh[2] - dh[0])
        jy[4 + j] = k * (dg[:, 1] - ry * dg[:, 2]) + (ry * dh[2] - dh[1])
    # object position P: dp/dP = Ry(alpha)
    rmx = (mx[0] * ca - mx[2] * sa, mx[1], mx[0] * sa + mx[2] * ca)
    rmy = (my[0] * ca - my[2] * sa, my[1], my[0] * sa + my[2] * ca)
    for j in range(3):
        jx[7 + j] = rmx[j]
        jy[7 + j] = rmy[j]
    # object orientation: R_obj = Ry(rho_Y) Rz(rho_Z) Rx(rho_X)
    rxo, ryo, rzo = w[10], w[11], w[12]
    d_obj = (rot_y(ryo) @ rot_z(rzo) @ _drot_x(rxo),
             _drot_y(ryo) @ rot_z(rzo) @ rot_x(rxo),
             rot_y(ryo) @ _drot_z(rzo) @ rot_x(rxo))
    for j, dro in enumerate(d_obj):
        dc = (centres_of_m @ dro.T)[idx]                   # (Q, 3)
        jx[10 + j] = rmx[0] * dc[:, 0] + rmx[1] * dc[:, 1] + rmx[2] * dc[:, 2]
        jy[10 + j] = rmy[0] * dc[:, 0] + rmy[1] * dc[:, 1] + rmy[2] * dc[:, 2]
    # angle terms: dp/dalpha = (-sa ax + ca az, 0, -ca ax - sa az)
    if a_derivs:
        dpa0 = -sa * ax + ca * az
        dpa2 = -ca * ax - sa * az
        jax = mx[0] * dpa0 + mx[2] * dpa2
        jay = my[0] * dpa0 + my[2] * dpa2
        for cols, dd in a_derivs:
            jx[cols] = jax[None, :] * dd.T
            jy[cols] = jay[None, :] * dd.T
    pitch = detector.pixel_pitch_m
    if not any(t.stage == "image" for t in terms):
        jt = np.empty((n, q, 2))
        jt[:, :, 0] = jx * (1.0 / pitch)
        jt[:, :, 1] = jy * (-1.0 / pitch)
        return _to_pixels(xy, None, detector, False), jt.transpose(1, 2, 0)   # (Q, 2, n) view
    jac = np.stack([jx.T, jy.T], axis=1)                  # (Q, 2, n)
    xy = _image_stage(xy, jac, tpar, terms, obs, 13, True)
    uv = _to_pixels(xy, jac, detector, True)
    return uv, jac


def static_residuals(x, obs: CentreObservations, centres_of_m, detector: DetectorSpec, terms=()):
    """THE residual function of the static model (eq. 3): modelled - observed.

    Returns
    -------
    ndarray of shape (2Q,) [px], interleaved (u_1, v_1, u_2, v_2, ...).
    """
    uv, _ = static_predict(x, obs, centres_of_m, detector, terms, want_jac=False)
    return (uv - obs.uv_px).ravel()


def static_residuals_jac(x, obs: CentreObservations, centres_of_m, detector: DetectorSpec, terms=()):
    """Residuals (2Q,) [px] and their analytic Jacobian (2Q, 13 + p).

    The Jacobian may be a non-contiguous (Fortran-ordered) view; ``J.T @ J``
    is then a fast BLAS product.
    """
    uv, jac = static_predict(x, obs, centres_of_m, detector, terms, want_jac=True)
    q = len(uv)
    if jac.flags.c_contiguous:
        return (uv - obs.uv_px).ravel(), jac.reshape(2 * q, -1)
    return (uv - obs.uv_px).ravel(), jac.transpose(2, 0, 1).reshape(-1, 2 * q).T


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
        a = (centres - self.stage)[obs.sphere_index]       # (Q, 3)
        c, s = np.cos(alpha)[:, None], np.sin(alpha)[:, None]
        self.e = a * c + np.cross(axis, a) * s + np.outer(a @ axis, axis) * (1.0 - c)

    def predict(self, m, want_jac=False):
        """(col, row) (Q, 2) [px] and optionally d/dm (Q, 2, 6)."""
        m = np.asarray(m, dtype=float)
        if m.shape != (6,) or not np.all(np.isfinite(m)):
            raise ValueError(f"motion must be 6 finite values, got shape {m.shape}")
        gmat = motion_rotation(m[3], m[4], m[5])
        p = self.stage + m[:3] + self.e @ gmat.T           # eqs 8-11
        s = self.source
        dz = p[:, 2] - s[2]
        mag = -s[2] / dz
        dx, dy = p[:, 0] - s[0], p[:, 1] - s[1]
        xy = np.empty((len(p), 2))
        xy[:, 0] = s[0] + dx * mag                         # App. B
        xy[:, 1] = s[1] + dy * mag
        jac = None
        if want_jac:
            q = len(p)
            mq = np.zeros((q, 2, 3))
            mq[:, 0, 0] = mag
            mq[:, 0, 2] = -dx * mag / dz
            mq[:, 1, 1] = mag
            mq[:, 1, 2] = -dy * mag / dz
            jac = np.empty((q, 2, 6))
            jac[:, :, :3] = mq
            gx, gy, gz = m[3], m[4], m[5]
            d_g = (_drot_x(gx) @ rot_y(gy) @ rot_z(gz),
                   rot_x(gx) @ _drot_y(gy) @ rot_z(gz),
                   rot_x(gx) @ rot_y(gy) @ _drot_z(gz))
            for j, dg in enumerate(d_g):
                jac[:, :, 3 + j] = np.einsum("qij,qj->qi", mq, self.e @ dg.T)
        xy = _image_stage_fixed(xy, jac, self.tpar, self.terms, self.obs)
        return _to_pixels(xy, jac, self.detector, want_jac), jac

    def residuals(self, m):
        uv, _ = self.predict(m)
        return (uv - self.obs.uv_px).ravel()

    def residuals_jac(self, m):
        uv, jac = self.predict(m, want_jac=True)
        return (uv - self.obs.uv_px).ravel(), jac.reshape(2 * len(uv), 6)


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
    """THE residual function of the error-motion model (eqs 8-11): modelled - observed.

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
