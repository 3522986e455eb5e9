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
Input silence counted only while a node is spun (nodes.common.Silence).

Input silence is counted only while a node is spun (nodes.common.Silence): a stalled executor
(a publisher blocked on a slow RELIABLE reader, a long callback, a loaded machine) is not a
stream that stopped. Before, a run on a 2-core machine at load 8 registered with 7 of 12 ED
slices when the executor resumed and the registration's timer ran before the frames waiting in
its queue, and delivered 14 wrong phases with verdict ok.
"""

from __future__ import annotations

import time

from conftest import spin_until
from graphkit import Probe
from mlv_ros import conversions, qos
from mlv_ros.core.sim import simulate_study
from mlv_ros.nodes.common import Silence
from mlv_ros.nodes.frame_source import count_slices
from mlv_ros.nodes.registration import Registration
import pytest
from rclpy.parameter import Parameter


def test_silence_counts_ticks_and_a_stall_as_two_periods_at_most():
    s = Silence(0.25)
    assert s.tick(100.0) == 0.0  # the first tick only starts the clock
    for k in range(1, 5):
        s.tick(100.0 + 0.25 * k)
    assert s.seconds == pytest.approx(1.0)
    assert s.tick(130.0) == pytest.approx(1.5)  # 29 s without a tick: the node was not spun
    s.heard()
    assert s.seconds == 0.0 and s.tick(130.25) == pytest.approx(0.25)
    assert s.tick(130.0) == pytest.approx(0.25)  # a clock that goes back adds nothing


@pytest.fixture(scope='module')
def ed_frames():
    frames = count_slices(list(simulate_study('normal', snr=20, quick=True, num_phases=2).frames))
    return [f for f in frames if f.phase_index == 0]


def test_a_stalled_executor_does_not_register_without_the_waiting_ed_frame(
    ed_frames, ros_context, executor
):
    reg = Registration(
        context=ros_context,
        parameter_overrides=[
            Parameter('num_particles', value=400),
            Parameter('ed_timeout_s', value=1.0),
        ],
    )
    probe = Probe(ros_context)
    for node in (reg, probe):
        executor.add_node(node)
    assert spin_until(executor, lambda: probe.pubs[qos.FRAMES].get_subscription_count() >= 1, 20)
    *first, last = ed_frames
    for i, f in enumerate(first):
        probe.publish(qos.FRAMES, conversions.frame_to_msg(f, stamp=1.0 + i))
    assert spin_until(executor, lambda: len(reg.ed_frames) == len(first), 20), len(reg.ed_frames)
    probe.publish(qos.FRAMES, conversions.frame_to_msg(last, stamp=100.0))
    time.sleep(3.0)  # the executor stalls (not spun) three ED timeouts long, the last frame queued
    assert spin_until(executor, lambda: reg.registered, 60)
    assert len(reg.ed_frames) == len(ed_frames) == reg.expected
    assert reg.result is not None and len(reg.result.slice_reports) == len(ed_frames)
