"""Partial-edge pass (issue 14.3, ``DetectionSettings.arc_pass``): a sphere next to the body tube's
end rim and the rod, which both the one-direction background and the corner model of two steps
refuse, is measured on the part of its edge whose surroundings a plane fits. Rendered by the
independent generator (tests/ct_validation/ct_indep_gen.py, case 7230 view 13: helix49 on its
tube, a rod at 40 deg; truth used only to score), three noise draws: ~3 s CPU."""

import os
import sys

import numpy as np
import pytest

from ct_calib_nodes.core import detect

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "ct_validation"))
import ct_indep_gen as gen  # noqa: E402

SEED, VIEW, SPHERE = 7230, 13, 0


@pytest.fixture(scope="module")
def scene():
    case = gen.draw_case(SEED)
    inst, phys = case["inst"], case["phys"]
    ren = gen.Renderer(inst, case["c_true"], case["diam"], phys)
    dr = detect.shadow_diameter_range_px(case["diam"], case["c_file"], inst.sdd_reported_m, inst.srd_reported_m,
                                         inst.pitch_m)
    flat = float(round(phys.counts * ren.gain.mean()))
    return inst, ren, dr, flat, case["alphas"][VIEW]


@pytest.mark.parametrize("noise_seed", [1, 2, 3])
def test_sphere_at_rim_and_rod_measured_on_partial_edge(scene, noise_seed):
    inst, ren, dr, flat, alpha = scene
    img, cr, rad = ren.frame(alpha, np.random.default_rng(noise_seed))
    assert img.dtype == np.uint16
    off = detect.detect_spheres(img, encoding="mono16", flat_field_counts=flat, diameter_px_range=dr,
                                settings=detect.DetectionSettings(arc_pass=False, two_model_pass=False))
    # (the two-model pass, which comes after this one, is off in both: it would keep the sphere too)
    on = detect.detect_spheres(img, encoding="mono16", flat_field_counts=flat, diameter_px_range=dr,
                               settings=detect.DetectionSettings(two_model_pass=False))
    # without the pass the sphere is refused as background_structure
    assert np.min(np.linalg.norm(off.centre_px - cr[SPHERE], axis=1)) > rad[SPHERE]
    i = [j for j, c in enumerate(off.rejected.centre_px) if np.linalg.norm(c - cr[SPHERE]) < rad[SPHERE]]
    assert i and off.rejected.reason[i[0]] == "background_structure"
    # with it: found, nothing else changed, no false detection
    assert len(on) == len(off) + 1
    d = np.linalg.norm(on.centre_px[:, None] - cr[None], axis=2)
    assert np.all(d.min(axis=1) < 0.5 * rad[d.argmin(axis=1)])
    m = int(np.argmin(d[:, SPHERE]))
    assert on.on_corner[m]
    others = np.delete(np.arange(len(on)), m)
    assert np.array_equal(on.centre_px[others], off.centre_px)
    assert np.array_equal(on.centre_cov_px2[others], off.centre_cov_px2)
    # its centre within 4 of its stated sd of the true ellipse centre (ct_core.md), per axis
    b = on.semi_axes_px[m, 1]
    e = on.centre_px[m] - inst.ellipse_centre_px(cr[SPHERE], b)
    assert np.all(np.abs(e) < 4 * on.centre_std_px[m]), (e, on.centre_std_px[m])
    # the partial edge costs precision: the stated sd is larger than a full edge's
    assert np.max(on.centre_std_px[m]) > np.median(np.max(on.centre_std_px[others], axis=1))
