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
A node holding a registered model it cannot build on says so through its progress() counters.

The solver and the analyzer pair the registered cloud with the registered state of the same
header stamp (:class:`~mlv_ros.core.streaming.StampPairer`); a pair the solver cannot build on
(here three particles: the model needs at least five) leaves it ``blocked`` with the reason as
its latest ERROR, which is what ``mlv-ros run`` ends the run with. So does a frame source that
gives up waiting for a subscriber with its frames unsent; one that finds fewer subscribers than
it waits for publishes to those present, with a WARN (:class:`SubscriberWait`, the solver's and
the replay's wait too).
"""

import time

from conftest import spin_until
from graphkit import Probe
from mlv_msgs.msg import TaggedFrame
from mlv_ros import conversions, qos
from mlv_ros.core.types import ModelState, RegisteredModel
from mlv_ros.nodes.common import status_text, SubscriberWait, WARN
from mlv_ros.nodes.frame_source import FrameSource
from mlv_ros.nodes.meshless_solver import MeshlessSolver
from mlv_ros.nodes.motion_analyzer import MotionAnalyzer
import numpy as np
from rclpy.parameter import Parameter


def registered(n: int, stamp: float):
    """Return the cloud and state messages of an n-particle registered model stamped ``stamp``."""
    rng = np.random.default_rng(0)
    state = ModelState(
        phase_index=0,
        num_phases=4,
        translation=np.zeros(3),
        rotation=np.array([1.0, 0.0, 0.0, 0.0]),
        a0=30.0,
        study_id='study-blocked',
    )
    model = RegisteredModel(
        rng.normal(0.0, 20.0, (n, 3)),
        rng.uniform(-1.5, 0.0, n),
        rng.uniform(-np.pi, np.pi, n),
        np.ones(n),
        state,
    )
    return conversions.registered_to_msgs(model, stamp)


def test_a_model_it_cannot_build_on_leaves_the_node_blocked_with_the_reason(
    ros_context, executor
):
    solver, analyzer = MeshlessSolver(context=ros_context), MotionAnalyzer(context=ros_context)
    probe = Probe(ros_context)
    for node in (solver, analyzer, probe):
        executor.add_node(node)
    cloud, _ = registered(3, 1.0)
    _, other_state = registered(3, 2.0)
    probe.publish(qos.REGISTERED_CLOUD, cloud)
    probe.publish(qos.REGISTERED_STATE, other_state)  # another stamp: no pair, nothing built
    assert spin_until(
        executor, lambda: all(n.messages_handled or n.streams for n in (solver, analyzer)), 15
    )
    spin_until(executor, lambda: False, 1.0)
    assert solver.progress()['blocked'] == analyzer.progress()['blocked'] == 0
    assert solver.tracker is None and solver.rest_state is None and analyzer.analyzer is None

    _, state = registered(3, 1.0)
    probe.publish(qos.REGISTERED_STATE, state)  # the cloud's own state: the pair is complete
    assert spin_until(
        executor, lambda: solver.progress()['blocked'] and analyzer.analyzer is not None, 15
    )
    assert 'cannot build the model' in status_text(solver.last_error)
    assert 'at least 5 rows' in status_text(solver.last_error)
    assert analyzer.progress()['blocked'] == 0  # it takes three particles


def test_a_frame_source_no_one_subscribes_to_is_blocked_with_the_reason(ros_context, executor):
    source = FrameSource(
        context=ros_context,
        parameter_overrides=[
            Parameter('source', value='pattern'),
            Parameter('num_phases', value=2),
            Parameter('wait_for_subscribers', value=1),
            Parameter('wait_timeout_s', value=0.5),
        ],
    )
    executor.add_node(source)
    assert spin_until(executor, lambda: source.done, 15)
    assert source.progress() == {'received': 0, 'published': 0, 'blocked': 1}
    assert 'no subscriber appeared' in status_text(source.last_error)


def test_a_subscriber_wait_goes_on_only_with_enough_or_after_its_time_limit():
    wait = SubscriberWait(2, 5.0)
    assert wait.poll(2) == SubscriberWait.GO and not wait.waiting
    assert wait.poll(1) == SubscriberWait.WAIT and wait.waiting  # the wait starts now
    assert wait.poll(2, ready=False) == SubscriberWait.WAIT  # something else not there yet
    assert wait.poll(3) == SubscriberWait.GO and not wait.waiting  # enough: the wait ends
    late = SubscriberWait(2, 5.0, since=time.monotonic() - 6.0)
    assert late.poll(1) == late.poll(0) == SubscriberWait.LATE
    assert SubscriberWait(0, 0.0).poll(0) == SubscriberWait.GO  # 0 expected: never waits


def test_a_frame_source_with_fewer_subscribers_than_expected_publishes_to_them_and_warns(
    ros_context, executor
):
    source = FrameSource(
        context=ros_context,
        parameter_overrides=[
            Parameter('source', value='pattern'),
            Parameter('num_phases', value=2),
            Parameter('wait_for_subscribers', value=2),
            Parameter('wait_timeout_s', value=0.5),
            Parameter('exit_when_done', value=False),
        ],
    )
    probe = Probe(ros_context)  # the /diagnostics listener the source also waits for
    frames = []
    probe.create_subscription(
        TaggedFrame, qos.FRAMES, frames.append, qos.subscription_qos(qos.FRAMES)
    )
    for node in (source, probe):
        executor.add_node(node)
    assert spin_until(executor, lambda: len(frames) == len(source.frames), 20), len(frames)
    warned = [
        v for _, level, m, v in probe.statuses() if level == WARN and 'fewer subscribers' in m
    ]
    assert warned and warned[0]['matched'] == '1' and warned[0]['expected'] == '2', warned
    assert source.subscriber_wait.expected == 1  # it waits no more for the absent one
    assert source.progress()['blocked'] == 0
