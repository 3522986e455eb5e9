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
The recorder's MCAP read by an independent reader (rosbags), nothing lost on SIGINT/SIGTERM.

The recorder writes MCAP that an independent reader (rosbags) opens, with rosbag2's schema,
channel and metadata conventions, and loses nothing on SIGINT/SIGTERM.
"""

import signal
import subprocess
import time

from conftest import console_script, spin_until
from mlv_ros import bagio, qos
from mlv_ros.core.sim.pattern import pattern_frames
from mlv_ros.nodes.frame_source import FrameSource
from mlv_ros.nodes.recorder import Recorder
import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_typestore, Stores
import yaml


def pattern_source(ros_context, num_phases, *extra):
    """
    Build a pattern frame source publishing slice-major, the order the assertions read back.

    Parameters
    ----------
    ros_context : rclpy.context.Context
        The test's ROS context.
    num_phases : int
        Phases per slice.
    *extra : rclpy.parameter.Parameter
        Further parameter overrides.

    Returns
    -------
    FrameSource
        The node, not yet added to an executor.

    """
    return FrameSource(
        context=ros_context,
        parameter_overrides=[
            Parameter('source', value='pattern'),
            Parameter('order', value='slice_major'),
            Parameter('num_phases', value=num_phases),
            *extra,
        ],
    )


def read_with_rosbags(path):
    """(topic, msgtype, deserialised message) for every message, by rosbags alone."""
    out = []
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        for conn, _t, raw in reader.messages():
            out.append((conn.topic, conn.msgtype, reader.deserialize(raw, conn.msgtype)))
    return out


def test_recorder_in_process_and_rosbags_reads_it(ros_context, executor, tmp_path):
    out = tmp_path / 'run' / 'run.mcap'
    rec = Recorder(context=ros_context, parameter_overrides=[Parameter('output', value=str(out))])
    src = pattern_source(ros_context, 3, Parameter('wait_for_subscribers', value=1))
    executor.add_node(rec)
    executor.add_node(src)
    assert spin_until(executor, lambda: src.done, timeout=30)
    assert spin_until(executor, lambda: rec.writer.topics[qos.FRAMES].count >= 6, timeout=10)
    rec.finish()

    expected = pattern_frames(num_phases=3)
    topics = bagio.bag_topics(out)
    assert topics[qos.FRAMES]['count'] == len(expected) == 6
    assert topics[qos.FRAMES]['type'] == 'mlv_msgs/msg/TaggedFrame'
    assert topics[qos.FRAMES]['type_hash'].startswith('RIHS01_')
    assert yaml.safe_load(topics[qos.FRAMES]['qos'])[0]['reliability'] == 'reliable'

    # The directory is a rosbag2 bag as well (metadata.yaml), and rosbags reads the file alone.
    meta = yaml.safe_load((out.parent / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information'
    ]
    assert meta['storage_identifier'] == 'mcap' and meta['relative_file_paths'] == ['run.mcap']
    frames = [m for t, _, m in read_with_rosbags(out) if t == qos.FRAMES]
    assert len(frames) == 6
    for f, m in zip(expected, frames):
        assert (m.slice_index, m.phase_index, m.image.encoding) == (
            f.slice_index,
            f.phase_index,
            'mono16',
        )
        img = np.frombuffer(m.image.data.tobytes(), np.uint16).reshape(
            m.image.height, m.image.width
        )
        np.testing.assert_array_equal(img, f.image)
        np.testing.assert_allclose(m.geometry.image_position, f.geometry.image_position)


def test_schema_text_follows_rosbag2(tmp_path):
    text = bagio.message_definition('sensor_msgs/msg/PointCloud2')
    sections = text.split('\n' + '=' * 80 + '\n')
    assert [s.splitlines()[0] for s in sections[1:]] == [
        'MSG: std_msgs/Header',
        'MSG: builtin_interfaces/Time',
        'MSG: sensor_msgs/PointField',
    ]
    with pytest.raises(FileNotFoundError, match='no .msg for nosuch_msgs/msg/Thing'):
        bagio.message_definition('nosuch_msgs/msg/Thing')
    with pytest.raises(ValueError, match='not a message type'):
        bagio.message_definition('Thing')


def test_writer_refuses_to_overwrite_and_unknown_topics(tmp_path):
    path = tmp_path / 'a.mcap'
    w = bagio.BagWriter(path)
    with pytest.raises(ValueError, match='was not added'):
        w.write('/nope', b'', 0)
    w.close()
    with pytest.raises(FileExistsError, match='refusing to overwrite'):
        bagio.BagWriter(path)
    with pytest.raises(ValueError, match='cannot read'):
        list(bagio.read_bag(tmp_path / 'metadata.yaml'))


def recorder_process_and_source(ros_context, executor, out, num_phases, *extra):
    """
    Start the recorder's console script recording to ``out`` and a pattern frame source.

    The recorder's console script recording frames to ``out`` (a process of its own, as under
    ``ros2 launch``) and a pattern frame source in this process, on ``executor``, with the
    parameter overrides ``extra``.
    """
    rec = subprocess.Popen(
        [
            console_script('recorder'),
            '--ros-args',
            '-p',
            f'output:={out}',
            '-p',
            f"topics:=['{qos.FRAMES}']",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    src = pattern_source(ros_context, num_phases, *extra)
    executor.add_node(src)
    return rec, src


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_recorder_process_keeps_every_message_on_signal(sig, ros_context, executor, tmp_path):
    out = tmp_path / 'run.mcap'
    rec, src = recorder_process_and_source(ros_context, executor, out, num_phases=20)
    try:
        assert spin_until(executor, lambda: src.done, timeout=60), 'recorder never subscribed'
        executor.remove_node(src)
        src.destroy_node()  # the graph is gone (the recorder would wait for it: see the next test)
        rec.send_signal(sig)  # every frame was acknowledged by the recorder before this
        assert rec.wait(timeout=30) == 0
    finally:
        if rec.poll() is None:
            rec.kill()
    log = rec.stdout.read()
    assert bagio.bag_topics(out)[qos.FRAMES]['count'] == 40, log
    assert sum(1 for t, _, _ in read_with_rosbags(out) if t == qos.FRAMES) == 40


def record_pattern(ros_context, executor, path, num_phases=3):
    rec = Recorder(context=ros_context, parameter_overrides=[Parameter('output', value=str(path))])
    src = pattern_source(ros_context, num_phases)
    executor.add_node(rec)
    executor.add_node(src)
    assert spin_until(
        executor,
        lambda: src.done and rec.writer.topics[qos.FRAMES].count >= src.published,
        timeout=30,
    )
    rec.finish()
    for node in (rec, src):
        executor.remove_node(node)
        node.destroy_node()


def test_replay_republishes_recorded_bytes(ros_context, executor, tmp_path):
    from mlv_msgs.msg import TaggedFrame
    from mlv_ros.nodes.replay import Replay

    path = tmp_path / 'run.mcap'
    record_pattern(ros_context, executor, path)
    recorded = [m.data for m in bagio.read_bag(path, topics=[qos.FRAMES])]
    got = []
    sink = rclpy.create_node('sink', context=ros_context)
    sink.create_subscription(TaggedFrame, qos.FRAMES, got.append, qos.stream_qos(), raw=True)
    replay = Replay(
        context=ros_context,
        parameter_overrides=[
            Parameter('path', value=str(path)),
            Parameter('topics', value=[qos.FRAMES]),
        ],
    )
    executor.add_node(sink)
    executor.add_node(replay)
    assert spin_until(executor, lambda: replay.done, timeout=30)
    assert spin_until(executor, lambda: len(got) == len(recorded) == 6, timeout=10)
    assert got == recorded  # byte for byte, as recorded


def test_frame_source_plays_frames_from_a_bag(ros_context, executor, tmp_path):
    from mlv_ros.nodes.frame_source import read_bag_frames

    path = tmp_path / 'run.mcap'
    record_pattern(ros_context, executor, path, num_phases=2)
    frames = read_bag_frames(path)
    expected = pattern_frames(num_phases=2)
    assert len(frames) == len(expected)
    for f, g in zip(expected, frames):
        np.testing.assert_array_equal(f.image, g.image)
        assert (f.slice_index, f.phase_index) == (g.slice_index, g.phase_index)


def test_replay_without_path_is_a_clear_error():
    out = subprocess.run([console_script('replay')], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and 'parameter path is required' in out.stderr


def test_recorder_sigkill_leaves_completed_chunks_that_recover_rewrites(
    ros_context, executor, tmp_path
):
    out = tmp_path / 'run.mcap'
    rec = subprocess.Popen(
        [
            console_script('recorder'),
            '--ros-args',
            '-p',
            f'output:={out}',
            '-p',
            f"topics:=['{qos.FRAMES}']",
            '-p',
            'chunk_size_kib:=64',
            '-p',
            'flush_period_s:=0.1',
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    src = pattern_source(ros_context, 30)
    executor.add_node(src)
    try:
        assert spin_until(executor, lambda: src.done, timeout=60)
        size = lambda: out.stat().st_size if out.exists() else 0  # noqa: E731
        assert spin_until(
            executor, lambda: size() > 200_000, timeout=10
        )  # chunks reached the disk
        # Every frame is acknowledged, but a loaded machine may still be writing the recorder's
        # queue: kill once the file has stopped growing (all but the chunk being filled written).
        last = [size(), time.monotonic()]

        def settled():
            if size() != last[0]:
                last[:] = [size(), time.monotonic()]
            return time.monotonic() - last[1] > 1.0

        assert spin_until(executor, settled, timeout=20)
        rec.kill()  # SIGKILL: no summary, no footer
        rec.wait(timeout=10)
    finally:
        if rec.poll() is None:
            rec.kill()
    with pytest.raises(ValueError):
        bagio.bag_topics(out)  # the damaged file has no summary
    fixed = tmp_path / 'recovered.mcap'
    result = bagio.recover(out, fixed)
    n = result['topics'][qos.FRAMES]
    # each 64 KiB chunk holds ~7 frames of 8 KiB; all but the one being filled survive
    assert 60 - 10 <= n <= 60, result
    assert sum(1 for t, _, _ in read_with_rosbags(fixed) if t == qos.FRAMES) == n
    assert bagio.bag_topics(fixed)[qos.FRAMES]['count'] == n


def test_recorder_refuses_to_overwrite_with_a_clear_error(tmp_path):
    out = tmp_path / 'run.mcap'
    out.write_bytes(b'precious')
    res = subprocess.run(
        [console_script('recorder'), '--ros-args', '-p', f'output:={out}'],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2 and 'refusing to overwrite' in res.stderr
    assert out.read_bytes() == b'precious'


def test_recorder_process_signalled_mid_stream_keeps_what_the_graph_still_sends(
    ros_context, executor, tmp_path
):
    """
    Check that the recorder, on SIGINT while frames flow, keeps every frame and closes the file.

    As under ``ros2 launch``: the recorder (its console script, a process of its own) gets
    SIGINT while frames still flow. It records what its publishers still send until they leave,
    then closes the file with metadata.yaml: every published frame is in it, in order.
    """
    out = tmp_path / 'run.mcap'
    # A steady stream (the pattern's 40 ms phases × 0.1: a frame every 4 ms); as fast as possible
    # the source would send all 120 in one burst, before the signal.
    pace = Parameter('rate_factor', value=10.0)
    rec, src = recorder_process_and_source(ros_context, executor, out, 60, pace)
    try:
        assert spin_until(executor, lambda: src.published >= 20, timeout=60), (
            'recorder never subscribed'
        )
        rec.send_signal(signal.SIGINT)  # mid-stream: 100 of 120 frames still to come
        at_signal = src.published
        time.sleep(
            0.5
        )  # the recorder is in its shutdown now (it would have closed after 0.2 s quiet)
        assert spin_until(executor, lambda: src.done, timeout=60)
        executor.remove_node(src)
        src.destroy_node()  # the graph leaves: the recorder closes
        left_at = time.monotonic()
        assert rec.wait(timeout=30) == 0
        closed_after = time.monotonic() - left_at
    finally:
        if rec.poll() is None:
            rec.kill()
    log = rec.stdout.read()
    assert at_signal < 120 == src.published
    assert closed_after < 5, closed_after
    frames = [m for t, _, m in read_with_rosbags(out) if t == qos.FRAMES]
    assert [(m.slice_index, m.phase_index) for m in frames] == [
        (f.slice_index, f.phase_index) for f in pattern_frames(num_phases=60)
    ], log
    meta = yaml.safe_load((out.parent / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information'
    ]
    assert meta['message_count'] == 120
    assert 'recording closed' in log and 'lost=0' in log, log
