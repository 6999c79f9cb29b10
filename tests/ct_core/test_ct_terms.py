"""Optional model terms: encoder eccentricity is recovered when enabled, and
leaving it out gives a measurably worse fit."""

import numpy as np

from ct_calib_nodes.core.ct_model import static_residuals_jac

from ct_calib_nodes.core.simulate_obs import simulate_observations
from ct_calib_nodes.core.static_solver import solve_static
from ct_calib_nodes.core.terms import EncoderEccentricity

from ct_core_settings import SIGMA_PX

ECC = np.array([6e-4, -4e-4])   # [rad], about 2 and 1.4 arcmin: 0.1-0.2 px at the object radius


def test_encoder_eccentricity_recovered(campaign, centres, detector, alphas):
    rng = np.random.default_rng(5)
    term = EncoderEccentricity()
    sim = simulate_observations(campaign.static_w, centres, detector, alphas[::2], rng, SIGMA_PX,
                                terms=(term,), term_params=ECC)
    args = (sim.obs, centres, detector, campaign.srd_reported_m[0], campaign.sdd_reported_m)
    with_t = solve_static(*args, terms=(term,))
    without = solve_static(*args)
    assert with_t.success, with_t.message
    assert with_t.names[-2:] == ("ecc_a", "ecc_b") and with_t.units[-2:] == ("rad", "rad")
    truth = np.concatenate([campaign.static_w, ECC])
    _, jac = static_residuals_jac(with_t.x, sim.obs, centres, detector, (term,))
    crlb_sd = np.sqrt(np.diag(SIGMA_PX ** 2 * np.linalg.inv(jac.T @ jac)))
    # 4.5 sqrt(CRLB) as in test_ct_static (linear regime at 0.05 px)
    assert np.all(np.abs(with_t.x - truth) <= 4.5 * crlb_sd)
    # with the term the residual variance matches the noise (chi-square band, 5 sd)
    dof = 2 * with_t.n_obs - with_t.x.size
    assert abs(with_t.variance_factor / SIGMA_PX ** 2 - 1) < 5 * np.sqrt(2 / dof)
    # without it the unmodelled eccentricity shows up in the residuals
    print("\nrms with term %.4f px, without %.4f px" % (with_t.rms_px, without.rms_px))
    assert without.variance_factor / SIGMA_PX ** 2 - 1 > 20 * np.sqrt(2 / dof)
