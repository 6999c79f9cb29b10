"""Node-process and rclpy fixtures of tests/ros reused here."""
import importlib.util
import pathlib

_spec = importlib.util.spec_from_file_location("reliab_ros_conftest",
                                               pathlib.Path(__file__).resolve().parents[1] / "ros" / "conftest.py")
_ros = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_ros)
start_node, ros_node, executable, NodeProcess = _ros.start_node, _ros.ros_node, _ros.executable, _ros.NodeProcess
