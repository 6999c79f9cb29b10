"""Physics of the CT renderer checked against analytic truth.

Every tolerance below is derived in the comment next to it, from float
precision, the sub-pixel sampling, or the counting noise.
"""

import numpy as np
import pytest

from ct_calib_nodes.core import geometry
from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import CarbonTube, helix49
from ct_calib_nodes.core.render import (
    RenderSettings,
    frame_truth,
    render_projection,
    render_projection_bruteforce,
    silhouette_ellipses,
)
from ct_calib_nodes.core.scenario import default_static_truth

MU = 292.5  # steel [1/m]
CLEAN = dict(poisson=False, blur_sigma_px=0.0)


def _centroid(weight, c0=0, r0=0):
    rows, cols = np.mgrid[r0:r0 + weight.shape[0], c0:c0 + weight.shape[1]]
    s = weight.sum()
    return np.array([(weight * cols).sum() / s, (weight * rows).sum() / s])


def _patch(img, centre, half):
    c, r = int(round(centre[0])), int(round(centre[1]))
    return img[r - half:r + half + 1, c - half:c + half + 1], c - half, r - half


def test_axis_sphere_lands_at_detector_centre(render_ideal_w, render_one_sphere, render_small_detector):
    """Ideal geometry: a sphere on the axis at source height projects on the detector centre."""
    det = render_small_detector
    ref = render_one_sphere([0.0, 0.0, 0.0])
    for alpha in (0.0, 1.0, 4.0):
        fr = render_projection(render_ideal_w(), np.zeros(6), alpha, ref, det,
                               RenderSettings(oversample=1, **CLEAN), output="transmission")
        # exact arithmetic gives (50, 50); float64 rounding of ~1 m lengths: 1e-9 px
        np.testing.assert_allclose(fr.truth.centre_px[0], [50.0, 50.0], atol=1e-9)
        np.testing.assert_allclose(fr.truth.ellipse_centre_px[0], [50.0, 50.0], atol=1e-9)
        # the image's darkest pixel is that centre pixel
        assert np.unravel_index(np.argmin(fr.image), fr.image.shape) == (50, 50)


def test_central_ray_transmission_is_beer_lambert(render_ideal_w, render_one_sphere, render_small_detector):
    """The ray through the sphere centre crosses a full diameter: T = exp(-mu d)."""
    d = 0.003
    ref = render_one_sphere([0.0, 0.0, 0.0], diameter_m=d)
    fr = render_projection(render_ideal_w(), np.zeros(6), 0.3, ref, render_small_detector,
                           RenderSettings(oversample=1, mu_sphere_per_m=MU, **CLEAN), output="transmission")
    # oversample 1 samples the pixel centre only, which is on the central ray;
    # the chord is exact in float64, the image is float32: rel. 1e-6
    assert fr.image[50, 50] == pytest.approx(np.exp(-MU * d), rel=1e-6)
    # mono16: rounding to integer counts, +-0.5 count
    fr16 = render_projection(render_ideal_w(), np.zeros(6), 0.3, ref, render_small_detector,
                             RenderSettings(oversample=1, mu_sphere_per_m=MU, **CLEAN))
    assert fr16.image.dtype == np.uint16
    assert abs(float(fr16.image[50, 50]) - 50000 * np.exp(-MU * d)) <= 0.5
    assert fr16.image[0, 0] == 50000


def test_tube_central_ray_crosses_two_walls(render_ideal_w, render_one_sphere, render_small_detector):
    """The CFRP tube on the axis: the central ray crosses both walls normally."""
    tube = CarbonTube(outer_radius_m=0.036, inner_radius_m=0.035, height_m=0.11, mu_per_m=23.5)
    ref = render_one_sphere([0.0, 0.05, 0.0], tube=tube)   # sphere off the central pixel
    fr = render_projection(render_ideal_w(), np.zeros(6), 0.0, ref, render_small_detector,
                           RenderSettings(oversample=1, **CLEAN), output="transmission")
    # path = 2 (ro - ri) = 2 mm exactly; float32 image: rel 1e-6
    assert fr.image[50, 50] == pytest.approx(np.exp(-23.5 * 0.002), rel=1e-6)
    # and mu_tube_per_m = 0 switches it off
    off = render_projection(render_ideal_w(), np.zeros(6), 0.0, ref, render_small_detector,
                            RenderSettings(oversample=1, mu_tube_per_m=0.0, **CLEAN), output="transmission")
    assert off.image[50, 50] == 1.0


