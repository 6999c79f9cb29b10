"""The solver's model reproduces geometry.py and its analytic Jacobian matches finite differences."""

import numpy as np

from ct_calib_nodes.core import geometry as G
from ct_calib_nodes.core.ct_model import (MotionKernel, motion_residuals, static_residuals,
                                          static_residuals_jac)
from ct_calib_nodes.core.observations import CentreObservations
from ct_calib_nodes.core.terms import EncoderEccentricity, RadialDistortion


def _full_obs(uv, alpha):
    m, n = uv.shape[:2]
    return CentreObservations(uv.reshape(-1, 2), np.tile(np.arange(n), m), np.repeat(alpha, n),
                              np.repeat(np.arange(m), n), np.repeat(np.arange(m), n) * 1000)


def _fd(fun, x, steps):
    cols = []
    for i, h in enumerate(steps):
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        cols.append((fun(xp) - fun(xm)) / (2 * h))
    return np.stack(cols, axis=1)


def test_static_model_equals_geometry(campaign, centres, detector):
    alpha = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    uv = G.forward_srf(campaign.static_w, centres, alpha, detector)
    r = static_residuals(campaign.static_w, _full_obs(uv, alpha), centres, detector)
    assert np.max(np.abs(r)) < 1e-9


def test_static_jacobian_matches_finite_differences(campaign, centres, detector):
    alpha = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    terms = (EncoderEccentricity(), RadialDistortion())
    x = np.concatenate([campaign.static_w, [3e-4, -2e-4], [0.02]])
    obs = _full_obs(G.forward_srf(campaign.static_w, centres, alpha, detector), alpha)
    _, jac = static_residuals_jac(x, obs, centres, detector, terms)
    steps = np.where(np.isin(np.arange(x.size), [0, 1, 2, 3, 7, 8, 9]), 1e-7, 1e-6)
    jfd = _fd(lambda v: static_residuals(v, obs, centres, detector, terms), x, steps)
    # central differences: truncation O(h^2 f''') ~ 1e-8 relative here; 1e-6 leaves margin
    scale = np.max(np.abs(jfd), axis=0)
    assert np.all(np.max(np.abs(jac - jfd), axis=0) <= 1e-6 * scale)


def test_motion_model_equals_geometry_and_jacobian(campaign, centres, detector):
    alpha = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    geom = G.static_to_detector_frame(campaign.static_w, centres)
    m = campaign.motions[12]
    obs = _full_obs(G.forward_df(geom, m, alpha, detector), alpha)
    assert np.max(np.abs(motion_residuals(m, obs, geom, detector))) < 1e-9
    terms, tp = (RadialDistortion(),), [0.03]
    kern = MotionKernel(geom, obs, detector, terms, tp)
    _, jac = kern.residuals_jac(m)
    jfd = _fd(kern.residuals, m, [1e-7] * 3 + [1e-6] * 3)
    scale = np.max(np.abs(jfd), axis=0)
    assert np.all(np.max(np.abs(jac - jfd), axis=0) <= 1e-6 * scale)


def test_df_model_at_k1_equals_srf_model(campaign, centres, detector):
    alpha = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    geom = G.static_to_detector_frame(campaign.static_w, centres)
    a = G.forward_df(geom, np.zeros(6), alpha, detector)
    b = G.forward_srf(campaign.static_w, centres, alpha, detector)
    assert np.max(np.abs(a - b)) < 1e-9


def test_kernels_blocked_layout_matches_public_functions(campaign, centres, detector):
    """The solvers' fast path (blocked f = modelled - observed, lazy (n, 2Q) Jacobian) is the same
    model as the interleaved public functions (observed - modelled): only the row order and the
    sign differ (exact up to rounding)."""
    from ct_calib_nodes.core.ct_model import StaticKernel
    alpha = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    terms = (EncoderEccentricity(), RadialDistortion())
    x = np.concatenate([campaign.static_w, [3e-4, -2e-4], [0.02]])
    obs = _full_obs(G.forward_srf(campaign.static_w, centres, alpha, detector) + 0.3, alpha)
    r_i, j_i = static_residuals_jac(x, obs, centres, detector, terms)
    r_b, jac = StaticKernel(obs, centres, detector, terms).evaluate(x)
    q = obs.n_obs
    assert np.max(np.abs(r_b.reshape(2, q).T.ravel() + r_i)) < 1e-12
    k = jac()
    assert k.shape == (x.size, 2 * q) and k.flags.c_contiguous
    assert np.max(np.abs(k.reshape(-1, 2, q).transpose(2, 1, 0).reshape(2 * q, -1) + j_i)) < 1e-12 * np.max(np.abs(j_i))
    geom = G.static_to_detector_frame(campaign.static_w, centres)
    kern = MotionKernel(geom, obs, detector, (RadialDistortion(),), [0.03])
    m = campaign.motions[12]
    rm_i, jm_i = kern.residuals_jac(m)
    rm_b, jm = kern.evaluate(m)
    assert np.max(np.abs(rm_b.reshape(2, q).T.ravel() + rm_i)) < 1e-12
    assert np.max(np.abs(jm().reshape(6, 2, q).transpose(2, 1, 0).reshape(2 * q, 6) + jm_i)) < 1e-12 * np.max(np.abs(jm_i))
