# Copyright 2026 The mlv_ros authors
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.

"""
What every node shares: parameters, /diagnostics, its study and a ``main()`` runner.

Declared parameters with descriptors, /diagnostics reporting, the study a node keeps to (messages
of another study are reported and ignored), and a ``main()`` runner with clean shutdown on
SIGINT/SIGTERM.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
import inspect
import signal
import sys
import time
from typing import Callable

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from mlv_msgs.msg import ModelState as ModelStateMsg
from mlv_ros import conversions, qos
from mlv_ros.core.streaming import StampPairer
from mlv_ros.core.types import StudyShape
from mlv_ros.threads import compute_threads
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
import rclpy
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.exceptions import ParameterException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import QoSPolicyKind
from rclpy.signals import SignalHandlerOptions
from rclpy.task import Future
from sensor_msgs.msg import PointCloud2

OK, WARN, ERROR = DiagnosticStatus.OK, DiagnosticStatus.WARN, DiagnosticStatus.ERROR
USE_FQN = 'diagnostic_updater.use_fqn'
# diagnostic_updater's hardware_id for what has no hardware of its own ("set this value to none").
HARDWARE_ID = 'none'
# Registered clouds / states held while waiting for their pair: the registration publishes one
# pair (latched), a restart another.
REGISTRATIONS_HELD = 4


@dataclass
class StreamCount:
    """
    What one subscription has seen: messages received and messages lost or missed.

    ``lost``: messages its publisher sent that never arrived (sequence-number gaps); ``missed``:
    messages it sent before this subscription matched.
    """

    received: int = 0
    lost: int = 0
    missed: int = 0
    last_sequence: int | None = None
    publisher_restarts: int = 0


def stamp_key(stamp) -> tuple[int, int]:
    """Return a header stamp as a dict key (what pairs a cloud with its model state)."""
    return (int(stamp.sec), int(stamp.nanosec))


class Silence:
    """
    Seconds an input stream has been silent, counted only while the node was spun.

    A wall-clock gap since the last message mistakes a stalled executor for a stream that
    stopped: a frame publisher blocked on a slow RELIABLE reader, a long solve, or a loaded
    machine holds every callback of the process, and when the executor resumes, a timer may run
    before the messages that waited in the queue (seen: a run on a 2-core machine at load 8
    registered with 7 of 12 ED slices and delivered 14 wrong phases as ok). Each :meth:`tick`
    (from the node's own timer of period ``period_s``) adds the time since the last tick, but
    never more than two periods, so a stall counts as two periods of silence at most.
    """

    def __init__(self, period_s: float):
        self.period_s = float(period_s)
        self.seconds = 0.0
        self._tick_at = None

    def heard(self) -> None:
        """Note that a message arrived: the stream is alive."""
        self.seconds = 0.0

    def tick(self, now: float | None = None) -> float:
        """Count the time since the last tick, at most two periods; return the silence, s."""
        now = time.monotonic() if now is None else now
        if self._tick_at is not None:
            self.seconds += min(max(now - self._tick_at, 0.0), 2.0 * self.period_s)
        self._tick_at = now
        return self.seconds


class SubscriberWait:
    """
    A publisher's wait for its subscribers: up to a time limit, then on with those present.

    A subscriber that matches after a message went out on a VOLATILE topic never gets it, so a
    node waits for ``expected`` matched subscribers before it publishes; one that never comes must
    not hold the graph for ever: after ``timeout_s`` the node goes on with those present
    (:meth:`go_on`: one WARN naming how many it waited for) or gives up.

    Parameters
    ----------
    expected : int
        Matched subscribers to wait for (0: never wait).
    timeout_s : float
        Seconds to wait, from ``since`` or from the first :meth:`poll` that finds too few.
    since : float, optional
        ``time.monotonic()`` when the wait began (default: at the first poll that waits).

    """

    WAIT, GO, LATE = 'wait', 'go', 'late'

    def __init__(self, expected: int, timeout_s: float, since: float | None = None):
        self.expected = int(expected)
        self.timeout_s = float(timeout_s)
        self.since = since

    @property
    def waiting(self) -> bool:
        """Return whether a wait is under way (the last poll did not find enough)."""
        return self.since is not None

    def poll(self, matched: int, ready: bool = True) -> str:
        """
        Return whether to publish now: GO, WAIT, or LATE (the wait ran out).

        Parameters
        ----------
        matched : int
            Subscribers matched now.
        ready : bool
            Whatever else the node waits for is there (e.g. a /diagnostics listener).

        Returns
        -------
        str
            GO: ``matched`` ≥ ``expected`` and ``ready`` (the wait ends); WAIT: not yet, within
            ``timeout_s``; LATE: not yet, and ``timeout_s`` has passed.

        """
        if matched >= self.expected and ready:
            self.since = None
            return self.GO
        now = time.monotonic()
        if self.since is None:
            self.since = now
        return self.WAIT if now - self.since < self.timeout_s else self.LATE

    def go_on(self, node: 'GraphNode', matched: int) -> None:
        """
        Publish to the subscribers present after a LATE poll; wait no more for the absent.

        Parameters
        ----------
        node : GraphNode
            Reports the WARN when fewer than ``expected`` matched.
        matched : int
            Subscribers matched now: the new ``expected``.

        """
        if matched < self.expected:
            node.report(
                WARN,
                'fewer subscribers than expected; publishing anyway',
                matched=matched,
                expected=self.expected,
                waited_s=self.timeout_s,
            )
        self.expected = matched


class RecentKeys:
    """
    The last ``size`` keys added, each with a value (bounded memory).

    E.g. the stamps of another study's model states → that study, whose point clouds (which cannot
    carry a study id) are dropped with them.
    """

    def __init__(self, size: int = 1000):
        self.size = size
        self._keys: dict = {}

    def add(self, key, value=None) -> None:
        self._keys[key] = value
        while len(self._keys) > self.size:
            del self._keys[next(iter(self._keys))]

    def get(self, key, default=None):
        return self._keys.get(key, default)

    def __contains__(self, key) -> bool:
        return key in self._keys


class GraphNode(Node):
    """
    A Node with typed parameters, /diagnostics, loss accounting and the study it keeps to.

    Typed parameter declaration, a /diagnostics publisher, loss accounting on every subscription,
    and the study it keeps to (:attr:`study`, :meth:`foreign`).
    """

    # What this node's one diagnostic task is called: statuses are named "<node>: <task>", as
    # diagnostic_updater names them (subclasses say what they do).
    DIAGNOSTIC_TASK = 'status'

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        # The uniform counters of progress(): messages taken from the graph, results put out,
        # and whether the node holds an input it could not use and waits for a new one.
        self.messages_handled = 0
        self.published = 0
        self.blocked = 0
        self._topics: dict[str, str] = {}
        self._diag_pub = self.create_publisher(
            DiagnosticArray, qos.DIAGNOSTICS, qos.diagnostics_qos()
        )
        self.diagnostics_sent = 0
        # As diagnostic_updater: "<node name>: <task>", the node's fully qualified name when
        # diagnostic_updater.use_fqn is true (two graphs in two namespaces share /diagnostics).
        use_fqn = self.param(
            USE_FQN,
            False,
            "name diagnostic statuses by the node's fully qualified name "
            "(as diagnostic_updater's parameter of that name)",
        )
        node = self.get_fully_qualified_name() if use_fqn else self.get_name()
        self.diagnostic_name = f'{node}: {self.DIAGNOSTIC_TASK}'
        # Like diagnostic_updater: the node's current status is republished every second, so a
        # monitor that joins late still sees it; events are also published the moment they occur.
        self._status = self.diagnostic_status(OK, 'starting')
        self.streams: dict[str, StreamCount] = {}
        self._heartbeat = self.create_timer(
            1.0, lambda: self._publish(self._with_counts(self._status))
        )
        self.finished = Future()  # completed when the node's job is over (run_node then exits)
        self.last_error: DiagnosticStatus | None = None  # the latest ERROR reported
        self.failure: str | None = None  # why the node gave up (see fail)
        # The study this node works on: adopted from the first message it takes (or set by
        # whoever starts the graph); messages of any other study are reported and ignored.
        self.study = StudyShape()
        self.other_studies: Counter = Counter()  # other study id → its messages ignored
        # Stamps of model states of another study → that study: the clouds of those stamps (a
        # cloud cannot carry a study) go with them, the ones held in these (topic, StampPairer)
        # at once, later ones as they come (other_study_state, other_study_cloud).
        self._other_study_stamps = RecentKeys()
        self.held_clouds: list[tuple[str, StampPairer]] = []

    # Parameter checks beyond what a descriptor's range can say (param's ``check``): rclpy runs
    # this callback when a parameter is declared with its start-up value and whenever one is set.
    def _checked_parameters(self, parameters) -> SetParametersResult:
        for p in parameters:
            check = self._parameter_checks.get(p.name)
            why = check(p.value) if check is not None else None
            if why:
                return SetParametersResult(successful=False, reason=f'{p.name}={p.value!r}: {why}')
        return SetParametersResult(successful=True)

    def progress(self) -> dict:
        """
        Return what the node has done so far, under the same names for every node.

        Returns
        -------
        dict
            ``received``: messages it took from the graph's topics; ``published``: results it
            put out (frames, tag point sets, phases, metrics, replayed messages); ``blocked``: 1
            while it holds an input it could not use and cannot go on without (a registration
            that failed, a registered model the solver or analyzer cannot build on, frames no
            subscriber takes: it waits for what will not come, its latest ERROR says why),
            else 0.

        """
        return {
            'received': int(self.messages_handled),
            'published': int(self.published),
            'blocked': int(self.blocked),
        }

    def publisher(self, topic: str, msg_type):
        """
        Create the publisher of graph topic ``topic``, relative to the node's namespace.

        Parameters
        ----------
        topic : str
            A graph topic by its root name (:mod:`mlv_ros.qos`), published with its profile.
        msg_type : type
            Its message class.

        Returns
        -------
        Publisher
            The publisher.

        """
        return self.create_publisher(msg_type, qos.relative(topic), qos.topic_qos(topic))

    def subscribe(self, topic: str, msg_type, callback, catch_up: bool = False):
        """
        Subscribe to graph topic ``topic``, relative to the node's namespace, accounting for loss.

        Parameters
        ----------
        topic : str
            A graph topic by its root name (:mod:`mlv_ros.qos`).
        msg_type : type
            Its message class.
        callback : callable
            Called with each message (see :meth:`create_subscription`).
        catch_up : bool
            Ask for the publisher's history (:func:`mlv_ros.qos.subscription_qos`).

        Returns
        -------
        Subscription
            The subscription.

        """
        return self.create_subscription(
            msg_type, qos.relative(topic), callback, qos.subscription_qos(topic, catch_up=catch_up)
        )

    def topic_name(self, topic: str) -> str:
        """
        Return graph topic ``topic`` as this node resolves it.

        ``topic`` is a root name, e.g. :data:`qos.FRAMES`; it resolves to ``/study2/mlv/frames`` in
        namespace ``/study2`` (remappings applied).
        """
        if topic not in self._topics:
            self._topics[topic] = self.resolve_topic_name(qos.relative(topic))
        return self._topics[topic]

    def diagnostic_status(
        self, level: int, message: str, values: dict | None = None
    ) -> DiagnosticStatus:
        """Return a status of this node's task, named and identified as diagnostic_updater does."""
        status = DiagnosticStatus(
            level=level, name=self.diagnostic_name, message=message, hardware_id=HARDWARE_ID
        )
        status.values = [KeyValue(key=str(k), value=str(v)) for k, v in (values or {}).items()]
        return status

    @property
    def done(self) -> bool:
        return self.finished.done()

    @property
    def status(self) -> DiagnosticStatus:
        """Return the node's current status, the last one reported."""
        return self._status

    def stop(self) -> None:
        """Declare the node's job over; ``run_node`` returns once the executor sees it."""
        if not self.finished.done():
            self.finished.set_result(True)

    def fail(self, message: str, **values) -> None:
        """
        Give up: report ``message`` as an ERROR, keep it as :attr:`failure` and stop.

        For what the node cannot go on from (not for a bad message it can skip): ``run_node``
        then exits 1, and ``mlv-ros run`` ends the run at once with this reason.
        """
        self.report(ERROR, message, **values)
        self.failure = status_text(self._status)
        self.stop()

    def param(
        self,
        name: str,
        default,
        description: str,
        *,
        min_value=None,
        max_value=None,
        choices: tuple | None = None,
        read_only: bool = True,
        check: Callable | None = None,
    ):
        """
        Declare a parameter with a descriptor (and range) and return its value.

        Integer/float ranges are enforced by rclpy when set at start-up or at run time.
        ``check(value)`` returns why a value inside the range is still refused (None: accepted),
        e.g. the core's own rule; it runs as a parameter callback, so a refused start-up value
        makes the node refuse to start (rclpy's InvalidParameterValueException, with that reason)
        and a refused run-time set is answered unsuccessful.
        """
        if check is not None:
            if not hasattr(self, '_parameter_checks'):
                self._parameter_checks: dict[str, Callable] = {}
                self.add_on_set_parameters_callback(self._checked_parameters)
            self._parameter_checks[name] = check
        desc = ParameterDescriptor(description=description, read_only=read_only)
        if choices:
            desc.additional_constraints = 'one of: ' + ', '.join(map(str, choices))
        if min_value is not None or max_value is not None:
            if isinstance(default, bool):
                raise TypeError('bool parameters take no range')
            if isinstance(default, int):
                desc.integer_range = [
                    IntegerRange(from_value=int(min_value), to_value=int(max_value), step=0)
                ]
            else:
                desc.floating_point_range = [
                    FloatingPointRange(
                        from_value=float(min_value), to_value=float(max_value), step=0.0
                    )
                ]
        value = self.declare_parameter(name, default, desc).value
        if choices and value not in choices:
            raise ValueError(f'parameter {name}={value!r} must be one of {choices}')
        return value

    def declare_settings(self, settings) -> None:
        """
        Declare each setting as a parameter; keep its value as the setting's attribute.

        A grouped setting's keyword is the flat name it had before it was grouped
        (:mod:`mlv_ros.settings`): a value given under that name (a parameters file, ``-p``, a
        launch file) would be ignored without a word, so it is refused, naming the new one.

        Parameters
        ----------
        settings : iterable of mlv_ros.settings.Setting
            Declared in this order, each with its range and check (:meth:`param`).

        Raises
        ------
        ValueError
            A value is given under a setting's former flat name.

        """
        settings = tuple(settings)
        # rclpy keeps every value given for the node (declared or not) in _parameter_overrides.
        given = set(self._parameter_overrides)
        for s in settings:
            if s.attribute != s.name and s.attribute in given:
                raise ValueError(
                    f"parameter '{s.attribute}' is now '{s.name}': rename it in the parameters "
                    f'file or -p argument ({s.name.split(".")[0]}: {{'
                    f'{s.name.split(".", 1)[1]}: ...}} in YAML)'
                )
        for s in settings:
            value = self.param(
                s.name,
                s.default,
                s.description,
                min_value=s.min_value,
                max_value=s.max_value,
                check=s.check,
            )
            setattr(self, s.attribute, value)

    def create_subscription(self, msg_type, topic: str, callback, qos_profile, **kwargs):
        """
        ``Node.create_subscription`` that also accounts for loss on ``topic``.

        DDS does not tell a subscriber that its own queue overflowed or that a KEEP_LAST writer
        dropped samples it had not delivered; the writer's sequence numbers do: a gap between two
        consecutive messages is that many messages lost, reported on /diagnostics at once and
        counted in every heartbeat (``received``/``lost``/``missed`` per topic). rclpy does not
        expose the writer's GUID, so sequences are only checked while the topic has a single
        publisher (every graph stream has one); a sequence number going back means a new
        (restarted) publisher.
        ``callback`` may take ``(msg)`` or ``(msg, message_info)``, as with rclpy. The counts
        are kept (:attr:`streams`) and reported under the topic's resolved name.
        """
        topic, name = self.resolve_topic_name(topic), topic
        count = self.streams.setdefault(topic, StreamCount())
        try:
            inspect.signature(callback).bind(object())
            wants_info = False
        except TypeError:
            wants_info = True

        def counted(msg, info):
            self._account(topic, count, info.get('publication_sequence_number'))
            return callback(msg, info) if wants_info else callback(msg)

        # A publisher whose QoS cannot serve this subscription (e.g. VOLATILE where history is
        # asked for) never connects: nothing would arrive, so say why.
        kwargs.setdefault(
            'event_callbacks',
            SubscriptionEventCallbacks(
                incompatible_qos=lambda event: self.report(
                    ERROR,
                    "a publisher's QoS is incompatible with this subscription: its messages "
                    'cannot arrive',
                    topic=topic,
                    policy=QoSPolicyKind(event.last_policy_kind).name,
                    publishers=event.total_count,
                )
            ),
        )
        return super().create_subscription(msg_type, name, counted, qos_profile, **kwargs)

    def foreign(self, study_id: str, topic: str, run_id: str = '', **where) -> str:
        """
        Return the other study's or run's name if a message is foreign to this node, else ``""``.

        A message of ``study_id`` / ``run_id`` taken from graph topic ``topic`` is foreign when it
        belongs to another study or run than this node's (:attr:`study`; an empty id, or none
        adopted yet, is never foreign); the name is :meth:`StudyShape.other`.

        A foreign message is reported at once as an ERROR on /diagnostics naming both, the topic
        and ``where`` (stamp, slice, phase...), and counted in every heartbeat; the console gets
        the first one of each other study or run (later ones are DEBUG lines). The caller ignores
        the message.
        """
        other = self.study.other(study_id, run_id)
        if other is None:
            return ''
        first = other not in self.other_studies
        self.other_studies[other] += 1
        self._report(
            ERROR,
            'message of another study ignored (another graph on this ROS_DOMAIN_ID?)',
            {
                'topic': self.topic_name(topic),
                'study': self.study.label,
                'other_study': other,
                **where,
            },
            log=first,
        )
        return other

    def foreign_slice_message(self, msg, topic: str) -> str:
        """
        Return :meth:`foreign` for a frame or tag point set, naming its view, slice, phase, stamp.

        Parameters
        ----------
        msg : TaggedFrame or TagPoints
            The message.
        topic : str
            The graph topic it came on.

        Returns
        -------
        str
            The other study's or run's name, or ``""`` when the message is this node's.

        """
        return self.foreign(
            msg.study_id,
            topic,
            run_id=msg.run_id,
            view=msg.view,
            slice=msg.slice_index,
            phase=msg.phase_index,
            stamp=conversions.stamp_text(msg.header.stamp),
        )

    def converted(
        self,
        msg,
        convert: Callable,
        message: str,
        level: int = ERROR,
        check_study: bool = False,
        **where,
    ):
        """
        Return ``convert(msg)``, or None once the ValueError it raised is reported.

        Parameters
        ----------
        msg : message with a header
            What arrived.
        convert : callable
            ``convert(msg)`` returns what the node works on (never None) or raises ValueError
            saying why ``msg`` is unusable (:mod:`mlv_ros.conversions`).
        message : str
            What the report says happened to ``msg`` (e.g. ``'bad motion cloud dropped'``).
        level : int
            The report's level (``ERROR``; ``WARN`` for what only is not shown).
        check_study : bool
            Also adopt or verify the study and dimensions the result declares
            (:meth:`StudyShape.check`; a frame or tag point set).
        **where
            Values naming ``msg`` (phase, slice...), reported before its stamp and the reason.

        Returns
        -------
        object or None
            ``convert(msg)``; None when it raised (the caller drops ``msg``).

        """
        try:
            item = convert(msg)
            if check_study:
                self.study.check(item)
            return item
        except ValueError as exc:
            stamp = conversions.stamp_text(msg.header.stamp)
            self.report(level, message, **where, stamp=stamp, reason=str(exc))
            return None

    def hold(self, pairer: StampPairer, side: str, key, item, serve: Callable, dropped: str):
        """
        Hold ``item`` in ``pairer`` until its pair is in, and report what its bound drops.

        Parameters
        ----------
        pairer : StampPairer
            Where it waits.
        side : str
            Its side of the pairer.
        key : tuple of int
            Its stamp (:func:`stamp_key`).
        item : object
            What waits.
        serve : callable
            Called with no argument once ``item`` is in: takes the complete pairs out.
        dropped : str
            What the WARN of each item that had waited longest says, when more than the pairer's
            ``max_unpaired`` wait (so memory stays bounded, and the node says so).

        """
        pairer.add(side, key, item)
        serve()
        for sec, nanosec in pairer.trim(side):
            self.report(WARN, dropped, stamp=f'{sec}.{nanosec:09d}', held=len(pairer.held[side]))

    def other_study_state(self, msg, topic: str, **where) -> bool:
        """
        Return whether model state ``msg`` is of another study (reported); its clouds go too.

        Its stamp is kept: a cloud of that stamp held in :attr:`held_clouds` is dropped now and
        reported, one that comes later by :meth:`other_study_cloud`.

        Parameters
        ----------
        msg : mlv_msgs.msg.ModelState
            The state.
        topic : str
            The graph topic it came on.
        **where
            Values naming it (e.g. its phase), reported before its stamp.

        Returns
        -------
        bool
            True: ``msg`` is another study's, the caller ignores it.

        """
        stamp = conversions.stamp_text(msg.header.stamp)
        other = self.foreign(msg.study_id, topic, run_id=msg.run_id, **where, stamp=stamp)
        if not other:
            return False
        key = stamp_key(msg.header.stamp)
        self._other_study_stamps.add(key, other)
        for cloud_topic, held in self.held_clouds:
            if 'cloud' in held.discard(key):
                self.cloud_of_other_study(cloud_topic, stamp, other)
        return True

    def other_study_cloud(self, topic: str, msg) -> bool:
        """
        Return whether point cloud ``msg`` goes with a model state of another study (reported).

        Parameters
        ----------
        topic : str
            The graph topic it came on.
        msg : sensor_msgs.msg.PointCloud2
            The cloud; its stamp is its state's (:meth:`other_study_state`).

        Returns
        -------
        bool
            True: the caller drops ``msg``.

        """
        key = stamp_key(msg.header.stamp)
        if key not in self._other_study_stamps:
            return False
        stamp = conversions.stamp_text(msg.header.stamp)
        self.cloud_of_other_study(topic, stamp, self._other_study_stamps.get(key))
        return True

    def subscribe_registration(self, build: Callable) -> None:
        """
        Take the registered cloud and state into :attr:`registered`, paired by stamp.

        Each is checked on arrival (its study, its fields); a bad one is reported and dropped.
        The registration stamps cloud and state alike, so a cloud whose state is of another
        study is dropped with it.

        Parameters
        ----------
        build : callable
            ``build(model)``: called with the :class:`~mlv_ros.core.types.RegisteredModel` of
            each registration complete (cloud and state in), the latest first taken.

        """
        self.registered = StampPairer(REGISTRATIONS_HELD)
        self.held_clouds.append((qos.REGISTERED_CLOUD, self.registered))
        self._build_on_registration = build
        self.subscribe(qos.REGISTERED_CLOUD, PointCloud2, self._on_registered_cloud)
        self.subscribe(qos.REGISTERED_STATE, ModelStateMsg, self._on_registered_state)

    def _on_registered_cloud(self, msg) -> None:
        if self.other_study_cloud(qos.REGISTERED_CLOUD, msg):
            return
        cloud = self.converted(msg, conversions.msg_to_registered_cloud, 'bad registered cloud')
        if cloud is not None:
            self._take_registered('cloud', msg, cloud)

    def _on_registered_state(self, msg) -> None:
        if self.other_study_state(msg, qos.REGISTERED_STATE):
            return
        state = self.converted(msg, conversions.msg_to_model_state, 'bad registered state')
        if state is not None:
            self.study.adopt(state.study_id, state.run_id)
            self._take_registered('state', msg, state)

    def _take_registered(self, side: str, msg, item) -> None:
        self.registered.add(side, stamp_key(msg.header.stamp), item)
        self.registered.trim(side)
        pairs = self.registered.pairs()
        if pairs:  # else the cloud or the state (same stamp) has not come yet
            _, cloud, state = pairs[-1]  # the latest registration complete
            self._build_on_registration(conversions.registered_model(cloud, state))

    def cloud_of_other_study(self, topic: str, stamp: str, other_study: str) -> None:
        """
        Report a cloud on ``topic`` whose model state (same stamp) is of ``other_study``.

        It is reported on /diagnostics and counted as :meth:`foreign` does (the console has had
        the state's line); the caller drops it.
        """
        self.other_studies[other_study] += 1
        self._report(
            ERROR,
            'point cloud of another study ignored with its model state',
            {
                'topic': self.topic_name(topic),
                'study': self.study.label,
                'other_study': other_study,
                'stamp': stamp,
            },
            log=False,
        )

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
                self.report(
                    WARN,
                    'messages published before this node subscribed were not received',
                    topic=topic,
                    missed=seq - 1,
                    first_sequence=seq,
                )
        elif seq <= last:
            count.publisher_restarts += 1
            count.missed += seq - 1
            self.report(
                WARN if seq > 1 else OK,
                'a new publisher started on the topic',
                topic=topic,
                sequence=seq,
                previous_sequence=last,
            )
        elif seq > last + 1:
            count.lost += seq - last - 1
            self.report(
                ERROR,
                'messages lost',
                topic=topic,
                lost=seq - last - 1,
                total_lost=count.lost,
                after_sequence=last,
                received=count.received,
            )

    def _with_counts(self, status: DiagnosticStatus) -> DiagnosticStatus:
        """
        Return ``status`` plus the per-topic counts, as the heartbeat publishes it.

        At ERROR, saying so, once messages of another study were ignored.
        """
        extra = []
        for topic, c in self.streams.items():
            extra += [
                KeyValue(key=f'received {topic}', value=str(c.received)),
                KeyValue(key=f'lost {topic}', value=str(c.lost)),
                KeyValue(key=f'missed {topic}', value=str(c.missed)),
            ]
        level, message = status.level, status.message
        if self.other_studies:
            ignored = sum(self.other_studies.values())
            level = max(level, ERROR)
            message = f'{message}; {ignored} message(s) of another study ignored'
            extra += [
                KeyValue(key='study', value=self.study.label),
                KeyValue(
                    key='other studies ignored',
                    value=', '.join(f'{sid}: {n}' for sid, n in self.other_studies.most_common(5)),
                ),
            ]
        return DiagnosticStatus(
            level=level,
            name=status.name,
            message=message,
            hardware_id=status.hardware_id,
            values=list(status.values) + extra,
        )

    def report(self, level: int, message: str, **values) -> None:
        """
        Publish one DiagnosticStatus now, make it the node's current status, and log it.

        The status is :meth:`diagnostic_status`'s.
        """
        self._report(level, message, values)

    def _report(self, level: int, message: str, values: dict, log: bool = True) -> None:
        """:meth:`report`; with ``log`` false the console line is DEBUG whatever the level."""
        status = self.diagnostic_status(level, message, values)
        self._status = status
        if level == ERROR:
            self.last_error = status
        self._publish(status)
        text = f'{message} ' + ' '.join(f'{k}={v}' for k, v in values.items())
        # rclpy ties a severity to each call site, so each level needs its own line.
        if not log:
            self.get_logger().debug(text.strip())
        elif level == OK:
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