def test_integral_of_line_integrals_is_magnified_volume(render_ideal_w, render_one_sphere, render_detector):
    """Sum over the shadow of -log T times pixel area = mu V (SDD/Z)^2 / cos(theta).

    Change of variables from detector area to object volume along the rays
    (plane at depth z' maps with (SDD/z')^2, path length dz'/cos theta). For a
    small sphere at depth Z and ray angle theta the variation across the sphere
    contributes O((r/Z)^2) = 2e-5 relative.
    """
    det = render_detector
    w = render_ideal_w()
    srd, sdd = w[0], w[3]
    d = 0.003
    mu = 1.0   # weak absorber: -log(mean exp(-x)) >= mean(x) - x_max/2 * mean(x), rel. gap <= mu d / 2 = 1.5e-3
    for xy in ((0.0, 0.0), (0.04, 0.04)):
        ref = render_one_sphere([xy[0], xy[1], 0.0], diameter_m=d)
        fr = render_projection(w, np.zeros(6), 0.0, ref, det,
                               RenderSettings(oversample=8, mu_sphere_per_m=mu, **CLEAN), output="transmission")
        integral = -np.log(fr.image.astype(np.float64)).sum() * det.pixel_pitch_m ** 2
        theta = np.arctan(np.hypot(*xy) / srd)
        expected = mu * np.pi / 6 * d ** 3 * (sdd / srd) ** 2 / np.cos(theta)
        # tolerance 4e-3 = Jensen gap (1.5e-3) + midpoint-rule error of the
        # sqrt rim with 1/8 px sub-samples on an 11 px radius, ~1.5 (h/R)^1.5 = 2e-3,
        # + float32 rounding of T ~1 (6e-8 per px over ~400 px, < 1e-4)
        assert integral == pytest.approx(expected, rel=4e-3)
    # the off-axis obliquity factor 1/cos(theta) = 1.012 is resolved by this test
    assert 1.0 / np.cos(theta) - 1.0 > 3 * 4e-3


def test_poisson_variance_equals_mean(render_ideal_w, render_one_sphere):
    """Open-beam pixels: mean I0 and variance I0, both noise paths."""
    det = DetectorSpec(200, 200, 0.0004)
    ref = render_one_sphere([0.0, 0.3, 0.0])      # far outside the field of view
    n = det.cols * det.rows
    for i0, exact_below in ((50000.0, 1000.0), (50000.0, np.inf), (300.0, 1000.0)):
        rng = np.random.default_rng(12345)
        fr = render_projection(render_ideal_w(), np.zeros(6), 0.0, ref, det,
                               RenderSettings(flat_field_counts=i0, poisson_exact_below=exact_below),
                               rng)
        v = fr.image.astype(np.float64)
        # sample mean: standard error sqrt(I0 / n); 5 sigma
        assert abs(v.mean() - i0) < 5 * np.sqrt(i0 / n)
        # sample variance: relative standard error sqrt(2 / (n - 1)) = 0.71 %; 5 sigma
        assert v.var(ddof=1) == pytest.approx(i0, rel=5 * np.sqrt(2.0 / (n - 1)))
        # noise is white (blur acts on the expected signal): lag-1 correlation
        # has standard error 1/sqrt(n) = 0.005; 5 sigma
        z = v - v.mean()
        rho = (z[:, 1:] * z[:, :-1]).mean() / z.var()
        assert abs(rho) < 5 / np.sqrt(n)


def test_noise_needs_rng(render_ideal_w, render_one_sphere, render_small_detector):
    with pytest.raises(ValueError, match="rng"):
        render_projection(render_ideal_w(), np.zeros(6), 0.0, render_one_sphere([0, 0, 0]),
                          render_small_detector, RenderSettings(poisson=True), None)


def test_tilted_detector_truth_matches_srf_model(render_detector):
    """Truth centres equal the paper's {SRF} model (App. A), computed the other way round ({DF}, App. B)."""
    w = default_static_truth()
    ref = helix49()
    for alpha in (0.0, 0.9, 3.3):
        tr = frame_truth(w, np.zeros(6), alpha, ref, render_detector)
        model = geometry.forward_srf(w, ref.centres_of_m, [alpha], render_detector)[0]
        # same geometry, two code paths: float64 rounding only
        np.testing.assert_allclose(tr.centre_px, model, atol=1e-8)
        assert tr.in_view.all()


