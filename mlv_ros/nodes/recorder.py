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
recorder: writes every graph topic to MCAP the way rosbag2 does (see :mod:`mlv_ros.bagio`).

It subscribes to the graph's topics in its own namespace and records them under the names they
resolve to there (``/mlv/frames`` at the root, ``/study2/mlv/frames`` under ``/study2``), as
``ros2 bag record`` would; ``/diagnostics`` is shared by every namespace.

Subscriptions are raw (the CDR bytes are written as received, never deserialised), RELIABLE and
as deep as the publishers' queues. SIGINT/SIGTERM: the node first takes every message already
queued and, while a node still publishes on a recorded topic, what it still sends (at most
``shutdown_wait_s``; under ``ros2 launch`` every node gets the signal at once, and the upstream
ones publish the phases in flight before they exit), then finalises the file (summary, indexes,
``metadata.yaml``). A second signal closes the file at once. Completed chunks go to
the OS as they are written, so a SIGKILL loses at most the chunk being filled (``mlv-ros
recover`` rewrites a valid file from what is on disk).

A write that fails (disk full, file size limit, I/O error) stops the recording: an ERROR on
/diagnostics says so, the file is cut back to its last whole record and closed, later messages
are counted as ``dropped``, ``metadata.yaml`` counts what the file holds, and the node stops
(:meth:`GraphNode.fail`: exit 1 on its own, the end of the run under ``mlv-ros run``).

