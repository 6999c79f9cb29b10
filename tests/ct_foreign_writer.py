"""CT recordings written by software the project has never seen: the `rosbags` package.

rosbags has its own type store, CDR serializer and MCAP writer and writes the rosbag2 directory
layout (metadata.yaml + .mcap). Recordings written here follow INTERFACES.md (CT cell) and nothing
else; the options make the choices the project's own writer never makes (padded row steps, another
frame_id, unrelated topics, a stage reading logged after its frame).

Shared by tests/graph/test_foreign_recording.py and tests/ct_validation/ct_indep_gen.py (tests/ is on
sys.path through tests/conftest.py; scripts outside pytest insert it themselves).
"""

from __future__ import annotations

import pathlib
from typing import Iterable

import numpy as np

_ENCODINGS = {("u", 2): ("mono16", 2), ("f", 4): ("32FC1", 4)}


def write_ct_recording(bag_dir: pathlib.Path, frames: Iterable, *, frame_id: str = "ct_detector",
                       row_pad_bytes: int = 0, log_topic: bool = False, stage_late_every: int = 0,
                       image_delay_ns: int = 0) -> int:
    """Write ``frames`` = iterable of (stamp_ns, image, alpha_rad, srd_reading_m) as a rosbag2 MCAP directory.

    ``image`` is uint16 (written ``mono16``, raw counts) or float32 (``32FC1``, transmission). The image
    and its JointState carry the identical header stamp; the image is logged ``image_delay_ns`` after
    it, and every ``stage_late_every``-th stage reading is logged after its frame (0 = never).
    ``log_topic`` adds an unrelated /rosout message per frame. Returns the number of frames written.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_JAZZY)
    Image = ts.types["sensor_msgs/msg/Image"]
    JointState = ts.types["sensor_msgs/msg/JointState"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    Log = ts.types["rcl_interfaces/msg/Log"]
    n = 0
    with Writer(pathlib.Path(bag_dir), version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c_log = w.add_connection("/rosout", "rcl_interfaces/msg/Log", typestore=ts) if log_topic else None
        c_js = w.add_connection("/ct/stage/joint_states", "sensor_msgs/msg/JointState", typestore=ts)
        c_img = w.add_connection("/ct/detector/image", "sensor_msgs/msg/Image", typestore=ts)
        for t, image, alpha, srd in frames:
            t = int(t)
            img = np.asarray(image)
            if img.ndim != 2 or (img.dtype.kind, img.dtype.itemsize) not in _ENCODINGS:
                raise ValueError(f"frame {n}: image {img.dtype} {img.shape} is neither a 2-D uint16 (mono16) "
                                 "nor a 2-D float32 (32FC1) array")
            encoding, bpp = _ENCODINGS[(img.dtype.kind, img.dtype.itemsize)]
            img = np.ascontiguousarray(img, dtype=f"<{img.dtype.kind}{bpp}")
            step = img.shape[1] * bpp + row_pad_bytes
            rows = np.zeros((img.shape[0], step), dtype=np.uint8)
            rows[:, : img.shape[1] * bpp] = img.view(np.uint8).reshape(img.shape[0], -1)
            n += 1
            stamp = Time(sec=t // 10**9, nanosec=t % 10**9)
            im = Image(header=Header(stamp=stamp, frame_id=frame_id), height=img.shape[0], width=img.shape[1],
                       encoding=encoding, is_bigendian=0, step=step, data=rows.ravel())
            js = JointState(header=Header(stamp=stamp, frame_id=""), name=["rotary", "magnification"],
                            position=np.array([float(alpha), float(srd)]), velocity=np.zeros(0), effort=np.zeros(0))
            pairs = [(c_js, t, ts.serialize_cdr(js, "sensor_msgs/msg/JointState")),
                     (c_img, t + image_delay_ns, ts.serialize_cdr(im, "sensor_msgs/msg/Image"))]
            if stage_late_every and n % stage_late_every == 0:
                pairs.reverse()
            if c_log is not None:
                log = Log(stamp=stamp, level=20, name="acq", msg=f"frame {n}", file="", function="", line=0)
                w.write(c_log, t, ts.serialize_cdr(log, "rcl_interfaces/msg/Log"))
            for conn, log_t, data in pairs:
                w.write(conn, log_t, data)
    return n
