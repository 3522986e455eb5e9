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
The phantom's right ventricle and the septum found from it.

Small ED short-axis stacks of drawn protocols (any septum direction, grid, pixel size, contrast,
SA orientation): the RV's insertion points are in the truth, and the septum found in the images
agrees with it; without an RV the anatomical prior is kept and the result says why.
"""

import math

from mlv_ros.core.registration import segment as seg
from mlv_ros.core.registration.anatomy import estimate_septum, SOURCE_DETECTED, SOURCE_PRIOR
from mlv_ros.core.registration.initialise import default_reference
from mlv_ros.core.sim.imaging import ImageSynthesizer, plan_slices
from mlv_ros.core.sim.motion import make_motion
from mlv_ros.core.sim.protocol import complete_protocol, draw_protocol, protocol_preset
from mlv_ros.core.types import VIEW_SA
import numpy as np
import pytest

# A small stack that still segments (4 SA slices of 144² at 1.8 mm, centred on the heart).
SMALL = {'sa_slices': 4, 'size': 144, 'pixel_spacing_mm': 1.8, 'sa_fov_shift_mm': [0.0, 0.0]}


def _angle_deg(a, b, axis):
    a = np.asarray(a) - (np.asarray(a) @ axis) * axis
    b = np.asarray(b) - (np.asarray(b) @ axis) * axis
    return math.degrees(
        math.acos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))
    )


def _ed_stack(protocol):
    pre = protocol_preset(protocol)
    m = make_motion(pre)
    im, f = pre['imaging'], m.frame
    rng = np.random.default_rng(0)
    out = []
    for s in plan_slices(m, im):
        if s.view != VIEW_SA:
            continue
        img = ImageSynthesizer(m, s, im['size'], im, subplanes=1).render(0, 0.0, im['snr'], rng)
        g = s.geometry
        x = (
            f.apex
            + ((g.pixel_to_patient(np.zeros(2))[0] - f.apex) @ g.normal)
            / (f.long_axis @ g.normal)
            * f.long_axis
        )
        sg = seg.segment_sa(img, g.patient_to_pixel(x)[0], g.row_spacing)
        if sg.ok:
            out.append((img, sg, g))
    return m, out


# Seeds' draws: 2004 dilated, no background, bright blood, 1.27 mm; 2008 normal, tagged
# background, dark blood (0.32), SNR 14; 2010 infarct, tagged background, 1.98 mm pixels.
@pytest.mark.parametrize('seed', [2004, 2008, 2010])
def test_septum_found_from_the_rv(seed):
    p = draw_protocol(seed, {'right_ventricle': True, 'abnormal_regions': [], **SMALL})
    m, stack = _ed_stack(p)
    axis = m.frame.long_axis
    truth = m.rv_insertions()
    assert _angle_deg(
        truth['anterior_direction'], truth['inferior_direction'], axis
    ) == pytest.approx(120.0)
    est = estimate_septum(stack, axis, default_reference(axis, rotate_deg=0.0))
    assert est.source == SOURCE_DETECTED, est.reason
    assert 0.3 < est.confidence <= 1.0
    # The septum (the insertions' bisector) within 6°; each insertion within 20° (the blood
    # tapers to nothing there, so the detected arc is short: 76–113° of 120 on 15 seeds).
    assert _angle_deg(est.septum, truth['septum_direction'], axis) < 6.0
    assert _angle_deg(est.anterior, truth['anterior_direction'], axis) < 20.0
    assert _angle_deg(est.inferior, truth['inferior_direction'], axis) < 20.0
    d = est.to_dict()
    assert d['source'] == 'detected' and d['slices_used'] >= 2


def test_no_rv_keeps_the_prior_and_says_why():
    p = draw_protocol(2008, {'right_ventricle': False, 'abnormal_regions': [], **SMALL})
    m, stack = _ed_stack(p)
    axis = m.frame.long_axis
    prior = default_reference(axis, rotate_deg=0.0)
    est = estimate_septum(stack, axis, prior)
    assert est.source == SOURCE_PRIOR and est.confidence == 0.0 and 'no RV found' in est.reason
    np.testing.assert_allclose(est.septum, prior / np.linalg.norm(prior), atol=1e-12)
    assert m.rv_insertions() is None


def test_rv_is_drawn_and_leaves_the_rest_of_the_protocol_and_the_lv_alone():
    draws = [draw_protocol(s)['right_ventricle'] for s in range(40)]
    assert 0 < sum(draws) < 40
    a, b = (
        draw_protocol(7, {'right_ventricle': False}),
        draw_protocol(7, {'right_ventricle': True}),
    )

    def others(p):
        return {k: v for k, v in p.items() if k != 'right_ventricle'}

    assert others(a) == others(b)
    assert complete_protocol({})['right_ventricle'] is False  # the presets' own studies have none
    ma = make_motion(protocol_preset(complete_protocol({'septum_deg': 40.0})))
    mb = make_motion(
        protocol_preset(complete_protocol({'septum_deg': 40.0, 'right_ventricle': True}))
    )
    X = mb.frame.from_local(np.full(5, 60.0), np.radians([-90, -30, 0, 30, 90]), np.full(5, 50.0))
    assert np.array_equal(
        ma.inside_myocardium(X), mb.inside_myocardium(X)
    )  # the LV truth is unchanged
    # The RV sits on the septal side, centred on the septum, between its insertions (θ ±60°),
    # its blood next to the LV epicardium and its free wall beyond; nothing on the lateral side.
    r_epi = float(mb.epi_radius(50.0))
    wall, blood = mb.inside_rv(
        mb.frame.from_local(
            np.array([r_epi + 2.0, r_epi + 2.0, r_epi + 2.0]),
            np.radians([0.0, 70.0, 180.0]),
            np.full(3, 50.0),
        )
    )
    assert blood.tolist() == [True, False, False] and not wall.any()
    ins = mb.rv_insertions()
    assert (ins['anterior_deg'], ins['inferior_deg']) == pytest.approx((-60.0, 60.0))
    with pytest.raises(ValueError, match='geometry.rv.span_deg'):
        make_motion(
            {
                **protocol_preset(complete_protocol({})),
                'geometry': {
                    **protocol_preset(complete_protocol({}))['geometry'],
                    'rv': {'span_deg': 10},
                },
            }
        )


def test_registration_orients_the_model_by_the_detected_septum():
    """
    Check that register_ed places β = 0 and the AHA anterior insertion from the septum.

    register_ed: with an RV the model's β = 0 (the inferior insertion) lies 60° CCW from the
    detected septum, within a few degrees of the truth's inferior insertion; the analysis frame of
    the registered model then puts the AHA anterior insertion where the truth has it.
    """
    from mlv_ros.core.registration import register_ed
    from mlv_ros.core.sim.study import simulate_study
    from mlv_ros.core.analysis.frame import lv_frame_axes

    p = draw_protocol(
        2002,
        {
            'right_ventricle': True,
            'abnormal_regions': [],
            'sa_slices': 5,
            'la_planes': 3,
            'size': 144,
            'pixel_spacing_mm': 1.8,
            'sa_fov_shift_mm': [0.0, 0.0],
            'la_fov_shift_mm': [0.0, 0.0],
        },
    )
    st = simulate_study(protocol_preset(p), snr=p['snr'], num_phases=2, subplanes=1, seed=1)
    res = register_ed([f for f in st.frames if f.phase_index == 0], num_particles=1000, seed=0)
    assert res.septum is not None and res.septum.source == SOURCE_DETECTED, res.septum
    m = make_motion(protocol_preset(p))
    axis, truth = m.frame.long_axis, m.rv_insertions()
    _, _, ref = lv_frame_axes(res.particles, res.state.rotation)
    assert _angle_deg(ref, truth['inferior_direction'], axis) < 8.0
    assert _angle_deg(res.septum.septum, truth['septum_direction'], axis) < 6.0
