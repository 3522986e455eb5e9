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
Regional wall-motion abnormalities of the simulator.

Regional wall-motion abnormalities of the simulator: akinetic, hypokinetic and
dyskinetic regions move as documented, stay smooth and invertible, leave the rest of the heart
alone; protocols draw, fix and round-trip them; the ground truth carries their strain and class.
"""

from mlv_ros.core.io import load_groundtruth, write_groundtruth
from mlv_ros.core.sim import load_preset, make_motion, simulate_study
from mlv_ros.core.sim.protocol import (
    complete_protocol,
    draw_protocol,
    ITEMS,
    load_protocol,
    protocol_preset,
    save_protocol,
)
from mlv_ros.core.sim.regional import (
    check_regions,
    CLASSES,
    classify_contraction,
    regional_truth,
    strain_components,
)
import numpy as np
import pytest

# A mid-lateral sector: core levels 0.45–0.7 (blend 0.1), angles 150 ± 45 (blend 30°).
SECTOR = {'levels': [0.4, 0.75], 'centre_deg': 150.0, 'width_deg': 120.0}


def _motion(kind=None, contraction=None, shape='normal', extra=()):
    p = load_preset(shape)
    regions = list(extra)
    if kind:
        reg = {'kind': kind, **SECTOR}
        if contraction is not None:
            reg['contraction'] = contraction
        regions.append(reg)
    if regions:
        p['motion']['regions'] = regions
    return make_motion(p)


def _core_points(m, n=400, seed=3):
    """ED myocardium inside the sector's core (away from every blend)."""
    X = m.sample_myocardium(20 * n, seed=seed)
    _, th, z = m.frame.to_local(X)
    u = z / m.length
    d = np.degrees(np.angle(np.exp(1j * (th - np.radians(150.0)))))
    return X[(u > 0.5) & (u < 0.65) & (np.abs(d) < 30.0)][:n]


@pytest.fixture(scope='module')
def motions():
    return {k: _motion(k) for k in (None, 'hypokinetic', 'akinetic', 'dyskinetic')}


def test_akinetic_core_has_no_strain_and_moves_rigidly(motions):
    m = motions['akinetic']
    X = _core_points(m)
    es = m.es_phase
    E = strain_components(m, X, es)
    assert np.abs(E).max() < 2e-3, np.abs(E).max(axis=0)  # Err, Ecc, Ell ≈ 0
    # rigid: within one level the core moves as a rigid body (pairwise distances kept). Across
    # levels it still twists with the heart (torsional shear E_cl), as tethered tissue does.
    r, th, z = m.frame.to_local(X)
    z0 = np.full_like(z, 0.575 * m.length)
    r0 = m.endo_radius(z0) + (r - r.min()) / np.ptp(r) * (m.epi_radius(z0, th) - m.endo_radius(z0))
    X0 = m.frame.from_local(r0, th, z0)
    x0 = m.position(X0, es)
    dX = np.linalg.norm(X0[:, None] - X0[None], axis=2)
    dx = np.linalg.norm(x0[:, None] - x0[None], axis=2)
    assert np.abs(dx - dX).max() < 0.05, np.abs(dx - dX).max()  # mm, over a ~30 mm arc
    assert np.linalg.norm(x0 - X0, axis=1).min() > 3.0  # it does move (carried by the heart)


def test_hypokinetic_between_normal_and_akinetic_and_dyskinetic_reversed(motions):
    X = _core_points(motions[None])
    es = motions[None].es_phase
    E = {k: strain_components(m, X, es).mean(axis=0) for k, m in motions.items()}
    r = {}
    for k, m in motions.items():
        r0, _, _ = m.frame.to_local(X)
        r1, _, _ = m.frame.to_local(m.position(X, es))
        r[k] = float(np.mean(r1 - r0))  # radial displacement, + outward
    err, ecc = {k: v[0] for k, v in E.items()}, {k: v[1] for k, v in E.items()}
    assert err[None] > 0.3 and ecc[None] < -0.1  # normal: thickens, shortens
    assert err[None] > err['hypokinetic'] > err['akinetic'] > err['dyskinetic']
    assert ecc[None] < ecc['hypokinetic'] < ecc['akinetic'] < ecc['dyskinetic']
    assert 0.3 * err[None] < err['hypokinetic'] < 0.7 * err[None]  # contraction 0.5
    assert err['dyskinetic'] < -0.05 and ecc['dyskinetic'] > 0.02 and E['dyskinetic'][2] > 0.02
    assert r[None] < -3.0 and r['dyskinetic'] > 1.0  # normal wall moves in, dyskinetic bulges out


