"""Pixel Probe targeting (core/cellio.py, core/targeting.py) against the simulator's truth.

Triangulation is checked on exact projections with known pixel noise (z-scores over many
points, two cells); drive_to on rendered frames of the chrome-targets plate in the cells that
the shared calibration sessions calibrated (conftest `sessions`), with the probe built from the
calibration only. Tolerances come from the stated covariances (4 sigma) or the stage step.
"""
import numpy as np
import pytest

from picms_nodes.core import camera, cell, cellio, scenes, targeting
from picms_nodes.core.instruments import StageSim
from picms_nodes.io.files import calibration_dict
from picms_nodes.measure_sim import truth_probe


def probe_of(session):
    rec, st, res, _ = session
    return targeting.Probe.from_calibration_yaml(calibration_dict(res), rec.camera_info), st.truth


def roi_at(truth, q, p_stage, half_px):
    out = {}
    for j, c in enumerate(truth.cameras):
        u = camera.project(truth.camera_pose_at(j, q), c.true_intrinsics, p_stage)[0]
        out[c.name] = (u[0] - half_px, u[1] - half_px, u[0] + half_px, u[1] + half_px)
    return out


@pytest.mark.parametrize("seed", [3, 4])
def test_triangulation_accuracy_and_covariance(seed):
    rng = np.random.default_rng(seed)
    truth = cell.make_cell(rng, cell.make_physics(rng))
    probe = truth_probe(truth, sigma_px=1e-4)
    A = truth.A_travel
    sig = 0.2
    z, dlt_err = [], []
    for _ in range(150):
        P = rng.uniform(-1e-3, 1e-3, 3)
        px = {c.name: (*(camera.project(c.pose, c.true_intrinsics, P)[0] + rng.normal(0, sig, 2)), sig)
              for c in truth.cameras}
        tri = targeting.triangulate(probe, px)
        e = tri.offset_stage - P
        z.append(np.linalg.solve(np.linalg.cholesky(tri.cov), e))
        dlt_err.append(np.linalg.norm(tri.dlt_point_body - probe.xstar_body - P))
        assert tri.rms_px < 5 * sig
    # the vectorised form gives the same points
    Ps = rng.uniform(-1e-3, 1e-3, (20, 3))
    pxs = {c.name: camera.project(c.pose, c.true_intrinsics, Ps) + rng.normal(0, sig, (20, 2)) for c in truth.cameras}
    many = targeting.triangulate_many(probe, pxs, sig)[0]
    one = [targeting.triangulate(probe, {c: (*pxs[c][i], sig) for c in pxs}).offset_stage for i in range(20)]
    assert np.allclose(many, one, atol=1e-10)
    z = np.array(z)
    # whitened errors: unit variance per component (150 x 3 samples: sd within ~15 %)
    assert 0.8 < z.std() < 1.2, z.std(0)
    assert np.all(np.abs(z.mean(0)) < 0.35)
    # the pixel-weighted DLT is already close; GN refines
    assert np.median(dlt_err) < 3 * np.sqrt(np.trace(tri.cov))
    assert np.allclose(probe.xstar_stage([1e-3, 0, 0]), A[:, 0] * 1e-3, atol=1e-12)


def test_triangulation_bad_input():
    truth = cell.make_cell(np.random.default_rng(5))
    probe = truth_probe(truth)
    with pytest.raises(targeting.TargetingError, match="at least two cameras"):
        targeting.triangulate(probe, {"camera_1": (1000.0, 900.0)})
    with pytest.raises(targeting.TargetingError, match="not a calibrated camera"):
        targeting.triangulate(probe, {"camera_1": (1000.0, 900.0), "camera_9": (1.0, 2.0)})
    with pytest.raises(targeting.TargetingError, match="finite"):
        targeting.triangulate(probe, {"camera_1": (1000.0, np.nan), "camera_2": (1.0, 2.0)})


