"""Small shared pieces of the node layer: the Jazzy main() pattern and QoS profiles."""

from __future__ import annotations

import os
import pathlib
import sys
import time

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


FASTDDS_DYNAMIC_PAYLOADS = pathlib.Path(__file__).with_name("fastdds_dynamic_payloads.xml")


def release_frame_memory() -> str:
    """For a process that sends or receives big frames (5 MP images): give each frame's memory back
    to the system once the frame is done with. Call at the start of ``main``, before ``rclpy.init``.

    Two pools kept the memory of the most frames ever held at once, for good:
    - rmw_fastrtps keeps sample payloads in a pool (PREALLOCATED_WITH_REALLOC) that grows to the
      most samples held at once (up to the history depth) and never shrinks. Here each payload is
      freed once taken (reader) or acknowledged (writer): Fast DDS ``historyMemoryPolicy``
      DYNAMIC through an XML profile (RMW_FASTRTPS_USE_QOS_FROM_XML only stops rmw from overriding
      the memory policy; the node's own QoS, depth, reliability and durability, still apply);
    - glibc raises its mmap threshold to the size of the first big block freed, after which
      frame-sized blocks come from the heap and stay with the process when freed: the threshold is
      fixed at 1 MiB (``mallopt``), so every frame buffer is mapped and unmapped.
    Measured (tests/benchmarks/soak_ct_graph.py, doc/ct_reliability.md): the idle Pixel Probe
    calibration node grew 114 -> 189 MiB over 5 minutes of 3 x 5 MP frames/s; with both it follows
    the frames in hand and returns to its start. A Fast DDS XML configuration given in the
    environment, or another middleware, is left alone. Returns what was done (for the log)."""
    done = []
    try:
        import ctypes  # noqa: PLC0415

        if ctypes.CDLL("libc.so.6").mallopt(-3, 1 << 20) == 1:      # M_MMAP_THRESHOLD
            done.append("blocks of 1 MiB and more mapped and unmapped (malloc)")
    except (OSError, AttributeError):                                # not glibc
        pass
    given = [k for k in ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE",
                         "RMW_FASTRTPS_USE_QOS_FROM_XML") if os.environ.get(k)]
    if not os.environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp").startswith("rmw_fastrtps"):
        done.append(f"{os.environ['RMW_IMPLEMENTATION']} left as configured")
    elif given:
        done.append(f"the Fast DDS configuration in {', '.join(given)} left as given")
    else:
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(FASTDDS_DYNAMIC_PAYLOADS)
        os.environ["RMW_FASTRTPS_USE_QOS_FROM_XML"] = "1"
        done.append(f"DDS payloads freed once taken or acknowledged ({FASTDDS_DYNAMIC_PAYLOADS.name})")
    return "frame memory: " + "; ".join(done)


def run_node(node_factory, args=None, threads: int = 0) -> int:
    """Create a node, spin it until shutdown (Ctrl-C, SIGTERM, or the node asks), clean up.

    ``node_factory`` is called after ``rclpy.init``. A node may set
    ``node.exit_code`` and call ``rclpy.try_shutdown()`` to end the process.
    ``threads`` > 0 spins a MultiThreadedExecutor with that many threads (nodes whose services
    wait on their own subscriptions), else the default single-threaded executor.
    """
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        try:
            node = node_factory()
        except ValueError as exc:       # bad parameters or input files: say what, exit 2, no traceback
            print(f"[{getattr(node_factory, '__name__', 'node')}] configuration error: {exc}", file=sys.stderr,
                  flush=True)
            return 2
        if threads > 0:
            from rclpy.executors import MultiThreadedExecutor  # noqa: PLC0415

            executor = MultiThreadedExecutor(num_threads=threads)
            executor.add_node(node)
            executor.spin()
        else:
            rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:                   # noqa: BLE001
        # Ctrl-C / SIGTERM shuts the context down while the executor may be between two waits: rclpy
        # then raises RCLError ("the given context is not valid") instead of ExternalShutdownException.
        # That is a normal stop; anything raised while the context is still valid is a real failure.
        if rclpy.ok():
            raise
    finally:
        if node is not None:
            code = int(getattr(node, "exit_code", 0) or 0)
            close = getattr(node, "close", None)
            if close is not None:
                close()
            bad = getattr(node, "bad_input", None)     # nodes/bad_input.py: totals on the way out
            if bad is not None:
                bad.log_totals()
            node.destroy_node()
        rclpy.try_shutdown()
    return code


