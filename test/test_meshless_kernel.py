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

"""Kernel, phyxels, MLS gradient and St Venant–Kirchhoff forces (paper eq. 4, 16–23)."""

from mlv_ros.core.meshless import elastic
from mlv_ros.core.meshless.globals import quat_from_axis_angle, quat_to_matrix
from mlv_ros.core.meshless.kernel import build_phyxels, poly6
from mlv_ros.core.meshless.local import LocalOperators
from mlv_ros.core.meshless.mls import MLSOperator
import numpy as np
import pytest
from scipy import integrate


@pytest.fixture(scope='module')
def cloud():
    rng = np.random.default_rng(0)
    g = np.mgrid[0:10, 0:9, 0:7].reshape(3, -1).T.astype(float)
    x = g + rng.uniform(-0.25, 0.25, g.shape)
    ph = build_phyxels(x)
    return x, ph, MLSOperator(ph)


def test_poly6_normalised_and_compact():
    h = 2.5
    val, _ = integrate.quad(lambda r: 4 * np.pi * r * r * poly6(r, h), 0, h)
    assert val == pytest.approx(1.0, rel=1e-10)
    assert poly6(h, h) == 0.0 and poly6(1.01 * h, h) == 0.0


def test_support_radius_and_volumes(cloud):
    x, ph, _ = cloud
    from scipy.spatial import cKDTree

    d, _ = cKDTree(x).query(x, k=11)
    np.testing.assert_allclose(ph.h, 3.0 * d[:, 1:].mean(axis=1))
    assert not ph.regrouped.any() and not ph.pinv.any()
    assert np.mean(ph.density) == pytest.approx(1.0)
    # interior volumes ≈ the lattice cell (1 mm³) within kernel-density accuracy
    inner = np.all((x > 2.5) & (x < np.array([6.5, 5.5, 3.5])), axis=1)
    assert np.median(ph.volume[inner]) == pytest.approx(1.0, rel=0.1)


def test_mls_gradient_exact_for_affine(cloud):
    x, _, op = cloud
    rng = np.random.default_rng(1)
    a = rng.normal(size=(3, 3)) * 0.2
    u = x @ a.T + rng.normal(size=3)
    np.testing.assert_allclose(op.gradient(u), np.broadcast_to(a, (len(x), 3, 3)), atol=1e-12)
    # full 9N x 3N operator agrees with the compact one
    g = op.full_matrix() @ u.ravel()
    np.testing.assert_allclose(g.reshape(-1, 3, 3), op.gradient(u), atol=1e-12)


def test_rigid_rotation_zero_strain_and_force(cloud):
    x, ph, op = cloud
    r = quat_to_matrix(quat_from_axis_angle([1, 2, 3], 0.7))
    u = x @ r.T + [3.0, -1.0, 2.0] - x
    h = op.gradient(u)
    assert np.abs(elastic.green_lagrange(h)).max() < 1e-12
    lam, mu = elastic.lame_parameters(10.0, 0.45)
    f = elastic.internal_forces(op, u, ph.volume, lam, mu)
    assert np.abs(f).max() < 1e-10


def test_internal_forces_sum_to_zero_and_match_energy_gradient(cloud):
    x, ph, op = cloud
    lam, mu = elastic.lame_parameters(3.0, 0.3)
    rng = np.random.default_rng(2)
    u = 0.1 * rng.normal(size=x.shape) + 0.05 * x @ rng.normal(size=(3, 3))
    f = elastic.internal_forces(op, u, ph.volume, lam, mu)
    assert np.abs(f.sum(axis=0)).max() < 1e-10 * np.abs(f).max()

    def energy(v):
        return elastic.strain_energy(op.gradient(v), ph.volume, lam, mu).sum()

    eps = 1e-6
    for j, a in [(0, 0), (77, 1), (250, 2), (401, 0)]:
        up, um = u.copy(), u.copy()
        up[j, a] += eps
        um[j, a] -= eps
        fd = -(energy(up) - energy(um)) / (2 * eps)
        assert f[j, a] == pytest.approx(fd, rel=1e-6, abs=1e-9)


def test_linear_stiffness_is_energy_hessian_and_diagonal(cloud):
    x, ph, op = cloud
    lam, mu = elastic.lame_parameters(1.0, 0.45)
    rng = np.random.default_rng(3)
    v = rng.normal(size=x.shape)
    t = 1e-6
    # K v = −d/dt f_int(t v) at t = 0
    kv = -elastic.internal_forces(op, t * v, ph.volume, lam, mu) / t
    # the local stage's elasticity (no other term): K, and its diagonal
    local = LocalOperators(op, ph.volume, lam, mu, 0.0)
    stiffness = local.system()
    np.testing.assert_allclose(
        stiffness.internal(v), kv, rtol=1e-4, atol=1e-6 * np.abs(kv).max()
    )
    kd = local.elastic_diagonal()
    for j, a in [(3, 0), (200, 2)]:
        e = np.zeros_like(x)
        e[j, a] = 1.0
        assert kd[j, a] == pytest.approx(stiffness.internal(e)[j, a], rel=1e-12)


