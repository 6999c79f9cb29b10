"""Thermal expansion of the reference object, and the projection model against a hand derivation."""

import numpy as np
import pytest

from ct_calib_nodes.core import geometry as G
from ct_calib_nodes.core.ct_model import static_predict
from ct_calib_nodes.core.observations import CentreObservations
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.simulate_obs import simulate_observations
from ct_calib_nodes.core.static_solver import solve_static

from ct_core_settings import CONTOUR_RADIUS_M


def test_projection_onto_a_tilted_detector_by_hand():
    """Detector turned by theta = 30 deg about X only (R = Rx(30 deg)), its centre at D = (0, 0, 1 m);
    a point at P = (0.05, 0.1, 0.5) m from the source. By hand: normal n = (0, -sin t, cos t),
    n.P = -0.1 sin30 + 0.5 cos30 = 0.38301270; n.D = cos30 = 0.86602540; the ray hits at
    t P with t = 0.86602540 / 0.38301270 = 2.26108795, H = (0.11305440, 0.22610879, 1.13054397);
    H - D = (0.11305440, 0.22610879, 0.13054397). In-plane axes u = (1, 0, 0),
    v = (0, cos t, sin t): u = 0.11305440 m, v = 0.22610879 cos30 + 0.13054397 sin30 =
    0.19581596 + 0.06527199 = 0.26108795 m. With 1 mm pixels on 1001 x 1001 (centre 500, 500):
    col = 500 + 113.05440, row = 500 - 261.08795."""
    det = G.DetectorSpec(1001, 1001, 0.001)
    w = np.zeros(13)
    w[0] = 0.5                      # z_R (the object pose below places the point directly)
    w[3] = 1.0                      # z_D
    w[4] = np.radians(30.0)         # theta
    w[7:10] = [0.05, 0.1, 0.5]      # object origin = the point, at alpha = 0
    expect = np.array([500.0 + 113.05440, 500.0 - 261.08795])
    uv = G.project_srf(w, np.array([0.05, 0.1, 0.5]), det)
    assert uv == pytest.approx(expect, abs=2e-5)
    obs = CentreObservations(np.zeros((1, 2)), [0], [0.0], [0])
    model, _ = static_predict(w, obs, np.zeros((1, 3)), det)
    assert model[0] == pytest.approx(expect, abs=2e-5)
    geom = G.static_to_detector_frame(w, np.zeros((1, 3)))
    assert G.forward_df(geom, np.zeros(6), [0.0], det)[0, 0] == pytest.approx(expect, abs=2e-5)


def test_ellipse_centre_closed_form_equals_the_general_conic():
    """The solvers' E - P = (1 + (b/D)^2)(C - P) against the general cone-section conic
    (geometry.silhouette_ellipses) on a tilted detector, far off axis."""
    det = G.DetectorSpec(2000, 2000, 0.0002)
    w = np.array([0.3, 0.004, -0.003, 1.1, np.radians(0.6), np.radians(-0.5), np.radians(0.3),
                  0.0, 0.0, 0.3, 0.0, 0.0, 0.0])
    geom = G.static_to_detector_frame(w, np.zeros((1, 3)))
    pts = np.array([[0.05, 0.06, 0.2], [-0.04, 0.0, 0.25], [0.0, -0.07, 0.3]]) + geom.source_df_m
    radius = 0.002
    ell, axes = G.silhouette_ellipses(geom.source_df_m, pts, np.full(3, radius))
    s = geom.source_df_m
    c = s[:2] + (pts[:, :2] - s[:2]) * (-s[2] / (pts[:, 2] - s[2]))[:, None]    # centre projections [m]
    closed = s[:2] + (1.0 + (axes[:, 1] / -s[2]) ** 2)[:, None] * (c - s[:2])
    shift = np.linalg.norm(ell - c, axis=1) / det.pixel_pitch_m
    assert np.all(shift > 0.02)                                       # a real effect here
    assert np.max(np.abs(closed - ell)) / det.pixel_pitch_m < 1e-9


def test_thermal_expansion_applied_and_reported(campaign, detector):
    """A CFRP frame (2e-6 /K) scanned 5 K above its calibration: the centres are 1e-5 larger.
    A uniform scale s of the object is exactly equivalent to moving it (z_R and the object
    origin) by s along the rays: the residuals cannot show it, so solved with the calibrated
    (cold) centres z_R comes out short by (s - 1) z_R = 3.65 um, z_D unchanged, same residuals.
    With the expansion applied the estimate is the truth's within its uncertainty."""
    ref = helix49()
    ref = type(ref)(name=ref.name, ids=ref.ids, centres_of_m=ref.centres_of_m, diameters_m=ref.diameters_m,
                    temperature_K=293.15, thermal_expansion_per_K=2e-6)
    warm, note = ref.at_temperature(298.15)
    assert "applied" in note and "+5.00 K" in note
    alphas = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    sim = simulate_observations(campaign.static_w, warm.centres_of_m, detector, alphas, np.random.default_rng(5),
                                0.02, contour_radius_m=CONTOUR_RADIUS_M, report_sigma=True)
    args = (detector, campaign.srd_reported_m[0], campaign.sdd_reported_m)
    cold = solve_static(sim.obs, ref.centres_of_m, *args)
    hot = solve_static(sim.obs, warm.centres_of_m, *args)
    scale = 1e-5
    print(f"\nz_R cold - warm {1e6 * (cold.x[0] - hot.x[0]):.3f} um (expected {-1e6 * scale * hot.x[0]:.3f}); "
          f"rms {cold.rms_px:.6f} / {hot.rms_px:.6f} px")
    assert cold.x[0] - hot.x[0] == pytest.approx(-scale * hot.x[0], rel=0.02)
    assert abs(cold.x[3] - hot.x[3]) < 0.02 * scale * hot.x[3]
    assert cold.rms_px == pytest.approx(hot.rms_px, rel=1e-6)            # invisible in the residuals
    assert np.all(np.abs(hot.x - campaign.static_w) < 4.5 * hot.std)
    # missing keys are said, never silently ignored
    bare = type(ref)(name="x", ids=ref.ids, centres_of_m=ref.centres_of_m, diameters_m=ref.diameters_m)
    same, why = bare.at_temperature(298.15)
    assert same is bare and "NOT applied" in why and "temperature" in why and "thermal_expansion" in why
    assert "no object temperature" in ref.at_temperature(None)[1]
