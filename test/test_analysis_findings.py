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
Per-segment findings on a simulated heart with akinetic and dyskinetic regions.

Per-segment findings: the true motion of a simulated heart with an akinetic and a
dyskinetic region, analysed phase by phase, names those segments and calls the remote ones
normal; missing support gives 'indeterminate', never a class; the report draws the classes.
"""

import json

from mlv_ros.core.analysis import LVAnalyzer, PhaseMetrics, segment_findings, SegmentFindings
from mlv_ros.core.analysis.findings import (
    classify,
    MIN_SEGMENT_PARTICLES,
    UNCERTAINTY_FLOOR,
    VERDICT_INFLATION,
)
from mlv_ros.core.sim import load_preset, make_motion
from mlv_ros.core.sim.regional import regional_truth, truth_frame
import numpy as np
import pytest

# Basal septum akinetic (AHA 2, 3), mid/apical lateral dyskinetic (AHA 11, 12, 16), apart.
REGIONS = [
    {'kind': 'akinetic', 'levels': [0.65, 1.0], 'centre_deg': 0.0, 'width_deg': 120.0},
    {
        'kind': 'dyskinetic',
        'levels': [0.3, 0.6],
        'centre_deg': 180.0,
        'width_deg': 120.0,
        'contraction': -0.5,
    },
]


@pytest.fixture(scope='module')
def heart():
    """(motion, per-phase metrics of its true motion, truth classes)."""
    p = load_preset('normal')
    p['motion']['regions'] = REGIONS
    m = make_motion(p, num_phases=16)
    X = m.sample_myocardium(2500, seed=1)
    an = LVAnalyzer(X, truth_frame(m))
    phases = [
        an.phase(m.position(X, k), phase_index=k, num_phases=m.num_phases, residual_mm=0.3)
        for k in range(int(round(m.es_phase)) + 2)
    ]
    truth = [s['class'] for s in regional_truth(m, n_points=3000)['segments']]
    return m, phases, truth


def test_true_motion_names_the_abnormal_segments_and_remote_normal(heart):
    m, phases, truth = heart
    sf = SegmentFindings()
    for p in phases:  # streaming, phase by phase
        f = sf.update(p)
    assert f.es_phase == int(np.argmin([p.cavity_volume_ml for p in phases]))
    cls = f.classes
    want_ak = {k + 1 for k, c in enumerate(truth) if c in ('akinetic', 'dyskinetic')}
    got_ak = set(f.abnormal())
    assert want_ak, truth
    # every segment the truth calls akinetic or dyskinetic is found, no other is called so
    assert got_ak == want_ak, (cls, truth)
    # the dyskinetic segments stretch circumferentially at ES (their means take in the blend
    # toward contracting wall, so the truth's own means read akinetic-to-dyskinetic too)
    dys = [k for k in want_ak if truth[k - 1] == 'dyskinetic']
    assert dys and all(f.es['ecc'][k - 1] > 0 for k in dys), f.es['ecc']
    # remote: segments the truth calls normal, away from both regions, read normal
    remote = [1, 4, 7, 10, 13, 14]
    assert [truth[k - 1] for k in remote] == ['normal'] * len(remote)
    assert [cls[k - 1] for k in remote] == ['normal'] * len(remote), cls
    # peaks: Ecc of a remote segment shortens, uncertainty at least the floor
    assert f.peak['ecc'][0] < -0.05 and f.peak_unc['ecc'][0] >= UNCERTAINTY_FLOOR['ecc']
    d = f.to_dict()
    assert d['segments'][10]['class'] == cls[10] and set(d['thresholds']) >= {
        'class_bounds',
        'stretch_z',
    }
    # the one-shot function agrees with the stream
    assert segment_findings(phases).classes == cls


def test_indeterminate_without_support(heart):
    _, phases, _ = heart
    # ED only: no systolic phase yet
    assert set(segment_findings(phases[:1]).classes) == {'indeterminate'}
    # segment 11 loses its particles; a failed phase is never used
    thin = []
    for p in phases:
        c = p.segment_count.copy()
        c[10] = MIN_SEGMENT_PARTICLES - 1
        thin.append(PhaseMetrics.from_dict(p.to_dict() | {'segment_count': c}))
    f = segment_findings(thin)
    assert f.classes[10] == 'indeterminate' and np.isnan(f.es_unc['ecc'][10])
    assert f.classes[0] == 'normal'
    bad = PhaseMetrics.from_dict(
        phases[-1].to_dict()
        | {'verdict': 2, 'cavity_volume_ml': 1.0, 'segment_ecc': np.full(17, 0.5)}
    )
    assert segment_findings([*phases, bad]).classes == segment_findings(phases).classes
    # too uncertain to classify: σ 0.2 in Ecc and Err against a normal heart's references
    es = {'ecc': np.full(17, -0.15), 'err': np.full(17, 0.45)}
    es['ecc'][5], es['err'][5] = -0.02, 0.05
    cls, f_idx, f_unc, _ = classify(es, {'ecc': np.full(17, 0.02), 'err': np.full(17, 0.05)})
    assert cls[5] == 'akinetic' and cls[0] == 'normal'
    unc = {'ecc': np.full(17, 0.02), 'err': np.full(17, 0.05)}
    unc['ecc'][5], unc['err'][5] = 0.2, 0.5
    cls, _, f_unc, _ = classify(es, unc)
    assert cls[5] == 'indeterminate' and f_unc[5] > 0.33
    # support-only uncertainty when the metrics carry none (recordings of today's message)
    bare = [
        PhaseMetrics.from_dict({k: v for k, v in p.to_dict().items() if not k.endswith('_unc')})
        for p in phases
    ]
    assert bare[0].segment_ecc_unc.size == 0
    assert segment_findings(bare).es_unc['ecc'][0] == pytest.approx(UNCERTAINTY_FLOOR['ecc'])


def test_report_draws_the_classes(heart, tmp_path, monkeypatch):
    from mlv_ros.core.report import build_report, figures

    monkeypatch.setattr(figures, 'DPI', 30)
    _, phases, _ = heart
    index = build_report(tmp_path, phases, meta={'label': 'regional'})
    s = json.loads((tmp_path / 'summary.json').read_text())
    assert 'segment_findings.png' in s['figures'], s['figures_skipped']
    found = s['runs'][0]['segment_findings']
    assert [r['class'] for r in found['segments']] == segment_findings(phases).classes
    assert s['runs'][0]['key']['akinetic_segments'] == segment_findings(phases).abnormal(
        ('akinetic',)
    )
    page = index.read_text()
    assert 'Regional findings' in page and 'akinetic' in page
    # why the cap has no class is said on the findings line
    assert found['notes'][0].startswith('apex cap (17)') and 'apex cap (17)' in page


def test_a_phase_degraded_for_a_sector_inflates_and_marks_only_its_segments(
    heart, tmp_path, monkeypatch
):
    """
    Inflate only the named segments of a phase degraded for a sector, every one for the heart.

    The solver's sector check names the segments the ES tag data no longer support: only those
    are less sure and, at ES, unsupported (indeterminate, out of the references); a phase
    degraded for a whole-heart reason inflates every segment as before.
    """
    _, phases, _ = heart
    es = segment_findings(phases).es_phase
    ok = segment_findings(phases)

    def degraded(segments):
        return [
            PhaseMetrics.from_dict(
                p.to_dict()
                | (
                    {'verdict': 1, 'verdict_reasons': 'x', 'degraded_segments': segments}
                    if p.phase_index == es
                    else {}
                )
            )
            for p in phases
        ]

    sector = segment_findings(degraded((1, 4, 13)))
    whole = segment_findings(degraded(()))
    named = np.array([0, 3, 12])
    rest = np.setdiff1d(np.arange(17), named)
    for c in ('err', 'ecc', 'ell'):
        inflated = VERDICT_INFLATION * ok.es_unc[c][named]
        np.testing.assert_allclose(sector.es_unc[c][named], inflated)
        np.testing.assert_array_equal(sector.es_unc[c][rest], ok.es_unc[c][rest])
        np.testing.assert_allclose(whole.es_unc[c], VERDICT_INFLATION * ok.es_unc[c])
    assert sector.unsupported == [1, 4, 13] and whole.unsupported == ok.unsupported == []
    assert [sector.classes[k] for k in named] == ['indeterminate'] * 3
    # The others keep the class of the ok phase (1, 4 and 13 read normal there).
    assert [ok.classes[k] for k in named] == ['normal'] * 3
    assert [sector.classes[k] for k in rest] == [ok.classes[k] for k in rest], sector.classes
    assert sector.to_dict()['unsupported'] == [1, 4, 13]
    # An ok phase naming segments (never sent so) changes nothing.
    stray = [PhaseMetrics.from_dict(p.to_dict() | {'degraded_segments': (1,)}) for p in phases]
    assert segment_findings(stray).classes == ok.classes
    # The report says which segments are unsupported, in summary.json and on the page.
    from mlv_ros.core.report import build_report, figures

    monkeypatch.setattr(figures, 'DPI', 30)
    index = build_report(tmp_path, degraded((1, 4, 13)), meta={'label': 'sector'})
    found = json.loads((tmp_path / 'summary.json').read_text())['runs'][0]['segment_findings']
    assert found['unsupported'] == [1, 4, 13]
    page = index.read_text()
    assert page.count('(unsupported)') == 3 and 'unsupported at ES' in page


def test_a_weak_heart_is_said_and_its_still_segments_are_akinetic_on_absolute_bounds():
    """
    Say a globally hypokinetic heart and find its still segments on the absolute bounds.

    A heart whose median ES Ecc / Err are −0.04 / 0.10 is within about three reader spreads of
    no motion: against its own function every segment is indeterminate (σ_f > 0.33). Segments
    that barely move (|Ecc| 0.005, Err 0.01) are still akinetic on the absolute bounds (2σ
    inside |Ecc| 0.05, Err 0.10); the others stay indeterminate and the findings say why. In a
    normal heart the same segments are akinetic on the relative rule, and no note says weak.
    """
    from mlv_ros.core.analysis.findings import (
        absolute_akinetic,
        findings_notes,
        Findings,
        global_function,
    )

    unc = {'ecc': np.full(17, 0.02), 'err': np.full(17, 0.05)}
    es = {'ecc': np.full(17, -0.04), 'err': np.full(17, 0.10)}
    es['ecc'][[8, 9]], es['err'][[8, 9]] = -0.005, 0.01
    cls, f_idx, f_unc, ref = classify(es, unc)
    assert global_function(ref) == 'globally hypokinetic'
    assert [k + 1 for k, c in enumerate(cls) if c == 'akinetic'] == [9, 10]
    assert set(cls[:8]) == {'indeterminate'} and np.all(f_unc[:16] > 0.33)
    assert list(np.flatnonzero(absolute_akinetic(es, unc)) + 1) == [9, 10]
    # a moving segment of a weak heart is not akinetic: 2σ above it reaches the bounds
    assert not absolute_akinetic({'ecc': np.full(17, -0.03), 'err': np.full(17, 0.06)}, unc).any()
    f = Findings(es=es, es_unc=unc, classes=[str(c) for c in cls], function_index=f_idx,
                 function_unc=f_unc, reference=ref, global_function=global_function(ref))
    notes = findings_notes(f)
    assert any(n.startswith('globally hypokinetic') for n in notes)
    assert any('absolute bounds' in n and n.endswith('9, 10') for n in notes)
    assert any(n.startswith('apex cap (17)') for n in notes)
    normal = {'ecc': np.full(17, -0.15), 'err': np.full(17, 0.40)}
    normal['ecc'][[8, 9]], normal['err'][[8, 9]] = -0.005, 0.01
    cls, _, _, ref = classify(normal, unc)
    assert global_function(ref) == 'measured' and list(cls).count('akinetic') == 2
    assert cls[16] == 'indeterminate'  # the cap: no class claimed


def test_segments_read_between_hypokinesis_and_akinesis_are_named_not_classed():
    """
    Name "hypokinetic or akinetic" where akinesis is within 1σ of a below-normal reading.

    A weak heart (median ES Ecc −0.09, Err 0.16; the readers' spreads as σ) whose apical
    segments 13–15 read Ecc −0.022, Err 0.035: against the apical ring's expected share (0.6,
    0.75 of the median) f = 0.36 ± 0.28, hypokinetic, akinesis 1σ below: named, the class kept.
    The same reading in a segment the model carried (16) is not named (no measurement); the
    remote segments (f ≈ 1) and the cap never are. In a normal heart (−0.15, 0.40) a segment at
    half the function (f 0.50 ± 0.09) is plainly hypokinetic and not named; one at f 0.40 ± 0.09
    is.
    """
    from mlv_ros.core.analysis.findings import findings_notes, Findings, possibly_akinetic

    unc = {'ecc': np.full(17, 0.02), 'err': np.full(17, 0.05)}
    es = {'ecc': np.full(17, -0.09), 'err': np.full(17, 0.16)}
    es['ecc'][12:16], es['err'][12:16] = -0.022, 0.035
    cls, f_idx, f_unc, ref = classify(es, unc, unsupported=(16,))
    w = np.array([1 / (0.02 / 0.054) ** 2, 1 / (0.05 / 0.12) ** 2])
    expect = (w @ [0.022 / 0.054, 0.035 / 0.12]) / w.sum()
    assert f_idx[12] == pytest.approx(expect, rel=1e-2) and f_unc[12] == pytest.approx(
        1 / np.sqrt(w.sum()), rel=1e-2
    )
    assert list(cls[12:15]) == ['hypokinetic'] * 3 and cls[15] == 'indeterminate'
    named = possibly_akinetic(list(cls), f_idx, f_unc, unsupported=(16,))
    assert named == [13, 14, 15]
    f = Findings(es=es, es_unc=unc, classes=[str(c) for c in cls], function_index=f_idx,
                 function_unc=f_unc, reference=ref, possibly_akinetic=named)
    note = [n for n in findings_notes(f) if n.startswith('hypokinetic or akinetic')]
    assert len(note) == 1 and note[0].endswith(f'15 (f {f_idx[14]:.2f} ± {f_unc[14]:.2f})')
    assert f.to_dict()['possibly_akinetic'] == [13, 14, 15] and f.classes[12] == 'hypokinetic'

    normal = {'ecc': np.full(17, -0.15), 'err': np.full(17, 0.40)}
    normal['ecc'][7], normal['err'][7] = -0.075, 0.20  # f 0.50 ± 0.09
    normal['ecc'][8], normal['err'][8] = -0.06, 0.16  # f 0.40 ± 0.09
    cls, f_idx, f_unc, _ = classify(normal, unc)
    assert cls[7] == cls[8] == 'hypokinetic'
    assert possibly_akinetic(list(cls), f_idx, f_unc) == [9]
    with pytest.raises(ValueError, match='17 entries'):
        possibly_akinetic(list(cls)[:16], f_idx, f_unc)


def test_streamed_findings_name_possibly_akinetic_segments():
    """The streamed findings set possibly_akinetic at their ES phase and say it in the notes."""
    def phase(index, volume, ecc13):
        ecc = np.full(17, -0.15)
        ecc[12] = ecc13
        return PhaseMetrics(
            phase_index=index, num_phases=10, cavity_volume_ml=volume,
            segment_err=np.full(17, 0.3), segment_ecc=ecc, segment_ell=np.full(17, -0.1),
            segment_count=np.full(17, 500), segment_err_unc=np.full(17, 0.3),
            segment_ecc_unc=np.full(17, 0.02), segment_ell_unc=np.full(17, 0.02),
        )

    # Segment 13 (apical, expected 0.6 of the median Ecc): Ecc −0.04 → f_ecc 0.44 ± 0.22, Err as
    # the others (f_err 1.33 ± 1.33, little weight): f ≈ 0.47 ± 0.22, hypokinetic, named.
    f = segment_findings([phase(1, 100.0, -0.14), phase(4, 60.0, -0.04)])
    assert f.es_phase == 4 and f.classes[12] == 'hypokinetic' and f.possibly_akinetic == [13]
    assert any(n.startswith('hypokinetic or akinetic') for n in f.notes)
    early = segment_findings([phase(1, 100.0, -0.09)])
    assert early.possibly_akinetic == []
