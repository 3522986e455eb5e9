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

"""Report: figures written, summary numbers, missing data reported instead of crashing."""

import json

from mlv_ros.core.analysis import LVAnalyzer, PhaseMetrics
from mlv_ros.core.report import build_report, RunData, summarize, write_summary_json
from mlv_ros.core.report.figures import _aha_wedges
from mlv_ros.core.report.summary import signed_peak
from mlv_ros.core.sim.analytic_lv import cylinder_shell, oblique_frame, synthetic_cycle
from mlv_ros.core.types import SEGMENT_ORIGIN_CODES
import numpy as np
import pytest

FR = oblique_frame()
X, ENDO = cylinder_shell(FR, r_in=20, r_out=30, n_r=3, n_theta=24, n_z=10)
NP = 10
PNG = b'\x89PNG\r\n\x1a\n'


def make_run(strain=True, **kw):
    an = LVAnalyzer(X, FR, endo_mask=ENDO, estimate_strain=False)
    cyc = synthetic_cycle(FR, X, NP, **kw)
    phases = [
        an.phase(x, F if strain else None, phase_index=i, num_phases=NP)
        for i, (x, F) in enumerate(cyc)
    ]
    return phases, {i: x for i, (x, _) in enumerate(cyc)}


@pytest.fixture(scope='module')
def normal():
    return make_run(
        es_fraction=0.3, s_r_es=0.85, s_l_es=0.9, twist_apex_es_deg=10, twist_base_es_deg=-3
    )


@pytest.fixture
def low_dpi(monkeypatch):
    # rendering resolution does not matter to what these tests check; keeps the suite fast
    import mlv_ros.core.report.figures as figures

    monkeypatch.setattr(figures, 'DPI', 30)


def read_summary(out):
    return json.loads(
        (out / 'summary.json').read_text(),
        parse_constant=lambda c: pytest.fail(f'non-strict JSON {c}'),
    )


def test_full_report_with_comparison(tmp_path, normal):
    phases, pos = normal
    hyp, hpos = make_run(
        es_fraction=0.5, s_r_es=0.93, s_l_es=0.95, twist_apex_es_deg=6, twist_base_es_deg=-2
    )
    index = build_report(
        tmp_path,
        phases,
        X,
        pos,
        compare=RunData(hyp, X, hpos, FR, 'hypertrophic'),
        meta={'label': 'normal', 'title': 'synthetic pair'},
        frame=FR,
    )
    assert index == tmp_path / 'index.html'
    names = (
        'level_curves.png',
        'global_curves.png',
        'strain_bullseye.png',
        'segment_findings.png',
        'displacement_es.png',
    )
    for n in names:
        data = (tmp_path / n).read_bytes()
        assert data.startswith(PNG) and len(data) > 10_000, n
    page = index.read_text()
    for n in names:
        assert f'src="{n}"' in page
    assert 'normal' in page and 'hypertrophic' in page and 'Nothing missing.' in page
    s = read_summary(tmp_path)
    assert s['figures_skipped'] == [] and sorted(s['figures']) == sorted(names)
    k, kh = s['runs'][0]['key'], s['runs'][1]['key']
    # ES at phase 3 (t = 0.3): V = s_r² s_l V_ed exactly; torsion −13° over 80 mm
    assert k['es_phase_index'] == 3 and k['es_time_fraction'] == pytest.approx(0.3)
    assert k['ejection_fraction'] == pytest.approx(1 - 0.85**2 * 0.9, abs=1e-12)
    assert k['peak_torsion_deg_per_cm'] == pytest.approx(-13 / 8, abs=1e-9)
    assert k['peak_global_ecc'] == pytest.approx(0.5 * (0.85**2 - 1), abs=1e-9)
    assert k['peak_twist_apex_deg'] == pytest.approx(10 - 13 * 0.05, abs=1e-9)
    # the comparison contracts less and later
    assert kh['es_time_fraction'] > k['es_time_fraction']
    assert kh['ejection_fraction'] < k['ejection_fraction']
    assert abs(kh['peak_global_ecc']) < abs(k['peak_global_ecc'])
    assert (
        len(s['runs'][0]['phases']) == NP and len(s['runs'][0]['peak_segment_strain']['ecc']) == 17
    )


def s_none_findings(path) -> bool:
    """No strain: the summary says so (findings null), the page says why."""
    return (
        read_summary(path)['runs'][0]['segment_findings'] is None
        and 'no regional findings' in (path / 'index.html').read_text()
    )