def test_abnormal_motion_smooth_invertible_isochoric(motions):
    m = motions['dyskinetic']
    X = m.sample_myocardium(3000, seed=1)
    for ph in (m.es_phase, 0.6 * m.num_phases):
        x = m.position(X, ph)
        np.testing.assert_allclose(m.inverse(x, ph), X, atol=1e-8)
        np.testing.assert_allclose(np.linalg.det(m.deformation_gradient(X, ph)), 1.0, atol=1e-5)
    # smooth in space: along a line through both blends the positions have no jumps
    _, th, z = m.frame.to_local(_core_points(m, 1))
    zz = np.linspace(0.25, 0.95, 2000) * m.length
    for line in (
        m.frame.from_local(np.full_like(zz, m.endo_radius(z[0]) + 3), np.full_like(zz, th[0]), zz),
        m.frame.from_local(
            np.full(2000, m.endo_radius(z[0]) + 3),
            np.linspace(0, 2 * np.pi, 2000),
            np.full(2000, z[0]),
        ),
    ):
        step = np.linalg.norm(np.diff(m.position(line, m.es_phase), axis=0), axis=1)
        ed = np.linalg.norm(np.diff(line, axis=0), axis=1)
        assert step.max() < 4.0 * ed.max()
    # the truth's myocardium stays the ED geometry's (the map does not depend on it)
    assert m.inside_myocardium(X).all()


def test_normal_region_unchanged(motions):
    base, m = motions[None], motions['dyskinetic']
    X = base.sample_myocardium(4000, seed=2)
    _, th, _ = m.frame.to_local(X)
    d = np.abs(np.degrees(np.angle(np.exp(1j * (th - np.radians(150.0))))))
    away = d > 60.0 + 15.0 + 1.0  # outside the sector and its blend
    for ph in (m.es_phase, 4):
        np.testing.assert_array_equal(m.position(X[away], ph), base.position(X[away], ph))
    assert m.contraction(X[away]).min() == 1.0


def test_region_checks():
    g = load_preset('normal')['geometry']
    ok = check_regions([{'kind': 'akinetic', **SECTOR}], g)[0]
    assert ok['contraction'] == 0.0 and ok['blend_fraction'] == 0.1
    bad = [
        ({'kind': 'scarred', **SECTOR}, 'kind'),
        ({'kind': 'akinetic', **SECTOR, 'contraction': 0.5}, 'contraction'),
        ({'kind': 'akinetic', **SECTOR, 'levels': [0.7, 0.4]}, 'levels'),
        ({'kind': 'akinetic', **SECTOR, 'levels': [0.05, 0.4]}, 'apex tip'),
        ({'kind': 'akinetic', **SECTOR, 'colour': 1}, 'unknown key'),
    ]
    for reg, what in bad:
        with pytest.raises(ValueError, match=what):
            check_regions([reg], g)
    with pytest.raises(ValueError, match='overlaps'):
        check_regions(
            [
                {'kind': 'akinetic', **SECTOR},
                {'kind': 'dyskinetic', **SECTOR, 'centre_deg': 200.0},
            ],
            g,
        )
    check_regions(
        [{'kind': 'akinetic', **SECTOR}, {'kind': 'dyskinetic', **SECTOR, 'centre_deg': 330.0}], g
    )
    with pytest.raises(ValueError, match='overlaps'):  # the infarct shape's own segment 7
        make_motion(
            {
                **load_preset('infarct'),
                'motion': {
                    **load_preset('infarct')['motion'],
                    'regions': [
                        {
                            'kind': 'akinetic',
                            'levels': [0.5, 0.9],
                            'centre_deg': 280.0,
                            'width_deg': 60.0,
                        }
                    ],
                },
            }
        )
    assert list(classify_contraction([1.0, 0.5, 0.0, -0.4])) == list(CLASSES)


def test_protocol_draws_fixes_and_round_trips_regions(tmp_path):
    draws = [draw_protocol(s)['abnormal_regions'] for s in range(60)]
    n = [len(r) for r in draws]
    assert 0 in n and 1 in n and 2 in n and max(n) <= 2
    kinds = {r['kind'] for rs in draws for r in rs}
    assert kinds == {'hypokinetic', 'akinetic', 'dyskinetic'}
    assert any(r['width_deg'] == 360.0 for rs in draws for r in rs)
    assert any(r['width_deg'] < 360.0 for rs in draws for r in rs)
    # independent stream: fixing the regions leaves every other item as drawn
    fixed = [
        {
            'kind': 'dyskinetic',
            'levels': [0.0, 0.3],
            'centre_deg': 0.0,
            'width_deg': 360.0,
            'contraction': -0.4,
        }
    ]
    p, q = draw_protocol(11), draw_protocol(11, {'abnormal_regions': fixed})
    assert q['abnormal_regions'][0]['contraction'] == -0.4
    assert {k: v for k, v in p.items() if k != 'abnormal_regions'} == {
        k: v for k, v in q.items() if k != 'abnormal_regions'
    }
    assert draw_protocol(11, {'abnormal_regions': []})['abnormal_regions'] == []
    # file round trip
    save_protocol(q, tmp_path / 'p.yaml')
    assert load_protocol(tmp_path / 'p.yaml')['abnormal_regions'] == q['abnormal_regions']
    m = make_motion(protocol_preset(complete_protocol({'abnormal_regions': fixed})))
    assert [r['kind'] for r in m.regions] == ['dyskinetic']
    assert complete_protocol({})['abnormal_regions'] == [] and 'abnormal_regions' in ITEMS
    for bad, what in (
        ([{'kind': 'akinetic'}], 'missing key'),
        ('x', 'not a list'),
        ([{'kind': 'akinetic', **SECTOR, 'levels': [0.1, 0.4]}], 'apex tip'),
    ):
        with pytest.raises(ValueError, match=f'abnormal_regions.*{what}'):
            complete_protocol({'shape': 'normal', 'abnormal_regions': bad})


