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
A calm console: counts for routine events, WARN only for what needs action.

A calm console: routine events are counts, WARN is for what a user must act
on, and every CLI mistake is one line with the fix.

The tag detector runs over real Fast DDS on a short simulated cine whose tags fade (T1 recovery
over the cycle): its log lines are read from /rosout, as any ROS tool would, and its statuses
from /diagnostics. The CLI is run as a user runs it, in a subprocess.
"""

from __future__ import annotations

import dataclasses
import subprocess

from conftest import console_script, REPO, spin_until
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from mlv_msgs.msg import TaggedFrame, TagPoints
from mlv_ros import conversions, qos
from mlv_ros.core.sim import simulate_study
from mlv_ros.nodes.common import status_node
from mlv_ros.nodes.frame_source import count_slices, order_frames
from mlv_ros.nodes.registration import Registration
from mlv_ros.nodes.tag_detector import TagDetector
import numpy as np
import pytest
from rcl_interfaces.msg import Log
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

PHASES = 4
WARN_LOG = 30  # rcl_interfaces/Log levels: DEBUG 10, INFO 20, WARN 30, ERROR 40


@pytest.fixture(scope='module')
def cine():
    frames = count_slices(
        list(simulate_study('normal', snr=20, quick=True, num_phases=PHASES).frames)
    )
    return order_frames(frames, 'slice_major')


class Watcher(Node):
    """Publishes frames; collects tag points, /diagnostics and /rosout."""

    def __init__(self, context):
        super().__init__('calm_watcher', context=context)
        self.pub = self.create_publisher(TaggedFrame, qos.FRAMES, qos.topic_qos(qos.FRAMES))
        self.points, self.diag, self.logs = [], [], []
        self.create_subscription(TagPoints, qos.TAG_POINTS, self.points.append, qos.stream_qos())
        self.create_subscription(
            DiagnosticArray, qos.DIAGNOSTICS, self.diag.append, qos.stream_qos()
        )
        # /rosout keeps its history (TRANSIENT_LOCAL): lines logged before discovery arrive too.
        self.create_subscription(
            Log,
            '/rosout',
            self.logs.append,
            QoSProfile(
                depth=1000,
                reliability=ReliabilityPolicy.RELIABLE,
                durability=DurabilityPolicy.TRANSIENT_LOCAL,
            ),
        )

    def statuses(self, node='tag_detector'):
        return [s for d in self.diag for s in d.status if status_node(s) == node]

    def lines(self, min_level=0, node='tag_detector'):
        return [f'{m.level} {m.msg}' for m in self.logs if m.name == node and m.level >= min_level]


def run_detector(ros_context, executor, msgs):
    det = TagDetector(context=ros_context)
    w = Watcher(ros_context)
    for n in (det, w):
        executor.add_node(n)
    assert spin_until(executor, lambda: w.pub.get_subscription_count() >= 1 and w.lines(), 20)
    for m in msgs:
        w.pub.publish(m)

    def heartbeat_after_all():
        return any(
            s.message.startswith(('tracking', 'no tag points'))
            and {kv.key: kv.value for kv in s.values}.get('frames') == str(len(msgs))
            for s in w.statuses()
        )

    assert spin_until(
        executor, lambda: len(w.points) == len(msgs) and heartbeat_after_all(), 60
    ), f'{len(w.points)}/{len(msgs)} tag sets'
    return det, w


def last_heartbeat(w):
    s = w.statuses()[-1]
    return s, {kv.key: kv.value for kv in s.values}


def test_fading_tags_are_counted_not_warned(cine, ros_context, executor):
    msgs = [conversions.frame_to_msg(f, stamp=1.0 + i) for i, f in enumerate(cine)]
    det, w = run_detector(ros_context, executor, msgs)
    # The tags did fade: later phases report fewer points than their slice had at ED.
    ed = {(p.view, p.slice_index): len(p.track_id) for p in w.points if p.phase_index == 0}
    faded = [
        p for p in w.points if p.phase_index > 0 and len(p.track_id) < ed[(p.view, p.slice_index)]
    ]
    assert len(faded) >= len(ed), 'the cine has too little fading to test anything'
    # ... and nobody is told to worry about it: no WARN line, no WARN/ERROR status.
    assert w.lines(), 'no log line of the detector reached /rosout'
    assert not w.lines(WARN_LOG), w.lines(WARN_LOG)
    assert not [s.message for s in w.statuses() if s.level != DiagnosticStatus.OK]
    # The heartbeat carries the counts instead.
    status, values = last_heartbeat(w)
    assert status.level == DiagnosticStatus.OK and status.message.startswith('tracking')
    assert int(values['frames_with_ended_tracks']) + int(
        values.get('frames_without_points', 0)
    ) >= len(faded)
    assert int(values['tracks_alive']) < int(values['tracks_at_ed'])
    assert values['slices'] == str(len(ed))


def test_a_slice_without_tags_is_said_once(cine, ros_context, executor):
    # One SA slice whose ED image holds nothing: its grid cannot be read, so its whole cine gives
    # no tag points. That the user must know, once; its other phases add nothing to say.
    broken = (0, 2)
    msgs = []
    for i, f in enumerate(cine):
        m = conversions.frame_to_msg(f, stamp=1.0 + i)
        if (f.view, f.slice_index, f.phase_index) == (*broken, 0):
            m = conversions.frame_to_msg(
                dataclasses.replace(f, image=np.full_like(f.image, 700)), stamp=1.0 + i
            )
        msgs.append(m)
    det, w = run_detector(ros_context, executor, msgs)
    warned = w.lines(WARN_LOG)
    assert len(warned) == 1, warned
    assert (
        'slice=2' in warned[0]
        and 'image is constant' in warned[0]
        and 'no tag points' in warned[0]
    )
    # The heartbeat keeps saying it at WARN, by name, with the routine counts beside it.
    status, values = last_heartbeat(w)
    assert status.level == DiagnosticStatus.WARN and 'SA 2' in status.message, status.message
    assert values['frames_in_slices_without_tags'] == str(PHASES - 1)
    assert int(values['frames_with_ended_tracks']) > 0


def test_registration_says_what_it_lacks_once(cine, ros_context, executor):
    # SA slices only, each ED frame sent twice (as a restarted source would): the copies are not
    # news; the missing long-axis views are, in the one `registered` status.
    from rclpy.parameter import Parameter

    ed = count_slices([f for f in cine if f.view == 0 and f.phase_index == 0])
    reg = Registration(
        context=ros_context, parameter_overrides=[Parameter('num_particles', value=500)]
    )
    w = Watcher(ros_context)
    for n in (reg, w):
        executor.add_node(n)
    assert spin_until(
        executor, lambda: w.pub.get_subscription_count() >= 1 and w.lines(node='registration'), 20
    )
    for i, f in enumerate(ed + ed):
        w.pub.publish(conversions.frame_to_msg(f, stamp=1.0 + i))
    assert spin_until(
        executor,
        lambda: (
            any(s.message == 'registered' for s in w.statuses('registration'))
            and any('registered' in ln for ln in w.lines(node='registration'))
        ),
        30,
    )
    warned = w.lines(WARN_LOG, node='registration')
    assert len(warned) == 1 and 'registered' in warned[0] and 'no LA views' in warned[0], warned
    done = next(s for s in w.statuses('registration') if s.message == 'registered')
    assert done.level == DiagnosticStatus.WARN


# --------------------------------------------------------------------------- the CLI


@pytest.fixture(scope='module')
def files(tmp_path_factory):
    """Paths for the CLI mistakes: a recording of another type, a non-MCAP file, a run dir."""
    from mlv_ros import bagio
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String

    d = tmp_path_factory.mktemp('cli')
    foreign = bagio.BagWriter(d / 'foreign' / 'run.mcap')
    foreign.add_topic(qos.METRICS, 'std_msgs/msg/String')
    foreign.write(qos.METRICS, serialize_message(String(data='not metrics')), 1)
    foreign.close()
    (d / 'empty').mkdir()
    (d / 'notes.mcap').write_text('not a recording\n')
    (d / 'afile').write_text('x')
    (d / 'done').mkdir()
    (d / 'done' / 'run.mcap').write_bytes(b'')
    return d


def mlv(*args, cwd=None):
    return subprocess.run(
        [console_script('mlv-ros'), *map(str, args)],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=cwd or REPO,
    )


MISTAKES = {
    # name: (arguments, words the one line must hold)
    'no command': ((), ['required', '--help']),
    'unknown command': (('nope',), ['invalid choice']),
    'recover a directory without a recording': (
        ('recover', '{d}/empty', '{d}/x.mcap'),
        ['no .mcap', 'give'],
    ),
    'recover a missing file': (('recover', '{d}/missing.mcap', '{d}/x.mcap'), ['does not exist']),
    'recover onto a directory': (
        ('recover', '{d}/foreign/run.mcap', '{d}/empty'),
        ['exists', 'new file name'],
    ),
    'recover a non-MCAP file': (
        ('recover', '{d}/notes.mcap', '{d}/y.mcap'),
        ['no message', 'MCAP'],
    ),
    'report another type on /lv/metrics': (
        ('report', '{d}/foreign/run.mcap'),
        ['/lv/metrics', 'std_msgs/msg/String', 'run.mcap'],
    ),
    'report a missing file': (('report', '{d}/missing.mcap'), ['does not exist']),
    'report a non-MCAP file': (('report', '{d}/notes.mcap'), ['not an MCAP file']),
    'report a directory without a recording': (('report', '{d}/empty'), ['no .mcap']),
    'report --out under a file': (
        ('report', '{bag}', '--out', '{d}/afile/report'),
        ['choose another --out'],
    ),
    'simulate --snr nan': (('simulate', '--snr', 'nan', '--out', '{d}/s'), ['--snr', 'finite']),
    'simulate --snr negative': (('simulate', '--snr', '-3', '--out', '{d}/s'), ['--snr', '>= 0']),
    'simulate --size 0': (('simulate', '--size', '0', '--out', '{d}/s'), ['--size', '>= 16']),
    'simulate --phases 1': (('simulate', '--phases', '1', '--out', '{d}/s'), ['--phases', '>= 2']),
    'simulate --points -5': (('simulate', '--points', '-5', '--out', '{d}/s'), ['--points']),
    'simulate --seed abc': (
        ('simulate', '--seed', 'abc', '--out', '{d}/s'),
        ['--seed', 'not an integer'],
    ),
    'simulate --out under a file': (
        ('simulate', '--out', '{d}/afile/s'),
        ['--out', 'not a directory'],
    ),
    'demo unknown preset': (
        ('demo', '--preset', 'nope', '--out', '{d}/demo'),
        ['unknown phantom preset'],
    ),
    'demo into a finished run': (('demo', '--out', '{d}/done'), ['new --out']),
    'bench a path': (('bench', '../setup'), ['no benchmark', 'choose one of']),
}


@pytest.mark.parametrize('name', list(MISTAKES))
def test_cli_mistake_is_one_line_with_the_fix(name, files):
    args, words = MISTAKES[name]
    bag = REPO / 'bags' / 'normal_sample.mcap'
    res = mlv(*(a.format(d=files, bag=bag) for a in args))
    lines = [ln for ln in res.stderr.split('\n') if ln.strip()]
    assert res.returncode != 0, (res.returncode, res.stderr)
    assert 'Traceback' not in res.stderr and len(lines) == 1, res.stderr
    assert all(w.lower() in lines[0].lower() for w in words), lines[0]
    assert lines[0].startswith('mlv-ros'), lines[0]


def test_cli_mistakes_leave_nothing_behind(files):
    # Refused before any work: no study directory, no empty recovered file.
    assert not (files / 's').exists() and not (files / 'demo').exists()
    assert not (files / 'y.mcap').exists()


def test_recover_takes_a_run_directory(files, tmp_path):
    res = mlv('recover', files / 'foreign', tmp_path / 'fixed.mcap')
    assert res.returncode == 0 and not res.stderr.strip(), res.stderr
    assert (tmp_path / 'fixed.mcap').stat().st_size > 0