def test_missing_phases_no_strain_no_positions(tmp_path, low_dpi):
    phases, pos = make_run(strain=False)
    kept = [p for p in phases if p.phase_index not in (2, 7)]
    index = build_report(tmp_path, kept, None, None, meta={'label': 'partial'})
    page = index.read_text()
    assert '2 of 10 phases missing: [2, 7]' in page
    assert 'no strain in any phase' in page and 'no ED positions' in page
    assert not (tmp_path / 'strain_bullseye.png').exists()
    assert not (tmp_path / 'segment_findings.png').exists()
    assert s_none_findings(tmp_path)
    assert not (tmp_path / 'displacement_es.png').exists()
    assert (tmp_path / 'level_curves.png').read_bytes().startswith(PNG)
    assert (tmp_path / 'global_curves.png').read_bytes().startswith(PNG)
    s = read_summary(tmp_path)
    assert s['runs'][0]['missing_phases'] == [2, 7]
    assert s['runs'][0]['key']['peak_global_ecc'] is None


def test_es_positions_missing_bad_shape_and_no_frame(tmp_path, low_dpi):
    phases, pos = make_run(strain=False, es_fraction=0.3)
    only = {0: pos[0], 5: pos[5]}  # ES (phase 3) positions absent
    build_report(tmp_path, phases, X, only)
    page = (tmp_path / 'index.html').read_text()
    assert 'no positions for the ES phase 3; 3D figure shows phase 5' in page
    assert 'estimated from the ED cloud' in page
    assert (tmp_path / 'displacement_es.png').exists()
    out2 = tmp_path / 'bad'
    build_report(out2, phases, X, {3: pos[3][:-5]}, frame=FR)
    assert 'differ in shape' in (out2 / 'index.html').read_text()
    assert not (out2 / 'displacement_es.png').exists()


def test_no_phases_at_all(tmp_path, low_dpi):
    index = build_report(tmp_path, [], None, None)
    page = index.read_text()
    assert 'no phases: nothing to report' in page and 'No figures could be drawn.' in page
    assert read_summary(tmp_path)['runs'][0]['num_phases'] == 0


def test_summary_of_messages_without_extras_and_with_nan():
    # as rebuilt from MotionMetrics messages: no counts; a NaN volume must not leak into JSON
    p0 = PhaseMetrics(
        phase_index=0,
        num_phases=3,
        level_position=[0.5],
        twist_deg=[0.0],
        sa_radius_mm=[25.0],
        longitudinal_displacement_mm=[0.0],
        cavity_volume_ml=100.0,
    )
    p1 = PhaseMetrics(
        phase_index=1,
        num_phases=3,
        time_fraction=1 / 3,
        level_position=[0.5],
        twist_deg=[4.0],
        sa_radius_mm=[22.0],
        longitudinal_displacement_mm=[-3.0],
        cavity_volume_ml=60.0,
        torsion_deg_per_cm=float('nan'),
    )
    s = summarize([p1, p0, p1], 'msg')
    assert s['phases_present'] == [0, 1] and s['missing_phases'] == [2]
    assert any('duplicate phases [1]' in m for m in s['missing'])
    assert s['key']['ejection_fraction'] == pytest.approx(0.4)
    assert s['key']['peak_sa_radius_change_mm'] == pytest.approx(-3.0)
    assert s['key']['peak_torsion_deg_per_cm'] == 0.0  # NaN ignored, 0.0 from phase 0


def test_write_summary_json_is_strict(tmp_path):
    p = write_summary_json(
        tmp_path / 's.json', {'a': float('nan'), 'b': np.arange(3), 'c': [np.inf]}
    )
    assert json.loads(p.read_text()) == {'a': None, 'b': [0, 1, 2], 'c': [None]}


def test_signed_peak():
    assert signed_peak([0.1, -0.3, 0.2]) == -0.3
    np.testing.assert_array_equal(
        signed_peak(np.array([[1.0, np.nan], [-2.0, np.nan]]), axis=0)[0], -2.0
    )
    assert np.isnan(signed_peak(np.array([[1.0, np.nan], [-2.0, np.nan]]), axis=0)[1])


def test_bullseye_layout_anterior_top_septum_left():
    # display angle = 90° + ψ − 330°: segment centres (deg, CCW on the page)
    centre = {seg: (90 + psi0 + w / 2 - 330) % 360 for seg, ring, psi0, w in _aha_wedges()}
    assert (
        centre[1] == pytest.approx(90)
        and centre[7] == pytest.approx(90)
        and centre[13] == pytest.approx(90)
    )
    assert centre[2] == pytest.approx(150) and centre[3] == pytest.approx(
        210
    )  # septal side = left
    assert centre[4] == pytest.approx(270) and centre[14] == pytest.approx(180)
    assert centre[5] == pytest.approx(330) and centre[16] == pytest.approx(0)
    rings = {seg: ring for seg, ring, _, _ in _aha_wedges()}
    assert rings[1] == 3 and rings[7] == 2 and rings[13] == 1 and len(rings) == 16


