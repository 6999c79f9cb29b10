"""The numerical core must never import rclpy or a message package (DESIGN.md, layers)."""
import ast
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
CORE_DIRS = sorted(ROOT.glob("ros_ws/src/*/*/core"))
FORBIDDEN_PREFIXES = ("rclpy", "rosidl", "rosbag2", "rmw")


def _forbidden(name: str) -> bool:
    top = name.split(".")[0]
    return top.startswith(FORBIDDEN_PREFIXES) or top.endswith("_msgs") or top.endswith("_srvs") \
        or top in ("builtin_interfaces", "metro_msgs")


def _core_files():
    files = [p for d in CORE_DIRS for p in d.rglob("*.py")]
    assert files, "no core modules found: layout changed?"
    return files


def test_core_dirs_exist():
    names = {d.parent.name for d in CORE_DIRS}
    assert {"ct_calib_nodes", "picms_nodes"} <= names


@pytest.mark.parametrize("path", _core_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_ros_import_in_source(path):
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    bad = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            bad += [a.name for a in node.names if _forbidden(a.name)]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if _forbidden(node.module):
                bad.append(node.module)
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) == "import_module":
            if node.args and isinstance(node.args[0], ast.Constant) and _forbidden(str(node.args[0].value)):
                bad.append(node.args[0].value)
    assert not bad, f"{path} imports ROS packages {bad}"


def test_core_imports_with_ros_blocked():
    """Importing every core module in a fresh interpreter where rclpy and messages cannot load."""
    mods = []
    for p in _core_files():
        pkg_root = p.parents[1]
        rel = p.relative_to(pkg_root.parent).with_suffix("")
        mods.append(".".join(rel.parts).replace(".__init__", ""))
    code = (
        "import sys, importlib\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        top = name.split('.')[0]\n"
        "        if top.startswith(('rclpy', 'rosidl', 'rmw')) or top.endswith(('_msgs', '_srvs')) or top == 'builtin_interfaces':\n"
        "            raise ImportError('core imported ROS package ' + name)\n"
        "sys.meta_path.insert(0, Block())\n"
        f"for m in {mods!r}:\n"
        "    importlib.import_module(m)\n"
        "print('ok', len(sys.modules))\n"
    )
    paths = [str(d.parents[0].parent) for d in CORE_DIRS]
    env_path = ":".join(sorted(set(paths)))
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={"PYTHONPATH": env_path, "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"})
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.startswith("ok")


def test_purity_check_can_fail(tmp_path):
    """The AST check flags a forbidden import (guards against a check that cannot fail)."""
    f = tmp_path / "bad.py"
    f.write_text("import numpy\nfrom sensor_msgs.msg import Image\nimport rclpy.node\n")
    tree = ast.parse(f.read_text())
    found = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
    names = [a.name for n in found if isinstance(n, ast.Import) for a in n.names] + \
            [n.module for n in found if isinstance(n, ast.ImportFrom)]
    assert [n for n in names if _forbidden(n)] == ["rclpy.node", "sensor_msgs.msg"] or \
           sorted(n for n in names if _forbidden(n)) == ["rclpy.node", "sensor_msgs.msg"]
