"""Sim-to-real discrepancy node (issue 11): the engine of core/ct_discrepancy.py on the live graph.

Collects ``ct/observations`` (SphereObservationArray, as the solvers do, with the same campaign guard)
and the latched static geometry ``ct/geometry``. After each geometry solve (a new CtGeometry with status
SUCCESS) it runs the discrepancy engine on the first stage position's observations up to the geometry's
stamp (the data that geometry rests on) with that geometry as the nominal calibration, and publishes
``ct/discrepancy`` (metro_msgs/DiscrepancyReport, latched): verdict, adequate, noise floor, findings with
parameters and uncertainties, unexplained structure, detection limits, and the whole report as JSON.
The report's status is SUCCESS when the model is adequate and POOR_FIT when it was found inadequate;
ct_geometry_solver re-publishes its geometry with POOR_FIT on such a report (its parameter
``mark_inadequate``), so plant software reading ``ct/geometry`` sees it.

Every stage position: after each error-map solve (a new ``ct/error_map`` of ct_error_motion, mode multi) it
judges every stage position of that map, each with its own 13-parameter calibration
(ct_discrepancy.judge_position; a position judged once is not judged again while its frames are the same),
fits the named terms against SRD and tests the calibrated focal spot for a campaign-long drift
(ct_discrepancy.campaign_drift), and publishes ``ct/discrepancy/error_map`` (DiscrepancyReport, latched;
stamp = the map's stamp; POOR_FIT when a position or the campaign was found inadequate; report_json carries
``stage_positions``). ct_error_motion re-publishes that map with the inadequate positions' motions marked
POOR_FIT. Stored in the history as kind ``discrepancy_error_map`` (parameter ``judge_error_map``).

Topic names are relative (``--ros-args -r __ns:=/cell_a``). Every report is stored in the calibration
history as kind ``discrepancy`` (parameter ``history_db``); at start the latest one of the cell is
re-published latched. The engine runs in the executor's thread (about 1-3 s for 72 projections of 49
spheres on a loaded 2-core machine); observations arriving meanwhile queue (reliable, depth 200).
"""

from __future__ import annotations

import time

import numpy as np
from metro_msgs.msg import CtGeometry, DiscrepancyReport, ErrorMap, SphereObservationArray
from rclpy.node import Node

from ct_calib_nodes.nodes import plant
from ct_calib_nodes.nodes.bad_input import BadInputCounter
from ct_calib_nodes.nodes.runner import (CT_FILE_PARAMS, QOS_LATCHED, QOS_RELIABLE_STREAM, ObservationIntake,
                                         declare_parameters, load_ct_files, run_node)

KIND, MSG_TYPE = "discrepancy", "metro_msgs/msg/DiscrepancyReport"
KIND_MAP = "discrepancy_error_map"
PARAMS = {
    **CT_FILE_PARAMS,
    **plant.HISTORY_PARAMS,
    "max_terms": (4, "most catalogue terms the engine adds [count]"),
    "wait_for_observations_s": (10.0, "how long a new geometry waits for the observations it rests on to arrive "
                                      "before the node reports INSUFFICIENT_DATA [s]"),
    "min_frames": (8, "fewest projections of a stage position the engine judges [count]"),
    "judge_error_map": (True, "after each error-map solve judge every stage position and the campaign, publish "
                              "ct/discrepancy/error_map"),
}


def _stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


