"""Shared truth and simulated data for the CT core solver tests.

Truth: scenario.default_campaign() (misaligned instrument, paper-like error
motions). Reference object: the shipped helix49 (phantom.helix49, the package's
reference_object.yaml). Detector: 1024 x 1024 px, 0.4 mm pitch (INTERFACES.md).
Pixel noise: 0.05 px, the detection target. Observations are silhouette-ellipse
centres of a contour of CONTOUR_RADIUS_M about each sphere centre, with their
semi-minor axes, as the detector reports them.
"""

import numpy as np
import pytest

from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.scenario import default_campaign
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.simulate_obs import simulate_observations
from ct_calib_nodes.core.static_solver import solve_static

from ct_core_settings import CONTOUR_RADIUS_M, N_VIEWS, SIGMA_PX  # noqa: F401 (re-exported for fixtures)


@pytest.fixture(scope="session")
def detector():
    return DetectorSpec(cols=1024, rows=1024, pixel_pitch_m=0.0004)


@pytest.fixture(scope="session")
def centres():
    return helix49().centres_of_m


@pytest.fixture(scope="session")
def campaign():
    return default_campaign()


@pytest.fixture(scope="session")
def alphas():
    return np.linspace(0.0, 2 * np.pi, N_VIEWS, endpoint=False)


@pytest.fixture(scope="session")
def sim_k1(campaign, centres, detector, alphas):
    return simulate_observations(campaign.static_w, centres, detector, alphas,
                                 np.random.default_rng(20240611), SIGMA_PX, contour_radius_m=CONTOUR_RADIUS_M)


@pytest.fixture(scope="session")
def static_k1(sim_k1, campaign, centres, detector):
    return solve_static(sim_k1.obs, centres, detector, campaign.srd_reported_m[0], campaign.sdd_reported_m)
