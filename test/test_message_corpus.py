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
The message bad-input corpus (``corpus/message_cases.py``) through the live graph.

One in-process graph (tag detector, registration, solver, analyzer over real Fast DDS) gets a
valid 4-phase study with every corpus case interleaved: corrupt frames right after the frame
they were copied from, stand-in frames in place of the frame whose slot they take, corrupt tag
points among the frames, and — once the model is registered — corrupt motion clouds, model
states and registered-model messages. Every case must be reported by the node that consumes
it, naming it by its stamp, with the expected reason; legal stand-ins must come out as tag
points with nothing reported against them; no valid frame may be reported; every node must
still answer afterwards, and every phase must be solved and analysed.
"""

from collections import Counter

from corpus.message_cases import message_cases
from graphkit import feed_corpus, graph_nodes, Probe, wait_matched
from mlv_ros import conversions, qos
from mlv_ros.core.sim import simulate_study
from mlv_ros.nodes.frame_source import count_slices, order_frames
import pytest

pytestmark = pytest.mark.slow  # a graph run: scheduled first (conftest)

PHASES = 4
MAX_PIXELS = 256 * 256
STAMP0 = 1000.0  # corpus stamps start here; valid frames are stamped 1, 2, ...


@pytest.fixture(scope='module')
def study():
    frames = order_frames(
        count_slices(list(simulate_study('normal', snr=20, quick=True, num_phases=PHASES).frames)),
        'slice_major',
    )
    valid = [conversions.frame_to_msg(f, stamp=1.0 + i) for i, f in enumerate(frames)]
    return valid, message_cases(valid, stamp0=STAMP0, max_pixels=MAX_PIXELS)


def test_corpus_has_every_kind():
    def study_msgs(num_phases):
        return [
            conversions.frame_to_msg(f)
            for f in count_slices(
                list(simulate_study('normal', quick=True, num_phases=num_phases).frames)
            )
        ]

    valid = study_msgs(3)
    cases = message_cases(valid)
    assert len(cases) >= 110 and len({c.name for c in cases}) == len(cases)
    assert len({conversions.stamp_text(c.msg.header.stamp) for c in cases}) == len(cases)
    kinds = Counter(c.category.split('/')[0] for c in cases)
    assert set(kinds) == {
        'frame',
        'tag_points',
        'motion',
        'model_state',
        'registered_cloud',
        'registered_state',
    }
    with pytest.raises(ValueError, match='SA and LA'):
        message_cases([m for m in valid if m.view == 0])
    with pytest.raises(ValueError, match='non-ED slots'):
        message_cases(study_msgs(2))


def test_every_case_is_reported_and_the_run_completes(study, ros_context, executor):
    valid, cases = study
    nodes = graph_nodes(ros_context, max_pixels=MAX_PIXELS)
    probe = Probe(ros_context)
    for n in (*nodes.values(), probe):
        executor.add_node(n)
    wait_matched(
        executor,
        probe,
        {
            qos.FRAMES: 2,
            qos.TAG_POINTS: 1,
            qos.MOTION: 1,
            qos.MODEL_STATE: 1,
            qos.REGISTERED_CLOUD: 2,
            qos.REGISTERED_STATE: 2,
        },
    )
    report = feed_corpus(executor, probe, nodes, valid, cases)

    assert not report.crashes, report.crashes
    assert not report.failures, '\n'.join(report.failures)
    # No false alarms: nothing is reported as bad about a valid frame.
    assert not report.false_alarms, report.false_alarms
    # Corrupt copies never displaced a genuine tag set: one set per slot, no duplicates downstream.
    assert report.tag_sets == len(valid)
    assert not [s for s in probe.statuses() if s[0] == 'meshless_solver' and 'duplicate' in s[2]]
    # Every phase solved and analysed exactly once.
    assert sorted(s.phase_index for s in probe.received('state')) == list(range(PHASES))
    assert sorted(m.phase_index for m in probe.received('metrics')) == list(range(PHASES))
    # Every node still up and answering: a heartbeat from each after the corpus.
    assert not report.nodes_down, f'no status after the corpus from {report.nodes_down}'
    counts = Counter(c.category for c in cases)
    print(
        f'\n{len(cases)} cases, all reported by the consuming node: {dict(sorted(counts.items()))}'
    )
