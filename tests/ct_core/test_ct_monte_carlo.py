"""Monte Carlo: the spread of the static estimates matches the reported covariance
and the Cramer-Rao bound (seeded)."""

import numpy as np

from ct_calib_nodes.core.ct_model import static_residuals_jac
from ct_calib_nodes.core.simulate_obs import simulate_observations
from ct_calib_nodes.core.static_solver import solve_static

from ct_core_settings import CONTOUR_RADIUS_M, SIGMA_PX

N_TRIALS = 60


def test_monte_carlo_zscores_and_efficiency(campaign, centres, detector, alphas):
    rng = np.random.default_rng(99)
    w = campaign.static_w
    a = alphas[::10]                                   # 36 projections keep the test fast
    est, zs, crlb = [], [], None
    for _ in range(N_TRIALS):
        sim = simulate_observations(w, centres, detector, a, rng, SIGMA_PX, contour_radius_m=CONTOUR_RADIUS_M)
        r = solve_static(sim.obs, centres, detector, campaign.srd_reported_m[0], campaign.sdd_reported_m)
        assert r.success, r.message
        est.append(r.x)
        zs.append((r.x - w) / r.std)                   # reported (residual-variance) covariance
        if crlb is None:                               # Cramer-Rao bound: sigma^2 (J^T J)^-1 at the truth
            _, jac = static_residuals_jac(w, sim.obs, centres, detector)
            crlb = SIGMA_PX ** 2 * np.linalg.inv(jac.T @ jac)
    est, zs = np.array(est), np.array(zs)
    z_sd = zs.std(axis=0, ddof=1)
    z_mean = zs.mean(axis=0)
    efficiency = np.diag(crlb) / est.var(axis=0, ddof=1)
    print("\nparam    z-mean  z-sd   CRLB/var(MC)")
    for n, m, s, e in zip(r.names, z_mean, z_sd, efficiency):
        print(f"{n:8s} {m: .2f}  {s:.2f}   {e:.2f}")
    # Sample sd of N Normal(0, 1) z-scores has sd 1/sqrt(2(N-1)) = 0.092 for
    # N = 60: a 4-sd band is [0.63, 1.37]. The mean has sd 1/sqrt(N) = 0.13:
    # 4-sd band |mean| < 0.52. 1 / efficiency is a ratio of VARIANCES, whose
    # relative sd is twice that of an sd, sqrt(2/(N-1)) = 0.18: 4-sd band 0.74.
    band = 4 / np.sqrt(2 * (N_TRIALS - 1))
    assert np.all(np.abs(z_sd - 1) < band)
    assert np.all(np.abs(z_mean) < 4 / np.sqrt(N_TRIALS))
    assert np.all(np.abs(1 / efficiency - 1) < 2 * band)
