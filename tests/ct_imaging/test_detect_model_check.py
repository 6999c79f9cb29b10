"""Second background model where the first misfits (issue 14.3, accuracy on other holders).

On the holder frames of tests/benchmarks/validate_ct_detect_holders.py (seed 1: an acrylic plate
seen obliquely near its corner, a tilted tube's wall band turning into its end rim) the
one-direction background lines miss the background under a few shadows by 2-5 %, and those
centres lie 0.04-0.17 px off at 6-12 reported sd. ``_model_check`` measures every shadow whose
lines misfit more than the frame's typical one again on a low-order surface and adds the two
centres' difference to its covariance. It changes no centre, only those shadows' covariances.
"""

import os
import sys

import numpy as np
import pytest

from ct_calib_nodes.core import detect

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
import validate_ct_detect_holders as V  # noqa: E402

DR = (3e-3 * V.SDD / (0.364 + 0.045) / 4e-4, 3e-3 * V.SDD / (0.364 - 0.045) / 4e-4)


@pytest.fixture(scope="module")
def runs():
    out = []
    for kind, enc, img, tr, _ in V.frames(8, 1):
        encoding = "mono16" if img.dtype == np.uint16 else "mono8"
        on = detect.detect_spheres(img, encoding=encoding, diameter_px_range=DR)
        off = detect.detect_spheres(img, encoding=encoding, diameter_px_range=DR,
                                    settings=detect.DetectionSettings(model_check_misfit=None))
        out.append((kind, tr, on, off))
    return out


def _z(det, tr):
    d = np.linalg.norm(det.centre_px[:, None] - tr.centre_px[None], axis=2)
    j = d.argmin(axis=1)
    good = (d[np.arange(len(j)), j] < 0.5) & V.expected(tr)[j]
    return (det.centre_px[good] - tr.centre_px[j[good]]) / det.centre_std_px[good]


def test_same_centres_only_flagged_covariances_change(runs):
    n_changed = 0
    for _, _, on, off in runs:
        assert np.array_equal(on.centre_px, off.centre_px)
        changed = np.any(on.centre_cov_px2 != off.centre_cov_px2, axis=(1, 2))
        n_changed += int(changed.sum())
        # a covariance only grows (the outer product of a difference is added)
        grow = on.centre_cov_px2[changed] - off.centre_cov_px2[changed]
        assert np.all(np.linalg.eigvalsh(grow) > -1e-12)
    total = sum(len(r[2]) for r in runs)
    assert 0 < n_changed < 0.15 * total          # a few shadows per frame, not all


def test_gross_errors_now_within_their_sd(runs):
    z_on = np.vstack([_z(on, tr) for _, tr, on, _ in runs])
    z_off = np.vstack([_z(off, tr) for _, tr, _, off in runs])
    # the defect is in these frames: without the check several centres lie > 6 sd off
    assert int(np.sum(np.abs(z_off).max(axis=1) > 6)) >= 3
    # with it none beyond 4.5 sd (~1000 z values: a normal one passes 4.5 with p ~ 0.007)
    assert np.abs(z_on).max() < 4.5
    # and the good shadows keep their weight: robust z (MAD) not drowned by the added terms
    rz = 1.4826 * np.median(np.abs(z_on), axis=0)
    assert np.all(rz > 0.7) and np.all(rz < 1.2)

