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
In-process graph harness: the processing nodes over real Fast DDS and a probe node.

The in-process graph as tests and benchmarks drive it: the four processing nodes (and
optionally the recorder) over real Fast DDS, and a probe node that publishes on any graph topic
and collects every output.

Usable outside pytest (``bench/reliability.py``: ``sys.path.insert(0, "test")``); importing it
imports ``conftest``, which claims a private ROS domain for the process.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
import time

from conftest import spin_until
from diagnostic_msgs.msg import DiagnosticArray
from mlv_msgs.msg import ModelState, MotionMetrics, TaggedFrame, TagPoints
from mlv_ros import bagio, conversions, qos
from mlv_ros.core.types import Frame
from mlv_ros.nodes.common import status_node
from mlv_ros.nodes.frame_source import count_slices, order_frames
from mlv_ros.nodes.meshless_solver import MeshlessSolver
from mlv_ros.nodes.motion_analyzer import MotionAnalyzer
from mlv_ros.nodes.recorder import Recorder
from mlv_ros.nodes.registration import Registration
from mlv_ros.nodes.tag_detector import TagDetector
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2

# What the probe collects: key → (type, topic).
OUTPUTS = {
    'diag': (DiagnosticArray, qos.DIAGNOSTICS),
    'points': (TagPoints, qos.TAG_POINTS),
    'motion': (PointCloud2, qos.MOTION),
    'state': (ModelState, qos.MODEL_STATE),
    'metrics': (MotionMetrics, qos.METRICS),
}
TOPIC_MSG = {
    qos.FRAMES: TaggedFrame,
    qos.TAG_POINTS: TagPoints,
    qos.REGISTERED_CLOUD: PointCloud2,
    qos.REGISTERED_STATE: ModelState,
    qos.MOTION: PointCloud2,
    qos.MODEL_STATE: ModelState,
}


class Probe(Node):
    """
    Publish on any graph topic with the graph's own QoS and collect every graph output.

    Publishes on any graph topic with the QoS the graph's own publisher offers there (so every
    consumer matches it, TRANSIENT_LOCAL ones included) and collects every graph output.
    """

    def __init__(self, context, name: str = 'probe'):
        super().__init__(name, context=context)
        self.pubs = {
            t: self.create_publisher(m, t, qos.topic_qos(t)) for t, m in TOPIC_MSG.items()
        }
        self.out = {k: [] for k in OUTPUTS}
        self.sent: set = set()  # (topic, stamp) of what the probe published itself
        # Deep RELIABLE queues on every output, /diagnostics included: a burst of reports (one per
        # bad message) must not push unread ones out of a KEEP_LAST(100) reader.
        for key, (typ, topic) in OUTPUTS.items():
            self.create_subscription(typ, topic, self.out[key].append, qos.stream_qos())

    def publish(self, topic: str, msg) -> None:
        self.sent.add((topic, conversions.stamp_text(msg.header.stamp)))
        self.pubs[topic].publish(msg)

    def received(self, key: str) -> list:
        """Return what the graph published on output ``key`` (not the probe's own messages)."""
        topic = OUTPUTS[key][1]
        return [
            m
            for m in self.out[key]
            if (topic, conversions.stamp_text(m.header.stamp)) not in self.sent
        ]

    def statuses(self) -> list[tuple[str, int, str, dict]]:
        """Every DiagnosticStatus received: (node name, level, message, values)."""
        return [
            (status_node(s), s.level, s.message, {kv.key: kv.value for kv in s.values})
            for d in self.out['diag']
            for s in d.status
        ]