def test_shadow_centroid_matches_truth_on_tilted_detector(render_one_sphere, render_detector):
    """Attenuation-weighted centroid of a sphere's shadow vs the true centre projection."""
    det = render_detector
    w = default_static_truth()
    ref = render_one_sphere([0.02, 0.03, 0.03])     # well off-centre on the detector
    settings = RenderSettings(poisson=False, blur_sigma_px=0.7)
    fr = render_projection(w, np.zeros(6), 0.4, ref, det, settings, output="transmission")
    truth = fr.truth.centre_px[0]
    half = int(fr.truth.radius_px[0]) + 6
    p, c0, r0 = _patch(-np.log(fr.image.astype(np.float64)), truth, half)
    err = _centroid(p, c0, r0) - truth
    # noise-free bias bound 0.02 px: the density centroid differs from the
    # ellipse centre (put on the centre projection) at O(SDD tan psi (r/D)^2)
    # = 1048 mm * 0.3 * 1.7e-5 / 0.4 mm = 0.013 px; blur is symmetric.
    assert np.all(np.abs(err) < 0.02), err

    # with counting noise: propagate var(-log(n/I0)) = 1/(I0 T) through the
    # centroid, sigma^2 = sum((x - xc)^2 var_i) / W^2; bound 5 sigma + 0.02 px
    i0 = settings.flat_field_counts
    rng = np.random.default_rng(2024)
    noisy = render_projection(w, np.zeros(6), 0.4, ref, det,
                              RenderSettings(blur_sigma_px=0.7), rng, output="transmission")
    q, _, _ = _patch(-np.log(noisy.image.astype(np.float64)), truth, half)
    t_clean, _, _ = _patch(fr.image.astype(np.float64), truth, half)
    var_i = 1.0 / (i0 * t_clean)
    rows, cols = np.mgrid[r0:r0 + p.shape[0], c0:c0 + p.shape[1]]
    sig = np.sqrt([(((cols - truth[0]) ** 2) * var_i).sum(), (((rows - truth[1]) ** 2) * var_i).sum()]) / p.sum()
    err_n = _centroid(q, c0, r0) - truth
    assert np.all(np.abs(err_n) < 5 * sig + 0.02), (err_n, sig)


def test_overlapping_shadows_multiply(render_ideal_w, render_one_sphere, render_small_detector):
    """Two spheres on the same central ray: chords add in the exponent."""
    # centres 2.5 mm apart along the beam (Z of {OF} at alpha=0 is the beam axis)
    ref = render_one_sphere([[0.0, 0.0, -0.00125], [0.0, 0.0, 0.00125]], diameter_m=0.003)
    fr = render_projection(render_ideal_w(), np.zeros(6), 0.0, ref, render_small_detector,
                           RenderSettings(oversample=1, **CLEAN), output="transmission")
    # both diameters lie on the central ray: T = exp(-mu 2 d), float32 rel 1e-6
    assert fr.image[50, 50] == pytest.approx(np.exp(-MU * 0.006), rel=1e-6)
    assert fr.truth.overlapping.all()
    # a ray that misses the back sphere but crosses the front one: chord from
    # the closed-form line-sphere distance, computed independently here
    w = render_ideal_w()
    det = render_small_detector
    col = 50 + 7                      # 7 px right of centre, row 50
    x = 7 * det.pixel_pitch_m
    chords = []
    for zc in (w[0] - 0.00125, w[0] + 0.00125):
        ray = np.array([x, 0.0, w[3]]) / np.linalg.norm([x, 0.0, w[3]])
        c = np.array([0.0, 0.0, zc])          # in {SRF}; the source is the origin
        dist2 = c @ c - (c @ ray) ** 2
        chords.append(2 * np.sqrt(max(1.5e-3 ** 2 - dist2, 0.0)))
    assert fr.image[50, col] == pytest.approx(np.exp(-MU * sum(chords)), rel=1e-6)


