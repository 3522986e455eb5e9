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

"""Global deformation: shape (eq. 1–3), Jacobians B and J (eq. 7–8, 13) by finite differences."""

from mlv_ros.core.meshless.globals import (
    control_jacobian,
    cylindrical_frame,
    global_shape,
    GlobalParameters,
    KAPPA_MAX,
    matrix_to_quat,
    model_jacobian,
    ModelCoordinates,
    polar_frame,
    quat_from_axis_angle,
    quat_normalize,
    quat_to_matrix,
    reduce_rotation,
    rotation_jacobian,
    shape_jacobian,
    tangent_gram,
    thick_wall_frame,
    world_positions,
)
import numpy as np
import pytest
import scipy.sparse as sp

RNG = np.random.default_rng(7)
N = 40
ALPHA = RNG.uniform(-np.pi / 2, np.pi / 4, N)
BETA = RNG.uniform(-np.pi, np.pi, N)
W = RNG.uniform(0.3, 1.0, N)
ZETA = RNG.uniform(-1, 1, N)
A = np.array([30.0, 0.9, 1.1, 1.3])
TAU = 0.07
# The thick-walled variant at a wall-volume ratio J_a = 0.6 of the affine part (an ES-like
# contraction), cavity fractions across a wall.
THICK = ModelCoordinates(
    'polar',
    ModelCoordinates.polar(ALPHA, BETA, W).basis,
    np.sin(ALPHA),
    RNG.uniform(0.3, 1.0, N),
    float(A[0] ** 3 * np.prod(A[1:]) / 0.6),
)
COORDS = [
    ModelCoordinates.polar(ALPHA, BETA, W),
    ModelCoordinates.cylindrical(BETA, W, ZETA),
    THICK,
]
KINDS = ['polar', 'cylindrical', 'thick-walled']


def test_polar_shape_matches_eq_1_2():
    s = global_shape(COORDS[0], A, TAU)
    e = (
        W[:, None]
        * A[0]
        * np.stack(
            [
                A[1] * np.cos(ALPHA) * np.cos(BETA),
                A[2] * np.cos(ALPHA) * np.sin(BETA),
                A[3] * np.sin(ALPHA),
            ],
            1,
        )
    )
    phi = np.pi * TAU * np.sin(ALPHA)
    ref = np.stack(
        [
            e[:, 0] * np.cos(phi) - e[:, 1] * np.sin(phi),
            e[:, 0] * np.sin(phi) + e[:, 1] * np.cos(phi),
            e[:, 2],
        ],
        1,
    )
    np.testing.assert_allclose(s, ref, rtol=1e-13, atol=1e-12)


@pytest.mark.parametrize('coords', COORDS, ids=KINDS)
def test_shape_jacobian_matches_finite_differences(coords):
    jac = shape_jacobian(coords, A, TAU)
    qs = np.concatenate([A, [TAU]])
    for k in range(5):
        h = 1e-6 * max(1.0, abs(qs[k]))
        qp, qm = qs.copy(), qs.copy()
        qp[k] += h
        qm[k] -= h
        fd = (global_shape(coords, qp[:4], qp[4]) - global_shape(coords, qm[:4], qm[4])) / (2 * h)
        np.testing.assert_allclose(jac[:, :, k], fd, rtol=1e-6, atol=1e-7)


