"""A PiCMS recording (one .mcap or a rosbag2 directory) read into the core's `Recording`.

Two passes, so that images need not be held in memory: pass 1 reads CameraInfo, joint_states
and tracker readings (messages may be logged in any order: pairing is by header stamp); pass 2
streams the images, which the pipeline detects only when they fall in a settled period.
Unreadable or non-conforming messages are counted and named, never fatal by themselves.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from ct_calib_nodes.io.mcap_io import ReadReport, iter_recording

from ..core.campaign import Recording
from .convert import MessageError, image_array, intrinsics_from_camera_info, joint_positions, point, stamp_ns

IMAGE_RE = re.compile(r"^/picms/(camera_\d+)/image_raw$")
INFO_RE = re.compile(r"^/picms/(camera_\d+)/camera_info$")
SMR_PREFIX = "/picms/tracker/smr/"
JOINTS = "/picms/stage/joint_states"
JOINTS_REL = "picms/stage/joint_states"


def _names(namespace: str = "/"):
    """(image re, info re, smr prefix, joints topic) of a Pixel Probe cell in a namespace."""
    from ct_calib_nodes.io.namespaces import normalise  # noqa: PLC0415

    ns = normalise(namespace)
    pre = "" if ns == "/" else ns
    return (re.compile("^" + re.escape(pre) + r"/picms/(camera_\d+)/image_raw$"),
            re.compile("^" + re.escape(pre) + r"/picms/(camera_\d+)/camera_info$"),
            pre + SMR_PREFIX, pre + JOINTS)


def find_namespace(path, namespace=None) -> str:
    """The namespace of the Pixel Probe cell in a recording: the given one (checked), else the only one
    whose stage joint_states are present ('/' when none is: the calibration then says what it lacks).
    ValueError naming the candidates when there are several or the given one is absent."""
    from ct_calib_nodes.io.namespaces import normalise, recording_topics, topic  # noqa: PLC0415

    topics = recording_topics(path)
    suffix = "/" + JOINTS_REL
    found = sorted(t[: -len(suffix)] or "/" for t in topics if t.endswith(suffix))
    if namespace is not None:
        ns = normalise(namespace)
        if topic(ns, JOINTS_REL) not in topics:
            raise ValueError(f"the recording has no {topic(ns, JOINTS_REL)}; Pixel Probe cells in it: "
                             f"{found or 'none'}")
        return ns
    if len(found) <= 1:
        return found[0] if found else "/"
    raise ValueError(f"the recording holds several Pixel Probe cells {found}: choose one with --namespace")


def types_of(namespace: str = "/") -> dict:
    """INTERFACES.md types of the cell's topics in a namespace: a topic carrying another type (or a
    schema without the type's fields) is counted as undecodable by the reader, never handed on."""
    img_re, info_re, smr_prefix, joints = _names(namespace)
    return {joints: "sensor_msgs/msg/JointState", img_re: "sensor_msgs/msg/Image",
            info_re: "sensor_msgs/msg/CameraInfo",
            re.compile("^" + re.escape(smr_prefix) + ".+$"): "geometry_msgs/msg/PointStamped"}


@dataclass
class RecordingReport:
    read: ReadReport = field(default_factory=ReadReport)
    problems: list = field(default_factory=list)     # human-readable: what could not be used
    counts: dict = field(default_factory=dict)


def read_recording(path, cell: dict, namespace: str = "/") -> tuple[Recording, RecordingReport]:
    """Pass 1: everything but the images. Returns the Recording (frames empty) and a report."""
    _img_re, INFO_RE, SMR_PREFIX, JOINTS = _names(namespace)  # noqa: N806 - the module names, in the namespace
    rep = RecordingReport()
    rec = Recording(cell=cell)
    js_t, js_q, infos = [], [], {}
    for m in iter_recording(path, report=rep.read, types=types_of(namespace)):
        t = m.topic
        try:
            if t == JOINTS:
                js_q.append(joint_positions(m.msg))
                js_t.append(stamp_ns(m.msg.header.stamp))
            elif t.startswith(SMR_PREFIX):
                rec.tracker.append((stamp_ns(m.msg.header.stamp), t[len(SMR_PREFIX):], point(m.msg)))
            elif INFO_RE.match(t):
                cam = INFO_RE.match(t).group(1)
                if cam not in infos:
                    infos[cam] = intrinsics_from_camera_info(m.msg)
            else:
                continue
            rep.counts[t if not t.startswith(SMR_PREFIX) else "tracker"] = rep.counts.get(t if not t.startswith(SMR_PREFIX) else "tracker", 0) + 1
        except MessageError as exc:
            if len(rep.problems) < 50:
                rep.problems.append(f"{t} at {m.log_time_ns} ns: {exc}")
    rec.camera_info = infos
    rec.joint_stamps_ns = np.array(js_t, dtype=np.int64)
    rec.joint_positions = np.array(js_q, dtype=np.float64).reshape(-1, 3)
    return rec, rep


def iter_frames(path, rep: RecordingReport, namespace: str = "/"):
    """Pass 2: (stamp_ns, camera, image) of every readable image; problems go to rep."""
    IMAGE_RE = _names(namespace)[0]  # noqa: N806
    for m in iter_recording(path, report=ReadReport(), types=types_of(namespace)):
        mm = IMAGE_RE.match(m.topic)
        if not mm:
            continue
        cam = mm.group(1)
        try:
            yield stamp_ns(m.msg.header.stamp), cam, image_array(m.msg)
        except MessageError as exc:
            rep.problems.append(f"{m.topic} at {m.log_time_ns} ns: {exc}")
