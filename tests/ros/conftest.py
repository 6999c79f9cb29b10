"""Helpers for node- and graph-level tests: private rclpy contexts and node processes."""
import os
import pathlib
import signal
import subprocess
import sys
import time

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
INSTALL = ROOT / "ros_ws" / "install"

try:
    import rclpy  # noqa: F401 - only checks that the ROS environment is loaded
    import metro_msgs.msg  # noqa: F401
except ImportError as exc:  # pragma: no cover - a clear message instead of a wall of errors
    raise pytest.UsageError(
        f"ROS environment not loaded ({exc}). Run the tests with `bash scripts/test.sh`, "
        "or `source scripts/env.sh` first.") from None


def executable(pkg: str, exe: str) -> pathlib.Path:
    """Where `ros2 run pkg exe` finds a console script (install/<pkg>/lib/<pkg>/<exe>)."""
    path = INSTALL / pkg / "lib" / pkg / exe
    assert path.is_file(), f"{path} missing: run scripts/setup.sh"
    return path


class NodeProcess:
    """A node started in its own process, like `ros2 run`; output kept in a log file."""

    def __init__(self, argv, log_path: pathlib.Path):
        self.log_path = log_path
        self._log = open(log_path, "wb")
        self.proc = subprocess.Popen([str(a) for a in argv], stdout=self._log, stderr=subprocess.STDOUT,
                                     env=os.environ.copy(), start_new_session=True)

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors="replace")

    def stop(self, timeout=15.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
        self._log.close()
        return self.proc.returncode


@pytest.fixture
def start_node(tmp_path):
    procs = []

    def _start(pkg, exe, *args, name=None):
        p = NodeProcess([executable(pkg, exe), *args], tmp_path / f"{name or exe}.log")
        procs.append(p)
        return p

    def _python(code: str, name="child"):
        p = NodeProcess([sys.executable, "-c", code], tmp_path / f"{name}.log")
        procs.append(p)
        return p

    _start.python = _python
    yield _start
    for p in procs:
        p.stop()


@pytest.fixture
def ros_node():
    """An rclpy node in a private context; spin with `spin_until(pred, timeout)`."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    ctx = Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node("test_probe", context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)

    def spin_until(pred, timeout=20.0):
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            ex.spin_once(timeout_sec=0.05)
            if pred():
                return True
        return False

    node.spin_until = spin_until
    yield node
    ex.shutdown()
    node.destroy_node()
    rclpy.shutdown(context=ctx)
