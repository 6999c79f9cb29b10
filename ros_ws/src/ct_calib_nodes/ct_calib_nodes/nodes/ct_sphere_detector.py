"""Sphere detection node: CT frames + stage readings -> sphere-centre observations with ids.

Subscribes ``/ct/detector/image`` and ``/ct/stage/joint_states`` and pairs them
by identical ``header.stamp`` (never by arrival order). Each pair goes through
core detection and identity (ct_pipeline.FrameProcessor); the result, accepted
and rejected spheres with reasons, is published on ``/ct/observations``
(metro_msgs/SphereObservationArray, same stamp as the frame). Identity is
initialised from the frames of each stage position themselves (the first
``init_frames`` of a position are published together once it is). Bad frames and
unpaired messages are logged (rate-limited), counted and skipped; the node keeps running.
The pairing buffers are bounded (``pair_max_pending`` messages and ``pair_max_bytes`` bytes
per stream, oldest dropped first, besides ``pair_timeout_s``): frames whose stage readings
never come cannot make the node grow. The reader queue of the image subscription is bounded
in bytes too: with reliable QoS its depth is ``pair_max_bytes`` / (rows x cols x 2 bytes of the
instrument file's detector), at least 2 and at most the shared 200 (2048^2 frames: 32, so 256 MiB),
so a detector that falls behind holds at most about twice ``pair_max_bytes`` of frames, not
200 frames (1.6 GiB at 2048^2); the stage readings keep the shared depth. Frames the full
queue drops never reach the node: each image arriving after them makes the stage readings
stamped before it unpairable, which are dropped and counted at once (``images_lost``; pairing
reason ``overtaken``) instead of after ``pair_timeout_s``. This assumes one image publisher
whose frames arrive in stamp order (a driver, a bag replay); frames published out of stamp
order would lose their stage readings this way (counted, never silent).

Keeping up: the node measures its processing time per frame and the interval
between frame stamps (both smoothed); when it processes slower than frames come,
every such frame is counted (``falling_behind`` in the counts) and a warning
(at most every 10 s) gives both rates. Detection costs about 40 ms per 1024^2
frame on a free core (tests/benchmarks/bench_ct_detect.py), so a real CT's
10 frames/s at 1024^2 is kept up with; at 2048^2 (about 4 times the pixels)
3 frames/s is.
"""

from __future__ import annotations

import time
from collections import deque

from metro_msgs.msg import SphereObservationArray
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import Image, JointState

from ct_calib_nodes.core.ct_pipeline import FrameProcessor, FrameRateMonitor
from ct_calib_nodes.core.detect import FrameError
from ct_calib_nodes.io.convert import MessageError, array_from_image, stage_from_joint_state, stamp_ns
from ct_calib_nodes.io.observations_out import observation_array_msg
from ct_calib_nodes.nodes.bad_input import BadInputCounter
from ct_calib_nodes.nodes.pairing import StampPairer
from ct_calib_nodes.nodes.runner import (CT_FILE_PARAMS, POSITION_PARAMS, QOS_RELIABLE_STREAM, declare_parameters,
                                         load_ct_files, run_node)

IMAGE, STAGE = "ct/detector/image", "ct/stage/joint_states"   # relative: a namespace moves the cell
PARAMS = {
    **CT_FILE_PARAMS,
    **POSITION_PARAMS,
    "init_frames": (6, "frames used to initialise sphere identity at each stage position [count]"),
    "pair_timeout_s": (120.0, "drop an image or stage reading left unpaired this long [s]"),
    "pair_max_pending": (100, "most unpaired images (and stage readings) held, oldest dropped first [count]"),
    "pair_max_bytes": (256 * 1024 * 1024, "most bytes of unpaired images held, oldest dropped first [bytes]"),
    "reliable": (True, "reliable subscriptions (complete campaigns); false = sensor-data QoS for best-effort drivers"),
}


