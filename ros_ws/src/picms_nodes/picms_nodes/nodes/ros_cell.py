"""RosCell: the core's CellIO protocol (core/cellio.py) over the INTERFACES.md topics.

Attach it to a node that is spun by a MultiThreadedExecutor (its callbacks run in their own
callback groups while move_and_settle/current block a worker thread). It subscribes
joint_states, camera_N/image_raw and camera_info, and the tracker's SMR readings (relative
names, nodes/common.py), and commands the stage only through stage/command.

Settled, as the calibration node decides it: after a command, the encoder readings stamped
after it stay within `settle_tol_m` of each other for `settle_hold_s`. Then, for each camera,
the first frame whose stamp lies in that settled run (a frame and its stage reading carry the
same stamp) is taken, and tracker readings stamped in the run are averaged for
`tracker_window_s`. If the stage moves again before the frames arrive, the run restarts.
Only the latest frame per camera is kept (5 MP frames).
"""
from __future__ import annotations

import bisect

import threading
import time

import numpy as np
from geometry_msgs.msg import PointStamped
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, JointState
from trajectory_msgs.msg import JointTrajectory

from ct_calib_nodes.nodes.bad_input import BadInputCounter
from ct_calib_nodes.nodes.runner import QOS_LATCHED

from ..core.cellio import Settled, SettleTimeout
from ..io.convert import MessageError, image_array, intrinsics_from_camera_info, joint_positions, point, stage_command, stamp_ns
from .common import COMMAND_TOPIC, IMAGE_TOPIC, INFO_TOPIC, JOINTS_TOPIC, SMR_TOPIC


