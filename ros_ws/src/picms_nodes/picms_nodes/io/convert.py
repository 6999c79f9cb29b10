"""Message <-> array conversion for the PiCMS raw topics (INTERFACES.md, PiCMS section).

Works on rclpy messages and on the dynamic messages an MCAP decoder returns (duck typing):
no message package is imported here.
"""
from __future__ import annotations

import numpy as np

from ..core.camera import Intrinsics

JOINT_NAMES = ("x", "y", "z")


class MessageError(ValueError):
    """A message does not follow INTERFACES.md; the text names what is wrong."""


def stamp_ns(stamp) -> int:
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def image_array(msg) -> np.ndarray:
    """(H, W) uint8 or uint16 array of a mono8 / mono16 sensor_msgs/Image."""
    enc = str(msg.encoding).lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if enc == "mono8":
        dt, bpp = np.uint8, 1
    elif enc == "mono16":
        dt, bpp = (np.dtype("<u2") if not msg.is_bigendian else np.dtype(">u2")), 2
    else:
        raise MessageError(f"image encoding {msg.encoding!r}: mono8 or mono16 expected")
    if h <= 0 or w <= 0 or step < w * bpp:
        raise MessageError(f"image size {w}x{h} with step {step} is inconsistent")
    buf = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if buf.size < h * step:
        raise MessageError(f"image data has {buf.size} bytes, {h * step} expected")
    rows = buf[:h * step].reshape(h, step)[:, :w * bpp]
    return np.ascontiguousarray(rows).view(dt).reshape(h, w).astype(dt.newbyteorder("=") if bpp == 2 else dt)


def intrinsics_from_camera_info(msg) -> Intrinsics:
    """Intrinsics (K, D plumb_bob, size) from a sensor_msgs/CameraInfo."""
    model = str(msg.distortion_model)
    d = np.asarray(list(msg.d), float)
    if model not in ("plumb_bob", "") and d.size and np.any(d):
        raise MessageError(f"CameraInfo distortion model {model!r}: plumb_bob expected")
    K = np.asarray(list(msg.k), float).reshape(3, 3) if len(msg.k) == 9 else None
    if K is None or not np.any(K):
        raise MessageError("CameraInfo K is empty: the camera is not intrinsically calibrated")
    try:
        return Intrinsics(K, d[:5], int(msg.width), int(msg.height))
    except ValueError as exc:
        raise MessageError(f"CameraInfo: {exc}") from exc


def joint_positions(msg) -> np.ndarray:
    """(3,) encoder positions [x, y, z] in m from a sensor_msgs/JointState (by name)."""
    names = list(msg.name)
    pos = list(msg.position)
    if len(pos) != len(names):
        raise MessageError(f"joint_states: {len(names)} names but {len(pos)} positions")
    try:
        q = np.array([pos[names.index(n)] for n in JOINT_NAMES], float)
    except ValueError:
        raise MessageError(f"joint_states names {names}: x, y, z expected") from None
    if not np.all(np.isfinite(q)):
        raise MessageError("joint_states: non-finite position")
    return q


def stage_command(q):
    """trajectory_msgs/JointTrajectory commanding the stage to q = [x, y, z] in m (one point, joints
    x, y, z as INTERFACES.md names them). The message package is imported here only, when a node
    builds a command, so offline tools keep working without it."""
    from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: PLC0415
    q = np.asarray(q, float).reshape(-1)
    if q.shape != (3,) or not np.all(np.isfinite(q)):
        raise ValueError(f"stage command needs three finite positions [x, y, z] in m, got {q.tolist()}")
    m = JointTrajectory()
    m.joint_names = list(JOINT_NAMES)
    pt = JointTrajectoryPoint()
    pt.positions = [float(v) for v in q]
    m.points = [pt]
    return m


def point(msg) -> np.ndarray:
    p = np.array([msg.point.x, msg.point.y, msg.point.z], float)
    if not np.all(np.isfinite(p)):
        raise MessageError("tracker reading is not finite")
    return p