def test_rotation_jacobian_matches_finite_differences():
    q = quat_from_axis_angle([0.3, -1.0, 0.5], 1.1)
    p = RNG.normal(size=(N, 3)) * 10
    b = rotation_jacobian(q, p)
    for k in range(4):
        h = 1e-6
        qp, qm = q.copy(), q.copy()
        qp[k] += h
        qm[k] -= h
        # R(q/|q|): B is the derivative on the unit sphere, and B q = 0
        fd = (p @ quat_to_matrix(qp).T - p @ quat_to_matrix(qm).T) / (2 * h)
        np.testing.assert_allclose(b[:, :, k], fd, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(b @ q, 0.0, atol=1e-12)


@pytest.mark.parametrize('coords', COORDS, ids=KINDS)
def test_model_jacobian_and_tangent_step(coords):
    params = GlobalParameters([1.0, -2.0, 3.0], quat_from_axis_angle([1, 1, 0], 0.4), A, TAU)
    d = RNG.normal(size=(N, 3)) * 0.5
    lmat = reduce_rotation(model_jacobian(params, coords, d), params.rotation)
    x0 = world_positions(params, coords, d)
    for k in range(11):
        h = 1e-6
        step = np.zeros(11)
        step[k] = h
        fd = (
            world_positions(params.stepped(step), coords, d)
            - world_positions(params.stepped(-step), coords, d)
        ) / (2 * h)
        np.testing.assert_allclose(lmat[:, :, k], fd, rtol=1e-5, atol=1e-6)
    assert np.all(np.isfinite(x0))


@pytest.mark.parametrize('coords', COORDS, ids=KINDS)
def test_control_jacobian_is_the_weighted_sum_of_particle_jacobians(coords):
    # L_k = Σ_j φ_kj L_j (eq. 14) against finite differences of the control points' motion
    params = GlobalParameters([1.0, -2.0, 3.0], quat_from_axis_angle([1, 1, 0], 0.4), A, TAU)
    d = RNG.normal(size=(N, 3)) * 0.5
    phi = sp.random(7, N, density=0.3, random_state=3, format='csr')
    lk = reduce_rotation(control_jacobian(params, coords, d, phi), params.rotation)
    for k in range(11):
        step = np.zeros(11)
        step[k] = 1e-6
        fd = phi @ (
            world_positions(params.stepped(step), coords, d)
            - world_positions(params.stepped(-step), coords, d)
        ) / 2e-6
        np.testing.assert_allclose(lk[:, :, k], fd, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize('coords', COORDS, ids=KINDS)
def test_tangent_gram_sums_the_particles_squared_jacobians(coords):
    # Σ_n L_nᵀ L_n from the finite-difference Jacobian of every particle
    params = GlobalParameters([1.0, -2.0, 3.0], quat_from_axis_angle([0, 1, 1], -0.7), A, TAU)
    d = RNG.normal(size=(N, 3)) * 0.5
    fd = np.empty((N, 3, 11))
    for k in range(11):
        step = np.zeros(11)
        step[k] = 1e-6
        fd[:, :, k] = (
            world_positions(params.stepped(step), coords, d)
            - world_positions(params.stepped(-step), coords, d)
        ) / 2e-6
    gram = tangent_gram(params, coords, d)
    np.testing.assert_allclose(gram, gram.T, rtol=0, atol=0)
    np.testing.assert_allclose(gram, np.einsum('nak,nal->kl', fd, fd), rtol=1e-5, atol=1e-4)


def test_quaternion_roundtrip_and_validation():
    for axis, ang in [([0, 0, 1], 0.3), ([1, 2, 3], 2.9), ([1, 0, 0], np.pi)]:
        q = quat_from_axis_angle(axis, ang)
        r = quat_to_matrix(q)
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(r)), r, atol=1e-12)
    with pytest.raises(ValueError, match='non-zero'):
        quat_normalize([0, 0, 0, 0])
    with pytest.raises(ValueError, match='orthonormal'):
        matrix_to_quat(np.diag([1.0, 1.0, -1.0]))


@pytest.mark.parametrize('maker', ['polar', 'cylindrical'])
def test_frames_reproduce_rest_positions(maker):
    pts = RNG.normal(size=(200, 3)) * [10, 8, 20] + [5, -3, 40]
    centre, axis, ref = [5, -3, 40], [0.2, 0.1, 1.0], [1, 0, 0]
    if maker == 'polar':
        frame = polar_frame(pts, centre, axis, ref)
        assert np.linalg.norm(frame.coords.basis, axis=1).max() == pytest.approx(1.0)  # w ∈ [0, 1]
    else:
        frame = cylindrical_frame(pts, centre, axis, ref)
    x = world_positions(frame.params, frame.coords, np.zeros((200, 3)))
    np.testing.assert_allclose(x, pts, atol=1e-10)
    with pytest.raises(ValueError, match='axis'):
        polar_frame(pts, centre, [0, 0, 0])
    with pytest.raises(ValueError, match='parallel'):
        cylindrical_frame(pts, centre, axis, ref_direction=axis)


def _thick_wall_shape(x, rest, a, tau, endo):
    """Return the thick-walled global shape (N, 3) of rest points ``x`` (model frame, mm)."""
    q = x / (rest[0] * rest[1:])
    w = np.linalg.norm(q, axis=1)
    rho, theta = np.hypot(x[:, 0], x[:, 1]), np.arctan2(x[:, 1], x[:, 0])
    polar = ModelCoordinates.polar(np.arcsin(q[:, 2] / w), np.arctan2(q[:, 1], q[:, 0]), w)
    coords = ModelCoordinates(
        'polar',
        polar.basis,
        polar.twist,
        (endo(x[:, 2], theta) / rho) ** 2,
        float(np.prod(rest[0] * rest[1:])),
    )
    return global_shape(coords, a, tau)


