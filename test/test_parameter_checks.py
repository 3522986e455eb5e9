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
Parameters refused by the node's parameter check with the core's reason.

Parameters a descriptor's range cannot refuse are refused by the node's parameter check with
the core's reason: at start-up (the node does not start) and when set at run time.
"""

from mlv_ros.core.tracking import MotionTracker, twist_knots_error
from mlv_ros.nodes.meshless_solver import MeshlessSolver
import pytest
from rclpy.exceptions import InvalidParameterValueException
from rclpy.parameter import Parameter


@pytest.mark.parametrize('knots', [0, 2, 11, 100])
def test_twist_knots_the_model_takes_are_accepted(knots, ros_context):
    assert twist_knots_error(knots) is None
    node = MeshlessSolver(
        context=ros_context, parameter_overrides=[Parameter('twist_knots', value=knots)]
    )
    try:
        assert node.twist_knots == knots
    finally:
        node.destroy_node()


def test_one_twist_knot_is_refused_at_start_with_the_cores_reason(ros_context):
    why = twist_knots_error(1)
    assert why and 'one knot' in why
    with pytest.raises(
        ValueError, match='one knot is no function of height'
    ):  # the core says the same
        MotionTracker(
            [[0.0, 0.0, 0.0]] * 4, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], 10.0, twist_knots=1
        )
    with pytest.raises(
        InvalidParameterValueException, match='twist_knots=1: .*one knot is no function of height'
    ):
        MeshlessSolver(
            context=ros_context, parameter_overrides=[Parameter('twist_knots', value=1)]
        )


def test_parameter_check_also_answers_a_run_time_set(ros_context):
    """
    Declare a parameter writable with a check that refuses values with a reason.

    A parameter declared writable with a check: a refused value is answered unsuccessful with
    the reason and the old value stays.
    """
    from mlv_ros.nodes.common import GraphNode

    node = GraphNode('checked', context=ros_context)
    try:
        value = node.param(
            'knots',
            11,
            'test',
            min_value=0,
            max_value=100,
            read_only=False,
            check=twist_knots_error,
        )
        assert value == 11
        result = node.set_parameters([Parameter('knots', value=1)])[0]
        assert not result.successful and 'one knot' in result.reason
        assert node.get_parameter('knots').value == 11
        assert node.set_parameters([Parameter('knots', value=4)])[0].successful
    finally:
        node.destroy_node()