def test_simcell_settles_from_encoders_and_times_out():
    truth = cell.make_cell(np.random.default_rng(6))
    sc = cellio.SimCell(truth, np.random.default_rng(1), None, window_px=20)
    s = sc.move_and_settle([0.0012, -0.0007, 0.0003])
    # settled: the mean encoder reading is the quantised target; the ringing had decayed
    assert np.allclose(s.q, sc.stage.quantise([0.0012, -0.0007, 0.0003]), atol=1.5e-7)
    assert set(s.images) == set(sc.camera_names) and all(v.dtype == np.uint8 for v in s.images.values())
    assert min(s.tracker_n.values()) >= 4 and len(s.tracker) == 5
    sc2 = cellio.SimCell(truth, np.random.default_rng(1), None, window_px=20,
                         stage=StageSim(never_settles=True))
    with pytest.raises(TimeoutError, match="did not settle"):
        sc2.move_and_settle([0.001, 0.0, 0.0], timeout_s=3.0)


def test_window_render_matches_full_frame():
    from picms_nodes.core import render
    truth = cell.make_cell(np.random.default_rng(7))
    part = scenes.chrome_targets()
    c = truth.cameras[1]
    fa = render.render_frame(c.pose, c.true_intrinsics, truth.physics, np.random.default_rng(2), part=part)
    centre = camera.project(c.pose, c.true_intrinsics, np.zeros(3))[0]
    fb, (x0, y0, w, h) = cellio.render_window(c.pose, c.true_intrinsics, truth.physics, np.random.default_rng(3),
                                              centre, 60, part=part)
    assert fb.shape == fa.shape and (w, h) == (121, 121)
    a, b = fa[y0:y0 + h, x0:x0 + w].astype(float), fb[y0:y0 + h, x0:x0 + w].astype(float)
    # same scene, levels and vignetting: the difference is noise only (two independent draws)
    assert abs(a.mean() - b.mean()) < 1.0 and np.abs(cv2_blur(a) - cv2_blur(b)).max() < 12


def cv2_blur(a):
    import cv2
    return cv2.blur(a, (5, 5))


@pytest.mark.parametrize("k", [0, 1])
def test_drive_to_dots_stage_and_tracker_modes(sessions, k):
    probe, truth = probe_of(sessions[k])
    rng = np.random.default_rng(40 + k)
    part = scenes.chrome_targets((2e-4, -1e-4, 1e-4), (0.004, -0.003), 0.1)
    grid = [f for f in scenes.part_truth(part)["features"] if f["id"] == "grid"][0]
    sc = cellio.SimCell(truth, rng, part, window_px=90)
    for d in (6, 18):
        P = grid["dots_stage"][d]
        s0 = sc.move_and_settle(probe.move_for(P + [3e-4, -2e-4, 1e-4]))
        loc = targeting.circle_feature_locator(roi_at(truth, s0.q, P, 20), 250e-6)
        its = []
        r = targeting.drive_to(sc, probe, loc, start=s0, progress=its.append)
        assert r.ok, r.reason
        assert len(its) == len(r.iterations) and 2 <= len(r.iterations) <= 4
        assert np.linalg.norm(r.offset_stage) <= sc.resolution_m
        e = r.p_stage - P
        assert np.all(np.abs(e) < 4 * np.sqrt(np.diag(r.cov_stage)) + 0.3e-6), (e, np.diag(r.cov_stage))
        assert np.linalg.norm(e) < 3e-6
        et = r.p_tracker - truth.to_tracker(P)[0]
        assert np.all(np.abs(et) < 4 * np.sqrt(np.diag(r.cov_tracker))), (et, np.diag(r.cov_tracker))


def test_resolution_limit_not_chased(sessions):
    """A coarse 25 um stage: moves below one step are not commanded; the point is X*(q) plus the
    triangulated remainder, so its error stays far below the step."""
    probe, truth = probe_of(sessions[0])
    part = scenes.chrome_targets((8e-6, -9e-6, 5e-6))
    P = [f for f in scenes.part_truth(part)["features"] if f["id"] == "grid"][0]["dots_stage"][12]
    sc = cellio.SimCell(truth, np.random.default_rng(9), part, window_px=90, stage=StageSim(resolution_m=25e-6))
    s0 = sc.current()
    r = targeting.drive_to(sc, probe, targeting.circle_feature_locator(roi_at(truth, s0.q, P, 20), 250e-6),
                           tol_m=1e-6, start=s0)
    assert r.ok and "resolution limit" in r.reason, r.reason
    assert r.n_moves == 0 and sc.n_moves == 0           # 8, 9, 5 um offsets round to no 25 um step
    assert np.linalg.norm(r.offset_stage) > 8e-6
    assert np.linalg.norm(r.p_stage - P) < 2.5e-6       # X*(q) alone would be 13 um off
    assert np.linalg.norm(probe.xstar_stage(r.q) - P) > 10e-6


