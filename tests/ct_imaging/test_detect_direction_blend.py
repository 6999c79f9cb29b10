"""The local background's direction and the frame's (detect._blend_direction).

By default a window's direction is replaced by the frame's dominant one when it lies within
``snap_sigma`` (4) sd of its own noise of it, and kept otherwise: where that decision flips (a
crop's noise estimate, a slightly turned band) the centre jumps by ~0.4-0.6 of its sd
(tests/ct_imaging/test_track.py). ``DetectionSettings(direction_blend=True)`` blends smoothly
instead. The scene here is drawn by this test alone (not by core/render.py): five balls (soft
edges, 4 x 4 sub-pixels, Gaussian blur, fixed noise); four sit on strong straight steps that set
the frame's direction, the fifth has a thin weak band through its edge, turned by phi from that
direction. Sweeping phi moves the fifth window's evidence t = |theta - frame's| / sd across 4:
with the blend its centre moves in small steps, with the hard switch it jumps.
(The blend is not the default: between a crop and its whole frame it moves more centres, and
some by more, than the switch does; doc/ct_detect.md.)
"""

import cv2
import numpy as np
from ct_calib_nodes.core import detect as D

R = 10.0
TH = np.deg2rad(20.0)
TEST = (180.35, 120.2)
OUTER = ((60.3, 60.2), (60.7, 180.4), (300.2, 60.6), (300.4, 180.1))


def scene(phi, rows=240, cols=360, os_=4, blur=0.7, noise=0.004, band=0.08, seed=3):
    gy = (np.arange(rows * os_) + 0.5) / os_ - 0.5
    gx = (np.arange(cols * os_) + 0.5) / os_ - 0.5
    x, y = np.meshgrid(gx, gy)
    t = np.ones_like(x)
    for bx, by in OUTER + (TEST,):
        t *= np.exp(-0.25 * 2.0 * np.sqrt(np.clip(R * R - (x - bx) ** 2 - (y - by) ** 2, 0.0, None)))
    g = np.ones_like(x)
    for bx, by in OUTER:       # a 10 % step beside each outer ball, across TH
        u = (x - bx) * np.cos(TH) + (y - by) * np.sin(TH)
        g = np.where((np.hypot(x - bx, y - by) < 45) & (u > 4.0), g * 0.9, g)
    u = (x - TEST[0]) * np.cos(TH + phi) + (y - TEST[1]) * np.sin(TH + phi)
    g = np.where((np.hypot(x - TEST[0], y - TEST[1]) < 45) & (np.abs(u - 9.0) < 1.0), g * (1.0 - band), g)
    img = cv2.GaussianBlur((t * g).reshape(rows, os_, cols, os_).mean(axis=(1, 3)), (0, 0), blur)
    return (img + np.random.default_rng(seed).normal(0.0, noise, img.shape)).astype(np.float32)


def _sweep(phis, settings):
    """Per phi: the evidence of the test ball's window, and per settings its centre / its sd."""
    st = D.DetectionSettings()
    cs, ev = [[] for _ in settings], []
    for phi in phis:
        img = scene(np.deg2rad(phi))
        for c, s_ in zip(cs, settings):
            d = D.detect_spheres(img, encoding="32FC1", flat_field_counts=1.0, settings=s_)
            assert len(d) == 5
            j = int(np.argmin(np.hypot(d.centre_px[:, 0] - TEST[0], d.centre_px[:, 1] - TEST[1])))
            c.append((d.centre_px[j] - TEST) / d.centre_std_px[j])
        trans = D.to_transmission(img, "32FC1", 1.0)
        cand = D._candidates(trans, D._segmentation_background(trans, st, None), st, None, D._Rejections())
        cand.noise = D._noise_level(trans)
        model, _ = D._local_backgrounds(trans, None, cand, st)
        k = int(np.argmin(np.hypot(cand.centre[:, 0] - TEST[0], cand.centre[:, 1] - TEST[1])))
        ev.append(model.direction_evidence[k])
    return [np.array(c) for c in cs], np.array(ev)


def test_centre_moves_smoothly_across_the_threshold():
    phis = np.arange(0.0, 2.01, 0.2)
    (cs, cs_h), ev = _sweep(phis, (D.DetectionSettings(direction_blend=True), D.DetectionSettings()))
    print("evidence", ev.round(2))
    assert ev[0] < 3.5 and ev[-1] > 6.0            # the sweep crosses the hard switch's threshold (4 sd)
    step = np.linalg.norm(np.diff(cs, axis=0), axis=1)
    print("blend: steps of the centre [sd]", step.round(3))
    # the centre follows the grid, which turns by <= 2.3 sd_theta per unit of t (t grows by
    # ~0.4 per 0.2 deg step here): a fraction of the switch's 4 sd_theta jump
    assert step.max() < 0.2
    step_h = np.linalg.norm(np.diff(cs_h, axis=0), axis=1)
    print("hard switch (default): steps [sd]", step_h.round(3))
    assert step_h.max() > 0.4                       # measured 0.58 sd where the decision flips
    # blend: measured 0.17 sd at most, 0.30 of the hard switch's jump
    assert step.max() < 0.4 * step_h.max()


def test_blend_is_continuous_and_has_the_right_limits():
    tf = 0.3
    sd = np.full(200001, np.deg2rad(1.0))
    theta = tf + np.linspace(-np.deg2rad(30.0), np.deg2rad(30.0), sd.size)
    out, t = D._blend_direction(theta, sd, tf, 0.0, 4.0, smooth=True)
    slope = np.diff(out) / np.diff(theta)
    assert np.all(slope > -1e-9) and slope.max() < 2.3 + 1e-3       # monotone, d theta'/d theta <= 2.299
    assert np.all(np.abs(out[t <= 2.0] - tf) < 1e-12)               # t <= k / 2: the frame's direction
    assert np.all(np.abs(out[t >= 6.0] - theta[t >= 6.0]) < 1e-12)  # t >= 3 k / 2: the window's own
    half = np.argmin(np.abs(t - 4.0))
    assert abs(out[half] - tf - 0.5 * (theta[half] - tf)) < 1e-4     # one half at t = k
    # no frame direction (its sd far above FRAME_DIRECTION_SD): every window keeps its own
    own, _ = D._blend_direction(theta, sd, tf, 20.0 * D.FRAME_DIRECTION_SD, 4.0, smooth=True)
    np.testing.assert_allclose(own - theta, 0.0, atol=1e-4 * np.deg2rad(30.0))
    # wrap-around: a window at tf + pi - 1 deg is 1 deg from the frame's direction
    w1, _ = D._blend_direction(np.array([tf + np.pi - np.deg2rad(1.0)]), np.array([np.deg2rad(1.0)]), tf, 0.0, 4.0,
                              smooth=True)
    assert abs((w1[0] - tf + 0.5 * np.pi) % np.pi - 0.5 * np.pi) < 1e-9

