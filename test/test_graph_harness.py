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
The harness itself: real nodes over real Fast DDS, in one process and across processes.

The harness itself: real nodes over real Fast DDS, in one process and across processes
started from our console scripts.
"""

import os
import subprocess
import sys

from conftest import console_script, spin_until
from diagnostic_msgs.msg import DiagnosticArray
from mlv_msgs.msg import TaggedFrame
from mlv_ros import conversions, qos
from mlv_ros.core.sim.pattern import pattern_frames
from mlv_ros.nodes.common import status_node
from mlv_ros.nodes.frame_source import FrameSource
import numpy as np
import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter

ALL_NODES = [
    'frame_source',
    'tag_detector',
    'registration',
    'meshless_solver',
    'motion_analyzer',
    'recorder',
    'replay',
]


class Collector(Node):
    def __init__(self, context, topic=qos.FRAMES, msg_type=TaggedFrame, qos_profile=None):
        super().__init__('collector', context=context)
        self.msgs = []
        self.create_subscription(
            msg_type, topic, self.msgs.append, qos_profile or qos.stream_qos()
        )


def test_domain_isolation_is_set():
    assert 1 <= int(os.environ['ROS_DOMAIN_ID']) <= 232
    assert os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'


def test_mlv_msgs_importable_from_venv_python():
    out = subprocess.run(
        [sys.executable, '-c', 'import mlv_msgs.msg as m; print(m.TaggedFrame.__name__)'],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == 'TaggedFrame'


def test_frames_between_nodes_in_one_process(ros_context, executor):
    collector = Collector(ros_context)
    source = FrameSource(
        context=ros_context,
        parameter_overrides=[
            Parameter('source', value='pattern'),
            Parameter('num_phases', value=4),
        ],
    )
    executor.add_node(collector)
    executor.add_node(source)
    expected = pattern_frames(num_phases=4)
    assert spin_until(executor, lambda: source.done, timeout=30), 'frame_source never finished'
    assert spin_until(executor, lambda: len(collector.msgs) == len(expected) == 8, timeout=10)
    got = sorted(
        (conversions.msg_to_frame(m) for m in collector.msgs),
        key=lambda f: (f.slice_index, f.phase_index),
    )
    for f, g in zip(expected, got):
        assert (f.slice_index, f.phase_index) == (g.slice_index, g.phase_index)
        np.testing.assert_array_equal(f.image, g.image)
        np.testing.assert_array_equal(f.geometry.image_position, g.geometry.image_position)
    # phase-major order (the default): every slice's phase p before any slice's phase p + 1
    assert [m.slice_index for m in collector.msgs] == [0, 1] * 4
    assert [m.phase_index for m in collector.msgs] == [0, 0, 1, 1, 2, 2, 3, 3]


def test_frames_across_processes_from_console_script(ros_context, executor):
    collector = Collector(ros_context)
    diags = Collector(ros_context, qos.DIAGNOSTICS, DiagnosticArray, qos.diagnostics_qos())
    executor.add_node(collector)
    executor.add_node(diags)
    proc = subprocess.Popen(
        [
            console_script('frame_source'),
            '--ros-args',
            '-p',
            'source:=pattern',
            '-p',
            'num_phases:=5',
            '-p',
            'order:=phase_major',
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        assert spin_until(executor, lambda: len(collector.msgs) == 10, timeout=60), (
            f'received {len(collector.msgs)} of 10 frames'
        )
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        log = proc.stdout.read()
    assert [m.phase_index for m in collector.msgs] == [p for p in range(5) for _ in range(2)], log
    assert spin_until(
        executor,
        lambda: any('all frames published' in s.message for d in diags.msgs for s in d.status),
    )


@pytest.fixture(scope='module')
def recording(tmp_path_factory):
    """Return a small MCAP of pattern frames written with BagWriter (no nodes involved)."""
    from mlv_ros import bagio
    from rclpy.serialization import serialize_message

    path = tmp_path_factory.mktemp('bag') / 'pattern.mcap'
    writer = bagio.BagWriter(path)
    writer.add_topic(qos.FRAMES, qos.TOPIC_TYPES[qos.FRAMES], [qos.qos_dict(qos.stream_qos())])
    for i, f in enumerate(pattern_frames()):
        writer.write(qos.FRAMES, serialize_message(conversions.frame_to_msg(f)), 1_000_000_000 + i)
    writer.close()
    return path


@pytest.mark.parametrize('name', ALL_NODES)
def test_every_node_console_script_starts_and_stops_on_sigint(
    name, ros_context, executor, tmp_path, recording
):
    diags = Collector(ros_context, qos.DIAGNOSTICS, DiagnosticArray, qos.diagnostics_qos())
    executor.add_node(diags)
    extra = {
        'frame_source': ['-p', 'source:=pattern', '-p', 'wait_for_subscribers:=5'],
        'recorder': ['-p', f'output:={tmp_path / "run.mcap"}'],
        'replay': ['-p', f'path:={recording}', '-p', 'wait_for_subscribers:=5'],
    }.get(name)
    args = [console_script(name)] + (['--ros-args', *extra] if extra else [])
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert spin_until(
            executor,
            lambda: any(status_node(s) == name for d in diags.msgs for s in d.status),
            timeout=60,
        ), f'{name} never reported on /diagnostics'
        proc.send_signal(2)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()


def test_bad_parameter_is_a_clear_error():
    out = subprocess.run(
        [console_script('frame_source'), '--ros-args', '-p', 'order:=sideways'],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2
    assert "order='sideways' must be one of" in out.stderr
    out = subprocess.run(
        [console_script('frame_source'), '--ros-args', '-p', 'snr:=-3.0'],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 2
    assert 'snr' in out.stderr
