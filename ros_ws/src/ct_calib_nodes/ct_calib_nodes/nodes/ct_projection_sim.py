"""Simulated cone-beam CT: renders a calibration campaign and publishes it per INTERFACES.md.

Publishes ``/ct/detector/image`` (sensor_msgs/Image, mono16 counts or 32FC1
transmission, frame_id ``ct_detector``) and ``/ct/stage/joint_states``
(names [rotary, magnification], positions [alpha rad, reported SRD m]) with
identical stamps, for every projection of every stage position. The object
is the reference object's spheres on their carbon-fibre support tube
(``support_tube``; the tube is not in reference_object.yaml). The truth
(geometry, error motions) never goes on a topic; it can be written to a file
for tests and for a simulated independent reference measurement.

Start: the campaign begins once both raw topics have ``wait_for_subscribers``
subscribers (a detector and a recorder started by hand: 2), and, with
``wait_for_start`` true, once service ``~/start`` (std_srvs/Trigger) was called;
calling ``~/start`` also starts a campaign still waiting for subscribers
(the operator's override). Topic names are relative (``__ns`` moves the cell).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import rclpy
from rclpy.node import Node
from sensor_msgs.msg import Image, JointState
from std_srvs.srv import Trigger

from ct_calib_nodes.core.phantom import CarbonTube
from ct_calib_nodes.core.render import RenderSettings, render_projection
from ct_calib_nodes.core.scenario import default_campaign
from ct_calib_nodes.io.convert import image_from_array
from ct_calib_nodes.io.truth_files import write_reference_error_map, write_truth
from ct_calib_nodes.nodes.runner import (CT_FILE_PARAMS, QOS_RELIABLE_STREAM, declare_parameters, load_ct_files,
                                         run_node)

PARAMS = {
    **CT_FILE_PARAMS,
    "n_positions": (6, "stage positions along the magnification axis [count]"),
    "srd_first_m": (0.364, "instrument-reported SRD of the first stage position [m]"),
    "step_m": (0.072, "stage step between positions [m]"),
    "projections_per_position": (24, "projections over one full turn at each position [count]"),
    "rate_hz": (8.0, "frame rate; 0 = as fast as rendering allows [Hz]"),
    "encoding": ("mono16", "frame encoding: mono16 (counts) or 32FC1 (transmission I/I0)"),
    "seed": (20201, "random seed of the photon noise [-]"),
    "wait_for_subscribers": (1, "start only when both raw topics have this many subscribers [count]"),
    "wait_timeout_s": (60.0, "give up waiting for subscribers (and the start call) after this long [s]; 0 = never"),
    "wait_for_start": (False, "also wait for a call of the ~/start service (std_srvs/Trigger) [-]"),
    "exit_when_done": (True, "end the process after the last frame"),
    "truth_output": ("", "write the simulation truth here (YAML; for tests, never read by solvers) [path]"),
    "reference_output": ("", "write a simulated independent reference error map here (CSV) [path]"),
    "support_tube": (True, "render the CFRP tube that carries the spheres (not part of reference_object.yaml; "
                           "the solvers never see it) [-]"),
    "tube_outer_radius_m": (0.036, "support tube outer radius [m]"),
    "tube_wall_m": (0.001, "support tube wall thickness [m]"),
    "tube_height_m": (0.110, "support tube length along the object's Y axis [m]"),
    "blur_sigma_px": (0.7, "detector blur, Gaussian sigma [px]"),
    "flat_field_counts": (0.0, "open-beam counts; 0 = the instrument file's value [counts]"),
    # hidden physics: off by default; the solvers are never told
    "encoder_eccentricity_rad": (0.0, "hidden: rotary-encoder error amplitude A, alpha_true = alpha + A sin(alpha + phase) [rad]"),
    "encoder_phase_rad": (0.0, "hidden: phase of the encoder error [rad]"),
    "focal_spot_drift_m_per_s": ([0.0, 0.0, 0.0], "hidden: focal-spot drift velocity in the detector frame [m/s]"),
    "detector_distortion_k1_per_m2": (0.0, "hidden: radial detector distortion k1 [1/m^2]"),
    "ellipse_centre_bias": (True, "render exact cone-sphere silhouettes (ellipse centre != centre projection; "
                                  "the solvers model it); false = shift shadows onto the centre projection"),
}


class CtProjectionSim(Node):
    def __init__(self):
        super().__init__("ct_projection_sim")
        self.p = p = declare_parameters(self, PARAMS)
        self.instrument, self.ref = load_ct_files(p)
        if p["support_tube"]:
            # reference_object.yaml lists the calibrated spheres only; the physical object also
            # has the carbon-fibre tube they are glued to, which real frames show (faint bands,
            # an elliptical end rim), so the simulator renders it too
            r_out = float(p["tube_outer_radius_m"])
            self.ref = dataclasses.replace(self.ref, tube=CarbonTube(
                outer_radius_m=r_out, inner_radius_m=r_out - float(p["tube_wall_m"]),
                height_m=float(p["tube_height_m"])))
        if p["encoding"] not in ("mono16", "32FC1"):
            raise ValueError(f"encoding must be mono16 or 32FC1, got {p['encoding']!r}")
        n_pos, step, srd0 = int(p["n_positions"]), float(p["step_m"]), float(p["srd_first_m"])
        srd_last = srd0 + step * (n_pos - 1)
        reach = float(np.max(np.linalg.norm(self.ref.centres_of_m, axis=1))) + float(np.max(self.ref.diameters_m))
        if n_pos < 1 or min(srd0, srd_last) - reach <= 0.0 or max(srd0, srd_last) + reach >= self.instrument.sdd_reported_m:
            raise ValueError(f"campaign SRD {srd0:.3f} to {srd_last:.3f} m ({n_pos} positions, step {step:.4f} m) puts "
                             f"the object (reach {reach:.3f} m) outside the space between the source and the "
                             f"detector at {self.instrument.sdd_reported_m:.3f} m")
        self.truth = default_campaign(n_pos, step, srd0, self.instrument.sdd_reported_m)
        flat = float(p["flat_field_counts"]) or self.instrument.flat_field_counts or 50000.0
        self.settings = RenderSettings(
            flat_field_counts=flat, blur_sigma_px=float(p["blur_sigma_px"]),
            encoder_eccentricity_rad=float(p["encoder_eccentricity_rad"]), encoder_phase_rad=float(p["encoder_phase_rad"]),
            focal_spot_drift_m_per_s=tuple(float(v) for v in p["focal_spot_drift_m_per_s"]),
            detector_distortion_k1_per_m2=float(p["detector_distortion_k1_per_m2"]),
            ellipse_centre_bias=bool(p["ellipse_centre_bias"]))
        if p["truth_output"]:
            write_truth(p["truth_output"], self.truth, self.settings, int(p["projections_per_position"]))
        if p["reference_output"]:
            write_reference_error_map(p["reference_output"], self.truth)
        self.rng = np.random.default_rng(int(p["seed"]))
        self.pub_img = self.create_publisher(Image, "ct/detector/image", QOS_RELIABLE_STREAM)
        self.pub_js = self.create_publisher(JointState, "ct/stage/joint_states", QOS_RELIABLE_STREAM)
        n = int(p["projections_per_position"])
        if n < 1:
            raise ValueError("projections_per_position must be >= 1")
        self.alphas = 2 * np.pi * np.arange(n) / n
        self.queue = [(k, j) for k in range(len(self.truth.srd_reported_m)) for j in range(n)]
        self.sent = 0
        self.t_start = None
        self.t_wait = time.monotonic()
        period = 1.0 / p["rate_hz"] if p["rate_hz"] > 0 else 0.001
        self.timer = self.create_timer(period, self._tick)
        self.start_requested = False
        self.create_service(Trigger, "~/start", self._on_start)
        self.last_wait_log = 0.0
        from ct_calib_nodes.nodes import plant  # noqa: PLC0415
        self.diagnostics = plant.Diagnostics(self, self.diagnose)
        self.get_logger().info(
            f"campaign: {len(self.truth.srd_reported_m)} positions x {n} projections, "
            f"SRD {self.truth.srd_reported_m[0]*1e3:.1f}..{self.truth.srd_reported_m[-1]*1e3:.1f} mm, "
            f"{self.instrument.detector.cols}x{self.instrument.detector.rows} {p['encoding']}")

    def _tick(self):
        if self.t_start is None:
            # both raw topics: a recorder matches them one after the other
            subs = min(self.pub_img.get_subscription_count(), self.pub_js.get_subscription_count())
            need = int(self.p["wait_for_subscribers"])
            ready = self.start_requested or (subs >= need and not self.p["wait_for_start"])
            if not ready:
                waited = time.monotonic() - self.t_wait
                what = (f"{subs} of {need} subscriber(s) on both raw topics"
                        + ("; waiting for a call of ~/start" if self.p["wait_for_start"] else ""))
                if float(self.p["wait_timeout_s"]) > 0 and waited > float(self.p["wait_timeout_s"]):
                    self.get_logger().error(f"not started after {self.p['wait_timeout_s']} s ({what}); giving up")
                    self.exit_code = 3
                    rclpy.try_shutdown()
                elif waited - self.last_wait_log >= 5.0:
                    self.last_wait_log = waited
                    self.get_logger().info(f"waiting to start: {what}")
                return
            self.t_start = time.monotonic()
            self.get_logger().info(f"starting the campaign ({subs} subscriber(s)"
                                   f"{', start requested' if self.start_requested else ''})")
        if self.sent >= len(self.queue):
            return
        k, j = self.queue[self.sent]
        t_s = time.monotonic() - self.t_start
        frame = render_projection(self.truth.static_w, self.truth.motions[k], self.alphas[j], self.ref,
                                  self.instrument.detector, self.settings, self.rng, time_s=t_s,
                                  output="mono16" if self.p["encoding"] == "mono16" else "transmission")
        stamp = self.get_clock().now().to_msg()
        js = JointState(name=["rotary", "magnification"],
                        position=[float(self.alphas[j]), float(self.truth.srd_reported_m[k])])
        js.header.stamp = stamp
        js.header.frame_id = "ct_stage"
        self.pub_js.publish(js)
        self.pub_img.publish(image_from_array(frame.image, stamp, "ct_detector"))
        self.sent += 1
        if j == 0 or self.sent == len(self.queue):
            self.get_logger().info(f"position {k + 1}/{len(self.truth.srd_reported_m)}: frame {self.sent}/{len(self.queue)}")
        if self.sent == len(self.queue):
            self.get_logger().info(f"campaign complete: {self.sent} frames in {time.monotonic() - self.t_start:.1f} s")
            if self.p["exit_when_done"]:
                self._finish()

    def _on_start(self, _request, response):
        if self.t_start is not None:
            response.success, response.message = False, f"already running: {self.sent}/{len(self.queue)} frames sent"
        else:
            self.start_requested = True
            response.success, response.message = True, "campaign starts"
        return response

    def diagnose(self):
        from ct_calib_nodes.nodes import plant  # noqa: PLC0415

        subs = min(self.pub_img.get_subscription_count(), self.pub_js.get_subscription_count())
        values = {"frames sent": self.sent, "frames in campaign": len(self.queue), "subscribers": subs}
        if self.t_start is None:
            return plant.OK, "waiting to start", values
        values["frame rate [1/s]"] = self.sent / max(time.monotonic() - self.t_start, 1e-9)
        if self.sent >= len(self.queue):
            return plant.OK, "campaign complete", values
        return plant.OK, "publishing the campaign", values

    def _finish(self):
        """End the process only once every subscriber acknowledged every frame (reliable QoS):
        a frame still in flight to a busy subscriber would otherwise die with this process."""
        from rclpy.duration import Duration  # noqa: PLC0415

        acked = all(pub.wait_for_all_acked(Duration(seconds=60.0)) for pub in (self.pub_img, self.pub_js))
        if not acked:
            self.get_logger().warning("some subscribers did not acknowledge every frame within 60 s")
        rclpy.try_shutdown()


def main(args=None):
    from ct_calib_nodes.nodes.runner import release_frame_memory  # noqa: PLC0415

    print(f"[ct_projection_sim] {release_frame_memory()}", flush=True)   # 2-8 MB frames in deep queues
    raise SystemExit(run_node(CtProjectionSim, args))


if __name__ == "__main__":
    main()
