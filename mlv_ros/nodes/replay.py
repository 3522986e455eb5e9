"""replay: publishes a recorded MCAP's topics (as ``ros2 bag play`` does), with the original
timing scaled by ``rate``, or as fast as the subscribers acknowledge (``rate: 0``).

Messages are republished as the recorded CDR bytes (never deserialised), each topic with the QoS
it was recorded with (``offered_qos_profiles``), so latched topics stay latched.
"""

from __future__ import annotations

import time

import yaml
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from mlv_ros import bagio
from mlv_ros.nodes.common import ERROR, OK, WARN, GraphNode, run_node
from mlv_ros.nodes.recorder import message_class


def recorded_qos(text: str) -> QoSProfile:
    """The first offered QoS profile of a recorded topic (RELIABLE KEEP_LAST(1000) if absent)."""
    try:
        p = (yaml.safe_load(text) or [{}])[0]
    except (yaml.YAMLError, IndexError, TypeError):
        p = {}
    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL if p.get("history") == "keep_all" else HistoryPolicy.KEEP_LAST,
        depth=max(int(p.get("depth", 1000) or 1000), 1),
        reliability=ReliabilityPolicy.BEST_EFFORT if p.get("reliability") == "best_effort" else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if p.get("durability") == "transient_local" else DurabilityPolicy.VOLATILE)


class Replay(GraphNode):
    def __init__(self, **node_kwargs):
        super().__init__("replay", **node_kwargs)
        self.path = self.param("path", "", "MCAP file (or rosbag2 directory) to play")
        self.rate = self.param("rate", 0.0, "time scale of the original timing; 0 = as fast as possible", min_value=0.0, max_value=1000.0)
        only = self.param("topics", [""], "topics to play (empty = all)")
        self.wait_for_subscribers = self.param("wait_for_subscribers", 1, "matched subscribers (on any topic) to wait for", min_value=0, max_value=100)
        self.wait_timeout_s = self.param("wait_timeout_s", 30.0, "give up waiting after this long", min_value=0.0, max_value=3600.0)
        self.exit_when_done = self.param("exit_when_done", True, "stop once everything is played and acknowledged")
        if not self.path:
            raise ValueError("parameter path is required: the MCAP file to play")
        wanted = [t for t in only if t]
        recorded = bagio.bag_topics(self.path)
        missing = [t for t in wanted if t not in recorded]
        if missing:
            self.report(WARN, "topics not in the recording", topics=",".join(missing))
        self.pubs = {}
        for topic, info in recorded.items():
            if wanted and topic not in wanted:
                continue
            try:
                cls = message_class(info["type"])
            except (ImportError, AttributeError, ValueError):
                self.report(WARN, "skipping topic of unknown type", topic=topic, type=info["type"])
                continue
            self.pubs[topic] = self.create_publisher(cls, topic, recorded_qos(info["qos"]))
        self.messages = iter(bagio.read_bag(self.path, topics=list(self.pubs)))
        self.published = 0
        self._t0 = time.monotonic()
        self._start = None
        self._next = next(self.messages, None)
        self.timer = self.create_timer(0.001, self._tick)
        self.report(OK, "replaying", path=self.path, topics=len(self.pubs), rate=self.rate)

    def _tick(self):
        if self._start is None:
            matched = sum(p.get_subscription_count() for p in self.pubs.values())
            if matched < self.wait_for_subscribers:
                if time.monotonic() - self._t0 > self.wait_timeout_s:
                    self.report(ERROR, "no subscriber appeared; not replaying", waited_s=self.wait_timeout_s)
                    self.timer.cancel()
                    self.stop()
                return
            self._start = (time.monotonic(), self._next.log_time_ns if self._next else 0)
        while self._next is not None:
            if self.rate > 0:
                due = self._start[0] + (self._next.log_time_ns - self._start[1]) * 1e-9 / self.rate
                if time.monotonic() < due:
                    return
            self.pubs[self._next.topic].publish(self._next.data)  # raw CDR bytes
            self.published += 1
            self._next = next(self.messages, None)
            if self.rate <= 0:
                return  # one per tick: lets the executor serve other callbacks in one process
        self.timer.cancel()
        for topic, pub in self.pubs.items():
            if not pub.wait_for_all_acked(Duration(seconds=self.wait_timeout_s)):
                self.report(WARN, "not every message was acknowledged", topic=topic)
        self.report(OK, "replay finished", messages=self.published)
        if self.exit_when_done:
            self.stop()


def main(args=None):
    return run_node(Replay, args)


if __name__ == "__main__":
    raise SystemExit(main())
