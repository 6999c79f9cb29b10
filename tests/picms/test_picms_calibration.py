"""Pixel Probe calibration against the simulator's truth (two cells, varied physics).

Tolerances are 4 sigma of the uncertainty the calibration itself states (per axis), so these
tests check the estimates AND the stated uncertainties; the z-score statistics over many
seeds are in tests/benchmarks/validate_picms_calibration.py.
"""
import copy

import numpy as np
import pytest

from picms_nodes.core import camera, cell
from picms_nodes.core.calibrate import CalibrationError, calibrate, constellation_frame, travel_matrix


def test_probe_point_and_pixels(sessions):
    for rec, st, res, rep in sessions:
        c = st.truth
        # frames taken mid-move were seen and not used
        assert rep.n_frames > rep.n_settled_frames == rep.n_detected
        x_true = c.to_tracker(c.smr_star_stage)[0]
        u = np.sqrt(np.diag(res.cov_p_tracker))
        assert np.all(np.abs(res.p_tracker - x_true) < 4 * u), (res.p_tracker - x_true, u)
        for name, px in res.pixels.items():
            err = px - st.x_star_px[name]
            assert np.all(np.abs(err) < 4 * res.u_pixels[name] + 0.005), (name, err, res.u_pixels[name])
        # tracker noise estimated from the data vs the stated (15 um + 6 um/m) / 2
        assert abs(res.tracker_sigma_m / c.tracker_sigma_m() - 1) < 0.1


def test_constellation_frame_holds_x_star(sessions):
    rec, st, res, rep = sessions[0]
    c = st.truth
    # re-measure the constellation (truth, stage elsewhere): X* follows from the frame
    q = np.array([0.002, -0.001, 0.0005])
    pts = np.array([c.to_tracker(c.body_point_stage(c.constellation_stage[n], q))[0] for n in res.constellation])
    R, o = constellation_frame(pts)
    x_pred = o + R @ res.p_constellation
    x_true = c.to_tracker(c.probe_point_stage(q))[0]
    u = np.sqrt(np.trace(res.cov_p_constellation))
    assert np.linalg.norm(x_pred - x_true) < 4 * u + 1e-6


def test_stage_axes(sessions):
    for rec, st, res, rep in sessions:
        c = st.truth
        sq = cell.squareness_truth(c.A_travel)
        for k in sq:
            assert abs(res.squareness_rad[k] - sq[k]) < 4 * res.u_squareness_rad[k], k
        # stage x axis seen by the tracker: within the tracker's resolution of a short travel
        ang = camera.rotation_angle_rad(res.R_tracker_stage, c.R_tracker_stage)
        assert ang < 2e-3
        assert np.allclose(travel_matrix([sq["xy"], sq["xz"], sq["yz"]]), c.A_travel, atol=1e-12)


def test_camera_poses(sessions):
    for rec, st, res, rep in sessions:
        c = st.truth
        assert 0.3 < res.chi2_dof < 3.0
        for j, name in enumerate(sorted(res.cameras)):
            cr, ct = res.cameras[name], c.cameras[j]
            dc = cr.p_stage_centre - ct.pose.p_stage_centre
            assert np.all(np.abs(dc) < 4 * cr.u_p_stage_centre), (name, dc, cr.u_p_stage_centre)
            rv = cr.R_stage_camera @ camera.matrix_to_rotvec(ct.pose.R_stage_camera.T @ cr.R_stage_camera)
            assert np.all(np.abs(rv) < 4 * cr.u_rotation_rad), (name, rv, cr.u_rotation_rad)
            assert cr.reprojection_rms_px < 0.05
            # solvePnP (unweighted) on the same data lands close to the joint GLS
            assert camera.rotation_angle_rad(cr.pnp_R_stage_camera, cr.R_stage_camera) < 1e-4


def _stations(rec):
    from picms_nodes.core.calibrate import assign, settled_windows
    from picms_nodes.core.pipeline import PipelineReport, detect_settled_frames
    w = settled_windows(rec.joint_stamps_ns, rec.joint_positions)
    dets = detect_settled_frames(rec.frames, rec.camera_info, w, PipelineReport())
    return w, dets


@pytest.fixture(scope="module")
def station_data(sessions):
    rec = sessions[0][0]
    return rec, _stations(rec)


def test_bad_inputs_named(station_data):
    from picms_nodes.core.calibrate import assign
    rec, (w, dets) = station_data
    ok = calibrate(assign(w, dets, rec.tracker), rec.camera_info, rec.cell)
    assert ok.success
    # fewer than 3 constellation SMRs
    few = [r for r in rec.tracker if r[1] not in ("smr_3", "smr_4", "smr_5")]
    with pytest.raises(CalibrationError, match="fewer than 3"):
        calibrate(assign(w, dets, few), rec.camera_info, rec.cell)
    # collinear constellation: every SMR reading moved onto one line
    lin = []
    for stamp, name, p in rec.tracker:
        if name.startswith("smr_") and name != "smr_star":
            k = int(name[-1])
            p = np.array([1.0, 2.0, 0.5]) + k * np.array([0.03, 0.01, 0.0]) + (p - p.round(2)) * 1e-3
        lin.append((stamp, name, p))
    with pytest.raises(CalibrationError, match="collinear"):
        calibrate(assign(w, dets, lin), rec.camera_info, rec.cell)
    # missing CameraInfo
    with pytest.raises(CalibrationError, match="CameraInfo missing"):
        calibrate(assign(w, dets, rec.tracker), {"camera_1": rec.camera_info["camera_1"]}, rec.cell)
    # no SMR*
    nostar = [r for r in rec.tracker if r[1] != "smr_star"]
    with pytest.raises(CalibrationError, match="SMR"):
        calibrate(assign(w, dets, nostar), rec.camera_info, rec.cell)
    # no tracker readings at the first (reference) station: X* moves to the next station's reading,
    # and the result says so (a live node whose tracker subscriptions matched late did this silently)
    late = [r for r in rec.tracker if not (w[0].start_ns <= r[0] <= w[0].end_ns)]
    moved = calibrate(assign(w, dets, late), rec.camera_info, rec.cell)
    assert not np.allclose(moved.stage_reading, ok.stage_reading)
    assert np.allclose(moved.stage_reading, w[1].q)
    assert "X* is defined at the reading" in moved.message and "X* is defined" not in ok.message


def test_stage_that_never_settles():
    from picms_nodes.core.calibrate import settled_windows
    from picms_nodes.core.instruments import StageSim
    st = StageSim(never_settles=True)
    st.command([0.002, 0, 0], 0.1)
    t = np.arange(0, 5, 0.02)
    q = np.array([st.encoder(x) for x in t])
    assert settled_windows((t * 1e9).astype(np.int64), q) == []
    from picms_nodes.core.campaign import Recording
    from picms_nodes.core.pipeline import calibrate_recording
    rec = Recording(cell={}, joint_stamps_ns=(t * 1e9).astype(np.int64), joint_positions=q)
    with pytest.raises(CalibrationError, match="never settled"):
        calibrate_recording(rec)