# --- pieces every CT node shares -----------------------------------------------------------------

CT_FILE_PARAMS = {
    "instrument_file": ("", "ct_instrument.yaml (nominal SDD, detector); empty = package default [path]"),
    "reference_object_file": ("", "reference_object.yaml (calibrated sphere centres); empty = package default [path]"),
}


def declare_parameters(node, params: dict) -> dict:
    """Declare ``{name: (default, description)}`` on a node; return the values in force."""
    from rcl_interfaces.msg import ParameterDescriptor  # noqa: PLC0415

    for name, (default, text) in params.items():
        node.declare_parameter(name, default, ParameterDescriptor(description=text))
    return {name: node.get_parameter(name).value for name in params}


def load_ct_files(p: dict, logger=None):
    """(CtInstrument, ReferenceObject at the scan temperature) from the CT_FILE_PARAMS values
    (package defaults when empty); the thermal-expansion note goes to ``logger``."""
    from ct_calib_nodes.io import ct_files  # noqa: PLC0415

    instrument = ct_files.load_instrument(p["instrument_file"] or ct_files.default_instrument_path())
    ref = ct_files.load_reference_object(p["reference_object_file"] or ct_files.default_reference_object_path())
    ref, note = ct_files.reference_at_scan(ref, instrument)
    if logger is not None:
        logger.info(note)
    return instrument, ref


POSITION_PARAMS = {
    "position_tolerance_m": (1e-4, "a reported SRD further than this from the current stage position's readings "
                                   "(their median) starts a new position; above the read-back jitter, below the "
                                   "smallest stage step [m]"),
}


def position_tolerance(node) -> float:
    """The node's ``position_tolerance_m`` (declared here when the node has not declared it)."""
    if not node.has_parameter("position_tolerance_m"):
        declare_parameters(node, POSITION_PARAMS)
    tol = float(node.get_parameter("position_tolerance_m").value)
    if not (tol > 0 and tol < float("inf")):
        raise ValueError(f"position_tolerance_m must be a positive length [m], got {tol}")
    return tol


class ObservationIntake:
    """``/ct/observations`` messages into a CampaignAccumulator; bad messages are logged,
    counted and skipped. Stage positions are split on motion in time (parameter
    ``position_tolerance_m``, ct_pipeline.PositionSegmenter)."""

    def __init__(self, node, ref):
        from ct_calib_nodes.core.ct_pipeline import CampaignAccumulator  # noqa: PLC0415

        self.node = node
        self.acc = CampaignAccumulator(position_tolerance(node))
        self.id_to_index = {int(i): k for k, i in enumerate(ref.ids)}
        self.bad_messages = 0
        self.last_rx = None

    def add(self, msg):
        """Add one SphereObservationArray; returns its stage-position index, or None if skipped."""
        from ct_calib_nodes.io.convert import MessageError  # noqa: PLC0415
        from ct_calib_nodes.io.observations_msg import frame_observations  # noqa: PLC0415

        try:
            k = self.acc.add_frame(*frame_observations(msg, self.id_to_index))
        except (MessageError, ValueError) as exc:
            self.bad_messages += 1
            reporter = getattr(self.node, "bad_input", None)      # counted, logged rate-limited
            if reporter is not None:
                reporter.report("/ct/observations", exc)
            else:
                self.node.get_logger().warning(f"skipped bad observation message #{self.bad_messages}: {exc}")
            return None
        self.last_rx = time.monotonic()
        return k

    def idle_for(self, seconds: float) -> bool:
        """True when observations came and none arrived for ``seconds``."""
        return seconds > 0 and self.last_rx is not None and time.monotonic() - self.last_rx > seconds
