"""Rejection behaviour of core/detect.py: overlaps, edge cuts, the tube, bad frames."""

import numpy as np
import pytest

from ct_calib_nodes.core import detect
from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, frame_truth, render_projection
from ct_calib_nodes.core.scenario import default_static_truth

DET = DetectorSpec(1024, 1024, 0.0004)
I0 = 50000.0
DRANGE = (14.0, 27.0)    # nominal shadow diameters at SRD 364 mm (3 mm sphere, +-40 mm depth)


def _match(found, truth):
    d = np.linalg.norm(found[:, None, :] - truth.centre_px[None], axis=2)
    j = d.argmin(axis=1)
    return j, d[np.arange(len(j)), j]


@pytest.fixture(scope="module")
def overlap_frame():
    """A frame where the truth says several shadows touch or overlap."""
    w = default_static_truth(0.364)
    ref = helix49()
    rs = RenderSettings()
    alphas = np.deg2rad(np.arange(0.0, 360.0, 3.0))
    n_over = [frame_truth(w, np.zeros(6), a, ref, DET, rs).overlapping.sum() for a in alphas]
    a = alphas[int(np.argmax(n_over))]
    return render_projection(w, np.zeros(6), a, ref, DET, rs, np.random.default_rng(5))


def test_overlapping_shadows_are_rejected_not_split(overlap_frame):
    tr = overlap_frame.truth
    assert tr.overlapping.sum() >= 2
    det = detect.detect_spheres(overlap_frame.image, flat_field_counts=I0, diameter_px_range=DRANGE)
    j, dist = _match(det.centre_px, tr)
    # every accepted detection is one real, non-overlapping sphere measured to < 0.2 px
    assert np.all(dist < 0.2)
    assert not np.any(tr.overlapping[j])
    assert det.rejected.count("overlap") >= 1     # a merged pair is one blob
    # each overlapping sphere's neighbourhood holds an overlap rejection
    rc = det.rejected.centre_px[np.array(det.rejected.reason) == "overlap"]
    for c, rad in zip(tr.centre_px[tr.overlapping & tr.in_view], tr.radius_px[tr.overlapping & tr.in_view]):
        assert np.min(np.linalg.norm(rc - c, axis=1)) < 2.5 * rad
    # the usable spheres are found (a few may fall to the conservative proximity margin)
    assert len(det) >= 0.85 * tr.usable.sum()


def test_spheres_cut_by_the_detector_edge():
    """Shift the detector so the object runs off its left edge."""
    w = default_static_truth(0.364)
    w[1] += 0.110          # detector centre 110 mm to +X: shadows move to low columns
    fr = render_projection(w, np.zeros(6), 0.4, helix49(), DET, RenderSettings(), np.random.default_rng(6))
    tr = fr.truth
    assert (~tr.in_view).sum() >= 3
    det = detect.detect_spheres(fr.image, flat_field_counts=I0, diameter_px_range=DRANGE)
    j, dist = _match(det.centre_px, tr)
    assert np.all(dist < 0.2)
    assert np.all(tr.in_view[j])
    assert det.rejected.count("edge_cut") >= 2
    # nothing accepted whose ellipse comes within 1 px of the border
    assert np.all(det.centre_px[:, 0] - det.semi_axes_px[:, 0] > 1.0)


def test_tube_and_noise_are_not_spheres():
    """The CFRP tube's dark bands never produce a detection; pure noise frames give none."""
    w = default_static_truth(0.364)
    fr = render_projection(w, np.zeros(6), 1.3, helix49(), DET, RenderSettings(), np.random.default_rng(7))
    det = detect.detect_spheres(fr.image, flat_field_counts=I0, diameter_px_range=DRANGE)
    _, dist = _match(det.centre_px, fr.truth)
    assert np.all(dist < 0.2)
    # an open-beam frame with Poisson noise: no blob, no error
    rng = np.random.default_rng(8)
    flat = rng.poisson(I0, size=(1024, 1024)).astype(np.uint16)
    d0 = detect.detect_spheres(flat, flat_field_counts=I0, diameter_px_range=DRANGE)
    assert len(d0) == 0 and len(d0.rejected) == 0 and not d0.success


