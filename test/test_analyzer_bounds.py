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
The analyzer's bounded memory: unpaired model states or clouds dropped beyond ``max_unpaired``.

The analyzer's memory is bounded: model states (or clouds) whose pair never comes are dropped
oldest first beyond ``max_unpaired``, each with a /diagnostics entry naming it.
"""

from conftest import spin_until
from graphkit import Probe
from mlv_ros import conversions, qos
from mlv_ros.core.types import ModelState
from mlv_ros.nodes.motion_analyzer import MotionAnalyzer
from rclpy.parameter import Parameter


def test_unpaired_states_are_bounded_and_reported(ros_context, executor):
    analyzer = MotionAnalyzer(
        context=ros_context, parameter_overrides=[Parameter('max_unpaired', value=3)]
    )
    probe = Probe(ros_context)
    for n in (analyzer, probe):
        executor.add_node(n)
    assert spin_until(
        executor, lambda: probe.pubs[qos.MODEL_STATE].get_subscription_count() >= 1, 20
    )
    state = ModelState(phase_index=1, num_phases=10, a0=30.0)
    stamps = []
    for i in range(5):  # no motion cloud ever comes for these
        msg = conversions.model_state_to_msg(state, stamp=10.0 + i)
        stamps.append(conversions.stamp_text(msg.header.stamp))
        probe.publish(qos.MODEL_STATE, msg)
    assert spin_until(executor, lambda: analyzer.messages_handled == 5, 10)

    def dropped():
        return [
            v['stamp']
            for node, _l, m, v in probe.statuses()
            if node == 'motion_analyzer' and m == 'unpaired model state dropped'
        ]

    assert spin_until(executor, lambda: len(dropped()) == 2, 10), probe.statuses()
    assert dropped() == stamps[:2]  # oldest first
    assert len(analyzer.states) == 3
