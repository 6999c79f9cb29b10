"""Simulated XYZ stepper stage (INTERFACES.md, PiCMS).

Subscribes /picms/stage/command (trajectory_msgs/JointTrajectory: joint_names x, y, z, one
point, target positions in m); publishes /picms/stage/joint_states (encoder positions, m)
continuously. Targets are quantised to the step resolution; moves are trapezoidal, then ring
and settle (core.instruments.StageSim). A bad command is logged and ignored.
"""
from __future__ import annotations

import numpy as np
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory

from ct_calib_nodes.nodes.bad_input import BadInputCounter
from ct_calib_nodes.nodes.runner import QOS_RELIABLE_STREAM, declare_parameters, run_node

from ..core.instruments import StageSim
from .common import COMMAND_TOPIC, JOINTS_TOPIC

PARAMS = {
    "rate_hz": (50.0, "joint_states rate [Hz]"),
    "resolution_m": (6.0e-6, "step of each axis (picms_cell.yaml stage.resolution) [m]"),
    "vmax_m_per_s": (0.005, "maximum speed per axis [m/s]"),
    "amax_m_per_s2": (0.02, "acceleration per axis [m/s^2]"),
    "ring_amplitude_m": (3.0e-6, "ringing amplitude after a move [m]"),
    "travel_m": (0.025, "travel limit: |target| per axis [m]"),
    "never_settles": (False, "bad-input switch: the stage keeps hunting and never settles [-]"),
}


class PicmsStageSim(Node):
    def __init__(self):
        super().__init__("picms_stage_sim")
        self.p = p = declare_parameters(self, PARAMS)
        self.stage = StageSim(resolution_m=float(p["resolution_m"]), vmax=float(p["vmax_m_per_s"]),
                              amax=float(p["amax_m_per_s2"]), ring_amplitude_m=float(p["ring_amplitude_m"]),
                              never_settles=bool(p["never_settles"]))
        self.t0 = self.get_clock().now().nanoseconds
        self.pub = self.create_publisher(JointState, JOINTS_TOPIC, QOS_RELIABLE_STREAM)
        self.bad_input = BadInputCounter(self.get_logger())    # counted by kind, logged rate-limited
        self.create_subscription(JointTrajectory, COMMAND_TOPIC, self.bad_input.guard(COMMAND_TOPIC, self.on_command), 10)
        self.create_timer(1.0 / float(p["rate_hz"]), self.tick)
        from .plant_hooks import SimDiagnostics
        self.diag = SimDiagnostics(self, "stage readings")

    def _t(self, ns=None):
        return ((self.get_clock().now().nanoseconds if ns is None else ns) - self.t0) * 1e-9

    def on_command(self, msg):
        try:
            names = list(msg.joint_names)
            if sorted(names) != ["x", "y", "z"] or len(msg.points) != 1:
                raise ValueError(f"joint_names {names} with {len(msg.points)} points: x, y, z and one point expected")
            pos = np.array(msg.points[0].positions, float)
            if pos.shape != (3,) or not np.all(np.isfinite(pos)):
                raise ValueError(f"positions {list(pos)}: three finite values expected")
            q = np.array([pos[names.index(n)] for n in ("x", "y", "z")])
            if np.any(np.abs(q) > float(self.p["travel_m"])):
                raise ValueError(f"target {q.tolist()} m beyond the travel limit {self.p['travel_m']} m")
        except ValueError as exc:
            self.bad_input.report(COMMAND_TOPIC, f"ignored stage command: {exc}")
            self.diag.bad += 1
            return
        t_end = self.stage.command(q, self._t())
        self.get_logger().info(f"move to {np.round(q * 1e3, 4).tolist()} mm, profile ends in {t_end - self._t():.2f} s")

    def tick(self):
        now = self.get_clock().now()
        q = self.stage.encoder(self._t(now.nanoseconds))
        m = JointState()
        m.header.stamp = now.to_msg()
        m.header.frame_id = "stage"
        m.name = ["x", "y", "z"]
        m.position = [float(v) for v in q]
        self.pub.publish(m)
        self.diag.sent.tick()


def main(args=None):
    return run_node(PicmsStageSim, args)


if __name__ == "__main__":
    main()