def test_failed_phases_are_not_plotted_and_flagged_phases_are_named(tmp_path, normal, low_dpi):
    """
    Check that failed and degraded phases are left out of the curves and named with reasons.

    Phase 3 (ES) failed with an absurd volume, phase 7 degraded: the failed one enters no
    curve, peak or table (ES moves to the best remaining phase), both are named with their
    reasons at the top of the page and in summary.json.
    """
    import dataclasses

    phases, pos = normal
    bad = dataclasses.replace(
        phases[3],
        cavity_volume_ml=40605.0,
        verdict=2,
        verdict_reasons='ejection fraction -300.00 outside [-0.3, 0.95]',
    )
    meh = dataclasses.replace(
        phases[7], verdict=1, verdict_reasons='2 of 8 SA slices with 3+ tag points'
    )
    flagged = phases[:3] + [bad] + phases[4:7] + [meh] + phases[8:]
    index = build_report(tmp_path, flagged, X, pos, meta={'label': 'run'}, frame=FR)
    run = read_summary(tmp_path)['runs'][0]
    assert run['phases_failed'] == {'3': bad.verdict_reasons}
    assert run['phases_degraded'] == {'7': meh.verdict_reasons}
    assert 3 not in run['phases_present'] and 7 in run['phases_present']
    assert (
        run['key']['es_phase_index'] != 3 and run['key']['ejection_fraction'] < 1
    )  # 40 l never used
    assert (tmp_path / 'level_curves.png').stat().st_size > 1000  # drawn with the degraded band
    page = index.read_text()
    assert 'phase 3 failed (not plotted)' in page and 'phase 7 degraded' in page
    assert '2 of 8 SA slices' in page


def test_twist_beyond_the_sa_slices_is_marked_extrapolated(tmp_path, normal, low_dpi, monkeypatch):
    import mlv_ros.core.report.build as build

    monkeypatch.setattr(build, 'plot_displacement_3d', lambda *a, **k: None)  # not what is checked
    phases, pos = normal
    # SA slices from level 0.42 to 0.96: the apical bins (0.05…0.35) are extrapolated, the base is
    # not.
    build_report(tmp_path / 'a', phases, X, pos, frame=FR, twist_span=(0.42, 0.96))
    s = read_summary(tmp_path / 'a')['runs'][0]
    assert s['twist_measured_levels'] == [0.42, 0.96]
    assert 'apical' in s['twist_extrapolated'] and 'basal' not in s['twist_extrapolated']
    assert s['key']['extrapolated'] == ['peak_torsion_deg_per_cm', 'peak_twist_apex_deg']
    page = (tmp_path / 'a' / 'index.html').read_text()
    assert page.count('(extrapolated*)') == 2 and 'not measured' in page
    # SA slices cover every level: nothing marked; not known (an old caller): no claim either way.
    build_report(tmp_path / 'b', phases, X, pos, frame=FR, twist_span=(0.03, 0.97))
    s = read_summary(tmp_path / 'b')['runs'][0]
    assert s['twist_extrapolated'] == '' and s['key']['extrapolated'] == []
    assert 'extrapolated*' not in (tmp_path / 'b' / 'index.html').read_text()
    build_report(tmp_path / 'c', phases, X, pos, frame=FR)
    assert 'twist_extrapolated' not in read_summary(tmp_path / 'c')['runs'][0]


def test_segment_names_from_the_prior_are_marked_uncertain(tmp_path, normal, low_dpi, monkeypatch):
    import dataclasses

    import mlv_ros.core.report.build as build
    import mlv_ros.core.report.figures as figures

    for name in ('plot_displacement_3d', 'plot_level_curves', 'plot_global_curves'):
        monkeypatch.setattr(build, name, lambda *a, **k: None)  # not what is checked
    titles = []
    draw = figures.draw_class_bullseye
    monkeypatch.setattr(
        figures,
        'draw_class_bullseye',
        lambda ax, *a, title='', **k: titles.append(title) or draw(ax, *a, title=title, **k),
    )
    phases, pos = normal
    for origin, unsure in (('prior', True), ('detected', False)):
        code = SEGMENT_ORIGIN_CODES[origin]
        ph = [dataclasses.replace(p, segment_origin=code) for p in phases]
        build_report(tmp_path / origin, ph, X, pos, frame=FR)
        s = read_summary(tmp_path / origin)['runs'][0]['segment_findings']['segment_origin']
        assert s['source'] == origin and s['names_uncertain'] is unsure
        page = (tmp_path / origin / 'index.html').read_text()
        assert ('Segment names uncertain' in page) is unsure
        assert (figures.PRIOR_NAMES_NOTE in titles[-1]) is unsure, titles