def graph_nodes(
    context,
    *,
    max_pixels: int = 1024 * 1024,
    num_particles: int = 1500,
    timeout_s: float = 2.0,
    record_to: Path | None = None,
) -> dict[str, Node]:
    """
    Build the processing graph in one process: name → node.

    Parameters
    ----------
    context : rclpy Context
        The context every node (and the recorder) is created in.
    max_pixels : int
        ``tag_detector.max_pixels``.
    num_particles : int
        ``registration.num_particles``.
    timeout_s : float
        ``registration.ed_timeout_s`` and ``meshless_solver.incomplete_timeout_s``.
    record_to : Path, optional
        Also run a recorder writing every graph topic to this MCAP file.

    """
    nodes = {
        'tag_detector': TagDetector(
            context=context, parameter_overrides=[Parameter('max_pixels', value=max_pixels)]
        ),
        'registration': Registration(
            context=context,
            parameter_overrides=[
                Parameter('num_particles', value=num_particles),
                Parameter('ed_timeout_s', value=timeout_s),
            ],
        ),
        'meshless_solver': MeshlessSolver(
            context=context,
            parameter_overrides=[Parameter('incomplete_timeout_s', value=timeout_s)],
        ),
        'motion_analyzer': MotionAnalyzer(context=context),
    }
    if record_to is not None:
        nodes['recorder'] = Recorder(
            context=context, parameter_overrides=[Parameter('output', value=str(record_to))]
        )
    return nodes


def wait_matched(executor, probe: Probe, counts: dict[str, int], timeout: float = 30.0) -> None:
    """Spin until each topic's probe publisher has at least ``counts[topic]`` subscribers."""
    ok = spin_until(
        executor,
        lambda: all(probe.pubs[t].get_subscription_count() >= n for t, n in counts.items()),
        timeout,
    )
    if not ok:
        have = {t: probe.pubs[t].get_subscription_count() for t in counts}
        raise TimeoutError(
            f'subscribers not matched within {timeout} s: want {counts}, have {have}'
        )


@dataclass
class LoadReport:
    """
    Frames in vs out of one whole-study burst through the graph (counts are messages).

    ``published`` frames were sent; ``detector_received`` reached the tag detector;
    ``tag_sets`` it published; ``recorded_frames`` / ``recorded_tag_sets`` are in the recording;
    ``phases_solved`` / ``phases_analysed`` are motion clouds and metrics received of
    ``num_phases``. Seconds: ``publish_s`` for the burst, ``total_s`` until the last metrics.
    """

    published: int
    detector_received: int
    tag_sets: int
    recorded_frames: int
    recorded_tag_sets: int
    phases_solved: int
    phases_analysed: int
    num_phases: int
    publish_s: float
    total_s: float

    @property
    def frames_lost(self) -> int:
        """Frames that did not make it through every stage (0 when nothing was lost)."""
        return self.published - min(
            self.detector_received, self.tag_sets, self.recorded_frames, self.recorded_tag_sets
        )

    def as_dict(self) -> dict:
        return {**asdict(self), 'frames_lost': self.frames_lost}


def spin_until_stalled(executor, progress, done: tuple, timeout: float, stall_s: float) -> bool:
    """
    Spin until ``progress()`` reaches ``done``, stalls for ``stall_s`` or ``timeout`` passes.

    Spin until ``progress()`` reaches ``done`` (element-wise ≥), has not changed for
    ``stall_s`` seconds, or ``timeout`` passes; returns whether it reached ``done``.
    """
    deadline = time.monotonic() + timeout
    last, changed_at = progress(), time.monotonic()
    while time.monotonic() < deadline and time.monotonic() - changed_at < stall_s:
        now = progress()
        if all(a >= b for a, b in zip(now, done)):
            return True
        if now != last:
            last, changed_at = now, time.monotonic()
        executor.spin_once(timeout_sec=0.05)
    return all(a >= b for a, b in zip(progress(), done))