def image_queue_depth(max_bytes: int, rows: int, cols: int, most: int = 200) -> int:
    """Reader queue depth holding about ``max_bytes`` of rows x cols 16-bit frames (2 to ``most``)."""
    return max(2, min(int(most), int(max_bytes) // max(1, 2 * int(rows) * int(cols))))


class CtSphereDetector(Node):
    def __init__(self):
        super().__init__("ct_sphere_detector")
        self.p = p = declare_parameters(self, PARAMS)
        self.instrument, self.ref = load_ct_files(p, self.get_logger())
        self.proc = FrameProcessor(self.ref, self.instrument.detector, self.instrument.sdd_reported_m,
                                   self.instrument.flat_field(), init_frames=int(p["init_frames"]),
                                   srd_tolerance_m=float(p["position_tolerance_m"]), dark=self.instrument.dark)
        self.pairer = StampPairer(int(p["pair_max_pending"]), int(p["pair_max_bytes"]), float(p["pair_timeout_s"]))
        self.bad_input = BadInputCounter(self.get_logger())
        self.counts = {"frames": 0, "bad_frames": 0, "bad_stage": 0, "unpaired": 0, "published": 0,
                       "falling_behind": 0, "images_lost": 0}
        self.rate = FrameRateMonitor()
        self._last_lag_warning = -1e9
        self._dropped_logged = 0
        self._in_hand = None        # stamp of the frame being processed (see _pair)
        self._outbox = deque()      # its results not yet published
        qos = QOS_RELIABLE_STREAM if p["reliable"] else qos_profile_sensor_data
        self.pub = self.create_publisher(SphereObservationArray, "ct/observations", QOS_RELIABLE_STREAM)
        qos_image = qos
        if p["reliable"]:
            det = self.instrument.detector
            self.image_queue_depth = image_queue_depth(int(p["pair_max_bytes"]), det.rows, det.cols,
                                                       QOS_RELIABLE_STREAM.depth)
            qos_image = QoSProfile(history=qos.history, depth=self.image_queue_depth, reliability=qos.reliability,
                                   durability=qos.durability)
            self.get_logger().info(f"image reader queue depth {self.image_queue_depth} "
                                   f"({det.rows}x{det.cols} frames, pair_max_bytes {int(p['pair_max_bytes'])})")
        self.create_subscription(Image, IMAGE, self.bad_input.guard(IMAGE, self._on_image), qos_image)
        self.create_subscription(JointState, STAGE, self.bad_input.guard(STAGE, self._on_stage), qos)
        self.create_timer(1.0, self._expire)
        from ct_calib_nodes.nodes import plant  # noqa: PLC0415
        self.rates = {"image": plant.RateMeter(), "stage": plant.RateMeter()}
        self.last_counts = dict(self.counts)
        self.diagnostics = plant.Diagnostics(self, self.diagnose)

    def _on_image(self, msg):
        self.rates["image"].tick()
        t = stamp_ns(msg.header.stamp)
        pair = self.pairer.add("image", t, msg, len(msg.data))
        lost = self.pairer.drop_older("stage", t)    # their images were lost (dropped by a full queue)
        if lost:
            self.counts["images_lost"] += lost
            self.counts["unpaired"] = self.pairer.total_dropped()
        if pair:
            self._pair(t, *pair)

    def _on_stage(self, msg):
        self.rates["stage"].tick()
        t = stamp_ns(msg.header.stamp)
        pair = self.pairer.add("stage", t, msg, 64 + 16 * len(msg.position) + sum(len(n) for n in msg.name))
        if pair:
            self._pair(t, *pair)

    def _pair(self, t, img, js):
        self.counts["frames"] += 1
        # A stop (SIGINT raises KeyboardInterrupt in the callback) can land while a frame is being
        # processed: the frame's stamp stays in ``_in_hand`` and its results in ``_outbox`` until
        # published, so close() can say what became of it instead of losing it silently.
        self._in_hand = t
        self._process(t, img, js)
        self._in_hand = None

    def _process(self, t, img, js):
        try:
            alpha, srd = stage_from_joint_state(js)
        except MessageError as exc:
            self.counts["bad_stage"] += 1
            self.bad_input.report(STAGE, exc)
            return
        c0 = time.monotonic()
        try:
            image, enc = array_from_image(img, (self.instrument.detector.rows, self.instrument.detector.cols))
            self._outbox.extend(self.proc.push(t, image, enc, alpha, srd))
            self._keep_up(t, time.monotonic() - c0)
        except (MessageError, FrameError, ValueError) as exc:   # never take the node down
            self.counts["bad_frames"] += 1
            self.bad_input.report(IMAGE, exc)
            return
        while self._outbox:
            self._publish(self._outbox[0])
            self._outbox.popleft()

    def _keep_up(self, stamp, seconds):
        if not self.rate.add(stamp, seconds):
            return
        self.counts["falling_behind"] += 1
        now = time.monotonic()
        if now - self._last_lag_warning >= 10.0:
            self._last_lag_warning = now
            self.get_logger().warning(
                f"falling behind: processing {self.rate.processing_hz:.1f} frames/s but frames come at "
                f"{self.rate.arrival_hz:.1f} frames/s (stamps); {self.counts['falling_behind']} frame(s) so far "
                f"processed slower than they came (queued, or dropped by the reader queue: "
                f"{self.counts['images_lost']} image(s) lost so far)")

    def _publish(self, fr):
        from builtin_interfaces.msg import Time  # noqa: PLC0415

        stamp = Time(sec=fr.stamp_ns // 1_000_000_000, nanosec=fr.stamp_ns % 1_000_000_000)
        self.pub.publish(observation_array_msg(fr, stamp, self.instrument.detector))
        self.counts["published"] += 1
        if self.counts["published"] % 24 == 0:
            n_ok = int((fr.flag == 0).sum())
            self.get_logger().info(f"{self.counts['published']} frames published; last: {n_ok} accepted, "
                                   f"{len(fr.flag) - n_ok} rejected; counts {self.counts}")

    def _expire(self):
        self.pairer.expire()
        self.counts["unpaired"] = self.pairer.total_dropped()
        now = time.monotonic()
        if self.counts["unpaired"] != self._dropped_logged and now - getattr(self, "_dropped_t", 0.0) > 10.0:
            self._dropped_logged, self._dropped_t = self.counts["unpaired"], now
            self.get_logger().warning(
                f"{self.counts['unpaired']} unpaired message(s) dropped so far {self.pairer.dropped} "
                f"(bounds: {self.pairer.max_count} messages, {self.pairer.max_bytes} bytes, "
                f"{self.pairer.timeout_s:g} s); pending {self.pairer.pending('image')} image(s), "
                f"{self.pairer.pending('stage')} stage reading(s)")
        self.bad_input.maybe_summarise()

    def diagnose(self):
        from ct_calib_nodes.nodes import plant  # noqa: PLC0415

        c = self.counts
        values = {"image rate [1/s]": self.rates["image"].rate(), "stage rate [1/s]": self.rates["stage"].rate(),
                  "frames": c["frames"], "published": c["published"], "bad frames": c["bad_frames"],
                  "bad stage readings": c["bad_stage"], "unpaired dropped": c["unpaired"],
                  "queue: images waiting for a stage reading": self.pairer.pending("image"),
                  "queue: stage readings waiting for an image": self.pairer.pending("stage")}
        new = {k: c[k] - self.last_counts.get(k, 0) for k in ("bad_frames", "bad_stage", "unpaired")}
        self.last_counts = dict(c)
        if any(new.values()):
            return plant.WARN, ("in the last second: " + ", ".join(f"{v} {k.replace('_', ' ')}" for k, v in new.items()
                                                                    if v)), values
        waiting = self.pairer.pending("image") + self.pairer.pending("stage")
        if waiting > 50:
            return plant.WARN, f"{waiting} messages wait for their partner", values
        return plant.OK, "running" if c["frames"] else "waiting for frames", values

    def close(self):
        ready = list(self._outbox)          # results of the frame in hand at the stop, not yet published
        pending = self.proc.flush()
        known = {fr.stamp_ns for fr in ready + pending}
        interrupted = self._in_hand is not None and self._in_hand not in known
        lost = unsent = 0
        for k, fr in enumerate(ready + pending):
            try:
                self._publish(fr)
            except Exception:  # noqa: BLE001 - the context is already shut down (Ctrl-C): nothing can be sent
                if k < len(ready):
                    unsent += 1
                else:
                    lost += 1
        self._outbox.clear()
        self.pairer.expire()
        self.counts["unpaired"] = self.pairer.total_dropped()
        self.bad_input.maybe_summarise(force=True)
        waiting = {side: self.pairer.pending(side) for side in ("image", "stage")}
        msg = (f"detector counts: {self.counts}; dropped unpaired {self.pairer.dropped}; "
               f"still unpaired at stop {waiting}; "
               f"pairing peak {self.pairer.peak}; bad input {self.bad_input.total}")
        if lost:
            msg += (f"; {lost} frame(s) still held for identity initialisation were not published "
                    "(stopped before the position completed)")
        if unsent:
            msg += f"; {unsent} frame(s) processed at the stop were not published"
        if interrupted:
            msg += (f"; 1 frame in progress at the stop (stamp {self._in_hand} ns) was dropped: "
                    "the stop interrupted its processing")
        print(f"[ct_sphere_detector] {msg}", flush=True)


def main(args=None):
    from ct_calib_nodes.nodes.runner import release_frame_memory  # noqa: PLC0415

    print(f"[ct_sphere_detector] {release_frame_memory()}", flush=True)   # 2-8 MB frames in deep queues
    raise SystemExit(run_node(CtSphereDetector, args))


if __name__ == "__main__":
    main()
