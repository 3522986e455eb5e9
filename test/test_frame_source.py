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
The frame source publishes every due frame in bursts of at most BURST_FRAMES, none lost.

A pattern study of several bursts (the bound made small, so the study is) goes out over an
executor it shares with its subscriber: each tick publishes exactly the bound (not one frame, not
all), the last the rest, and the subscriber receives every frame once, in publication order,
with its pixels. A phantom's frames, simulated as they are published (in a render process, in the
node, or in the node after the render process failed), are the whole simulated study's, bit for
bit.
"""

import shutil
import sys
import time

from conftest import spin_until
from diagnostic_msgs.msg import DiagnosticArray
from mlv_msgs.msg import TaggedFrame
from mlv_ros import conversions, qos, render_process
from mlv_ros.core.sim.pattern import pattern_frames
from mlv_ros.nodes import frame_source
from mlv_ros.nodes.frame_source import FrameSource, order_frames
import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter


def test_frames_go_out_in_bounded_bursts_and_all_arrive(ros_context, executor, monkeypatch):
    num_phases, burst = 7, 4  # 2 slices: 14 frames, bursts of 4, 4, 4, 2
    monkeypatch.setattr(frame_source, 'BURST_FRAMES', burst)
    received = []
    sink = rclpy.create_node('frame_sink', context=ros_context)
    sink.create_subscription(
        TaggedFrame, qos.FRAMES, received.append, qos.subscription_qos(qos.FRAMES)
    )
    src = FrameSource(
        context=ros_context,
        parameter_overrides=[
            Parameter('source', value='pattern'),
            Parameter('order', value='slice_major'),
            Parameter('num_phases', value=num_phases),
            Parameter('wait_for_subscribers', value=1),
        ],
    )
    expected = order_frames(pattern_frames(num_phases=num_phases), 'slice_major')
    assert len(expected) == len(src.frames) == 14
    executor.add_node(sink)
    executor.add_node(src)
    counts = []

    def published_all():
        counts.append(src.published)
        return src.done

    assert spin_until(executor, published_all, timeout=30, step=0.01)
    # One tick publishes what is due up to the bound, so the count only ever takes these values.
    assert sorted(set(counts)) == [0, 4, 8, 12, 14]
    assert spin_until(executor, lambda: len(received) == len(expected), timeout=10)
    got = [conversions.msg_to_frame(m) for m in received]
    assert [(f.slice_index, f.phase_index) for f in got] == [
        (f.slice_index, f.phase_index) for f in expected
    ]
    for f, e in zip(got, expected):
        np.testing.assert_array_equal(f.image, e.image)


@pytest.mark.parametrize('layout', ['render_process', 'one_process', 'render_process_fails'])
def test_phantom_frames_rendered_on_demand_equal_the_simulated_study(
    ros_context, executor, monkeypatch, layout
):
    from mlv_ros.core.sim import load_preset, simulate_study

    monkeypatch.setenv('MLV_ROS_ONE_PROCESS', '1' if layout == 'one_process' else '0')
    # 4 frames of 40² float32, of 33: the bound is met
    monkeypatch.setattr(render_process, 'RENDER_AHEAD_BYTES', 4 * 4 * 40 * 40)
    if layout == 'render_process_fails':
        monkeypatch.setattr(sys, 'executable', shutil.which('false'))  # exits 1 at once

    received, diags = [], []
    sink = rclpy.create_node('frame_sink', context=ros_context)
    sink.create_subscription(
        TaggedFrame, qos.FRAMES, received.append, qos.subscription_qos(qos.FRAMES)
    )
    sink.create_subscription(
        DiagnosticArray, qos.DIAGNOSTICS, diags.append, qos.diagnostics_qos()
    )
    src = FrameSource(
        context=ros_context,
        parameter_overrides=[
            Parameter('source', value='phantom'),
            Parameter('size', value=40),
            Parameter('num_phases', value=3),
            Parameter('seed', value=3),
        ],
    )
    # Nothing is simulated before the node is asked for frames: only the plan.
    assert len(src.frames) == 33 and all(f.image is None for f in src.frames)
    assert (src._render_process is None) == (layout == 'one_process')
    ahead = []  # frames handed over and not yet published, as each is handed over
    proc = src._render_process
    if proc is not None:
        hand_over = proc._on_frame
        proc._on_frame = lambda i, img: (ahead.append(i + 1 - src.published), hand_over(i, img))
        # Nothing is published before the executor spins: the child renders up to the bound.
        deadline = time.monotonic() + 30.0
        while proc.received < 4 and proc.failure is None and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.5)  # unbounded, all 33 would be handed over meanwhile
    executor.add_node(sink)
    executor.add_node(src)
    assert spin_until(executor, lambda: src.done and len(received) == 33, timeout=60, step=0.01)
    study = simulate_study(load_preset('normal'), snr=20.0, size=40, num_phases=3, seed=3)
    expected = order_frames(study.frames, 'phase_major')
    got = [conversions.msg_to_frame(m) for m in received]
    assert [(f.view, f.slice_index, f.phase_index) for f in got] == [
        (f.view, f.slice_index, f.phase_index) for f in expected
    ]
    for f, e in zip(got, expected):
        np.testing.assert_array_equal(f.image, e.image)
    # The render process waits while RENDER_AHEAD_BYTES of frames are handed over, not published.
    assert max(ahead, default=0) <= 4, ahead
    assert (len(ahead) > 20) == (layout == 'render_process'), ahead
    # Published pixels are not kept by the node (the writer's history holds them).
    assert all(f.image is None for f in src.frames)
    # A failed render process is said on /diagnostics (the node's status: diagnostic_updater
    # repeats it once a period), and the frames are simulated here instead.
    fallback = [
        st for d in diags for st in d.status if 'simulated in this process' in st.message
    ]
    assert bool(fallback) == (layout == 'render_process_fails')
    src.destroy_node()