Run isolation: the recording holds one graph's statuses: of what arrives on the shared
``/diagnostics``, statuses of the graph's nodes in this namespace (:meth:`Recorder.ours`; all of
them with ``all_diagnostics``); the others are counted (``other_graph_statuses``) and left out.
The recording holds one study. Messages that carry a ``study_id`` (frames, tag
points, model states, metrics) are read for it (their bytes are still written as received); the
recorder keeps to the study of the first one (or the one ``mlv-ros run`` gives it) and reports
and leaves out messages of another. Point clouds cannot carry a study: each is written once its
model state (same stamp) is in, and left out with a state of another study; a cloud whose state
never comes is written when the recording closes.
"""

from __future__ import annotations

import errno
from pathlib import Path
import time

from diagnostic_msgs.msg import DiagnosticArray
from mlv_ros import bagio, conversions, graph_table, qos
from mlv_ros.nodes.common import (
    ERROR,
    GraphNode,
    OK,
    RecentKeys,
    run_node,
    stamp_key,
    status_place,
    USE_FQN,
)
from rclpy.serialization import deserialize_message, serialize_message

# Topics whose messages carry study_id, and the point clouds paired with a model state by stamp.
STUDY_TOPICS = (qos.FRAMES, qos.TAG_POINTS, qos.REGISTERED_STATE, qos.MODEL_STATE, qos.METRICS)
CLOUD_STATES = {qos.REGISTERED_CLOUD: qos.REGISTERED_STATE, qos.MOTION: qos.MODEL_STATE}
MAX_HELD_CLOUDS = 64
# The nodes of an mlv_ros graph: their statuses on the shared /diagnostics are the ones a
# recording keeps.
GRAPH_NODE_NAMES = graph_table.NODE_NAMES


class Recorder(GraphNode):
    DIAGNOSTIC_TASK = 'recording'

    def __init__(self, **node_kwargs):
        super().__init__('recorder', **node_kwargs)
        topics, chunk_kib, compression, catch_up = self._declare_parameters()
        self.other_graph_statuses = (
            0  # statuses of other graphs' (or other) nodes left out of /diagnostics
        )
        self._arrays_left_out = (
            0  # /diagnostics messages left out whole (none of their statuses ours)
        )
        unknown = [t for t in topics if t not in qos.TOPIC_TYPES]
        if unknown:
            raise ValueError(
                f'cannot record unknown topic(s) {unknown}; known: {sorted(qos.TOPIC_TYPES)}'
            )
        self.writer = bagio.BagWriter(
            Path(self.output), chunk_size=chunk_kib * 1024, compression=compression
        )
        self.messages_handled = 0
        self.dropped = 0  # messages received after the recording stopped on a write error
        self.ignored = 0  # messages of another study left out
        self.classes: dict = {}
        # (state topic, stamp) → (cloud topic, bytes, log time, publish time)
        self._held: dict = {}
        self._ours = RecentKeys()  # (state topic, stamp) of states of this study written
        self._foreign_stamps = RecentKeys()  # (state topic, stamp) of states of another study
        self.recorded: dict[
            str, str
        ] = {}  # graph topic (root name) → the name recorded: as it resolves here
        for topic in topics:
            type_name = qos.TOPIC_TYPES[topic]
            self.classes[topic] = bagio.message_class(type_name)
            self.recorded[topic] = self.topic_name(topic)
            self.writer.add_topic(
                self.recorded[topic], type_name, [qos.qos_dict(qos.topic_qos(topic))]
            )
            self.create_subscription(
                bagio.message_class(type_name),
                qos.relative(topic),
                lambda data, info, topic=topic: self._on_message(topic, data, info),
                qos.subscription_qos(topic, catch_up=catch_up),
                raw=True,
            )
        self.create_timer(self.flush_period_s, self.writer.flush)
        self.report(OK, 'recording', output=self.output, topics=len(topics))

    def _declare_parameters(self):
        """
        Declare the node's parameters: where and what to record, and when to stop.

        Returns the ones used only while starting: ``topics``, ``chunk_kib``, ``compression``
        and ``catch_up``.
        """
        self.output = self.param(
            'output', 'runs/latest/run.mcap', 'MCAP file to write (its directory is created)'
        )
        topics = self.param(
            'topics',
            list(qos.TOPIC_TYPES),
            'graph topics to record, by their root names '
            "(/mlv/frames; recorded as they resolve in the recorder's namespace)",
        )
        self.flush_period_s = self.param(
            'flush_period_s',
            1.0,
            'sync completed chunks to disk (fsync) this often',
            min_value=0.05,
            max_value=60.0,
        )
        chunk_kib = self.param(
            'chunk_size_kib', 1024, 'MCAP chunk size, KiB', min_value=16, max_value=65536
        )
        compression = self.param(
            'compression', 'zstd', 'chunk compression', choices=('zstd', 'lz4', 'none')
        )
        # A recorder that matches a publisher late (across a network, discovery takes a moment)
        # would miss what was sent before; frames and tag points keep their history for it.
        catch_up = self.param(
            'catch_up',
            True,
            'take frames and tag points with their history (TRANSIENT_LOCAL); '
            'false for a publisher without history',
        )
        self.shutdown_wait_s = self.param(
            'shutdown_wait_s',
            10.0,
            "after SIGINT/SIGTERM, keep recording while the graph's nodes still publish "
            'on the recorded topics, at most this long (a second signal closes at once)',
            min_value=0.0,
            max_value=3600.0,
        )
        self.all_diagnostics = self.param(
            'all_diagnostics',
            False,
            "record every status on /diagnostics (false: only this graph's: the graph's "
            'node names in this namespace)',
        )
        return topics, chunk_kib, compression, catch_up

    def upstream_alive(self) -> bool:
        """
        Check whether a node still publishes on a recorded graph topic (``/diagnostics`` aside).

        ``/diagnostics`` is left aside because every node and this one publish it. After a signal
        the recording stays open for such a node.
        """
        return any(
            self.count_publishers(self.recorded[t]) for t in self.recorded if t != qos.DIAGNOSTICS
        )

    def progress(self) -> dict:
        """
        Return the messages of the graph's topics taken (/diagnostics left out: it never stops).

        Returns
        -------
        dict
            ``received`` as the per-topic counts say, ``published`` 0 (it writes a file),
            ``blocked`` as every node's.

        """
        received = sum(c.received for t, c in self.streams.items() if t != qos.DIAGNOSTICS)
        return {**super().progress(), 'received': received, 'published': 0}

    def _on_message(self, topic: str, data: bytes, info: dict) -> None:
        self.messages_handled += 1
        if self.writer.error is not None or self.writer.closed:
            self.dropped += 1
            return
        now, published = time.time_ns(), info.get('source_timestamp') or None
        if topic == qos.DIAGNOSTICS and not self.all_diagnostics:
            data = self._own_statuses(data)
            if data is None:
                return
        if topic in STUDY_TOPICS or topic in CLOUD_STATES:
            try:
                msg = deserialize_message(data, self.classes[topic])
            except Exception:  # rclpy's private errors; not ours to judge: record it as it came
                msg = None
            if msg is not None and not self._take(topic, msg, data, now, published):
                return
        self._write(self.recorded[topic], data, now, published)

    def ours(self, status) -> bool:
        """
        Check whether a /diagnostics status is this graph's.

        It is when it names a graph node (:data:`GRAPH_NODE_NAMES`) in this recorder's namespace. A
        status named by the node's name alone (no namespace) counts as ours at the root, or when
        this graph does not name its statuses by namespace (``diagnostic_updater.use_fqn`` false
        here): then another graph's in another namespace cannot be told apart, and is kept.
        """
        ns, node = status_place(status)
        if node not in GRAPH_NODE_NAMES:
            return False
        if ns is None:
            return self.get_namespace() == '/' or not self.get_parameter(USE_FQN).value
        return ns == qos.full_namespace(self.get_namespace())

    def _own_statuses(self, data: bytes) -> bytes | None:
        """
        Return ``data`` (a DiagnosticArray) with only this graph's statuses, or None.

        Statuses are this graph's by :meth:`ours`: ``data`` as received when all are, re-serialised
        when some are not, None when none is.
        """
        try:
            arr = deserialize_message(data, DiagnosticArray)
        except Exception:  # not ours to judge: recorded as it came
            return data
        keep = [st for st in arr.status if self.ours(st)]
        if len(keep) == len(arr.status):
            return data
        self.other_graph_statuses += len(arr.status) - len(keep)
        if not keep:
            self._arrays_left_out += 1
            return None
        arr.status = keep
        return serialize_message(arr)

    def _take(self, topic: str, msg, data: bytes, now: int, published) -> bool:
        """
        Return whether ``msg`` is written now.

        False: left out as another study's, or a cloud held until its state is in.
        """
        key, stamp = stamp_key(msg.header.stamp), conversions.stamp_text(msg.header.stamp)
        if topic in CLOUD_STATES:
            pair = (CLOUD_STATES[topic], key)
            if pair in self._foreign_stamps:
                self.ignored += 1
                self.cloud_of_other_study(topic, stamp, self._foreign_stamps.get(pair))
                return False
            if pair in self._ours:
                return True
            self._held[pair] = (self.recorded[topic], data, now, published)
            while len(self._held) > MAX_HELD_CLOUDS:  # states that never come: write the oldest
                self._write(*self._held.pop(next(iter(self._held))))
            return False
        other = self.foreign(msg.study_id, topic, run_id=msg.run_id, stamp=stamp)
        if other:
            self.ignored += 1
            if topic in CLOUD_STATES.values():
                self._foreign_stamps.add((topic, key), other)
                held = self._held.pop((topic, key), None)
                if held is not None:
                    self.ignored += 1
                    self.cloud_of_other_study(held[0], stamp, other)  # (its recorded name)
            return False
        self.study.adopt(msg.study_id, msg.run_id)
        if topic in CLOUD_STATES.values():
            self._write(self.recorded[topic], data, now, published)
            self._ours.add((topic, key))
            held = self._held.pop((topic, key), None)
            if held is not None:
                self._write(*held)
            return False  # written here, before its cloud
        return True

    def _write(self, topic: str, data: bytes, log_time_ns: int, published) -> None:
        """Write one message of ``topic`` (its recorded name) to the file."""
        if self.writer.error is not None or self.writer.closed:
            self.dropped += 1
            return
        try:
            self.writer.write(topic, data, log_time_ns, published)
        except OSError as exc:
            self.dropped += 1
            self._write_failed(exc)

    def _write_failed(self, exc: OSError) -> None:
        """Close what the file has and stop: it cannot take more."""
        code = errno.errorcode.get(exc.errno, str(exc.errno))
        try:
            self.writer.close()  # metadata.yaml for the messages in the file
            kept = 'metadata.yaml written'
        except OSError as again:
            kept = f'metadata.yaml not written: {again.strerror or again}'
        fix = {
            errno.ENOSPC: 'free space on that disk',
            errno.EDQUOT: 'free space within your disk quota',
            errno.EFBIG: 'raise the file size limit (ulimit -f)',
        }.get(exc.errno, 'check that disk')
        self.fail(
            f'recording stopped: {exc.strerror or exc} ({code}); the file keeps the '
            f'{self.writer.message_count} messages written before, {kept}',
            output=self.output,
            fix=f'{fix}; `mlv-ros recover` adds the missing index to this file',
        )

    def finish(self) -> None:
        """
        Close the recording and report the counts.

        Every message already taken is in it, clouds still waiting for their state too.
        """
        if self.writer.closed:
            return
        while self._held:
            self._write(*self._held.pop(next(iter(self._held))))
        try:
            self.writer.close()
            if (
                self.writer.error is not None
            ):  # failed while finishing: the file has what it could take
                self.fail(
                    f'recording stopped: {self.writer.error.strerror or self.writer.error}',
                    output=self.output,
                    messages_in_file=self.writer.message_count,
                )
                return
            received = sum(c.received for c in self.streams.values())
            lost = sum(c.lost for c in self.streams.values())
            other = {'other_study': self.ignored} if self.ignored else {}
            if self.other_graph_statuses:
                other['other_graph_statuses'] = self.other_graph_statuses
            left_out = self.ignored + self._arrays_left_out
            self.report(
                OK if received == self.writer.message_count + left_out and not lost else ERROR,
                'recording closed',
                output=self.output,
                messages=self.writer.message_count,
                received=received,
                lost=lost,
                **other,
            )
        except OSError as exc:
            self.report(
                ERROR, 'could not finalise the recording', output=self.output, reason=str(exc)
            )


def main(args=None):
    return run_node(Recorder, args)


if __name__ == '__main__':
    raise SystemExit(main())
