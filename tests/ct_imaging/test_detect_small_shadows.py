"""Small isolated shadows (7 px across, sharp blur) are not refused as merged (ct_detect.md, "Small shadows").

The binary moment axis ratio of a thresholded 7 px blob scatters by pixelation up to ~1.16 (the
merged-shadow screen's limit is 1.12); the screen falls back to the depth-weighted moments for blobs
within the pixelation bound of their size. Frames of the project's renderer, helix49 on a 342 px
detector of 1.2 mm pixels (shadow radius ~3.6 px), blur 0.35 px, 12 views."""

import numpy as np
import pytest

from ct_calib_nodes.core import detect
from ct_calib_nodes.core.geometry import DetectorSpec
from ct_calib_nodes.core.phantom import helix49
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.scenario import default_static_truth

PITCH = 0.0012
DET = DetectorSpec(342, 342, PITCH)
DRANGE = (14.0 * 0.0004 / PITCH, 27.0 * 0.0004 / PITCH)    # test_detect_rejection's range, scaled
CLEAR_GAP_PX = 6.0


def _merged_refusals(det):
    sel = np.array(["moment axis ratio" in s for s in det.rejected.detail], dtype=bool)
    return det.rejected.centre_px[sel].reshape(-1, 2)


@pytest.fixture(scope="module")
def runs():
    w, ref, rs = default_static_truth(0.364), helix49(), RenderSettings(blur_sigma_px=0.35)
    former = detect.DetectionSettings(grey_moment_screen=False)
    out = []
    for k, a in enumerate(np.deg2rad(np.arange(0.0, 360.0, 30.0))):
        fr = render_projection(w, np.zeros(6), a, ref, DET, rs, np.random.default_rng(k))
        new = detect.detect_spheres(fr.image, flat_field_counts=50000.0, diameter_px_range=DRANGE)
        old = detect.detect_spheres(fr.image, flat_field_counts=50000.0, diameter_px_range=DRANGE, settings=former)
        out.append((fr.truth, new, old))
    return out


def _clear(tr):
    """In view, and >= CLEAR_GAP_PX from every other shadow (bounding circles)."""
    c, r = tr.centre_px, tr.radius_px
    gap = np.linalg.norm(c[:, None] - c[None], axis=2) - r[:, None] - r[None]
    np.fill_diagonal(gap, np.inf)
    return tr.in_view & (gap.min(axis=1) >= CLEAR_GAP_PX)


def test_no_clear_shadow_refused_as_merged(runs):
    n_clear = n_old = 0
    for tr, new, old in runs:
        clear = tr.centre_px[_clear(tr)]
        n_clear += len(clear)
        for det, is_new in ((new, True), (old, False)):
            m = _merged_refusals(det)
            hit = int(np.sum(np.min(np.linalg.norm(clear[:, None] - m[None], axis=2), axis=1) < 2.0)) if len(m) else 0
            if is_new:
                assert hit == 0
            else:
                n_old += hit
    assert n_clear >= 200
    assert n_old >= 10          # the former binary screen refused them: these frames exercise it


def test_merged_pairs_still_refused_and_detections_real(runs):
    n_pairs = 0
    for tr, new, _ in runs:
        d = np.linalg.norm(new.centre_px[:, None] - tr.centre_px[None], axis=2)
        j = d.argmin(axis=1)
        assert np.all(d[np.arange(len(j)), j] < 0.3)           # every detection is a sphere
        assert not np.any(tr.overlapping[j])                   # none of them touches another shadow
        # merged refusals: at touching shadows, or at a sphere near another (< CLEAR_GAP_PX), never
        # at a clear one
        ov = tr.centre_px[tr.overlapping & tr.in_view]
        near = tr.centre_px[tr.in_view & ~_clear(tr)]
        for c in _merged_refusals(new):
            at_pair = len(ov) and np.min(np.linalg.norm(ov - c, axis=1)) < 2.5 * np.median(tr.radius_px)
            n_pairs += int(at_pair)
            assert at_pair or np.min(np.linalg.norm(near - c, axis=1)) < 1.0
    assert n_pairs >= 5
