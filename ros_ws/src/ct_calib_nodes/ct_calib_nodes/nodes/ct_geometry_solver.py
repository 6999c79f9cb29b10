"""Static CT geometry solver node (Ferrucci et al. 2020, sections 3.1-3.2).

Collects sphere-centre observations of the first stage position from
``/ct/observations``; when that position is complete (the reported SRD moves
on, or no observation arrived for ``idle_solve_s``) it solves the 13-parameter
static geometry and publishes ``/ct/geometry`` (metro_msgs/CtGeometry, latched)
with covariance and status. Service ``~/solve`` (metro_msgs/srv/TriggerSolve)
(re-)runs the solve on the observations held.
"""

from __future__ import annotations

import time

from metro_msgs.msg import CtGeometry, SphereObservationArray
from metro_msgs.srv import TriggerSolve
from rclpy.node import Node

from ct_calib_nodes.core.ct_pipeline import solve_campaign_static
from ct_calib_nodes.io.results import geometry_msg
from ct_calib_nodes.nodes.bad_input import BadInputCounter
from ct_calib_nodes.nodes.runner import (CT_FILE_PARAMS, QOS_LATCHED, QOS_RELIABLE_STREAM, ObservationIntake,
                                         declare_parameters, load_ct_files, run_node)

PARAMS = {
    **CT_FILE_PARAMS,
    "idle_solve_s": (3.0, "solve the first position when no observation arrived for this long [s]; 0 = never"),
    "min_frames": (3, "fewest frames of the first position before a solve is attempted [count]"),
    "loss": ("linear", "least-squares loss: linear, huber, soft_l1, cauchy, arctan"),
}


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
        self.pub = self.create_publisher(CtGeometry, "/ct/geometry", QOS_LATCHED)
        self.create_subscription(SphereObservationArray, "/ct/observations",
                                 self.bad_input.guard("/ct/observations", self._on_obs), QOS_RELIABLE_STREAM)
        self.create_service(TriggerSolve, "~/solve", self._on_solve)
        self.create_timer(0.5, self._on_timer)
        self.get_logger().info(f"waiting for /ct/observations ({self.ref.n_spheres} spheres, "
                               f"{self.instrument.detector.cols}x{self.instrument.detector.rows} px)")

    def _on_obs(self, msg):
        k = self.intake.add(msg)
        if k is not None and k >= 1 and self.result is None:
            self._solve("the stage moved to position 2")

    def _on_timer(self):
        self.bad_input.maybe_summarise()
        idle = float(self.p["idle_solve_s"])
        if self.result is None and self.intake.idle_for(idle) and self.acc.positions:
            self._solve(f"no observations for {idle:.1f} s")

    def _solve(self, why: str):
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
        msg = geometry_msg(res, p0.srd_reported_m, self.instrument.sdd_reported_m, self.instrument.detector,
                           self.get_clock().now().to_msg(), n_rejected=p0.n_rejected)
        self.pub.publish(msg)
        log = self.get_logger().info if res.success else self.get_logger().error
        log(f"static geometry ({why}): {'converged' if res.success else 'NOT USABLE'}: {res.message}; "
            f"{p0.n_frames} frames, {res.n_obs} centres, rms {res.rms_px:.4f} px, {dt * 1e3:.0f} ms; "
            f"z_R = {res.x[0] * 1e3:.3f} mm, z_D = {res.x[3] * 1e3:.3f} mm")
        return res, res.message

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
            response.result = self._last_msg_estimate()
        return response

    def _last_msg_estimate(self):
        p0 = self.acc.positions[0]
        return geometry_msg(self.result, p0.srd_reported_m, self.instrument.sdd_reported_m,
                            self.instrument.detector, self.get_clock().now().to_msg()).static_estimate


def main(args=None):
    raise SystemExit(run_node(CtGeometrySolver, args))


if __name__ == "__main__":
    main()
