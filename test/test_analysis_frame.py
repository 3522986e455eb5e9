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

"""LV frame and cardiac coordinates: orientation, sign conventions, validation."""

from mlv_ros.core.analysis.frame import (
    angle_bin,
    cardiac_coordinates,
    estimate_frame,
    level_bin,
    LVFrame,
)
from mlv_ros.core.sim.analytic_lv import cylinder_shell, oblique_frame, to_patient
import numpy as np
import pytest

TOL = 1e-12


def test_axis_length_and_inplane_basis():
    fr = LVFrame([1, 2, 3], [1, 2, 83], [1, 0, 5])  # reference has an axial part: removed
    np.testing.assert_allclose(fr.axis, [0, 0, 1], atol=TOL)
    assert fr.length == pytest.approx(80.0, abs=TOL)
    np.testing.assert_allclose(fr.e1, [1, 0, 0], atol=TOL)
    # e2 = e1 × axis = x × z = −y
    np.testing.assert_allclose(fr.e2, [0, -1, 0], atol=TOL)


def test_positive_angle_is_counter_clockwise_seen_from_apex():
    # Apex at the origin, base up +z. A viewer at the apex looks along +z; seen from there
    # +x is on the viewer's left when +y is up, so CCW (left -> top) goes from +x toward −y.
    fr = LVFrame([0, 0, 0], [0, 0, 80], [1, 0, 0])
    pts = np.array([[10.0, 0, 40], [0, -10.0, 40], [-10.0, 0, 40], [0, 10.0, 40]])
    c = cardiac_coordinates(pts, fr)
    np.testing.assert_allclose(np.degrees(c.theta), [0, 90, 180, -90], atol=1e-9)
    # e_c at θ = 0 points toward increasing θ (toward −y here)
    np.testing.assert_allclose(c.e_c[0], [0, -1, 0], atol=TOL)
    np.testing.assert_allclose(c.h, 0.5, atol=TOL)
    np.testing.assert_allclose(c.rho, 10.0, atol=TOL)


def test_unit_vectors_orthonormal_and_radial_outward():
    fr = oblique_frame()
    X, _ = cylinder_shell(fr, n_theta=12, n_z=5)
    c = cardiac_coordinates(X, fr)
    for v in (c.e_r, c.e_c, c.e_l):
        np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=TOL)
    np.testing.assert_allclose(np.einsum('ij,ij->i', c.e_r, c.e_c), 0, atol=TOL)
    np.testing.assert_allclose(np.einsum('ij,ij->i', c.e_r, c.e_l), 0, atol=TOL)
    np.testing.assert_allclose(np.einsum('ij,ij->i', c.e_c, c.e_l), 0, atol=TOL)
    # radial: X − (point on axis at the same level) = ρ e_r
    foot = fr.apex + np.outer(c.axial, fr.axis)
    np.testing.assert_allclose(X - foot, c.rho[:, None] * c.e_r, atol=1e-9)
    # e_c = e_r × e_l (documented: left-handed triple)
    np.testing.assert_allclose(c.e_c, np.cross(c.e_r, c.e_l), atol=TOL)


def test_transmural_from_radii_and_per_bin():
    fr = oblique_frame()
    X, endo = cylinder_shell(fr, r_in=20, r_out=30, n_r=5, n_theta=24, n_z=10)
    c = cardiac_coordinates(X, fr, endo_radius=20.0, epi_radius=30.0)
    np.testing.assert_allclose(c.transmural, (c.rho - 20) / 10, atol=1e-9)
    c2 = cardiac_coordinates(X, fr)  # per (level, angle) bin normalisation
    np.testing.assert_allclose(c2.transmural, c.transmural, atol=1e-9)
    np.testing.assert_allclose(c2.transmural[endo], 0.0, atol=1e-12)


def test_bins_clip_and_wrap():
    np.testing.assert_array_equal(
        level_bin(np.array([-0.2, 0.0, 0.15, 0.999, 1.0, 1.3]), 10), [0, 0, 1, 9, 9, 9]
    )
    np.testing.assert_array_equal(
        angle_bin(np.radians([0, 5, 95, 180, -90, -1]), 4), [0, 0, 1, 2, 3, 3]
    )


