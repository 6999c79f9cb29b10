"""Each hidden-physics switch moves the truth (and the image) by the expected amount."""

import numpy as np
import pytest

from ct_calib_nodes.core.render import RenderSettings, frame_truth, render_projection

R_M = 0.0375   # sphere radius from the axis, like helix49
CLEAN = dict(poisson=False, blur_sigma_px=0.7)


def _centroid_of(fr, centre, half):
    c, r = int(round(centre[0])), int(round(centre[1]))
    p = -np.log(fr.image[r - half:r + half + 1, c - half:c + half + 1].astype(np.float64))
    rows, cols = np.mgrid[r - half:r + half + 1, c - half:c + half + 1]
    return np.array([(p * cols).sum(), (p * rows).sum()]) / p.sum()


def test_switches_are_off_by_default():
    s = RenderSettings()
    assert s.encoder_eccentricity_rad == 0.0
    assert s.detector_distortion_k1_per_m2 == 0.0
    assert s.focal_spot_drift_m_per_s == (0.0, 0.0, 0.0)
    assert s.ellipse_centre_bias is True          # physics, on by default (the solvers model it)


@pytest.mark.parametrize("alpha", [0.0, 1.0, 2.5])
def test_encoder_eccentricity_shifts_by_r_m_a_sin(alpha, render_ideal_w, render_one_sphere, render_detector):
    """alpha_true = alpha + A sin(alpha + phi) moves the image by d col/d alpha * A sin(alpha + phi).

    For the sphere at radius R on +Z of {OF}, col = SDD R sin(a) / (SRD + R cos(a)),
    d col / d a = SDD R (SRD cos a + R) / (SRD + R cos a)^2, which at alpha = 0
    is R M with M = SDD / (SRD + R): the shift is R M A sin(phi).
    """
    w = render_ideal_w()
    det = render_detector
    ref = render_one_sphere([0.0, 0.0, R_M])       # on +Z of {OF}: behind the axis at alpha = 0
    amp, phase = 1e-3, 1.1
    on = RenderSettings(encoder_eccentricity_rad=amp, encoder_phase_rad=phase, **CLEAN)
    t0 = frame_truth(w, np.zeros(6), alpha, ref, det)
    t1 = frame_truth(w, np.zeros(6), alpha, ref, det, on)
    assert t1.alpha_true_rad == pytest.approx(alpha + amp * np.sin(alpha + phase), abs=1e-15)
    srd, sdd = w[0], w[3]
    dcol = sdd * R_M * (srd * np.cos(alpha) + R_M) / (srd + R_M * np.cos(alpha)) ** 2
    expected = dcol * amp * np.sin(alpha + phase) / det.pixel_pitch_m     # up to 0.22 px
    # first order in A: the neglected second-order term ~ R M A^2 / pitch
    # = 0.0375 * 2.6 * 1e-6 / 4e-4 = 2.4e-4 px; bound 1e-3 px
    assert t1.centre_px[0, 0] - t0.centre_px[0, 0] == pytest.approx(expected, abs=1e-3)
    assert abs(t1.centre_px[0, 1] - t0.centre_px[0, 1]) < 1e-6
    # the rendered shadow moves with it: noise-free centroid difference, the
    # shape change over 0.2 px is negligible; bound 0.01 px
    f0 = render_projection(w, np.zeros(6), alpha, ref, det, RenderSettings(**CLEAN), output="transmission")
    f1 = render_projection(w, np.zeros(6), alpha, ref, det, on, output="transmission")
    d = _centroid_of(f1, t0.centre_px[0], 16) - _centroid_of(f0, t0.centre_px[0], 16)
    assert d[0] == pytest.approx(t1.centre_px[0, 0] - t0.centre_px[0, 0], abs=0.01)


def test_eccentricity_is_periodic_in_alpha(render_ideal_w, render_one_sphere, render_detector):
    on = RenderSettings(encoder_eccentricity_rad=2e-4, encoder_phase_rad=0.3)
    ref = render_one_sphere([0.0, 0.01, R_M])
    a = 0.7
    t_a = frame_truth(render_ideal_w(), np.zeros(6), a, ref, render_detector, on)
    t_b = frame_truth(render_ideal_w(), np.zeros(6), a + 2 * np.pi, ref, render_detector, on)
    np.testing.assert_allclose(t_a.centre_px, t_b.centre_px, atol=1e-9)


