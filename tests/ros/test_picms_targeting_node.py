"""The targeting node over real DDS with the stage, camera and tracker simulators in their own
processes: a Feature Mode goal on a 250 um dot of the chrome targets drives X* onto it with
per-iteration feedback and returns the point in the stage and tracker frames; a Direct Mode
goal with inconsistent pixels is aborted with the cause.

The calibration file given to the node is written here from the simulated cell's TRUE geometry
(this test is about the node and RosCell plumbing; the calibration's own accuracy and the
targeting accuracy with a calibrated probe are tested in tests/picms)."""
import numpy as np
import pytest
import yaml

pytestmark = pytest.mark.ros

SEED = 8
PART_POS = (1.6e-4, -1.1e-4, 0.0)


def truth_calibration(truth):
    from picms_nodes.core import camera, cell
    from picms_nodes.core.calibrate import constellation_frame
    names = list(truth.constellation_stage)
    pts = np.array([truth.to_tracker(truth.constellation_stage[n])[0] for n in names])
    R, o = constellation_frame(pts)
    xs = truth.to_tracker(np.zeros(3))[0]
    sq = cell.squareness_truth(truth.A_travel)
    return {
        "units": "SI",
        "probe_point": {
            "pixels": {c.name: camera.project(c.pose, c.true_intrinsics, np.zeros(3))[0].tolist() for c in truth.cameras},
            "u_pixels": {c.name: [0.02, 0.02] for c in truth.cameras},
            "p_tracker": xs.tolist(), "stage_reading": [0.0, 0.0, 0.0], "cov_p_tracker": (np.eye(3) * 1e-12).tolist(),
            "p_constellation": (R.T @ (xs - o)).tolist(), "cov_p_constellation": (np.eye(3) * 1e-12).tolist(),
            "constellation": {n: (R.T @ (p - o)).tolist() for n, p in zip(names, pts)},
        },
        "cameras": {c.name: {"R_stage_camera": c.pose.R_stage_camera.tolist(),
                             "p_stage_centre": c.pose.p_stage_centre.tolist(),
                             "u_rotation_rad": [1e-5] * 3, "u_p_stage_centre": [1e-6] * 3,
                             "reprojection_rms_px": 0.0} for c in truth.cameras},
        "stage": {"R_tracker_stage": truth.R_tracker_stage.tolist(), "squareness_rad": sq,
                  "u_squareness_rad": {k: 1e-6 for k in sq}},
        "quality": {"tracker_sigma_m": truth.tracker_sigma_m()},
    }


def test_drive_probe_action_feature_and_direct_modes(start_node, ros_node, tmp_path):
    from metro_msgs.action import DriveProbe
    from ros_actions import GoalClient
    from picms_nodes.core import camera, cell, scenes

    truth = cell.cell_from_seed(SEED)
    cal = tmp_path / "picms_calibration.yaml"
    cal.write_text(yaml.safe_dump(truth_calibration(truth)))
    part = scenes.chrome_targets(PART_POS)
    dot = [f for f in scenes.part_truth(part)["features"] if f["id"] == "grid"][0]["dots_stage"][12]
    pos = ",".join(repr(float(v)) for v in PART_POS)
    start_node("picms_nodes", "picms_stage_sim", "--ros-args", "-p", "rate_hz:=100.0")
    cams = start_node("picms_nodes", "picms_camera_sim", "--ros-args", "-p", f"cell_seed:={SEED}", "-p", "rate_hz:=2.0",
                      "-p", "scene:=chrome_targets", "-p", f"part_position:=[{pos}]")
    start_node("picms_nodes", "picms_tracker_sim", "--ros-args", "-p", f"cell_seed:={SEED}",
               "-p", "smr_star_present:=false")
    tgt = start_node("picms_nodes", "picms_targeting", "--ros-args", "-p", f"calibration_file:={cal}",
                     # 5 MP renders on a loaded CI machine: "CameraInfo missing within 20 s" happened (round 21)
                     "-p", "frame_timeout_s:=60.0", "-p", "ready_timeout_s:=60.0")
    client = GoalClient(ros_node, DriveProbe, "/picms/drive_probe")   # survives a lost goal response
    assert client.wait_for_server(timeout=40), tgt.log()

    def run(goal, timeout=90):
        fb = []
        gh = client.send_goal(goal, feedback_callback=lambda m: fb.append(m.feedback), timeout=30)
        assert gh is not None and gh.accepted, tgt.log()
        rf = gh.get_result_async()
        assert ros_node.spin_until(rf.done, timeout=timeout), tgt.log() + cams.log()
        return rf.result().result, fb

    names = [c.name for c in truth.cameras]
    rois = []
    for c in truth.cameras:
        u = camera.project(c.pose, c.true_intrinsics, dot)[0]
        rois += [u[0] - 20, u[1] - 20, u[0] + 20, u[1] + 20]
    res, fb = run(DriveProbe.Goal(mode="circle", cameras=names, rois=rois, diameter=250e-6))
    assert res.success, res.message + tgt.log()
    assert len(fb) == res.iterations >= 2
    assert np.linalg.norm(fb[0].offset) > 100e-6 and list(fb[0].move_steps) != [0, 0, 0]
    assert np.linalg.norm(res.offset_stage) <= 6e-6
    e = np.array(res.p_stage) - dot
    assert np.linalg.norm(e) < 3e-6, e           # true geometry: pixel noise of the dot edges only
    assert res.has_tracker
    et = np.array(res.p_tracker) - truth.to_tracker(dot)[0]
    sd = np.sqrt(np.diag(np.reshape(res.cov_tracker, (3, 3))))
    assert np.all(np.abs(et) < 4 * sd), (et, sd)
    # Direct Mode with pixels whose rays miss each other: aborted with the cause, nothing moves
    px = [camera.project(c.pose, c.true_intrinsics, dot)[0] for c in truth.cameras[:2]]
    bad = [px[0][0], px[0][1], px[1][0], px[1][1] + 10.0]
    res2, _ = run(DriveProbe.Goal(mode="direct", cameras=names[:2], pixels=bad))
    assert not res2.success and "inconsistent" in res2.message, res2.message
    # a malformed goal is rejected at once
    gh = client.send_goal(DriveProbe.Goal(mode="direct", cameras=["camera_1"], pixels=[1.0, 2.0]), timeout=20)
    assert gh is not None and not gh.accepted
    assert "goal rejected" in tgt.log()
    # cancel: accepted, honoured at the first iteration (the stage settled, before any move)
    from action_msgs.msg import GoalStatus
    fb = []
    gh = client.send_goal(DriveProbe.Goal(mode="circle", cameras=names, rois=rois, diameter=250e-6),
                          feedback_callback=lambda m: fb.append(m.feedback), timeout=30)
    assert gh is not None and gh.accepted
    cf = gh.cancel_goal_async()
    assert ros_node.spin_until(cf.done, timeout=20)
    assert len(cf.result().goals_canceling) == 1, "cancel refused"
    rf = gh.get_result_async()
    assert ros_node.spin_until(rf.done, timeout=90), tgt.log()
    res3 = rf.result().result
    assert rf.result().status == GoalStatus.STATUS_CANCELED, (rf.result().status, res3.message)
    assert "canceled after 1 iterations" in res3.message and res3.iterations == 1, res3.message
    assert len(res3.q) == 3                 # the settled position it stopped at
    if fb:
        assert np.allclose(res3.q, fb[-1].q)

