"""Sphere identity of a reference object leaning on the rotary table (issue 14), in-process, no rendering.

Before the lean search, the pose search held the object upright (rho_X = rho_Z = 0 in its coarse grid): with
the object leaning 5 deg it refused 9 of 12 instruments and 8 deg was out of reach (ct_detect.md, failure 3).
Instruments and poses are drawn by tests/ct_validation/ct_indep_gen.py (no project code); the lean is then
set to exactly 5 or 8 deg in a given direction (about the object's X and Z axes). Detections are idealised
as in tests/benchmarks/bench_identify_screw.py (true centre projections of the spheres the detector finds,
+ 0.02 px noise, shadows closer than 4 px to a neighbour lost). The truth ids are used only to score.
"""

import math
import pathlib
import sys

import numpy as np
import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_identify_screw as bench  # noqa: E402
from ct_calib_nodes.core import identify  # noqa: E402
from ct_calib_nodes.core.geometry import DetectorSpec  # noqa: E402


def leaning_case(seed, lean_deg, direction_deg):
    case = bench.gen.draw_case(seed, cols=384, n_views=30, vary_physics=False, object_tilt_deg=0.0)
    w = case["inst"].w
    w[10] = math.radians(lean_deg) * math.cos(math.radians(direction_deg))
    w[12] = math.radians(lean_deg) * math.sin(math.radians(direction_deg))
    return case


def identify_case(case, seed):
    inst = case["inst"]
    views = bench.ideal_detections(case, np.random.default_rng(seed + 10**6), 0.02, 0.6, 0.04)
    idf = identify.SphereIdentifier(case["ids"], case["c_file"], case["diam"],
                                    DetectorSpec(inst.cols, inst.rows, inst.pitch_m), inst.sdd_reported_m)
    init = idf.initialise([v[1] for v in views[:6]], [v[0] for v in views[:6]], inst.srd_reported_m)
    right = right_flip = n = 0
    if init.success:
        for a, det, true_idx in views:
            asg = idf.assign(det, a)
            got = asg.ids >= 0
            n += int(np.sum(got))
            right += int(np.sum(asg.ids[got] == case["ids"][true_idx[got]]))
            # helix49 turned upside down is itself relabelled i -> N - 1 - i: that labelling is legitimate
            right_flip += int(np.sum(asg.ids[got] == case["ids"][::-1][true_idx[got]]))
    return init, max(right, right_flip), n, sum(len(v[1]) for v in views)


@pytest.mark.parametrize("seed,lean_deg,direction_deg", [(9601, 5.0, 30.0), (9602, 8.0, 200.0)])
def test_leaning_object_identified(seed, lean_deg, direction_deg):
    case = leaning_case(seed, lean_deg, direction_deg)
    init, right, n, total = identify_case(case, seed)
    assert init.success, init.message
    # every assigned id right, and nearly every detection assigned
    assert right == n >= 0.95 * total, (right, n, total, init.message)
    # the identification pose leans as the object does (to within 1 deg; it is a nominal-instrument model)
    a_true = identify.object_rotation(*case["inst"].w[10:13]) @ np.array([0.0, 1.0, 0.0])
    a_fit = identify.object_rotation(*init.estimate[10:13]) @ np.array([0.0, 1.0, 0.0])
    assert math.degrees(math.acos(min(1.0, abs(float(a_true @ a_fit))))) < 1.0, init.message


def test_arc_of_the_initialisation_frames():
    assert identify._arc_deg([0.3]) == 0.0
    assert abs(identify._arc_deg(np.deg2rad([10.0, 11.0, 12.0])) - 2.0) < 1e-9
    assert abs(identify._arc_deg(np.deg2rad([355.0, 2.0])) - 7.0) < 1e-9        # across 0
    assert abs(identify._arc_deg(np.deg2rad(np.arange(0.0, 360.0, 10.0))) - 350.0) < 1e-9


def test_upright_object_from_three_frames_over_four_degrees():
    """Three initialisation frames over 4 deg run the lean vote (lean_min_arc_deg 1) and find the upright object
    upright with every sphere labelled right. One frame does not observe the lean (round 21: the upright object
    was refused as leaning 23 deg from one frame): the upright search takes it, as tests/ros/test_ct_nodes.py
    does with init_frames 1 (on this independent instrument one frame labels 3 of 33 detections wrong, with or
    without the lean search: init_frames 1 is not safe, the default is 6)."""
    frames, step, first = 3, 2, 0
    case = bench.gen.draw_case(9601, cols=384, n_views=180, vary_physics=False, object_tilt_deg=0.0)
    inst = case["inst"]
    views = bench.ideal_detections(case, np.random.default_rng(9601 + 10**6), 0.02, 0.6, 0.04)
    sel = [views[first + i * step] for i in range(frames)]
    idf = identify.SphereIdentifier(case["ids"], case["c_file"], case["diam"],
                                    DetectorSpec(inst.cols, inst.rows, inst.pitch_m), inst.sdd_reported_m)
    init = idf.initialise([v[1] for v in sel], [v[0] for v in sel], inst.srd_reported_m)
    assert init.success, init.message
    a_fit = identify.object_rotation(*init.estimate[10:13]) @ np.array([0.0, 1.0, 0.0])
    assert math.degrees(math.acos(min(1.0, abs(float(a_fit[1]))))) < 1.0, init.message
    right = n = 0
    for a, det, true_idx in views[::15]:
        asg = idf.assign(det, a)
        got = asg.ids >= 0
        n += int(np.sum(got))
        right += max(int(np.sum(asg.ids[got] == case["ids"][true_idx[got]])),
                     int(np.sum(asg.ids[got] == case["ids"][::-1][true_idx[got]])))
    assert right == n > 0, (right, n, init.message)
