"""The Pixel Probe calibration node as a plant citizen: its calibration history and its diagnostics
(the CT cell's ct_calib_nodes.nodes.plant classes, with the PiCMS kind).

- every calibration run, usable or not, is stored (kind ``picms_calibration``, source ``live``,
  the cell file's sha256 and the live topics with their stamp range as inputs, the published
  message with it);
- at start the latest valid calibration of the cell (live or offline) is re-published latched on
  ``picms/calibration``, so a restarted node or a late subscriber never sees "no calibration";
- a run that is not SUCCESS never replaces a valid calibration on the topic (it is logged, stored,
  returned by the service and reported on ``/diagnostics``);
- ``/diagnostics``: stage-reading and image rates, cameras with CameraInfo, frames detected and
  skipped, calibrating or idle, last run status and age, valid calibration published.
"""
from __future__ import annotations

import time

from ct_calib_nodes.nodes import plant

from ..io.picms_history import KIND, MSG_TYPE, calibration_record

SUCCESS = 0


class PicmsPlant:
    def __init__(self, node, history_db: str = ""):
        from metro_msgs.msg import PicmsCalibration  # noqa: PLC0415

        self.node = node
        self.history = plant.HistoryHook(node, str(history_db))
        self.valid_msg = None
        self.last_status, self.last_t = None, None
        self.joints, self.images = plant.RateMeter(), plant.RateMeter()
        rec, msg = self.history.latest_msg(KIND, PicmsCalibration, MSG_TYPE)
        if msg is not None:
            self.valid_msg = msg
            node.pub.publish(msg)
            node.get_logger().info(f"re-published the latest valid Pixel Probe calibration of cell {self.history.cell}: "
                                   f"history solve {rec.id} of {rec.created_utc} ({rec.source})")
        self.diagnostics = plant.Diagnostics(node, self.diagnose)

    def publish(self, msg) -> bool:
        """Publish a run's message unless it is not SUCCESS and a valid calibration is held."""
        self.last_status, self.last_t = (int(msg.status.code), str(msg.status.message)), time.monotonic()
        if msg.status.code == SUCCESS or self.valid_msg is None:
            self.node.pub.publish(msg)
            if msg.status.code == SUCCESS:
                self.valid_msg = msg
            return True
        self.node.get_logger().error("the calibration is not usable: not published; the last valid calibration "
                                     f"(stamp {self.valid_msg.header.stamp.sec} s) stays on picms/calibration")
        return False

    def store(self, res, msg, message: str | None, cell_file, joint_stamps_ns):
        from ct_calib_nodes.io.history import Input  # noqa: PLC0415

        n = self.node
        topics = Input(role="topic", path=n.resolve_topic_name("picms/stage/joint_states"),
                       detail={"cameras": list(n.p["cameras"]), "readings": len(joint_stamps_ns)})
        rec = calibration_record(res, cell=self.history.cell, source="live",
                                 inputs=[Input.file("picms_cell_yaml", cell_file), topics],
                                 joint_stamps_ns=joint_stamps_ns, message=message)
        self.history.store(rec, msg, MSG_TYPE)

    def diagnose(self):
        n = self.node
        cams = list(n.p["cameras"])
        values = {"stage readings": self.joints.total, "stage reading rate [1/s]": self.joints.rate(),
                  "images": self.images.total, "image rate [1/s]": self.images.rate(),
                  "cameras with CameraInfo": f"{sum(c in n.info for c in cams)} of {len(cams)}",
                  "calibrating": "yes" if n.busy.locked() else "no",
                  "frames detected (this run)": len(n.dets), "frames skipped": n.skipped,
                  "last calibration": "none" if self.last_status is None else
                  f"{'SUCCESS' if self.last_status[0] == SUCCESS else 'code ' + str(self.last_status[0])}: "
                  f"{self.last_status[1]}",
                  "last calibration age": plant.solve_age_text(self.last_t),
                  "valid calibration published": "yes" if self.valid_msg is not None else "no"}
        if self.last_status is not None and self.last_status[0] != SUCCESS:
            if self.valid_msg is not None:
                return plant.WARN, ("the last calibration failed; the previous valid calibration stays published: "
                                    f"{self.last_status[1]}"), values
            return plant.ERROR, f"no valid calibration: the last run failed: {self.last_status[1]}", values
        if self.valid_msg is None:
            return plant.WARN, "no calibration yet (call picms/run_calibration)", values
        return plant.OK, "calibrated", values


class SimDiagnostics:
    """/diagnostics of a simulator node: what it published (count, rate), and WARN while it waits for its
    input (``waiting()`` -> reason or None) or after bad commands (``bad`` counted by the node)."""

    def __init__(self, node, what: str, waiting=None):
        self.node, self.what, self.waiting = node, what, waiting
        self.sent = plant.RateMeter()
        self.bad = 0
        self.diagnostics = plant.Diagnostics(node, self.diagnose)

    def diagnose(self):
        values = {f"{self.what} published": self.sent.total, f"{self.what} rate [1/s]": self.sent.rate(),
                  "bad commands ignored": self.bad}
        why = self.waiting() if self.waiting is not None else None
        if why:
            return plant.WARN, why, values
        if self.bad:
            return plant.WARN, f"{self.bad} bad command(s) ignored (see the log)", values
        return plant.OK, f"publishing {self.what}", values
