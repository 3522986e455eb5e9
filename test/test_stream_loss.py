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
Loss is never silent: missed messages counted and reported on /diagnostics.

Loss is never silent: a subscriber that cannot keep up, or joins late, says on /diagnostics
how many messages it did not get (publisher sequence-number gaps), and its heartbeat carries
received/lost/missed counts per topic, so frames in = frames out + frames reported lost.

The recorder is the subscriber here because it is the one node where a silent loss would cost a
user data. The overflow is real: 1100 frames are published before the recorder's executor runs,
into a RELIABLE KEEP_LAST(1000) subscription queue.
"""

from conftest import spin_until
from diagnostic_msgs.msg import DiagnosticArray
from mlv_msgs.msg import TaggedFrame
from mlv_ros import bagio, conversions, qos
from mlv_ros.core.sim.pattern import pattern_frames
from mlv_ros.nodes.common import ERROR, status_node
from mlv_ros.nodes.recorder import Recorder
from rclpy.node import Node
from rclpy.parameter import Parameter

BURST = qos.STREAM_DEPTH + 100


class Monitor(Node):
    def __init__(self, context):
        super().__init__('loss_monitor', context=context)
        self.statuses = []
        self.create_subscription(
            DiagnosticArray,
            qos.DIAGNOSTICS,
            lambda m: self.statuses.extend(m.status),
            qos.diagnostics_qos(),
        )

    def events(self, message):
        """Return the recorder's statuses with ``message``, once each, its counts left out."""
        seen = {}
        for s in self.statuses:
            if status_node(s) == 'recorder' and s.message == message:
                values = {kv.key: kv.value for kv in s.values if ' ' not in kv.key} | {
                    'level': s.level
                }
                seen.setdefault(tuple(sorted(values.items())), values)
        return list(seen.values())

    def last_counts(self, topic):
        for s in reversed(self.statuses):
            values = {kv.key: kv.value for kv in s.values}
            if status_node(s) == 'recorder' and f'received {topic}' in values:
                return {k: int(values[f'{k} {topic}']) for k in ('received', 'lost', 'missed')}
        return None


def test_overflow_late_join_and_restart_are_reported(ros_context, executor, tmp_path):
    out = tmp_path / 'run.mcap'
    rec = Recorder(
        context=ros_context,
        parameter_overrides=[
            Parameter('output', value=str(out)),
            Parameter('topics', value=[qos.FRAMES]),
        ],
    )
    mon = Monitor(ros_context)
    src = Node('burst_source', context=ros_context)
    frame = conversions.frame_to_msg(pattern_frames(num_phases=1, size=32)[0])
    # TRANSIENT_LOCAL like the frame source, so the late-join case below is a real one.
    pub = src.create_publisher(TaggedFrame, qos.FRAMES, qos.history_qos())
    for n in (rec, mon, src):
        executor.add_node(n)
    assert spin_until(
        executor,
        lambda: pub.get_subscription_count() >= 1 and mon.count_publishers(qos.DIAGNOSTICS) >= 1,
        20,
    )

    published = 0
    for _ in range(10):
        pub.publish(frame)
        published += 1
    assert spin_until(executor, lambda: rec.writer.topics[qos.FRAMES].count == 10, 10)
    for _ in range(BURST):  # nobody spins meanwhile: the recorder's queue overflows
        pub.publish(frame)
        published += 1
    assert spin_until(
        executor,
        lambda: (
            rec.writer.topics[qos.FRAMES].count + rec.streams[qos.FRAMES].lost == published
            and sum(int(e['lost']) for e in mon.events('messages lost'))
            == rec.streams[qos.FRAMES].lost
            > 0
        ),
        20,
    ), (mon.events('messages lost'), rec.streams[qos.FRAMES])
    recorded = rec.writer.topics[qos.FRAMES].count
    lost = rec.streams[qos.FRAMES].lost
    assert lost > 0 and recorded + lost == published, (recorded, lost, published)
    # One report per gap seen; under CPU load the queue can overflow in more than one episode.
    events = mon.events('messages lost')
    assert all(e['level'] == ERROR and e['topic'] == qos.FRAMES for e in events), events
    assert sum(int(e['lost']) for e in events) == lost and int(events[-1]['total_lost']) == lost, (
        events
    )
    # the heartbeat carries the same accounting
    counts = {'received': recorded, 'lost': lost, 'missed': 0}
    assert spin_until(executor, lambda: mon.last_counts(qos.FRAMES) == counts, 5), mon.last_counts(
        qos.FRAMES
    )

    # A second (VOLATILE) subscriber joining now misses everything published so far, and says so.
    late = Recorder(
        context=ros_context,
        parameter_overrides=[
            Parameter('output', value=str(tmp_path / 'late.mcap')),
            Parameter('topics', value=[qos.FRAMES]),
            Parameter('catch_up', value=False),
        ],
    )
    executor.add_node(late)
    assert spin_until(executor, lambda: pub.get_subscription_count() >= 2, 10)
    pub.publish(frame)
    published += 1
    assert spin_until(executor, lambda: late.streams[qos.FRAMES].received == 1, 10)
    assert late.streams[qos.FRAMES].missed == published - 1

    # A restarted publisher starts its sequence again: noted, not counted as loss.
    src.destroy_publisher(pub)
    pub = src.create_publisher(TaggedFrame, qos.FRAMES, qos.history_qos())
    assert spin_until(executor, lambda: pub.get_subscription_count() >= 2, 10)
    pub.publish(frame)
    assert spin_until(
        executor, lambda: bool(mon.events('a new publisher started on the topic')), 10
    )
    assert rec.streams[qos.FRAMES].publisher_restarts == 1 and rec.streams[qos.FRAMES].lost == lost

    rec.finish()
    late.finish()
    assert (
        bagio.bag_topics(out)[qos.FRAMES]['count'] == recorded + 2
    )  # + the late-join and restart frames


