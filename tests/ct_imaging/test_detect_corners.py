"""Corner background model (issue 14.3): a sphere at a plate corner, which the one-direction
local background refuses, is measured with the two-step corner model (frame 0 of
tests/benchmarks/validate_ct_detect_holders.py, seed 1, mono16 and JPEG q90)."""

import os
import sys

import numpy as np
import pytest

from ct_calib_nodes.core import detect

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
import validate_ct_detect_holders as V  # noqa: E402


@pytest.fixture(scope="module")
def plate_frames():
    return V.frames(1, 1)


@pytest.mark.parametrize("k", [0, 1])
def test_plate_corner_sphere_found_with_corner_model(plate_frames, k):
    kind, enc, img, tr, _ = plate_frames[k]
    assert kind == "plate"
    encoding = "mono16" if img.dtype == np.uint16 else "mono8"
    dr = (3e-3 * V.SDD / (0.364 + 0.045) / 4e-4, 3e-3 * V.SDD / (0.364 - 0.045) / 4e-4)
    det = detect.detect_spheres(img, encoding=encoding, diameter_px_range=dr)
    f, n, false, e, z = V.score(det.centre_px, det.centre_std_px, tr)
    assert f == n and false == 0                       # every expected sphere, nothing else
    assert det.on_corner.sum() >= 1
    c = det.on_corner
    d = np.linalg.norm(det.centre_px[c][:, None] - tr.centre_px[None], axis=2).min(axis=1)
    # within 4 reported sd (rss of both axes) and 0.03 px of the truth
    assert np.all(d < np.minimum(0.03, 4 * np.linalg.norm(det.centre_std_px[c], axis=1) + 0.01))
    # without the corner pass (and the two-model pass, the last resort after it) the same
    # shadows are refused as background_structure
    off = detect.detect_spheres(img, encoding=encoding, diameter_px_range=dr,
                                settings=detect.DetectionSettings(max_corner_misfit=None, two_model_pass=False))
    assert len(off) == len(det) - int(c.sum())
    assert off.rejected.count("background_structure") >= int(c.sum())