class RosCell:
    """CellIO over ROS topics (see module doc)."""

    def __init__(self, node, cameras, resolution_m: float, constellation=(), *, settle_tol_m: float = 2.5e-7,
                 settle_hold_s: float = 0.3, tracker_window_s: float = 0.5, image_reliable: bool = True,
                 frame_timeout_s: float = 20.0):
        self.node = node
        self.camera_names = list(cameras)
        self.camera_info: dict = {}
        self.resolution_m = float(resolution_m)
        self.smr_names = list(constellation)
        self.settle_tol_m = float(settle_tol_m)
        self.settle_hold_ns = int(settle_hold_s * 1e9)
        self.tracker_window_ns = int(tracker_window_s * 1e9)
        self.frame_timeout_s = float(frame_timeout_s)
        self.lock = threading.Lock()
        self.js_t: list = []
        self.js_q: list = []
        self.frames: dict = {}            # camera -> (stamp_ns, Image msg), the latest
        self.tracker: list = []           # (stamp_ns, name, (3,))
        self.skipped = 0
        # bad messages counted by topic and kind (the node's counter if it has one, else one given to
        # it, so nodes/runner logs the totals on the way out); callbacks guarded: no message ends the node
        self.bad_input = getattr(node, "bad_input", None)
        if self.bad_input is None:
            self.bad_input = node.bad_input = BadInputCounter(node.get_logger())
            node.create_timer(5.0, self.bad_input.maybe_summarise)
        guard = self.bad_input.guard
        sensors = MutuallyExclusiveCallbackGroup()
        images = MutuallyExclusiveCallbackGroup()
        node.create_subscription(JointState, JOINTS_TOPIC, guard(JOINTS_TOPIC, self._on_joints), qos_profile_sensor_data,
                                 callback_group=sensors)
        for n in self.smr_names:
            node.create_subscription(PointStamped, SMR_TOPIC.format(n),
                                     guard(SMR_TOPIC.format(n), lambda m, n=n: self._on_smr(n, m)),
                                     qos_profile_sensor_data, callback_group=sensors)
        img_qos = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE) if image_reliable \
            else qos_profile_sensor_data
        for c in self.camera_names:
            node.create_subscription(CameraInfo, INFO_TOPIC.format(c),
                                     guard(INFO_TOPIC.format(c), lambda m, c=c: self._on_info(c, m)),
                                     QOS_LATCHED, callback_group=sensors)
            node.create_subscription(Image, IMAGE_TOPIC.format(c),
                                     guard(IMAGE_TOPIC.format(c), lambda m, c=c: self._on_image(c, m)),
                                     img_qos, callback_group=images)
        self.cmd = node.create_publisher(JointTrajectory, COMMAND_TOPIC, 10)

    # ---------------------------------------------------------------- intake
    def _warn(self, text, topic=None):
        self.skipped += 1
        if topic is None:
            self.node.get_logger().warning(text, throttle_duration_sec=2.0)
        else:                               # counted by kind, logged once per kind plus summaries
            self.bad_input.report(topic, text)

    def _on_joints(self, m):
        try:
            q = joint_positions(m)
        except MessageError as exc:
            self._warn(f"skipped joint_states: {exc}", JOINTS_TOPIC)
            return
        with self.lock:
            self.js_t.append(stamp_ns(m.header.stamp))
            self.js_q.append(q)
            if len(self.js_t) > 60000:     # >= 300 s kept at 100 Hz: longer than any settle + frame wait
                del self.js_t[:30000], self.js_q[:30000]

    def _on_smr(self, name, m):
        try:
            p = point(m)
        except MessageError as exc:
            self._warn(f"skipped tracker reading: {exc}", SMR_TOPIC.format(name))
            return
        with self.lock:
            self.tracker.append((stamp_ns(m.header.stamp), name, p))
            if len(self.tracker) > 20000:
                del self.tracker[:10000]

    def _on_info(self, cam, m):
        try:
            intr = intrinsics_from_camera_info(m)
        except MessageError as exc:
            self._warn(f"skipped CameraInfo: {exc}", INFO_TOPIC.format(cam))
            return
        with self.lock:
            self.camera_info[cam] = intr

    def _on_image(self, cam, m):
        with self.lock:
            self.frames[cam] = (stamp_ns(m.header.stamp), m)

    # ---------------------------------------------------------------- protocol
    def wait_ready(self, timeout_s: float = 20.0) -> None:
        """Wait for joint_states, every CameraInfo and a stage subscriber; ValueError naming what is missing."""
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            with self.lock:
                ok = bool(self.js_t) and all(c in self.camera_info for c in self.camera_names)
            if ok and self.cmd.get_subscription_count() > 0:
                return
            time.sleep(0.05)
        with self.lock:
            missing = [c for c in self.camera_names if c not in self.camera_info]
            js = bool(self.js_t)
        raise ValueError("cell not ready within {:.0f} s: {}".format(timeout_s, "; ".join(
            x for x in (("no joint_states (is the stage running?)" if not js else ""),
                        (f"CameraInfo missing for {missing}" if missing else ""),
                        ("nobody subscribes the stage command topic" if self.cmd.get_subscription_count() == 0
                         else "")) if x)))

    def move_and_settle(self, q_target, *, timeout_s: float = 30.0) -> Settled:
        q = np.asarray(q_target, float).reshape(3)
        if not np.all(np.isfinite(q)):
            raise ValueError(f"move_and_settle: target is not finite: {q}")
        t_cmd = self.node.get_clock().now().nanoseconds
        self.cmd.publish(stage_command(q))
        return self._settle(t_cmd, timeout_s, target=q)

    def current(self) -> Settled:
        return self._settle(self.node.get_clock().now().nanoseconds, 30.0)

    # ---------------------------------------------------------------- internals
    def _settled_run(self, after_ns):
        """(start_ns, end_ns, readings (N, 3)) of the still run ending at the latest reading, if it
        has lasted settle_hold; else None. Only readings stamped after `after_ns` count."""
        with self.lock:
            # every reading since after_ns, however long the frames took (a fixed count of the
            # latest readings covered 30 s at 100 Hz and lost the start of a run settled earlier)
            i0 = bisect.bisect_right(self.js_t, after_ns)
            i0 = max(0, i0 - 200)           # readings may arrive slightly out of stamp order
            t = np.array(self.js_t[i0:], dtype=np.int64)
            q = np.array(self.js_q[i0:]).reshape(-1, 3)
        keep = t > after_ns
        t, q = t[keep], q[keep]
        if t.size < 3:
            return None
        o = np.argsort(t, kind="stable")
        t, q = t[o], q[o]
        # walk back from the latest reading while all readings stay within tol of it
        lo, hi = q[-1].copy(), q[-1].copy()
        i = t.size - 1
        while i > 0:
            nlo, nhi = np.minimum(lo, q[i - 1]), np.maximum(hi, q[i - 1])
            if np.any(nhi - nlo > self.settle_tol_m):
                break
            lo, hi = nlo, nhi
            i -= 1
        if t[-1] - t[i] < self.settle_hold_ns:
            return None
        return int(t[i]), int(t[-1]), q[i:]

    def _settle(self, after_ns, timeout_s, target=None) -> Settled:
        t_end = time.monotonic() + timeout_s
        run = None
        while time.monotonic() < t_end:
            run = self._settled_run(after_ns)
            if run is not None:
                break
            time.sleep(0.02)
        if run is None:
            raise SettleTimeout(f"stage did not settle within {timeout_s:.1f} s of the command "
                                f"(encoders within {self.settle_tol_m * 1e6:.2f} um for "
                                f"{self.settle_hold_ns * 1e-9:.2f} s)")
        start = run[0]
        if target is not None and np.any(np.abs(run[2].mean(0) - target) > max(self.resolution_m, 2e-6)):
            raise SettleTimeout(f"stage settled at {np.round(run[2].mean(0) * 1e3, 4).tolist()} mm, not at the "
                                f"commanded {np.round(target * 1e3, 4).tolist()} mm (command rejected?)")
        # frames whose stamp is in the settled run, then tracker readings while still settled
        t_frames = time.monotonic() + self.frame_timeout_s
        images, stamps = {}, {}
        while time.monotonic() < t_frames:
            with self.lock:
                got = {c: f for c, f in self.frames.items() if c in self.camera_names and f[0] >= start}
            for c, (st, msg) in got.items():
                if c in images:
                    continue
                try:
                    images[c] = image_array(msg)
                    stamps[c] = st
                except MessageError as exc:
                    self._warn(f"frame skipped: {exc}", IMAGE_TOPIC.format(c))
                    with self.lock:
                        if self.frames.get(c, (0,))[0] == st:
                            del self.frames[c]
            if len(images) == len(self.camera_names):
                break
            time.sleep(0.02)
        missing = [c for c in self.camera_names if c not in images]
        if missing:
            raise SettleTimeout(f"no settled frame from {missing} within {self.frame_timeout_s:.0f} s of settling")
        t_tr = max(stamps.values()) if stamps else start
        while self.node.get_clock().now().nanoseconds < max(t_tr, start + self.settle_hold_ns) \
                + self.tracker_window_ns and time.monotonic() < t_frames + 5:
            time.sleep(0.02)
        run2 = self._settled_run(after_ns)
        if run2 is None or run2[0] > start or run2[1] < max(stamps.values()):
            raise SettleTimeout("the stage moved again while the frames were taken")
        with self.lock:
            rd = [(n, p) for st, n, p in self.tracker if run2[0] <= st <= run2[1]]
        sums, nn = {}, {}
        for n, p in rd:
            sums[n] = sums.get(n, 0.0) + p
            nn[n] = nn.get(n, 0) + 1
        q = run2[2]
        return Settled(q=q.mean(0), stamp_ns=int(max(stamps.values())), images=images,
                       tracker={n: sums[n] / nn[n] for n in nn}, tracker_n=nn, q_sd=q.std(0))


