"""Message <-> array conversion for the CT cell. Works on rclpy messages and on the objects
mcap-ros2-support decodes from recordings (attribute access only)."""

from __future__ import annotations

import numpy as np

SUPPORTED_ENCODINGS = ("mono16", "16UC1", "mono8", "8UC1", "32FC1")
_DTYPE = {"mono16": "u2", "16UC1": "u2", "mono8": "u1", "8UC1": "u1", "32FC1": "f4"}


class MessageError(ValueError):
    """A message that cannot be used; the text names what is wrong."""


def stamp_ns(stamp) -> int:
    """builtin_interfaces/Time -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def array_from_image(msg, expected_shape=None) -> tuple[np.ndarray, str]:
    """sensor_msgs/Image -> (array (rows, cols), encoding), checked. The one decoder of the live
    detector node and the offline replay.

    Integer encodings (``mono16``, ``16UC1``: uint16; ``mono8``, ``8UC1``: uint8) are raw counts
    (INTERFACES.md's mono16 semantics, the bit depth from the encoding); ``32FC1`` is I/I0.

    Raises MessageError naming the problem: unsupported encoding, size or step
    inconsistent with the data, size different from ct_instrument.yaml.
    """
    enc = str(msg.encoding)
    if enc not in SUPPORTED_ENCODINGS:
        raise MessageError(f"unsupported image encoding {enc!r} (expected one of {SUPPORTED_ENCODINGS})")
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    code = _DTYPE[enc]
    bpp = int(code[1])
    if h <= 0 or w <= 0:
        raise MessageError(f"empty image {w}x{h}")
    if step < w * bpp:
        raise MessageError(f"step {step} too small for {w} px of {enc}")
    data = bytes(msg.data) if not isinstance(msg.data, (bytes, bytearray, memoryview)) else msg.data
    if len(data) != step * h:
        raise MessageError(f"data has {len(data)} bytes, expected step*height = {step * h}")
    if expected_shape is not None and (h, w) != tuple(expected_shape):
        raise MessageError(f"image is {w}x{h} px but ct_instrument.yaml says {expected_shape[1]}x{expected_shape[0]}")
    big = bool(msg.is_bigendian)
    dtype = np.dtype((">" if big else "<") + code)
    arr = np.frombuffer(data, dtype=np.uint8).reshape(h, step)[:, : w * bpp]
    arr = np.ascontiguousarray(arr).view(dtype).reshape(h, w)
    return arr.astype(dtype.newbyteorder("=")), enc


def image_from_array(image: np.ndarray, stamp, frame_id: str):
    """(rows, cols) uint16 -> mono16 Image, float32 -> 32FC1 Image."""
    from sensor_msgs.msg import Image  # noqa: PLC0415

    a = np.ascontiguousarray(image)
    if a.dtype == np.uint16:
        enc, bpp = "mono16", 2
    elif a.dtype == np.float32:
        enc, bpp = "32FC1", 4
    else:
        raise ValueError(f"image dtype must be uint16 or float32, got {a.dtype}")
    msg = Image(height=a.shape[0], width=a.shape[1], encoding=enc, is_bigendian=0, step=a.shape[1] * bpp)
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.data = a.astype(a.dtype.newbyteorder("<")).tobytes()
    return msg


def stage_from_joint_state(msg) -> tuple[float, float]:
    """sensor_msgs/JointState of the CT stage -> (alpha [rad], reported SRD [m]), checked."""
    names = list(msg.name)
    pos = list(msg.position)
    try:
        ia, im = names.index("rotary"), names.index("magnification")
    except ValueError:
        raise MessageError(f"joint names {names} lack 'rotary' and 'magnification'") from None
    if len(pos) != len(names):
        raise MessageError(f"{len(names)} joint names but {len(pos)} positions")
    alpha, srd = float(pos[ia]), float(pos[im])
    if not (np.isfinite(alpha) and np.isfinite(srd)):
        raise MessageError(f"non-finite stage reading (alpha={alpha}, srd={srd})")
    if not 0.0 < srd < 20.0:
        raise MessageError(f"reported SRD {srd} m is not plausible (metres expected)")
    return alpha, srd
