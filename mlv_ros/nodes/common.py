"""What every node shares: declared parameters with descriptors, /diagnostics reporting, and a
``main()`` runner with clean shutdown on SIGINT/SIGTERM."""

from __future__ import annotations

import inspect
import signal
import sys
import time
from dataclasses import dataclass
from typing import Callable

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSPolicyKind
from rclpy.signals import SignalHandlerOptions
from rclpy.node import Node
from rclpy.task import Future

from mlv_ros import qos

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR


@dataclass
class StreamCount:
    """What one subscription has seen: messages received, and messages its publisher sent that
    never arrived (sequence-number gaps) or were sent before it matched (``missed``)."""

    received: int = 0
    lost: int = 0
    missed: int = 0
    last_sequence: int | None = None
    publisher_restarts: int = 0


class GraphNode(Node):
    """A Node with typed parameter declaration, a /diagnostics publisher, and loss accounting on
    every subscription."""

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        self._diag_pub = self.create_publisher(DiagnosticArray, qos.DIAGNOSTICS, qos.diagnostics_qos())
        self.diagnostics_sent = 0
        # Like diagnostic_updater: the node's current status is republished every second, so a
        # monitor that joins late still sees it; events are also published the moment they occur.
        self._status = DiagnosticStatus(level=OK, name=self.get_fully_qualified_name(),
                                        message="starting", hardware_id=self.get_name())
        self.streams: dict[str, StreamCount] = {}
        self._heartbeat = self.create_timer(1.0, lambda: self._publish(self._with_counts(self._status)))
        self.finished = Future()  # completed when the node's job is over (run_node then exits)
        self.last_error: DiagnosticStatus | None = None  # the latest ERROR reported
        self.failure: str | None = None  # why the node gave up (see fail)

    @property
    def done(self) -> bool:
        return self.finished.done()

    @property
    def status(self) -> DiagnosticStatus:
        """The node's current status (the last one reported)."""
        return self._status

    def stop(self) -> None:
        """Declare the node's job over; ``run_node`` returns once the executor sees it."""
        if not self.finished.done():
            self.finished.set_result(True)

    def fail(self, message: str, **values) -> None:
        """Give up: report ``message`` as an ERROR, keep it as :attr:`failure` and stop.

        For what the node cannot go on from (not for a bad message it can skip): ``run_node``
        then exits 1, and ``mlv-ros run`` ends the run at once with this reason.
        """
        self.report(ERROR, message, **values)
        self.failure = status_text(self._status)
        self.stop()

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

    def create_subscription(self, msg_type, topic: str, callback, qos_profile, **kwargs):
        """``Node.create_subscription`` that also accounts for loss on ``topic``.

        DDS does not tell a subscriber that its own queue overflowed or that a KEEP_LAST writer
        dropped samples it had not delivered; the writer's sequence numbers do: a gap between two
        consecutive messages is that many messages lost, reported on /diagnostics at once and
        counted in every heartbeat (``received``/``lost``/``missed`` per topic). rclpy does not
        expose the writer's GUID, so sequences are only checked while the topic has a single
        publisher (every graph stream has one); a sequence number going back means a new
        (restarted) publisher.
        ``callback`` may take ``(msg)`` or ``(msg, message_info)``, as with rclpy.
        """
        count = self.streams.setdefault(topic, StreamCount())
        try:
            inspect.signature(callback).bind(object())
            wants_info = False
        except TypeError:
            wants_info = True

        def counted(msg, info):
            self._account(topic, count, info.get("publication_sequence_number"))
            return callback(msg, info) if wants_info else callback(msg)

        # A publisher whose QoS cannot serve this subscription (e.g. VOLATILE where history is
        # asked for) never connects: nothing would arrive, so say why.
        kwargs.setdefault("event_callbacks", SubscriptionEventCallbacks(incompatible_qos=lambda event: self.report(
            ERROR, "a publisher's QoS is incompatible with this subscription: its messages cannot arrive",
            topic=topic, policy=QoSPolicyKind(event.last_policy_kind).name, publishers=event.total_count)))
        return super().create_subscription(msg_type, topic, counted, qos_profile, **kwargs)

    def _account(self, topic: str, count: StreamCount, seq: int | None) -> None:
        count.received += 1
        # No sequence numbers from the rmw, or several publishers whose sequences interleave
        # (rclpy does not say which one sent a message), or /diagnostics (a report about it would
        # feed back into it): count only.
        if not seq or topic == qos.DIAGNOSTICS or self.count_publishers(topic) > 1:
            return
        last, count.last_sequence = count.last_sequence, seq
        if last is None:
            if seq > 1:
                count.missed += seq - 1
                self.report(WARN, "messages published before this node subscribed were not received",
                            topic=topic, missed=seq - 1, first_sequence=seq)
        elif seq <= last:
            count.publisher_restarts += 1
            count.missed += seq - 1
            self.report(WARN if seq > 1 else OK, "a new publisher started on the topic",
                        topic=topic, sequence=seq, previous_sequence=last)
        elif seq > last + 1:
            count.lost += seq - last - 1
            self.report(ERROR, "messages lost", topic=topic, lost=seq - last - 1, total_lost=count.lost,
                        after_sequence=last, received=count.received)

    def _with_counts(self, status: DiagnosticStatus) -> DiagnosticStatus:
        """``status`` plus the per-topic counts, as the heartbeat publishes it."""
        extra = []
        for topic, c in self.streams.items():
            extra += [KeyValue(key=f"received {topic}", value=str(c.received)),
                      KeyValue(key=f"lost {topic}", value=str(c.lost)),
                      KeyValue(key=f"missed {topic}", value=str(c.missed))]
        return DiagnosticStatus(level=status.level, name=status.name, message=status.message,
                                hardware_id=status.hardware_id, values=list(status.values) + extra)

    def report(self, level: int, message: str, **values) -> None:
        """Publish one DiagnosticStatus (name = node, hardware_id = node name) now, make it the
        node's current status, and log it."""
        status = DiagnosticStatus(level=level, name=self.get_fully_qualified_name(),
                                  message=message, hardware_id=self.get_name())
        status.values = [KeyValue(key=str(k), value=str(v)) for k, v in values.items()]
        self._status = status
        if level == ERROR:
            self.last_error = status
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


def status_text(status: DiagnosticStatus) -> str:
    """One line for people: ``message (key: value, ...)``."""
    values = ", ".join(f"{kv.key}: {kv.value}" for kv in status.values)
    return f"{status.message} ({values})" if values else status.message


def run_node(factory: Callable[..., Node], args=None) -> int:
    """Create the node, spin until SIGINT/SIGTERM or the node calls :meth:`GraphNode.stop`,
    then drain what has already arrived and shut down cleanly. Returns 0, 2 for a node that
    could not start (bad parameters or paths), 1 for one that gave up (:meth:`GraphNode.fail`).

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
    return 1 if getattr(node, "failure", None) else 0
