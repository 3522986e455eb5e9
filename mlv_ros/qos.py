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
Topic names and QoS profiles of the graph, in one place (as image_pipeline does).

Every stream that carries acquisition data or results is RELIABLE with a deep KEEP_LAST queue,
so a whole study (25 phases × 11 slices = 275 frames) fits in flight without a drop. What late
joiners need is also TRANSIENT_LOCAL: the registered model (latched, depth 1) and the frames and
tag points (the whole study's history), so a node restarted mid-run catches up.

Topic names. The constants below are the graph's topics as they resolve in the root namespace
(and as a run there records them). Nodes create their publishers and subscriptions with the
relative form (:func:`relative`: ``mlv/frames``), so a node started in a namespace
(``-r __ns:=/study2``, ``mlv-ros run --namespace study2``) talks on ``/study2/mlv/frames``;
``/diagnostics`` stays absolute, as diagnostic_updater's. Readers of recordings find the graph
topics in whatever namespace they were recorded (:func:`split_graph_topic`).
"""

import re

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

# Topics, by their names in the root namespace (nodes use them relative: see relative()).
FRAMES = '/mlv/frames'  # mlv_msgs/TaggedFrame
TAG_POINTS = '/mlv/tag_points'  # mlv_msgs/TagPoints
REGISTERED_CLOUD = '/mlv/registered_cloud'  # sensor_msgs/PointCloud2, ED particles (latched)
REGISTERED_STATE = '/mlv/registered_state'  # mlv_msgs/ModelState at ED (latched)
MOTION = '/lv/motion'  # sensor_msgs/PointCloud2, one per phase
MODEL_STATE = '/lv/model_state'  # mlv_msgs/ModelState, one per phase
METRICS = '/lv/metrics'  # mlv_msgs/MotionMetrics, one per phase
DIAGNOSTICS = '/diagnostics'  # diagnostic_msgs/DiagnosticArray

# What each topic carries, as rosbag2 names types (pkg/msg/Type).
TOPIC_TYPES = {
    FRAMES: 'mlv_msgs/msg/TaggedFrame',
    TAG_POINTS: 'mlv_msgs/msg/TagPoints',
    REGISTERED_CLOUD: 'sensor_msgs/msg/PointCloud2',
    REGISTERED_STATE: 'mlv_msgs/msg/ModelState',
    MOTION: 'sensor_msgs/msg/PointCloud2',
    MODEL_STATE: 'mlv_msgs/msg/ModelState',
    METRICS: 'mlv_msgs/msg/MotionMetrics',
    DIAGNOSTICS: 'diagnostic_msgs/msg/DiagnosticArray',
}
LATCHED_TOPICS = (REGISTERED_CLOUD, REGISTERED_STATE)
# Inputs a restarted node must be able to catch up on: their publishers keep the whole study
# (TRANSIENT_LOCAL, KEEP_LAST(STREAM_DEPTH)), so a node that (re)joins late receives the history.
HISTORY_TOPICS = (FRAMES, TAG_POINTS)

# The topics a node resolves in its namespace (all but /diagnostics).
GRAPH_TOPICS = tuple(t for t in TOPIC_TYPES if t != DIAGNOSTICS)
_NAMESPACE = re.compile(r'(/[A-Za-z_][A-Za-z0-9_]*)+')

STREAM_DEPTH = 1000
LATCHED_READER_DEPTH = 10  # subscriptions to the latched topics (see subscription_qos)


def relative(topic: str) -> str:
    """
    Return the name a node publishes or subscribes graph topic ``topic`` with.

    Parameters
    ----------
    topic : str
        A graph topic by its root-namespace name (e.g. :data:`FRAMES`).

    Returns
    -------
    str
        ``mlv/frames`` for ``/mlv/frames`` (resolved in the node's namespace); any other name
        (``/diagnostics``, a topic not of the graph) unchanged.

    """
    return topic.lstrip('/') if topic in GRAPH_TOPICS else topic


def split_graph_topic(name: str) -> tuple[str, str] | None:
    """
    Return the namespace and the graph topic of a resolved (recorded) topic name.

    Parameters
    ----------
    name : str
        A fully qualified topic name, e.g. ``/study2/mlv/frames``.

    Returns
    -------
    tuple of (str, str) or None
        ``("/study2", "/mlv/frames")``; ``("/", "/mlv/frames")`` for the root namespace; None
        for a name that is no graph topic (``/diagnostics`` included: it has no namespace).

    """
    for topic in GRAPH_TOPICS:
        if name == topic:
            return '/', topic
        if name.endswith(topic) and _NAMESPACE.fullmatch(name[:-len(topic)]):
            return name[:-len(topic)], topic
    return None


def namespace_error(namespace: str) -> str | None:
    """
    Why ``namespace`` is not a ROS namespace (None when it is).

    Tokens of letters, digits and underscores, not starting with a digit, separated by ``/``;
    the leading ``/`` may be left out (``study2`` is ``/study2``).
    """
    ns = '/' + namespace.strip('/') if namespace.strip('/') else '/'
    if ns == '/' or (_NAMESPACE.fullmatch(ns) and '__' not in ns):
        return None
    return (
        f'{namespace!r} is not a ROS namespace: use letters, digits and underscores, tokens '
        "separated by '/' and not starting with a digit (e.g. study2 or site_a/study2)"
    )


def full_namespace(namespace: str | None) -> str:
    """Write ``namespace`` as ROS does: ``/study2`` for ``study2`` or ``/study2/``, else ``/``."""
    ns = (namespace or '').strip('/')
    return '/' + ns if ns else '/'


def stream_qos(depth: int = STREAM_DEPTH) -> QoSProfile:
    """RELIABLE, VOLATILE, KEEP_LAST(depth): per-frame and per-phase data that must not be lost."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def latched_qos(depth: int = 1) -> QoSProfile:
    """RELIABLE, TRANSIENT_LOCAL: the last ``depth`` messages are delivered to late joiners."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def diagnostics_qos() -> QoSProfile:
    """
    RELIABLE, VOLATILE, KEEP_LAST(1000).

    diagnostic_updater publishes ``/diagnostics`` with depth 1 (one array of every task, once a
    period); our nodes publish each event the moment it happens as well, and a burst of bad input
    gives one report per message, so the queue is as deep as the data streams' for a monitor not
    to lose them. Any RELIABLE or BEST_EFFORT VOLATILE subscriber matches.
    """
    return stream_qos(STREAM_DEPTH)


def history_qos(depth: int = STREAM_DEPTH) -> QoSProfile:
    """RELIABLE, TRANSIENT_LOCAL, KEEP_LAST(depth): a stream whose history late joiners get."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def topic_qos(topic: str) -> QoSProfile:
    """
    Return the profile a graph topic is published with.

    Latched for the registration results, with history for frames and tag points, a deep RELIABLE
    stream otherwise.
    """
    if topic in LATCHED_TOPICS:
        return latched_qos()
    return history_qos() if topic in HISTORY_TOPICS else stream_qos()


def subscription_qos(topic: str, catch_up: bool = False) -> QoSProfile:
    """
    Return the profile to subscribe with.

    VOLATILE matches any RELIABLE publisher (a bag player, another tool); ``catch_up`` asks for the
    publisher's history (TRANSIENT_LOCAL, which only a TRANSIENT_LOCAL publisher can serve) — the
    solver does so for tag points, so that a restarted solver rebuilds the run. Latched topics are
    taken with a queue of ``LATCHED_READER_DEPTH``: a publisher keeps only its last model, but a
    second one on the domain (another graph) must not push ours out of the reader's queue before it
    is read.
    """
    if topic in LATCHED_TOPICS:
        return latched_qos(LATCHED_READER_DEPTH)
    return history_qos() if catch_up and topic in HISTORY_TOPICS else stream_qos()


def qos_dict(profile: QoSProfile) -> dict:
    """Return a profile in rosbag2's offered_qos_profiles vocabulary."""
    return {
        'history': 'keep_all' if profile.history == HistoryPolicy.KEEP_ALL else 'keep_last',
        'depth': profile.depth,
        'reliability': 'best_effort'
        if profile.reliability == ReliabilityPolicy.BEST_EFFORT
        else 'reliable',
        'durability': 'transient_local'
        if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
        else 'volatile',
    }
