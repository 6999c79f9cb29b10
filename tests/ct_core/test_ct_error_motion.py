"""Per-position error motions (section 3.3) and the error map against the scenario truth."""

import json

import numpy as np
import pytest

from ct_calib_nodes.core.error_map import error_map, joint_motion_covariance
from ct_calib_nodes.core.error_motion import solve_error_motion
from ct_calib_nodes.core.simulate_obs import simulate_observations

from ct_core_settings import CONTOUR_RADIUS_M, SIGMA_PX

# Same argument as the static tests: estimates ~ Normal(truth, cov) in the
# linear regime; 4.5 sd per component (6 components x 19 positions x 2 modes:
# family-wise false-failure probability < 2e-3).
K_SIGMA = 4.5


@pytest.fixture(scope="module")
def campaign_solution(campaign, centres, detector, alphas, static_k1):
    rng = np.random.default_rng(31)
    multi, single = [], []
    for k in range(len(campaign.srd_reported_m)):
        sim = simulate_observations(campaign.static_w, centres, detector, alphas, rng, SIGMA_PX,
                                    motion=campaign.motions[k], contour_radius_m=CONTOUR_RADIUS_M)
        args = (sim.obs, static_k1, detector, campaign.srd_reported_m[k], campaign.srd_reported_m[0])
        multi.append(solve_error_motion(*args, mode="multi"))
        single.append(solve_error_motion(*args, mode="single"))
    return multi, single


def test_multi_recovers_motions(campaign_solution, campaign):
    multi, _ = campaign_solution
    for k, r in enumerate(multi):
        assert r.success, (k, r.message)
        # total covariance: the static geometry's error is part of the error
        z = (r.x - campaign.motions[k]) / r.std_total
        assert np.all(np.abs(z) <= K_SIGMA), (k, z)
        # the residual variance matches the pixel noise (chi-square, 5 sd)
        dof = 2 * r.n_obs - 6
        assert abs(r.variance_factor / SIGMA_PX ** 2 - 1) < 5 * np.sqrt(2 / dof)
    json.dumps(multi[3].to_dict())


def test_single_projection_agrees_with_multi(campaign_solution, campaign):
    multi, single = campaign_solution
    for k, (m, s) in enumerate(zip(multi, single)):
        assert s.success, (k, s.message)
        assert s.n_views == 1 and s.mode == "single"
        # single uses a subset of multi's data and the same static geometry, so
        # Var(single - multi) = Var(single) - Var(multi) <= Var(single), conditional.
        assert np.all(np.abs(s.x - m.x) <= K_SIGMA * s.std), k
        # and it is honest about being less precise
        assert np.all(s.std >= m.std)
        z = (s.x - campaign.motions[k]) / s.std_total
        assert np.all(np.abs(z) <= K_SIGMA), (k, z)


def test_error_map_matches_truth(campaign_solution, campaign, static_k1):
    """Both definitions against the truth built from the stage model (scenario.py, no error_map call)."""
    multi, single = campaign_solution
    for definition in ("travel", "detector"):
        truth = campaign.error_map(definition)
        for results in (multi, single):
            joint = joint_motion_covariance(np.array([r.covariance for r in results]),
                                            np.array([r.static_sensitivity for r in results]), static_k1.covariance)
            em = error_map(campaign.srd_reported_m, np.array([r.x for r in results]), joint, definition=definition)
            est, unc = em.as_truth_dict(), em.uncertainty_dict()
            for key in truth:
                z = (est[key] - truth[key]) / np.where(unc[key] > 0, unc[key], np.inf)
                scale, unit = (1e6, "um") if key.endswith("_m") else (206264.80624709636, "arcsec")
                print(f"{definition:8s} {results[0].mode:6s} {key:18s} "
                      f"max|err| {np.max(np.abs(est[key] - truth[key])) * scale:8.3f} "
                      f"median u {np.median(unc[key][1:]) * scale:8.3f} {unit:6s} max|z| {np.max(np.abs(z)):.2f}")
                assert np.all(np.abs(z) <= K_SIGMA), (definition, results[0].mode, key, np.round(z, 2))
            # the fitted travel direction is the stage's (the truth's) within its uncertainty
            dang = np.arccos(min(1.0, float(em.travel_direction_df @ campaign.travel_direction_df)))
            assert dang <= K_SIGMA * em.u_angle_travel_normal_rad + 1e-9
            assert abs(em.angle_travel_normal_rad - campaign.angle_travel_normal_rad) <= \
                K_SIGMA * em.u_angle_travel_normal_rad
            assert np.allclose(em.pitch_arcsec, em.pitch_rad * 206264.80624709636)
            json.dumps(em.to_dict())
    # the two positioning definitions differ by the cosine error (~27 um at the far end here)
    t = campaign.error_map("travel")["positioning_m"] - campaign.error_map("detector")["positioning_m"]
    assert abs(t[-1]) > 20e-6
    # the joint treatment matters: independent positions overstate straightness uncertainty
    naive = error_map(campaign.srd_reported_m, np.array([r.x for r in multi]),
                      np.array([r.covariance_total for r in multi]))
    joint = joint_motion_covariance(np.array([r.covariance for r in multi]),
                                    np.array([r.static_sensitivity for r in multi]), static_k1.covariance)
    em = error_map(campaign.srd_reported_m, np.array([r.x for r in multi]), joint)
    assert np.median(naive.u_straightness_x_m[1:] / em.u_straightness_x_m[1:]) > 1.0