@pytest.mark.parametrize(
    'kwargs, match',
    [
        ({'apex': [0, 0, 0], 'base': [0, 0, 0], 'reference': [1, 0, 0]}, 'coincide'),
        ({'apex': [0, 0, 0], 'base': [0, 0, 1], 'reference': [0, 0, 2]}, 'parallel'),
        ({'apex': [0, 0, 0], 'base': [0, 0, 1], 'reference': [0, 0, 0]}, 'zero vector'),
        (
            {'apex': [0, 0, np.nan], 'base': [0, 0, 1], 'reference': [1, 0, 0]},
            'apex is not finite',
        ),
        ({'apex': [0, 0], 'base': [0, 0, 1], 'reference': [1, 0, 0]}, '3 components'),
    ],
)
def test_frame_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LVFrame(**kwargs)


def test_cardiac_coordinates_rejects_bad_points():
    fr = oblique_frame()
    with pytest.raises(ValueError, match=r'shape \(N, 3\)'):
        cardiac_coordinates(np.zeros((4, 2)), fr)
    with pytest.raises(ValueError, match='non-finite rows .*row 1'):
        cardiac_coordinates(np.array([[0, 0, 0], [np.nan, 0, 0]]), fr)
    with pytest.raises(ValueError, match='empty'):
        cardiac_coordinates(np.zeros((0, 3)), fr)


def test_estimate_frame_recovers_axis_direction_of_a_prolate_cloud():
    fr = oblique_frame()
    # tapered cloud: radius grows from apex (small) to base (large)
    z = np.repeat(np.linspace(2, 78, 20), 36)
    th = np.tile(np.linspace(0, 2 * np.pi, 36, endpoint=False), 20)
    X = to_patient(fr, 5 + 0.3 * z, th, z)
    est = estimate_frame(X, reference=fr.e1)
    assert est.axis @ fr.axis > 0.999
    assert np.linalg.norm(est.apex - fr.apex) < 0.1 * fr.length
    assert est.e1 @ fr.e1 > 0.999


def test_plane_levels_and_what_twist_is_extrapolated():
    from mlv_ros.core.analysis.frame import (
        levels_outside,
        plane_level_span,
        twist_extrapolation_note,
        TWIST_EXTRAPOLATION_DEG_PER_TENTH,
    )

    fr = oblique_frame()
    # SA planes ⟂ the axis at 40 % and 85 % of the length, one tilted 20° (its centre still on
    # level 0.6), and an LA plane holding the axis (no crossing: skipped).
    tilt = fr.axis * np.cos(np.radians(20)) + fr.e1 * np.sin(np.radians(20))
    planes = [
        (fr.apex + 0.4 * fr.length * fr.axis + 7 * fr.e2, fr.axis),
        (fr.apex + 0.85 * fr.length * fr.axis, -fr.axis),
        (fr.apex + 0.6 * fr.length * fr.axis, tilt),
        (fr.apex, fr.e1),
    ]
    lo, hi = plane_level_span(fr, planes)
    assert lo == pytest.approx(0.4, abs=1e-12) and hi == pytest.approx(0.85, abs=1e-12)
    assert plane_level_span(fr, planes[3:]) is None
    centres = (np.arange(10) + 0.5) / 10
    # Bins more than half a bin beyond the span: 0.05…0.35 below 0.42, 0.95 above 0.85.
    assert list(np.flatnonzero(levels_outside(centres, (0.42, hi)))) == [0, 1, 2, 3, 9]
    note = twist_extrapolation_note((lo, hi))
    assert '0.40 and 0.85' in note and 'torsion' in note
    # How far beyond the slices each end's farthest bin lies, and how uncertain its twist is:
    # apical 0.40 − 0.05, basal 0.95 − 0.85 of the length, at the stated rate per 0.1.
    rate = TWIST_EXTRAPOLATION_DEG_PER_TENTH
    assert 'apical levels (up to 0.35 of the length below them' in note, note
    assert f'about ±{rate["apical"] * 3.5:.1f}°' in note, note
    assert 'basal levels (up to 0.10 of the length above them' in note, note
    assert f'about ±{rate["basal"] * 1.0:.1f}°' in note, note
    # The solver's end gradients known to ±5°, ±1° per length (1 σ): two σ per 0.1 more.
    noisy = twist_extrapolation_note((lo, hi), 10, (np.radians(5.0), np.radians(1.0)))
    assert f'about ±{(rate["apical"] + 1.0) * 3.5:.1f}°' in noisy, noisy
    assert f'about ±{(rate["basal"] + 0.2) * 1.0:.1f}°' in noisy, noisy
    assert 'apical' in twist_extrapolation_note(
        (0.3, 0.97)
    ) and 'basal' not in twist_extrapolation_note((0.3, 0.97))
    assert twist_extrapolation_note((0.04, 0.96)) == ''
    assert 'not measured at any level' in twist_extrapolation_note(None)
    with pytest.raises(ValueError, match='plane normal'):
        plane_level_span(fr, [(fr.apex, [0, np.nan, 1])])


