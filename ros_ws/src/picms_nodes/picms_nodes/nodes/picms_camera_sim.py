"""Simulated Pixel Probe cameras: rendered mono8 frames and CameraInfo (INTERFACES.md, PiCMS).

One node serves the cameras in `cameras` (default all three; run one instance per camera with
cameras:=[camera_2] if preferred). The cameras ride on the stage: each frame is rendered at
the latest /picms/stage/joint_states reading and carries that reading's stamp (INTERFACES:
an image and its stage reading have the identical stamp). The scene (`scene`) is the back-lit
SMR* in its nest at X* (default, `smr`; scene_smr:=false removes it), `empty`, `wire` (a 40 um
wire whose tip sits at X*), `chrome_targets` (bright field) or `flange` (dark field), the part
placed by `part_position` (m, stage frame at encoder 0), `part_tilt_rad` (rotation vector
[tx, ty] of the plane) and `part_rotation_rad` (in-plane). CameraInfo carries K and D
(plumb_bob), or D = 0 when the hidden_distortion switch is on.
"""
from __future__ import annotations

import numpy as np
from rclpy.node import Node
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, JointState

from ct_calib_nodes.nodes.runner import QOS_LATCHED, QOS_RELIABLE_STREAM, declare_parameters, run_node

from ..core.render import Wire, render_frame
from ..core.scenes import make_part
from ..io.convert import MessageError, joint_positions
from .common import CELL_PARAMS, IMAGE_TOPIC, INFO_TOPIC, JOINTS_TOPIC, truth_from_params

PARAMS = {
    **CELL_PARAMS,
    "cameras": (["camera_1", "camera_2", "camera_3"], "cameras this node simulates [-]"),
    "rate_hz": (1.0, "frame rate per camera [Hz]"),
    "scene_smr": (True, "the SMR* sits in its nest at X* (false: empty back-light) [-]"),
    "noise_seed": (1, "seed of the image noise [-]"),
    "scene": ("smr", "what is in view: smr | empty | wire | chrome_targets | flange [-]"),
    "part_position": ([0.0, 0.0, 0.0], "part origin in the stage frame (encoder 0) [m]"),
    "part_tilt_rad": ([0.0, 0.0], "tilt of the part plane, rotation vector [tx, ty] [rad]"),
    "part_rotation_rad": (0.0, "in-plane rotation of the part about its normal [rad]"),
}


def camera_info_msg(intr, stamp, frame_id):
    m = CameraInfo()
    m.header.stamp = stamp
    m.header.frame_id = frame_id
    m.width, m.height = int(intr.width), int(intr.height)
    m.distortion_model = "plumb_bob"
    m.d = [float(v) for v in intr.D]
    m.k = [float(v) for v in intr.K.ravel()]
    m.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    m.p = [float(v) for v in np.column_stack([intr.K, np.zeros(3)]).ravel()]
    return m


class PicmsCameraSim(Node):
    def __init__(self):
        super().__init__("picms_camera_sim")
        self.p = p = declare_parameters(self, PARAMS)
        self.truth = truth_from_params(p)
        names = [c.name for c in self.truth.cameras]
        self.index = {}
        for c in p["cameras"]:
            if c not in names:
                raise ValueError(f"unknown camera {c!r}; the cell has {names}")
            self.index[c] = names.index(c)
        self.rng = np.random.default_rng(int(p["noise_seed"]))
        scene = str(p["scene"])
        if len(p["part_position"]) != 3 or len(p["part_tilt_rad"]) != 2:
            raise ValueError("part_position needs 3 values (m), part_tilt_rad 2 (rad)")
        self.part = make_part(scene, [float(v) for v in p["part_position"]], [float(v) for v in p["part_tilt_rad"]],
                              float(p["part_rotation_rad"]))   # ValueError names an unknown scene
        self.sphere = self.truth.smr_star_stage if (scene == "smr" and p["scene_smr"]) else None
        self.wire = Wire(self.truth.smr_star_stage, np.array([0.3, 0.2, 1.0]), radius_m=20e-6) if scene == "wire" else None
        self.pubs = {c: self.create_publisher(Image, IMAGE_TOPIC.format(c), QOS_RELIABLE_STREAM) for c in self.index}
        self.info_pubs = {c: self.create_publisher(CameraInfo, INFO_TOPIC.format(c), QOS_LATCHED) for c in self.index}
        self.latest = None
        from ct_calib_nodes.nodes.bad_input import BadInputCounter
        self.bad_input = BadInputCounter(self.get_logger())    # counted by kind, logged rate-limited
        self.create_subscription(JointState, JOINTS_TOPIC, self.bad_input.guard(JOINTS_TOPIC, self.on_joints),
                                 qos_profile_sensor_data)
        self.create_timer(1.0 / float(p["rate_hz"]), self.tick)
        from .plant_hooks import SimDiagnostics
        self.diag = SimDiagnostics(self, "frames", lambda: "waiting for stage joint_states" if self.latest is None else None)
        self.get_logger().info(f"simulating {list(self.index)} (cell seed {p['cell_seed']}, scene {scene})")

    def on_joints(self, msg):
        try:
            self.latest = (msg.header.stamp, joint_positions(msg))
        except MessageError as exc:
            self.bad_input.report(JOINTS_TOPIC, f"ignored joint_states: {exc}")

    def tick(self):
        try:
            self._tick()
        except Exception:   # noqa: BLE001 - shutdown while a frame was being rendered
            import rclpy
            if rclpy.ok():
                raise

    def _tick(self):
        if self.latest is None:
            return
        stamp, q = self.latest
        for c, j in self.index.items():
            cam = self.truth.cameras[j]
            img = render_frame(self.truth.camera_pose_at(j, q), cam.true_intrinsics, self.truth.physics, self.rng,
                               sphere_stage=self.sphere, nest_axis_stage=self.truth.nest_axis_stage,
                               wire=self.wire, part=self.part)
            m = Image()
            m.header.stamp = stamp
            m.header.frame_id = f"{c}_optical"
            m.height, m.width = img.shape
            m.encoding = "mono8"
            m.is_bigendian = 0
            m.step = img.shape[1]
            m.data = img.tobytes()
            self.info_pubs[c].publish(camera_info_msg(cam.info_intrinsics, stamp, f"{c}_optical"))
            self.pubs[c].publish(m)
            self.diag.sent.tick()


def main(args=None):
    from ct_calib_nodes.nodes.runner import release_frame_memory  # noqa: PLC0415

    print(f"[picms_camera_sim] {release_frame_memory()}", flush=True)   # 5 MP frames in a writer history of depth 200
    return run_node(PicmsCameraSim, args)


if __name__ == "__main__":
    main()
