"""Two-model pass (issue 14.3, ``DetectionSettings.two_model_pass``): a shadow that no single
background model holds round (refused by the one-direction model's structure screens, the corner
model and the partial edge) is kept on its one-direction measurement with the difference to a
surface model's centre in its covariance, unless a dark pixel lies within the proximity margin
outside it (a neighbour merged with the structure). Holder frames of
tests/benchmarks/validate_ct_detect_holders.py, seeds 1 and 3 (plates and tilted tubes, mono16 and
JPEG q90; truth only to score): ~8 s CPU."""

import os
import sys

import numpy as np
import pytest

from ct_calib_nodes.core import detect

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "benchmarks"))
import validate_ct_detect_holders as V  # noqa: E402

DR = (3e-3 * V.SDD / (0.364 + 0.045) / 4e-4, 3e-3 * V.SDD / (0.364 - 0.045) / 4e-4)


@pytest.fixture(scope="module")
def results():
    out = []
    for seed in (1, 3):
        for kind, enc, img, tr, _ in V.frames(8, seed):
            encoding = "mono16" if img.dtype == np.uint16 else "mono8"
            on = detect.detect_spheres(img, encoding=encoding, diameter_px_range=DR)
            off = detect.detect_spheres(img, encoding=encoding, diameter_px_range=DR,
                                        settings=detect.DetectionSettings(two_model_pass=False))
            out.append((kind, enc, tr, on, off))
    return out


def test_every_sphere_found_and_the_kept_ones_within_their_sd(results):
    n_new, z_new, sd_ratio, n_dark = 0, [], [], 0
    for kind, enc, tr, on, off in results:
        f_on, n, false_on, _, _ = V.score(on.centre_px, on.centre_std_px, tr)
        f_off, _, false_off, _, _ = V.score(off.centre_px, off.centre_std_px, tr)
        assert false_on == 0 and false_off == 0, (kind, enc)
        assert f_on == n, (kind, enc, f_on, n)                     # every expected sphere
        # no truly overlapping sphere (touch gap 4 px) is accepted
        d = np.linalg.norm(on.centre_px[:, None] - tr.centre_px[None], axis=2)
        assert not np.any(tr.overlapping[d.argmin(axis=1)]), (kind, enc)
        # the pass adds shadows and changes nothing else
        new = on.two_models
        assert len(on) == len(off) + int(new.sum())
        assert np.array_equal(on.centre_px[~new], off.centre_px)
        assert np.array_equal(on.centre_cov_px2[~new], off.centre_cov_px2)
        n_dark += sum("two models: dark pixels" in t for t in on.rejected.detail)
        if new.any():
            j = d[new].argmin(axis=1)
            z_new.append((on.centre_px[new] - tr.centre_px[j]) / on.centre_std_px[new])
            sd_ratio.extend(np.max(on.centre_std_px[new], axis=1) / np.median(np.max(on.centre_std_px[~new], axis=1)))
            n_new += int(new.sum())
    z = np.vstack(z_new)
    print(f"kept by the two-model pass: {n_new}; z {z.round(2).tolist()}; sd / frame median "
          f"{np.round(sd_ratio, 1).tolist()}; refused for dark pixels nearby: {n_dark}")
    assert n_new >= 3                       # without the pass these were refused (seeds 1 and 3)
    assert np.all(np.abs(z) < 4.0)
    assert min(sd_ratio) > 1.0              # the two models' difference costs precision