def test_stated_twist_uncertainty_per_level_matches_the_note():
    from mlv_ros.core.analysis.frame import (
        twist_extrapolation_bound,
        twist_extrapolation_note,
        TWIST_EXTRAPOLATION_DEG_PER_TENTH,
    )

    rate = TWIST_EXTRAPOLATION_DEG_PER_TENTH
    centres = (np.arange(10) + 0.5) / 10
    bound = twist_extrapolation_bound(centres, (0.42, 0.85))
    # 0 where measured (0.45 … 0.85); the rate times the lever beyond: apical bins 0.05 … 0.35
    # (0.37 … 0.07 below the span), the basal bin 0.95 (0.10 above).
    expect = np.zeros(10)
    expect[:4] = rate['apical'] * np.array([3.7, 2.7, 1.7, 0.7])
    expect[9] = rate['basal'] * 1.0
    np.testing.assert_allclose(bound, expect, atol=1e-9)
    # The farthest bin of each end is what the run's sentence states.
    note = twist_extrapolation_note((0.42, 0.85))
    assert f'about ±{bound[0]:.1f}°' in note and f'about ±{bound[9]:.1f}°' in note, note
    assert not twist_extrapolation_bound(centres, (0.04, 0.96)).any()
    assert np.isinf(twist_extrapolation_bound(centres, None)).all()


def test_apex_cap_strain_is_taken_across_its_wall():
    """
    Read an analytic thickening apical cap's strain in the wall-normal frame.

    A spherical shell (radius R, wall 0.25 R), cut at the base 1.7 R above the apex, thickens
    along its normal with the epicardium fixed: r' = R − (1 + k)(R − r). Across the wall the
    Green–Lagrange strain is ½((1 + k)² − 1) everywhere; in the wall ½((r'/r)² − 1) < 0. The
    cap's (17) Err must be the first, its Ecc and Ell the second; in the cylindrical frame its
    "radial" would be mostly in-wall shortening.
    """
    from mlv_ros.core.analysis import LVAnalyzer

    R, k = 40.0, 0.3
    length = 1.7 * R
    rng = np.random.default_rng(3)
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = R * np.cbrt(rng.uniform(0.75**3, 1.0, size=len(d)))
    centre = np.array([0.0, 0.0, R])  # apex at the origin, axis +z
    X = centre + r[:, None] * d
    keep = X[:, 2] <= length
    X, d, r = X[keep], d[keep], r[keep]
    r_new = R - (1.0 + k) * (R - r)
    x = centre + r_new[:, None] * d
    lam_t = r_new / r
    nn = d[:, :, None] * d[:, None, :]
    F = (1.0 + k) * nn + lam_t[:, None, None] * (np.eye(3) - nn)
    an = LVAnalyzer(X, LVFrame([0, 0, 0], [0, 0, length], [1, 0, 0]))
    m = an.phase(x, F, phase_index=1, num_phases=2)
    cap = an.segments == 17
    e_n = 0.5 * ((1.0 + k) ** 2 - 1.0)
    e_t = float(np.mean(0.5 * (lam_t[cap] ** 2 - 1.0)))
    assert e_t < -0.01
    assert m.segment_err[16] == pytest.approx(e_n, abs=0.01)
    assert m.segment_ecc[16] == pytest.approx(e_t, abs=0.01)
    assert m.segment_ell[16] == pytest.approx(e_t, abs=0.01)
    # the cylindrical frame mixes them: its cap "radial" is far from the thickening
    cyl = an.strain(x, F)['rr'][cap].mean()
    assert cyl < e_n - 0.1
    # elsewhere the frame is the cylindrical one, as the truth's
    mid = an.segments == 9
    np.testing.assert_allclose(m.segment_err[8], an.strain(x, F)['rr'][mid].mean(), atol=1e-12)
