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

"""Green–Lagrange strain in the cardiac frame, MLS deformation gradients, AHA segments."""

from mlv_ros.core.analysis.frame import cardiac_coordinates
from mlv_ros.core.analysis.strain import (
    AHA_SEGMENT_NAMES,
    aha_segments,
    cardiac_strain,
    deformation_gradient_mls,
    green_lagrange,
    mls_neighbourhood,
    segment_means,
)
from mlv_ros.core.sim.analytic_lv import cylinder_shell, cylindrical_motion, oblique_frame
import numpy as np
import pytest

FR = oblique_frame()
X, _ = cylinder_shell(FR, r_in=20, r_out=30, n_r=5, n_theta=48, n_z=20)
C = cardiac_coordinates(X, FR)
EXACT = 1e-12


def strain_of(F):
    return cardiac_strain(green_lagrange(F), C.e_r, C.e_c, C.e_l)


def test_green_lagrange_of_a_stretch_keeps_the_half():
    F = np.diag([1.2, 0.9, 1.0])[None]
    np.testing.assert_allclose(
        green_lagrange(F)[0], np.diag([0.5 * (1.44 - 1), 0.5 * (0.81 - 1), 0]), atol=EXACT
    )


def test_pure_radial_contraction_strain_exact():
    s = 0.85
    _, F = cylindrical_motion(FR, X, s_r=s)
    e = strain_of(F)
    np.testing.assert_allclose(e['rr'], 0.5 * (s * s - 1), atol=EXACT)
    np.testing.assert_allclose(e['cc'], 0.5 * (s * s - 1), atol=EXACT)
    for k in ('ll', 'rc', 'rl', 'cl'):
        np.testing.assert_allclose(e[k], 0, atol=EXACT)


def test_pure_longitudinal_shortening_strain_exact():
    s = 0.88
    _, F = cylindrical_motion(FR, X, s_l=s)
    e = strain_of(F)
    np.testing.assert_allclose(e['ll'], 0.5 * (s * s - 1), atol=EXACT)
    for k in ('rr', 'cc', 'rc', 'rl', 'cl'):
        np.testing.assert_allclose(e[k], 0, atol=EXACT)


def test_uniform_twist_and_rigid_motion_have_zero_strain():
    _, F = cylindrical_motion(FR, X, twist_apex_deg=12, twist_base_deg=12)
    for v in strain_of(F).values():
        np.testing.assert_allclose(v, 0, atol=EXACT)


def test_linear_twist_gives_shear_and_longitudinal_strain():
    # φ(z) = k z: E_cl = ½ ρ k (sign follows e_c, e_l), E_ll = ½ (ρ k)²
    _, F = cylindrical_motion(FR, X, twist_apex_deg=10, twist_base_deg=-3)
    k = np.radians(-13.0) / FR.length
    e = strain_of(F)
    np.testing.assert_allclose(e['cl'], 0.5 * C.rho * k, atol=1e-12)
    np.testing.assert_allclose(e['ll'], 0.5 * (C.rho * k) ** 2, atol=1e-12)
    np.testing.assert_allclose(e['cc'], 0, atol=EXACT)


def test_mls_gradient_is_exact_for_affine_motion():
    rng = np.random.default_rng(3)
    A = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    x = X @ A.T + np.array([5.0, -2.0, 1.0])
    F = deformation_gradient_mls(X, x, k=12)
    np.testing.assert_allclose(F, np.broadcast_to(A, F.shape), atol=1e-9)


def test_mls_gradient_rigid_rotation_zero_strain_and_reuse():
    th = np.radians(30)
    R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    nb = mls_neighbourhood(X, k=10)
    F = deformation_gradient_mls(X, X @ R.T - 7.0, neighbourhood=nb)
    np.testing.assert_allclose(green_lagrange(F), 0, atol=1e-10)


def test_mls_gradient_close_to_analytic_for_radial_contraction_with_twist():
    x, F_true = cylindrical_motion(FR, X, s_r=0.85, s_l=0.9, twist_apex_deg=10, twist_base_deg=-3)
    F = deformation_gradient_mls(X, x)
    # the motion is not affine (ρ-dependent rotation): first-order MLS error on a 2.5 mm lattice
    e_est, e_true = strain_of(F), strain_of(F_true)
    for k in ('rr', 'cc', 'll'):
        assert np.max(np.abs(e_est[k] - e_true[k])) < 2e-3


def test_mls_degenerate_neighbourhood_is_nan_not_garbage():
    flat = np.c_[np.random.default_rng(0).uniform(size=(50, 2)), np.zeros(50)]  # coplanar
    F = deformation_gradient_mls(flat, flat * 0.9)
    assert np.all(np.isnan(F))


def test_mls_validation():
    with pytest.raises(ValueError, match='at least 13 particles'):
        deformation_gradient_mls(X[:5], X[:5])
    with pytest.raises(ValueError, match='same shape'):
        deformation_gradient_mls(X, X[:-1])
    with pytest.raises(ValueError, match=r'\(N, 3, 3\)'):
        green_lagrange(np.eye(3))


def test_aha_assignment_of_hand_placed_points():
    # Reference = inferior RV–LV junction (θ = 0); anterior insertion at θ = −120°.
    # ψ = θ + 120 (mod 360): anteroseptal 0–60, inferoseptal 60–120, inferior 120–180,
    # inferolateral 180–240, anterolateral 240–300, anterior 300–360.
    theta_deg = np.array(
        [
            -90,
            -30,
            30,
            90,
            150,
            -150,  # ψ = 30, 90, 150, 210, 270, 330
            -90,
            30,  # mid ring: ψ = 30, 150
            -60,
            30,
            120,
            -150,  # apical: ψ = 60, 150, 240, 330
            0.0,
        ]
    )
    h = np.array([0.95] * 6 + [0.55] * 2 + [0.2] * 4 + [0.05])
    seg = aha_segments(h, np.radians(theta_deg))
    np.testing.assert_array_equal(seg, [2, 3, 4, 5, 6, 1, 8, 10, 14, 15, 16, 13, 17])
    assert AHA_SEGMENT_NAMES[seg[0] - 1] == 'basal anteroseptal'
    assert AHA_SEGMENT_NAMES[seg[8] - 1] == 'apical septal'
    # level thirds above the cap: [0.1, 0.4) apical, [0.4, 0.7) mid, [0.7, 1] basal
    np.testing.assert_array_equal(
        aha_segments(np.array([0.099, 0.1, 0.399, 0.4, 0.7, 1.2]), np.radians([-90.0] * 6)),
        [17, 14, 14, 8, 2, 2],
    )
    # a mid-septum reference shifts the origin by 60°
    assert aha_segments(np.array([0.95]), np.radians([0.0]), aha_origin_deg=-60.0)[0] == 3


def test_aha_covers_all_segments_on_a_full_shell():
    seg = aha_segments(C.h, C.theta, FR.aha_origin_deg)
    assert set(np.unique(seg)) == set(range(1, 18))


def test_segment_means_and_fill():
    seg = np.array([1, 1, 2, 17])
    means, cnt = segment_means(np.array([0.1, 0.3, -0.2, np.nan]), seg, fill=0.0)
    np.testing.assert_allclose(means[:2], [0.2, -0.2], atol=EXACT)
    assert means[16] == 0.0 and cnt[16] == 0  # NaN skipped -> empty -> fill
    assert cnt.sum() == 3 and np.all(np.isfinite(means))
    with pytest.raises(ValueError, match='1..17'):
        segment_means(np.zeros(1), np.array([18]))
