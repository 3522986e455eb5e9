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
``bench/strain.py``'s offline comparison (``bench/retrack.py --strain``) on analytic motion.

The truth's own motion of a heart with an akinetic and a dyskinetic region, given as solved
positions to :func:`strain.ours_from_positions` with the rotation a registration would give,
compares with the truth's regional strain within the analysis' own error and finds the
abnormal segments; a phase marked failed is left out as the analysis node leaves it out. A miss
is told apart from its cause: motion read wrong, or segment names turned by a prior septum.
"""

from pathlib import Path
import sys

from mlv_ros.core.meshless.globals import matrix_to_quat, quat_to_matrix
from mlv_ros.core.sim.regional import regional_truth, truth_frame
from mlv_ros.core.verdict import FAILED
import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'bench'))
from strain import brief, compare, explain_abnormal, ours_from_positions  # noqa: E402, I100
# the normal preset with an akinetic and a dyskinetic region, 16 phases
from test_analysis_findings import heart as findings_heart  # noqa: E402, F401


@pytest.fixture(scope='module')
def heart(findings_heart):  # noqa: F811
    """(ED particles, rotation, phase → true positions, regional truth, ES phase)."""
    m = findings_heart[0]
    X = m.sample_myocardium(2500, seed=2)
    f = truth_frame(m)
    # The registration's rotation: z the long axis, x the analyzer's reference, which sits
    # 60° past the truth's mid-septum (LVFrame's default AHA origin −120° against −60°).
    a = np.radians(60.0)
    x = np.cos(a) * f.e1 + np.sin(a) * f.e2
    rotation = matrix_to_quat(np.stack([x, np.cross(f.axis, x), f.axis], axis=1))
    es = int(round(m.es_phase))
    positions = {k: m.position(X, k) for k in range(es + 2)}
    return X, rotation, positions, regional_truth(m, n_points=6000), es


def test_true_motion_matches_the_regional_truth_and_finds_the_regions(heart):
    X, rotation, positions, truth, es = heart
    ours = ours_from_positions(X, rotation, positions, es)
    assert not ours['published']
    got = compare(truth, ours)
    # Same motion: what is left is the particle sample (2500 against 6000 points), the frame's
    # extent (the particles' extreme levels against the truth's apex and base plane) and the
    # MLS strain estimate, which smooths the regions' blends: the square of their shear enters
    # E_ll, so the smoothed Ell reads lower (measured −0.020 here, −0.003 without the regions).
    for c, tol in (('err', 0.02), ('ecc', 0.01), ('ell', 0.025)):
        assert abs(got['global'][c]['error']) < tol, (c, got['global'])
    assert got['segments']['ecc']['p95'] < 0.03, got['segments']
    # (no sign check: a segment's mean of a sharp region's small strain depends on the sample
    # itself — the exact strain at 2500 particles gives segment 12's Ecc 0.003–0.040 by seed)
    assert got['signs']['checked'] > 0
    cls = got['classification']
    want = {
        s['segment'] for s in truth['segments'] if s['class'] in ('akinetic', 'dyskinetic')
    }
    assert want and cls['true_positive'] == len(want), cls['per_segment']
    assert cls['false_positive'] == 0, cls['per_segment']
    b = brief(got)
    assert b['found']['tp'] == len(want) and b['must'] == got['must']
    assert set(b['classes']) >= want


def test_a_failed_phase_is_left_out_and_es_must_be_solved(heart):
    X, rotation, positions, truth, es = heart
    # A failed ES phase (the solver's verdict) is never the findings' end-systole.
    states = {es: (FAILED, 'not solved: test', 0.0)}
    ours = ours_from_positions(X, rotation, positions, es, states)
    assert ours['findings'].es_phase != es
    assert es not in ours['findings'].phases_used
    with pytest.raises(ValueError, match='ES phase'):
        ours_from_positions(X, rotation, {k: v for k, v in positions.items() if k != es}, es)


def _turned(rotation, deg):
    """Return ``rotation`` turned by ``deg`` about its own z axis (the long axis)."""
    a = np.radians(deg)
    rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return matrix_to_quat(quat_to_matrix(np.asarray(rotation)) @ rz)


def test_a_miss_is_told_apart_from_its_cause(heart, findings_heart):  # noqa: F811
    X, rotation, positions, truth, es = heart
    motion = findings_heart[0]
    want = sorted(
        s['segment'] for s in truth['segments'] if s['class'] in ('akinetic', 'dyskinetic')
    )
    ours = ours_from_positions(X, rotation, positions, es)
    got = explain_abnormal(truth, ours, motion, X, rotation, positions)
    assert [e['segment'] for e in got] == want
    assert all(e['why'] == 'found' and e['named_share'] > 0.8 for e in got), got
    # The same frame, every segment read normal: the truth's motion finds them, ours did not.
    normal = dict(ours, classes=['normal'] * 17)
    got = explain_abnormal(truth, normal, motion, X, rotation, positions)
    assert all(e['why'] == 'motion' for e in got), got
    # The septum from the prior, 120° off (two basal sectors): the truth's motion in that frame
    # does not find the segments under their names, and the named segments are not the truth's.
    turned = _turned(rotation, 120.0)
    prior = ours_from_positions(X, turned, positions, es) | {'segment_origin': 1}
    got = explain_abnormal(truth, prior, motion, X, turned, positions)
    missed = [e for e in got if e['why'] != 'found']
    assert missed and all(e['why'] == 'names' and e['named_share'] < 0.5 for e in missed), got


def _case(truth_classes, our_classes, coverage=0.8):
    """Return a truth and our reading of 17 segments with these classes (strain alike)."""
    seg = [
        {
            'segment': k + 1, 'class': c, 'count': 100, 'err': 0.3, 'ecc': -0.1, 'ell': -0.1,
            'abnormal_fraction': coverage if c in ('akinetic', 'dyskinetic') else 0.0,
        }
        for k, c in enumerate(truth_classes)
    ]
    truth = {'segments': seg, 'global': {'err': 0.3, 'ecc': -0.1, 'ell': -0.1}}
    same = {c: np.array([s[c] for s in seg]) for c in ('err', 'ecc', 'ell')}
    ours = {'global': dict(truth['global']), 'segments': same, 'reanalysis': same,
            'count': np.full(17, 100), 'classes': list(our_classes)}
    return truth, ours


def test_the_apex_cap_is_scored_apart_and_partial_segments_are_counted_by_coverage():
    """
    Score the cap beside the criterion; split the found by the abnormal core's coverage.

    The simulator's cap motion contradicts its label (``strain.CAP``'s comment): a dyskinetic
    cap we leave indeterminate is no miss of the criterion, and a cap we flagged would be no false
    positive of it; both are counted beside (``found_cap``, ``found_with_cap``).
    """
    from strain import summarise

    truth_cls = ['normal'] * 17
    truth_cls[6] = 'akinetic'
    truth_cls[16] = 'dyskinetic'
    ours_cls = ['normal'] * 16 + ['indeterminate']
    ours_cls[6] = 'akinetic'
    truth, ours = _case(truth_cls, ours_cls)
    got = compare(truth, ours)
    cls = got['classification']
    assert cls['true_positive'] == 1 and cls['false_negative'] == 0
    assert cls['true_negative'] == 15 and cls['false_positive'] == 0
    assert cls['cap'] == {'truth': 'dyskinetic', 'ours': 'indeterminate'}
    explained = [
        {'segment': 7, 'why': 'found', 'coverage': 0.8, 'unsupported': False},
        {'segment': 17, 'why': 'cap', 'coverage': 1.0, 'unsupported': False},
    ]
    # A partial one (core over half of the segment, under 0.6), missed as carried by the model.
    truth_cls[9] = 'akinetic'
    ours_cls[9] = 'indeterminate'
    t2, o2 = _case(truth_cls, ours_cls, coverage=0.55)
    case2 = {'seed': 2, 'must': False, **compare(t2, o2), 'explained': [
        {'segment': 7, 'why': 'found', 'coverage': 0.55, 'unsupported': False},
        {'segment': 10, 'why': 'unsupported', 'coverage': 0.55, 'unsupported': True},
        {'segment': 17, 'why': 'cap', 'coverage': 1.0, 'unsupported': False},
    ]}
    s = summarise([{'seed': 1, 'must': False, **got, 'explained': explained}, case2])
    assert s['found'] == '2/3' and s['normal_not_flagged'] == '29/29'
    assert s['abnormal_segments'] == 3
    assert s['found_cap'] == '0/2' and s['found_with_cap'] == '2/5'
    assert s['found_by_coverage'] == {'>=0.6': '1/1', '<0.6': '1/2'}
    assert s['not_assessable'] == 1 and s['missed_why'] == {'cap': 2, 'unsupported': 1}


def test_a_physiological_apex_cap_is_scored_with_the_rest():
    """
    Count an abnormal cap in the criterion when the study's cap moves as a heart's does.

    Random protocols draw ``motion.apex_thickening`` (a cap that thickens and shortens): its
    label is what its motion shows, so a dyskinetic cap the product leaves indeterminate is a
    miss, and nothing of it is counted beside.
    """
    from strain import summarise

    truth_cls = ['normal'] * 17
    truth_cls[6] = 'akinetic'
    truth_cls[16] = 'dyskinetic'
    ours_cls = ['normal'] * 16 + ['indeterminate']
    ours_cls[6] = 'akinetic'
    truth, ours = _case(truth_cls, ours_cls)
    got = compare(truth, ours, cap_scored=True)
    cls = got['classification']
    assert cls['true_positive'] == 1 and cls['false_negative'] == 1
    assert cls['true_negative'] == 15 and cls['cap'] is None and cls['cap_scored']
    s = summarise([{'seed': 1, 'must': False, **got, 'explained': []}])
    assert s['found'] == '1/2' and s['abnormal_segments'] == 2
    assert s['found_cap'] == '0/0' and s['found_with_cap'] == '1/2'
