"""The Pixel Probe calibration node over DDS with a lens distortion its CameraInfo does not carry
(camera simulator hidden_distortion:=true, k1 = -0.3, D = 0 published): the grid session is
calibrated, the discrepancy engine names the missing lens k1, the calibration is published
POOR_FIT, and the calibration file plant software reads keeps the good calibration it held
(nothing poor is written over it). ~2-3 min: 33 stations."""
import pytest

pytestmark = [pytest.mark.ros, pytest.mark.slow]


def test_poor_fit_calibration_is_published_but_not_written(start_node, ros_node, tmp_path):
    from metro_msgs.msg import DiscrepancyReport, PicmsCalibration, SolveStatus
    from metro_msgs.srv import RunPicmsCalibration

    from ct_calib_nodes.nodes.runner import QOS_LATCHED

    out = tmp_path / "picms_calibration.yaml"
    out.write_text("good: calibration\n")
    seed = ["-p", "cell_seed:=8"]
    start_node("picms_nodes", "picms_stage_sim")
    start_node("picms_nodes", "picms_camera_sim", "--ros-args", *seed, "-p", "hidden_distortion:=true",
               "-p", "distortion_k1:=-0.3")
    start_node("picms_nodes", "picms_tracker_sim", "--ros-args", *seed)
    cal = start_node("picms_nodes", "picms_calibration", "--ros-args", "-p", f"output_file:={out}",
                     "-p", "pattern:=grid", "-p", "dwell_s:=1.0")
    msgs, reps = [], []
    ros_node.create_subscription(PicmsCalibration, "/picms/calibration", msgs.append, QOS_LATCHED)
    ros_node.create_subscription(DiscrepancyReport, "/picms/discrepancy", reps.append, QOS_LATCHED)
    cli = ros_node.create_client(RunPicmsCalibration, "/picms/run_calibration")
    assert ros_node.spin_until(cli.service_is_ready, timeout=60), cal.log()
    fut = cli.call_async(RunPicmsCalibration.Request(write_file=True))
    assert ros_node.spin_until(fut.done, timeout=420), cal.log()[-3000:]
    r = fut.result()
    assert r.success, r.message                                # calibrated: the solve itself ran
    assert ros_node.spin_until(lambda: msgs and reps, timeout=30), cal.log()[-3000:]
    m, rep = msgs[-1], reps[-1]
    assert m.status.code == SolveStatus.POOR_FIT, m.status
    assert m.file_path == ""
    assert not rep.adequate
    assert "lens_radial_k1" in [f.term for f in rep.findings], rep.verdict
    assert out.read_text() == "good: calibration\n"            # the good file stands
    assert "not written: POOR_FIT" in cal.log()
