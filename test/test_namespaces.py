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
Namespaces: the graph, its config, runs and recordings under a ROS namespace.

Namespaces: every node names its topics relative, so a graph started under a
namespace talks on ``/NS/mlv/*`` and ``/NS/lv/*`` (the root names unchanged without one);
``config/graph.yaml`` applies in any namespace (``/**/node`` keys); ``mlv-ros run --namespace``
runs and records the whole graph there, two such runs share one ROS domain, and a namespaced
recording replays. Real nodes over real Fast DDS, in this test process's own domain.
"""

import json
import os
import subprocess

from conftest import console_script, spin_until
from mlv_msgs.msg import TaggedFrame
from mlv_ros import bagio, qos
from mlv_ros.nodes.frame_source import FrameSource, read_bag_frames
from mlv_ros.nodes.motion_analyzer import MotionAnalyzer
from mlv_ros.nodes.recorder import Recorder
from mlv_ros.nodes.replay import Replay
from mlv_ros.nodes.tag_detector import TagDetector
from mlv_ros.recording import phantom_accuracy
from mlv_ros.resources import config_file
from mlv_ros.runner import graph_nodes_on, node_parameters
import pytest
from rclpy.parameter import Parameter

pytestmark = pytest.mark.slow  # a graph run: scheduled first (conftest)

# Two studies of different hearts, small enough to run side by side in 27-34 s on 2 busy cores
# (noise-free 96² images, 8 phases: ES median error about 1 mm alone).
STUDIES = {'study_a': 'normal', 'study_b': 'dilated'}
SMALL = ['--size', '96', '--phases', '8', '--particles', '400', '--snr', '0', '--quiet']


def test_topics_resolve_in_the_node_namespace(ros_context, tmp_path):
    """
    Check topic names at the root and under a namespace.

    Root names as before at the root; under a namespace every graph topic moves with the node,
    /diagnostics stays where diagnostic_updater publishes.
    """
    for ns, prefix in (('/', ''), ('/study2', '/study2')):
        det = TagDetector(context=ros_context, namespace=ns)
        rec = Recorder(
            context=ros_context,
            namespace=ns,
            parameter_overrides=[Parameter('output', value=str(tmp_path / f'{len(prefix)}.mcap'))],
        )
        try:
            published = {p.topic_name for p in det.publishers}
            assert {prefix + qos.TAG_POINTS, qos.DIAGNOSTICS} <= published
            assert not {t for t in published if t.startswith(('/mlv', '/lv'))} - {
                prefix + qos.TAG_POINTS
            }
            assert {s.topic_name for s in det.subscriptions} >= {prefix + qos.FRAMES}
            assert set(det.streams) == {prefix + qos.FRAMES}  # loss counts under the resolved name
            # The recorder takes and records every graph topic as it resolves in its namespace.
            assert set(rec.writer.topics) == {prefix + t for t in qos.GRAPH_TOPICS} | {
                qos.DIAGNOSTICS
            }
        finally:
            rec.writer.discard()
            for node in (det, rec):
                node.destroy_node()


def test_graph_yaml_applies_in_any_namespace_and_statuses_are_named_as_diagnostic_updater(
    ros_context,
):
    params = node_parameters(config_file('graph.yaml'), {'frame_source': {'source': 'pattern'}})[
        'frame_source'
    ]
    for ns in ('/', '/study2', '/site_a/study2'):
        src = FrameSource(context=ros_context, namespace=ns, **params)
        try:
            # graph.yaml's value (3), not the code's default (1): its /**/frame_source key matches
            assert src.wait_for_subscribers == 3 and src.max_pixels == 1048576
            assert src.pub.topic_name == ns.rstrip('/') + qos.FRAMES
            assert (src.status.name, src.status.hardware_id) == ('frame_source: input', 'none')
        finally:
            src.destroy_node()
    # `-p` on the command line still wins over the file, in any namespace (graph.yaml keeps its
    # `/**` key last: rcl files `-p` under `/**` too, and node keys after it would win)
    cli = dict(
        params,
        cli_args=params['cli_args'] + ['-p', 'wait_for_subscribers:=2', '-p', 'max_pixels:=4096'],
    )
    for ns in ('/', '/study2'):
        src = FrameSource(context=ros_context, namespace=ns, **cli)
        assert (src.wait_for_subscribers, src.max_pixels) == (2, 4096)
        src.destroy_node()
    # diagnostic_updater.use_fqn (mlv-ros run --namespace sets it): the node's full name
    fqn = dict(
        params,
        parameter_overrides=params['parameter_overrides']
        + [Parameter('diagnostic_updater.use_fqn', value=True)],
    )
    src = FrameSource(context=ros_context, namespace='/study2', **fqn)
    assert src.status.name == '/study2/frame_source: input'
    src.destroy_node()


def test_domain_check_is_namespace_aware(ros_context, executor, tmp_path, capsys):
    """
    Check that a graph in the same namespace is refused and one in another is no conflict.

    A graph in the same namespace is refused; one in another namespace is no conflict (the
    two runs below share a domain; here: the probe keeps to its namespace).
    """
    from mlv_ros import cli

    executor.add_node(MotionAnalyzer(context=ros_context, namespace='/busy'))
    domain = int(os.environ['ROS_DOMAIN_ID'])
    # (The refusal first: a probe right after another probe of this process was destroyed may
    # not be discovered within the second it looks.)
    rc = cli.main(
        [
            'run',
            '--phantom',
            'normal',
            '--out',
            str(tmp_path / 'run'),
            '--namespace',
            '/busy/',
            '--timeout',
            '20',
        ]
    )
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1, lines
    assert f'ROS domain {domain} is busy' in lines[0] and 'namespace /busy ' in lines[0], lines[0]
    assert '--namespace NS' in lines[0] and '/busy/motion_analyzer' in lines[0]
    assert not (tmp_path / 'run').exists()
    assert graph_nodes_on(domain, wait_s=0.3, namespace='/other') == []
    rc = cli.main(
        ['run', '--phantom', 'normal', '--out', str(tmp_path / 'run'), '--namespace', '2nd-study']
    )
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and 'is not a ROS namespace' in lines[0], lines


@pytest.fixture(scope='module')
def two_runs(tmp_path_factory):
    """Run two studies at once (`mlv-ros run`), on this process's ROS domain, in two namespaces."""
    tmp = tmp_path_factory.mktemp('namespaces')
    domain = os.environ['ROS_DOMAIN_ID']
    procs = {
        ns: subprocess.Popen(
            [
                console_script('mlv-ros'),
                'run',
                '--phantom',
                preset,
                *SMALL,
                '--namespace',
                ns,
                '--domain-id',
                domain,
                '--out',
                str(tmp / ns),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for ns, preset in STUDIES.items()
    }
    runs = {}
    for ns, proc in procs.items():
        try:
            _, err = proc.communicate(timeout=150)
        except subprocess.TimeoutExpired:
            for p in procs.values():
                p.kill()
            pytest.fail(f'mlv-ros run --namespace {ns} did not end within 150 s')
        summary = tmp / ns / 'summary.json'
        runs[ns] = (
            proc.returncode,
            err,
            json.loads(summary.read_text()) if summary.exists() else None,
        )
    return tmp, runs


def test_two_studies_at_once_in_two_namespaces(two_runs):
    tmp, runs = two_runs
    ids = set()
    for ns, (rc, err, s) in runs.items():
        assert rc == 0 and s is not None, err[-3000:]
        assert 'Traceback' not in err
        assert (
            s['complete']
            and s['namespace'] == f'/{ns}'
            and s['ros_domain_id'] == int(os.environ['ROS_DOMAIN_ID'])
        )
        assert s['metrics_published'] == s['num_phases'] == 8
        assert 'messages_of_other_studies' not in s  # the topics never met
        ids.add(s['study_id'])
        # The recording holds this graph's topics, under its namespace, and only its study.
        mcap = tmp / ns / 'run.mcap'
        assert set(bagio.bag_topics(mcap)) == {f'/{ns}{t}' for t in qos.GRAPH_TOPICS} | {
            qos.DIAGNOSTICS
        }
        frames = read_bag_frames(mcap)
        assert len(frames) == s['frames_published'] and {f.study_id for f in frames} == {
            s['study_id']
        }
        # Each study's own motion: close to its own heart's truth, far from the other's.
        es = s['accuracy']['es']
        assert es['median_mm'] <= 1.5 and es['p95_mm'] <= 4.0, es
        other = next(p for n, p in STUDIES.items() if n != ns)
        assert phantom_accuracy(mcap, other, 8)['es']['median_mm'] > 2 * es['median_mm']
    assert len(ids) == 2


def test_a_namespaced_recording_replays_in_the_player_namespace(two_runs, ros_context, executor):
    """
    Check that the replay plays a /study_a recording in its own namespace.

    The replay plays the graph topics of a /study_a recording in its own namespace; a bag
    source reads its frames.
    """
    import rclpy

    tmp, runs = two_runs
    mcap, summary = tmp / 'study_a' / 'run.mcap', runs['study_a'][2]
    src = FrameSource(
        context=ros_context,
        parameter_overrides=[Parameter('source', value='bag'), Parameter('path', value=str(mcap))],
    )
    assert len(src.frames) == summary['frames_published'] and src.study_id == summary['study_id']
    src.destroy_node()
    got, elsewhere = [], []
    sink = rclpy.create_node('namespaced_frames_sink', context=ros_context)
    sink.create_subscription(
        TaggedFrame, '/again' + qos.FRAMES, got.append, qos.stream_qos(), raw=True
    )
    sink.create_subscription(
        TaggedFrame, '/study_a' + qos.FRAMES, elsewhere.append, qos.stream_qos(), raw=True
    )
    replay = Replay(
        context=ros_context,
        namespace='/again',
        parameter_overrides=[
            Parameter('path', value=str(tmp / 'study_a')),
            Parameter('topics', value=['/study_a' + qos.FRAMES]),
        ],
    )
    executor.add_node(sink)
    executor.add_node(replay)
    assert [p.topic_name for p in replay.pubs.values()] == ['/again' + qos.FRAMES]
    assert spin_until(
        executor, lambda: replay.done and len(got) == summary['frames_published'], 20
    ), len(got)
    assert not elsewhere
    # A graph topic may also be asked for by its root name.
    by_root = Replay(
        context=ros_context,
        parameter_overrides=[
            Parameter('path', value=str(mcap)),
            Parameter('topics', value=[qos.MOTION]),
        ],
    )
    assert {t: p.topic_name for t, p in by_root.pubs.items()} == {
        '/study_a' + qos.MOTION: qos.MOTION
    }
    by_root.destroy_node()
