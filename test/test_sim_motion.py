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

"""Ground-truth motion of the presets: invertibility, incompressibility, documented ranges."""

from mlv_ros.core.sim import aha_segment_window, load_preset, make_motion
from mlv_ros.core.sim.presets import PRESET_NAMES
import numpy as np
import pytest

PRESETS = list(PRESET_NAMES)


@pytest.fixture(scope='module', params=PRESETS)
def motion(request):
    return make_motion(request.param)


def test_presets_load_and_validate():
    for name in PRESETS:
        p = load_preset(name)
        assert p['name'] == name
    with pytest.raises(FileNotFoundError, match='unknown phantom preset'):
        load_preset('no_such_heart')
    bad = load_preset('normal')
    del bad['motion']['twist_apex_deg']
    with pytest.raises(ValueError, match='motion.twist_apex_deg'):
        load_preset(bad)
    bad = load_preset('normal')
    bad['motion']['es_fraction'] = 0.8
    with pytest.raises(ValueError, match='es_fraction'):
        load_preset(bad)


def test_frame_is_orthonormal_and_right_handed(motion):
    f = motion.frame
    B = np.stack([f.septum, f.e2, -f.long_axis])
    np.testing.assert_allclose(B @ B.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(B) == pytest.approx(1.0)
    np.testing.assert_allclose(np.linalg.norm(f.base_centre - f.apex), motion.length, rtol=1e-12)


def test_inverse_round_trip(motion):
    X = motion.sample_myocardium(2000, seed=3)
    assert motion.inside_myocardium(X).all()
    for ph in np.linspace(0, motion.num_phases, 9):
        x = motion.position(X, ph)
        np.testing.assert_allclose(motion.inverse(x, ph), X, atol=1e-8)


def test_identity_at_ed_and_periodic(motion):
    X = motion.sample_myocardium(500, seed=1)
    np.testing.assert_allclose(motion.position(X, 0), X, atol=1e-12)
    np.testing.assert_allclose(motion.position(X, motion.num_phases), X, atol=1e-12)
    assert motion.activation(motion.es_phase) == pytest.approx(1.0)


def test_det_f_within_documented_tolerance(motion):
    tol = load_preset(motion.preset)['expected']['det_f_tol']
    X = motion.sample_myocardium(1500, seed=2)
    for ph in range(0, motion.num_phases, 3):
        J = np.linalg.det(motion.deformation_gradient(X, ph))
        assert np.all(np.abs(J - 1.0) < tol), (ph, J.min(), J.max())
    # The map is isochoric by construction (module docstring): far tighter than the tolerance.
    J = np.linalg.det(motion.deformation_gradient(X, motion.es_phase))
    assert np.abs(J - 1.0).max() < 1e-5


def test_myocardial_volume_conserved_on_a_grid(motion):
    """Independent of F: count grid points that are myocardium at ED and (via inverse) at ES."""
    f = motion.frame
    R = 1.2 * motion.max_radius
    h = 1.0 if motion.kind == 'cylinder' else 1.5
    g = np.arange(-R, R, h)
    zz = np.arange(-2.0, motion.length + 2.0, h)
    A, B, Z = np.meshgrid(g, g, zz, indexing='ij')
    pts = (
        f.apex
        + np.outer(Z.ravel(), f.long_axis)
        + np.outer(A.ravel(), f.septum)
        + np.outer(B.ravel(), f.e2)
    )
    v_ed = motion.inside_myocardium(pts).sum()
    v_es = motion.inside_myocardium(motion.inverse(pts, motion.es_phase)).sum()
    assert abs(v_es / v_ed - 1.0) < 0.01


def test_documented_ranges(motion):
    exp = load_preset(motion.preset)['expected']
    es = motion.es_phase
    c = motion.level_curves([0.05, 0.5, 0.95], [0, es])

    def within(key, value):
        lo, hi = exp[key]
        assert lo <= value <= hi, (
            f'{motion.preset["name"]}: {key} = {value:.3f} not in [{lo}, {hi}]'
        )

    within('twist_apex_deg', c['twist_deg'][1, 0])
    within('twist_base_deg', c['twist_deg'][1, 2])
    within('net_twist_deg', c['twist_deg'][1, 0] - c['twist_deg'][1, 2])
    within('wall_thickening', c['thickness_mm'][1, 1] / c['thickness_mm'][0, 1] - 1.0)
    within('base_descent_mm', motion.base_descent_mm(es))
    within('mid_endo_radius_ed_mm', c['endo_radius_mm'][0, 1])
    within('mid_wall_ed_mm', c['thickness_mm'][0, 1])
    if 'es_fraction' in exp:
        # ES = the phase of peak endocardial contraction, found on a fine time grid.
        ph = np.linspace(0, motion.num_phases, 201)
        r = motion.level_curves([0.5], ph)['endo_radius_mm'][:, 0]
        within('es_fraction', ph[np.argmin(r)] / motion.num_phases)


def test_twist_sign_seen_from_apex():
    """Apex turns CCW as seen from the apex (looking toward the base), base CW (method notes)."""
    m = make_motion('normal')
    f = m.frame
    view = f.apex - f.base_centre  # points from the base toward the viewer at the apex
    for level, sign in ((0.1, +1), (0.95, -1)):
        th = np.linspace(-np.pi, np.pi, 36, endpoint=False)
        z = np.full_like(th, level * m.length)
        X = f.from_local(0.5 * (m.endo_radius(z) + m.epi_radius(z)), th, z)
        x = m.position(X, m.es_phase)
        p0 = X - f.apex - np.outer((X - f.apex) @ f.long_axis, f.long_axis)
        p1 = x - f.apex - np.outer((x - f.apex) @ f.long_axis, f.long_axis)
        assert np.all(sign * (np.cross(p0, p1) @ view) > 0)


def test_motion_smooth_in_time():
    m = make_motion('normal')
    X = m.sample_myocardium(300, seed=4)
    ph = np.linspace(0, m.num_phases, 401)
    x = np.stack([m.position(X, p) for p in ph])
    v = np.diff(x, axis=0)  # per-step displacement
    a = np.diff(v, axis=0)
    # C¹ activation: no velocity jumps larger than what the curvature of a smooth path gives.
    assert np.abs(a).max() < 0.05 * np.abs(v).max()
    assert np.linalg.norm(x[np.argmin(np.abs(ph - m.es_phase))] - X, axis=1).max() > 5.0


def test_infarct_segment_is_akinetic_and_remote_normal():
    m = make_motion('infarct')
    exp = load_preset('infarct')['expected']
    out = {}
    for seg in (7, 10):
        cen, _, u0, u1 = aha_segment_window(seg)
        th = np.radians(cen)
        z = 0.5 * (u0 + u1) * m.length
        r_en, r_ep = m.endo_radius(z), m.epi_radius(z, th)
        X = m.frame.from_local(np.array([r_en, r_ep]), np.array([th, th]), np.array([z, z]))
        r, _, _ = m.frame.to_local(m.position(X, m.es_phase))
        out[seg] = (r[1] - r[0]) / (r_ep - r_en) - 1.0
    assert exp['infarct_thickening'][0] <= out[7] <= exp['infarct_thickening'][1]
    assert exp['remote_thickening'][0] <= out[10] <= exp['remote_thickening'][1]


def test_sample_myocardium_deterministic():
    m = make_motion('normal')
    np.testing.assert_array_equal(m.sample_myocardium(100, 7), m.sample_myocardium(100, 7))
    assert not np.array_equal(m.sample_myocardium(100, 7), m.sample_myocardium(100, 8))
    with pytest.raises(ValueError):
        m.position(np.zeros((1, 3)), [0, 1])


def _f4(m, X, phase, h):
    """F by a fourth-order central stencil (step h mm): truncation O(h⁴) where the map is C⁵."""
    F = np.empty((len(X), 3, 3))
    for j in range(3):
        d = np.zeros(3)
        d[j] = h

        def at(k):
            return m.position(X + k * d, phase)

        F[:, :, j] = (8.0 * (at(1) - at(-1)) - (at(2) - at(-2))) / (12.0 * h)
    return F


@pytest.mark.parametrize('cap', [None, -0.5])
def test_det_f_is_one_to_1e9_with_the_apex_profile(cap):
    """The map is isochoric to 1e-9 (apex profile, and with a dyskinetic cap)."""
    p = load_preset('normal')
    p['motion']['apex_thickening'] = 0.3
    if cap is not None:
        p['motion']['regions'] = [
            {'kind': 'dyskinetic', 'levels': [0.0, 0.25], 'centre_deg': 0.0,
             'width_deg': 360.0, 'contraction': cap}
        ]
    m = make_motion(p)
    X = m.sample_myocardium(1500, seed=4)
    r, _, z = m.frame.to_local(X)
    u = z / m.length
    # Off the map's features that are C¹ only (a 4th-order stencil is not 4th order there, and
    # they are older than the apex profile): the twist PCHIP's knot, the clip at the base plane,
    # the reference radius's ramp at the endocardial apex; off the axis (cylindrical singularity).
    keep = (
        (r > 3.0)
        & (np.abs(u - p['motion']['twist_zero_level']) > 0.003)
        & (u < 0.995)
        & (np.abs(z - (m.length - m.endo_c) - 0.5) > 1.5)
    )
    d = np.abs(np.linalg.det(_f4(m, X[keep], m.es_phase, 0.01)) - 1.0)
    assert np.percentile(d, 99) < 1e-9 and d.max() < 1e-6, (np.percentile(d, 99), d.max())


@pytest.mark.parametrize('contraction', [None, 0.0, -0.4])
def test_apex_cap_thickens_along_the_axis(contraction):
    """
    The solid apical wall's axis points stretch by exactly 1 + s τ c (c the contraction kept).

    Normal cap (c = 1): thickens by τ; akinetic (c = 0): not at all; dyskinetic (c < 0): thins.
    The base still descends base_descent_mm (the wall above the cap shortens more, ε_w).
    """
    p = load_preset('normal')
    p['motion']['apex_thickening'] = tau = 0.3
    c = 1.0
    if contraction is not None:
        c = contraction
        kind = 'akinetic' if contraction == 0.0 else 'dyskinetic'
        p['motion']['regions'] = [
            {'kind': kind, 'levels': [0.0, 0.3], 'centre_deg': 0.0, 'width_deg': 360.0,
             'contraction': contraction}
        ]
    m = make_motion(p)
    es = m.es_phase
    assert float(m.activation(es)) == 1.0
    z = np.linspace(0.0, 0.1 * m.length, 7)  # up to the thickening slab's top (u_c = 0.1)
    x = m.position(m.frame.from_local(np.zeros_like(z), np.zeros_like(z), z), es)
    np.testing.assert_allclose((x - m.frame.apex) @ m.frame.long_axis, (1.0 + tau * c) * z,
                               atol=1e-9)
    if contraction is None:
        # Endocardial-apex rise of the normal cap: the wall above shortens by ε_w > ε so that
        # the base descends as prescribed (to the mid-wall ring's twist, within 0.05 mm).
        assert m.eps_wall > m.eps
        assert abs(m.base_descent_mm(es) - p['motion']['base_descent_mm']) < 0.05


def test_legacy_cap_without_apex_thickening():
    """Without apex_thickening every level shortens by ε alike (the presets, older studies)."""
    m = make_motion('normal')
    assert m.apex_thickening is None and m.eps_wall == m.eps
    z = np.linspace(0.0, m.length, 9)
    x = m.position(m.frame.from_local(np.zeros_like(z), np.zeros_like(z), z), m.es_phase)
    np.testing.assert_allclose((x - m.frame.apex) @ m.frame.long_axis, (1.0 - m.eps) * z,
                               atol=1e-9)
    p = load_preset('normal')
    for bad in (-0.1, 0.9, True, 'x'):
        p['motion']['apex_thickening'] = bad
        with pytest.raises(ValueError, match='apex_thickening'):
            make_motion(p)
