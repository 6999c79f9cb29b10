"""MCAP written by the project (recorder node over DDS, and the offline writer) read back by
independent readers: mcap-ros2-support's decoder and the rosbags package."""
import pathlib

import numpy as np
import pytest
from sensor_msgs.msg import Image, JointState

from metro_msgs.msg import EstimateStamped
from ct_calib_nodes.io.mcap_io import (Rosbag2McapWriter, ReadReport, iter_recording, message_definition,
                                       type_hash)
from ct_calib_nodes.nodes.runner import QOS_LATCHED, QOS_RELIABLE_STREAM

TOPICS = {"/ct/detector/image": "sensor_msgs/msg/Image", "/ct/stage/joint_states": "sensor_msgs/msg/JointState",
          "/ct/geometry/estimate": "metro_msgs/msg/EstimateStamped"}


def _messages(i: int):
    img = Image(height=4, width=5, encoding="mono16", is_bigendian=0, step=10)
    img.data = (np.arange(20, dtype=np.uint16) * (i + 1)).tobytes()
    img.header.frame_id = "ct_detector"
    img.header.stamp.sec, img.header.stamp.nanosec = 100 + i, 5000
    js = JointState(name=["rotary", "magnification"], position=[0.1 * i, 0.364])
    js.header.stamp = img.header.stamp
    return img, js


def _check_independent_readers(path: pathlib.Path, n_frames: int):
    # 1. mcap-ros2-support: decodes from the schema text stored in the file
    from mcap_ros2.reader import read_ros2_messages

    files = [path] if path.is_file() else sorted(path.glob("*.mcap"))
    got = {}
    for f in files:
        for m in read_ros2_messages(str(f)):
            got.setdefault(m.channel.topic, []).append(m.ros_msg)
            assert m.schema.encoding == "ros2msg" and m.channel.message_encoding == "cdr"
    imgs = got["/ct/detector/image"]
    assert len(imgs) == n_frames
    for i, img in enumerate(sorted(imgs, key=lambda m: m.header.stamp.sec)):
        np.testing.assert_array_equal(np.frombuffer(bytes(img.data), np.uint16), np.arange(20) * (i + 1))
        assert img.encoding == "mono16" and img.header.frame_id == "ct_detector"
    js = sorted(got["/ct/stage/joint_states"], key=lambda m: m.header.stamp.sec)
    assert [list(j.name) for j in js] == [["rotary", "magnification"]] * n_frames
    np.testing.assert_allclose([j.position[0] for j in js], 0.1 * np.arange(n_frames))
    est = got["/ct/geometry/estimate"][-1]
    assert list(est.names) == ["z_R", "x_D"] and list(est.values) == [0.3652, 1.3e-3]

    # 2. rosbags: reads the bare file and the rosbag2 directory; computes RIHS01 from the schema text
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    with AnyReader([path]) as reader:
        counts = {}
        for conn, _t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
            if conn.topic == "/ct/geometry/estimate":
                assert list(msg.values) == [0.3652, 1.3e-3]
            if conn.topic == "/ct/detector/image":
                assert msg.height == 4 and msg.width == 5
        assert counts["/ct/detector/image"] == n_frames and counts["/ct/stage/joint_states"] == n_frames
        for conn in reader.connections:
            assert conn.msgtype == TOPICS[conn.topic]
            # the full definition text reproduces rosidl's type hash: nothing is missing from it
            schema_text = conn.msgdef.data if hasattr(conn.msgdef, "data") else conn.msgdef
            ts = get_typestore(Stores.EMPTY)
            ts.register(get_types_from_msg(schema_text, conn.msgtype))
            assert ts.hash_rihs01(conn.msgtype) == type_hash(conn.msgtype) != ""


def test_definition_text_has_dependencies():
    text = message_definition("sensor_msgs/msg/Image")
    assert text.startswith("# This message contains an uncompressed image")
    assert "\n" + "=" * 80 + "\nMSG: std_msgs/msg/Header\n" in text
    assert "\nMSG: builtin_interfaces/msg/Time\n" in text


@pytest.mark.parametrize("layout", ["file", "directory"])
def test_offline_writer_read_by_independent_readers(tmp_path, layout):
    path = tmp_path / ("rec.mcap" if layout == "file" else "rec_bag")
    with Rosbag2McapWriter(path) as w:
        for i in range(3):
            img, js = _messages(i)
            w.write("/ct/detector/image", img, 10**9 * (i + 1))
            w.write("/ct/stage/joint_states", js, 10**9 * (i + 1) + 1)
        w.write("/ct/geometry/estimate", EstimateStamped(names=["z_R", "x_D"], values=[0.3652, 1.3e-3]), 5 * 10**9)
    if layout == "directory":
        assert (path / "metadata.yaml").is_file()
    _check_independent_readers(path, 3)
    rep = ReadReport()
    topics = [m.topic for m in iter_recording(path, report=rep)]
    assert rep.complete and rep.messages_read == 7 and topics.count("/ct/detector/image") == 3


