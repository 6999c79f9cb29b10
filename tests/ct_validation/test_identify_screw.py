"""Sphere identity on the independent renderer's instruments, in-process (no rendering): the screw symmetry.

helix49 shifted by k spheres along the helix maps onto itself by a rigid motion, so a labelling shifted by k
fits all but the k end spheres. Before round 19, 5 of these 8 instruments (seeds 9000-9007, drawn by
ct_indep_gen.draw_case, detections idealised as in tests/benchmarks/bench_identify_screw.py: true centres of
the spheres the detector finds, + 0.02 px noise) came out labelled 1-3 spheres along and reported success.
Now every initialisation is either right (as the file, or upside down, which helix49's symmetry makes
legitimate) or refused naming the screw symmetry; a refusal is allowed only where the end spheres are hidden
(seed 9000 here: its best labelling leaves 5 detections unexplained, the shifted one 6).
"""

import pathlib
import sys
from types import SimpleNamespace

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_identify_screw as bench  # noqa: E402
from ct_calib_nodes.core import identify  # noqa: E402

SEEDS = range(9000, 9008)


def test_no_shifted_labelling_reported_as_success():
    args = SimpleNamespace(cols=384, views=30, object_tilt_deg=0.5, init=6, noise_px=0.02, p_close=0.6,
                           p_drop=0.04, identify=identify)
    rows = [bench.run_one(s, args) for s in SEEDS]
    for r in rows:
        print(r["seed"], r["outcome"], r["ok"], r["wrong"], r["message"][:120])
        assert r["outcome"] in ("right", "refused"), r
        if r["outcome"] == "refused":
            assert "screw-symmetric" in r["message"], r["message"]
        else:
            assert r["wrong"] == 0 and r["ok"] == r["detections"] > 0, r
    assert sum(r["outcome"] == "right" for r in rows) >= 6
    # the screw motions found in the file: k = +-1..3, exact for the ideal helix
    ids, centres, diameters, _u = bench.gen.load_reference()
    idf = identify.SphereIdentifier(ids, centres, diameters, identify.DetectorSpec(384, 384, 1e-3), 1.0)
    assert sorted(k for k, *_ in idf.screws) == [-3, -2, -1, 1, 2, 3]
    assert max(rms for *_, rms in idf.screws) < 1e-8