def test_in_view_and_overlap_flags(render_ideal_w, render_one_sphere, render_small_detector):
    det = render_small_detector   # 40 mm wide, 14 mm at the object
    ref = render_one_sphere([[0.0, 0.0, 0.0], [0.0, 0.03, 0.0], [0.0, 0.0047, 0.0]])
    tr = frame_truth(render_ideal_w(), np.zeros(6), 0.0, ref, det)
    # sphere 2 projects 0.03 * 2.88 = 86 mm above centre: off the detector
    assert list(tr.in_view) == [True, False, True]
    # spheres 1 and 3: 4.7 mm apart -> 13.5 mm = 33.8 px between centres;
    # shadow radii 10.8 px each + 1 px gap = 22.6 px < 33.8: not overlapping
    assert not tr.overlapping.any()
    ref2 = render_one_sphere([[0.0, 0.0, 0.0], [0.0, 0.0035, 0.0]])
    # 3.5 mm -> 25.2 px < 2 * 10.8 + 1 = 22.6? no: 25.2 > 22.6, still separate
    assert not frame_truth(render_ideal_w(), np.zeros(6), 0.0, ref2, det).overlapping.any()
    ref3 = render_one_sphere([[0.0, 0.0, 0.0], [0.0, 0.0030, 0.0]])
    # 3.0 mm -> 21.6 px < 22.6: touching shadows
    assert frame_truth(render_ideal_w(), np.zeros(6), 0.0, ref3, det).overlapping.all()


def test_silhouette_ellipse_closed_form():
    """Ellipse centre and major axis against the 2D tangent-line construction."""
    sdd = 1.0
    src = np.array([0.0, 0.0, -sdd])
    for psi, dist, r in ((0.0, 0.4, 0.0015), (0.15, 0.364, 0.0015), (0.25, 0.15, 0.01)):
        c = src + dist * np.array([np.sin(psi), 0.0, np.cos(psi)])
        centre, axes = silhouette_ellipses(src, c[None], [r])
        beta = np.arcsin(r / dist)
        # in the XZ plane the silhouette's extreme rays make angles psi +- beta
        x1, x2 = sdd * np.tan(psi - beta), sdd * np.tan(psi + beta)
        np.testing.assert_allclose(centre[0], [(x1 + x2) / 2, 0.0], atol=1e-12)
        assert axes[0, 0] == pytest.approx((x2 - x1) / 2, rel=1e-10)
        # centre projection sdd tan(psi) vs ellipse centre: offset ~ sdd tan(psi) sec^2(psi) beta^2
        off = (x1 + x2) / 2 - sdd * np.tan(psi)
        assert off == pytest.approx(sdd * np.tan(psi) / np.cos(psi) ** 2 * beta ** 2, rel=0.05, abs=1e-15)


def test_ellipse_centre_bias_switch(render_ideal_w, render_one_sphere):
    """Exact silhouette: its area centroid is the ellipse centre, away from the centre projection."""
    det = DetectorSpec(1600, 1600, 0.0004)     # large enough for the whole shadow
    w = render_ideal_w(srd_m=0.20)
    # a 20 mm sphere 35 mm off-axis, 200 mm from the source: psi = 0.173,
    # beta = 0.049, offset ~ sdd tan(psi) sec^2(psi) beta^2 = 0.46 mm = 1.1 px
    xs, r = 0.035, 0.01
    ref = render_one_sphere([xs, 0.0, 0.0], diameter_m=2 * r)
    opaque = dict(mu_sphere_per_m=1e7, oversample=8, **CLEAN)   # T = 0 inside: 1 - T = pixel coverage
    out = {}
    for bias in (False, True):
        fr = render_projection(w, np.zeros(6), 0.0, ref, det, RenderSettings(ellipse_centre_bias=bias, **opaque),
                               output="transmission")
        cov = 1.0 - fr.image.astype(np.float64)
        out[bias] = (_centroid(cov), fr.truth)
    (c_off, t_off), (c_on, t_on) = out[False], out[True]
    np.testing.assert_allclose(t_on.centre_px, t_off.centre_px, atol=1e-12)   # same geometry
    shift = t_on.ellipse_centre_px[0] - t_on.centre_px[0]
    psi, beta = np.arctan(xs / w[0]), np.arcsin(r / np.hypot(xs, w[0]))
    expected = w[3] * ((np.tan(psi + beta) + np.tan(psi - beta)) / 2 - np.tan(psi)) / det.pixel_pitch_m
    assert shift[0] == pytest.approx(expected, rel=1e-9) and abs(shift[1]) < 1e-9
    assert shift[0] > 1.0
    # coverage centroid = area centroid of the ellipse; sub-sampling the rim
    # with 1/8 px on a ~135 px radius ellipse: error << 0.01 px; bound 0.02 px
    np.testing.assert_allclose(c_on, t_on.ellipse_centre_px[0], atol=0.02)
    np.testing.assert_allclose(c_off, t_off.centre_px[0], atol=0.02)
    # textbook mode: reported ellipse centre is the centre projection
    np.testing.assert_allclose(t_off.ellipse_centre_px, t_off.centre_px, atol=0)


