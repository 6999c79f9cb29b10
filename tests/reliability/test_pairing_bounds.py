"""Bounded pairing buffers: frames whose stage readings never arrive cannot make a node grow.
(The resident-memory measurement over minutes: tests/benchmarks/bench_pairing_memory.py.)"""

import ast
import re

import numpy as np
import pytest

from ct_calib_nodes.nodes.pairing import StampPairer


def test_pairer_bounds_count_and_bytes():
    now = [0.0]
    p = StampPairer(max_count=50, max_bytes=20 << 20, timeout_s=120.0, clock=lambda: now[0])
    frame = 1 << 20                                   # 1 MiB frames: the byte bound binds first (20)
    for i in range(1000):
        now[0] += 0.1
        assert p.add("image", i, f"img{i}", frame) is None
        assert p.pending("image") <= 20 and p.nbytes["image"] <= 20 << 20
    assert p.pending("image") == 20 and p.dropped["image"]["byte_bound"] == 980
    assert p.peak["image"] == {"count": 20, "bytes": 20 << 20}
    # the newest frames are the ones kept, and they still pair
    assert p.add("stage", 999, "js999") == ("img999", "js999") and p.add("stage", 979, "js979") is None
    q = StampPairer(max_count=10, max_bytes=1 << 30, timeout_s=5.0, clock=lambda: now[0])
    for i in range(100):                              # small messages: the count bound binds
        q.add("stage", i, i, 100)
    assert q.pending("stage") == 10 and q.dropped["stage"]["count_bound"] == 90
    now[0] += 6.0
    assert q.expire() == 10 and q.pending("stage") == 0 and q.nbytes["stage"] == 0
    q.add("image", 1, "a", 5)
    q.add("image", 1, "b", 5)                         # duplicate stamp: replaced, counted
    assert q.pending("image") == 1 and q.dropped["image"]["replaced"] == 1 and q.nbytes["image"] == 5


@pytest.mark.ros
def test_detector_holds_at_most_the_bound(tmp_path, start_node, ros_node):
    from sensor_msgs.msg import Image

    from ct_calib_nodes.io import ct_files
    from ct_calib_nodes.nodes.runner import QOS_RELIABLE_STREAM

    inst = tmp_path / "ct_instrument.yaml"
    ct_files.write_yaml(inst, {"units": "SI", "source_to_detector": 1.04821,
                               "detector": {"cols": 128, "rows": 128, "pixel_pitch": 0.0032}})
    det = start_node("ct_calib_nodes", "ct_sphere_detector", "--ros-args", "-p", f"instrument_file:={inst}",
                     "-p", "pair_max_pending:=1000", "-p", f"pair_max_bytes:={15 * 128 * 128 * 2}")
    pub = ros_node.create_publisher(Image, "/ct/detector/image", QOS_RELIABLE_STREAM)
    assert ros_node.spin_until(lambda: pub.get_subscription_count() > 0, timeout=30), det.log()
    n = 120
    data = np.zeros((128, 128), np.uint16).tobytes()
    for i in range(n):
        img = Image(height=128, width=128, encoding="mono16", step=256, data=data)
        img.header.stamp.sec, img.header.stamp.nanosec = 1000 + i, 0
        pub.publish(img)
        if i % 20 == 19:
            ros_node.spin_until(lambda: False, timeout=0.2)
    ros_node.spin_until(lambda: False, timeout=2.0)
    assert det.proc.poll() is None
    assert det.stop() == 0, det.log()
    log = det.log()
    peak = ast.literal_eval(re.search(r"pairing peak (\{.*?\}\})", log).group(1))
    dropped = ast.literal_eval(re.search(r"dropped unpaired (\{.*?\}\})", log).group(1))
    assert peak["image"]["count"] == 15 and peak["image"]["bytes"] == 15 * 128 * 128 * 2, log[-2000:]
    assert dropped["image"]["byte_bound"] == n - 15, log[-2000:]
