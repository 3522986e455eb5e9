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
The node graph in one table: each node's name, entry point, and the topics it takes and puts out.

Read by ``setup.py`` (console scripts; it loads this file by path, so it imports nothing but the
standard library), ``launch/pipeline.launch.py`` and :mod:`mlv_ros.runner` (``mlv-ros run``).
Topics are named as in the root namespace (:mod:`mlv_ros.qos`); every node resolves them in its
own namespace.
"""

from typing import NamedTuple

FRAMES = '/mlv/frames'
TAG_POINTS = '/mlv/tag_points'
REGISTERED = ('/mlv/registered_cloud', '/mlv/registered_state')
MOTION = ('/lv/motion', '/lv/model_state')
METRICS = '/lv/metrics'
DIAGNOSTICS = '/diagnostics'


class NodeEntry(NamedTuple):
    """
    One node of the graph.

    Attributes
    ----------
    name : str
        Node name, console script (``ros2 run mlv_ros <name>``) and module
        ``mlv_ros.nodes.<name>`` (whose ``main()`` runs it).
    node_class : str
        Its :class:`~mlv_ros.nodes.common.GraphNode` subclass in that module.
    subscribes : tuple of str
        Topics it takes.
    publishes : tuple of str
        Topics it puts out (besides /diagnostics, which every node publishes).
    in_run : bool
        Started by every run (``mlv-ros run``, the launch file); the others are started on
        demand (the live view) or stand alone (replay).

    """

    name: str
    node_class: str
    subscribes: tuple
    publishes: tuple
    in_run: bool = True

    @property
    def entry_point(self) -> str:
        """Return the console script's target, ``mlv_ros.nodes.<name>:main``."""
        return f'mlv_ros.nodes.{self.name}:main'


# Downstream first: a run starts them in this order, so that every subscriber exists before
# frames flow.
NODES = (
    NodeEntry(
        'recorder',
        'Recorder',
        (FRAMES, TAG_POINTS, *REGISTERED, *MOTION, METRICS, DIAGNOSTICS),
        (),
    ),
    NodeEntry('motion_analyzer', 'MotionAnalyzer', (*MOTION, *REGISTERED), (METRICS,)),
    NodeEntry('meshless_solver', 'MeshlessSolver', (TAG_POINTS, *REGISTERED), MOTION),
    NodeEntry('registration', 'Registration', (FRAMES,), REGISTERED),
    NodeEntry('tag_detector', 'TagDetector', (FRAMES,), (TAG_POINTS,)),
    NodeEntry('frame_source', 'FrameSource', (), (FRAMES,)),
    NodeEntry('replay', 'Replay', (), (FRAMES, TAG_POINTS, *REGISTERED, *MOTION, METRICS), False),
    NodeEntry(
        'live_view', 'LiveView', (*MOTION, METRICS, FRAMES, TAG_POINTS), (), in_run=False
    ),
)
# The nodes every run starts, downstream first.
RUN_NODES = tuple(n.name for n in NODES if n.in_run)
NODE_NAMES = tuple(n.name for n in NODES)
