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
The local stage of :mod:`mlv_ros.core.meshless.local` against the reference copies.

The local stage of :mod:`mlv_ros.core.meshless.local` against the reference copies of the
stages it replaced (``bench/reference_local.py``): same operator, same solutions.
"""

from pathlib import Path
import sys

from mlv_ros.core import tracking
from mlv_ros.core.meshless import _fused, cylindrical_frame, MeshlessModel
from mlv_ros.core.meshless import plane_projectors
from mlv_ros.core.meshless.local import (
    CoarseSpace,
    cofactors_3x3,
    farthest_point_aggregates,
    LocalOperators,
    rigid_mode_eps,
    sandwich_3x3,
    symmetric_inverse_3x3,
)
from mlv_ros.core.sim import simulate_study
from mlv_ros.core.sim.paper_cylinder import (
    control_subset,
    deform,
    H_CYL,
    R_OUTER,
    sample_cylinder_shell,
)
import numpy as np
import pytest
import scipy.sparse as sp
from test_tracking import observed, referenced_tracker

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'bench'))
from reference_local import (  # noqa: E402, I100
    linear_stiffness_apply,  # noqa: E402, I100
    PhantomSystemReference,
    stabilisation_apply,
    stabilisation_weights,
    tracker_fit_error_matrix,
    tracker_local_solve,
)


@pytest.fixture(scope='module')
def study():
    return simulate_study('normal', snr=20, quick=True)


def test_operators_equal_the_assembled_fit_error_and_matrix_free_stiffness(study):
    _, tr, _ = referenced_tracker(study, n=800)
    m, rng = tr.model, np.random.default_rng(0)
    L = tracker_fit_error_matrix(m)
    np.testing.assert_allclose(tr._local.fit_error_diagonal, L.diagonal(), rtol=1e-10)
    system = tr._local.system(fit_error=2.0, eps=0.5)
    for u in (rng.normal(size=(tr.num_particles, 3)), np.sin(tr.rest / 15.0)):  # rough and smooth
        ref = (
            linear_stiffness_apply(m.operator, u, m.phyxels.volume, m.lam, m.mu)
            + 2.0 * (L @ u)
            + 0.5 * u
        )
        np.testing.assert_allclose(system.internal(u), ref, atol=1e-9 * np.abs(ref).max())
    # the paper model's stabilisation is the same penalty with other weights
    coef = m.stabilisation * m.mu * stabilisation_weights(m.operator, m.phyxels.volume)
    u = rng.normal(size=(tr.num_particles, 3))
    ref = stabilisation_apply(m.operator, u, coef)
    np.testing.assert_allclose(
        m.stabilisation * m.mu * m.local_operators.fit_error_apply(u),
        ref,
        atol=1e-9 * np.abs(ref).max(),
    )


def test_block_diagonal_is_the_exact_diagonal_block_of_every_term(study):
    """Check the preconditioner's 3 × 3 blocks against ``A e`` on unit vectors, all terms on."""
    _, tr, _ = referenced_tracker(study, n=800)
    n, rng = tr.num_particles, np.random.default_rng(1)
    # one cofactor and one axial measure for all particles: then the blocks are exact
    C = np.broadcast_to(np.eye(3) + 0.2 * rng.normal(size=(3, 3)), (n, 3, 3))
    M = rng.normal(size=(3, 3))
    ctrl = tr.model.attach(tr.rest[rng.choice(n, 40, replace=False)])
    P = plane_projectors(rng.normal(size=(40, 3)), 40)
    S = np.broadcast_to(rng.normal(size=(3, 3)), (n, 3, 3))
    for axial, shear in (
        ((7.0, np.array([0.0, 0.6, 0.8])), None),
        ((7.0, np.broadcast_to(M, (n, 3, 3))), (5.0, S)),
    ):
        system = tr._local.system(
            fit_error=3.0,
            volume=(50.0, C, None),
            axial=axial,
            data=(2.0, ctrl.weights, P),
            eps=0.1,
            shear=shear,
        )
        scale = np.abs(system.block_diagonal).max()
        for i in rng.choice(n, 6, replace=False):
            for c in range(3):
                e = np.zeros((n, 3))
                e[i, c] = 1.0
                np.testing.assert_allclose(
                    system.block_diagonal[i, :, c], system.matvec(e)[i], atol=1e-10 * scale
                )
        np.testing.assert_allclose(
            system._block_inv @ system.block_diagonal,
            np.broadcast_to(np.eye(3), (n, 3, 3)),
            atol=1e-8,
        )
    with pytest.raises(ValueError, match='coarse or coarse_correction'):
        tr._local.system(coarse=tr._coarse, coarse_correction=lambda r: r)