def test_focal_spot_drift_moves_projection_by_one_minus_m(render_ideal_w, render_one_sphere, render_detector):
    """A source shift dS (in the detector plane) moves a point's image by dS (1 - M) exactly."""
    w = render_ideal_w()
    det = render_detector
    ref = render_one_sphere([0.01, 0.02, 0.0])
    drift = (2e-6, -1e-6, 0.0)       # m/s
    t = 30.0                          # s -> 60 um, -30 um
    on = RenderSettings(focal_spot_drift_m_per_s=drift, **CLEAN)
    t0 = frame_truth(w, np.zeros(6), 0.0, ref, det, time_s=t)
    t1 = frame_truth(w, np.zeros(6), 0.0, ref, det, on, time_s=t)
    np.testing.assert_allclose(t1.source_df_m - t0.source_df_m, np.array(drift) * t, atol=1e-15)
    mag = w[3] / w[0]                 # sphere at the axis depth
    dx, dy = drift[0] * t * (1 - mag), drift[1] * t * (1 - mag)
    expected = np.array([dx, -dy]) / det.pixel_pitch_m        # rows grow along -Y
    # exact (linear in dS when dS_z = 0): float64 only
    np.testing.assert_allclose(t1.centre_px[0] - t0.centre_px[0], expected, atol=1e-9)
    # no drift at t = 0
    np.testing.assert_allclose(frame_truth(w, np.zeros(6), 0.0, ref, det, on).centre_px, t0.centre_px, atol=0)
    f0 = render_projection(w, np.zeros(6), 0.0, ref, det, RenderSettings(**CLEAN), time_s=t, output="transmission")
    f1 = render_projection(w, np.zeros(6), 0.0, ref, det, on, time_s=t, output="transmission")
    d = _centroid_of(f1, t0.centre_px[0], 16) - _centroid_of(f0, t0.centre_px[0], 16)
    np.testing.assert_allclose(d, expected, atol=0.01)


def test_detector_distortion_moves_recorded_position(render_ideal_w, render_one_sphere, render_detector):
    """x_rec = x (1 + k1 |x|^2): truth and image both move radially by k1 |x|^2 x."""
    w = render_ideal_w()
    det = render_detector
    ref = render_one_sphere([0.045, 0.04, 0.0])       # lands ~(130, 115) mm from the centre
    k1 = 0.15               # 1/m^2: k1 |x|^3 = 0.15 * 0.174^3 m = 0.79 mm = 2.0 px radial shift
    on = RenderSettings(detector_distortion_k1_per_m2=k1, **CLEAN)
    t0 = frame_truth(w, np.zeros(6), 0.0, ref, det)
    t1 = frame_truth(w, np.zeros(6), 0.0, ref, det, on)
    u, v = det.metric_from_pixels(*t0.centre_px[0])
    r2 = u * u + v * v
    expected = np.array([k1 * r2 * u, -k1 * r2 * v]) / det.pixel_pitch_m
    np.testing.assert_allclose(t1.centre_px[0] - t0.centre_px[0], expected, atol=1e-9)
    assert np.linalg.norm(expected) > 1.5
    f0 = render_projection(w, np.zeros(6), 0.0, ref, det, RenderSettings(**CLEAN), output="transmission")
    f1 = render_projection(w, np.zeros(6), 0.0, ref, det, on, output="transmission")
    d = _centroid_of(f1, t1.centre_px[0], 16) - _centroid_of(f0, t0.centre_px[0], 16)
    # the warp also stretches the 11 px shadow by up to k1 * 3 |x|^2 = 1.4 %, shifting
    # its centroid by a second-order amount ~ k1 r_shadow^2 |x| / pitch = 0.15 * (4.4 mm)^2 * 0.174 / 0.4 mm = 0.001 px; bound 0.02 px
    np.testing.assert_allclose(d, expected, atol=0.02)


def test_motion_carries_truth(render_ideal_w, render_one_sphere, render_detector):
    """A stage displacement dx_R in {DF} moves the image of a point by dx M / pitch."""
    w = render_ideal_w()
    ref = render_one_sphere([0.0, 0.0, 0.0])
    m = np.array([50e-6, 0.0, 0.0, 0.0, 0.0, 0.0])
    t0 = frame_truth(w, np.zeros(6), 0.0, ref, render_detector)
    t1 = frame_truth(w, m, 0.0, ref, render_detector)
    assert t1.centre_px[0, 0] - t0.centre_px[0, 0] == pytest.approx(50e-6 * w[3] / w[0] / 4e-4, rel=1e-9)
    np.testing.assert_array_equal(t1.motion, m)
