"""What every node shares: declared parameters with descriptors, /diagnostics reporting, and a
``main()`` runner with clean shutdown on SIGINT/SIGTERM."""

from __future__ import annotations

import signal
import sys
import time
from typing import Callable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.executors import SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from rclpy.node import Node
from rclpy.task import Future

from mlv_ros import qos

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


class GraphNode(Node):
    """A Node with typed parameter declaration and a /diagnostics publisher."""

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        self._diag_pub = self.create_publisher(DiagnosticArray, qos.DIAGNOSTICS, qos.diagnostics_qos())
        self.diagnostics_sent = 0
        # Like diagnostic_updater: the node's current status is republished every second, so a
        # monitor that joins late still sees it; events are also published the moment they occur.
        self._status = DiagnosticStatus(level=OK, name=self.get_fully_qualified_name(),
                                        message="starting", hardware_id=self.get_name())
        self._heartbeat = self.create_timer(1.0, lambda: self._publish(self._status))
        self.finished = Future()  # completed when the node's job is over (run_node then exits)

    @property
    def done(self) -> bool:
        return self.finished.done()

    def stop(self) -> None:
        """Declare the node's job over; ``run_node`` returns once the executor sees it."""
        if not self.finished.done():
            self.finished.set_result(True)

    def param(self, name: str, default, description: str, *, min_value=None, max_value=None,
              choices: tuple | None = None, read_only: bool = True):
        """Declare a parameter with a descriptor (and range) and return its value.

        Integer/float ranges are enforced by rclpy when set at start-up or at run time.
        """
        desc = ParameterDescriptor(description=description, read_only=read_only)
        if choices:
            desc.additional_constraints = "one of: " + ", ".join(map(str, choices))
        if min_value is not None or max_value is not None:
            if isinstance(default, bool):
                raise TypeError("bool parameters take no range")
            if isinstance(default, int):
                desc.integer_range = [IntegerRange(from_value=int(min_value), to_value=int(max_value), step=0)]
            else:
                desc.floating_point_range = [FloatingPointRange(
                    from_value=float(min_value), to_value=float(max_value), step=0.0)]
        value = self.declare_parameter(name, default, desc).value
        if choices and value not in choices:
            raise ValueError(f"parameter {name}={value!r} must be one of {choices}")
        return value

    def report(self, level: int, message: str, **values) -> None:
        """Publish one DiagnosticStatus (name = node, hardware_id = node name) now, make it the
        node's current status, and log it."""
        status = DiagnosticStatus(level=level, name=self.get_fully_qualified_name(),
                                  message=message, hardware_id=self.get_name())
        status.values = [KeyValue(key=str(k), value=str(v)) for k, v in values.items()]
        self._status = status
        self._publish(status)
        text = f"{message} " + " ".join(f"{k}={v}" for k, v in values.items())
        # rclpy ties a severity to each call site, so each level needs its own line.
        if level == OK:
            self.get_logger().info(text.strip())
        elif level == WARN:
            self.get_logger().warning(text.strip())
        else:
            self.get_logger().error(text.strip())

    def _publish(self, status: DiagnosticStatus) -> None:
        arr = DiagnosticArray(status=[status])
        arr.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(arr)
        self.diagnostics_sent += 1


def run_node(factory: Callable[..., Node], args=None) -> int:
    """Create the node, spin until SIGINT/SIGTERM or the node calls :meth:`GraphNode.stop`,
    then drain what has already arrived and shut down cleanly.

    rclpy's own signal handlers are replaced by ours: a signal only sets a flag, so the context
    stays valid while the node takes every message still queued (a recorder must not lose what
    was sent before the signal) and runs its ``finish()`` (e.g. closing a file).
    """
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop_requested = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: stop_requested.append(signum))
    node = None
    executor = SingleThreadedExecutor()
    try:
        try:
            node = factory()
        except (ValueError, ParameterException, OSError) as exc:  # bad parameters or paths: say so, exit 2
            print(f"error: {exc}", file=sys.stderr)
            return 2
        executor.add_node(node)
        while not stop_requested and not getattr(node, "done", False) and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
        # Drain: keep taking queued messages until none has arrived for 0.2 s.
        handled = getattr(node, "messages_handled", 0)
        quiet_since = time.monotonic()
        while rclpy.ok() and time.monotonic() - quiet_since < 0.2:
            executor.spin_once(timeout_sec=0.05)
            if getattr(node, "messages_handled", 0) != handled:
                handled, quiet_since = node.messages_handled, time.monotonic()
    finally:
        if node is not None:
            if hasattr(node, "finish"):
                node.finish()
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown()
    return 0