def test_small_dark_blobs_are_rejected_by_size():
    rng = np.random.default_rng(9)
    img = rng.poisson(I0, size=(256, 256)).astype(np.uint16)
    img[100:103, 50:53] = 1000          # a 3x3 dead cluster
    img[30:200, 200:204] = 20000        # a thin long streak
    d = detect.detect_spheres(img, flat_field_counts=I0, diameter_px_range=DRANGE)
    assert len(d) == 0
    assert set(d.rejected.reason) <= {"not_a_sphere_size", "overlap", "edge_cut"}
    assert d.rejected.count("not_a_sphere_size") >= 1


@pytest.mark.parametrize("make,encoding,reason", [
    (lambda g: np.zeros_like(g), "mono16", "all_dark"),
    (lambda g: np.full_like(g, 65535), "mono16", "saturated"),
    (lambda g: np.full_like(g, 50000), "mono16", "uniform"),
    (lambda g: g[:, :1000], "mono16", "wrong_size"),
    (lambda g: g.astype(np.float32), "mono16", "wrong_dtype"),
    (lambda g: np.where(np.arange(g.shape[1]) == 7, np.nan, g / I0).astype(np.float32), "32FC1", "non_finite"),
    (lambda g: g, "bgr8", "wrong_encoding"),
])
def test_bad_frames_raise_frame_error_and_the_run_continues(make, encoding, reason):
    w = default_static_truth(0.364)
    good = render_projection(w, np.zeros(6), 0.2, helix49(), DET, RenderSettings(),
                             np.random.default_rng(10)).image
    kw = dict(flat_field_counts=I0, expected_shape=(1024, 1024), diameter_px_range=DRANGE)
    first = detect.detect_spheres(good, **kw)
    outcomes = []
    for frame, enc in ((good, "mono16"), (make(good), encoding), (good, "mono16")):
        try:
            outcomes.append(detect.detect_spheres(frame, encoding=enc, **kw))
        except detect.FrameError as exc:
            outcomes.append(exc)
    assert isinstance(outcomes[1], detect.FrameError)
    assert isinstance(outcomes[1], ValueError)
    assert outcomes[1].reason == reason, str(outcomes[1])
    # pure function: the frames around the bad one give identical results
    for o in (outcomes[0], outcomes[2]):
        assert np.array_equal(o.centre_px, first.centre_px)


def test_argument_errors():
    img = np.full((64, 64), 50000, np.uint16)
    with pytest.raises(ValueError):
        detect.detect_spheres(img, diameter_px_range=(10.0, 5.0))
    with pytest.raises(ValueError):
        detect.DetectionSettings(ellipse_fitter="magic")
    with pytest.raises(detect.FrameError):
        detect.detect_spheres(np.zeros((4, 4, 3), np.uint16))


def test_hot_pixels_near_shadows_are_repaired():
    """Hot (and dead) single pixels injected on the edges of shadows: without the repair they
    shift centres by up to ~0.1 px; with it the centres stay at the clean frame's values
    within the noise, and the detections near them count them (``n_hot_pixels``)."""
    w = default_static_truth(0.364)
    fr = render_projection(w, np.zeros(6), 0.7, helix49(), DET, RenderSettings(), np.random.default_rng(9))
    clean = detect.detect_spheres(fr.image, flat_field_counts=I0, diameter_px_range=DRANGE)
    img = fr.image.copy()
    rng = np.random.default_rng(3)
    for (cx, cy), (a, _b) in zip(clean.centre_px, clean.semi_axes_px):
        phi = rng.uniform(0, 2 * np.pi)
        c, r = int(round(cx + a * np.cos(phi))), int(round(cy + a * np.sin(phi)))
        img[r, c] = 65000 if rng.random() < 0.7 else 0
    shift = {}
    for sig in (0.0, 6.0):
        d = detect.detect_spheres(img, flat_field_counts=I0, diameter_px_range=DRANGE,
                                  settings=detect.DetectionSettings(hot_pixel_sigma=sig))
        dist = np.linalg.norm(d.centre_px[:, None] - clean.centre_px[None], axis=2)
        j = dist.argmin(axis=1)
        shift[sig] = np.linalg.norm(d.centre_px - clean.centre_px[j], axis=1)
        if sig:
            assert np.count_nonzero(d.n_hot_pixels) >= 0.9 * len(clean)
            assert len(d) >= len(clean) - 1
    print(f"max centre shift by hot pixels: unrepaired {shift[0.0].max():.3f} px, repaired {shift[6.0].max():.4f} px")
    assert shift[0.0].max() > 0.02           # the effect is present (the fit's outlier cut hides the worst)
    assert shift[6.0].max() < 0.01
