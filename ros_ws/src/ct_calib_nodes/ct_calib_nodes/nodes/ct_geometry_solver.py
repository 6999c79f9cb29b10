"""Static CT geometry solver node (Ferrucci et al. 2020, sections 3.1-3.2).

Collects sphere-centre observations of the first stage position from
``/ct/observations``; when that position is complete (the reported SRD moves
on, or no observation arrived for ``idle_solve_s``) it solves the 13-parameter
static geometry and publishes ``/ct/geometry`` (metro_msgs/CtGeometry, latched)
with covariance and status. Service ``~/solve`` (metro_msgs/srv/TriggerSolve)
(re-)runs the solve on the observations held.

Restart recovery (nodes/campaign_journal.py): every accepted observation message is journaled; a
solver killed mid-campaign replays its journal at start (the state is rebuilt exactly, the solve
then bit-identical to an uninterrupted run's once the frames sent while it was down are re-sent;
the log names them), while the latest valid calibration stays published from the history.

Model adequacy (issue 11): the node listens to ``ct/discrepancy`` (metro_msgs/DiscrepancyReport of
ct_discrepancy_node). When a report on the geometry it last published says the model is inadequate
(status POOR_FIT), it re-publishes that geometry with status POOR_FIT and the verdict as its message, so
plant software reading ``ct/geometry`` sees that the calibration rests on a model the data contradict
(parameter ``mark_inadequate``; false = report only).
"""

from __future__ import annotations

import time

from metro_msgs.msg import CtGeometry, DiscrepancyReport, SphereObservationArray
from metro_msgs.srv import TriggerSolve
from rclpy.node import Node

from ct_calib_nodes.core.ct_pipeline import solve_campaign_static
from ct_calib_nodes.io.results import geometry_msg
from ct_calib_nodes.nodes import plant
from ct_calib_nodes.nodes.bad_input import BadInputCounter
from ct_calib_nodes.nodes.campaign_journal import JOURNAL_PARAMS, CampaignJournal
from ct_calib_nodes.nodes.runner import (CT_FILE_PARAMS, QOS_LATCHED, QOS_RELIABLE_STREAM, ObservationIntake,
                                         declare_parameters, load_ct_files, run_node)

KIND, MSG_TYPE = "ct_geometry", "metro_msgs/msg/CtGeometry"
STATUS_NAMES = {0: "SUCCESS", 1: "NOT_CONVERGED", 2: "DEGENERATE", 3: "INSUFFICIENT_DATA", 4: "FAILED", 5: "POOR_FIT"}