def test_groundtruth_carries_regional_truth(tmp_path):
    regions = [
        {
            'kind': 'dyskinetic',
            'levels': [0.0, 0.3],
            'centre_deg': 0.0,
            'width_deg': 360.0,
            'contraction': -0.4,
        },
        {'kind': 'akinetic', 'levels': [0.4, 0.75], 'centre_deg': 150.0, 'width_deg': 150.0},
    ]
    preset = protocol_preset(
        complete_protocol(
            {
                'abnormal_regions': regions,
                'apex_thickening': 0.3,
                'size': 64,
                'num_phases': 6,
                'sa_slices': 3,
                'la_planes': 1,
            }
        )
    )
    study = simulate_study(preset, snr=None, subplanes=1)
    write_groundtruth(study, tmp_path, n_points=200)
    gt = load_groundtruth(tmp_path)
    reg = gt.regional
    assert [r['kind'] for r in reg['regions']] == ['dyskinetic', 'akinetic']
    seg = {s['segment']: s for s in reg['segments']}
    # The truth's frame is cylindrical: in the cap, err is in-wall (radial) and ell along the
    # axis, the cap's wall normal; the dyskinetic cap thins (ell < 0) and stretches (err > 0).
    assert seg[17]['class'] == 'dyskinetic' and seg[17]['err'] > 0 and seg[17]['ell'] < 0
    assert seg[11]['class'] == 'akinetic' and abs(seg[11]['ecc']) < 0.03
    assert seg[8]['class'] == 'normal' and seg[8]['err'] > 0.2 and seg[8]['ecc'] < -0.1
    assert reg['phase'] == round(study.motion.es_phase)
    assert (
        gt.strain.shape == (6, 200, 3)
        and gt.segments.shape == (200,)
        and gt.contraction.shape == (200,)
    )
    np.testing.assert_allclose(gt.strain[0], 0.0, atol=1e-6)
    np.testing.assert_allclose(
        gt.strain[reg['phase']],
        strain_components(study.motion, gt.material_points, reg['phase']),
        atol=1e-5,
    )
    assert set(gt.segments) <= set(range(1, 18))
    # the dense truth and the stored points' means agree on the strong segment
    again = regional_truth(study.motion, n_points=20000, seed=study.seed)
    assert again['segments'][7]['err'] == seg[8]['err']


@pytest.mark.parametrize(
    'contraction, sign', [(None, 1.0), (0.5, 1.0), (0.0, 0.0), (-0.3, -1.0), (-0.6, -1.0)]
)
def test_apex_cap_in_the_wall_normal_frame(contraction, sign):
    """
    Check the cap's true ES strain in the wall-normal frame.

    A normal (or hypokinetic) cap thickens (Err > 0) and shortens in-wall (Ecc < 0), an akinetic
    one has none, a dyskinetic one thins and stretches; the apical ring above is normal in each
    case (thickens, shortens).
    """
    from mlv_ros.core.analysis import LVAnalyzer
    from mlv_ros.core.sim.regional import truth_frame

    extra = ()
    if contraction is not None:
        kind = {1.0: 'hypokinetic', 0.0: 'akinetic', -1.0: 'dyskinetic'}[sign]
        extra = ({'kind': kind, 'levels': [0.0, 0.12], 'centre_deg': 0.0, 'width_deg': 360.0,
                  'contraction': contraction, 'blend_fraction': 0.04},)
    p = load_preset('normal')
    p['motion']['apex_thickening'] = 0.3
    if extra:
        p['motion']['regions'] = list(extra)
    m = make_motion(p)
    X = m.sample_myocardium(4000, seed=5)
    an = LVAnalyzer(X, truth_frame(m))
    es = int(round(m.es_phase))
    st = an.strain(m.position(X, es), m.deformation_gradient(X, es), segment_frame=True)
    cap = an.segments == 17
    err, ecc = float(np.mean(st['rr'][cap])), float(np.mean(st['cc'][cap]))
    if sign > 0:
        assert err > 0.05 and ecc < -0.03, (err, ecc)
    elif sign == 0:
        assert abs(err) < 0.01 and abs(ecc) < 0.01, (err, ecc)
    else:
        assert err < -0.02 and ecc > 0.02, (err, ecc)
    # the apical ring above the region and its blend (levels 0.2–0.4)
    apical = (an.segments >= 13) & (an.segments <= 16) & (an.coords.h > 0.2)
    assert np.mean(st['rr'][apical]) > 0.1 and np.mean(st['cc'][apical]) < -0.03
    assert np.mean(st['ll'][apical]) < -0.03
