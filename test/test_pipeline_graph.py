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
The whole graph end to end, in one process and across processes.

The whole graph end to end: in one process on a simulated phantom (accuracy against the
analytic ground truth; the recording read back by rosbags), and across processes started from
the console scripts.
"""

import json
from pathlib import Path
import subprocess
import sys

from conftest import console_script, spin_until
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from mlv_ros import bagio, qos
from mlv_ros.nodes.common import status_node
from mlv_ros.recording import phantom_accuracy, read_run
from mlv_ros.runner import run_graph
import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'bench'))

pytestmark = pytest.mark.slow  # a graph run: scheduled first (conftest)

# A reduced acquisition that runs in about a minute on 2 cores (the default study is
# 256² × 25 phases; `mlv-ros bench pipeline` measures that one).
PHANTOM = {'source': 'phantom', 'preset': 'normal', 'snr': 20.0, 'size': 192, 'num_phases': 16}
PARTICLES = {'registration': {'num_particles': 2000}}


@pytest.fixture(scope='module')
def phantom_run(tmp_path_factory):
    out = tmp_path_factory.mktemp('run')
    with pytest.MonkeyPatch.context() as mp:  # the default study as a user runs it: the layout too
        mp.delenv('MLV_ROS_ONE_PROCESS', raising=False)
        summary = run_graph(
            PHANTOM, out, overrides=PARTICLES, timeout=400, progress=lambda *_: None
        )
    return out, summary


def test_graph_completes_every_phase(phantom_run):
    _, s = phantom_run
    assert s['complete'], s
    assert s['frames_published'] == 11 * 16
    assert s['tag_sets_published'] == s['frames_published']
    assert s['phases_solved'] == s['metrics_published'] == 16


def test_end_to_end_accuracy_against_ground_truth(phantom_run):
    out, s = phantom_run
    acc = phantom_accuracy(out / 'run.mcap', 'normal', 16)
    es = acc['es']
    # Issue acceptance (default study): median ≤ 1.0 mm, p95 ≤ 2.5 mm, twist ≤ 2°.
    assert acc['inside_myocardium'] >= 0.95
    assert es['median_mm'] <= 1.0, es
    assert es['p95_mm'] <= 2.5, es
    assert es['twist_error_deg'] <= 2.0, es
    worst = max(r['median_mm'] for r in acc['per_phase'])
    assert worst <= 1.5, acc['per_phase']
    # Every phase within 1.5 mm of the truth: none may be marked failed, and end-systole is ok;
    # anything not ok says why (mlv_ros.core.verdict).
    metrics = read_run(out / 'run.mcap')['metrics']
    assert sorted(metrics) == list(range(16))
    assert all(m['verdict'] < 2 for m in metrics.values()), {
        p: m['verdict_reasons'] for p, m in metrics.items()
    }
    assert metrics[acc['es_phase']]['verdict'] == 0, metrics[acc['es_phase']]['verdict_reasons']
    assert all((m['verdict'] == 0) == (m['verdict_reasons'] == '') for m in metrics.values())


def test_recording_opens_with_rosbags_with_every_topic(phantom_run):
    out, s = phantom_run
    counts, last = {}, {}
    with AnyReader(
        [out / 'run.mcap'], default_typestore=get_typestore(Stores.ROS2_JAZZY)
    ) as reader:
        for conn, _t, raw in reader.messages():
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
            if conn.topic == qos.MOTION and counts[conn.topic] == 1:
                cloud = reader.deserialize(raw, conn.msgtype)
                assert [f.name for f in cloud.fields][:6] == ['x', 'y', 'z', 'dx', 'dy', 'dz']
                assert cloud.header.frame_id == 'patient'
            if conn.topic in (qos.METRICS, qos.REGISTERED_STATE):
                last[conn.topic] = reader.deserialize(raw, conn.msgtype)
    assert counts[qos.FRAMES] == s['frames_published']
    assert counts[qos.TAG_POINTS] == s['tag_sets_published']
    assert counts[qos.MOTION] == counts[qos.MODEL_STATE] == counts[qos.METRICS] == 16
    assert counts[qos.REGISTERED_CLOUD] == counts[qos.REGISTERED_STATE] == 1
    assert counts[qos.DIAGNOSTICS] >= 1
    assert sum(counts.values()) == s['recorded_messages']
    # The findings and where the segments' origin came from, as rosbags reads them: this phantom
    # has no RV, so the anatomical prior, said in the registered state and every metrics message.
    m, reg = last[qos.METRICS], last[qos.REGISTERED_STATE]
    assert reg.segment_origin == m.segment_origin == 1 and m.segment_origin_confidence == 0.0
    assert len(m.segment_class) == 17 and set(m.segment_class) <= {0, 1, 2, 3, 4}
    assert len(m.finding_es_ecc) == len(m.finding_peak_err_unc) == len(m.segment_ecc_unc) == 17
    assert m.findings_es_phase > 0
    run = read_run(out / 'run.mcap')
    assert sorted(run['positions']) == list(range(16))
    np.testing.assert_allclose(run['positions'][0], run['ed'], atol=1e-4)  # phase 0 = ED


def test_local_stage_matches_the_reference_on_the_recorded_tag_points(phantom_run):
    """
    Check the local stage against the old one (bench/reference_local.py) on recorded tag points.

    The run's registration and detected tag points (noisy, screened, unequally confident) are
    solved by a tracker built as the solver node builds it; each local solve of end-systole
    (solved from rest) is run by both stages from the same start on the same attachment and
    global fit, without the per-point weights and the longitudinal coupling the old stage lacks.
    CG runs to rtol 1e-6 either way, so what differs is the operators, not where CG stopped
    (the simulated-tag check at the node's rtol is test_local_stage's).
    """
    from pipeline import recorded_solver_input, recorded_tracker
    from reference_local import tracker_local_solve

    out, _ = phantom_run
    cloud, state, sets = recorded_solver_input(out / 'run.mcap')
    tr = recorded_tracker(cloud, state, sets[0], longitudinal_coupling=0.0)
    tr.cg_rtol = tr.cg_rtol_following = 1e-6  # every pass, and the reference (it reads cg_rtol)
    tr.cg_maxiter = 5000
    new_solve, cache, diffs = tr._local_solve, {}, []

    def both(phi, targets, normals, x_global, weights=None, rtol=None, scale=None):
        start = (None if tr.delta is None else tr.delta.copy(), tr._local_gradients)
        plain = new_solve(phi, targets, normals, x_global)
        old, _ = tracker_local_solve(tr, phi, targets, normals, x_global, start[0], cache)
        tr.delta, tr._local_gradients = start  # the node's solve goes on from the same start
        diffs.append((np.linalg.norm(plain - old, axis=1), np.abs(old).max()))
        return new_solve(phi, targets, normals, x_global, weights, rtol, scale)

    tr._local_solve = both
    volume = {p: m['cavity_volume_ml'] for p, m in read_run(out / 'run.mcap')['metrics'].items()}
    es = min(volume, key=volume.get)  # the analyzer's end-systole
    tr.solve(es, sets[es], 16)
    assert len(diffs) == 2
    assert max(d for _, d in diffs) > 1.0  # δ reaches millimetres by end-systole
    # measured 1.7e-5 / 8e-5 mm (median / p95); a fit-error penalty 5 % off: 0.0057 mm median
    assert max(np.median(d) for d, _ in diffs) < 1e-3, [np.median(d) for d, _ in diffs]
    assert max(np.percentile(d, 95) for d, _ in diffs) < 5e-3, [
        np.percentile(d, 95) for d, _ in diffs
    ]


def test_report_from_the_recording(phantom_run, tmp_path):
    from mlv_ros.recording import write_report

    out, _ = phantom_run
    index = write_report(out / 'run.mcap', tmp_path / 'report')
    summary = json.loads((tmp_path / 'report' / 'summary.json').read_text())
    assert index.exists() and '<img' in index.read_text()
    assert (tmp_path / 'report' / 'level_curves.png').stat().st_size > 10_000
    assert summary


def test_nodes_in_separate_processes(ros_context, executor, tmp_path):
    """Run frame_source → tag_detector → registration/solver/analyzer → recorder, each alone."""
    from mlv_msgs.msg import TagPoints
    from rclpy.node import Node

    diags, points = [], []
    watcher = Node('watcher', context=ros_context)
    watcher.create_subscription(
        DiagnosticArray, qos.DIAGNOSTICS, diags.append, qos.diagnostics_qos()
    )
    watcher.create_subscription(TagPoints, qos.TAG_POINTS, points.append, qos.stream_qos())
    executor.add_node(watcher)
    mcap = tmp_path / 'run.mcap'
    procs = [
        subprocess.Popen(
            [console_script(n), '--ros-args', *args],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for n, args in [
            ('recorder', ['-p', f'output:={mcap}']),
            ('tag_detector', []),
            ('registration', ['-p', 'ed_timeout_s:=2.0']),
            ('meshless_solver', []),
            ('motion_analyzer', []),
        ]
    ]
    try:

        def up(name):
            return any(status_node(st) == name for d in diags for st in d.status)

        assert spin_until(
            executor,
            lambda: all(
                up(n)
                for n in (
                    'recorder',
                    'tag_detector',
                    'registration',
                    'meshless_solver',
                    'motion_analyzer',
                )
            ),
            60,
        )
        src = subprocess.run(
            [
                console_script('frame_source'),
                '--ros-args',
                '-p',
                'source:=pattern',
                '-p',
                'num_phases:=3',
                '-p',
                'wait_for_subscribers:=3',
            ],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert src.returncode == 0, src.stderr
        assert spin_until(executor, lambda: len(points) == 6, 60), f'{len(points)} tag point sets'
        # The pattern has no heart: registration must say so on /diagnostics, not crash.
        assert spin_until(
            executor,
            lambda: any(
                status_node(st) == 'registration' and st.level == DiagnosticStatus.ERROR
                for d in diags
                for st in d.status
            ),
            30,
        )
    finally:
        for p in procs:
            p.send_signal(2)
        for p in procs:
            try:
                assert p.wait(timeout=30) == 0
            finally:
                if p.poll() is None:
                    p.kill()
    topics = bagio.bag_topics(mcap)
    assert topics[qos.FRAMES]['count'] == 6
    assert topics[qos.TAG_POINTS]['count'] == 6


def restart_mid_run(ros_context, executor, victim: str, phases: int = 4):
    """
    Run the graph on a phantom, SIGKILL and restart ``victim``, and return what it published.

    Run tag_detector, registration and meshless_solver as processes on a phantom, SIGKILL
    ``victim`` after half the phases are solved, start it again, and return the model states and
    tag sets published after the restart (the run must then complete). Four phases: two solved
    before the kill, two (and, for a new solver, all four again) after it, which is all the
    checks need; every phase more only costs tag detection and solves.
    """
    from mlv_msgs.msg import ModelState, TagPoints
    from rclpy.node import Node

    states, tag_sets = [], []
    watcher = Node('restart_watcher', context=ros_context)
    watcher.create_subscription(ModelState, qos.MODEL_STATE, states.append, qos.stream_qos())
    # with history: a restarted tag detector publishes at once, before a VOLATILE reader matches it
    watcher.create_subscription(
        TagPoints,
        qos.TAG_POINTS,
        tag_sets.append,
        qos.subscription_qos(qos.TAG_POINTS, catch_up=True),
    )
    executor.add_node(watcher)
    common = ['--ros-args', '--params-file', 'config/graph.yaml']
    # the watcher is the solver's one subscriber here (no analyzer, no recorder)
    extra = {
        'registration': ['-p', 'num_particles:=1000'],
        'meshless_solver': ['-p', 'wait_for_subscribers:=1'],
    }
    procs = {
        n: subprocess.Popen(
            [console_script(n), *common, *extra.get(n, [])],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for n in ('tag_detector', 'registration', 'meshless_solver')
    }
    src = subprocess.Popen(
        [
            console_script('frame_source'),
            *common,
            '-p',
            'size:=128',
            '-p',
            f'num_phases:={phases}',
            '-p',
            'wait_for_subscribers:=2',
            '-p',
            'exit_when_done:=false',
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        half = phases // 2
        assert spin_until(executor, lambda: len({s.phase_index for s in states}) >= half, 240), (
            f'phases before the kill: {sorted({s.phase_index for s in states})}'
        )
        procs[victim].kill()
        procs[victim].wait(timeout=10)
        before, sets_before = len(states), len(tag_sets)
        procs[victim] = subprocess.Popen(
            [console_script(victim), *common, *extra.get(victim, [])],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        done = set(range(phases))
        assert spin_until(
            executor,
            lambda: (
                {s.phase_index for s in states} == done
                and (
                    victim != 'meshless_solver' or {s.phase_index for s in states[before:]} == done
                )
            ),
            300,
        ), f'after restart: {sorted({s.phase_index for s in states[before:]})}'
        if victim == 'tag_detector':  # every frame again, from the frame publisher's history
            per_study = phases * (tag_sets[0].num_sa_slices + tag_sets[0].num_la_slices)
            assert spin_until(executor, lambda: len(tag_sets) - sets_before >= per_study, 120), (
                f'{len(tag_sets) - sets_before} of {per_study} tag sets after the restart'
            )
        return states[before:], tag_sets[sets_before:]
    finally:
        for p in [*procs.values(), src]:
            p.send_signal(2)
        for p in [*procs.values(), src]:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()


def test_solver_killed_mid_run_and_restarted_completes_the_run(ros_context, executor):
    """
    Check that a new solver process gets the latched history and solves every phase again.

    A new solver process gets the latched registration and the tag-point history
    (TRANSIENT_LOCAL) and solves every phase again.
    """
    restart_mid_run(ros_context, executor, 'meshless_solver')


def test_tag_detector_killed_mid_run_and_restarted_completes_the_run(ros_context, executor):
    """
    Check that a new tag detector takes the frames' history and republishes every tag set.

    A new tag detector takes the frames' history (catch_up) and republishes every tag set;
    the solver, still running, completes the phases it had not solved.
    """
    restart_mid_run(ros_context, executor, 'tag_detector')
