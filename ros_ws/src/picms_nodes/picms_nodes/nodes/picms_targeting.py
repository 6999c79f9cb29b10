"""Pixel Probe targeting node: drives X* onto a target and records the point.

Action picms/drive_probe (metro_msgs/action/DriveProbe): a target given as pixels in >= 2
images (Direct Mode: the third view is predicted and checked) or as ROIs around a circular
feature (Feature Mode, mode "circle"); each iteration's offset is sent as feedback; the result
holds the point in the stage frame (tracker-free mode) and, when the constellation was read,
in the tracker frame (tracker mode), with covariances. The point is also published on
picms/targeting/point_stage and picms/targeting/point_tracker (geometry_msgs/PointStamped).

The probe comes from picms_calibration.yaml (`calibration_file`, re-read when it changes) and
the CameraInfo intrinsics; the cell is a RosCell (nodes/ros_cell.py) over the INTERFACES.md
topics. One goal at a time; a bad goal is rejected with the reason, a failed one aborts with it.
A cancel request is accepted and honoured between iterations (the stage settled, no move
pending): the goal ends canceled with the iterations done so far.
"""
from __future__ import annotations

import pathlib
import threading

import numpy as np
from geometry_msgs.msg import PointStamped
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node

from metro_msgs.action import DriveProbe

from ct_calib_nodes.nodes.runner import QOS_LATCHED, declare_parameters

from ..core.targeting import (Probe, TargetingError, circle_feature_locator, direct_locator, drive_to)
from .ros_cell import CELL_PARAMS, open_cell

ACTION = "picms/drive_probe"
POINT_STAGE_TOPIC = "picms/targeting/point_stage"
POINT_TRACKER_TOPIC = "picms/targeting/point_tracker"

PARAMS = {
    **CELL_PARAMS,
    "max_moves": (6, "default bound on the moves per target [count]"),
    "settle_timeout_s": (30.0, "give up when the stage has not settled this long after a command [s]"),
}


class _Canceled(Exception):
    """The goal was canceled; raised from drive_to's progress callback (between iterations, stage settled)."""


def goal_locator(goal, names):
    """(locator, description) of a DriveProbe goal; TargetingError naming what is wrong."""
    mode = str(goal.mode).strip().lower()
    cams = list(goal.cameras)
    unknown = [c for c in cams if c not in names]
    if unknown:
        raise TargetingError(f"unknown cameras {unknown}; the probe has {names}")
    if mode == "direct":
        px = np.asarray(goal.pixels, float)
        if px.size != 2 * len(cams) or len(cams) < 2:
            raise TargetingError(f"direct: {len(cams)} cameras need 2 pixel values each (>= 2 cameras), "
                                 f"got {px.size} values")
        return direct_locator({c: px[2 * k:2 * k + 2] for k, c in enumerate(cams)}), f"direct {cams}"
    if mode == "circle":
        if not goal.diameter > 0:
            raise TargetingError(f"circle: diameter must be > 0 m, got {goal.diameter}")
        r = np.asarray(goal.rois, float)
        if r.size == 0:
            roi = None
        elif r.size != 4 * len(cams) or len(cams) < 2:
            raise TargetingError(f"circle: {len(cams)} cameras need 4 ROI values each (>= 2 cameras), got {r.size}")
        else:
            roi = {c: tuple(r[4 * k:4 * k + 4]) for k, c in enumerate(cams)}
        return circle_feature_locator(roi, float(goal.diameter)), f"circle d={goal.diameter * 1e3:.3f} mm"
    raise TargetingError(f"unknown mode {goal.mode!r}: direct or circle")


