"""The idle Pixel Probe calibration node gives the memory of 5 MP frames back once they are done
with (nodes/runner.release_frame_memory): bursts of frames fill its image queues (depth 4 per
camera), and its RSS returns to where it was instead of staying at the most frames ever held
(the pools of Fast DDS and glibc kept about 15 frames, +73 MiB, for good before)."""
import time

import numpy as np
import pytest

pytestmark = pytest.mark.ros

FRAME = 2592 * 1944          # bytes of one mono8 frame (4.8 MiB)


def rss_mib(pid):
    with open(f"/proc/{pid}/status") as f:
        return next(int(ln.split()[1]) for ln in f if ln.startswith("VmRSS:")) / 1024


# Timing-dependent (when DDS and the allocator hand back the last frames): in fresh-clone runs of round 22
# one burst in 3 of 6 runs left 3-5 frames held for the whole wait, released by the next burst; a
# regression (the pre-fix pools: +38.5 MiB after every burst) fails every attempt.
@pytest.mark.flaky(reruns=2)
def test_idle_calibration_node_returns_frame_memory(start_node, ros_node, tmp_path):
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import Image

    from ct_calib_nodes.nodes.runner import QOS_RELIABLE_STREAM

    node = start_node("picms_nodes", "picms_calibration", "--ros-args", "-p", f"output_file:={tmp_path / 'c.yaml'}",
                      "-p", "history_db:=none")
    pubs = [ros_node.create_publisher(Image, f"/picms/camera_{i}/image_raw", QOS_RELIABLE_STREAM) for i in (1, 2, 3)]
    assert ros_node.spin_until(lambda: all(p.get_subscription_count() for p in pubs), timeout=40), node.log()
    img = Image(height=1944, width=2592, encoding="mono8", step=2592)
    img.data = np.random.default_rng(0).integers(0, 255, FRAME, dtype=np.uint8).tobytes()
    pid = node.proc.pid

    def burst(n):
        for k in range(n):
            img.header.stamp = Time(sec=100 + k)
            for p in pubs:
                p.publish(img)
            ros_node.spin_until(lambda: False, timeout=0.05)

    def settled(seconds):                   # RSS once the node has taken every frame
        ros_node.spin_until(lambda: False, timeout=seconds)
        return rss_mib(pid)

    # a frame is 4.8 MiB. Allowed: the last frame of each of the 3 cameras still held (in 2 of the 5
    # fresh-clone runs of round 22: +13.8 and +16.2 MiB after a burst, released by the next one) and one
    # frame's worth of other allocations (Python objects, DDS bookkeeping). Before the fix the RSS stayed
    # at the most frames ever held: ~15 frames, +73 MiB.
    limit = 4 * FRAME / 2**20
    burst(3)                                # warm: the first frames' one-off allocations
    base = settled(3.0)
    peaks, after = [], []
    for _ in range(3):
        burst(8)                            # more than the queues hold: 4 per camera, and one in hand
        peaks.append(rss_mib(pid))
        # back within the limit once the node has taken the frames (a loaded machine takes longer);
        # before the fix the RSS stayed at the most frames ever held (~15 frames, +73 MiB)
        # (20 s ran out once in a fresh-clone run with both test workers busy, round 22: 3 frames still held)
        ros_node.spin_until(lambda: rss_mib(pid) - base < limit, timeout=60.0)
        after.append(settled(0.5))
    assert max(after) - base < limit, (base, peaks, after, node.log()[-2000:])
    assert "frame memory: " in node.log()