# Parameters and set-up shared by the nodes that drive the probe through a RosCell (targeting, measurement).
CELL_PARAMS = {
    "cell_file": ("", "picms_cell.yaml; empty = the package's config/picms_cell.yaml [path]"),
    "calibration_file": ("picms_calibration.yaml", "the Pixel Probe calibration (picms_calibration.yaml) [path]"),
    "cameras": (["camera_1", "camera_2", "camera_3"], "cameras of the Pixel Probe [-]"),
    "settle_tol_m": (2.5e-7, "encoder readings within this span count as still [m]"),
    "settle_hold_s": (0.3, "still for this long counts as settled [s]"),
    "tracker_window_s": (0.5, "average tracker readings over this long once settled [s]"),
    "frame_timeout_s": (20.0, "wait this long for a settled frame from every camera [s]"),
    "image_reliable": (True, "subscribe images reliably (false to match a best-effort camera driver) [-]"),
    "ready_timeout_s": (20.0, "wait this long for joint_states, CameraInfo and the stage [s]"),
}


def open_cell(node, p):
    """(cell YAML dict, RosCell) from the CELL_PARAMS values p of a node."""
    from ..io.files import read_cell  # noqa: PLC0415
    from .picms_calibration import _default_cell  # noqa: PLC0415
    cell_yaml = read_cell(p["cell_file"] or _default_cell())
    cell = RosCell(node, p["cameras"], float(cell_yaml["stage"]["resolution"]),
                   list(cell_yaml["tracker"]["constellation"]),
                   settle_tol_m=float(p["settle_tol_m"]), settle_hold_s=float(p["settle_hold_s"]),
                   tracker_window_s=float(p["tracker_window_s"]), image_reliable=bool(p["image_reliable"]),
                   frame_timeout_s=float(p["frame_timeout_s"]))
    return cell_yaml, cell
