"""Record topics to an MCAP file (rosbag2 layout) from raw, exact CDR bytes.

There is no rosbag2 wheel, so this node plays the part of ``ros2 bag record``
for the cell. Like rosbag2 it subscribes once a topic has a publisher,
adapting reliability and durability to what the publishers offer (so it
records best-effort drivers as well as latched results), and stores the raw
serialized bytes it receives with the receive time as log time.

File order is receive order, as with rosbag2. Under load a reliable DDS
sample lost in transport is repaired only at the writer's next heartbeat
(Fast DDS: ~3 s), so a burst of stage readings can land seconds after their
frames. Readers must pair frames and readings by header stamp over the whole
file (ct_offline_solve does), not by neighbourhood in the file.

Parameters
----------
output : str
    ``.mcap`` file or rosbag2 directory to create [path].
topics : string array
    Topics to record; empty = every topic that appears (except /rosout and
    /parameter_events); in a namespace (``__ns:=/cell_a``): every topic under
    it. Relative names resolve against the namespace (``ct/detector/image``).
discovery_period_s : double
    How often to look for new topics [s].
compression : str
    MCAP chunk compression: zstd, lz4 or none.
flush_period_s : double
    Crash safety: every this often the chunk in progress is closed and handed to the
    operating system, so a recorder killed (SIGKILL, power cut of the process) leaves a file
    that readers take up to its last complete chunk: at most this much recording is lost
    (plus what DDS still held). 0 = only when a chunk fills (1 MiB).

Diagnostics (``/diagnostics``, once a second, like every node of the cell: nodes/plant.Diagnostics):
messages and bytes written in total and per topic, the message rate, the age of the last flush
while messages wait in the chunk in progress, messages dropped (samples DDS reports lost to the
recorder's subscriptions, and messages that could not be written), topics that cannot be recorded
(type not installed). WARN when messages were dropped, a topic cannot be recorded, or the
unflushed data is older than 3 flush periods; ERROR when the file cannot be written.
"""

from __future__ import annotations

import time

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from ct_calib_nodes.io.mcap_io import Rosbag2McapWriter, import_message_type
from ct_calib_nodes.nodes import plant
from ct_calib_nodes.nodes.runner import declare_parameters

IGNORED = {"/rosout", "/parameter_events"}
DRAIN_QUIET_S = 1.0     # on stop: close once nothing arrived for this long [s]
DRAIN_MAX_S = 30.0      # on stop: never drain longer than this [s]
PARAMS = {
    "output": ("bags/recording.mcap", "MCAP file (.mcap) or rosbag2 directory to create [path]"),
    "topics": ([""], "topics to record; empty = all"),
    "discovery_period_s": (0.2, "topic discovery period [s]"),
    "compression": ("zstd", "MCAP chunk compression: zstd, lz4, none"),
    "flush_period_s": (1.0, "close the chunk in progress and flush the file this often (crash safety) [s]; 0 = off"),
}


def _qos_dict(q: QoSProfile) -> dict:
    return dict(history="keep_last", depth=q.depth,
                reliability="reliable" if q.reliability == ReliabilityPolicy.RELIABLE else "best_effort",
                durability="transient_local" if q.durability == DurabilityPolicy.TRANSIENT_LOCAL else "volatile",
                deadline=dict(sec=0, nsec=0), lifespan=dict(sec=0, nsec=0), liveliness="automatic",
                liveliness_lease_duration=dict(sec=0, nsec=0), avoid_ros_namespace_conventions=False)