def run_load(
    frames: list[Frame],
    out_dir: Path,
    *,
    order: str = 'slice_major',
    timeout: float = 300.0,
    stall_s: float = 30.0,
    num_particles: int = 1500,
) -> LoadReport:
    """
    Publish a whole study at once into the graph plus a recorder; count frames at every stage.

    Publish a whole study at once, as fast as possible, into the graph plus a recorder, and
    count frames in vs out at every stage.

    Parameters
    ----------
    frames : list of Frame
        The study (slice counts are filled in here).
    out_dir : Path
        Where the recording goes (``out_dir/load.mcap``; must not exist yet).
    order : str
        ``slice_major`` (as acquired) or ``phase_major``.
    timeout : float
        Seconds to wait for the last phase's metrics and for the recorder to catch up.
    stall_s : float
        Give up earlier when no stage has made progress for this long.
    num_particles : int
        Model size (solver cost).

    Returns
    -------
    LoadReport
        Also when the run timed out (then the counts show where messages stopped).

    """
    frames = order_frames(count_slices(list(frames)), order)
    num_phases = frames[0].num_phases
    msgs = [conversions.frame_to_msg(f, stamp=1.0 + i) for i, f in enumerate(frames)]
    path = Path(out_dir) / 'load.mcap'
    context = rclpy.Context()
    rclpy.init(context=context)
    executor = SingleThreadedExecutor(context=context)
    nodes = graph_nodes(context, num_particles=num_particles, record_to=path)
    probe = Probe(context)
    try:
        for n in (*nodes.values(), probe):
            executor.add_node(n)
        # frames: tag detector, registration, recorder; tag points: solver, recorder
        wait_matched(executor, probe, {qos.FRAMES: 3, qos.TAG_POINTS: 2})
        t0 = time.monotonic()
        for m in msgs:
            probe.publish(qos.FRAMES, m)
        publish_s = time.monotonic() - t0
        det, rec = nodes['tag_detector'], nodes['recorder']

        def progress():
            return (
                det.messages_handled,
                det.published,
                rec.writer.topics[qos.FRAMES].count,
                rec.writer.topics[qos.TAG_POINTS].count,
                len(probe.received('motion')),
                len(probe.received('metrics')),
            )

        done = (len(msgs), len(msgs), len(msgs), len(msgs), num_phases, num_phases)
        spin_until_stalled(executor, progress, done, timeout, stall_s)
        total_s = time.monotonic() - t0
        rec.finish()
        counts = {qos.FRAMES: 0, qos.TAG_POINTS: 0}
        for m in bagio.read_bag(path, topics=list(counts)):
            counts[m.topic] += 1
        return LoadReport(
            published=len(msgs),
            detector_received=det.messages_handled,
            tag_sets=det.published,
            recorded_frames=counts[qos.FRAMES],
            recorded_tag_sets=counts[qos.TAG_POINTS],
            phases_solved=len(probe.received('motion')),
            phases_analysed=len(probe.received('metrics')),
            num_phases=num_phases,
            publish_s=round(publish_s, 3),
            total_s=round(total_s, 3),
        )
    finally:
        for n in (*nodes.values(), probe):
            executor.remove_node(n)
            n.destroy_node()
        executor.shutdown()
        context.try_shutdown()


@dataclass
class CorpusReport:
    """
    What the graph made of a message corpus fed among a valid study.

    ``failures``: one line per case whose report is missing or wrong (or legal stand-in not
    processed); ``crashes``: exceptions that escaped a node callback into the executor;
    ``nodes_down``: nodes with no heartbeat after the corpus; ``false_alarms``: errors reported
    against valid frames; ``phases_analysed`` of ``num_phases``.
    """

    cases: int
    reported: int
    failures: list
    crashes: list
    nodes_down: list
    false_alarms: list
    phases_analysed: int
    num_phases: int
    tag_sets: int
    seconds: float