def status_node(status: DiagnosticStatus) -> str:
    """
    Return the name of the node that published ``status``.

    ``tag_detector`` for ``tag_detector: tag tracking`` or ``/study2/tag_detector: tag tracking``.
    """
    return status.name.partition(': ')[0].rpartition('/')[2]


def status_place(status: DiagnosticStatus) -> tuple[str | None, str]:
    """
    Return (namespace, node) of the node that published ``status``.

    ``('/study2', 'tag_detector')`` for ``/study2/tag_detector: tag tracking`` (named by its fully
    qualified name), ``(None, 'tag_detector')`` for ``tag_detector: tag tracking`` (by its name
    alone: namespace unknown).
    """
    node = status.name.partition(': ')[0]
    if not node.startswith('/'):
        return None, node
    ns, _, name = node.rpartition('/')
    return qos.full_namespace(ns), name


def status_text(status: DiagnosticStatus) -> str:
    """One line for people: ``message (key: value, ...)``."""
    values = ', '.join(f'{kv.key}: {kv.value}' for kv in status.values)
    return f'{status.message} ({values})' if values else status.message


def run_node(factory: Callable[..., Node], args=None) -> int:
    """
    Create the node, spin it until told to stop, then drain and shut down cleanly.

    It spins until SIGINT/SIGTERM or the node calls :meth:`GraphNode.stop`, then drains what has
    already arrived. Returns 0, 2 for a node that could not start (bad parameters or paths), 1 for
    one that gave up (:meth:`GraphNode.fail`).

    rclpy's own signal handlers are replaced by ours: a signal only sets a flag, so the context
    stays valid while the node takes every message still queued (a recorder must not lose what
    was sent before the signal) and runs its ``finish()`` (e.g. closing a file). Its BLAS,
    OpenMP and OpenCV pools hold one thread (:mod:`mlv_ros.threads`: the same motion whatever
    process the node runs in).
    """
    with compute_threads():
        return _run_node(factory, args)