def test_green_lagrange_half_convention():
    h = np.array([[[0.1, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]])
    # uniaxial stretch 1.1: E = ½(1.1² − 1) = 0.105 (the paper's eq. 19 would give 0.21)
    assert elastic.green_lagrange(h)[0, 0, 0] == pytest.approx(0.105)


@pytest.mark.parametrize('bad', [np.nan, np.inf])
def test_non_finite_points_rejected(cloud, bad):
    x = cloud[0].copy()
    x[5, 1] = bad
    with pytest.raises(ValueError, match='non-finite'):
        build_phyxels(x)


def test_duplicate_particles_rejected(cloud):
    x = np.vstack([cloud[0], cloud[0][17]])
    with pytest.raises(ValueError, match='duplicate particles'):
        build_phyxels(x)


def test_bad_shapes_and_material_rejected():
    with pytest.raises(ValueError, match=r'shape \(N, 3\)'):
        build_phyxels(np.zeros((10, 2)))
    with pytest.raises(ValueError, match='at least 5'):
        build_phyxels(np.eye(3))
    with pytest.raises(ValueError, match='Poisson'):
        elastic.lame_parameters(1.0, 0.5)
    with pytest.raises(ValueError, match='Young'):
        elastic.lame_parameters(-1.0, 0.3)


def test_coplanar_neighbourhood_falls_back_without_nan():
    # A flat sheet: every moment matrix is rank 2 even after regrouping.
    g = np.mgrid[0:8, 0:8].reshape(2, -1).T.astype(float)
    x = np.column_stack([g, np.zeros(len(g))])
    ph = build_phyxels(x)
    assert ph.regrouped.all() and ph.pinv.all()
    op = MLSOperator(ph)
    a = np.array([[0.1, 0.2, 0.0], [0.0, -0.1, 0.0], [0.3, 0.0, 0.0]])
    h = op.gradient(x @ a.T)
    assert np.all(np.isfinite(h))
    # the in-plane columns of the gradient are still exact; the normal column is zero
    np.testing.assert_allclose(h[:, :, :2], np.broadcast_to(a[:, :2], (len(x), 3, 2)), atol=1e-10)
    np.testing.assert_allclose(h[:, :, 2], 0.0, atol=1e-12)


def test_ill_shaped_phyxel_is_regrouped():
    # A dense, nearly flat layer 2 mm below a lattice block: with h = 3 r̄ the layer's phyxels
    # see only the layer (cond(A) ~ 1e8), so their support is enlarged until it reaches the block.
    g = np.mgrid[0:6, 0:6, 0:6].reshape(3, -1).T.astype(float)
    rng = np.random.default_rng(0)
    s = np.mgrid[0:8, 0:8].reshape(2, -1).T * 0.3 + 1.5
    layer = np.column_stack([s, -2.0 + rng.uniform(-1e-4, 1e-4, len(s))])
    x = np.vstack([g, layer])
    rbar_h = build_phyxels(x, max_regroup=0)
    assert np.all(rbar_h.cond[len(g):] > 1e4)
    ph = build_phyxels(x)
    assert ph.regrouped[len(g):].all() and not ph.regrouped[:len(g)].any()
    assert not ph.pinv.any() and np.all(ph.cond <= 1e4)
    assert np.all(ph.h[len(g):] > 3.0 * ph.rbar[len(g):])


def test_stabilisation_penalty_is_zero_on_affine_and_exact_gradient(cloud):
    x, ph, op = cloud
    # the paper model's per-phyxel weights v_i / (W_i h_i²) (MeshlessModel.local_operators)
    wsum = np.bincount(ph.pair_i, weights=ph.wij, minlength=ph.num_particles)
    s = ph.volume / wsum / ph.h**2
    local = LocalOperators(op, ph.volume, *elastic.lame_parameters(1.0, 0.45), s)
    c = s[ph.pair_i] * ph.wij
    rng = np.random.default_rng(4)
    assert np.abs(local.fit_error_apply(x @ rng.normal(size=(3, 3)).T + 2.0)).max() < 1e-12
    u = rng.normal(size=x.shape)

    def penalty(v):
        h = op.gradient(v)
        r = v[ph.pair_j] - v[ph.pair_i] - np.einsum('pab,pb->pa', h[ph.pair_i], ph.xij)
        return 0.5 * np.sum(c * np.sum(r**2, axis=1))

    g = local.fit_error_apply(u)
    eps = 1e-6
    for j, a in [(7, 1), (300, 2)]:
        up, um = u.copy(), u.copy()
        up[j, a] += eps
        um[j, a] -= eps
        assert g[j, a] == pytest.approx((penalty(up) - penalty(um)) / (2 * eps), rel=1e-6)