def test_shear_term_is_its_strain_measure_squared_for_affine_fields(study):
    """
    Check the ``shear`` term's energy against ``½ k_s Σ_i v_i (M_i : G)²`` for ``u = G X``.

    The MLS gradient reproduces an affine field's gradient ``G`` exactly, so the term's energy
    ``½ uᵀ A_s u`` (the system with it less the one without) is that sum to rounding, for any
    measures ``M_i``; the tracker's own measures (``a r_iᵀ``) read ``∂u_a/∂r``: a transmural
    axial shear ``u = γ (r · X) a`` costs ``½ k_s γ² Σ v_i`` and an axial stretch nothing.
    """
    _, tr, _ = referenced_tracker(study, n=800, global_thickening=True)
    n, rng = tr.num_particles, np.random.default_rng(3)
    vol = tr.model.phyxels.volume
    base = tr._local.system(fit_error=3.0, eps=0.1)

    def energy(u, shear):
        extra = tr._local.system(fit_error=3.0, eps=0.1, shear=shear).matvec(u) - base.matvec(u)
        return 0.5 * float(np.sum(u * extra))

    M = rng.normal(size=(n, 3, 3))
    G = rng.normal(size=(3, 3))
    u = tr.rest @ G.T
    expect = 0.5 * 5.0 * float(np.sum(vol * np.einsum('nab,ab->n', M, G) ** 2))
    assert energy(u, (5.0, M)) == pytest.approx(expect, rel=1e-8)
    # a transmural shear along the rest long axis: u_a = γ (r_i · X) about the rest frame
    rot = tracking.quat_to_matrix(tr.model.rest_params.rotation)
    axis = rot[:, 2]
    k, measures = tr._axial_shear(axis)
    assert k == pytest.approx(tr.longitudinal_weight * tr.model.mu)
    x_dir = rot[:, 0]  # an affine shear along x: ∂u_a/∂r = 0.1 (r · x) per particle
    u = 0.1 * np.outer(tr.rest @ x_dir, axis)
    r_x = tr._radial @ x_dir
    expect = 0.5 * k * float(np.sum(vol * (0.1 * r_x) ** 2))
    assert energy(u, (k, measures)) == pytest.approx(expect, rel=1e-8)
    assert energy(np.outer(tr.rest @ axis, axis), (k, measures)) == pytest.approx(0.0, abs=1e-9)
    # the paper's affine shape has the term too (la19); no axial stiffness, no term
    plain = tracking.MotionTracker(
        tr.rest, tr.model.rest_params.translation, tr.model.rest_params.rotation
    )
    assert plain._axial_shear(axis)[0] == pytest.approx(k)
    free = tracking.MotionTracker(
        tr.rest, tr.model.rest_params.translation, tr.model.rest_params.rotation,
        longitudinal_weight=0.0,
    )
    assert free._axial_shear(axis) is None