def feed_corpus(
    executor, probe: Probe, nodes: dict, valid: list, cases: list, timeout: float = 120.0
) -> CorpusReport:
    """
    Send ``valid`` frames with every corpus case interleaved and judge each case.

    Corrupt frames go right after the frame they were copied from, stand-ins in place of the
    frame whose slot they take, corrupt tag points among the frames (after the first genuine set
    fixed the study's dimensions); once solver and analyzer hold the model, corrupt outputs go in,
    and latched-topic cases one at a time (a KEEP_LAST(1) reader would otherwise drop the genuine
    model for them). A case passes if its consumer reports it, naming its stamp, with its
    ``expect`` fragment at WARN (``frame/content``) or ERROR; a legal stand-in passes if it comes
    out as a non-empty tag set with no error against it.
    """
    from corpus.message_cases import frames_with_cases
    from diagnostic_msgs.msg import DiagnosticStatus

    t0 = time.monotonic()
    crashes: list = []

    def spin(pred, limit):
        deadline = time.monotonic() + limit
        while time.monotonic() < deadline and not pred():
            try:
                executor.spin_once(timeout_sec=0.05)
            except Exception as exc:  # a callback raised: the crash the corpus must not cause
                crashes.append(f'{type(exc).__name__}: {exc}')
        return pred()

    frames = [c for c in cases if c.topic == qos.FRAMES]
    points = [c for c in cases if c.topic == qos.TAG_POINTS]
    outputs = [c for c in cases if c.topic in (qos.MOTION, qos.MODEL_STATE)]
    latched = [c for c in cases if c.topic in qos.LATCHED_TOPICS]
    solver, analyzer = nodes['meshless_solver'], nodes['motion_analyzer']
    num_phases = valid[0].num_phases
    pending_points = list(points)
    for i, (frame, derived) in enumerate(frames_with_cases(valid, frames)):
        probe.publish(qos.FRAMES, frame)
        for c in derived:
            probe.publish(qos.FRAMES, c.msg)
        if i == 0:
            spin(lambda: solver.messages_handled >= 1, 30)
        elif pending_points:
            probe.publish(qos.TAG_POINTS, pending_points.pop().msg)
    for c in pending_points:
        probe.publish(qos.TAG_POINTS, c.msg)
    spin(lambda: solver.tracker is not None and analyzer.analyzer is not None, 60)
    for c in outputs:
        probe.publish(c.topic, c.msg)

    def reports(case):
        return [
            (lvl, f'{msg} {vals}'.lower())
            for node, lvl, msg, vals in probe.statuses()
            if node == case.node and vals.get('stamp') == case.stamp
        ]

    for c in latched:
        probe.publish(c.topic, c.msg)
        spin(lambda c=c: reports(c), 60)

    def stamps_out():
        return {conversions.stamp_text(p.header.stamp) for p in probe.received('points')}

    legal = [c for c in cases if not c.expect]
    spin(
        lambda: (
            len(probe.received('metrics')) >= num_phases
            and all(reports(c) for c in cases if c.expect)
            and {c.stamp for c in legal} <= stamps_out()
        ),
        timeout,
    )

    warn, error = DiagnosticStatus.WARN, DiagnosticStatus.ERROR
    failures = []
    for c in cases:
        got = reports(c)
        if c.expect:
            want = warn if c.category == 'frame/content' else error
            if not any(lvl == want and c.expect in text for lvl, text in got):
                failures.append(f'{c.name}: want level {want} with {c.expect!r}, got {got}')
        else:
            out = [
                p
                for p in probe.received('points')
                if conversions.stamp_text(p.header.stamp) == c.stamp
            ]
            if any(lvl == error for lvl, _ in got) or not (
                len(out) == 1 and len(out[0].track_id) > 0
            ):
                failures.append(
                    f'{c.name}: legal frame not processed: {got}, {[p.status for p in out]}'
                )
    valid_stamps = {conversions.stamp_text(m.header.stamp) for m in valid}
    false_alarms = [
        s for s in probe.statuses() if s[1] == error and s[3].get('stamp') in valid_stamps
    ]
    seen = len(probe.out['diag'])

    def alive():
        return {status_node(s) for d in probe.out['diag'][seen:] for s in d.status}

    spin(lambda: alive() >= set(nodes), 5)
    return CorpusReport(
        cases=len(cases),
        reported=len(cases) - len(failures),
        failures=failures,
        crashes=crashes,
        nodes_down=sorted(set(nodes) - alive()),
        false_alarms=false_alarms,
        phases_analysed=len({m.phase_index for m in probe.received('metrics')}),
        num_phases=num_phases,
        tag_sets=nodes['tag_detector'].published,
        seconds=round(time.monotonic() - t0, 2),
    )
