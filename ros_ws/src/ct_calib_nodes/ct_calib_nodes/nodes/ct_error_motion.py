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
the solves. With ``results_dir`` set, the results (JSON with units) are written
there after every update (atomically).
"""

from __future__ import annotations

import time

import numpy as np

from metro_msgs.msg import CtGeometry, ErrorMap, SphereObservationArray
from metro_msgs.srv import TriggerSolve
from rclpy.node import Node

from ct_calib_nodes.core.ct_pipeline import campaign_error_map, solve_campaign_position, static_result_from_estimate
from ct_calib_nodes.io.results import error_map_msg, estimate_msg, static_from_geometry_msg
from ct_calib_nodes.nodes.bad_input import BadInputCounter
from ct_calib_nodes.nodes.runner import (CT_FILE_PARAMS, QOS_LATCHED, QOS_RELIABLE_STREAM, ObservationIntake,
                                         declare_parameters, load_ct_files, run_node)

PARAMS = {
    **CT_FILE_PARAMS,
    "idle_solve_s": (5.0, "solve the last position when no observation arrived for this long [s]; 0 = never"),
    "min_frames": (1, "fewest frames of a position before it is solved [count]"),
    "loss": ("linear", "least-squares loss: linear, huber, soft_l1, cauchy, arctan"),
}
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
        self.pubs = {"multi": self.create_publisher(ErrorMap, "/ct/error_map", QOS_LATCHED),
                     "single": self.create_publisher(ErrorMap, "/ct/error_map/single", QOS_LATCHED)}
        self.create_subscription(SphereObservationArray, "/ct/observations",
                                 self.bad_input.guard("/ct/observations", self._on_obs), QOS_RELIABLE_STREAM)
        self.create_subscription(CtGeometry, "/ct/geometry", self.bad_input.guard("/ct/geometry", self._on_geometry),
                                 QOS_LATCHED)
        self.create_service(TriggerSolve, "~/solve", self._on_solve)
        self.create_timer(0.5, self._on_timer)

    def _on_geometry(self, msg):
        vals = np.asarray(msg.static_estimate.values, dtype=float)
        if vals.size < 13 or not np.all(np.isfinite(vals[:13])):
            self.intake.bad_messages += 1
            self.bad_input.report("/ct/geometry", f"static geometry has {vals.size} values, not 13 finite ones")
            return
        try:
            w, cov, _geom, code = static_from_geometry_msg(msg, self.ref.centres_of_m)
        except ValueError as exc:
            self.intake.bad_messages += 1
            self.bad_input.report("/ct/geometry", exc)
            return
        if code != 0:
            self.get_logger().error(f"static geometry is not usable (status {code}: {msg.static_estimate.status.message}); "
                                    "error motions wait for a usable one")
            return
        self.static_msg = (w, cov, float(msg.static_estimate.status.rms_residual))
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
        k = self.intake.add(msg)
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
            self._publish()

    def _publish(self):
        stamp = self.get_clock().now().to_msg()
        for mode in MODES:
            if not self.results[mode]:
                continue
            em, ks = campaign_error_map(self.acc, self.results[mode], self.static, definition="travel", name=mode,
                                        index_repeatability_rad=self.instrument.index_repeatability_rad)
            motions = [estimate_msg(self.results[mode][k], f"ct_error_motion/{mode}", stamp) for k in ks[1:]]
            self.pubs[mode].publish(error_map_msg(em, mode, motions, stamp))
        self.get_logger().info(f"error map updated: {len(self.results['multi'])} position(s) solved")

    def _on_solve(self, request, response):
        if request.discard_previous:
            self.solved_frames = {m: {} for m in MODES}
        if self.static is None:
            response.accepted, response.message = False, "no usable static geometry on /ct/geometry yet"
            return response
        self._solve_complete(final=True)
        response.accepted = bool(self.results["multi"])
        response.message = f"{len(self.results['multi'])} position(s) solved"
        return response


def main(args=None):
    raise SystemExit(run_node(CtErrorMotion, args))


if __name__ == "__main__":
    main()