def _run_node(factory, args) -> int:
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop_requested = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda signum, _frame: stop_requested.append(signum))
    node = None
    executor = SingleThreadedExecutor()
    try:
        try:
            node = factory()
        except (
            ValueError,
            ParameterException,
            OSError,
        ) as exc:  # bad parameters or paths: say so, exit 2
            print(f'error: {exc}', file=sys.stderr)
            return 2
        executor.add_node(node)
        while not stop_requested and not getattr(node, 'done', False) and rclpy.ok():
            executor.spin_once(timeout_sec=0.1)
        # Drain: keep taking queued messages until none has arrived for 0.2 s. After a signal a
        # node may wait longer for what is still coming (upstream_alive: under `ros2 launch`
        # every node gets the signal at once and the upstream ones still publish what they had
        # queued), at most its shutdown_wait_s; a second signal ends the wait at once.
        signalled = len(stop_requested)
        waits = signalled and getattr(node, 'upstream_alive', None)
        end = time.monotonic() + (getattr(node, 'shutdown_wait_s', 0.0) if waits else 0.0)
        if waits and waits():
            node.get_logger().info(
                f'{signal.Signals(stop_requested[0]).name}: taking what the graph still sends '
                f'(at most {node.shutdown_wait_s:g} s; a second signal stops now)'
            )
        handled = getattr(node, 'messages_handled', 0)
        quiet_since = time.monotonic()
        while (
            rclpy.ok()
            and len(stop_requested) <= max(signalled, 1)
            and (
                time.monotonic() - quiet_since < 0.2
                or (waits and time.monotonic() < end and waits())
            )
        ):
            executor.spin_once(timeout_sec=0.05)
            if getattr(node, 'messages_handled', 0) != handled:
                handled, quiet_since = node.messages_handled, time.monotonic()
    finally:
        if node is not None:
            if hasattr(node, 'finish'):
                node.finish()
            executor.remove_node(node)
            node.destroy_node()
        executor.shutdown()
        rclpy.try_shutdown()
    return 1 if getattr(node, 'failure', None) else 0
