"""The static CT calibration on frames this project did not render (issue 14 items 1-3), reduced.

Three random instruments rendered by ct_indep_gen.py (its own ray tracing, beam hardening, PSF with an
exponential tail, heel / fall-off flat field, holders; nothing from ct_calib_nodes), 24 projections on a
384 x 384 detector, each through the user's command ``ct_offline_solve`` (a subprocess) and compared with
the truth by ct_indep_check.py. The full campaign (22 instruments, 30 projections, 384 px):
tests/benchmarks/validate_ct_indep.py; figures in ros_ws/src/ct_calib_nodes/doc/ct_detect.md,
"Independent renderer check".
"""

import numpy as np
import pytest

import ct_indep_check as ck

pytestmark = pytest.mark.ros
# Seeds 1, 3, 6 (24 projections, 384 px): 1 is an ordinary case, 3 has a sharp PSF (0.3-0.5 px) where the
# detector's merged-shadow test refused isolated spheres before its depth-weighted moments (ct_detect.md,
# "Small shadows"), 6 is one where the identity initialisation used to pick the helix labelled one sphere
# along (round 19: 12 of 22 instruments; the screw-shifted labellings are now compared explicitly,
# core/identify.py). Seed 1 has a sphere 6.3 px clear of a pair of merged shadows, which the proximity
# rule refused until it measured the gap to an elongated blob's own pixels (round 24; ct_detect.md,
# "Proximity to merged blobs").
SEEDS = (1, 3, 6)
GATE = 2.5     # the quality gate's factor between the residual rms and the stated sigma (ct_core.md)


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


def test_no_false_detections_and_stated_sigma_within_the_gate(cases):
    for c in cases:
        d = c["detection"]
        assert d["false"] == 0, d["false_at"]
        assert d["visible"] > 10 * 24 and d["found_visible"] > 0
        # accepted centres against the true ellipse centres: the detector's stated sigma is right to
        # within the quality gate's factor (the solve rescales it by its a-posteriori factor)
        assert all(1 / GATE < r < GATE for r in d["err_over_sigma_rms"]), d["err_over_sigma_rms"]
        assert c["variance_factor"] < GATE ** 2


def test_no_clear_sphere_refused_as_merged(cases):
    for c in cases:
        d = c["detection"]
        assert d["missed_reasons"].get("overlap_merged", 0) == 0, (c["seed"], d["missed_reasons"])


def test_every_clear_sphere_found(cases):
    for c in cases:
        d = c["detection"]
        assert d["found_visible"] == d["visible"], (c["seed"], d["missed_reasons"], d["missed"])


def test_sphere_identities(cases):
    for c in cases:
        assert c["labelling"] in ("file", "upside_down"), (c["seed"], c["labelling"], c["label_shift"])
        assert c["detection"]["misidentified"] == 0, c["seed"]
