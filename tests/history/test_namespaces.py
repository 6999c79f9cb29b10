"""Namespaced topic names and finding the CT cell in a recording."""
import pytest

from ct_calib_nodes.io.namespaces import find_namespace, normalise, recording_topics, topic


def test_names():
    assert topic("/", "ct/geometry") == "/ct/geometry"          # INTERFACES.md names in the root namespace
    assert topic("", "ct/detector/image") == "/ct/detector/image"
    assert topic("cell_a/", "ct/geometry") == "/cell_a/ct/geometry"
    assert topic("/plant/cell_b", "ct/error_map") == "/plant/cell_b/ct/error_map"
    assert normalise("/cell_a/") == "/cell_a"
    for bad in ("/1cell", "/cell-a", "/ce ll"):
        with pytest.raises(ValueError):
            normalise(bad)


@pytest.mark.ros
def test_find_namespace(tmp_path):
    from sensor_msgs.msg import Image

    from ct_calib_nodes.io.mcap_io import Rosbag2McapWriter

    def bag(name, namespaces):
        with Rosbag2McapWriter(tmp_path / name) as w:
            for ns in namespaces:
                w.add_topic(topic(ns, "ct/detector/image"), "sensor_msgs/msg/Image")
                w.write(topic(ns, "ct/detector/image"), Image(height=1, width=1, encoding="mono16", step=2,
                                                              data=[0, 0]), 1)
        return tmp_path / name

    one = bag("one", ["/cell_a"])
    assert recording_topics(one) == {"/cell_a/ct/detector/image": 1}
    assert find_namespace(one) == "/cell_a" and find_namespace(one, "cell_a") == "/cell_a"
    with pytest.raises(ValueError, match="no /cell_b/ct/detector/image"):
        find_namespace(one, "/cell_b")
    two = bag("two", ["/cell_a", "/"])
    with pytest.raises(ValueError, match=r"several CT cells \['/', '/cell_a'\]"):
        find_namespace(two)
    assert find_namespace(two, "/") == "/"
    assert find_namespace(bag("none", [])) == "/"      # nothing of a CT cell: the solve reports it