class CtDiscrepancyNode(Node):
    def __init__(self):
        super().__init__("ct_discrepancy")
        self.p = declare_parameters(self, PARAMS)
        self.instrument, self.ref = load_ct_files(self.p, self.get_logger())
        self.bad_input = BadInputCounter(self.get_logger())
        self.intake = ObservationIntake(self, self.ref)
        self.acc = self.intake.acc
        self.pub = self.create_publisher(DiscrepancyReport, "ct/discrepancy", QOS_LATCHED)
        self.create_subscription(SphereObservationArray, "ct/observations",
                                 self.bad_input.guard("ct/observations", self._on_obs), QOS_RELIABLE_STREAM)
        self.create_subscription(CtGeometry, "ct/geometry", self.bad_input.guard("ct/geometry", self._on_geometry),
                                 QOS_LATCHED)
        self.map_pub = self.create_publisher(DiscrepancyReport, "ct/discrepancy/error_map", QOS_LATCHED)
        if bool(self.p["judge_error_map"]):
            self.create_subscription(ErrorMap, "ct/error_map", self.bad_input.guard("ct/error_map", self._on_map),
                                     QOS_LATCHED)
        self.pending_map, self.map_since = None, None       # error map waiting for its observations
        self.maps_judged, self.rows = set(), {}             # (stamp_ns, K); position -> (key, row or skip)
        self.create_timer(0.5, self._on_timer)
        self.history = plant.HistoryHook(self, str(self.p["history_db"]))
        from ct_calib_nodes.io.campaign_guard import CampaignGuard  # noqa: PLC0415
        self.guard = CampaignGuard(self.history.cell)
        self.obs_rate = plant.RateMeter()
        self.pending, self.pending_since = None, None      # geometry waiting for its observations
        self.analysed = set()                               # (stamp_ns, values) of geometries judged
        self.last_report, self.last_t, self.runs = None, None, 0
        self.last_map_report = None
        rec, msg = self.history.latest_msg(KIND, DiscrepancyReport, MSG_TYPE)
        if msg is None and self.history.history is not None:   # an inadequate verdict is stored as poor_fit
            msg = self._latest_any(KIND)
        if msg is not None:
            self.last_report = msg
            self.pub.publish(msg)
            self.get_logger().info(f"re-published the latest discrepancy report of cell {self.history.cell}")
        _rec, mmsg = self.history.latest_msg(KIND_MAP, DiscrepancyReport, MSG_TYPE)
        if mmsg is None and self.history.history is not None:
            mmsg = self._latest_any(KIND_MAP)
        if mmsg is not None:
            self.map_pub.publish(mmsg)
            self.get_logger().info(f"re-published the latest stage-position report of cell {self.history.cell}")
        self.diagnostics = plant.Diagnostics(self, self.diagnose)
        self.get_logger().info(f"waiting for {self.resolve_topic_name('ct/geometry')} and "
                               f"{self.resolve_topic_name('ct/observations')}")

    def _latest_any(self, kind):
        from rclpy.serialization import deserialize_message  # noqa: PLC0415

        from ct_calib_nodes.io.ct_history import ros_msg_bytes  # noqa: PLC0415
        try:
            for rec in self.history.history.list(cell=self.history.cell, kind=kind, newest_first=True, limit=20):
                data = ros_msg_bytes(rec.result, MSG_TYPE)
                if data is not None:
                    return deserialize_message(data, DiscrepancyReport)
        except Exception as exc:  # noqa: BLE001 - the node works without its history
            self.get_logger().error(f"calibration history: could not read the latest report: {exc}")
        return None

    # ------------------------------------------------------------------ inputs
    def _on_obs(self, msg):
        self.obs_rate.tick()
        if plant.refused_as_other_campaign(self, msg):
            return
        if self.intake.add(msg) is not None:
            plant.accept_campaign_msg(self.guard, msg)

    def _on_geometry(self, msg):
        vals = tuple(float(v) for v in msg.static_estimate.values)
        key = (_stamp_ns(msg.header.stamp), vals[:13])
        if key in self.analysed:
            return                       # e.g. the solver re-publishing this geometry marked POOR_FIT
        if len(vals) < 13 or not np.all(np.isfinite(vals[:13])):
            self.bad_input.report("ct/geometry", f"static geometry has {len(vals)} values, not 13 finite ones")
            return
        if msg.static_estimate.status.code != 0:
            self.get_logger().info(f"geometry of stamp {key[0]} ns is not SUCCESS "
                                   f"({msg.static_estimate.status.message}); nothing to judge")
            return
        self.pending, self.pending_since = msg, time.monotonic()
        self._try_pending()

    def _on_timer(self):
        self.bad_input.maybe_summarise()
        if self.pending is not None:
            self._try_pending()
        if self.pending_map is not None:
            self._try_pending_map()

    # ------------------------------------------------------------------ the analysis
    def _observations_for(self, stamp_ns):
        """First-position observations up to the geometry's stamp, or None while they are incomplete."""
        if not self.acc.positions:
            return None
        p0 = self.acc.positions[0]
        if not p0.stamps_ns or max(p0.stamps_ns) < stamp_ns:
            return None
        obs = p0.observations()
        if obs.stamp_ns is not None:
            obs = obs.select(obs.stamp_ns <= stamp_ns)
        return obs

    def _try_pending(self):
        msg = self.pending
        stamp_ns = _stamp_ns(msg.header.stamp)
        obs = self._observations_for(stamp_ns)
        waited = time.monotonic() - self.pending_since
        if obs is None:
            if waited < float(self.p["wait_for_observations_s"]):
                return
            self._give_up(msg, 3, "the observations the geometry rests on did not arrive (first position up to "
                                  f"stamp {stamp_ns} ns)")
            return
        self.pending = None
        self.analysed.add((stamp_ns, tuple(float(v) for v in msg.static_estimate.values[:13])))
        if obs.n_views < int(self.p["min_frames"]):
            self._give_up(msg, 3, f"only {obs.n_views} projection(s) of the first position; the engine needs "
                                  f"{int(self.p['min_frames'])}")
            return
        try:
            self._analyse(msg, obs)
        except Exception as exc:  # noqa: BLE001 - report, keep the node alive
            self._give_up(msg, 4, f"the engine failed: {exc}")

    def _analyse(self, msg, obs):
        from ct_calib_nodes.core import ct_discrepancy  # noqa: PLC0415
        from ct_calib_nodes.core.ct_pipeline import static_result_from_estimate  # noqa: PLC0415
        from ct_calib_nodes.io.discrepancy_msg import discrepancy_msg  # noqa: PLC0415
        from ct_calib_nodes.io.results import static_from_geometry_msg  # noqa: PLC0415

        w, cov, _g, _code = static_from_geometry_msg(msg, self.ref.centres_of_m)
        det = self.instrument.detector
        static = static_result_from_estimate(w, cov[:13, :13] if cov is not None else None, self.ref.centres_of_m,
                                             rms_px=float(msg.static_estimate.status.rms_residual),
                                             n_obs=obs.n_obs)
        t0 = time.perf_counter()
        say = self.get_logger().info
        out = ct_discrepancy.run(obs, static, det, progress=lambda m: say(f"[engine] {m}"),
                                 max_terms=int(self.p["max_terms"]))
        dt = time.perf_counter() - t0
        out["nominal_outcome"] = msg.static_estimate.status.message
        out["recording"] = f"live: {self.resolve_topic_name('ct/observations')}"
        rep = discrepancy_msg(out, msg.header.stamp, campaign_id=self.guard.campaign_id or "",
                              calibration_topic=self.resolve_topic_name("ct/geometry"))
        self._publish(rep, out, obs)
        log = self.get_logger().info if out["adequate"] else self.get_logger().warning
        log(f"discrepancy verdict ({obs.n_views} projections, {obs.n_obs} centres, {dt:.1f} s): {out['verdict']}")

    # ------------------------------------------------------------------ every stage position (error map)
    def _on_map(self, msg):
        if msg.mode and msg.mode != "multi":
            return
        key = (_stamp_ns(msg.header.stamp), len(msg.srd_reported_m))
        if key in self.maps_judged:
            return                       # e.g. ct_error_motion re-publishing this map with positions marked
        if len(msg.srd_reported_m) < 2:
            self.bad_input.report("ct/error_map", f"error map with {len(msg.srd_reported_m)} position(s)")
            return
        self.pending_map, self.map_since = msg, time.monotonic()
        self._try_pending_map()

    def _try_pending_map(self):
        msg = self.pending_map
        stamp_ns, k_map = _stamp_ns(msg.header.stamp), len(msg.srd_reported_m)
        pos = self.acc.positions
        ready = len(pos) >= k_map and max((max(p.stamps_ns) for p in pos if p.stamps_ns), default=-1) >= stamp_ns
        if not ready:
            if time.monotonic() - self.map_since < float(self.p["wait_for_observations_s"]):
                return
            self._give_up(msg, 3, f"the observations of the error map's {k_map} stage positions (up to stamp "
                                  f"{stamp_ns} ns) did not arrive", error_map=True)
            return
        self.pending_map = None
        self.maps_judged.add((stamp_ns, k_map))
        try:
            self._analyse_map(msg, stamp_ns, k_map)
        except Exception as exc:  # noqa: BLE001 - report, keep the node alive
            self._give_up(msg, 4, f"the engine failed on the stage positions: {exc}", error_map=True)

    def _analyse_map(self, msg, stamp_ns, k_map):
        from ct_calib_nodes.core import ct_discrepancy  # noqa: PLC0415
        from ct_calib_nodes.io.discrepancy_msg import positions_msg  # noqa: PLC0415

        t0 = time.perf_counter()
        rows, skipped, judged = [], [], 0
        for k in range(k_map):
            obs = self.acc.positions[k].observations()
            if obs.stamp_ns is not None:
                obs = obs.select(obs.stamp_ns <= stamp_ns)
            key = (obs.n_views, None if obs.stamp_ns is None or not obs.n_obs else int(obs.stamp_ns.max()))
            cached = self.rows.get(k)
            if cached is None or cached[0] != key:
                srd = float(self.acc.positions[k].srd_reported_m)
                cached = (key, *ct_discrepancy.judge_position(
                    k, srd, obs, self.ref.centres_of_m, self.instrument.detector, self.instrument.sdd_reported_m,
                    min_views=int(self.p["min_frames"]), max_terms=int(self.p["max_terms"])))
                self.rows[k] = cached
                judged += 1
            row, skip = cached[1], cached[2]
            (rows if row is not None else skipped).append(row if row is not None else skip)
        sp = ct_discrepancy.across_positions(rows, skipped)
        rep = positions_msg(sp, msg.header.stamp, campaign_id=self.guard.campaign_id or "",
                            calibration_topic=self.resolve_topic_name("ct/error_map"))
        self._publish_map(rep, sp, msg)
        log = self.get_logger().info if rep.status.code == 0 else self.get_logger().warning
        log(f"stage-position verdict ({k_map} positions, {judged} judged anew, {time.perf_counter() - t0:.1f} s): "
            f"{rep.verdict}")

    def _publish_map(self, rep, sp, msg):
        from ct_calib_nodes.io.discrepancy_msg import positions_record  # noqa: PLC0415
        from ct_calib_nodes.io.history import STATUS_BY_CODE, Input  # noqa: PLC0415

        stamp_ns = _stamp_ns(rep.header.stamp)
        stamps = [t for p in self.acc.positions[:len(msg.srd_reported_m)] for t in p.stamps_ns if t <= stamp_ns]
        inputs = [Input(role="topic", path=self.resolve_topic_name("ct/error_map"),
                        detail={"stamp_ns": stamp_ns, "positions": len(msg.srd_reported_m), "final": bool(msg.final)})]
        rec = positions_record(sp, cell=self.history.cell, source="live", campaign_id=self.guard.campaign_id,
                               inputs=inputs, data_start_ns=min(stamps) if stamps else None,
                               data_end_ns=max(stamps) if stamps else None,
                               status=None if sp is not None else STATUS_BY_CODE[rep.status.code],
                               message=rep.status.message)
        # stored before it is published: a verdict anyone has seen is the one a restart re-publishes
        # (a node killed between the two re-published the previous verdict)
        self.history.store(rec, rep, MSG_TYPE)
        self.map_pub.publish(rep)
        self.last_map_report = rep

    def _give_up(self, msg, code, text, error_map: bool = False):
        from ct_calib_nodes.io.discrepancy_msg import failed_msg  # noqa: PLC0415

        self.get_logger().error(f"discrepancy: no verdict: {text}")
        topic = "ct/error_map" if error_map else "ct/geometry"
        rep = failed_msg(msg.header.stamp, code, text, campaign_id=self.guard.campaign_id or "",
                         calibration_topic=self.resolve_topic_name(topic))
        if error_map:
            self.pending_map = None
            self._publish_map(rep, None, msg)
        else:
            self.pending = None
            self._publish(rep, None, None)

    def _publish(self, rep, out, obs):
        from ct_calib_nodes.io.discrepancy_msg import discrepancy_record  # noqa: PLC0415
        from ct_calib_nodes.io.history import STATUS_BY_CODE, Input  # noqa: PLC0415

        inputs = [Input(role="topic", path=self.resolve_topic_name("ct/geometry"),
                        detail={"stamp_ns": _stamp_ns(rep.header.stamp)})]
        start = end = None
        if obs is not None and obs.stamp_ns is not None and obs.n_obs:
            start, end = int(obs.stamp_ns.min()), int(obs.stamp_ns.max())
            inputs.append(Input(role="topic", path=self.resolve_topic_name("ct/observations"),
                                detail={"frames": obs.n_views, "first_stamp_ns": start, "last_stamp_ns": end}))
        rec = discrepancy_record(out, cell=self.history.cell, source="live", campaign_id=self.guard.campaign_id,
                                 inputs=inputs, data_start_ns=start, data_end_ns=end,
                                 status=None if out is not None else STATUS_BY_CODE[rep.status.code],
                                 message=rep.status.message)
        self.history.store(rec, rep, MSG_TYPE)            # stored first, as in _publish_map
        self.pub.publish(rep)
        self.last_report, self.last_t, self.runs = rep, time.monotonic(), self.runs + 1

    def diagnose(self):
        r = self.last_report
        values = {"observation messages": self.obs_rate.total, "reports": self.runs,
                  "last report age": plant.solve_age_text(self.last_t),
                  "campaign": self.guard.campaign_id or "none", "refused (interleaved campaign)": self.guard.refused,
                  "bad observation messages": self.intake.bad_messages}
        m = self.last_map_report
        if m is not None:
            values["stage positions"] = m.verdict
        if r is None:
            return plant.OK, "no calibration judged yet", values
        if m is not None and m.status.code == 5:
            return plant.WARN, "model inadequate at a stage position: " + m.status.message, values
        values["verdict"] = r.verdict
        if r.status.code == 0:
            return plant.OK, "model adequate", values
        if r.status.code == 5:
            return plant.WARN, "model inadequate: " + r.verdict, values
        return plant.WARN, "no verdict: " + r.status.message, values

    def close(self):
        self.history.close()


def main(args=None):
    raise SystemExit(run_node(CtDiscrepancyNode, args))


if __name__ == "__main__":
    main()
