"""PiCMS measurement node: runs a part program on the live cell and writes measurement.json.

Service picms/run_measurement (std_srvs/srv/Trigger): runs the part program named by the
`part_program` parameter (core.measure on a RosCell over the INTERFACES.md topics, the probe
from `calibration_file` and CameraInfo), publishes every point as it is measured on
picms/measurement/point (geometry_msgs/PointStamped, frame `stage` or `tracker` per `mode`),
and the fitted result latched on picms/measurement/result (std_msgs/String, the JSON of
measurement.json without the raw points). measurement.json (and its .crops.npz) is written
atomically to `output_file`, only on success. `auto_start` runs once at start-up.
A failure is logged and answered (success false, the reason); the node keeps running.
"""
from __future__ import annotations

import json
import pathlib
import threading

import numpy as np
from geometry_msgs.msg import PointStamped
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ct_calib_nodes.nodes.runner import QOS_LATCHED, declare_parameters

from ..core import fitting, measure, part_program
from ..core.targeting import Probe, TargetingError
from .ros_cell import CELL_PARAMS, open_cell

SERVICE = "picms/run_measurement"
POINT_TOPIC = "picms/measurement/point"
RESULT_TOPIC = "picms/measurement/result"

PARAMS = {
    **CELL_PARAMS,
    "part_program": ("", "part_program.yaml to run [path]"),
    "output_file": ("measurement.json", "where measurement.json is written (atomically, on success) [path]"),
    "mode": ("stage", "stage (tracker-free, encoders) or tracker (constellation) [-]"),
    "max_moves": (4, "bound on the targeting moves per point [count]"),
    "auto_start": (False, "run the part program once at start-up [-]"),
    "history_db": ("", "calibration history (kind picms_measurement); empty = METRO_HISTORY_DB or the default, "
                       "none = off [path]"),
}


class PicmsMeasurementNode(Node):
    def __init__(self):
        super().__init__("picms_measurement")
        self.p = p = declare_parameters(self, PARAMS)
        if p["mode"] not in ("stage", "tracker"):
            raise ValueError(f"mode must be stage or tracker, got {p['mode']!r}")
        self.cell_yaml, self.cell = open_cell(self, p)
        self.busy = threading.Lock()
        from ct_calib_nodes.nodes.plant import HistoryHook
        self.history = HistoryHook(self, str(p["history_db"]))
        self.pub_point = self.create_publisher(PointStamped, POINT_TOPIC, 50)
        self.pub_result = self.create_publisher(String, RESULT_TOPIC, QOS_LATCHED)
        self.srv = self.create_service(Trigger, SERVICE, self.on_trigger, callback_group=ReentrantCallbackGroup())
        self.get_logger().info(f"measurement ready: service {self.resolve_topic_name(SERVICE)}, "
                               f"program {p['part_program'] or '(none set)'}")
        if p["auto_start"]:
            threading.Thread(target=self.run, daemon=True).start()

    def on_trigger(self, _req, resp):
        resp.success, resp.message = self.run()
        return resp

    def run(self):
        if not self.busy.acquire(blocking=False):
            return False, "a measurement is running"
        try:
            if not str(self.p["part_program"]).strip():
                raise ValueError("no part program: set the part_program parameter (a part_program.yaml)")
            prog = part_program.load(self.p["part_program"])
            self.cell.wait_ready(float(self.p["ready_timeout_s"]))
            cal_path = pathlib.Path(self.p["calibration_file"])
            import yaml
            cal = yaml.safe_load(cal_path.read_text())
            probe = Probe.from_calibration_yaml(cal, dict(self.cell.camera_info))
            mode = self.p["mode"]

            def progress(d):
                if d.get("event") != "point":
                    self.get_logger().info(str(d.get("message", d)))
                    return
                self.get_logger().info(f"{d['n']}/{d['of']} {d['feature']}[{d['index']}]: "
                                       f"{'ok' if d['ok'] else 'FAILED ' + d['reason']}, {d['iterations']} "
                                       f"triangulations, {d['elapsed_s']:.1f} s")
                p = d["p_stage"] if mode == "stage" else d["p_tracker"]
                if d["ok"] and p is not None and np.all(np.isfinite(p)):
                    m = PointStamped()
                    m.header.stamp = self.get_clock().now().to_msg()
                    m.header.frame_id = mode
                    m.point.x, m.point.y, m.point.z = (float(v) for v in p)
                    self.pub_point.publish(m)

            run = measure.measure(self.cell, probe, prog, progress=progress, max_iter=int(self.p["max_moves"]))
            doc = measure.measurement_document(run, probe, mode=mode, calibration=cal)
            out = measure.write_json_atomic(doc, self.p["output_file"])
            measure.write_crops(run, pathlib.Path(out).with_suffix(".crops.npz"))
            summary = {k: v for k, v in doc.items() if k not in ("points", "probe")}
            self.pub_result.publish(String(data=json.dumps(summary, default=measure._json_default)))
            self.store(json.loads(json.dumps(summary, default=measure._json_default)), out, cal_path)
            msg = f"measured {doc['summary']['n_ok']}/{doc['summary']['n_points']} points; written {out}"
            self.get_logger().info(msg)
            return True, msg
        except (part_program.PartProgramError, TargetingError, fitting.FitError, ValueError, OSError,
                TimeoutError) as exc:
            self.get_logger().error(f"measurement failed (nothing written): {exc}")
            self.store(None, None, None, message=str(exc))
            return False, str(exc)
        finally:
            self.busy.release()

    def store(self, summary, out, cal_path, message=""):
        """The measurement (or its failure) in the calibration history, linked to its files."""
        from ct_calib_nodes.io.history import Input
        from ..io.picms_history import measurement_record
        inputs = []
        for role, path in (("part_program", self.p["part_program"]), ("picms_calibration_yaml", cal_path),
                           ("measurement_json", out)):
            try:
                if path and pathlib.Path(path).is_file():
                    inputs.append(Input.file(role, pathlib.Path(path)))
            except OSError:
                pass
        try:
            rec = measurement_record(summary, cell=self.history.cell, source="live", inputs=inputs, message=message)
        except (KeyError, TypeError, ValueError) as exc:
            self.get_logger().error(f"calibration history: measurement not stored: {exc}")
            return
        r = self.history.store(rec)
        if r is not None:
            self.get_logger().info(f"measurement stored in the calibration history ({rec.status})")


def main(args=None):
    from ct_calib_nodes.nodes.runner import run_node  # noqa: PLC0415

    return run_node(PicmsMeasurementNode, args, threads=4)


if __name__ == "__main__":
    raise SystemExit(main())