class PicmsTargetingNode(Node):
    def __init__(self):
        super().__init__("picms_targeting")
        self.p = p = declare_parameters(self, PARAMS)
        self.cell_yaml, self.cell = open_cell(self, p)
        self.busy = threading.Lock()
        self._probe = None
        self._probe_key = None
        self.pub_stage = self.create_publisher(PointStamped, POINT_STAGE_TOPIC, QOS_LATCHED)
        self.pub_tracker = self.create_publisher(PointStamped, POINT_TRACKER_TOPIC, QOS_LATCHED)
        self.server = ActionServer(self, DriveProbe, ACTION, execute_callback=self.execute,
                                   goal_callback=self.on_goal, cancel_callback=lambda _: CancelResponse.ACCEPT,
                                   callback_group=ReentrantCallbackGroup())
        self.get_logger().info(f"targeting ready: action {self.resolve_topic_name(ACTION)}, "
                               f"calibration {p['calibration_file']}")

    def probe(self) -> Probe:
        """The probe from the calibration file and CameraInfo (re-read when the file changes)."""
        path = pathlib.Path(self.p["calibration_file"])
        try:
            key = (path.stat().st_mtime_ns, tuple(sorted(self.cell.camera_info)))
        except OSError as exc:
            raise TargetingError(f"calibration file {path}: {exc}") from exc
        if key != self._probe_key:
            self._probe = Probe.from_calibration_yaml(path, dict(self.cell.camera_info))
            self._probe_key = key
        return self._probe

    def on_goal(self, goal):
        if self.busy.locked():
            self.get_logger().warning("goal rejected: a target is being driven")
            return GoalResponse.REJECT
        try:
            goal_locator(goal, list(self.p["cameras"]))
        except TargetingError as exc:
            self.get_logger().warning(f"goal rejected: {exc}")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def execute(self, gh):
        res = DriveProbe.Result()
        if not self.busy.acquire(blocking=False):
            gh.abort()
            res.message = "a target is being driven"
            return res
        try:
            goal = gh.request
            loc, what = goal_locator(goal, list(self.p["cameras"]))
            self.cell.wait_ready(float(self.p["ready_timeout_s"]))
            probe = self.probe()

            def feedback(it):
                fb = DriveProbe.Feedback()
                fb.iteration = int(it["iteration"])
                fb.q = [float(v) for v in it["q"]]
                fb.offset = [float(v) for v in it["offset"]]
                fb.offset_norm = float(it["offset_norm"])
                fb.n_cameras = int(it["n_cameras"])
                fb.move_steps = [int(v) for v in it["move_steps"]]
                gh.publish_feedback(fb)
                self.get_logger().info(f"iteration {fb.iteration}: offset {np.round(it['offset'] * 1e6, 2).tolist()} um "
                                       f"({fb.n_cameras} cameras), next move {fb.move_steps} steps")
                done.append(it)
                if gh.is_cancel_requested:        # the stage is settled here: stop before the next move
                    raise _Canceled()

            done = []
            r = drive_to(self.cell, probe, loc, tol_m=(goal.tolerance if goal.tolerance > 0 else None),
                         max_iter=int(goal.max_moves) if goal.max_moves > 0 else int(self.p["max_moves"]),
                         progress=feedback)
            res.success, res.message = bool(r.ok), f"{what}: {r.reason}"
            if np.all(np.isfinite(r.p_stage)):
                res.q = [float(v) for v in r.q]
                res.offset_stage = [float(v) for v in r.offset_stage]
                res.p_stage = [float(v) for v in r.p_stage]
                res.cov_stage = [float(v) for v in np.ravel(r.cov_stage)]
                if r.p_tracker is not None:
                    res.has_tracker = True
                    res.p_tracker = [float(v) for v in r.p_tracker]
                    res.cov_tracker = [float(v) for v in np.ravel(r.cov_tracker)]
            res.iterations = len(r.iterations)
            res.iteration_offsets = [float(v) for it in r.iterations for v in it["offset"]]
            res.elapsed_s = float(r.elapsed_s)
            if r.ok:
                self._publish_points(r)
                self.get_logger().info(f"{res.message}; point (stage) {np.round(r.p_stage * 1e3, 5).tolist()} mm")
                gh.succeed()
            else:
                self.get_logger().error(f"target failed: {res.message}")
                gh.abort()
        except _Canceled:
            last = done[-1]
            res.success, res.iterations = False, len(done)
            res.q = [float(v) for v in last["q"]]
            res.iteration_offsets = [float(v) for it in done for v in it["offset"]]
            res.message = (f"{what}: canceled after {len(done)} iterations; stage settled at "
                           f"{np.round(last['q'] * 1e3, 4).tolist()} mm, no move pending")
            self.get_logger().info(res.message)
            gh.canceled()
        except (TargetingError, ValueError, TimeoutError) as exc:
            res.success, res.message = False, str(exc)
            self.get_logger().error(f"target failed: {exc}")
            gh.abort()
        finally:
            self.busy.release()
        return res

    def _publish_points(self, r):
        stamp = self.get_clock().now().to_msg()
        for pub, p, frame in ((self.pub_stage, r.p_stage, "stage"), (self.pub_tracker, r.p_tracker, "tracker")):
            if p is None:
                continue
            m = PointStamped()
            m.header.stamp = stamp
            m.header.frame_id = frame
            m.point.x, m.point.y, m.point.z = (float(v) for v in p)
            pub.publish(m)


def main(args=None):
    from ct_calib_nodes.nodes.runner import run_node  # noqa: PLC0415

    return run_node(PicmsTargetingNode, args, threads=4)


if __name__ == "__main__":
    import sys
    sys.exit(main())
