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
St Venant–Kirchhoff elasticity on MLS gradients (paper eq. 18–23; Müller et al. 2004).

Strain convention: the Green–Lagrange tensor **with** the ½, ``E = ½(JᵀJ − I)`` with
``J = I + H``, ``H = ∂u/∂x`` (see :mod:`mlv_ros.core.meshless.mls`). The paper's eq. 19 writes
``ε = JᵀJ − I = 2E``; every function here uses E. With it, the isotropic stress (eq. 20) is the
second Piola–Kirchhoff ``S = λ tr(E) I + 2 μ E`` and the energy (eq. 21) ``U_i = v_i ½ E:S =
v_i (½ λ tr(E)² + μ E:E)``. The internal force (eq. 22–23) is the exact negative gradient
``f_j = −Σ_i v_i (J_i S_i) d_ij`` (Müller's ``−2 v J σ`` with his unhalved strain).

Units: E (Young's modulus) and λ, μ in any pressure unit P; volumes mm³; energies P·mm³;
forces P·mm².
"""

from __future__ import annotations

from mlv_ros.core.meshless.mls import MLSOperator
import numpy as np


def lame_parameters(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """
    Lamé constants ``λ = Eν/((1+ν)(1−2ν))``, ``μ = E/(2(1+ν))``.

    Raises
    ------
    ValueError
        ``E`` not finite positive, or ``ν`` outside (−1, 0.5).

    """
    e, nu = float(youngs_modulus), float(poisson_ratio)
    if not np.isfinite(e) or e <= 0:
        raise ValueError(f"Young's modulus must be finite and > 0, got {youngs_modulus}")
    if not np.isfinite(nu) or not -1.0 < nu < 0.5:
        raise ValueError(f'Poisson ratio must lie in (-1, 0.5), got {poisson_ratio}')
    return e * nu / ((1 + nu) * (1 - 2 * nu)), e / (2 * (1 + nu))


def deformation_gradient(h: np.ndarray) -> np.ndarray:
    """``J = I + H`` (eq. 18), shape (N, 3, 3)."""
    return h + np.eye(3)


def green_lagrange(h: np.ndarray) -> np.ndarray:
    """Green–Lagrange strain ``E = ½(H + Hᵀ + HᵀH)`` (eq. 19 with the ½), shape (N, 3, 3)."""
    ht = h.transpose(0, 2, 1)
    return 0.5 * (h + ht + ht @ h)


def svk_stress(strain: np.ndarray, lam: float, mu: float) -> np.ndarray:
    """Second Piola–Kirchhoff stress ``S = λ tr(E) I + 2 μ E`` (eq. 20), shape (N, 3, 3)."""
    tr = np.trace(strain, axis1=1, axis2=2)
    return lam * tr[:, None, None] * np.eye(3) + 2.0 * mu * strain


def strain_energy(h: np.ndarray, volume: np.ndarray, lam: float, mu: float) -> np.ndarray:
    """
    Per-phyxel energy ``U_i = v_i (½ λ tr(E)² + μ E:E)`` (eq. 21).

    Parameters
    ----------
    h : ndarray, shape (N, 3, 3)
        Displacement gradients ``∂u/∂x``.
    volume : ndarray, shape (N,)
        Phyxel volumes, mm³.
    lam, mu : float
        Lamé constants.

    Returns
    -------
    ndarray, shape (N,)

    """
    e = green_lagrange(h)
    tr = np.trace(e, axis1=1, axis2=2)
    return volume * (0.5 * lam * tr**2 + mu * np.einsum('nab,nab->n', e, e))


def internal_forces(
    op: MLSOperator, u: np.ndarray, volume: np.ndarray, lam: float, mu: float
) -> np.ndarray:
    """
    Elastic forces ``f = −∂(Σ_i U_i)/∂u`` (eq. 22–23).

    Parameters
    ----------
    op : MLSOperator
        MLS gradient operator on the rest configuration.
    u : ndarray, shape (N, 3)
        Displacements from the operator's rest configuration, mm.
    volume : ndarray, shape (N,)
        Phyxel volumes, mm³.
    lam, mu : float
        Lamé constants.

    Returns
    -------
    ndarray, shape (N, 3)
        Forces; they sum to zero and vanish for rigid motions.

    """
    h = op.gradient(u)
    piola = deformation_gradient(h) @ svk_stress(green_lagrange(h), lam, mu)
    return -op.adjoint(volume[:, None, None] * piola)


def linear_stiffness_apply(
    op: MLSOperator, u: np.ndarray, volume: np.ndarray, lam: float, mu: float
) -> np.ndarray:
    """
    ``K u`` for the stiffness linearised at the rest state (small strain ``ε = sym H``).

    ``K`` is the Hessian of the energy at ``u = 0`` (so ``internal_forces(u) ≈ −K u`` for small u);
    it is never assembled (it would couple neighbours of neighbours).

    Returns
    -------
    ndarray, shape (N, 3)

    """
    h = op.gradient(u)
    eps = 0.5 * (h + h.transpose(0, 2, 1))
    return op.adjoint(volume[:, None, None] * svk_stress(eps, lam, mu))


def stiffness_diagonal(op: MLSOperator, volume: np.ndarray, lam: float, mu: float) -> np.ndarray:
    """
    Diagonal of the linearised stiffness, shape (N, 3) (Jacobi preconditioner).

    A unit displacement of ``u_j[a]`` gives phyxel ``i`` the gradient ``e_a d_ijᵀ``, hence energy
    ``½ v_i (λ d_a² + μ (|d|² + d_a²))``.
    """
    coo = op.matrix.tocoo()
    i, b = np.divmod(coo.row, 3)
    # Gather the 3-vector d_ij for every (i, j): entries with the same (i, j) differ only in b.
    key = i.astype(np.int64) * op.n + coo.col
    order = np.lexsort((b, key))
    key_s, vals = key[order], coo.data[order]
    uniq, start = np.unique(key_s, return_index=True)
    d = np.zeros((uniq.size, 3))
    d[np.searchsorted(uniq, key_s), b[order]] = vals
    ii, jj = np.divmod(uniq, op.n)
    v = volume[ii]
    dsq = np.einsum('pa,pa->p', d, d)
    per = v[:, None] * (lam * d**2 + mu * (dsq[:, None] + d**2))
    return np.stack([np.bincount(jj, weights=per[:, a], minlength=op.n) for a in range(3)], axis=1)


def stabilisation_weights(op: MLSOperator, volume: np.ndarray) -> np.ndarray:
    """
    Return the per-pair coefficients ``c_ij = v_i ŵ_ij / h_i²`` of :func:`stabilisation_apply`.

    Shape (P,), with ``ŵ_ij = w_ij / Σ_j w_ij`` (normalised kernel weights).
    """
    ph = op.phyxels
    wsum = np.bincount(ph.pair_i, weights=ph.wij, minlength=ph.num_particles)
    return volume[ph.pair_i] * ph.wij / wsum[ph.pair_i] / ph.h[ph.pair_i] ** 2


def stabilisation_apply(op: MLSOperator, u: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """
    Gradient of the zero-energy-mode penalty ``½ Σ_ij c_ij |u_j − u_i − H_i x_ij|²``.

    The MLS gradient of a phyxel averages ~100 neighbours, so displacing single particles away
    from the local affine fit costs almost no strain energy (nodal-integration zero-energy
    modes): with sparse control points the free particles would not follow their neighbours.
    This penalises exactly the MLS fitting error of eq. 16 (it vanishes for affine fields, so it
    adds no stiffness to rigid motion, uniform strain or the global deformation).

    Parameters
    ----------
    op : MLSOperator
        MLS gradient operator on the rest configuration (its neighbour pairs and gradients).
    u : ndarray, shape (N, 3)
        Displacements from the operator's rest configuration, mm.
    coef : ndarray, shape (P,)
        From :func:`stabilisation_weights` (times a modulus).

    Returns
    -------
    ndarray, shape (N, 3)
        ``∂/∂u`` of the penalty (a symmetric positive semi-definite linear map of u).

    """
    ph = op.phyxels
    n = ph.num_particles
    h = op.gradient(u)
    r = u[ph.pair_j] - u[ph.pair_i] - np.einsum('pab,pb->pa', h[ph.pair_i], ph.xij)
    cr = coef[:, None] * r
    g = np.stack(
        [
            np.bincount(ph.pair_j, weights=cr[:, a], minlength=n)
            - np.bincount(ph.pair_i, weights=cr[:, a], minlength=n)
            for a in range(3)
        ],
        axis=1,
    )
    # through H_i: ∂/∂H_i[a, b] of the penalty is −Σ_j c_ij r_ij[a] x_ij[b]
    gh = np.stack(
        [
            np.bincount(ph.pair_i, weights=-cr[:, a] * ph.xij[:, b], minlength=n)
            for a in range(3)
            for b in range(3)
        ],
        axis=1,
    ).reshape(n, 3, 3)
    return g + op.adjoint(gh)


def stabilisation_diagonal(op: MLSOperator, coef: np.ndarray) -> np.ndarray:
    """
    Return the approximate diagonal of :func:`stabilisation_apply`, shape (N,).

    The direct ``u_j − u_i`` terms; used in the Jacobi preconditioner.
    """
    ph = op.phyxels
    n = ph.num_particles
    return np.bincount(ph.pair_j, weights=coef, minlength=n) + np.bincount(
        ph.pair_i, weights=coef, minlength=n
    )
