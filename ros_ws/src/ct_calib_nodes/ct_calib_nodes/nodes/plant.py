"""What makes a node a plant citizen: its calibration history and its diagnostics.

- :class:`HistoryHook`: stores every solve of the node in the calibration
  history (io/history.py; parameter ``history_db``: a path, empty = the
  default (``$METRO_HISTORY_DB`` or ``~/.local/share/metro_cell/history.sqlite``),
  ``none`` = off) under the node's namespace as the cell name, and returns the
  latest valid published message of a kind so the node can re-publish it
  latched at start.
- :class:`Diagnostics`: diagnostic_msgs/DiagnosticArray on ``/diagnostics``
  (absolute: the ROS convention read by rqt_robot_monitor and the diagnostic
  aggregator; the status name carries the node's full name, so cells in
  different namespaces stay apart) once a second, from the node's
  ``diagnose()`` -> (level, message, {key: value}).

The Pixel Probe nodes use the same two classes with their own kinds.
"""

from __future__ import annotations

import time
from collections import deque

HISTORY_PARAMS = {
    "history_db": ("", "calibration history database: a path; empty = $METRO_HISTORY_DB or "
                       "~/.local/share/metro_cell/history.sqlite; none = do not record [path]"),
}

OK, WARN, ERROR, STALE = 0, 1, 2, 3


class HistoryHook:
    def __init__(self, node, path: str = ""):
        from ct_calib_nodes.io.history import cell_name, open_history  # noqa: PLC0415

        self.node = node
        self.cell = cell_name(node.get_namespace())
        self.history = open_history(path or None, logger=node.get_logger().warning)
        if self.history is not None:
            node.get_logger().info(f"calibration history: {self.history.path} (cell {self.cell})")

    def store(self, rec, msg=None, type_name: str = ""):
        """Record a solve; with ``msg``, the published message goes with it (re-published at restart).
        Never raises: a history that cannot be written is logged, the calibration goes on."""
        if self.history is None:
            return None
        from ct_calib_nodes.io.ct_history import ros_msg_blob  # noqa: PLC0415

        try:
            if msg is not None:
                from rclpy.serialization import serialize_message  # noqa: PLC0415
                rec.result["ros_msg"] = ros_msg_blob(type_name, serialize_message(msg))
            rec.cell = self.cell
            return self.history.record(rec)
        except Exception as exc:  # noqa: BLE001 - the cell keeps working without its history
            self.node.get_logger().error(f"calibration history: could not store the {rec.kind} solve: {exc}")
            return None

    def latest_msg(self, kind: str, msg_type, type_name: str, mode=None):
        """(record, message) of the newest SUCCESS solve of this cell and kind that carries its
        published message, or (None, None)."""
        if self.history is None:
            return None, None
        from rclpy.serialization import deserialize_message  # noqa: PLC0415

        from ct_calib_nodes.io.ct_history import ros_msg_bytes  # noqa: PLC0415

        try:
            for rec in self.history.list(cell=self.cell, kind=kind, status="success", newest_first=True, limit=50):
                if mode is not None and rec.result.get("mode") != mode:
                    continue
                if self.history.superseded(rec.uid):      # a later verdict withdrew it (e.g. POOR_FIT)
                    continue
                data = ros_msg_bytes(rec.result, type_name)
                if data is not None:
                    return rec, deserialize_message(data, msg_type)
        except Exception as exc:  # noqa: BLE001
            self.node.get_logger().error(f"calibration history: could not read the latest {kind}: {exc}")
        return None, None

    def supersede(self, original, status, message: str, msg=None, type_name: str = "", extra=None):
        """Append a record superseding ``original`` (History.supersede) with the re-published message.
        Never raises (logged)."""
        if self.history is None or original is None:
            return None
        from ct_calib_nodes.io.ct_history import ros_msg_blob  # noqa: PLC0415

        try:
            extra = dict(extra or {})
            if msg is not None:
                from rclpy.serialization import serialize_message  # noqa: PLC0415
                extra["ros_msg"] = ros_msg_blob(type_name, serialize_message(msg))
            return self.history.supersede(original, status, message, extra)
        except Exception as exc:  # noqa: BLE001
            self.node.get_logger().error(f"calibration history: could not store the {status} verdict "
                                         f"on solve {getattr(original, 'id', '?')}: {exc}")
            return None

    def latest_published(self, kind: str, msg_type, type_name: str):
        """(record, message) of what this cell published last for ``kind`` as stored: the newest SUCCESS
        solve with its message, unless a later record supersedes it (then that record, e.g. POOR_FIT),
        or (None, None). Failed solves that were never published do not count."""
        if self.history is None:
            return None, None
        from rclpy.serialization import deserialize_message  # noqa: PLC0415

        from ct_calib_nodes.io.ct_history import ros_msg_bytes  # noqa: PLC0415

        try:
            for rec in self.history.list(cell=self.cell, kind=kind, newest_first=True, limit=100):
                if rec.status != "success" and "supersedes" not in rec.result:
                    continue
                if rec.status == "success" and self.history.superseded(rec.uid):
                    continue
                data = ros_msg_bytes(rec.result, type_name)
                if data is not None:                     # with inputs and quantities (a later supersede copies them)
                    return self.history.get(rec.id), deserialize_message(data, msg_type)
        except Exception as exc:  # noqa: BLE001
            self.node.get_logger().error(f"calibration history: could not read the latest {kind}: {exc}")
        return None, None

    def close(self):
        if self.history is not None:
            self.history.close()


