"""Pixel Probe calibration node: drives the stage through the pattern, calibrates, publishes.

Service /picms/run_calibration (metro_msgs/RunPicmsCalibration), or auto_start:=true. The node
commands the stage (only through /picms/stage/command) to the reference and then +-X, +-Y, +-Z
(Appendix A), waits at each target until joint_states show it settled, dwells while frames and
tracker readings arrive, then calibrates with the same core as the offline tool
(core.pipeline). Frames are detected as they arrive (bad frames are logged and skipped); only
those inside settled periods are used. The result is published latched on /picms/calibration
(metro_msgs/PicmsCalibration) and written atomically to output_file only when it is neither failed nor
POOR_FIT (by its own fit, camera chi2/dof >= 4, or by the discrepancy engine's verdict below): a poor
calibration never replaces the good one plant software reads there.

With judge:=true (default) each calibration then goes through the discrepancy engine
(core/picms_discrepancy.judge, with the recorded streams, so a tracker clock lag shows on the moves) and
its verdict is published latched on /picms/discrepancy (metro_msgs/DiscrepancyReport; SUCCESS adequate,
POOR_FIT inadequate, INSUFFICIENT_DATA when the session is too small for a verdict: the Appendix-A
pattern's 7 stations are; pattern:=grid drives the engine's 33-station grid instead). When the engine
finds the settled stations' model inadequate the calibration is published POOR_FIT (so a valid earlier
calibration stays on the topic, plant_hooks); a finding on the moves only (a clock lag) is added to the
status message and leaves the code alone.
"""
from __future__ import annotations

import threading
import time

import numpy as np
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from geometry_msgs.msg import PointStamped
from metro_msgs.msg import DiscrepancyReport, PicmsCalibration, SolveStatus
from metro_msgs.srv import RunPicmsCalibration
from sensor_msgs.msg import CameraInfo, Image, JointState
from trajectory_msgs.msg import JointTrajectory

from ct_calib_nodes.nodes import plant
from ct_calib_nodes.nodes.bad_input import BadInputCounter
from ct_calib_nodes.nodes.runner import QOS_LATCHED, declare_parameters

from ..core.calibrate import CalibrationError, settled_windows, tracker_shortfall
from ..core.campaign import Recording, appendix_a_pattern
from ..core.picms_discrepancy import grid_pattern, judge, motion_of
from ..core.detect import DetectionError, detect_disc
from ..core.pipeline import calibrate_detections
from ..io.calibration_msg import calibration_msg, failure_msg
from ..io.convert import MessageError, image_array, intrinsics_from_camera_info, joint_positions, point, stage_command, stamp_ns
from ..io.files import read_cell, write_calibration
from .common import (CALIBRATION_TOPIC, COMMAND_TOPIC, DISCREPANCY_TOPIC, IMAGE_TOPIC, INFO_TOPIC, JOINTS_TOPIC, SERVICE,
                     SMR_TOPIC)

PARAMS = {
    "cell_file": ("", "picms_cell.yaml; empty = the package's config/picms_cell.yaml [path]"),
    "output_file": ("picms_calibration.yaml", "where a calibration is written unless failed or POOR_FIT [path]"),
    "cameras": (["camera_1", "camera_2", "camera_3"], "cameras of the Pixel Probe [-]"),
    "step_xy_m": (0.006, "stage excursion along +-x and +-y from the reference [m]"),
    "step_z_m": (0.004, "stage excursion along +-z [m]"),
    "reference": ([0.0, 0.0, 0.0], "stage reading at which the SMR* is at X* [m]"),
    "dwell_s": (3.0, "time to collect frames and tracker readings once settled [s]"),
    "frames_per_station": (2, "settled frames per camera to collect at each station [count]"),
    "settle_timeout_s": (30.0, "give up when the stage has not settled this long after a command [s]"),
    "image_reliable": (True, "subscribe images reliably (5 MP frames over best-effort UDP are mostly lost); "
                             "false to match a best-effort camera driver [-]"),
    "info_timeout_s": (20.0, "wait this long for joint_states and every CameraInfo before giving up [s]"),
    "command_subscribers": (1, "move the stage only once this many nodes subscribe to its command topic "
                               "(the stage; with a recorder that must see every command: 2) [count]"),
    "pattern": ("appendix_a", "stations: appendix_a (the paper's 7) or grid (33: enough for a discrepancy "
                              "verdict; step_xy_m / step_z_m are its half-widths) [-]"),
    "judge": (True, "run the discrepancy engine on each calibration and publish picms/discrepancy [-]"),
    "auto_start": (False, "run the calibration once at start-up [-]"),
    "exit_when_done": (False, "end the process after an auto_start run [-]"),
    **plant.HISTORY_PARAMS,
}


