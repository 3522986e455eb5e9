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
Motion analysis against analytic motions of lattice LV-like shells.

Displacement decomposition, per-level twist / radius, LA radius, torsion and cavity volume
against analytic motions of lattice LV-like shells (exact up to rounding unless stated).
"""

from mlv_ros.core.analysis.frame import LVFrame
from mlv_ros.core.analysis.motion import (
    cavity_volume,
    decompose_displacement,
    endocardial_mask,
    la_radius,
    level_metrics,
    torsion,
)
from mlv_ros.core.sim.analytic_lv import (
    cylinder_shell,
    cylindrical_motion,
    oblique_frame,
    prolate_shell,
    to_cylindrical,
)
import numpy as np
import pytest

FR = oblique_frame(length=80.0)
X_CYL, ENDO_CYL = cylinder_shell(FR, r_in=20, r_out=30, n_r=5, n_theta=72, n_z=40)
EXACT = 1e-9


def test_pure_twist_ccw_from_apex_is_positive_and_exact():
    x, _ = cylindrical_motion(FR, X_CYL, twist_apex_deg=7.5, twist_base_deg=7.5)
    lv = level_metrics(X_CYL, x, FR, levels=10)
    assert lv['twist_deg'].shape == (10,)
    np.testing.assert_allclose(lv['twist_deg'], 7.5, atol=EXACT)
    np.testing.assert_allclose(lv['longitudinal_displacement_mm'], 0, atol=EXACT)
    np.testing.assert_allclose(lv['radial_displacement_mm'], 0, atol=EXACT)
    np.testing.assert_allclose(
        lv['circumferential_displacement_mm'], 25.0 * np.radians(7.5), atol=EXACT
    )
    np.testing.assert_allclose(lv['sa_radius_mm'], 25.0, atol=EXACT)  # mean of 20..30 lattice
    # the sign really is "CCW seen from the apex": θ increases by the applied angle
    _, th0, _ = to_cylindrical(FR, X_CYL)
    _, th1, _ = to_cylindrical(FR, x)
    np.testing.assert_allclose(np.degrees(np.angle(np.exp(1j * (th1 - th0)))), 7.5, atol=EXACT)
    d = decompose_displacement(X_CYL, x, FR)
    np.testing.assert_allclose(d[:, :2], 0, atol=EXACT)


def test_clockwise_rotation_about_apex_to_base_axis_is_negative_twist():
    # Right-handed rotation about +axis (apex→base) by +5° looks clockwise from the apex.
    a = FR.axis
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(5.0)
    R = np.eye(3) + np.sin(t) * K + (1 - np.cos(t)) * K @ K
    x = (X_CYL - FR.apex) @ R.T + FR.apex
    np.testing.assert_allclose(level_metrics(X_CYL, x, FR)['twist_deg'], -5.0, atol=EXACT)


def test_linear_twist_gives_level_twists_and_exact_torsion():
    x, _ = cylindrical_motion(FR, X_CYL, twist_apex_deg=10.0, twist_base_deg=-3.0)
    lv = level_metrics(X_CYL, x, FR, levels=10)
    expected = 10.0 - 13.0 * lv['level_position']  # lattice levels centred in each bin
    np.testing.assert_allclose(lv['twist_deg'], expected, atol=1e-9)
    # torsion = (base − apex)/ED distance = −13° over 80 mm = −1.625 °/cm
    assert torsion(lv['twist_deg'], lv['axial_ed_mm']) == pytest.approx(-13.0 / 8.0, abs=1e-9)


def test_pure_radial_contraction():
    s = 0.8
    x, _ = cylindrical_motion(FR, X_CYL, s_r=s)
    lv = level_metrics(X_CYL, x, FR)
    np.testing.assert_allclose(lv['sa_radius_mm'], 25.0 * s, atol=EXACT)
    np.testing.assert_allclose(lv['radial_displacement_mm'], 25.0 * (s - 1), atol=EXACT)
    np.testing.assert_allclose(lv['twist_deg'], 0, atol=EXACT)
    np.testing.assert_allclose(lv['circumferential_displacement_mm'], 0, atol=EXACT)
    np.testing.assert_allclose(lv['longitudinal_displacement_mm'], 0, atol=EXACT)
    v0 = cavity_volume(X_CYL, X_CYL, FR, endo_mask=ENDO_CYL)
    assert cavity_volume(X_CYL, x, FR, endo_mask=ENDO_CYL) == pytest.approx(s * s * v0, rel=1e-12)


def test_pure_longitudinal_shortening_about_the_apex():
    s = 0.85
    x, _ = cylindrical_motion(FR, X_CYL, s_l=s)
    lv = level_metrics(X_CYL, x, FR)
    np.testing.assert_allclose(
        lv['longitudinal_displacement_mm'], (s - 1) * lv['axial_ed_mm'], atol=EXACT
    )
    np.testing.assert_allclose(lv['radial_displacement_mm'], 0, atol=EXACT)
    np.testing.assert_allclose(lv['twist_deg'], 0, atol=EXACT)
    assert la_radius(x, FR) == pytest.approx(s * la_radius(X_CYL, FR), abs=EXACT)
    assert la_radius(X_CYL, FR) == pytest.approx(40.0, abs=EXACT)
    v0 = cavity_volume(X_CYL, X_CYL, FR, endo_mask=ENDO_CYL)
    assert cavity_volume(X_CYL, x, FR, endo_mask=ENDO_CYL) == pytest.approx(s * v0, rel=1e-12)


def test_rigid_translation_has_no_twist_and_keeps_radius_and_volume():
    shift = np.array([3.0, -4.0, 2.5])
    x = X_CYL + shift
    lv = level_metrics(X_CYL, x, FR)
    np.testing.assert_allclose(lv['twist_deg'], 0, atol=EXACT)
    np.testing.assert_allclose(lv['sa_radius_mm'], 25.0, atol=EXACT)
    np.testing.assert_allclose(lv['longitudinal_displacement_mm'], shift @ FR.axis, atol=EXACT)
    v0 = cavity_volume(X_CYL, X_CYL, FR)
    assert cavity_volume(X_CYL, x, FR) == pytest.approx(v0, rel=1e-12)


def test_cylinder_cavity_volume_within_one_percent():
    # π r² L = π·20²·80 mm³ = 100.53 ml; 36 sectors under-estimate a circle by ≈ 0.8 %.
    exact = np.pi * 20.0**2 * 80.0 / 1000.0
    v = cavity_volume(X_CYL, X_CYL, FR, endo_mask=ENDO_CYL)
    assert v == pytest.approx(exact, rel=0.01)
    assert v < exact  # polygon inscribed in the circle
    # the default (innermost particle per sector: one of the 4 endocardial lattice points of
    # each slab × sector) picks endocardial points only, one per sector
    m = endocardial_mask(X_CYL, FR)
    assert m.sum() == 20 * 36 and np.all(ENDO_CYL[m])
    assert cavity_volume(X_CYL, X_CYL, FR) == pytest.approx(exact, rel=0.01)


def test_prolate_cavity_volume_within_two_percent():
    fr = oblique_frame(length=80.0)
    X, endo = prolate_shell(fr, a_in=25, c_in=70, a_out=35, c_out=80)
    exact = 2.0 / 3.0 * np.pi * 25.0**2 * 70.0 / 1000.0  # 91.63 ml
    assert cavity_volume(X, X, fr, endo_mask=endo) == pytest.approx(exact, rel=0.02)
    # and it follows a uniform contraction exactly: s_r² s_l
    x, _ = cylindrical_motion(fr, X, s_r=0.9, s_l=0.95)
    v0 = cavity_volume(X, X, fr, endo_mask=endo)
    assert cavity_volume(X, x, fr, endo_mask=endo) == pytest.approx(0.81 * 0.95 * v0, rel=1e-12)


def test_random_cloud_volume_default_mask_bias_is_bounded():
    # Uniform random cloud, no endocardial flags: innermost particle per sector lies
    # outside the true surface, so the volume is over-estimated, here by < 8 %.
    rng = np.random.default_rng(1)
    n = 10000
    r = np.sqrt(rng.uniform(20.0**2, 30.0**2, n))
    from mlv_ros.core.sim.analytic_lv import to_patient

    X = to_patient(FR, r, rng.uniform(-np.pi, np.pi, n), rng.uniform(0, 80, n))
    exact = np.pi * 20.0**2 * 80.0 / 1000.0
    v = cavity_volume(X, X, FR)
    assert exact < v < 1.08 * exact


def test_empty_levels_are_left_out():
    keep = FR.level(X_CYL) > 0.3  # nothing in bins 0..2
    lv = level_metrics(X_CYL[keep], X_CYL[keep], FR, levels=10)
    np.testing.assert_allclose(lv['level_position'], np.arange(3, 10) / 10 + 0.05, atol=EXACT)
    assert all(v.shape == (7,) for v in lv.values())


def test_torsion_edge_cases():
    assert torsion([5.0], [10.0]) == 0.0
    with pytest.raises(ValueError, match='equal length'):
        torsion([1.0, 2.0], [1.0])


@pytest.mark.parametrize(
    'fn',
    [
        lambda X, x:level_metrics(X, x, FR),
        lambda X, x:decompose_displacement(X, x, FR),
        lambda X, x:cavity_volume(X, x, FR),
    ],
)
def test_bad_inputs_raise_clear_errors(fn):
    x = X_CYL.copy()
    x[5, 1] = np.nan
    with pytest.raises(ValueError, match='x .*non-finite rows .*row 5'):
        fn(X_CYL, x)
    with pytest.raises(ValueError, match='same shape'):
        fn(X_CYL, X_CYL[:-1])
    with pytest.raises(ValueError, match=r'shape \(N, 3\)'):
        fn(X_CYL[:, :2], X_CYL[:, :2])


def test_endo_mask_validation():
    with pytest.raises(ValueError, match='boolean array'):
        cavity_volume(X_CYL, X_CYL, FR, endo_mask=np.ones(3, bool))
    with pytest.raises(ValueError, match='selects no particles'):
        cavity_volume(X_CYL, X_CYL, FR, endo_mask=np.zeros(len(X_CYL), bool))


def test_frame_independent_of_patient_orientation():
    # the same cloud and motion in an axis-aligned frame give identical metrics
    fr2 = LVFrame([0, 0, 0], [0, 0, 80], [1, 0, 0])
    X2, _ = cylinder_shell(fr2)
    x1, _ = cylindrical_motion(FR, X_CYL, 0.9, 0.9, 8, -2)
    x2, _ = cylindrical_motion(fr2, X2, 0.9, 0.9, 8, -2)
    a, b = level_metrics(X_CYL, x1, FR), level_metrics(X2, x2, fr2)
    for k in a:
        np.testing.assert_allclose(a[k], b[k], atol=1e-9)


def test_layered_cloud_with_empty_slabs_and_layers_on_slab_boundaries():
    # 10 layers at 4, 12, …, 76 mm: every layer sits exactly on a boundary of the 20 volume
    # slabs (4 mm) and every other slab is empty; the volume must still cover the full axis.
    X, endo = cylinder_shell(FR, r_in=20, r_out=30, n_r=3, n_theta=72, n_z=10)
    exact = np.pi * 20.0**2 * 80.0 / 1000.0
    v = cavity_volume(X, X, FR, endo_mask=endo)
    assert v == pytest.approx(exact, rel=0.01)
    x, _ = cylindrical_motion(FR, X, s_r=0.9, s_l=0.8)
    assert cavity_volume(X, x, FR, endo_mask=endo) == pytest.approx(0.81 * 0.8 * v, rel=1e-12)


def test_pure_twist_exact_on_a_random_cloud():
    # level centroids are off-axis for a random cloud, but rotate with it: still exact
    rng = np.random.default_rng(7)
    from mlv_ros.core.sim.analytic_lv import to_patient

    X = to_patient(
        FR, rng.uniform(18, 32, 3000), rng.uniform(-np.pi, np.pi, 3000), rng.uniform(0, 80, 3000)
    )
    x, _ = cylindrical_motion(FR, X, twist_apex_deg=-6.0, twist_base_deg=-6.0)
    lv = level_metrics(X, x, FR)
    np.testing.assert_allclose(lv['twist_deg'], -6.0, atol=1e-9)
    np.testing.assert_allclose(lv['radial_displacement_mm'], 0, atol=1e-9)