def test_truncated_recording_yields_what_is_readable(tmp_path):
    """Frames of 128 KiB in chunks of about 1 MiB: cutting the file in half loses the chunk that
    was cut and everything after it, and nothing before it."""
    path = tmp_path / "rec.mcap"
    frame = np.random.default_rng(1).integers(0, 60000, (256, 256)).astype(np.uint16)  # incompressible
    with Rosbag2McapWriter(path) as w:
        for i in range(40):
            img = Image(height=256, width=256, encoding="mono16", step=512, data=np.where(np.arange(frame.size).reshape(frame.shape) == 0, i, frame).astype(np.uint16).tobytes())
            w.write("/ct/detector/image", img, 10**9 * (i + 1))
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    rep = ReadReport()
    msgs = list(iter_recording(cut, report=rep))
    assert 8 <= len(msgs) < 20 and rep.messages_read == len(msgs)
    for i, m in enumerate(msgs):   # what was read is intact and in order
        assert np.frombuffer(bytes(m.msg.data), np.uint16)[0] == i
    assert rep.errors and "truncated" in rep.errors[0] and not rep.complete


def test_recorder_node_over_dds(tmp_path, start_node, ros_node):
    """The recorder console script records raw bytes of three topics published here."""
    out = tmp_path / "bag"
    rec = start_node("ct_calib_nodes", "mcap_recorder", "--ros-args", "-p", f"output:={out}",
                     "-p", "topics:=[/ct/detector/image, /ct/stage/joint_states, /ct/geometry/estimate]")
    pub_i = ros_node.create_publisher(Image, "/ct/detector/image", QOS_RELIABLE_STREAM)
    pub_j = ros_node.create_publisher(JointState, "/ct/stage/joint_states", QOS_RELIABLE_STREAM)
    pub_e = ros_node.create_publisher(EstimateStamped, "/ct/geometry/estimate", QOS_LATCHED)
    pub_e.publish(EstimateStamped(names=["z_R", "x_D"], values=[0.3652, 1.3e-3]))
    assert ros_node.spin_until(lambda: all(p.get_subscription_count() > 0 for p in (pub_i, pub_j, pub_e)),
                               timeout=30), rec.log()
    n = 4
    for i in range(n):
        img, js = _messages(i)
        pub_i.publish(img)
        pub_j.publish(js)
    # diagnostics: per topic what was written, checked against the file read back below
    from diagnostic_msgs.msg import DiagnosticArray
    diags = []
    ros_node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)

    def recorder_status():
        st = [s for d in diags for s in d.status if s.name == "/mcap_recorder"]
        return st[-1] if st else None

    def written(st):
        return {kv.key: kv.value for kv in st.values} if st is not None else {}
    assert ros_node.spin_until(lambda: written(recorder_status()).get("messages /ct/detector/image") == str(n),
                               timeout=15), (rec.log(), recorder_status())
    st = recorder_status()
    v = written(st)
    assert st.level == b"\x00" and st.hardware_id == "/", st
    assert v["messages /ct/stage/joint_states"] == str(n) and v["messages /ct/geometry/estimate"] == "1", v
    assert v["dropped (lost in DDS)"] == "0" and v["dropped (write errors)"] == "0"
    assert rec.stop() == 0, rec.log()
    assert "wrote" in rec.log()
    _check_independent_readers(out, n)
    from mcap.reader import make_reader
    size = {}
    for f in sorted(out.glob("*.mcap")):
        with open(f, "rb") as fh:
            r = make_reader(fh)
            for _schema, ch, msg in r.iter_messages():
                size[ch.topic] = size.get(ch.topic, 0) + len(msg.data)
    for t in TOPICS:
        assert int(v[f"bytes {t}"]) == size[t], (t, v, size)


def test_exact_size_of_messages_with_boolean_fields():
    """CameraInfo carries a boolean (roi.do_rectify): its exact CDR size is known and round-trips."""
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import CameraInfo

    from ct_calib_nodes.io.mcap_io import cdr_size, serialize_exact

    m = CameraInfo(width=581, height=682, distortion_model="plumb_bob")
    m.d = [-0.02, 0.0, 0.0, 0.0, 0.0]
    m.k = [4091.0, 0.0, 290.5, 0.0, 4091.0, 340.5, 0.0, 0.0, 1.0]
    m.roi.do_rectify = True
    data = serialize_exact(m)
    assert len(data) == cdr_size(m) <= len(serialize_message(m))
    back = deserialize_message(data, CameraInfo)
    assert back.roi.do_rectify and list(back.k) == list(m.k) and back.distortion_model == "plumb_bob"