def test_direct_mode_predicts_third_view_and_rejects_inconsistent(sessions):
    probe, truth = probe_of(sessions[1])
    part = scenes.chrome_targets((1e-4, 2e-4, 0.0))
    sq = [f for f in scenes.part_truth(part)["features"] if f["id"] == "grid"][0]
    P = sq["dots_stage"][8]
    rng = np.random.default_rng(12)
    sc = cellio.SimCell(truth, rng, part, window_px=90)
    s0 = sc.move_and_settle(probe.move_for(P + [2e-4, 1e-4, 0.0]))
    true_px = {c.name: camera.project(truth.camera_pose_at(j, s0.q), c.true_intrinsics, P)[0]
               for j, c in enumerate(truth.cameras)}
    given = {n: true_px[n] + rng.normal(0, 0.2, 2) for n in ("camera_1", "camera_2")}
    loc = targeting.direct_locator(given)
    r = targeting.drive_to(sc, probe, loc, start=s0)
    assert r.ok, r.reason
    assert loc.state["checked"] == ["camera_3"]
    assert loc.state.get("matched", 0) >= 3           # later iterations re-found the templates
    first = r.iterations[0]
    pred3 = probe.pixels_of_offset(first["offset"])["camera_3"]
    assert np.linalg.norm(pred3 - true_px["camera_3"]) < 1.5          # 0.2 px clicks, calibration errors
    assert np.linalg.norm(r.p_stage - P) < 15e-6                      # a clicked point: click noise ~ 5 um
    bad = dict(given, camera_2=given["camera_2"] + [0.0, 8.0])        # 8 px off the epipolar line
    with pytest.raises(targeting.TargetingError, match="inconsistent"):
        targeting.direct_locator(bad)(s0, probe)


def test_circle_centre_perspective_shift():
    """The image-ellipse centre of a 7 mm circle is not the image of its centre (tenths of a
    pixel here); the 250 um dots' shift is negligible. Checked against the true projection."""
    truth = cell.make_cell(np.random.default_rng(8))
    probe = truth_probe(truth)
    for rad, lo, hi in ((3.5e-3, 0.05, 2.0), (125e-6, 0.0, 5e-3)):
        for j, c in enumerate(truth.cameras):
            b = targeting.projected_circle_centre_bias(probe, c.name, np.zeros(3), (0, 0, 1), rad)
            a = np.linspace(0, 2 * np.pi, 200, endpoint=False)
            pts = camera.project(c.pose, c.true_intrinsics, np.column_stack([rad * np.cos(a), rad * np.sin(a), 0 * a]))
            ce = targeting._fit_ellipse(pts)[0]
            ref = ce - camera.project(c.pose, c.true_intrinsics, np.zeros(3))[0]
            assert lo <= np.linalg.norm(b) <= hi
            assert np.linalg.norm(b - ref) < 0.02 * max(np.linalg.norm(ref), 1e-3)



def test_feature_mode_dark_field_hole(sessions):
    """A 2 mm pin hole of the flange in dark field (dark hole inside a bright edge band on a
    dark face), tilted plate: X* on the hole's centre within the stated uncertainty."""
    probe, truth = probe_of(sessions[0])
    part = scenes.flange_face((2e-4, -1e-4, 1e-4), (0.003, -0.002), 0.2)
    pt = scenes.part_truth(part)
    f = [f for f in pt["features"] if f["id"] == "pin_1"][0]
    P = f["center_stage"]
    sc = cellio.SimCell(truth, np.random.default_rng(13), part, window_px=100)
    s0 = sc.move_and_settle(probe.move_for(P + [2e-4, -1.5e-4, 0.0]))
    r_px = f["diameter"] / 2 / probe.mm_per_px("camera_1")
    loc = targeting.circle_feature_locator(roi_at(truth, s0.q, P, r_px + 20), f["diameter"],
                                           plane_normal_stage=pt["normal_stage"])
    r = targeting.drive_to(sc, probe, loc, start=s0)
    assert r.ok, r.reason
    e = r.p_stage - P
    assert np.all(np.abs(e) < 4 * np.sqrt(np.diag(r.cov_stage)) + 0.3e-6), (e, np.diag(r.cov_stage))
    assert np.linalg.norm(e) < 2e-6