def test_a_recorder_that_joins_late_takes_the_history(ros_context, executor, tmp_path):
    """
    Check that the recorder takes tag sets it missed from the publisher's history.

    Across a network the recorder may match the tag detector only after its first sets went
    out; with ``catch_up`` (the default) it takes them from the publisher's history.
    """
    src = Node('early_source', context=ros_context)
    frame = conversions.frame_to_msg(pattern_frames(num_phases=1, size=32)[0])
    pub = src.create_publisher(TaggedFrame, qos.FRAMES, qos.topic_qos(qos.FRAMES))
    executor.add_node(src)
    for _ in range(5):
        pub.publish(frame)
    out = tmp_path / 'late.mcap'
    rec = Recorder(
        context=ros_context,
        parameter_overrides=[
            Parameter('output', value=str(out)),
            Parameter('topics', value=[qos.FRAMES]),
        ],
    )
    executor.add_node(rec)
    assert spin_until(executor, lambda: rec.streams[qos.FRAMES].received == 5, 10), rec.streams[
        qos.FRAMES
    ]
    assert rec.streams[qos.FRAMES].missed == 0
    rec.finish()
    assert bagio.bag_topics(out)[qos.FRAMES]['count'] == 5


def test_a_publisher_that_cannot_reach_a_subscription_is_reported(ros_context, executor):
    # The tag detector takes frames with their history (catch_up); a VOLATILE publisher cannot
    # serve that, never connects, and would otherwise be silently ignored.
    from mlv_ros.nodes.tag_detector import TagDetector

    mon = Monitor(ros_context)
    det = TagDetector(context=ros_context)
    src = Node('volatile_source', context=ros_context)
    for n in (mon, det, src):
        executor.add_node(n)
    src.create_publisher(TaggedFrame, qos.FRAMES, qos.stream_qos())

    def reports():
        return [
            {kv.key: kv.value for kv in s.values}
            for s in mon.statuses
            if status_node(s) == 'tag_detector' and 'incompatible' in s.message
        ]

    assert spin_until(executor, lambda: bool(reports()), 20)
    assert reports()[0]['topic'] == qos.FRAMES and reports()[0]['policy'] == 'DURABILITY'