@pytest.mark.parametrize(
    'a, tau, angular',
    [
        ([26.0, 0.85, 0.95, 1.3], 0.0, True),  # anisotropic in-plane scale, endocardium in θ
        ([27.0, 0.9, 0.9, 1.35], 0.08, False),  # twisted, in-plane isotropic
        ([31.0, 1.02, 1.02, 1.3], -0.05, False),  # dilating, twisted
    ],
)
def test_thick_wall_shape_keeps_volume(a, tau, angular):
    # Material points in a wall from the endocardial radius ρ_c(z, θ) outward 10 mm, rest
    # a = (30, 1, 1, 4/3): the global map's det ∂s/∂X by central differences is 1 although the
    # affine part changes volume by J_a = a0³ a1 a2 a3 / 40³ (0.64 / 0.74 / 1.16).
    rest = np.array([30.0, 1.0, 1.0, 4.0 / 3.0])

    def endo(z, theta):
        return 18.0 + 0.08 * z + (1.5 * np.cos(theta) if angular else 0.0)

    rng = np.random.default_rng(3)
    z = rng.uniform(-30.0, 15.0, 60)
    theta = rng.uniform(-np.pi, np.pi, 60)
    rho = endo(z, theta) + rng.uniform(0.5, 10.0, 60)
    x = np.stack([rho * np.cos(theta), rho * np.sin(theta), z], 1)
    h = 1e-4
    jac = np.empty((60, 3, 3))
    for k in range(3):
        dx = np.zeros(3)
        dx[k] = h
        jac[:, :, k] = (
            _thick_wall_shape(x + dx, rest, np.asarray(a), tau, endo)
            - _thick_wall_shape(x - dx, rest, np.asarray(a), tau, endo)
        ) / (2 * h)
    ja = a[0] ** 3 * np.prod(a[1:]) / np.prod(rest[0] * rest[1:])
    assert abs(ja - 1.0) > 0.1  # the affine part alone would change the volume
    np.testing.assert_allclose(np.linalg.det(jac), 1.0, atol=1e-6)


def test_thick_wall_frame_keeps_the_rest_shape_and_thickens_the_wall():
    # A polar frame of a thick cylindrical shell (endocardium 20 mm, epicardium 30 mm): at rest
    # the shape is the particles; contracted, the endocardium moves with the affine in-plane
    # scale λ and the wall outside it by r'² − (λ r_c)² = (r² − r_c²) / λ_z: it thickens.
    rng = np.random.default_rng(5)
    n = 4000
    rho = rng.uniform(20.0, 30.0, n)
    theta = rng.uniform(-np.pi, np.pi, n)
    z = rng.uniform(-40.0, 20.0, n)
    pts = np.stack([rho * np.cos(theta), rho * np.sin(theta), z], 1)
    frame = thick_wall_frame(polar_frame(pts, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]))
    np.testing.assert_allclose(
        global_shape(frame.coords, frame.params.a, 0.0), pts, atol=1e-9
    )
    lam, lam_z = 0.8, 0.9
    a = frame.params.a * np.array([1.0, lam, lam, lam_z])
    s = global_shape(frame.coords, a, 0.0)
    r_new = np.hypot(s[:, 0], s[:, 1])
    np.testing.assert_allclose(s[:, 2], lam_z * z, atol=1e-9)
    # The endocardium is the innermost particles' binned radius, smoothed in θ: outside the true
    # 20 mm by the smallest of ~9 random particles per bin, 1 mm in the median, within two
    # particle spacings (1.6 mm here) for 99 % of the particles away from the shell's open ends.
    mid = (z > -30.0) & (z < 10.0)
    r_c = np.sqrt(frame.coords.cavity) * rho
    assert r_c[mid].min() > 19.5 and np.percentile(r_c[mid], 99) < 23.2
    assert np.median(r_c[mid]) < 21.5
    assert frame.coords.cavity.max() < KAPPA_MAX  # no particle's cavity fraction was cut
    expected = np.sqrt((lam * r_c) ** 2 + (rho**2 - r_c**2) / lam_z)
    np.testing.assert_allclose(r_new, expected, rtol=1e-12)
    inner, outer = mid & (rho < 21.0), mid & (rho > 29.0)
    thickness = np.median(r_new[outer]) - np.median(r_new[inner])
    assert thickness > 1.1 * (np.median(rho[outer]) - np.median(rho[inner]))