def test_start_residual_from_stacked_products_equals_the_separate_ones(study):
    """
    ``right_hand_side`` and ``MLSOperator.apply`` stack columns: the same sums, bit for bit.

    The start's residual is ``b − A x0`` of :meth:`matvec` to the bit; with the compiled pass
    ``b``'s ``Dᵀ g`` is summed in that pass, the same as :meth:`constant_force` to 1e-13.
    """
    _, tr, _ = referenced_tracker(study, n=800)
    n, rng = tr.num_particles, np.random.default_rng(2)
    op = tr.model.operator
    x, x0 = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    gx, gx0 = op.apply(x, x0)
    assert np.array_equal(gx.reshape(n, 3, 3).transpose(0, 2, 1), op.gradient(x))
    assert np.array_equal(gx0, op.matrix_csc @ x0)
    C, J = cofactors_3x3(np.eye(3) + 0.1 * rng.normal(size=(n, 3, 3)))
    ctrl = tr.model.attach(tr.rest[rng.choice(n, 40, replace=False)])
    P = plane_projectors(rng.normal(size=(40, 3)), 40)
    force = rng.normal(size=(n, 3))
    for fit_error, offsets in ((3.0, J - 1.0), (0.0, J - 1.0), (3.0, None)):
        system = tr._local.system(
            fit_error=fit_error,
            volume=(50.0, C, offsets),
            axial=(7.0, np.array([0.0, 0.6, 0.8])),
            data=(2.0, ctrl.weights, P),
            eps=0.1,
        )
        b = force + system.constant_force()
        for start, grad in ((x0, None), (x0, gx0)):
            rhs, residual = system.right_hand_side(force, start, grad)
            if tr._local.fused is None or offsets is None:
                assert np.array_equal(rhs, b)
            else:  # the compiled pass takes Dᵀ g beside A x0: the same sums to rounding
                np.testing.assert_allclose(rhs, b, rtol=0, atol=1e-13 * np.abs(b).max())
            assert np.array_equal(residual.ravel(), rhs.ravel() - system.matvec(x0).ravel())
        rhs, residual = system.right_hand_side(force, np.zeros((n, 3)))
        assert residual is None and np.array_equal(rhs, b)


def test_compiled_product_equals_the_scipy_products(study, monkeypatch):
    """
    The compiled pass (``_fused.c``) gives the scipy products' ``A u`` and ``D u``.

    To 1e-13 of the largest entry (the sums' order differs), with and without the fit error and
    with the read-only fixed tangent; a tracker's phase solved either way moves no particle by
    1e-9 mm. Its AVX2 loop (where the CPU has one) gives its scalar loop's bits.
    ``MLV_ROS_COMPILED=0`` turns it off; index arrays out of range are refused.
    """
    _, tr, refs = referenced_tracker(study, n=800)
    ops, rng = tr._local, np.random.default_rng(4)
    if ops.fused is None:
        pytest.skip('_fused_c.so is not built (make bootstrap): the scipy products only')
    n = tr.num_particles
    C, J = cofactors_3x3(np.eye(3) + 0.1 * rng.normal(size=(n, 3, 3)))
    ctrl = tr.model.attach(tr.rest[rng.choice(n, 40, replace=False)])
    terms = {
        'volume': (50.0, C, J - 1.0),
        'axial': (7.0, np.array([0.0, 0.6, 0.8])),
        'data': (2.0, ctrl.weights, plane_projectors(rng.normal(size=(40, 3)), 40)),
        'eps': 0.1,
    }
    fused = ops.fused
    for fit_error, kw in ((3.0, terms), (0.0, terms), (3.0, {})):
        systems = []
        for kernel in (fused, None):
            ops.fused = kernel
            systems.append(ops.system(fit_error=fit_error, **kw))
        ops.fused = fused
        for u in (rng.normal(size=(n, 3)), np.sin(tr.rest / 15.0)):
            got, ref = (s.matvec(u) for s in systems)
            np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13 * np.abs(ref).max())
            g, g_ref = (s._last_gradient.reshape(n, 9) for s in systems)
            np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-13 * np.abs(g_ref).max())
            # the AVX2 loop (where the CPU has it) gives the scalar loop's bits
            # the AVX2 loop (where the CPU has it) gives the scalar loop's bits, the right-hand
            # side's Dᵀ of the incompressibility offsets included
            force = rng.normal(size=(n, 3))
            both = []
            for wide in (False, True):
                monkeypatch.setattr(_fused, 'WIDE', wide)
                both.append((
                    systems[0].matvec(u),
                    systems[0]._last_gradient.reshape(n, 9).copy(),
                    *systems[0].right_hand_side(force, u),
                ))
            assert all(np.array_equal(a, b) for a, b in zip(*both))
    # a phase solved with and without it
    _, tr2, _ = referenced_tracker(study, n=800)
    tr2._local.fused = None
    sets = observed(study, refs, 2)
    x, x2 = (t.solve(2, sets, study.motion.num_phases).positions for t in (tr, tr2))
    assert np.abs(x - x2).max() < 1e-9
    assert _fused.wide_available() in (True, False)
    with pytest.raises(ValueError, match='outside'):
        _fused.checked_rows([0, 2], [0, n], n)
    with pytest.raises(ValueError, match='span'):
        _fused.checked_rows([0, 3], [0, 1], n)
    monkeypatch.setenv('MLV_ROS_COMPILED', '0')
    assert _fused.kernel() is None


