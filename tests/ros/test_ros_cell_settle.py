"""RosCell's settle protocol on readings injected in process (no simulators; a thread plays the
stage and cameras while RosCell waits): a stage that settled long before the camera frames
arrived is still recognised as settled for the whole wait, and one that moved between settling
and the frames is refused.

Round 22: with 100 Hz joint_states and frames 37 s late on a loaded CI machine, the settled run
was looked for among the latest 3000 readings (30 s) only; its start fell out of that window and
a still stage was reported as "moved again while the frames were taken"."""
import threading
import time

import numpy as np
import pytest

pytestmark = pytest.mark.ros


def _image(stamp_ns):
    from sensor_msgs.msg import Image
    m = Image()
    m.header.stamp.sec, m.header.stamp.nanosec = divmod(int(stamp_ns), 10**9)
    m.height, m.width, m.step, m.encoding = 4, 4, 4, "mono8"
    m.data = bytes(16)
    return m


def _cell(ros_node):
    from picms_nodes.nodes.ros_cell import RosCell
    return RosCell(ros_node, ["camera_1", "camera_2"], 6e-6, settle_tol_m=2.5e-7, settle_hold_s=0.3,
                   tracker_window_s=0.0, frame_timeout_s=5.0)


def _play(cell, t0, t1, rate_hz, q_of_t, frame_ns=None, delay_s=0.0):
    """Append readings stamped t0..t1 (and, then, frames stamped frame_ns) after delay_s, as the
    subscriptions would."""
    def go():
        time.sleep(delay_s)
        ts = np.arange(t0, t1, int(1e9 / rate_hz))
        qs = q_of_t(ts)
        with cell.lock:
            cell.js_t.extend(int(t) for t in ts)
            cell.js_q.extend(qs)
            if frame_ns is not None:
                cell.frames = {c: (frame_ns + k, _image(frame_ns + k)) for k, c in enumerate(cell.camera_names)}
    th = threading.Thread(target=go, daemon=True)
    th.start()
    return th


TARGET = np.array([1e-3, -2e-3, 0.0])


def _moved_then_still(t_cmd, seed=1):
    rng = np.random.default_rng(seed)
    # 1 s of motion after the command, then still (encoder jitter far below settle_tol)
    return lambda ts: np.clip((ts - t_cmd) / 1e9, 0, 1)[:, None] * TARGET + rng.normal(0, 2e-9, (ts.size, 3))


@pytest.mark.parametrize("rate_hz", [100.0, 50.0])
def test_settle_keeps_the_run_start_when_frames_are_late(ros_node, rate_hz):
    cell = _cell(ros_node)
    now = ros_node.get_clock().now().nanoseconds
    t_cmd = now - int(70e9)
    q = _moved_then_still(t_cmd)
    # 10 s of readings when the stage is found settled; the frames come 59 s of still readings later
    _play(cell, t_cmd + int(1e7), t_cmd + int(10e9), rate_hz, q).join()
    _play(cell, t_cmd + int(10e9), now, rate_hz, q, frame_ns=now - int(1e9), delay_s=0.3)
    s = cell._settle(t_cmd, 2.0, target=TARGET)
    assert set(s.images) == {"camera_1", "camera_2"}
    assert np.allclose(s.q, TARGET, atol=1e-8)
    assert s.stamp_ns == now - int(1e9) + 1


def test_settle_refuses_a_stage_that_moved_while_the_frames_were_taken(ros_node):
    from picms_nodes.core.cellio import SettleTimeout
    cell = _cell(ros_node)
    now = ros_node.get_clock().now().nanoseconds
    t_cmd = now - int(10e9)
    still = _moved_then_still(t_cmd)
    _play(cell, t_cmd + int(1e7), t_cmd + int(4e9), 100.0, still).join()
    # a second, unexpected 5 um step 6 s after the command, before the frames (stamped 8 s) arrive
    _play(cell, t_cmd + int(4e9), now, 100.0,
          lambda ts: still(ts) + ((ts - t_cmd) > 6e9)[:, None] * np.array([5e-6, 0, 0]),
          frame_ns=t_cmd + int(8e9), delay_s=0.3)
    with pytest.raises(SettleTimeout, match="moved again"):
        cell._settle(t_cmd, 2.0, target=TARGET)