class RateMeter:
    """Messages per second over the last ``window_s``."""

    def __init__(self, window_s: float = 10.0):
        self.window_s = window_s
        self.t = deque()
        self.total = 0

    def tick(self):
        now = time.monotonic()
        self.t.append(now)
        self.total += 1
        while now - self.t[0] > self.window_s:      # bounded even when rate() is never asked
            self.t.popleft()

    def rate(self) -> float:
        now = time.monotonic()
        while self.t and now - self.t[0] > self.window_s:
            self.t.popleft()
        return len(self.t) / self.window_s


class Diagnostics:
    def __init__(self, node, diagnose, period_s: float = 1.0, hardware_id: str = ""):
        from diagnostic_msgs.msg import DiagnosticArray  # noqa: PLC0415

        self.node = node
        self.diagnose = diagnose
        self.name = node.get_fully_qualified_name()
        self.hardware_id = hardware_id or (node.get_namespace() or "/")
        self.pub = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.timer = node.create_timer(period_s, self.publish)

    def publish(self):
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue  # noqa: PLC0415

        try:
            level, message, values = self.diagnose()
        except Exception as exc:  # noqa: BLE001 - diagnostics must never take the node down
            level, message, values = ERROR, f"diagnostics failed: {exc}", {}
        arr = DiagnosticArray()
        arr.header.stamp = self.node.get_clock().now().to_msg()
        st = DiagnosticStatus(level=bytes([int(level)]), name=self.name, message=str(message),
                              hardware_id=self.hardware_id)
        st.values = [KeyValue(key=str(k), value=_text(v)) for k, v in values.items()]
        arr.status = [st]
        try:
            self.pub.publish(arr)
        except Exception:  # noqa: BLE001 - shutting down: the context may be gone
            pass


def refused_as_other_campaign(node, msg) -> bool:
    """Observations of another campaign interleaved with the node's (``node.guard``): refused,
    counted, logged (the first five, then every 50th)."""
    from ct_calib_nodes.io.convert import stamp_ns  # noqa: PLC0415

    try:
        why = node.guard.check(stamp_ns(msg.header.stamp), msg.srd_reported_m, msg.rotary_angle_rad)
    except (TypeError, ValueError):
        return False           # the intake names what is wrong with the message
    if why is not None:
        if node.guard.refused <= 5 or node.guard.refused % 50 == 0:
            node.get_logger().error(f"refused observations #{node.guard.refused}: {why}")
        return True
    return False


def accept_campaign_msg(guard, msg) -> None:
    """Record an observation message the node took into its campaign."""
    from ct_calib_nodes.io.convert import stamp_ns  # noqa: PLC0415

    guard.accept(stamp_ns(msg.header.stamp), msg.srd_reported_m, msg.rotary_angle_rad)


def take_campaign_observation(node, msg):
    """The solver nodes' intake of one observation message: the rate and a campaign change (the
    journal resets the node's campaign) for live messages, other campaigns refused, then
    ``node.intake``; a message taken is accepted into the campaign guard and journaled. Returns
    the stage position index it went to, or None (refused or bad: counted and logged)."""
    if not node.journal.replaying:
        node.obs_rate.tick()
        if not node.journal.continues(msg, node.guard):
            node.reset_campaign()
    if refused_as_other_campaign(node, msg):
        return None
    k = node.intake.add(msg)
    if k is not None:
        accept_campaign_msg(node.guard, msg)
        node.journal.accepted(msg)
    return k


def _text(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def solve_age_text(t_mono) -> str:
    return "never" if t_mono is None else f"{time.monotonic() - t_mono:.0f} s"
