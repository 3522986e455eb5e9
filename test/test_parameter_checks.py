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
Parameters refused by the node's parameter check with the core's reason, and by their old names.

Parameters a descriptor's range cannot refuse are refused by the node's parameter check with
the core's reason: at start-up (the node does not start) and when set at run time. The solver's
grouped parameters (``twist.knots``) refuse a value given under their former flat names, and
``config/graph.yaml`` and the README name every parameter the table declares. MotionTracker,
called as a library, refuses what the node refuses, by the same table.
"""

import inspect
from pathlib import Path

from mlv_ros.core.tracking import MotionTracker, twist_knots_error
from mlv_ros.nodes.meshless_solver import MeshlessSolver
from mlv_ros.resources import config_file
from mlv_ros.settings import check_keywords, REGISTRATION, Setting, SOLVER_MODEL, SOLVER_STREAM
import pytest
from rclpy.exceptions import InvalidParameterValueException
from rclpy.parameter import Parameter


@pytest.mark.parametrize('knots', [0, 2, 11, 100])
def test_twist_knots_the_model_takes_are_accepted(knots, ros_context):
    assert twist_knots_error(knots) is None
    node = MeshlessSolver(
        context=ros_context, parameter_overrides=[Parameter('twist.knots', value=knots)]
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
        InvalidParameterValueException, match='twist.knots=1: .*one knot is no function of height'
    ):
        MeshlessSolver(
            context=ros_context, parameter_overrides=[Parameter('twist.knots', value=1)]
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


@pytest.mark.parametrize('old', [s for s in SOLVER_MODEL if s.keyword], ids=lambda s: s.keyword)
def test_a_former_flat_name_is_refused_naming_the_grouped_one(old: Setting, ros_context):
    # Left unchecked, rclpy would ignore an undeclared name and run with the default.
    with pytest.raises(ValueError) as refused:
        MeshlessSolver(
            context=ros_context, parameter_overrides=[Parameter(old.keyword, value=old.default)]
        )
    said = str(refused.value)
    assert '\n' not in said
    assert f"'{old.keyword}' is now '{old.name}'" in said


def test_the_grouped_names_set_the_model():
    keywords = inspect.signature(MotionTracker).parameters
    assert [s.attribute for s in SOLVER_MODEL if s.attribute not in keywords] == []
    assert all('.' in s.name for s in SOLVER_MODEL)
    # The node's defaults are the core's: a graph run solves as the tracker does by default.
    differ = [s.name for s in SOLVER_MODEL if s.default != keywords[s.attribute].default]
    assert differ == []
    assert all(type(s.default) is type(keywords[s.attribute].default) for s in SOLVER_MODEL)
    assert all(s.min_value <= s.default <= s.max_value for s in SOLVER_MODEL)


def bad_values(s: Setting) -> list:
    """Return values the setting ``s`` must refuse: beyond each end, NaN, a wrong type."""
    step = 1 if isinstance(s.default, int) else max(abs(s.min_value), abs(s.max_value)) * 1e-3
    bad = [s.min_value - step, s.max_value + step, 'fast', True]
    return bad + ([s.default + 0.5] if isinstance(s.default, int) else [float('nan')])


@pytest.mark.parametrize('s', SOLVER_MODEL, ids=lambda s: s.name)
def test_the_tracker_refuses_what_the_node_refuses_by_the_same_table(s: Setting):
    assert s.error(s.min_value) is None or s.check  # a check may refuse an end (twist.knots 1)
    assert s.error(s.max_value) is None and s.error(s.default) is None
    for value in bad_values(s):
        assert s.error(value), value
        with pytest.raises(ValueError) as refused:
            MotionTracker(
                [[0.0, 0.0, 0.0]] * 4,
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0, 0.0],
                10.0,
                **{s.attribute: value},
            )
        said = str(refused.value)
        assert said.startswith(f'{s.attribute}=') and s.name in said and '\n' not in said, said


def test_keywords_a_table_does_not_name_are_left_to_their_owner():
    check_keywords(SOLVER_MODEL, {'coarse_aggregates': -1, 'cg_rtol': 2e-3})  # not its to check
    with pytest.raises(ValueError, match=r'^cg_rtol=0: must be from 1e-12 to 0.5 \(node '):
        check_keywords(SOLVER_MODEL, {'cg_rtol': 0})


def flat(params: dict, prefix: str = '') -> set:
    """Return the parameter names of a ``ros__parameters`` map, nested maps joined with dots."""
    return {
        name
        for key, value in params.items()
        for name in (
            flat(value, f'{prefix}{key}.') if isinstance(value, dict) else {f'{prefix}{key}'}
        )
    }


@pytest.mark.parametrize(
    'node, table',
    [('meshless_solver', SOLVER_MODEL + SOLVER_STREAM), ('registration', REGISTRATION)],
)
def test_graph_yaml_and_the_readme_name_every_setting(node, table):
    import yaml

    params = yaml.safe_load(config_file('graph.yaml').read_text())[f'/**/{node}']
    assert flat(params['ros__parameters']) == {s.name for s in table}
    readme = (Path(__file__).resolve().parents[1] / 'README.md').read_text()
    start = readme.index(f'- `{node}`')
    entry = readme[start:].split('\n- `')[0]
    assert [s.name for s in table if f'`{s.name}`' not in entry] == []


def test_tracking_register_reaches_every_slice_tracker(ros_context):
    # The same tagged slice through a tag detector with and without registration: the parameter
    # is what each slice's tracker runs with, and it changes where the tracks end up.
    from mlv_ros import conversions
    from mlv_ros.core.sim.tag_scene import TagScene
    from mlv_ros.core.types import Frame, SliceGeometry
    from mlv_ros.nodes.tag_detector import TagDetector
    import numpy as np

    geom = SliceGeometry(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 1.3, 1.3, 6.0)
    scene = TagScene(shape=(128, 128), ring=(19.8, 31.5), noise_sigma=0.02)
    positions = {}
    for value in (True, False):
        node = TagDetector(
            context=ros_context, parameter_overrides=[Parameter('tracking.register', value=value)]
        )
        try:
            for p in range(4):
                image = scene.render(p / 10, seed=p).astype(np.float32)
                frame = Frame(image, geom, 0, 2, p, 10, trigger_time=0.1 * p)
                node._on_frame(conversions.frame_to_msg(frame, stamp=0.1 * p))
            tracker = node.trackers[(0, 2)]
            assert tracker.register is value and tracker.alive.size >= 4
            positions[value] = tracker._pos[~tracker._dead].copy()
        finally:
            node.destroy_node()
    assert positions[True].shape != positions[False].shape or not np.allclose(
        positions[True], positions[False]
    )