class McapRecorder(Node):
    def __init__(self):
        super().__init__("mcap_recorder")
        p = declare_parameters(self, PARAMS)
        output = p["output"]
        self.wanted = {self.resolve_topic_name(t) for t in p["topics"] if t}
        ns = self.get_namespace()
        self.prefix = "" if ns in ("", "/") else ns.rstrip("/") + "/"   # a cell's recorder records its cell
        comp = p["compression"]
        self.writer = Rosbag2McapWriter(output, compression="" if comp == "none" else comp)
        self.subs = {}
        self.timer = self.create_timer(float(p["discovery_period_s"]), self._discover)
        self._flushed_count = 0
        self.flush_period_s = float(p["flush_period_s"])
        self.written = {}                # topic -> [messages, bytes]
        self.lost = {}                   # topic -> samples DDS reported lost
        self.write_errors, self.last_write_error = 0, ""
        self.unrecordable = []
        self.rate = plant.RateMeter()
        self._flush_t = time.monotonic()
        self.diagnostics = plant.Diagnostics(self, self.diagnose)
        if float(p["flush_period_s"]) > 0:
            self.flush_timer = self.create_timer(float(p["flush_period_s"]), self._flush)
        self._discover()
        self.get_logger().info(f"recording {sorted(self.wanted) if self.wanted else 'all topics'}"
                               f"{' under ' + self.prefix if self.prefix and not self.wanted else ''} to {output}")

    def _discover(self):
        for topic, types in self.get_topic_names_and_types():
            if topic in self.subs or topic in IGNORED or (self.wanted and topic not in self.wanted):
                continue
            if not self.wanted and self.prefix and not topic.startswith(self.prefix):
                continue
            pubs = self.get_publishers_info_by_topic(topic)
            if not pubs or len(types) != 1:
                continue
            reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in pubs)
            latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs)
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000,
                             reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
            type_name = types[0]
            try:
                msg_type = import_message_type(type_name)
            except ValueError as exc:
                self.get_logger().warning(f"cannot record {topic}: type {type_name} not installed ({exc})")
                self.subs[topic] = None
                self.unrecordable.append(f"{topic} [{type_name}]")
                continue
            self.writer.add_topic(topic, type_name, [_qos_dict(qos)])
            self.written[topic] = [0, 0]
            cb = (lambda data, t=topic: self._on_raw(t, data))
            try:
                self.subs[topic] = self.create_subscription(msg_type, topic, cb, qos, raw=True,
                                                            event_callbacks=self._lost_callbacks(topic))
            except Exception:  # noqa: BLE001 - the middleware does not report lost samples: record without
                self.subs[topic] = self.create_subscription(msg_type, topic, cb, qos, raw=True)
            self.get_logger().info(f"recording {topic} [{type_name}] "
                                   f"({'reliable' if reliable else 'best effort'}, "
                                   f"{'transient local' if latched else 'volatile'})")

    def _lost_callbacks(self, topic: str):
        """Count the samples DDS reports lost to this subscription (None when the event is unsupported)."""
        try:
            from rclpy.event_handler import SubscriptionEventCallbacks  # noqa: PLC0415

            def lost(info, t=topic):
                self.lost[t] = self.lost.get(t, 0) + int(info.total_count_change)
            return SubscriptionEventCallbacks(message_lost=lost)
        except Exception:  # noqa: BLE001 - older rclpy: no event, the count stays 0
            return None

    def _flush(self):
        if self.writer.message_count != self._flushed_count:     # no empty chunks while idle
            self.writer.flush()
            self._flushed_count = self.writer.message_count
        self._flush_t = time.monotonic()

    def _on_raw(self, topic: str, data: bytes):
        try:
            self.writer.write_raw(topic, data, self.get_clock().now().nanoseconds)
        except Exception as exc:  # noqa: BLE001 - a disk full / closed file: counted, reported, the node goes on
            self.write_errors += 1
            self.last_write_error = f"{topic}: {exc}"
            if self.write_errors <= 5:
                self.get_logger().error(f"could not write a message of {topic}: {exc}")
            return
        w = self.written[topic]
        w[0] += 1
        w[1] += len(data)
        self.rate.tick()

    def diagnose(self):
        n = sum(w[0] for w in self.written.values())
        nbytes = sum(w[1] for w in self.written.values())
        lost = sum(self.lost.values())
        pending = self.writer.message_count - self._flushed_count
        age = time.monotonic() - self._flush_t
        values = {"messages written": n, "bytes written": nbytes, "message rate [1/s]": self.rate.rate(),
                  "topics recorded": len(self.written),
                  "flush age [s]": age if pending else 0.0, "messages not yet flushed": pending,
                  "dropped (lost in DDS)": lost, "dropped (write errors)": self.write_errors,
                  "topics not recordable": ", ".join(self.unrecordable) or "none"}
        for t, (m, b) in sorted(self.written.items()):
            values[f"messages {t}"] = m
            values[f"bytes {t}"] = b
        for t, m in sorted(self.lost.items()):
            values[f"dropped {t}"] = m
        if self.write_errors:
            return plant.ERROR, (f"{self.write_errors} message(s) could not be written: {self.last_write_error}"), values
        warn = []
        if lost:
            warn.append(f"{lost} message(s) lost before reaching the recorder")
        if self.unrecordable:
            warn.append(f"{len(self.unrecordable)} topic(s) cannot be recorded (type not installed)")
        if pending and self.flush_period_s > 0 and age > 3 * self.flush_period_s:
            warn.append(f"{pending} message(s) not flushed for {age:.0f} s")
        if warn:
            return plant.WARN, "; ".join(warn), values
        return plant.OK, f"recording: {n} messages, {nbytes / 1e6:.1f} MB", values

    def close(self):
        path = self.writer.close()
        self.get_logger().info(f"wrote {self.writer.message_count} messages to {path}")


def main(args=None):
    """Record until SIGINT/SIGTERM, then drain what DDS still holds for us before closing.

    rclpy's own signal handling would shut the context down at once and drop
    messages still queued behind a slow write (a 2 MB frame being compressed);
    rosbag2 likewise flushes on stop. So the recorder handles the signals
    itself: on a stop request it keeps taking messages until none came for
    ``DRAIN_QUIET_S`` (at most ``DRAIN_MAX_S``), then closes the file.
    """
    import signal  # noqa: PLC0415
    import time  # noqa: PLC0415

    from rclpy.executors import SingleThreadedExecutor  # noqa: PLC0415
    from rclpy.signals import SignalHandlerOptions  # noqa: PLC0415

    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(True))
    node = McapRecorder()
    # One executor for the whole run. rclpy.spin_once(node) builds a fresh wait
    # set on every call and serves the first ready subscription in topic order,
    # so under load a backlog of frames can starve the joint states. A
    # persistent executor serves every ready subscription of a wait before
    # waiting again: round robin. (DDS repair delays can still reorder: see
    # the module docstring.)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        while not stop:
            executor.spin_once(timeout_sec=0.1)
        # the recorder's own diagnostics (1 Hz, recorded with everything else) would keep resetting
        # the quiet time: stop them before draining
        diag = getattr(node, "diagnostics", None)
        if diag is not None and getattr(diag, "timer", None) is not None:
            diag.timer.cancel()
        count, t_last, t0 = node.writer.message_count, time.monotonic(), time.monotonic()
        while time.monotonic() - t_last < DRAIN_QUIET_S and time.monotonic() - t0 < DRAIN_MAX_S:
            executor.spin_once(timeout_sec=0.05)
            if node.writer.message_count != count:
                count, t_last = node.writer.message_count, time.monotonic()
    finally:
        node.close()
        executor.remove_node(node)
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == "__main__":
    main()