def test_error_map_uncertainty_linear_algebra():
    """Straightness of a pure line is zero; uncertainties follow (I - H) C (I - H)^T."""
    srd = 0.364 + 0.02 * np.arange(5)
    m = np.zeros((5, 6))
    m[:, 0] = 2e-3 * (srd - srd[0])
    m[:, 2] = (srd - srd[0]) + 1e-5
    m[0] = 0.0
    cov = np.tile(np.eye(6) * 1e-12, (5, 1, 1))
    cov[0] = 0.0
    em = error_map(srd, m, cov, definition="detector")
    assert np.allclose(em.straightness_x_m[1:], 0, atol=1e-9)
    assert np.allclose(em.positioning_m[1:], -1e-5)        # travelled MORE than indexed: negative
    a = np.stack([np.ones(5), srd - srd[0]], axis=1)
    r = np.eye(5) - a @ np.linalg.pinv(a)
    c = np.diag([0.0] + [1e-12] * 4)
    assert np.allclose(em.u_straightness_x_m, np.sqrt(np.diag(r @ c @ r.T)), rtol=1e-5)
    assert np.allclose(em.u_positioning_m[1:], 1e-6, rtol=1e-6)
    with pytest.raises(ValueError, match="motions"):
        error_map(srd, m[:, :5])
    with pytest.raises(ValueError, match="definition"):
        error_map(srd, m, definition="iso")


def test_single_projection_with_too_few_points(sim_k1, static_k1, detector, campaign):
    obs = sim_k1.obs.first_view()
    few = obs.select(np.arange(obs.n_obs) < 3)
    r = solve_error_motion(few, static_k1, detector, campaign.srd_reported_m[0], campaign.srd_reported_m[0],
                           mode="single")
    assert not r.success and "too few spheres" in r.message
    assert np.all(np.isnan(r.covariance))


def test_rejects_failed_static(sim_k1, static_k1, detector, campaign):
    import dataclasses
    bad = dataclasses.replace(static_k1, success=False, message="x")
    with pytest.raises(ValueError, match="static solution"):
        solve_error_motion(sim_k1.obs, bad, detector, 0.364, 0.364)
    with pytest.raises(ValueError, match="mode"):
        solve_error_motion(sim_k1.obs, static_k1, detector, 0.364, 0.364, mode="both")


def test_campaign_residuals_follow_the_noise(campaign_solution, campaign, centres, detector, alphas, static_k1):
    """The report's residuals (every position against its model) have the pixel noise's RMS when
    the solved motions are used, and reveal a position whose motion is wrong by 50 um."""
    from ct_calib_nodes.core.ct_pipeline import CampaignAccumulator, campaign_residuals

    multi, _ = campaign_solution
    rng = np.random.default_rng(77)
    acc = CampaignAccumulator()
    for k in range(3):
        sim = simulate_observations(campaign.static_w, centres, detector, alphas, rng, SIGMA_PX,
                                    motion=campaign.motions[k], contour_radius_m=CONTOUR_RADIUS_M)
        o = sim.obs
        for v in np.unique(o.view_index):
            sel = o.view_index == v
            acc.add_frame(int(o.stamp_ns[sel][0]) + k * 10**12, float(o.alpha_rad[sel][0]),
                          campaign.srd_reported_m[k], o.sphere_index[sel], o.uv_px[sel])
    assert len(acc.positions) == 3
    motions = {k: multi[k].x for k in (1, 2)}
    res = campaign_residuals(acc, static_k1.x, centres, detector, motions)
    n = res.residuals_px.size
    assert set(np.unique(res.stage_index)) == {0, 1, 2}
    # RMS per coordinate ~ sigma (chi-square with n dof: relative sd sqrt(1/(2n)); 5 sd band)
    rms = np.sqrt(np.mean(res.residuals_px ** 2))
    assert abs(rms / SIGMA_PX - 1) < 5 * np.sqrt(1 / (2 * n)) + 0.01
    bad = dict(motions)
    bad[2] = motions[2] + np.array([50e-6, 0, 0, 0, 0, 0])     # ~0.36 px on the detector
    worse = campaign_residuals(acc, static_k1.x, centres, detector, bad)
    r2 = worse.residuals_px[worse.stage_index == 2]
    assert np.sqrt(np.mean(r2 ** 2)) > 3 * SIGMA_PX
    # positions without a motion are left out
    only0 = campaign_residuals(acc, static_k1.x, centres, detector, {})
    assert set(np.unique(only0.stage_index)) == {0}