def _default_cell():
    try:
        from ament_index_python.packages import get_package_share_directory
        import pathlib
        return pathlib.Path(get_package_share_directory("picms_nodes")) / "config" / "picms_cell.yaml"
    except Exception:   # noqa: BLE001 - running from the source tree
        import pathlib
        return pathlib.Path(__file__).resolve().parents[2] / "config" / "picms_cell.yaml"


class PicmsCalibrationNode(Node):
    def __init__(self):
        super().__init__("picms_calibration")
        self.p = p = declare_parameters(self, PARAMS)
        self.cell_file = p["cell_file"] or _default_cell()
        self.cell = read_cell(self.cell_file)
        self.lock = threading.Lock()
        self.busy = threading.Lock()
        self.exit_code = 0
        self.js_t, self.js_q, self.tracker, self.dets, self.info = [], [], [], [], {}
        self.skipped = 0
        self.bad_input = BadInputCounter(self.get_logger())   # bad messages counted by kind, logged rate-limited
        guard = self.bad_input.guard
        sensors = MutuallyExclusiveCallbackGroup()
        images = MutuallyExclusiveCallbackGroup()
        self.svc_group = ReentrantCallbackGroup()
        self.create_subscription(JointState, JOINTS_TOPIC, guard(JOINTS_TOPIC, self.on_joints), qos_profile_sensor_data,
                                 callback_group=sensors)
        tr = self.cell["tracker"]
        for name in list(tr["constellation"]) + [tr["probe_smr"]]:
            self.create_subscription(PointStamped, SMR_TOPIC.format(name),
                                     guard(SMR_TOPIC.format(name), lambda m, n=name: self.on_smr(n, m)),
                                     qos_profile_sensor_data,
                                     callback_group=sensors)
        img_qos = QoSProfile(depth=4, reliability=ReliabilityPolicy.RELIABLE) if p["image_reliable"] \
            else qos_profile_sensor_data
        for c in p["cameras"]:
            self.create_subscription(CameraInfo, INFO_TOPIC.format(c), guard(INFO_TOPIC.format(c),
                                                                              lambda m, c=c: self.on_info(c, m)),
                                     QOS_LATCHED, callback_group=sensors)
            self.create_subscription(Image, IMAGE_TOPIC.format(c), guard(IMAGE_TOPIC.format(c),
                                                                         lambda m, c=c: self.on_image(c, m)),
                                     img_qos, callback_group=images)
        self.cmd = self.create_publisher(JointTrajectory, COMMAND_TOPIC, 10)
        self.pub = self.create_publisher(PicmsCalibration, CALIBRATION_TOPIC, QOS_LATCHED)
        if p["pattern"] not in ("appendix_a", "grid"):
            raise ValueError(f"pattern must be appendix_a or grid, got {p['pattern']!r}")
        self.disc_pub = self.create_publisher(DiscrepancyReport, DISCREPANCY_TOPIC, QOS_LATCHED)
        self.create_service(RunPicmsCalibration, SERVICE, self.on_service, callback_group=self.svc_group)
        from .plant_hooks import PicmsPlant  # history (latest valid re-published now) and diagnostics
        self.plant = PicmsPlant(self, p["history_db"])
        self.create_timer(5.0, self.bad_input.maybe_summarise)
        if p["auto_start"]:
            threading.Thread(target=self._auto, daemon=True).start()

    # ---------------------------------------------------------------- intake
    def on_joints(self, m):
        try:
            q = joint_positions(m)
        except MessageError as exc:
            self.bad_input.report(JOINTS_TOPIC, f"skipped joint_states: {exc}")
            return
        self.plant.joints.tick()
        if not self.busy.locked():
            return                              # not calibrating: readings are not kept (memory stays flat)
        with self.lock:
            self.js_t.append(stamp_ns(m.header.stamp))
            self.js_q.append(q)

    def on_smr(self, name, m):
        try:
            p = point(m)
        except MessageError as exc:
            self.bad_input.report(SMR_TOPIC.format(name), f"skipped tracker reading: {exc}")
            return
        if not self.busy.locked():
            return
        with self.lock:
            self.tracker.append((stamp_ns(m.header.stamp), name, p))

    def on_info(self, cam, m):
        try:
            intr = intrinsics_from_camera_info(m)
        except MessageError as exc:
            self.bad_input.report(INFO_TOPIC.format(cam), f"skipped CameraInfo: {exc}")
            return
        with self.lock:
            self.info[cam] = intr

    def on_image(self, cam, m):
        self.plant.images.tick()
        try:
            img = image_array(m)                # checked always: malformed frames are counted
        except MessageError as exc:
            self.skipped += 1
            self.bad_input.report(IMAGE_TOPIC.format(cam), f"frame skipped: {exc}")
            return
        if not self.busy.locked():
            return                              # not calibrating: frames are not needed
        intr = self.info.get(cam)
        if intr is None:
            self.skipped += 1
            self.get_logger().warning(f"frame from {cam} skipped: no CameraInfo received yet", throttle_duration_sec=5.0)
            return
        try:
            d = detect_disc(img, intr)
        except DetectionError as exc:
            self.skipped += 1
            self.get_logger().warning(f"frame from {cam} skipped: {exc}", throttle_duration_sec=2.0)
            return
        with self.lock:
            self.dets.append((stamp_ns(m.header.stamp), cam, d))

    # ---------------------------------------------------------------- sequence
    def _command(self, q):
        self.cmd.publish(stage_command(q))

    def _wait_settled(self, target, t_cmd_ns):
        """Wait until the stage has settled at ``target`` for dwell_s with the frames and tracker readings a
        station needs. Returns "" when it has, else what was missing when settle_timeout_s ran out."""
        res = float(self.cell["stage"]["resolution"])
        deadline = time.monotonic() + float(self.p["settle_timeout_s"])
        dwell_ns = int(float(self.p["dwell_s"]) * 1e9)
        missing = "the stage never settled there"
        while time.monotonic() < deadline:
            time.sleep(0.1)
            with self.lock:
                t = np.array(self.js_t[-2000:], dtype=np.int64)
                q = np.array(self.js_q[-2000:]).reshape(-1, 3)
            if t.size < 3:
                continue
            keep = t > t_cmd_ns
            w = settled_windows(t[keep], q[keep]) if keep.sum() > 3 else []
            if w and w[-1].end_ns == t[keep].max() and np.all(np.abs(w[-1].q - target) <= res) \
                    and w[-1].end_ns - w[-1].start_ns >= dwell_ns:
                a, b = w[-1].start_ns, w[-1].end_ns
                with self.lock:
                    n = {c: sum(1 for st, cc, _ in self.dets if cc == c and a <= st <= b)
                         for c in self.p["cameras"]}
                    n_smr = {}
                    for st, name, _ in self.tracker:
                        if a <= st <= b:
                            n_smr[name] = n_smr.get(name, 0) + 1
                # the station must be usable by the calibration (tracker_shortfall): a station without
                # the tracker's readings is skipped there, and a reference station skipped moves X* to
                # the next station's reading
                short = [f"{c}: {k} usable frame(s)" for c, k in n.items() if k < int(self.p["frames_per_station"])]
                short += tracker_shortfall(n_smr, self.cell)
                if not short:
                    return ""
                missing = "settled, but " + "; ".join(short) + " (see the skipped-frame warnings; is the tracker running?)"
        return missing

    def run(self, write_file=True):
        """The whole calibration; returns (success, message, PicmsCalibration)."""
        if not self.busy.acquire(blocking=False):
            return False, "a calibration is already running", None
        try:
            with self.lock:
                self.js_t, self.js_q, self.tracker, self.dets = [], [], [], []
            cams = list(self.p["cameras"])
            t_wait = time.monotonic() + float(self.p["info_timeout_s"])
            while time.monotonic() < t_wait and (not self.js_t or any(c not in self.info for c in cams)):
                time.sleep(0.1)
            # what is missing from the cell first (a camera or the stage not running: every part that is
            # missing, in one message), then whether the stage hears its commands (discovery of its
            # subscription can lag its joint_states under load)
            missing = [c for c in cams if c not in self.info]
            absent = [] if self.js_t else ["no /picms/stage/joint_states: is the stage running?"]
            if missing:
                absent.append(f"CameraInfo missing for {missing}: intrinsic calibration K, D required")
            if absent:
                raise CalibrationError("; ".join(absent))
            need = int(self.p["command_subscribers"])
            t_wait = time.monotonic() + float(self.p["info_timeout_s"])
            while time.monotonic() < t_wait and self.cmd.get_subscription_count() < need:
                time.sleep(0.1)
            if self.cmd.get_subscription_count() < need:
                raise CalibrationError(f"{self.cmd.get_subscription_count()} subscriber(s) of the stage command topic, "
                                       f"{need} expected (command_subscribers) within {self.p['info_timeout_s']} s")
            ref = np.array(self.p["reference"], float)
            sxy, sz = float(self.p["step_xy_m"]), float(self.p["step_z_m"])
            pattern = appendix_a_pattern(sxy, sz) if self.p["pattern"] == "appendix_a" else \
                grid_pattern(half_xy_m=sxy, half_z_m=sz)
            for k, dq in enumerate(pattern):
                target = ref + dq
                t_cmd = self.get_clock().now().nanoseconds
                self._command(target)
                self.get_logger().info(f"station {k}: stage to {np.round(target * 1e3, 3).tolist()} mm")
                missing = self._wait_settled(target, t_cmd)
                if missing:
                    raise CalibrationError(f"station {k} at {np.round(target * 1e3, 3).tolist()} mm not complete "
                                           f"within {self.p['settle_timeout_s']} s: {missing}")
            self._command(ref)
            with self.lock:
                rec = Recording(cell=self.cell, camera_info=dict(self.info),
                                joint_stamps_ns=np.array(self.js_t, dtype=np.int64),
                                joint_positions=np.array(self.js_q).reshape(-1, 3), tracker=list(self.tracker))
                dets = list(self.dets)
            res = calibrate_detections(rec, dets)
            msg = calibration_msg(res, self.get_clock().now().to_msg(), "")
            if self.p["judge"]:
                try:
                    self._judge(res, rec, msg)
                except Exception as exc:  # noqa: BLE001 - the engine's failure must not cost the calibration
                    from ct_calib_nodes.io.discrepancy_msg import FAILED, failed_msg  # noqa: PLC0415
                    self.get_logger().error(f"discrepancy engine failed: {exc!r} (calibration kept)")
                    rep = failed_msg(msg.header.stamp, FAILED, f"engine error: {exc!r}",
                                     calibration_topic=self.pub.topic_name)
                    rep.header.frame_id = "tracker"
                    self.disc_pub.publish(rep)
            # the file plant software reads is written only after the verdict: a calibration whose
            # model the engine found inadequate (POOR_FIT) must not replace a good one there
            path = ""
            if write_file and self.p["output_file"]:
                if msg.status.code == SolveStatus.POOR_FIT:
                    self.get_logger().warning(f"calibration not written: POOR_FIT; {self.p['output_file']} "
                                              "left untouched")
                else:
                    path = str(write_calibration(res, self.p["output_file"]))
                    msg.file_path = path
            self.plant.publish(msg)
            self.plant.store(res, msg, None, self.cell_file, rec.joint_stamps_ns)
            self.get_logger().info(f"{res.message}; X* pixels " +
                                   ", ".join(f"{c}: {np.round(v, 3).tolist()}" for c, v in res.pixels.items()) +
                                   (f"; written to {path}" if path else ""))
            return True, res.message, msg
        except (CalibrationError, ValueError, OSError) as exc:
            self.get_logger().error(f"calibration failed: {exc} (no file written)")
            msg = failure_msg(str(exc), self.get_clock().now().to_msg())
            self.plant.publish(msg)
            self.plant.store(None, msg, str(exc), self.cell_file, list(self.js_t))
            return False, str(exc), msg
        finally:
            self.busy.release()

    def _judge(self, res, rec, msg):
        """Discrepancy verdict on this calibration: publish it; mark the calibration's status (see module doc)."""
        from ct_calib_nodes.io.discrepancy_msg import INSUFFICIENT_DATA, POOR_FIT, discrepancy_msg, failed_msg  # noqa: PLC0415
        self.get_logger().info("discrepancy engine: judging the calibration ...")
        out, state, text, settled = judge(res, rec.camera_info, motion_of(rec))
        if out is None:
            rep = failed_msg(msg.header.stamp, INSUFFICIENT_DATA, text, calibration_topic=self.pub.topic_name)
        else:
            rep = discrepancy_msg(out, msg.header.stamp, calibration_topic=self.pub.topic_name)
        rep.header.frame_id = "tracker"
        self.disc_pub.publish(rep)
        self.get_logger().info(f"discrepancy ({state}): {text}")
        if state == "inadequate":
            msg.status.message += f"; discrepancy engine: {text}"
            if settled:
                msg.status.code = POOR_FIT

    def on_service(self, req, resp):
        ok, text, msg = self.run(bool(req.write_file))
        resp.success, resp.message = ok, text
        if msg is not None:
            resp.calibration = msg
        return resp

    def _auto(self):
        ok, _, _ = self.run(True)
        self.exit_code = 0 if ok else 1
        if self.p["exit_when_done"]:
            import rclpy
            rclpy.try_shutdown()


def main(args=None):
    from ct_calib_nodes.nodes.runner import release_frame_memory, run_node  # noqa: PLC0415

    print(f"[picms_calibration] {release_frame_memory()}", flush=True)   # 5 MP frames: memory flat when idle
    return run_node(PicmsCalibrationNode, args, threads=3)


if __name__ == "__main__":
    import sys
    sys.exit(main())