def test_default_geometry_bias_is_small(render_detector):
    """At the paper's geometry the natural ellipse-centre bias is ~0.01 px (for the report)."""
    s = RenderSettings(ellipse_centre_bias=True)
    w = default_static_truth()
    tr = frame_truth(w, np.zeros(6), 0.0, helix49(), render_detector, s)
    off = np.linalg.norm(tr.ellipse_centre_px - tr.centre_px, axis=1)
    # analytic scale: SDD tan(psi) sec^2(psi) (r/D)^2 / pitch, psi <= 0.16 rad at
    # the detector corners, r/D = 1.5/330: 1048 * 0.16 * 2.1e-5 / 0.4 = 0.009 px
    assert 0.0 < off.max() < 0.02
    assert off.max() > 1e-3


@pytest.mark.parametrize("bad", [
    dict(static_w=np.zeros(12)),
    dict(static_w=np.r_[np.nan, np.zeros(12)]),
    dict(motion=np.zeros(5)),
    dict(motion=np.r_[np.inf, np.zeros(5)]),
    dict(alpha_rad=np.nan),
    dict(alpha_rad=[0.0, 1.0]),
    dict(output="png"),
    dict(time_s=np.inf),
])
def test_render_rejects_bad_inputs(bad, render_ideal_w, render_one_sphere, render_small_detector):
    args = dict(static_w=render_ideal_w(), motion=np.zeros(6), alpha_rad=0.0)
    kw = dict(output="mono16", time_s=0.0)
    for k, v in bad.items():
        (args if k in args else kw)[k] = v
    with pytest.raises(ValueError):
        render_projection(args["static_w"], args["motion"], args["alpha_rad"], render_one_sphere([0, 0, 0]),
                          render_small_detector, RenderSettings(**CLEAN), **kw)


@pytest.mark.parametrize("kw", [
    dict(oversample=0), dict(flat_field_counts=0.0), dict(blur_sigma_px=-1.0),
    dict(focal_spot_drift_m_per_s=(0.0, 1.0)), dict(mu_sphere_per_m=np.nan),
])
def test_settings_reject_bad_values(kw):
    with pytest.raises(ValueError):
        RenderSettings(**kw)


@pytest.mark.parametrize("hidden", [
    dict(),
    dict(ellipse_centre_bias=True, detector_distortion_k1_per_m2=2.0,
         encoder_eccentricity_rad=1e-3, focal_spot_drift_m_per_s=(1e-5, 2e-5, -1e-5)),
])
def test_box_renderer_equals_full_frame_ray_tracing(hidden):
    """The bounding-box shortcut changes nothing: compare with tracing every sub-ray through every sphere."""
    det = DetectorSpec(160, 160, 0.0026)       # whole helix49 at 2.6 mm pixels (shadows ~1.7 px radius)
    w = default_static_truth()
    ref = helix49()
    s = RenderSettings(poisson=False, oversample=2, tube_oversample=2, **hidden)
    for alpha in (0.0, 2.0):
        fast = render_projection(w, np.zeros(6), alpha, ref, det, s, time_s=10.0, output="transmission")
        slow = render_projection_bruteforce(w, np.zeros(6), alpha, ref, det, s, time_s=10.0,
                                            output="transmission")
        assert fast.n_rays < slow.n_rays
        # same arithmetic on the same sub-samples (non-member spheres add exact
        # zeros): float32 rounding at most
        np.testing.assert_allclose(fast.image, slow.image, atol=1e-6, rtol=0)
        assert fast.image.min() < 0.5    # spheres are in the picture
