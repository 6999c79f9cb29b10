"""The detector's faster code paths give what the straightforward ones gave (issue 14.4 speed
work): component statistics from the mask pixels equal OpenCV's connectedComponentsWithStats,
the hot-pixel screen's neighbour extremes from one ring dilation equal the explicit 8-neighbour
max/min, cyclic runs are found as before, and ``timing`` reports every stage."""

import cv2
import numpy as np
import pytest

from ct_calib_nodes.core import detect
from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.scenario import default_static_truth


@pytest.mark.parametrize("seed,density", [(0, 0.02), (1, 0.3), (2, 0.0), (3, 0.7)])
def test_component_statistics_equal_opencvs(seed, density):
    rng = np.random.default_rng(seed)
    mask = (cv2.GaussianBlur(rng.random((97, 131)).astype(np.float32), (0, 0), 1.5) < 0.3 + 0.4 * density)
    mask = mask.view(np.uint8) if density > 0 else np.zeros((97, 131), np.uint8)
    n, lab_cv, st_cv, ce_cv = cv2.connectedComponentsWithStats(mask, connectivity=8)
    lab, st, ce = detect._components(mask)
    assert st.shape == (n - 1, 5) and ce.shape == (n - 1, 2)
    assert np.array_equal(lab, lab_cv)
    assert np.array_equal(st, st_cv[1:].astype(np.int64))
    np.testing.assert_allclose(ce, ce_cv[1:], rtol=0, atol=1e-12)


def test_hot_pixel_neighbour_extremes_equal_the_explicit_ones():
    rng = np.random.default_rng(4)
    win = rng.normal(1.0, 0.01, (5, 21, 21)).astype(np.float32)
    win[2, 7, 9] = 1.5                      # hot, interior
    win[4, 13, 3] = 0.2                     # dead, interior
    win[1, 0, 5] = 1.5                      # on the window's border: not screened
    nb = [win[:, 1 + dr:20 + dr, 1 + dc:20 + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]
    mx, mn = np.max(nb, axis=0), np.min(nb, axis=0)
    cen = win[:, 1:-1, 1:-1]
    k = np.float32(6 * 0.01)
    want = np.argwhere((cen > mx + k) | (cen < mn - k))
    yy = np.broadcast_to(np.arange(21)[None, :, None] + 100 * np.arange(5)[:, None, None], win.shape)
    xx = np.broadcast_to(np.arange(21)[None, None, :], win.shape)
    trans = np.ones((600, 30), np.float32)
    trans[yy, xx] = win
    got = detect._repair_hot_pixels(trans, win.copy(), yy, xx, 0.01, detect.DetectionSettings())
    assert len(want) == 2
    assert sorted(map(tuple, got.astype(int))) == sorted((c + 1, 100 * w + r + 1) for w, r, c in want)


def test_cyclic_runs():
    assert detect._runs([]) == []
    assert [r.tolist() for r in detect._runs([1, 1, 0, 0, 1, 0, 1])] == [[4], [6, 0, 1]]
    assert [r.tolist() for r in detect._runs([1, 1, 1])] == [[0, 1, 2]]
    assert [r.tolist() for r in detect._runs([0, 1, 1, 0, 0, 1])] == [[1, 2], [5]]


def test_timing_reports_every_stage():
    det = DetectorSpec(256, 256, 0.0016)
    fr = render_projection(default_static_truth(0.364), np.zeros(6), 0.3, helix49(), det, RenderSettings(),
                           np.random.default_rng(0))
    timing = {}
    out = detect.detect_spheres(fr.image, diameter_px_range=(3.0, 9.0), timing=timing)
    assert set(timing) == {"flat_field", "background", "candidates", "local_background", "edges_fit",
                           "rejection", "uncertainty"}
    assert all(v >= 0 for v in timing.values())
    again = detect.detect_spheres(fr.image, diameter_px_range=(3.0, 9.0))
    assert np.array_equal(out.centre_px, again.centre_px)
