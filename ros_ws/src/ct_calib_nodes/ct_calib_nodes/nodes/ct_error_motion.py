"""Stage error-motion node (Ferrucci et al. 2020, section 3.3).

Collects ``/ct/observations`` of every stage position and the latched static
geometry ``/ct/geometry``. When a position k >= 2 is complete (the reported SRD
moves on, or no observation for ``idle_solve_s``) it solves the six error
motions from all projections ("multi") and from the first projection only
("single"), and republishes the growing error map on ``/ct/error_map`` and
``/ct/error_map/single`` (metro_msgs/ErrorMap, latched), in the "travel"
definition (ISO 230-1 geometry; sign: + = travelled less than indexed; see
core/error_map.py). Uncertainties are the joint covariance over positions,
including the static geometry's (shared by all positions) and, when
ct_instrument.yaml gives it, the rotary indexing repeatability in u(yaw). Service ``~/solve`` re-runs
the solves (``what`` "" or "error_motion"; ``stage_position`` k >= 1 (0-based, 0 is the reference)
returns that position's multi-projection motions, -1 the last solved position's).
Topic names are relative: ``--ros-args -r __ns:=/cell_a`` moves the node into cell ``/cell_a``.
Every final map (campaign complete or service request) is stored in the calibration history
(parameter ``history_db``); at start the latest valid maps of the cell are re-published latched, and a
map that is not SUCCESS never replaces a valid one.
Model adequacy (issue 11): the node listens to ``ct/discrepancy/error_map`` (ct_discrepancy_node's verdict
on every stage position of a map). A POOR_FIT verdict on the map it last published (same stamp) makes it
re-publish that map with the motions of the positions found inadequate marked POOR_FIT (every position when
the reference position or the campaign as a whole was found inadequate: every motion rests on them), the
verdict in their status messages; a final map's history record is superseded by a poor_fit one (the
original kept). Parameter ``mark_inadequate`` (false = report only). Plant software reading the motions'
statuses then sees that the map rests on a model the data contradict.
Restart recovery (nodes/campaign_journal.py): the accepted observations are journaled; a node killed
mid-campaign replays them at start and solves again once the (latched) geometry arrives; the log names
the frames it needs again (those published while it was down).
"""

from __future__ import annotations

import time

import numpy as np
from builtin_interfaces.msg import Time
from metro_msgs.msg import CtGeometry, DiscrepancyReport, ErrorMap, SphereObservationArray
from metro_msgs.srv import TriggerSolve
from rclpy.node import Node

from ct_calib_nodes.core.ct_pipeline import campaign_error_map, solve_campaign_position, static_result_from_estimate
from ct_calib_nodes.io.results import error_map_msg, estimate_msg, static_from_geometry_msg
from ct_calib_nodes.nodes import plant
from ct_calib_nodes.nodes.bad_input import BadInputCounter
from ct_calib_nodes.nodes.campaign_journal import JOURNAL_PARAMS, CampaignJournal
from ct_calib_nodes.nodes.runner import (CT_FILE_PARAMS, QOS_LATCHED, QOS_RELIABLE_STREAM, ObservationIntake,
                                         declare_parameters, load_ct_files, run_node)

KIND, MSG_TYPE = "ct_error_map", "metro_msgs/msg/ErrorMap"
PARAMS = {
    **CT_FILE_PARAMS,
    **plant.HISTORY_PARAMS,
    **JOURNAL_PARAMS,
    "idle_solve_s": (5.0, "solve the last position when no observation arrived for this long [s]; 0 = never"),
    "min_frames": (1, "fewest frames of a position before it is solved [count]"),
    "loss": ("linear", "least-squares loss: linear, huber, soft_l1, cauchy, arctan"),
    "mark_inadequate": (True, "re-publish the error map with the motions of positions ct/discrepancy/error_map "
                              "finds inadequate marked POOR_FIT"),
}
POOR_FIT = 5
MODES = ("multi", "single")


