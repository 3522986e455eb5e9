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
Run isolation: two graphs on one ROS domain cannot mix.

Every message of a study carries its ``study_id``; each node keeps to the study of the first
message it takes and reports (ERROR on /diagnostics, naming both ids) and ignores the others;
point clouds, which cannot carry an id, go with the model state of the same stamp. ``mlv-ros
run`` refuses a domain on which another mlv_ros graph's node is up. Real nodes over real Fast
DDS, in this test process's own domain.
"""

import os
import threading
import time

from conftest import spin_until
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from graphkit import Probe, wait_matched
from mlv_ros import bagio, conversions, qos
from mlv_ros.core.sim.pattern import pattern_frames
from mlv_ros.core.types import ModelState
from mlv_ros.nodes.frame_source import count_slices
from mlv_ros.nodes.motion_analyzer import MotionAnalyzer
from mlv_ros.nodes.recorder import Recorder
from mlv_ros.nodes.tag_detector import TagDetector
import pytest
from rclpy.parameter import Parameter

OURS, THEIRS = 'study-ours', 'study-theirs'
IGNORED = 'message of another study ignored (another graph on this ROS_DOMAIN_ID?)'


def frames_of(study: str, stamp0: float, run: str = '') -> list:
    frames = count_slices(pattern_frames(num_phases=3))  # 2 slices × 3 phases, 64²
    for f in frames:
        f.study_id, f.run_id = study, run
    return [conversions.frame_to_msg(f, stamp=stamp0 + i) for i, f in enumerate(frames)]


def cloud(stamp: float):
    pts = conversions.structured({k: [1.0, 2.0, 3.0] for k in ('x', 'y', 'z')})
    return conversions.cloud_to_msg(pts, conversions.make_header(stamp))


# Two graphs on one domain: of two studies, or two runs of the same study (each run draws its own
# run_id at its frame source), as (our study, our run), (their study, their run), how the other is
# named.
OTHERS = {
    'another study': ((OURS, 'run-a'), (THEIRS, 'run-b'), THEIRS),
    'another run of the same study': ((OURS, 'run-a'), (OURS, 'run-b'), f'{OURS} run run-b'),
}


@pytest.mark.parametrize('other', OTHERS)
def test_nodes_keep_to_the_first_study_and_report_the_other(
    other, ros_context, executor, tmp_path
):
    (our_study, our_run), (their_study, their_run), THEIRS = OTHERS[other]
    ours_label = f'{our_study} run {our_run}'
    det = TagDetector(context=ros_context)
    analyzer = MotionAnalyzer(context=ros_context)
    rec = Recorder(
        context=ros_context,
        parameter_overrides=[Parameter('output', value=str(tmp_path / 'run.mcap'))],
    )
    probe = Probe(ros_context)
    for n in (det, analyzer, rec, probe):
        executor.add_node(n)
    wait_matched(executor, probe, {qos.FRAMES: 2, qos.MODEL_STATE: 2, qos.MOTION: 2})

    ours, theirs = frames_of(our_study, 1.0, our_run), frames_of(their_study, 100.0, their_run)
    probe.publish(qos.FRAMES, ours[0])  # the first frame taken decides the study
    assert spin_until(
        executor, lambda: det.messages_handled == 1 and rec.streams[qos.FRAMES].received == 1, 10
    )
    for a, b in zip(theirs, ours[1:] + [None]):
        probe.publish(qos.FRAMES, a)
        if b is not None:
            probe.publish(qos.FRAMES, b)

    # Model states and their clouds: ours (stamp 300) is held for its cloud; theirs take their
    # clouds with them, whether the cloud comes before the state (301) or after (302).
    def state(phase, study, run, stamp):
        return conversions.model_state_to_msg(
            ModelState(phase, 3, study_id=study, run_id=run), stamp=stamp
        )

    probe.publish(qos.MODEL_STATE, state(1, our_study, our_run, 300.0))
    probe.publish(qos.MOTION, cloud(301.0))
    probe.publish(qos.MODEL_STATE, state(1, their_study, their_run, 301.0))
    probe.publish(qos.MODEL_STATE, state(2, their_study, their_run, 302.0))
    probe.publish(qos.MOTION, cloud(302.0))
    assert spin_until(
        executor,
        lambda: (
            det.messages_handled == 12
            and analyzer.messages_handled == 5
            and len(probe.received('points')) == 6
            and data_taken(rec) == 12 + 6 + 5
        ),
        15,
    )

    # The tag detector: our six frames tracked, theirs reported one by one and nothing sent on.
    assert sorted(p.header.stamp.sec for p in probe.received('points')) == [1, 2, 3, 4, 5, 6]
    assert {(p.study_id, p.run_id) for p in probe.received('points')} == {(our_study, our_run)}

    def said():
        return [
            v
            for node, level, msg, v in probe.statuses()
            if node == 'tag_detector' and msg == IGNORED
        ]

    assert spin_until(executor, lambda: len(said()) == 6, 5), said()
    said = said()
    assert all(
        v['study'] == ours_label and v['other_study'] == THEIRS and v['topic'] == qos.FRAMES
        for v in said
    )
    assert sorted(v['stamp'] for v in said) == sorted(
        conversions.stamp_text(m.header.stamp) for m in theirs
    )
    assert det.other_studies == {THEIRS: 6} and (det.study.study_id, det.study.run_id) == (
        our_study,
        our_run,
    )
    assert not [
        s
        for s in probe.statuses()
        if s[0] == 'tag_detector'
        and any(w in s[2] for w in ('bad frame', 'different frame', 'slot', 'duplicate'))
    ], 'their frames were taken for ours'
    # ... and its heartbeat keeps saying so, at ERROR.
    assert spin_until(
        executor,
        lambda: any(
            node == 'tag_detector'
            and level == DiagnosticStatus.ERROR
            and '6 message(s) of another study ignored' in msg
            for node, level, msg, _ in probe.statuses()
        ),
        3,
    )

    # The analyzer: their states reported and dropped with their clouds (whichever came first);
    # ours waits for its cloud.
    assert analyzer.other_studies == {THEIRS: 4} and analyzer.study.study_id == OURS
    assert list(analyzer.states) == [(300, 0)] and not analyzer.clouds
    # (A set: the heartbeat may repeat the node's current status, the last of these, meanwhile.)
    assert spin_until(
        executor,
        lambda: (
            sorted(
                {
                    v['stamp']
                    for node, _l, msg, v in probe.statuses()
                    if node == 'motion_analyzer' and 'point cloud of another study' in msg
                }
            )
            == ['301.000000000', '302.000000000']
        ),
        5,
    )

    # The recorder: one study in the file, what it left out counted.
    rec.finish()
    recorded = {}
    for m in bagio.read_bag(tmp_path / 'run.mcap'):
        recorded.setdefault(m.topic, []).append(m)
    assert len(recorded[qos.FRAMES]) == 6 and len(recorded[qos.TAG_POINTS]) == 6
    assert all(
        (
            bagio.deserialize(m.data, qos_class(m.topic)).study_id,
            bagio.deserialize(m.data, qos_class(m.topic)).run_id,
        )
        == (our_study, our_run)
        for topic in (qos.FRAMES, qos.TAG_POINTS, qos.MODEL_STATE)
        for m in recorded[topic]
    )
    assert len(recorded[qos.MODEL_STATE]) == 1 and qos.MOTION not in recorded
    assert rec.ignored == 6 + 2 + 2 and rec.other_studies == {THEIRS: 10}
    assert spin_until(
        executor,
        lambda: [s for s in probe.statuses() if s[0] == 'recorder' and s[2] == 'recording closed'],
        5,
    )
    closed = [s for s in probe.statuses() if s[0] == 'recorder' and s[2] == 'recording closed']
    assert closed[-1][1] == DiagnosticStatus.OK and closed[-1][3]['other_study'] == '10'


def data_taken(rec) -> int:
    """Messages the recorder took, /diagnostics left out."""
    return sum(c.received for topic, c in rec.streams.items() if topic != qos.DIAGNOSTICS)


def qos_class(topic: str):
    from mlv_ros.bagio import message_class

    return message_class(qos.TOPIC_TYPES[topic])


def test_run_refuses_a_domain_another_graph_runs_on(ros_context, executor, tmp_path, capsys):
    from mlv_ros import cli
    from mlv_ros.domain import claim_domain_id
    from mlv_ros.runner import graph_nodes_on

    executor.add_node(
        MotionAnalyzer(context=ros_context)
    )  # one node of another graph, on this domain
    domain = int(os.environ['ROS_DOMAIN_ID'])
    out = tmp_path / 'new' / 'run'
    for args in (
        ['--domain-id', str(domain)],
        [],
    ):  # chosen on the command line, or by ROS_DOMAIN_ID
        t0 = time.monotonic()
        rc = cli.main(['run', '--phantom', 'normal', '--out', str(out), *args])
        lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
        assert rc == 2 and len(lines) == 1, lines
        assert lines[0].startswith(f'mlv-ros run: ROS domain {domain} is busy'), lines[0]
        assert (
            '/motion_analyzer' in lines[0]
            and '--domain-id N' in lines[0]
            and 'export ROS_DOMAIN_ID=N' in lines[0]
        )
        assert time.monotonic() - t0 < 5
        assert not (tmp_path / 'new').exists()  # nothing left in --out
    # A domain nobody uses is free; two runs looking at it at once see each other, and only the
    # one that started later is refused.
    free, seen = claim_domain_id(), {}
    looks = [
        threading.Thread(target=lambda i=i: seen.setdefault(i, graph_nodes_on(free, wait_s=1.0)))
        for i in range(2)
    ]
    for look in looks:
        look.start()
        time.sleep(0.01)
    for look in looks:
        look.join()
    assert seen[0] == [] and len(seen[1]) == 1 and seen[1][0].startswith('/_mlv_ros_run_'), seen


def test_study_ids_of_each_source():
    """What frame_source stamps on its frames: distinct studies get distinct ids."""
    from mlv_ros.nodes.frame_source import study_id_for

    frames = count_slices(pattern_frames(num_phases=2))
    phantom = {'preset': {'name': 'normal'}, 'snr': 20.0, 'size': 64, 'num_phases': 2, 'seed': 0}
    a = study_id_for('phantom', frames, params=phantom)
    assert a.startswith('phantom-') and a == study_id_for('phantom', frames, params=dict(phantom))
    assert a != study_id_for('phantom', frames, params={**phantom, 'seed': 1})
    assert study_id_for('dicom', frames, study_uids={'1.2.3': 10, '1.2.4': 1}) == '1.2.3'
    hashed = study_id_for('dicom', frames, study_uids={})  # no StudyInstanceUID: the images' hash
    frames[0].image = frames[0].image + 1
    assert hashed.startswith('dicom-') and hashed != study_id_for('dicom', frames, study_uids={})
    assert study_id_for('bag', frames, path='/x/run.mcap').startswith(
        'bag-'
    )  # recorded before study ids
    frames[1].study_id = 'recorded'
    assert study_id_for('bag', frames, path='/x/run.mcap') == 'recorded'


def test_replay_of_a_recording_made_before_study_ids(ros_context, executor):
    """The sample bag predates study_id: replayed, its frames read (with an empty study)."""
    from conftest import REPO
    from mlv_msgs.msg import TaggedFrame
    from mlv_ros.nodes.replay import Replay
    import rclpy

    got = []
    sink = rclpy.create_node('old_frames_sink', context=ros_context)
    sink.create_subscription(TaggedFrame, qos.FRAMES, got.append, qos.stream_qos())
    replay = Replay(
        context=ros_context,
        parameter_overrides=[Parameter('path', value=str(REPO / 'bags' / 'normal_sample.mcap'))],
    )
    executor.add_node(sink)
    executor.add_node(replay)
    assert spin_until(executor, lambda: len(got) == 176, 20), len(got)
    assert {m.study_id for m in got} == {''} and got[0].image.height == 128


def test_namespaced_recording_keeps_only_its_own_graphs_statuses(ros_context, executor, tmp_path):
    """
    /diagnostics is shared by every graph on a domain.

    A recorder in namespace study_a records the statuses of its own graph's nodes (named
    /study_a/<node>, as mlv-ros run --namespace and the launch file name them) and leaves out those
    of study_b's graph, of a root graph and of any other node, counting them; with all_diagnostics
    it records them all.
    """
    from mlv_ros.nodes.common import GraphNode, OK, USE_FQN
    from mlv_ros.nodes.recorder import GRAPH_NODE_NAMES

    fqn = [Parameter(USE_FQN, value=True)]
    recs = {
        'own': Recorder(
            context=ros_context,
            namespace='study_a',
            parameter_overrides=[
                Parameter('output', value=str(tmp_path / 'own' / 'run.mcap')),
                *fqn,
            ],
        ),
        'all': Recorder(
            context=ros_context,
            namespace='study_a',
            parameter_overrides=[
                Parameter('output', value=str(tmp_path / 'all' / 'run.mcap')),
                Parameter('all_diagnostics', value=True),
                *fqn,
            ],
        ),
    }
    publishers = [
        GraphNode(
            'tag_detector', context=ros_context, namespace='study_a', parameter_overrides=fqn
        ),
        GraphNode(
            'tag_detector', context=ros_context, namespace='study_b', parameter_overrides=fqn
        ),
        GraphNode(
            'meshless_solver', context=ros_context
        ),  # a root graph's, named by its name alone
        GraphNode('battery', context=ros_context, namespace='study_a', parameter_overrides=fqn),
    ]
    for n in (*recs.values(), *publishers):
        executor.add_node(n)
    assert spin_until(
        executor, lambda: all(r.count_publishers(qos.DIAGNOSTICS) >= 6 for r in recs.values()), 10
    )
    for p in publishers:
        p.report(OK, 'hello')
    assert spin_until(
        executor,
        lambda: all(r.streams[qos.DIAGNOSTICS].received >= 6 + 2 for r in recs.values()),
        10,
    )  # (and the recorders' own)
    for r in recs.values():
        r.finish()
    names = {}
    for key in recs:
        names[key] = {
            st.name.partition(': ')[0]
            for m in bagio.read_bag(tmp_path / key / 'run.mcap')
            if m.topic == qos.DIAGNOSTICS
            for st in bagio.deserialize(m.data, DiagnosticArray, m.missing).status
        }
    assert names['own'] == {'/study_a/tag_detector', '/study_a/recorder'}, names['own']
    assert names['all'] >= {
        '/study_a/tag_detector',
        '/study_b/tag_detector',
        'meshless_solver',
        '/study_a/battery',
    }
    assert recs['own'].other_graph_statuses >= 3 and recs['all'].other_graph_statuses == 0
    assert recs['own'].status.level == OK and 'other_graph_statuses' in {
        kv.key for kv in recs['own'].status.values
    }
    assert 'meshless_solver' in GRAPH_NODE_NAMES  # left out for its namespace, not its name
    for n in (*recs.values(), *publishers):
        executor.remove_node(n)
        n.destroy_node()