def test_cofactors_and_block_inverses_equal_numpys():
    rng = np.random.default_rng(2)
    m = rng.normal(size=(50, 3, 3))
    cof, det = cofactors_3x3(m)
    np.testing.assert_allclose(det, np.linalg.det(m), rtol=1e-12, atol=1e-14)
    want = det[:, None, None] * np.swapaxes(np.linalg.inv(m), 1, 2)
    np.testing.assert_allclose(cof, want, atol=1e-10 * np.abs(want).max())
    s = m @ np.swapaxes(m, 1, 2) + 0.1 * np.eye(3)
    s[3] = 0.0  # a particle no term reaches: its pseudo-inverse
    s[7] = np.diag([2.0, 1.0, 0.0])  # singular: its pseudo-inverse too
    inv = symmetric_inverse_3x3(s)
    ok = np.setdiff1d(np.arange(50), [3, 7])
    np.testing.assert_allclose(inv[ok], np.linalg.inv(s[ok]), rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(inv[3], np.zeros((3, 3)))
    np.testing.assert_allclose(inv[7], np.diag([0.5, 1.0, 0.0]))
    q = rng.normal(size=(50, 3, 3))
    want = m @ q @ np.swapaxes(m, 1, 2)
    got = sandwich_3x3(m, q)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-13 * np.abs(want).max())


def test_tracker_local_stage_matches_the_reference_on_simulated_tags(study, monkeypatch):
    """
    Check every local solve of three phases against the old one on the same tag points.

    Every local solve of three phases (two slice-following passes each) against the old one on
    the same tag points, global fit and warm start: CG at rtol 1e-4 either way.
    """
    m = study.motion
    X, tr, refs = referenced_tracker(study, n=1500)
    new_solve, cache, diffs = tracking.MotionTracker._local_solve, {}, []

    # Every pass at the reference's tolerance, 1e-4: with the default volume term (4000 μ, the
    # system stiffer than with the former 1000) two CG iterates stopped at 2e-3 differ by up to
    # 0.025 mm in their median by the stopping point alone.
    tr.cg_rtol = tr.cg_rtol_following = 1e-4

    def both(self, phi, targets, normals, x_global, weights=None, rtol=None, scale=None):
        # The reference has no data weights: these tags all have confidence 1, so equal weights;
        # exact tags are below the tag noise the data weight holds for, so full springs.
        assert weights is None or np.ptp(weights) == 0
        assert scale is None or np.all(scale == 1.0)
        d0 = None if self.delta is None else self.delta.copy()
        new = new_solve(self, phi, targets, normals, x_global, weights, rtol, scale)
        old, _ = tracker_local_solve(self, phi, targets, normals, x_global, d0, cache)
        diffs.append(np.linalg.norm(new - old, axis=1))
        return new

    monkeypatch.setattr(tracking.MotionTracker, '_local_solve', both)
    for phase in (1, 2, int(round(m.es_phase))):
        tr.solve(phase, observed(study, refs, phase), m.num_phases)
    assert len(diffs) == 6
    assert max(np.median(d) for d in diffs) < 0.02, [np.median(d) for d in diffs]
    assert max(np.percentile(d, 95) for d in diffs) < 0.1, [np.percentile(d, 95) for d in diffs]


