"""Bounded pairing buffers: frames whose stage readings never arrive cannot make a node grow.
(The resident-memory measurement over minutes: tests/benchmarks/bench_pairing_memory.py.)"""

import ast
import re

import numpy as np
import pytest

from ct_calib_nodes.nodes.ct_sphere_detector import image_queue_depth
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
# Timing-dependent over DDS: one fresh-clone run of round 22 (of 6) counted 90 of the 105 images it
# expected as dropped on the byte bound (the rest not yet delivered when counted); a bound that does not
# hold fails every attempt.
@pytest.mark.flaky(reruns=2)
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
        if i % 10 == 9:            # paced: the reader queue (15 frames deep here) must not drop any
            ros_node.spin_until(lambda: False, timeout=0.2)
    ros_node.spin_until(lambda: False, timeout=2.0)
    assert det.proc.poll() is None
    assert det.stop() == 0, det.log()
    log = det.log()
    peak = ast.literal_eval(re.search(r"pairing peak (\{.*?\}\})", log).group(1))
    dropped = ast.literal_eval(re.search(r"dropped unpaired (\{.*?\}\})", log).group(1))
    assert peak["image"]["count"] == 15 and peak["image"]["bytes"] == 15 * 128 * 128 * 2, log[-2000:]
    assert dropped["image"]["byte_bound"] == n - 15, log[-2000:]


def test_reader_queue_depth_and_overtaken_readings():
    # the detector's image reader queue holds about pair_max_bytes of frames, 2 to 200 deep
    assert image_queue_depth(256 << 20, 2048, 2048) == 32
    assert image_queue_depth(256 << 20, 1024, 1024) == 128
    assert image_queue_depth(256 << 20, 512, 512) == 200
    assert image_queue_depth(1 << 20, 4096, 4096) == 2
    p = StampPairer(max_count=100, max_bytes=1 << 30, timeout_s=120.0)
    for t in range(10):
        p.add("stage", t, f"js{t}", 100)
    assert p.add("image", 0, "img0", 10) == ("img0", "js0")
    # images 1..4 lost on the way: image 5 makes their stage readings unpairable at once
    assert p.add("image", 5, "img5", 10) == ("img5", "js5")
    assert p.drop_older("stage", 5) == 4 and p.dropped["stage"]["overtaken"] == 4
    assert p.pending("stage") == 4 and p.nbytes["stage"] == 400 and p.add("image", 6, "img6", 10) == ("img6", "js6")
    assert p.drop_older("stage", 6) == 0 and p.total_dropped() == 4


@pytest.mark.ros
def test_detector_flooded_with_big_frames_stays_bounded(tmp_path, start_node, ros_node):
    """Reliable 1024^2 frames with their stage readings, published faster than the detector
    processes them: the image reader queue (pair_max_bytes 8 MiB -> 4 frames) drops the overflow,
    the node's resident peak stays far below what was sent, and every frame is accounted for:
    processed, or counted lost (its stage reading overtaken), or still unpaired at stop."""
    from rclpy.duration import Duration
    from sensor_msgs.msg import Image, JointState

    from ct_calib_nodes.io import ct_files
    from ct_calib_nodes.nodes.runner import QOS_RELIABLE_STREAM
    from reliab_recordings import ct_recording

    cell = tmp_path / "cell"
    ct_recording(cell, n_positions=1, n_proj=1)
    px, frame = 1024, 1024 * 1024 * 2
    inst = tmp_path / "ct_instrument.yaml"
    ct_files.write_yaml(inst, {"units": "SI", "source_to_detector": 1.04821,
                               "detector": {"cols": px, "rows": px, "pixel_pitch": 0.0004}})
    det = start_node("ct_calib_nodes", "ct_sphere_detector", "--ros-args", "-p", f"instrument_file:={inst}",
                     "-p", f"reference_object_file:={cell / 'reference_object.yaml'}",
                     "-p", f"pair_max_bytes:={4 * frame}", "-p", "init_frames:=2")
    pub_i = ros_node.create_publisher(Image, "/ct/detector/image", QOS_RELIABLE_STREAM)
    pub_j = ros_node.create_publisher(JointState, "/ct/stage/joint_states", QOS_RELIABLE_STREAM)
    assert ros_node.spin_until(lambda: pub_i.get_subscription_count() > 0 and pub_j.get_subscription_count() > 0
                               and "image reader queue depth 4" in det.log(), timeout=30), det.log()
    ros_node.spin_until(lambda: False, timeout=1.0)
    rss0 = _status_mib(det.proc.pid, "VmRSS")
    n = 80
    rng = np.random.default_rng(3)     # flat frames with a little noise: no spheres, quick to reject
    data = [rng.integers(30000, 30100, (px, px)).astype(np.uint16).tobytes() for _ in range(2)]
    def send(i):
        js = JointState(name=["rotary", "magnification"], position=[0.01 * i, 0.5])
        img = Image(height=px, width=px, encoding="mono16", step=2 * px, data=data[i % 2])
        js.header.stamp.sec = img.header.stamp.sec = 1000 + i
        pub_j.publish(js)
        pub_i.publish(img)

    for i in range(n):                  # as fast as this process can publish
        send(i)
    # every frame went to the reader (acknowledged: reliable), the queue's last frames are processed,
    # then one more frame comes (the campaign goes on): it overtakes the stage readings of the lost ones
    assert pub_i.wait_for_all_acked(Duration(seconds=60)) and pub_j.wait_for_all_acked(Duration(seconds=10))
    ros_node.spin_until(lambda: False, timeout=3.0)
    send(n)
    assert pub_i.wait_for_all_acked(Duration(seconds=30))
    ros_node.spin_until(lambda: False, timeout=4.0)
    n += 1
    hwm = _status_mib(det.proc.pid, "VmHWM")
    assert det.proc.poll() is None
    assert det.stop() == 0, det.log()[-3000:]
    log = det.log()
    counts = ast.literal_eval(re.findall(r"detector counts: (\{.*?\});", log)[-1])
    dropped = ast.literal_eval(re.search(r"dropped unpaired (\{.*?\}\})", log).group(1))
    waiting = ast.literal_eval(re.findall(r"still unpaired at stop (\{.*?\})", log)[-1])
    print(f"\nflood: {n} frames of {px}^2 sent; RSS start {rss0:.0f} MiB, peak {hwm:.0f} MiB "
          f"(sent {n * frame / 2**20:.0f} MiB); counts {counts}; dropped {dropped}; waiting {waiting}")
    assert counts["images_lost"] > 0, log[-2000:]         # the flood did overflow the queue
    assert counts["images_lost"] == dropped["stage"]["overtaken"]
    # the last frame overtook them all (on a loaded machine it may itself still sit in the queue
    # at stop: its stage reading then waits, and the frame before it did the overtaking)
    assert waiting["stage"] <= 1 and counts["images_lost"] >= n - 1 - counts["frames"] - 1, (waiting, counts)
    lost_any_way = sum(dropped["stage"].values()) + waiting["stage"]
    assert counts["frames"] + lost_any_way == n, log[-2000:]   # every frame accounted for
    # reader queue 4 frames + pairing bound 4 frames + a few in flight (decode, flat field)
    assert hwm - rss0 < 24 * frame / 2**20 + 40, (rss0, hwm)


def _status_mib(pid, key):
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    raise KeyError(key)
