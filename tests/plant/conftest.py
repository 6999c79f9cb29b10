"""The node-process fixtures of tests/ros, shared."""
import importlib.util
import pathlib

_spec = importlib.util.spec_from_file_location("ros_test_helpers",
                                               pathlib.Path(__file__).resolve().parents[1] / "ros" / "conftest.py")
_mod = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_mod)
NodeProcess, executable, ros_node, start_node = _mod.NodeProcess, _mod.executable, _mod.ros_node, _mod.start_node