class CtErrorMotion(Node):
    def __init__(self):
        super().__init__("ct_error_motion")
        self.p = declare_parameters(self, PARAMS)
        self.instrument, self.ref = load_ct_files(self.p, self.get_logger())
        self.bad_input = BadInputCounter(self.get_logger())
        self.intake = ObservationIntake(self, self.ref)
        self.acc = self.intake.acc
        self.static = None
        self.results = {m: {} for m in MODES}        # mode -> {k: MotionResult}
        self.solved_frames = {m: {} for m in MODES}  # mode -> {k: n_frames at solve}
        self.pubs = {"multi": self.create_publisher(ErrorMap, "ct/error_map", QOS_LATCHED),
                     "single": self.create_publisher(ErrorMap, "ct/error_map/single", QOS_LATCHED)}
        self.create_subscription(SphereObservationArray, "ct/observations",
                                 self.bad_input.guard("ct/observations", self._on_obs), QOS_RELIABLE_STREAM)
        self.create_subscription(CtGeometry, "ct/geometry", self.bad_input.guard("ct/geometry", self._on_geometry),
                                 QOS_LATCHED)
        self.create_subscription(DiscrepancyReport, "ct/discrepancy/error_map",
                                 self.bad_input.guard("ct/discrepancy/error_map", self._on_discrepancy), QOS_LATCHED)
        self.create_service(TriggerSolve, "~/solve", self._on_solve)
        self.last_pub = {m: None for m in MODES}      # mode -> (ErrorMap published last, positions of its motions)
        self.stored_rec = {m: None for m in MODES}    # mode -> history record of the last final map stored
        self.marks = {}                               # map stamp (sec, nanosec) -> {position: reason}
        self.create_timer(0.5, self._on_timer)
        self.history = plant.HistoryHook(self, str(self.p["history_db"]))
        self.valid = {m: None for m in MODES}         # mode -> the valid ErrorMap message published
        self.valid_campaign = {}
        self.last_map_status, self.last_solve_t, self.stored_key = None, None, {}
        self.obs_rate = plant.RateMeter()
        from ct_calib_nodes.io.campaign_guard import CampaignGuard  # noqa: PLC0415
        self.guard = CampaignGuard(self.history.cell)
        for mode in MODES:
            rec, msg = self.history.latest_msg(KIND, ErrorMap, MSG_TYPE, mode=mode)
            if msg is not None:
                self.valid[mode] = msg
                self.pubs[mode].publish(msg)
                self.get_logger().info(f"re-published the latest valid {mode} error map of cell {self.history.cell}: "
                                       f"history solve {rec.id} of {rec.created_utc}")
        self.journal = CampaignJournal(self, "ct_error_motion", SphereObservationArray, str(self.p["history_db"]))
        if self.journal.replay(self._on_obs):
            self.intake.last_rx = None       # the idle (final) solve waits for live data
        self.diagnostics = plant.Diagnostics(self, self.diagnose)

    def reset_campaign(self):
        """A new campaign begins (the journaled one was not continued)."""
        self.intake = ObservationIntake(self, self.ref)
        self.acc = self.intake.acc
        self.guard.reset()
        self.results = {m: {} for m in MODES}
        self.solved_frames = {m: {} for m in MODES}

    def _on_geometry(self, msg):
        vals = np.asarray(msg.static_estimate.values, dtype=float)
        if vals.size < 13 or not np.all(np.isfinite(vals[:13])):
            self.intake.bad_messages += 1
            self.bad_input.report("ct/geometry", f"static geometry has {vals.size} values, not 13 finite ones")
            return
        try:
            w, cov, _geom, code = static_from_geometry_msg(msg, self.ref.centres_of_m)
        except ValueError as exc:
            self.intake.bad_messages += 1
            self.bad_input.report("ct/geometry", exc)
            return
        if code != 0:
            self.get_logger().error(f"static geometry is not usable (status {code}: {msg.static_estimate.status.message}); "
                                    "error motions wait for a usable one")
            return
        self.static_msg = (w, cov, float(msg.static_estimate.status.rms_residual))
        self.static_stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.static = self._rebuild_static()
        self.results = {m: {} for m in MODES}
        self.solved_frames = {m: {} for m in MODES}
        self.get_logger().info("static geometry received")
        self._solve_complete(final=False)

    def _rebuild_static(self):
        """The published static estimate, its uncertainty rebuilt from the first position's
        observations as the offline solve does (centre uncertainty through both paths)."""
        w, cov, rms = self.static_msg
        obs = self.acc.positions[0].observations() if self.acc.positions else None
        return static_result_from_estimate(w, cov, self.ref.centres_of_m, rms_px=rms, obs=obs,
                                           n_obs=0 if obs is None else obs.n_obs, detector=self.instrument.detector,
                                           centre_uncertainty_m=self.ref.center_uncertainty_m)

    def _on_obs(self, msg):
        k = plant.take_campaign_observation(self, msg)
        if k is not None and k >= 2 and k == len(self.acc.positions) - 1 and self.acc.positions[k].n_frames == 1:
            self._solve_complete(final=False)      # position k-1 just completed

    def _on_timer(self):
        self.bad_input.maybe_summarise()
        if self.intake.idle_for(float(self.p["idle_solve_s"])):
            self._solve_complete(final=True)

    def _solve_complete(self, final: bool):
        """Solve every complete, not yet solved position (the last one only when final)."""
        if self.static is None or len(self.acc.positions) < 2:
            return
        if self.static.n_obs != self.acc.positions[0].n_obs:
            self.static = self._rebuild_static()
        last = len(self.acc.positions) - (0 if final else 1)
        changed = False
        for k in range(1, last):
            n = self.acc.positions[k].n_frames
            if n < int(self.p["min_frames"]):
                continue
            for mode in MODES:
                if self.solved_frames[mode].get(k) == n:
                    continue
                t0 = time.perf_counter()
                try:
                    res = solve_campaign_position(self.acc, k, self.static, self.instrument.detector, mode=mode,
                                                  loss=str(self.p["loss"]), multi=self.results["multi"].get(k))
                except ValueError as exc:
                    self.get_logger().error(f"position {k + 1} ({mode}): {exc}")
                    self.solved_frames[mode][k] = n
                    continue
                self.results[mode][k] = res
                self.solved_frames[mode][k] = n
                changed = True
                log = self.get_logger().info if res.success else self.get_logger().error
                log(f"position {k + 1} ({mode}, {res.n_views} view(s), {res.n_obs} centres): "
                    f"{'ok' if res.success else 'NOT USABLE: ' + res.message}; rms {res.rms_px:.4f} px; "
                    f"dz = {res.x[2] * 1e3:.4f} mm; {1e3 * (time.perf_counter() - t0):.0f} ms")
        if changed:
            self._publish(final)

    def _publish(self, final: bool = False):
        from ct_calib_nodes.io.ct_history import map_status  # noqa: PLC0415

        # stamp: when the data the map rests on ended (the last frame of the positions solved)
        last_ns = max(max(p.stamps_ns) for p in self.acc.positions if p.stamps_ns)
        stamp = Time(sec=last_ns // 1_000_000_000, nanosec=last_ns % 1_000_000_000)
        for mode in MODES:
            if not self.results[mode]:
                continue
            em, ks = campaign_error_map(self.acc, self.results[mode], self.static, definition="travel", name=mode,
                                        index_repeatability_rad=self.instrument.index_repeatability_rad)
            motions = [estimate_msg(self.results[mode][k], f"ct_error_motion/{mode}", stamp) for k in ks[1:]]
            # which geometry the map rests on, its campaign, and whether it is final
            msg = error_map_msg(em, mode, motions, stamp, campaign_id=self.guard.campaign_id,
                                geometry_stamp=Time(sec=self.static_stamp_ns // 1_000_000_000,
                                                    nanosec=self.static_stamp_ns % 1_000_000_000), final=final)
            status, text = map_status({k: self.results[mode][k] for k in ks[1:]})
            marked = self._apply_marks(msg, ks[1:])      # a verdict on this stamp arrived before (re-solve)
            if marked:
                status, text = "poor_fit", "found inadequate by the discrepancy engine: " + text
            if mode == "multi":
                self.last_map_status, self.last_solve_t = (status, text), time.monotonic()
            if final:            # stored before it is published: a restart re-publishes what was seen
                self._store(em, ks, mode, status, text, msg)
            if not final and self.valid[mode] is not None and self.valid_campaign.get(mode) == self.guard.campaign_id:
                pass   # this campaign's final map is out: a re-solve never re-publishes a shorter, growing one
            elif status == "success" or marked or self.valid[mode] is None:
                self.pubs[mode].publish(msg)
                self.last_pub[mode] = (msg, list(ks[1:]))
                if status == "success" and final:
                    self.valid[mode], self.valid_campaign[mode] = msg, self.guard.campaign_id
            else:
                self.get_logger().error(f"{mode} error map not usable ({text}): not published; the last valid map "
                                        "stays latched")
        if final and self.last_map_status is not None and self.last_map_status[0] == "success":
            self.journal.event("final", positions=len(self.acc.positions))   # nothing to resume
        self.get_logger().info(f"error map updated: {len(self.results['multi'])} position(s) solved")

    def _store(self, em, ks, mode, status, text, msg):
        key = (mode, tuple((k, self.solved_frames[mode].get(k)) for k in ks))
        if self.stored_key.get(mode) == key:       # the same final map: stored once
            return
        from ct_calib_nodes.io import ct_files  # noqa: PLC0415
        from ct_calib_nodes.io.ct_history import error_map_record, yaml_inputs  # noqa: PLC0415

        files = {"instrument": self.p["instrument_file"] or ct_files.default_instrument_path(),
                 "reference_object": self.p["reference_object_file"] or ct_files.default_reference_object_path()}
        stamps = [t for p in self.acc.positions for t in p.stamps_ns]
        from ct_calib_nodes.io.history import Input  # noqa: PLC0415
        upstream = Input(role="upstream", path=self.resolve_topic_name("ct/geometry"),
                         detail={"kind": "ct_geometry", "stamp_ns": self.static_stamp_ns})
        rec = error_map_record(em, mode, status=status, message=text, cell=self.history.cell, source="live",
                               inputs=yaml_inputs(files) + [upstream], campaign_id=self.guard.campaign_id, data_start_ns=min(stamps), data_end_ns=max(stamps),
                               positions=ks)
        stored = self.history.store(rec, msg, MSG_TYPE)
        if stored is not None:
            self.stored_key[mode] = key
            self.stored_rec[mode] = stored

    # ------------------------------------------------------------------ model adequacy (issue 11)
    def _apply_marks(self, msg, positions) -> bool:
        """Mark the motions of the positions a verdict on this map's stamp found inadequate (True if any changed)."""
        marks = self.marks.get((msg.header.stamp.sec, msg.header.stamp.nanosec))
        if not marks:
            return False
        hit = False
        for k, m in zip(positions, msg.motions):
            why = marks.get(k, marks.get("all"))
            if why is None or m.status.code == POOR_FIT:
                continue                           # not found inadequate, or POOR_FIT already (a repeated verdict)
            m.status.code = POOR_FIT
            m.status.message = f"{m.status.message}; {why}"[:2000]
            hit = True
        return hit

    def _on_discrepancy(self, rep):
        """A verdict on every stage position of a map: positions found inadequate -> motions POOR_FIT."""
        import json  # noqa: PLC0415

        if not bool(self.p["mark_inadequate"]) or rep.status.code != POOR_FIT:
            return
        try:
            sp = json.loads(rep.report_json)["stage_positions"]
        except (ValueError, KeyError, TypeError) as exc:
            self.bad_input.report("ct/discrepancy/error_map", f"report_json without stage_positions: {exc}")
            return
        marks = {}
        for r in sp.get("positions", []):
            if not r.get("adequate", True):
                marks[int(r["position"])] = (f"model inadequate at stage position {int(r['position']) + 1} "
                                             f"(discrepancy engine): {r.get('verdict', '')}")
        if 0 in marks:
            marks["all"] = "the reference position's model was found inadequate: " + marks.pop(0)
        if not sp.get("campaign", {}).get("adequate", True):
            marks["all"] = "model inadequate over the campaign (discrepancy engine): " + rep.verdict
        if not marks:
            return
        stamp = (rep.header.stamp.sec, rep.header.stamp.nanosec)
        self.marks[stamp] = marks
        for mode in MODES:
            last = self.last_pub[mode]
            if last is None or (last[0].header.stamp.sec, last[0].header.stamp.nanosec) != stamp:
                continue                           # a verdict on another map
            msg, positions = last
            if not self._apply_marks(msg, positions):
                continue
            if self.valid[mode] is msg:
                self.valid[mode] = None
            if mode == "multi":
                self.last_map_status = ("poor_fit", rep.status.message)
            rec = self.stored_rec[mode]
            if rec is not None and rec.data_end_ns == stamp[0] * 1_000_000_000 + stamp[1]:
                self.history.supersede(rec, "poor_fit", rep.status.message[:2000], msg=msg, type_name=MSG_TYPE,
                                       extra={"verdict": str(rep.verdict), "positions_marked": sorted(
                                           str(k) for k in marks)})
            self.pubs[mode].publish(msg)                 # after the superseding record is stored
            self.get_logger().error(f"{mode} error map of stamp {stamp[0]} s: motions marked POOR_FIT "
                                    f"({', '.join(str(k) for k in marks)}): {rep.verdict}")

    def diagnose(self):
        values = {"observation messages": self.obs_rate.total, "observation rate [1/s]": self.obs_rate.rate(),
                  "bad messages": self.intake.bad_messages, "positions held": len(self.acc.positions),
                  "positions solved (multi)": len(self.results["multi"]),
                  "static geometry": "received" if self.static is not None else "waiting",
                  "last map": "none" if self.last_map_status is None else ": ".join(self.last_map_status),
                  "last solve age": plant.solve_age_text(self.last_solve_t),
                  "valid map published": "yes" if self.valid["multi"] is not None else "no",
                  "campaign": self.guard.campaign_id or "none", "refused (interleaved campaign)": self.guard.refused}
        if self.last_map_status is not None and self.last_map_status[0] != "success":
            return (plant.WARN if self.valid["multi"] is not None else plant.ERROR,
                    f"last error map not usable: {self.last_map_status[1]}", values)
        if self.static is None:
            return plant.WARN, "waiting for a usable static geometry", values
        if self.intake.bad_messages or self.guard.refused:
            return plant.WARN, (f"{self.intake.bad_messages} bad message(s) skipped, {self.guard.refused} refused "
                                "as another campaign"), values
        return plant.OK, "running", values

    def close(self):
        self.journal.close()
        self.history.close()

    def _on_solve(self, request, response):
        what = str(request.what or "").strip()
        if what not in ("", "error_motion"):
            response.accepted = False
            response.message = (f"this node solves error motions (what 'error_motion' or ''), not {what!r}; "
                                "the static geometry is solved by ct_geometry_solver's ~/solve")
            return response
        if request.discard_previous:
            self.solved_frames = {m: {} for m in MODES}
        if self.static is None:
            response.accepted, response.message = False, "no usable static geometry on ct/geometry yet"
            return response
        self._solve_complete(final=True)
        k = int(request.stage_position)
        solved = self.results["multi"]
        if k >= 0 and k not in solved:
            response.accepted = False
            response.message = (f"stage position {k} has no error-motion solve (solved: {sorted(solved)}; "
                                "0 is the reference position)")
            return response
        if not solved:
            response.accepted, response.message = False, "no position solved yet"
            return response
        k = max(solved) if k < 0 else k
        last_ns = max(self.acc.positions[k].stamps_ns)
        stamp = Time(sec=last_ns // 1_000_000_000, nanosec=last_ns % 1_000_000_000)
        response.result = estimate_msg(solved[k], "ct_error_motion/multi", stamp)
        response.accepted = True
        response.message = f"{len(solved)} position(s) solved; result: position {k}"
        return response


def main(args=None):
    raise SystemExit(run_node(CtErrorMotion, args))


if __name__ == "__main__":
    main()
