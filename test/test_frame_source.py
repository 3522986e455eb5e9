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
with its pixels.
"""

from conftest import spin_until
from mlv_msgs.msg import TaggedFrame
from mlv_ros import conversions, qos
from mlv_ros.core.sim.pattern import pattern_frames
from mlv_ros.nodes import frame_source
from mlv_ros.nodes.frame_source import FrameSource, order_frames
import numpy as np
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
