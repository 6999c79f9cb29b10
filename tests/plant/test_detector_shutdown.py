"""Stopping the detector while it holds frames (identity not yet initialised at the position) ends
cleanly: no traceback, the log says how many frames were not published."""
import re

import numpy as np
import pytest
import yaml
from builtin_interfaces.msg import Time
from sensor_msgs.msg import Image, JointState

from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.scenario import default_static_truth
from ct_calib_nodes.io import ct_files
from ct_calib_nodes.io.convert import image_from_array
from ct_calib_nodes.nodes.runner import QOS_RELIABLE_STREAM

pytestmark = pytest.mark.ros


def test_detector_stops_cleanly_with_frames_held(start_node, ros_node, tmp_path):
    inst_file = tmp_path / "ct_instrument.yaml"
    inst_file.write_text(yaml.safe_dump({"units": "SI", "source_to_detector": 1.04821, "detector": {
        "cols": 384, "rows": 384, "pixel_pitch": 0.00107, "flat_field_counts": 50000}}))
    inst = ct_files.load_instrument(inst_file)
    ref = ct_files.load_reference_object(ct_files.default_reference_object_path())
    det = start_node("ct_calib_nodes", "ct_sphere_detector", "--ros-args", "-p", f"instrument_file:={inst_file}")
    pi = ros_node.create_publisher(Image, "/ct/detector/image", QOS_RELIABLE_STREAM)
    pj = ros_node.create_publisher(JointState, "/ct/stage/joint_states", QOS_RELIABLE_STREAM)
    assert ros_node.spin_until(lambda: pi.get_subscription_count() and pj.get_subscription_count(), timeout=30)
    rng = np.random.default_rng(0)
    w = default_static_truth()
    for j in range(3):                    # 3 < init_frames (6): held for identity initialisation
        a = 2 * np.pi * j / 24
        frame = render_projection(w, np.zeros(6), a, ref, inst.detector, RenderSettings(), rng)
        stamp = Time(sec=10 + j)
        js = JointState(name=["rotary", "magnification"], position=[a, 0.364])
        js.header.stamp = stamp
        pj.publish(js)
        pi.publish(image_from_array(frame.image, stamp, "ct_detector"))
    ros_node.spin_until(lambda: False, timeout=3.0)
    code = det.stop()
    log = det.log()
    assert "Traceback" not in log and code == 0, log[-3000:]
    # every frame published is accounted for at the stop: paired frames are held for identity
    # initialisation, or (a stop landing while the third is still being detected, seen once in a loaded CI
    # run) reported as interrupted; an image whose stage reading had not arrived by the stop (seen once in
    # a loaded local run: 2 frames, 1 image unpaired) is counted as still unpaired
    frames = int(re.search(r"'frames': (\d+), ", log).group(1))
    unpaired = int(re.search(r"still unpaired at stop \{'image': (\d+)", log).group(1))
    held = re.findall(r"(\d+) frame\(s\) still held for identity initialisation were not published", log)
    interrupted = len(re.findall(r"1 frame in progress at the stop \(stamp \d+ ns\) was dropped", log))
    assert frames + unpaired == 3 and frames >= 2, log[-3000:]
    assert int(held[-1] if held else 0) + interrupted == frames, log[-3000:]


def test_detector_reports_a_frame_interrupted_at_stop(capsys):
    """A stop (SIGINT raises KeyboardInterrupt in the callback) while a frame is being detected:
    close() names that frame as dropped (in-process, detection replaced by the interrupt)."""
    import rclpy

    from ct_calib_nodes.nodes.ct_sphere_detector import CtSphereDetector

    rclpy.init()
    try:
        node = CtSphereDetector()
        d = node.instrument.detector

        def stopped(*_a, **_k):
            raise KeyboardInterrupt
        node.proc.detect = stopped
        js = JointState(name=["rotary", "magnification"], position=[0.2, 0.364])
        with pytest.raises(KeyboardInterrupt):
            node._pair(12 * 10**9, image_from_array(np.zeros((d.rows, d.cols), np.uint16), Time(sec=12),
                                                    "ct_detector"), js)
        node.close()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
    out = capsys.readouterr().out
    assert "'frames': 1, " in out and "'published': 0" in out, out
    assert "1 frame in progress at the stop (stamp 12000000000 ns) was dropped" in out, out
    assert "still held" not in out, out