def test_paper_model_fit_matches_the_reference_local_stage():
    x = sample_cylinder_shell(1500, seed=0)
    model = MeshlessModel(
        x, cylindrical_frame(x, [0, 0, 0], [0, 0, 1], radius=R_OUTER, half_height=H_CYL / 2)
    )
    idx = control_subset(len(x), 0.1, seed=1)
    y = deform(x, 'bulge')
    new = model.fit(idx, y[idx], warm_start=False, max_iterations=60)
    model._local_system = lambda data: PhantomSystemReference(model, data)
    old = model.fit(idx, y[idx], warm_start=False, max_iterations=60)
    rms_new, rms_old = (
        float(np.sqrt(np.mean(np.sum((r.positions - y) ** 2, axis=1)))) for r in (new, old)
    )
    assert abs(rms_new - rms_old) < 1e-3, (rms_new, rms_old)
    assert np.median(np.linalg.norm(new.positions - old.positions, axis=1)) < 0.02


def test_both_callers_hold_rigid_modes_by_one_rule(study, monkeypatch):
    """Check that the tracker's and the paper model's systems both take ``ε = 10⁻⁶ κ``."""
    built, system = [], LocalOperators.system

    def record(self, **kw):
        built.append((kw['eps'], kw['data'][0]))
        return system(self, **kw)

    monkeypatch.setattr(LocalOperators, 'system', record)
    _, tr, refs = referenced_tracker(study, n=800)
    tr.solve(1, observed(study, refs, 1), study.motion.num_phases)
    x = sample_cylinder_shell(800, seed=0)
    model = MeshlessModel(
        x, cylindrical_frame(x, [0, 0, 0], [0, 0, 1], radius=R_OUTER, half_height=H_CYL / 2)
    )
    idx = control_subset(len(x), 0.1, seed=1)
    for weight in (100.0, 7.0):  # the model's ε follows the fit's data weight
        model.fit(idx, deform(x, 'bulge')[idx], warm_start=False, data_weight=weight)
    assert len(built) >= 4 and len({k for _, k in built}) >= 3
    assert all(eps == rigid_mode_eps(kappa) and eps > 0 for eps, kappa in built)
    for bad in (-1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match='kappa'):
            rigid_mode_eps(bad)


def _coarse_basis(coarse, n):
    """Return the vector basis ``Z = Z_s ⊗ I₃`` as a dense (N, 3, 3Q) array (index e·Q + q)."""
    q, zs = coarse.num_basis, coarse.basis.toarray()
    z = np.zeros((n, 3, 3 * q))
    for e in range(3):
        z[:, e, e * q:(e + 1) * q] = zs
    return z


