"""PiCMS nodes in their own processes: the stage simulator obeys, quantises, settles and ignores
bad commands; the calibration node, asked over its service with a stage that never settles,
answers with the cause, publishes a failure latched, and writes nothing over a good file."""
import numpy as np
import pytest

pytestmark = pytest.mark.ros


def test_stage_sim_moves_settles_and_ignores_bad_commands(start_node, ros_node):
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    node = start_node("picms_nodes", "picms_stage_sim", "--ros-args", "-p", "resolution_m:=6e-6")
    got = []
    ros_node.create_subscription(JointState, "/picms/stage/joint_states", got.append, qos_profile_sensor_data)
    pub = ros_node.create_publisher(JointTrajectory, "/picms/stage/command", 10)
    assert ros_node.spin_until(lambda: got and pub.get_subscription_count() > 0, timeout=30), node.log()

    def cmd(names, pos):
        m = JointTrajectory()
        m.joint_names = names
        p = JointTrajectoryPoint()
        p.positions = pos
        m.points = [p]
        pub.publish(m)

    cmd(["x", "y"], [0.001, 0.0])                          # bad: two joints
    cmd(["x", "y", "z"], [0.5, 0.0, 0.0])                  # bad: beyond the travel
    cmd(["z", "x", "y"], [-0.0010004, 0.0020031, 0.0])     # good, names in another order
    ros_node.spin_until(lambda: False, timeout=3.5)
    q = np.array([[m.position[m.name.index(n)] for n in "xyz"] for m in got[-10:]])
    assert np.allclose(q, [0.002004, 0.0, -0.001002], atol=2e-7)   # quantised to 6 um steps, settled
    log = node.log()
    assert "ignored stage command" in log and "travel limit" in log


def test_calibration_service_names_unsettled_stage_and_keeps_file(start_node, ros_node, tmp_path):
    from metro_msgs.msg import PicmsCalibration, SolveStatus
    from metro_msgs.srv import RunPicmsCalibration

    from ct_calib_nodes.nodes.runner import QOS_LATCHED

    out = tmp_path / "picms_calibration.yaml"
    out.write_text("good: calibration\n")
    start_node("picms_nodes", "picms_stage_sim", "--ros-args", "-p", "never_settles:=true")
    start_node("picms_nodes", "picms_camera_sim", "--ros-args", "-p", "rate_hz:=0.5")
    cal = start_node("picms_nodes", "picms_calibration", "--ros-args", "-p", f"output_file:={out}",
                     "-p", "settle_timeout_s:=6.0")
    from sensor_msgs.msg import CameraInfo
    infos = set()
    for k in (1, 2, 3):
        ros_node.create_subscription(CameraInfo, f"/picms/camera_{k}/camera_info", lambda m, k=k: infos.add(k), QOS_LATCHED)
    assert ros_node.spin_until(lambda: len(infos) == 3, timeout=60)     # cameras up (else the cause differs)
    msgs = []
    ros_node.create_subscription(PicmsCalibration, "/picms/calibration", msgs.append, QOS_LATCHED)
    cli = ros_node.create_client(RunPicmsCalibration, "/picms/run_calibration")
    assert ros_node.spin_until(cli.service_is_ready, timeout=30), cal.log()
    fut = cli.call_async(RunPicmsCalibration.Request(write_file=True))
    assert ros_node.spin_until(fut.done, timeout=90), cal.log()
    r = fut.result()
    assert not r.success and "never settled" in r.message, r.message
    assert ros_node.spin_until(lambda: msgs, timeout=10)
    assert msgs[-1].status.code == SolveStatus.FAILED
    assert out.read_text() == "good: calibration\n"


def test_calibration_without_tracker_names_what_is_missing(start_node, ros_node, tmp_path):
    """Stage and cameras but no tracker: the first station settles with frames, and the calibration
    stops there naming the missing readings (before, it moved on, and a reference station without
    the tracker's readings moved X* to the next station's reading)."""
    from metro_msgs.srv import RunPicmsCalibration

    out = tmp_path / "picms_calibration.yaml"
    start_node("picms_nodes", "picms_stage_sim")
    start_node("picms_nodes", "picms_camera_sim", "--ros-args", "-p", "rate_hz:=2.0")
    cal = start_node("picms_nodes", "picms_calibration", "--ros-args", "-p", f"output_file:={out}",
                     "-p", "settle_timeout_s:=8.0", "-p", "dwell_s:=1.0")
    cli = ros_node.create_client(RunPicmsCalibration, "/picms/run_calibration")
    assert ros_node.spin_until(cli.service_is_ready, timeout=30), cal.log()
    fut = cli.call_async(RunPicmsCalibration.Request(write_file=True))
    assert ros_node.spin_until(fut.done, timeout=90), cal.log()
    r = fut.result()
    assert not r.success and "station 0" in r.message and "no reading of the probe SMR" in r.message, r.message
    assert "settled, but" in r.message and "never settled" not in r.message, r.message
    assert not out.exists()


def test_namespace_moves_the_stage_and_its_command(start_node, ros_node):
    """Relative names: under __ns:=/cell_b the stage listens and publishes in /cell_b only."""
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import JointState
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

    node = start_node("picms_nodes", "picms_stage_sim", "--ros-args", "-r", "__ns:=/cell_b",
                      "-p", "resolution_m:=6e-6")
    in_ns, in_root = [], []
    ros_node.create_subscription(JointState, "/cell_b/picms/stage/joint_states", in_ns.append, qos_profile_sensor_data)
    ros_node.create_subscription(JointState, "/picms/stage/joint_states", in_root.append, qos_profile_sensor_data)
    pub = ros_node.create_publisher(JointTrajectory, "/cell_b/picms/stage/command", 10)
    assert ros_node.spin_until(lambda: in_ns and pub.get_subscription_count() > 0, timeout=30), node.log()
    m = JointTrajectory()
    m.joint_names = ["x", "y", "z"]
    m.points = [JointTrajectoryPoint(positions=[0.0012, 0.0, 0.0])]
    pub.publish(m)
    ros_node.spin_until(lambda: False, timeout=3.5)
    x = [s.position[s.name.index("x")] for s in in_ns[-5:]]
    assert np.allclose(x, 0.0012, atol=2e-7), x             # 200 steps of 6 um, settled
    assert not in_root                                     # nothing leaks into the root namespace


def test_camera_sim_scene_parameter_renders_the_flange(start_node, ros_node):
    from sensor_msgs.msg import Image

    from ct_calib_nodes.nodes.runner import QOS_RELIABLE_STREAM

    start_node("picms_nodes", "picms_stage_sim")
    cam = start_node("picms_nodes", "picms_camera_sim", "--ros-args", "-p", "rate_hz:=1.0", "-p", "scene:=flange",
                     "-p", "cameras:=[camera_2]", "-p", "part_rotation_rad:=0.3")
    imgs = []
    ros_node.create_subscription(Image, "/picms/camera_2/image_raw", imgs.append, QOS_RELIABLE_STREAM)
    assert ros_node.spin_until(lambda: imgs, timeout=60), cam.log()
    a = np.frombuffer(bytes(imgs[0].data), np.uint8).reshape(imgs[0].height, imgs[0].width)
    # dark field: a dark face with bright edge bands (the SMR scene is a bright back-light)
    assert np.median(a) < 25 and np.percentile(a, 99.9) > 60
    assert "scene flange" in cam.log()
