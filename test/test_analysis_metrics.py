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

"""PhaseMetrics / LVAnalyzer: the MotionMetrics.msg content of one phase."""

from pathlib import Path
import re

from mlv_ros.core.analysis import LVAnalyzer, phase_metrics, PhaseMetrics
from mlv_ros.core.analysis.metrics import NOT_IN_MSG_YET
from mlv_ros.core.sim.analytic_lv import cylinder_shell, cylindrical_motion, oblique_frame
import numpy as np
import pytest

FR = oblique_frame()
X, ENDO = cylinder_shell(FR, r_in=20, r_out=30, n_r=5, n_theta=48, n_z=20)
MSG = Path(__file__).resolve().parents[1] / 'msg_schemas' / 'msg' / 'MotionMetrics.msg'


def test_fields_map_onto_motion_metrics_msg():
    names = []
    for line in MSG.read_text().splitlines():
        m = re.match(r'^\s*[\w/]+(\[\])?\s+(\w+)', line)
        if (
            m and not line.lstrip().startswith('#') and '=' not in line.split('#')[0]
        ):  # constants aside
            names.append(m.group(2))
    names.remove('header')
    fields = set(PhaseMetrics.__dataclass_fields__) - set(NOT_IN_MSG_YET)
    assert set(names) == fields  # one-to-one, including level_count / segment_count
    assert not set(names) & set(
        NOT_IN_MSG_YET
    )  # once the message has them, drop them from the list


def test_phase_metrics_of_an_analytic_motion_with_given_F():
    s_r, s_l = 0.85, 0.9
    x, F = cylindrical_motion(FR, X, s_r=s_r, s_l=s_l, twist_apex_deg=9, twist_base_deg=9)
    m = phase_metrics(X, x, FR, F=F, levels=10, endo_mask=ENDO, phase_index=6, num_phases=20)
    assert m.phase_index == 6 and m.num_phases == 20 and m.time_fraction == pytest.approx(0.3)
    np.testing.assert_allclose(m.level_position, np.arange(10) / 10 + 0.05, atol=1e-12)
    np.testing.assert_allclose(m.twist_deg, 9.0, atol=1e-9)
    np.testing.assert_allclose(m.sa_radius_mm, 25 * s_r, atol=1e-9)
    assert m.torsion_deg_per_cm == pytest.approx(0.0, abs=1e-9)
    assert m.la_radius_mm == pytest.approx(40 * s_l, abs=1e-9)
    assert m.ejection_fraction == pytest.approx(1 - s_r**2 * s_l, abs=1e-12)
    assert m.has_strain
    np.testing.assert_allclose(m.segment_err, 0.5 * (s_r**2 - 1), atol=1e-12)
    np.testing.assert_allclose(m.segment_ecc, 0.5 * (s_r**2 - 1), atol=1e-12)
    np.testing.assert_allclose(m.segment_ell, 0.5 * (s_l**2 - 1), atol=1e-12)
    assert m.segment_count.shape == (17,) and m.segment_count.sum() == len(X)
    np.testing.assert_array_equal(m.level_count, len(X) // 10)


def test_analyzer_estimates_strain_when_no_F_and_can_be_told_not_to():
    x, _ = cylindrical_motion(FR, X, s_r=0.85, s_l=0.9)  # affine: MLS is exact
    an = LVAnalyzer(X, FR)
    m = an.phase(x)
    np.testing.assert_allclose(m.segment_ecc, 0.5 * (0.85**2 - 1), atol=1e-9)
    np.testing.assert_allclose(m.segment_ell, 0.5 * (0.9**2 - 1), atol=1e-9)
    m0 = LVAnalyzer(X, FR, estimate_strain=False).phase(x)
    assert not m0.has_strain and m0.segment_ecc.size == 0 and m0.segment_count.size == 0
    assert m0.cavity_volume_ml == pytest.approx(m.cavity_volume_ml)


def test_ed_phase_is_all_zero_motion():
    m = LVAnalyzer(X, FR).phase(X)
    for f in (
        'twist_deg',
        'longitudinal_displacement_mm',
        'radial_displacement_mm',
        'circumferential_displacement_mm',
        'segment_err',
        'segment_ecc',
        'segment_ell',
    ):
        np.testing.assert_allclose(getattr(m, f), 0, atol=1e-12)
    assert m.ejection_fraction == 0.0


def test_to_dict_roundtrip_and_from_partial_dict():
    x, F = cylindrical_motion(FR, X, 0.9, 0.9, 5, -2)
    m = phase_metrics(X, x, FR, F=F)
    d = m.to_dict()
    import json

    back = PhaseMetrics.from_dict(json.loads(json.dumps(d)))
    for k, v in d.items():
        if isinstance(v, str):
            assert getattr(back, k) == v
        else:
            np.testing.assert_allclose(getattr(back, k), v)
    assert back.verdict == 0 and back.verdict_reasons == ''  # an ordinary contraction is ok
    partial = PhaseMetrics.from_dict({'phase_index': 3, 'twist_deg': [1.0, 2.0], 'unknown': 1})
    assert partial.phase_index == 3 and partial.segment_ecc.size == 0


def test_bad_inputs():
    an = LVAnalyzer(X, FR)
    with pytest.raises(ValueError, match='like X_ed'):
        an.phase(X[:-1])
    with pytest.raises(ValueError, match=r'F must have shape'):
        an.phase(X, F=np.zeros((3, 3, 3)))
    bad = X.copy()
    bad[0] = np.inf
    with pytest.raises(ValueError, match='non-finite'):
        an.phase(bad)
    with pytest.raises(ValueError, match='LVFrame'):
        LVAnalyzer(X, 'frame')
    # NaN gradients (e.g. degenerate MLS) are skipped, never turned into NaN means
    F = np.broadcast_to(np.eye(3), (len(X), 3, 3)).copy()
    F[:100] = np.nan
    m = an.phase(X, F=F)
    assert np.all(np.isfinite(m.segment_ecc)) and m.segment_count.sum() == len(X) - 100