def time_from_ns(ns):
    from builtin_interfaces.msg import Time  # noqa: PLC0415

    return Time(sec=int(ns) // 1_000_000_000, nanosec=int(ns) % 1_000_000_000)


def _stamp_ns(msg) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def plant_input_topic(topic, pos):
    from ct_calib_nodes.io.history import Input  # noqa: PLC0415

    return Input(role="topic", path=topic, detail={"frames": pos.n_frames, "first_stamp_ns": min(pos.stamps_ns),
                                                   "last_stamp_ns": max(pos.stamps_ns)})


PARAMS = {
    **CT_FILE_PARAMS,
    **plant.HISTORY_PARAMS,
    **JOURNAL_PARAMS,
    "idle_solve_s": (3.0, "solve the first position when no observation arrived for this long [s]; 0 = never"),
    "min_frames": (3, "fewest frames of the first position before a solve is attempted [count]"),
    "loss": ("linear", "least-squares loss: linear, huber, soft_l1, cauchy, arctan"),
    "mark_inadequate": (True, "re-publish the geometry with status POOR_FIT when ct/discrepancy finds its model "
                              "inadequate"),
}
POOR_FIT = 5


class CtGeometrySolver(Node):
    def __init__(self):
        super().__init__("ct_geometry_solver")
        self.p = declare_parameters(self, PARAMS)
        self.instrument, self.ref = load_ct_files(self.p, self.get_logger())
        self.bad_input = BadInputCounter(self.get_logger())
        self.intake = ObservationIntake(self, self.ref)
        self.acc = self.intake.acc
        self.solved_n_frames = -1
        self.result = None
        self.pub = self.create_publisher(CtGeometry, "ct/geometry", QOS_LATCHED)
        self.create_subscription(SphereObservationArray, "ct/observations",
                                 self.bad_input.guard("ct/observations", self._on_obs), QOS_RELIABLE_STREAM)
        self.create_subscription(DiscrepancyReport, "ct/discrepancy",
                                 self.bad_input.guard("ct/discrepancy", self._on_discrepancy), QOS_LATCHED)
        self.create_service(TriggerSolve, "~/solve", self._on_solve)
        self.create_timer(0.5, self._on_timer)
        self.history = plant.HistoryHook(self, str(self.p["history_db"]))
        self.valid_msg, self.last_status, self.last_solve_t = None, None, None
        self.last_msg = None
        self.obs_rate = plant.RateMeter()
        from ct_calib_nodes.io.campaign_guard import CampaignGuard  # noqa: PLC0415
        self.guard = CampaignGuard(self.history.cell)
        self.last_rec, self.marked = None, {}      # stored record of last_msg; stamp -> restored POOR_FIT msg
        rec, msg = self.history.latest_published(KIND, CtGeometry, MSG_TYPE)
        if msg is not None and msg.static_estimate.status.code == 0:
            # a late subscriber or a restart never sees "no calibration"
            self.valid_msg = self.last_msg = msg     # a verdict on it (same stamp) still marks it
            self.last_rec = rec
            self.pub.publish(msg)
            self.get_logger().info(f"re-published the latest valid calibration of cell {self.history.cell}: "
                                   f"history solve {rec.id} of {rec.created_utc} (campaign {rec.campaign_id})")
        elif msg is not None:
            # the last geometry published was found inadequate after its solve: it stays marked
            self.marked[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = msg
            self.last_msg, self.last_status = msg, msg.static_estimate.status
            self.pub.publish(msg)
            self.get_logger().error(f"re-published the latest calibration of cell {self.history.cell} as "
                                    f"{STATUS_NAMES.get(msg.static_estimate.status.code, '?')}: history solve {rec.id} "
                                    f"(superseding solve {rec.result['supersedes'].get('id')}): "
                                    f"{msg.static_estimate.status.message}")
        self.final_journaled = False
        self.journal = CampaignJournal(self, "ct_geometry_solver", SphereObservationArray, str(self.p["history_db"]))
        if self.journal.replay(self._on_obs):
            self._after_replay()
        self.diagnostics = plant.Diagnostics(self, self.diagnose)
        self.get_logger().info(f"waiting for {self.resolve_topic_name('ct/observations')} ({self.ref.n_spheres} spheres, "
                               f"{self.instrument.detector.cols}x{self.instrument.detector.rows} px)")

    def _after_replay(self):
        """State rebuilt from the journal: solve what the killed node had solved (quietly: it was
        published and stored then) or would have solved next; the idle timer waits for live data."""
        self.intake.last_rx = None
        p0 = self.acc.positions[0] if self.acc.positions else None
        if p0 is not None and any(e.get("frames") == p0.n_frames for e in self.journal.events("solved")):
            self._solve("resumed: solved before the restart", quiet=True)
        elif len(self.acc.positions) >= 2:
            self._solve("resumed: the stage had moved to position 2")

    def reset_campaign(self):
        """A new campaign begins (the journaled one was not continued)."""
        self.intake = ObservationIntake(self, self.ref)
        self.acc = self.intake.acc
        self.guard.reset()
        self.result, self.solved_n_frames, self.final_journaled = None, -1, False

    def _on_obs(self, msg):
        k = plant.take_campaign_observation(self, msg)
        if k is not None:
            self.final_journaled = False
        if k is not None and k >= 1 and self.result is None and not self.journal.replaying:
            self._solve("the stage moved to position 2")

    def _on_timer(self):
        self.bad_input.maybe_summarise()
        idle = float(self.p["idle_solve_s"])
        if self.result is None and self.intake.idle_for(idle) and self.acc.positions:
            self._solve(f"no observations for {idle:.1f} s")
        elif (self.result is not None and self.result.success and not self.final_journaled
              and self.intake.idle_for(idle)):
            self.journal.event("final", frames=self.solved_n_frames)    # campaign over: nothing to resume
            self.final_journaled = True

    def _solve(self, why: str, quiet: bool = False):
        p0 = self.acc.positions[0] if self.acc.positions else None
        if p0 is None or p0.n_frames < int(self.p["min_frames"]):
            return None, f"only {0 if p0 is None else p0.n_frames} frame(s) of the first position"
        if p0.n_frames == self.solved_n_frames and self.result is not None:
            return self.result, "no new observations since the last solve"
        t0 = time.perf_counter()
        res = solve_campaign_static(self.acc, self.ref.centres_of_m, self.instrument.detector,
                                    self.instrument.sdd_reported_m, loss=str(self.p["loss"]),
                                    centre_uncertainty_m=self.ref.center_uncertainty_m)
        dt = time.perf_counter() - t0
        self.result, self.solved_n_frames = res, p0.n_frames
        # EstimateStamped: the stamp is when the data the estimate rests on ended (the last frame used)
        msg = geometry_msg(res, p0.srd_reported_m, self.instrument.sdd_reported_m, self.instrument.detector,
                           time_from_ns(max(p0.stamps_ns)), n_rejected=p0.n_rejected,
                           campaign_id=self.guard.campaign_id)
        self.last_msg = msg
        if quiet:        # re-solved from the journal: published and stored before the restart
            marked = self.marked.get((msg.header.stamp.sec, msg.header.stamp.nanosec))
            if marked is not None:       # found inadequate before the restart: stays POOR_FIT
                self.last_msg = marked
                self.last_status, self.last_solve_t = marked.static_estimate.status, time.monotonic()
                return res, marked.static_estimate.status.message
            if self.valid_msg is None and res.success:
                self.pub.publish(msg)
                self.valid_msg = msg
            self.last_status, self.last_solve_t = msg.static_estimate.status, time.monotonic()
            self.get_logger().info(f"static geometry ({why}): {res.message}; {p0.n_frames} frames, "
                                   f"z_R = {res.x[0] * 1e3:.3f} mm, z_D = {res.x[3] * 1e3:.3f} mm")
            return res, res.message
        # stored before it is published: a restart re-publishes what plant software has seen
        self._store(res, msg, p0)
        if res.success or self.valid_msg is None:
            self.pub.publish(msg)
            if res.success:
                self.valid_msg = msg
        else:
            self.get_logger().error("the new geometry is not usable: not published; the last valid calibration "
                                    f"(stamp {self.valid_msg.header.stamp.sec} s) stays on ct/geometry")
        self.last_status, self.last_solve_t = msg.static_estimate.status, time.monotonic()
        self.journal.event("solved", frames=p0.n_frames, success=bool(res.success))
        log = self.get_logger().info if res.success else self.get_logger().error
        log(f"static geometry ({why}): {'converged' if res.success else 'NOT USABLE'}: {res.message}; "
            f"{p0.n_frames} frames, {res.n_obs} centres, rms {res.rms_px:.4f} px, {dt * 1e3:.0f} ms; "
            f"z_R = {res.x[0] * 1e3:.3f} mm, z_D = {res.x[3] * 1e3:.3f} mm")
        return res, res.message

    def _on_discrepancy(self, rep):
        """A verdict on the geometry last published: inadequate -> re-published with status POOR_FIT."""
        m = self.last_msg
        if m is None or not bool(self.p["mark_inadequate"]) or rep.status.code != POOR_FIT:
            return
        if (rep.header.stamp.sec, rep.header.stamp.nanosec) != (m.header.stamp.sec, m.header.stamp.nanosec):
            return                                   # a verdict on another geometry
        if m.static_estimate.status.code != 0:
            return                                   # not usable anyway (or already marked)
        m.static_estimate.status.code = POOR_FIT
        m.static_estimate.status.message = (f"{m.static_estimate.status.message}; {rep.status.message}")[:2000]
        if self.valid_msg is m:
            self.valid_msg = None
        self.last_status = m.static_estimate.status
        # the history carries the verdict: a superseding poor_fit record (the original kept), so a
        # restarted solver re-publishes POOR_FIT, and latest_valid no longer returns this geometry;
        # stored before it is published
        if self.last_rec is not None and self.last_rec.data_end_ns == _stamp_ns(m):
            self.history.supersede(self.last_rec, "poor_fit", m.static_estimate.status.message, msg=m,
                                   type_name=MSG_TYPE, extra={"verdict": str(rep.verdict)})
        self.pub.publish(m)
        self.get_logger().error(f"the geometry of stamp {m.header.stamp.sec} s is marked POOR_FIT: {rep.verdict}")

    def _store(self, res, msg, p0):
        from ct_calib_nodes.io import ct_files  # noqa: PLC0415
        from ct_calib_nodes.io.ct_history import geometry_record, yaml_inputs  # noqa: PLC0415

        files = {"instrument": self.p["instrument_file"] or ct_files.default_instrument_path(),
                 "reference_object": self.p["reference_object_file"] or ct_files.default_reference_object_path()}
        topic = self.resolve_topic_name("ct/observations")
        inputs = yaml_inputs(files) + [plant_input_topic(topic, p0)]
        rec = geometry_record(res, cell=self.history.cell, source="live", inputs=inputs,
                              campaign_id=self.guard.campaign_id,
                              data_start_ns=min(p0.stamps_ns), data_end_ns=max(p0.stamps_ns),
                              extra={"frames": p0.n_frames, "srd_reported_m": p0.srd_reported_m})
        self.last_rec = self.history.store(rec, msg, MSG_TYPE)

    def diagnose(self):
        held = self.acc.positions[0].n_frames if self.acc.positions else 0
        values = {"observation messages": self.obs_rate.total, "observation rate [1/s]": self.obs_rate.rate(),
                  "bad observation messages": self.intake.bad_messages, "frames held (position 1)": held,
                  "last solve": "none" if self.last_status is None else
                  f"{STATUS_NAMES.get(self.last_status.code, self.last_status.code)}: {self.last_status.message}",
                  "last solve age": plant.solve_age_text(self.last_solve_t),
                  "valid calibration published": "yes" if self.valid_msg is not None else "no",
                  "campaign": self.guard.campaign_id or "none", "refused (interleaved campaign)": self.guard.refused}
        if self.last_status is not None and self.last_status.code != 0:
            lvl = plant.WARN if self.valid_msg is not None else plant.ERROR
            return lvl, ("last solve not usable; the previous valid calibration stays published"
                         if self.valid_msg is not None else "no usable calibration: last solve failed"), values
        if self.valid_msg is None:
            return plant.WARN, "no calibration yet: waiting for observations", values
        if self.intake.bad_messages or self.guard.refused:
            return plant.WARN, (f"calibration valid; {self.intake.bad_messages} bad observation message(s) skipped, "
                                f"{self.guard.refused} refused as another campaign"), values
        return plant.OK, "calibration valid", values

    def close(self):
        self.journal.close()
        self.history.close()

    def _on_solve(self, request, response):
        if request.discard_previous:
            self.result, self.solved_n_frames = None, -1
        try:
            res, text = self._solve("service request")
        except Exception as exc:  # noqa: BLE001 - report, keep the node alive
            res, text = None, f"solve failed: {exc}"
        response.accepted = res is not None
        response.message = text
        if res is not None:
            response.result = self.last_msg.static_estimate     # exactly what the topic carries
        return response


def main(args=None):
    raise SystemExit(run_node(CtGeometrySolver, args))


if __name__ == "__main__":
    main()
