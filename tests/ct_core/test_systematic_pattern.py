"""A systematic error pattern shared by every observation (CentreObservations.systematic_px).

The detector applies half the blur correction of the frame-wide background gradient and reports
the rest as one pattern at one standard deviation: the same unknown factor scales it in every
frame of the recording, so it does not average out and the solvers propagate it as a fully
correlated input. Checked here on simulated observations against the definition: the reported
shift of the solution is what a solve of the observations moved by the pattern gives (static, and
an error motion, directly and through the static geometry), its outer product is what the
covariance gains, and the error map's joint covariance carries it across positions.
"""

import dataclasses

import numpy as np

from ct_calib_nodes.core.ct_pipeline import CampaignAccumulator, campaign_error_map
from ct_calib_nodes.core.error_map import COMPONENT_FIELDS, error_map
from ct_calib_nodes.core.error_motion import solve_error_motion
from ct_calib_nodes.core.simulate_obs import simulate_observations
from ct_calib_nodes.core.static_solver import solve_static

from ct_core_settings import CONTOUR_RADIUS_M

SIGMA = 0.01        # detection noise [px]


def _pattern(obs, cols=1024, rows=1024):
    """A heel-like pattern: 0.004 px along a direction, a radial part of 3e-6 px per px and a
    quadratic one (1e-8 px per px^2). The constant and the radial part move the static geometry
    alone (a pattern fixed to the detector is common to every position, and the error motions are
    relative to the first): the quadratic part also moves the motions, by 0.1-0.2 of their sd."""
    d = obs.uv_px - np.array([(cols - 1) / 2, (rows - 1) / 2])
    return (0.004 * np.array([np.cos(0.7), np.sin(0.7)]) + 3e-6 * d
            + 1e-8 * d * np.linalg.norm(d, axis=1)[:, None])


def test_static_and_motion_shift_and_covariance(centres, detector, campaign, alphas):
    rng = np.random.default_rng(5)
    k = 3
    sims = [simulate_observations(campaign.static_w, centres, detector, alphas, rng, SIGMA,
                                  motion=campaign.motions[j], contour_radius_m=CONTOUR_RADIUS_M,
                                  report_sigma=True).obs for j in (0, k)]
    marked = [dataclasses.replace(o, systematic_px=_pattern(o)) for o in sims]
    moved = [dataclasses.replace(o, uv_px=o.uv_px + _pattern(o)) for o in sims]
    srd = campaign.srd_reported_m
    kw = dict(location_classes=False)
    st0 = solve_static(sims[0], centres, detector, srd[0], campaign.sdd_reported_m, **kw)
    st = solve_static(marked[0], centres, detector, srd[0], campaign.sdd_reported_m, **kw)
    st_mv = solve_static(moved[0], centres, detector, srd[0], campaign.sdd_reported_m, x0=st0.x, **kw)
    assert st0.success and st.success and st_mv.success
    d = st.systematic_sensitivity
    assert st0.systematic_sensitivity is None and d is not None
    # the pattern does not enter the fit
    np.testing.assert_array_equal(st.x, st0.x)
    # linear response = the solve of the moved observations (its noise model differs by the
    # pattern's small change of the residuals: 2 % of the largest shift, 0.02 sd)
    np.testing.assert_allclose(d[:7], (st_mv.x - st0.x)[:7], atol=0.02 * np.max(np.abs(d[:7])) + 0.02 * st0.std[:7].min())
    assert np.max(np.abs(d[:7]) / st0.std[:7]) > 0.3          # the pattern matters at this size
    np.testing.assert_allclose(st.covariance - st0.covariance, np.outer(d, d), rtol=1e-7,
                               atol=1e-9 * np.max(np.abs(st0.covariance)))
    assert st.to_dict()["std_systematic"] == list(np.abs(d))

    # error motion of position k: directly, and through the static geometry the pattern moved
    m0 = solve_error_motion(sims[1], st0, detector, srd[k], srd[0])
    m = solve_error_motion(marked[1], st, detector, srd[k], srd[0])
    m_mv = solve_error_motion(moved[1], st_mv, detector, srd[k], srd[0], x0=m0.x)
    assert m0.success and m.success and m_mv.success
    assert m0.systematic_shift is None and m.systematic_shift is not None
    np.testing.assert_allclose(m.systematic_shift, m_mv.x - m0.x, atol=0.02 * np.max(np.abs(m.systematic_shift))
                               + 0.02 * m0.std.min())
    assert np.max(np.abs(m.systematic_shift) / m0.std_total) > 0.05
    np.testing.assert_allclose(m.covariance, m0.covariance, rtol=1e-9)         # conditional: unchanged
    # (the static sensitivity's difference step is 0.1 static sd, which the pattern widens: 1e-6)
    np.testing.assert_allclose(m.covariance_total - m0.covariance_total,
                               np.outer(m.systematic_shift, m.systematic_shift), rtol=0,
                               atol=1e-6 * np.max(np.abs(m0.covariance_total)))


def test_error_map_carries_the_pattern_across_positions(centres, detector, campaign, alphas):
    """The map's joint covariance gains exactly e e^T, e the change of the map when every position's
    motion moves by its reported shift (0 at k = 0, the reference)."""
    rng = np.random.default_rng(9)
    srd = campaign.srd_reported_m
    accs = {True: CampaignAccumulator(), False: CampaignAccumulator()}
    for j in range(4):
        o = simulate_observations(campaign.static_w, centres, detector, alphas, rng, SIGMA,
                                  motion=campaign.motions[j], contour_radius_m=CONTOUR_RADIUS_M,
                                  report_sigma=True).obs
        s = _pattern(o)
        for v in range(o.n_views):
            sel = o.view_index == v
            stamp = (j * 1000 + v) * 10**8
            for with_sys, acc in accs.items():
                acc.add_frame(stamp, float(o.alpha_rad[sel][0]), srd[j], o.sphere_index[sel], o.uv_px[sel],
                              o.sigma_px[sel], 0, o.minor_axis_px[sel], s[sel] if with_sys else None)
    maps, motions, shifts = {}, None, None
    for with_sys, acc in accs.items():
        st = solve_static(acc.positions[0].observations(), centres, detector, srd[0], campaign.sdd_reported_m,
                          location_classes=False)
        assert (st.systematic_sensitivity is not None) == with_sys
        res = {k: solve_error_motion(acc.positions[k].observations(), st, detector, srd[k], srd[0])
               for k in range(1, 4)}
        maps[with_sys], ks = campaign_error_map(acc, res, st)
        assert ks == [0, 1, 2, 3]
        if with_sys:
            motions = np.array([np.zeros(6)] + [res[k].x for k in ks[1:]])
            shifts = np.array([np.zeros(6)] + [res[k].systematic_shift for k in ks[1:]])
    for f in COMPONENT_FIELDS:
        np.testing.assert_array_equal(getattr(maps[True], f), getattr(maps[False], f))
    srd4 = maps[True].srd_reported_m
    base, moved = error_map(srd4, motions), error_map(srd4, motions + shifts)
    e = np.stack([getattr(moved, f) - getattr(base, f) for f in COMPONENT_FIELDS], axis=1).reshape(-1)
    gained = maps[True].covariance - maps[False].covariance
    assert np.max(np.abs(e)) > 0
    np.testing.assert_allclose(gained, np.outer(e, e), rtol=0, atol=1e-3 * np.max(np.abs(np.outer(e, e))))
