"""Simulated laser tracker (INTERFACES.md, PiCMS).

Reads one SMR at a time, round-robin over the constellation and the SMR* (when present),
each reading with its own stamp, on /picms/tracker/smr/<name> (geometry_msgs/PointStamped,
frame_id tracker); and the 6-DOF probe pose on /picms/tracker/probe_pose. The probe body's
position comes from the latest /picms/stage/joint_states. Noise: u = (15 um + 6 um/m L) / 2 per
axis; hidden tracker_scale_ppm scales all lengths about the tracker origin, tracker_encoder_ppm
stretches the azimuth / elevation readings, smr_centring_um offsets every SMR* reading and
tracker_lag_ms stamps the readings late (cell.Physics; never told to the solvers).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
from geometry_msgs.msg import PointStamped, PoseStamped
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import JointState

from ct_calib_nodes.nodes.runner import QOS_RELIABLE_STREAM, declare_parameters, run_node

from ..core.cell import CONSTELLATION
from ..core.instruments import probe_pose_reading, smr_position_stage, tracker_reading
from ..io.convert import MessageError, joint_positions, stamp_ns
from .common import CELL_PARAMS, JOINTS_TOPIC, POSE_TOPIC, SMR_TOPIC, truth_from_params

PARAMS = {
    **CELL_PARAMS,
    "rate_hz": (60.0, "readings per second over all targets (round-robin) [Hz]"),
    "smr_star_present": (True, "the SMR* is in its nest at X* and is read too [-]"),
    "constellation": (list(CONSTELLATION), "SMRs on the probe body that the tracker reads [-]"),
    "pose_every": (10, "publish a 6-DOF probe pose after this many SMR readings [count]"),
    "noise_seed": (2, "seed of the reading noise [-]"),
    "tracker_encoder_ppm": ([0.0, 0.0], "hidden: azimuth, elevation encoder scale errors [ppm]"),
    "smr_centring_um": ([0.0, 0.0, 0.0], "hidden: SMR* optical centre off its sphere centre, tracker frame [um]"),
    "tracker_lag_ms": (0.0, "hidden: reading stamps late by this against the cell's clock [ms]"),
}


class PicmsTrackerSim(Node):
    def __init__(self):
        super().__init__("picms_tracker_sim")
        self.p = p = declare_parameters(self, PARAMS)
        self.truth = truth_from_params(p)
        enc, cen = [float(v) for v in p["tracker_encoder_ppm"]], [float(v) for v in p["smr_centring_um"]]
        if len(enc) != 2 or len(cen) != 3:
            raise ValueError(f"tracker_encoder_ppm needs 2 values and smr_centring_um 3, got {enc} and {cen}")
        self.truth = replace(self.truth, physics=replace(
            self.truth.physics, tracker_encoder_ppm=tuple(enc), smr_centring_m=tuple(1e-6 * v for v in cen),
            tracker_lag_s=1e-3 * float(p["tracker_lag_ms"])))
        self.names = [n for n in p["constellation"] if n]
        unknown = [n for n in self.names if n not in self.truth.constellation_stage]
        if unknown:
            raise ValueError(f"unknown constellation SMRs {unknown}")
        if p["smr_star_present"]:
            self.names.append("smr_star")
        self.rng = np.random.default_rng(int(p["noise_seed"]))
        self.pubs = {n: self.create_publisher(PointStamped, SMR_TOPIC.format(n), QOS_RELIABLE_STREAM) for n in self.names}
        self.pose_pub = self.create_publisher(PoseStamped, POSE_TOPIC, QOS_RELIABLE_STREAM)
        self.q, self.t_q, self.v = None, None, np.zeros(3)   # latest joint_states, its stamp, velocity since the last
        self.k = 0
        from ct_calib_nodes.nodes.bad_input import BadInputCounter
        self.bad_input = BadInputCounter(self.get_logger())    # counted by kind, logged rate-limited
        self.create_subscription(JointState, JOINTS_TOPIC, self.bad_input.guard(JOINTS_TOPIC, self.on_joints),
                                 qos_profile_sensor_data)
        self.create_timer(1.0 / float(p["rate_hz"]), self.tick)
        from .plant_hooks import SimDiagnostics
        self.diag = SimDiagnostics(self, "tracker readings", lambda: "waiting for stage joint_states" if self.q is None else None)

    def on_joints(self, msg):
        try:
            q = joint_positions(msg)
            t = stamp_ns(msg.header.stamp)
            if self.q is not None and self.t_q is not None and t > self.t_q:
                self.v = (q - self.q) / ((t - self.t_q) * 1e-9)
            self.q, self.t_q = q, t
        except MessageError as exc:
            self.bad_input.report(JOINTS_TOPIC, f"ignored joint_states: {exc}")

    def tick(self):
        if self.q is None or not self.names:
            return
        name = self.names[self.k % len(self.names)]
        self.k += 1
        # the stage where it is now, not where its last joint_states (up to a period and the DDS latency
        # old) put it: else a moving stage shows a clock lag of ~10 ms that no instrument has
        now = self.get_clock().now()
        q = self.q + self.v * min(max((now.nanoseconds - self.t_q) * 1e-9, 0.0), 0.1)
        p = tracker_reading(self.truth, smr_position_stage(self.truth, name, q), self.rng, probe=name == "smr_star")
        m = PointStamped()
        m.header.stamp = (now + Duration(nanoseconds=int(round(self.truth.physics.tracker_lag_s * 1e9)))).to_msg()
        m.header.frame_id = "tracker"
        m.point.x, m.point.y, m.point.z = (float(v) for v in p)
        self.pubs[name].publish(m)
        self.diag.sent.tick()
        if self.k % int(self.p["pose_every"]) == 0:
            from scipy.spatial.transform import Rotation
            R, pp = probe_pose_reading(self.truth, q, self.rng)
            ps = PoseStamped()
            ps.header = m.header
            ps.pose.position.x, ps.pose.position.y, ps.pose.position.z = (float(v) for v in pp)
            x, y, z, w = Rotation.from_matrix(R).as_quat()
            ps.pose.orientation.x, ps.pose.orientation.y, ps.pose.orientation.z, ps.pose.orientation.w = x, y, z, w
            self.pose_pub.publish(ps)


def main(args=None):
    return run_node(PicmsTrackerSim, args)


if __name__ == "__main__":
    main()
