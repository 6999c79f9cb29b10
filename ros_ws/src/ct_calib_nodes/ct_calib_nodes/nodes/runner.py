"""Small shared pieces of the node layer: the Jazzy main() pattern and QoS profiles."""

from __future__ import annotations

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# Calibration results: a late subscriber still gets the latest one.
QOS_LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Raw data and observations from the project's own instruments: reliable, deep queue, so a
# recording of a campaign is complete. Subscribers use qos_profile_sensor_data (best effort),
# which matches both these publishers and best-effort real drivers.
QOS_RELIABLE_STREAM = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=200,
                                 reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


def run_node(node_factory, args=None) -> int:
    """Create a node, spin it until shutdown (Ctrl-C, SIGTERM, or the node asks), clean up.

    ``node_factory`` is called after ``rclpy.init``. A node may set
    ``node.exit_code`` and call ``rclpy.try_shutdown()`` to end the process.
    """
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = node_factory()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            code = int(getattr(node, "exit_code", 0) or 0)
            close = getattr(node, "close", None)
            if close is not None:
                close()
            node.destroy_node()
        rclpy.try_shutdown()
    return code
