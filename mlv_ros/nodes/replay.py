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
replay: publishes a recorded MCAP's topics (as ``ros2 bag play`` does).

With the original timing scaled by ``rate``, or as fast as the subscribers acknowledge (``rate:
0``).

The graph's topics are played in the node's namespace whatever namespace they were recorded in
(``/study2/mlv/frames`` recorded, ``/mlv/frames`` played at the root, ``/study3/mlv/frames``
under ``-r __ns:=/study3``), as every node of the graph names its topics relative; other topics
go out under their recorded names. Messages are republished as the recorded CDR bytes (never
deserialised), each topic with the QoS it was recorded with (``offered_qos_profiles``), so
latched topics stay latched. Our messages recorded before fields were appended to their
definition (the recording's schema says so) get those fields' defaults appended
(:func:`mlv_ros.bagio.current_cdr`: e.g. an empty ``study_id``), so that today's subscribers can
read them (a recording without schemas: tried by deserialising).

The recorded ``/diagnostics`` stay in the recording unless ``republish_diagnostics`` is true:
replayed, old statuses of nodes that are not running would mix with the live graph's on the
same topic. With ``publish_clock`` the node publishes ``/clock`` (rosgraph_msgs/Clock) carrying
each message's recorded receive time just before the message, so nodes started with
``use_sim_time:=true`` see the time of the recording.
"""

from __future__ import annotations

import time

from mlv_ros import bagio, qos
from mlv_ros.nodes.common import ERROR, GraphNode, OK, run_node, SubscriberWait, WARN
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

CLOCK_TOPIC = '/clock'


def recorded_qos(offered) -> QoSProfile:
    """
    Return the first offered QoS profile of a recorded topic (RELIABLE KEEP_LAST(1000) if absent).

    ``offered`` is the recorded ``offered_qos_profiles`` in any of rosbag2's spellings (YAML text
    or a list of maps, see :func:`mlv_ros.bagio.parse_offered_qos`).
    """
    p = (bagio.parse_offered_qos(offered) or [{}])[0]
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL
        if p.get('history') == 'keep_all'
        else HistoryPolicy.KEEP_LAST,
        depth=max(int(p.get('depth', 1000) or 1000), 1),
        reliability=ReliabilityPolicy.BEST_EFFORT
        if p.get('reliability') == 'best_effort'
        else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL
        if p.get('durability') == 'transient_local'
        else DurabilityPolicy.VOLATILE,
    )


class Replay(GraphNode):
    DIAGNOSTIC_TASK = 'replay'

    def __init__(self, **node_kwargs):
        super().__init__('replay', **node_kwargs)
        only = self._declare_parameters()
        if not self.path:
            raise ValueError('parameter path is required: the MCAP file to play')
        wanted = [t for t in only if t]
        recorded = bagio.bag_topics(self.path)
        # A graph topic may be asked for by its recorded name or its root name (/lv/motion).
        roots = {topic: (qos.split_graph_topic(topic) or (None, None))[1] for topic in recorded}
        missing = [t for t in wanted if t not in recorded and t not in roots.values()]
        if missing:
            self.report(WARN, 'topics not in the recording', topics=','.join(missing))
        self.pubs = {}  # recorded topic → its publisher
        self.classes = {}
        namespaces = {}  # namespace the graph's topics were recorded in → one of them
        for topic, info in recorded.items():
            if wanted and topic not in wanted and roots[topic] not in wanted:
                continue
            split = qos.split_graph_topic(topic)
            if split is not None:
                namespaces.setdefault(split[0], topic)
            if topic == qos.DIAGNOSTICS and not self.republish_diagnostics:
                if topic in wanted:
                    self.report(
                        WARN,
                        'recorded diagnostics are not republished unless asked',
                        topic=topic,
                        set='republish_diagnostics:=true',
                    )
                continue
            try:
                cls = bagio.message_class(info['type'])
            except (ImportError, AttributeError, ValueError):
                self.report(WARN, 'skipping topic of unknown type', topic=topic, type=info['type'])
                continue
            # The graph's topics are played in this node's namespace, whatever namespace they were
            # recorded in (as every node of the graph names them: relative); others as recorded.
            name = qos.relative(split[1]) if split is not None else topic
            self.pubs[topic] = self.create_publisher(cls, name, recorded_qos(info['qos']))
            self.classes[topic] = cls
        if len(namespaces) > 1:
            raise ValueError(
                f"{self.path} holds the graph's topics of {len(namespaces)} namespaces "
                f'({", ".join(sorted(namespaces))}): play one with -p topics:="[...]" '
                f'(e.g. {", ".join(sorted(namespaces.values()))})'
            )
        # RELIABLE with a deep queue: a subscriber that wants every recorded time (a recorder, a
        # test) gets it; rclpy's time source subscribes BEST_EFFORT, depth 1, and matches too.
        self.clock_pub = (
            self.create_publisher(Clock, CLOCK_TOPIC, qos.stream_qos())
            if self.publish_clock
            else None
        )
        self.clocks_published = 0
        self.messages = iter(bagio.read_bag(self.path, topics=list(self.pubs)))
        self.published = 0
        self.subscriber_wait = SubscriberWait(
            self.wait_for_subscribers, self.wait_timeout_s, since=time.monotonic()
        )
        self._start = None
        self._next = next(self.messages, None)
        self.timer = self.create_timer(0.001, self._tick)
        self.report(OK, 'replaying', path=self.path, topics=len(self.pubs), rate=self.rate)

    def _declare_parameters(self):
        """
        Declare the node's parameters: the recording, what of it to replay, and the pace.

        Returns the topics to play, as given (``topics``).
        """
        self.path = self.param('path', '', 'MCAP file (or rosbag2 directory) to play')
        self.rate = self.param(
            'rate',
            0.0,
            'time scale of the original timing; 0 = as fast as possible',
            min_value=0.0,
            max_value=1000.0,
        )
        only = self.param(
            'topics', [''], 'topics to play, by recorded or (graph topics) root name; empty = all'
        )
        self.wait_for_subscribers = self.param(
            'wait_for_subscribers',
            1,
            'matched subscribers (on any topic) to wait for',
            min_value=0,
            max_value=100,
        )
        self.wait_timeout_s = self.param(
            'wait_timeout_s',
            30.0,
            'give up waiting after this long',
            min_value=0.0,
            max_value=3600.0,
        )
        self.exit_when_done = self.param(
            'exit_when_done', True, 'stop once everything is played and acknowledged'
        )
        self.republish_diagnostics = self.param(
            'republish_diagnostics',
            False,
            f'also play the recorded {qos.DIAGNOSTICS} onto the live topic (off: old statuses '
            'of nodes that '
            'are not running would mix with the live ones)',
        )
        self.publish_clock = self.param(
            'publish_clock',
            False,
            f"publish {CLOCK_TOPIC} (rosgraph_msgs/Clock) with each message's recorded time, "
            'before the '
            'message, for nodes running with use_sim_time',
        )
        return only

    def _tick(self):
        if self._start is None:
            matched = sum(p.get_subscription_count() for p in self.pubs.values())
            wait = self.subscriber_wait.poll(matched)
            if wait == SubscriberWait.LATE:
                self.report(
                    ERROR, 'no subscriber appeared; not replaying', waited_s=self.wait_timeout_s
                )
                self.timer.cancel()
                self.stop()
            if wait != SubscriberWait.GO:
                return
            self._start = (time.monotonic(), self._next.log_time_ns if self._next else 0)
        while self._next is not None:
            if self.rate > 0:
                due = self._start[0] + (self._next.log_time_ns - self._start[1]) * 1e-9 / self.rate
                if time.monotonic() < due:
                    return
            if self.clock_pub is not None:
                t = self._next.log_time_ns
                msg = Clock()
                msg.clock.sec, msg.clock.nanosec = t // 1_000_000_000, t % 1_000_000_000
                self.clock_pub.publish(msg)
                self.clocks_published += 1
            self.pubs[self._next.topic].publish(self._current(self._next))  # raw CDR bytes
            self.published += 1
            self._next = next(self.messages, None)
            if self.rate <= 0:
                return  # one per tick: lets the executor serve other callbacks in one process
        self.timer.cancel()
        pubs = dict(self.pubs)
        if self.clock_pub is not None:
            pubs[CLOCK_TOPIC] = self.clock_pub
        for topic, pub in pubs.items():
            if not pub.wait_for_all_acked(Duration(seconds=self.wait_timeout_s)):
                self.report(WARN, 'not every message was acknowledged', topic=topic)
        self.report(OK, 'replay finished', messages=self.published, clocks=self.clocks_published)
        if self.exit_when_done:
            self.stop()

    def _current(self, m: bagio.BagMessage) -> bytes:
        """Return the recorded bytes, with the defaults of fields appended since (if any) added."""
        if m.missing == ():
            return m.data
        try:
            return bagio.current_cdr(m.data, self.classes[m.topic], m.missing)
        except ValueError:
            return m.data  # as recorded: the subscriber reports what it cannot read


def main(args=None):
    return run_node(Replay, args)


if __name__ == '__main__':
    raise SystemExit(main())
