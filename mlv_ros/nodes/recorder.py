"""recorder: writes every graph topic to MCAP the way rosbag2 does (see :mod:`mlv_ros.bagio`).

Subscriptions are raw (the CDR bytes are written as received, never deserialised), RELIABLE and
as deep as the publishers' queues. SIGINT/SIGTERM: the node first takes every message already
queued, then finalises the file (summary, indexes, ``metadata.yaml``). Completed chunks are
flushed to the OS every ``flush_period_s``, so a SIGKILL loses at most the chunk being filled
(``mlv-ros recover`` rewrites a valid file from what is on disk).
"""

from __future__ import annotations

import importlib
import time
from pathlib import Path

from mlv_ros import bagio, qos
from mlv_ros.nodes.common import ERROR, OK, GraphNode, run_node


def message_class(type_name: str):
    """``pkg/msg/Type`` → the generated Python message class."""
    pkg, _, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


class Recorder(GraphNode):
    def __init__(self, **node_kwargs):
        super().__init__("recorder", **node_kwargs)
        self.output = self.param("output", "runs/latest/run.mcap", "MCAP file to write (its directory is created)")
        topics = self.param("topics", list(qos.TOPIC_TYPES), "topics to record (graph topics only)")
        self.flush_period_s = self.param("flush_period_s", 1.0, "push completed chunks to disk this often", min_value=0.05, max_value=60.0)
        chunk_kib = self.param("chunk_size_kib", 1024, "MCAP chunk size, KiB", min_value=16, max_value=65536)
        compression = self.param("compression", "zstd", "chunk compression", choices=("zstd", "lz4", "none"))
        # A recorder that matches a publisher late (across a network, discovery takes a moment)
        # would miss what was sent before; frames and tag points keep their history for it.
        catch_up = self.param("catch_up", True, "take frames and tag points with their history (TRANSIENT_LOCAL); "
                              "false for a publisher without history")
        unknown = [t for t in topics if t not in qos.TOPIC_TYPES]
        if unknown:
            raise ValueError(f"cannot record unknown topic(s) {unknown}; known: {sorted(qos.TOPIC_TYPES)}")
        self.writer = bagio.BagWriter(Path(self.output), chunk_size=chunk_kib * 1024, compression=compression)
        self.messages_handled = 0
        for topic in topics:
            type_name = qos.TOPIC_TYPES[topic]
            self.writer.add_topic(topic, type_name, [qos.qos_dict(qos.topic_qos(topic))])
            self.create_subscription(message_class(type_name), topic,
                                     lambda data, info, topic=topic: self._on_message(topic, data, info),
                                     qos.subscription_qos(topic, catch_up=catch_up), raw=True)
        self.create_timer(self.flush_period_s, self.writer.flush)
        self.report(OK, "recording", output=self.output, topics=len(topics))

    def _on_message(self, topic: str, data: bytes, info: dict) -> None:
        self.writer.write(topic, data, time.time_ns(), info.get("source_timestamp") or None)
        self.messages_handled += 1

    def finish(self) -> None:
        if self.writer.closed:
            return
        try:
            self.writer.close()
            received = sum(c.received for c in self.streams.values())
            lost = sum(c.lost for c in self.streams.values())
            self.report(OK if received == self.writer.message_count and not lost else ERROR, "recording closed",
                        output=self.output, messages=self.writer.message_count, received=received, lost=lost)
        except OSError as exc:
            self.report(ERROR, "could not finalise the recording", output=self.output, reason=str(exc))


def main(args=None):
    return run_node(Recorder, args)


if __name__ == "__main__":
    raise SystemExit(main())
