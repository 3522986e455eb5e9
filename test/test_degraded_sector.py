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
A phase degraded for a sector only, through the real solver, analyzer and recorder.

The solver and analyzer nodes over Fast DDS, fed a registered model and tag points that lose
one sector's SA tracks at end-systole: the solver's ModelState names the sector's AHA segments
(``degraded_segments``), the analyzer's findings inflate and leave unclassed only those, and the
recording read back by an independent reader (rosbags) carries the field.
"""

from conftest import spin_until
from graphkit import Probe, wait_matched
from mlv_ros import conversions, qos
from mlv_ros.core.analysis.findings import CLASS_CODES, VERDICT_INFLATION
from mlv_ros.core.analysis.strain import AHA_SEGMENT_NAMES
from mlv_ros.core.meshless import matrix_to_quat
from mlv_ros.core.sim import simulate_study
from mlv_ros.core.types import ModelState, RegisteredModel
from mlv_ros.core.verdict import DEGRADED, OK
from mlv_ros.nodes.meshless_solver import MeshlessSolver
from mlv_ros.nodes.motion_analyzer import MotionAnalyzer
from mlv_ros.nodes.recorder import Recorder
import numpy as np
import pytest
from rclpy.parameter import Parameter
from test_recorder import read_with_rosbags
from test_tracking import grid_tags, observed, tagset
from test_verdict import drop_sector


@pytest.fixture(scope='module')
def study():
    return simulate_study('normal', snr=20, quick=True)


def registration(study, n: int = 1000) -> RegisteredModel:
    """Return a registered model of the study's true ED myocardium (``n`` particles)."""
    m = study.motion
    X = m.sample_myocardium(n, seed=1)
    fr = m.frame
    R = np.stack([fr.septum, np.cross(fr.long_axis, fr.septum), fr.long_axis], axis=1)
    c = X.mean(0)
    p = (X - c) @ R
    r = np.linalg.norm(p, axis=1)
    a0 = float(r.max())
    state = ModelState(
        num_phases=2, translation=c, rotation=matrix_to_quat(R), a0=a0, study_id='sector-study'
    )
    return RegisteredModel(
        X, np.arcsin(np.clip(p[:, 2] / r, -1, 1)), np.arctan2(p[:, 1], p[:, 0]), r / a0, state
    )


def two_phases(study):
    """
    Return the tag point sets of ED (phase 0) and of ES as phase 1 of 2, one sector lost at ES.

    Exact in-plane tags on a grid (as the solver tests use); at ES the SA tracks whose ED point
    lies 40–140° about the long axis are lost on every slice, as an akinetic region's are.
    """
    m = study.motion
    refs = grid_tags(study)
    n_sa = sum(k[0] == 0 for k in study.geometries)
    ed = {
        k: tagset(k, g, 0, 2, refs[k], np.arange(len(refs[k])))
        for k, g in study.geometries.items()
    }
    es = drop_sector(study, refs, 40.0, 140.0)(observed(study, refs, int(round(m.es_phase))))
    out = []
    for phase, sets in ((0, ed), (1, es)):
        for s in sets.values():
            s.phase_index, s.num_phases = phase, 2
            s.num_sa_slices, s.num_la_slices = n_sa, len(study.geometries) - n_sa
            s.study_id = 'sector-study'
            out.append(s)
    return out


def test_a_sector_lost_at_es_reaches_the_findings_as_its_segments_only(
    study, ros_context, executor, tmp_path
):
    out = tmp_path / 'run' / 'run.mcap'
    nodes = [
        MeshlessSolver(context=ros_context),
        MotionAnalyzer(context=ros_context),
        Recorder(context=ros_context, parameter_overrides=[Parameter('output', value=str(out))]),
    ]
    probe = Probe(ros_context)
    for n in (*nodes, probe):
        executor.add_node(n)
    wait_matched(
        executor, probe, {qos.REGISTERED_CLOUD: 3, qos.REGISTERED_STATE: 3, qos.TAG_POINTS: 2}
    )
    cloud, state = conversions.registered_to_msgs(registration(study), stamp=1.0)
    probe.publish(qos.REGISTERED_CLOUD, cloud)
    probe.publish(qos.REGISTERED_STATE, state)
    for k, s in enumerate(two_phases(study)):
        probe.publish(qos.TAG_POINTS, conversions.tagpoints_to_msg(s, stamp=2.0 + k * 1e-3))
    assert spin_until(executor, lambda: len(probe.received('metrics')) >= 2, 60), (
        probe.statuses()
    )
    rec = nodes[2]
    assert spin_until(executor, lambda: rec.writer.topics[qos.METRICS].count >= 2, 10)
    rec.finish()

    states = {m.phase_index: conversions.msg_to_model_state(m) for m in probe.received('state')}
    es = states[1]
    assert es.verdict == DEGRADED and 'ED tag points lost' in es.verdict_reasons
    named = {k + 1 for k, n in enumerate(AHA_SEGMENT_NAMES) if n in es.verdict_reasons}
    assert es.degraded_segments and set(es.degraded_segments) == named, es.verdict_reasons
    assert states[0].verdict == OK and states[0].degraded_segments == ()

    metrics = {
        d['phase_index']: d for d in map(conversions.msg_to_metrics, probe.received('metrics'))
    }
    m = metrics[1]
    assert m['degraded_segments'] == es.degraded_segments and m['findings_es_phase'] == 1
    carried = np.zeros(17, dtype=bool)
    carried[np.array(es.degraded_segments) - 1] = True
    for c in ('err', 'ecc', 'ell'):
        # The findings' ES uncertainty is the phase's own, inflated in the named segments only.
        ratio = m[f'finding_es_{c}_unc'] / m[f'segment_{c}_unc']
        np.testing.assert_allclose(ratio[carried], VERDICT_INFLATION)
        np.testing.assert_allclose(ratio[~carried & np.isfinite(ratio)], 1.0)
    indeterminate = CLASS_CODES['indeterminate']
    assert all(m['segment_class'][carried] == indeterminate), m['segment_class']
    assert np.sum(m['segment_class'][~carried] != indeterminate) >= 8, m['segment_class']

    # The recording, read by rosbags alone, carries the segments on both topics.
    got = {
        (t, msg.phase_index): list(msg.degraded_segments)
        for t, _, msg in read_with_rosbags(out)
        if t in (qos.MODEL_STATE, qos.METRICS)
    }
    assert got[(qos.MODEL_STATE, 1)] == got[(qos.METRICS, 1)] == list(es.degraded_segments)
    assert got[(qos.MODEL_STATE, 0)] == []