def test_coarse_operator_is_the_galerkin_projection_of_the_reference_system(study):
    """
    Check the coarse matrix against ``Zᵀ A Z`` and the correction against ``Z A_c⁻¹ Zᵀ``.

    The coarse matrix assembled from sparse products equals ``Zᵀ A Z`` taken column by column
    through the system's own matrix–vector product (every term: elasticity, volume at rest, axial,
    transmural shear, fit error, ε, data springs), and the correction applies ``Z A_c⁻¹ Zᵀ``.
    """
    _, tr, _ = referenced_tracker(study, n=800, coarse_aggregates=0)
    ops, n, rng = tr._local, tr.num_particles, np.random.default_rng(3)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    rad = rng.normal(size=(n, 3))
    rad /= np.linalg.norm(rad, axis=1)[:, None]
    shear = (4.0, axis[None, :, None] * rad[:, None, :])  # the system's measures a r_iᵀ
    coarse = CoarseSpace(
        ops, 6, fit_error=3.0, volume_weight=50.0, axial=(7.0, axis), eps=0.1,
        shear=(4.0, axis, rad),
    )
    m = 40
    phi = sp.random(m, n, density=0.02, random_state=1, format='csr')
    nrm = rng.normal(size=(m, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    metric = (np.eye(3) - nrm[:, :, None] * nrm[:, None, :]) * rng.uniform(0.5, 2.0, m)[
        :, None, None
    ]
    system = ops.system(
        fit_error=3.0,
        volume=(50.0, np.broadcast_to(np.eye(3), (n, 3, 3)), None),
        axial=(7.0, axis),
        data=(5.0, phi, metric),
        eps=0.1,
        shear=shear,
    )
    z = _coarse_basis(coarse, n)
    az = np.stack([system.matvec(z[:, :, c]) for c in range(z.shape[2])], axis=2)
    galerkin = np.einsum('nec,ned->cd', z, az)
    r = rng.normal(size=(n, 3))
    want = np.einsum('nec,c->ne', z, np.linalg.solve(galerkin, np.einsum('nec,ne->c', z, r)))
    got = coarse.factor((5.0, phi, metric))(r)
    np.testing.assert_allclose(got, want, atol=1e-9 * np.abs(want).max())
    # internal part alone (no data): the same against the system without springs
    system = ops.system(
        fit_error=3.0,
        volume=(50.0, np.broadcast_to(np.eye(3), (n, 3, 3)), None),
        axial=(7.0, axis),
        eps=0.1,
        shear=shear,
    )
    az = np.stack([system.matvec(z[:, :, c]) for c in range(z.shape[2])], axis=2)
    np.testing.assert_allclose(
        coarse.internal,
        np.einsum('nec,ned->cd', z, az),
        atol=1e-12 * np.abs(coarse.internal).max(),
    )


def test_coarse_correction_keeps_the_solution_and_cuts_cg_iterations(study, monkeypatch):
    """
    Check that two-level PCG converges to block-Jacobi's solution, in fewer iterations.

    Two-level PCG converges to block-Jacobi's solution (tight tolerance), and at the
    tracker's tolerance in fewer iterations, on the tracker's own systems at ES.
    """
    m = study.motion
    _, tr, refs = referenced_tracker(study, n=800)
    assert tr._coarse is not None
    systems, build = [], tr._local.system

    def keep(**kw):
        systems.append(kw)
        return build(**kw)

    monkeypatch.setattr(tr._local, 'system', keep)
    tr.solve(int(round(m.es_phase)), observed(study, refs, int(round(m.es_phase))), m.num_phases)
    its_bj = its_two = 0
    for kw in systems:
        with_coarse = build(**kw)
        plain = build(**{k: v for k, v in kw.items() if k not in ('coarse', 'coarse_correction')})
        b = np.sin(tr.rest / 7.0) * kw['data'][0]
        exact, _ = plain.solve(b, rtol=1e-10, maxiter=5000)
        two, _ = with_coarse.solve(b, rtol=1e-10, maxiter=5000)
        np.testing.assert_allclose(two, exact, atol=1e-6 * np.abs(exact).max())
        its_bj += plain.solve(b, rtol=1e-3)[1]
        its_two += with_coarse.solve(b, rtol=1e-3)[1]
    assert len(systems) == 2
    # the second pass reuses the first pass's coarse factor (the tracker's per-phase reuse)
    assert systems[0]['coarse'] is tr._coarse and systems[1]['coarse_correction'] is not None
    assert its_two < 0.7 * its_bj, (its_two, its_bj)


def test_aggregates_cover_the_cloud_and_degenerate_ones_drop_directions():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(500, 3)) * [30.0, 20.0, 10.0]
    agg = farthest_point_aggregates(x, 16)
    assert agg.shape == (500,) and set(agg.tolist()) == set(range(16))
    np.testing.assert_array_equal(agg, farthest_point_aggregates(x, 16))  # deterministic
    for bad in (0, 501):
        with pytest.raises(ValueError, match='num_aggregates'):
            farthest_point_aggregates(x, bad)

    # a flat cloud: no aggregate spans z, so each keeps 1, x, y, orthonormal over its particles
    from mlv_ros.core.meshless.kernel import build_phyxels
    from mlv_ros.core.meshless.local import LocalOperators
    from mlv_ros.core.meshless.mls import MLSOperator

    g = np.mgrid[0:20, 0:20].reshape(2, -1).T * 1.5
    flat = np.concatenate([g, np.zeros((len(g), 1))], axis=1)
    ph = build_phyxels(flat)
    coarse = CoarseSpace(LocalOperators(MLSOperator(ph), ph.volume, 1.0, 1.0, 1.0), 8, eps=1.0)
    assert coarse.num_basis == 3 * 8
    np.testing.assert_allclose((coarse.basis.T @ coarse.basis).toarray(), np.eye(24), atol=1e-10)
    r = np.random.default_rng(1).normal(size=(len(flat), 3))
    assert np.all(np.isfinite(coarse.factor()(r)))
