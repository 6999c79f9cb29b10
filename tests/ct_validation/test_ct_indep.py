"""The static CT calibration on frames this project did not render (issue 14 items 1-3), reduced.

Three random instruments rendered by ct_indep_gen.py (its own ray tracing, beam hardening, PSF with an
exponential tail, heel / fall-off flat field, holders; nothing from ct_calib_nodes), 24 projections on a
384 x 384 detector, each through the user's command ``ct_offline_solve`` (a subprocess) and compared with
the truth by ct_indep_check.py. The full campaign (24 instruments, 36 projections, 512 px):
tests/benchmarks/validate_ct_indep.py; figures in ros_ws/src/ct_calib_nodes/doc/ct_detect.md,
"Independent renderer check".
"""

import numpy as np
import pytest

import ct_indep_check as ck

pytestmark = pytest.mark.ros
SEEDS = (1, 2, 3)


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    work = tmp_path_factory.mktemp("ct_indep")
    return [ck.run_case(s, work, cols=384, n_views=24) for s in SEEDS]


def test_instrument_geometry_within_its_uncertainty(cases):
    for c in cases:
        print(f"\nseed {c['seed']}: {c['outcome']}, z {np.round(c.get('z', [])[:7], 2).tolist()}, "
              f"pixel {c.get('pixel')}, chi2/dof {c.get('variance_factor')}")
        assert c["outcome"] == "success" and not c["problems"], (c.get("message"), c["problems"])
        # the 7 instrument parameters, each within 4 of its own reported standard uncertainty
        assert np.all(np.abs(c["z"][:7]) < 4.0), dict(zip(ck.gen.PARAM_NAMES, np.round(c["z"], 2)))
        # convention-free: the fitted geometry's sphere-centre projections (every view, every sphere)
        # against the true ones, relative to the uncertainty the reported covariance gives each point
        px = c["pixel"]
        assert px["rms_z"] < 2.5 and px["max_abs_z"] < 5.0, px
        # the detector's stated sigma holds within the quality gate's factor
        assert 0.5 < c["variance_factor"] < 2.5 ** 2


def test_identities_and_no_false_detections(cases):
    for c in cases:
        d = c["detection"]
        assert c["labelling"] in ("file", "upside_down"), c["labelling"]
        assert d["false"] == 0, d["false_at"]
        assert d["misidentified"] == 0
        # accepted centres against the true ellipse centres: the reported sigma is honest to within 2x
        assert all(0.5 < r < 2.0 for r in d["err_over_sigma_rms"]), d["err_over_sigma_rms"]


def test_nearly_every_clear_sphere_found(cases):
    for c in cases:
        d = c["detection"]
        assert d["visible"] > 10 * 24
        assert d["found_visible"] >= 0.98 * d["visible"], (d["missed_reasons"], d["missed"])


@pytest.mark.xfail(strict=True, reason="issue 14.3 not met on independent frames: the detector rejects a few isolated "
                                       "spheres (gap >= 6 px) as 'merged shadows' (moment axis ratio just above 1.12) "
                                       "or 'background_structure' at a tube corner; see ct_detect.md")
def test_every_clear_sphere_found(cases):
    for c in cases:
        d = c["detection"]
        assert d["found_visible"] == d["visible"], (d["missed_reasons"], d["missed"])
