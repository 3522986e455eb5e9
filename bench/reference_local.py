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
Reference copies of the local stages as they were before :mod:`mlv_ros.core.meshless.local`.

For benchmarks and the equivalence test only; not part of the package.

- :func:`tracker_local_solve`: ``MotionTracker._local_solve`` — matrix-free Jacobi-PCG whose
  matvec calls the MLS gradient and adjoint and an assembled (N, N) fit-error matrix
  (:func:`tracker_fit_error_matrix`, the slow part of the first phase).
- :class:`PhantomSystemReference`: the PCG system of ``MeshlessModel.fit``
  (``local_update="solve"``) on the matrix-free stage that was ``mlv_ros.core.meshless.elastic``'s
  until session 17 (:func:`linear_stiffness_apply`, :func:`stiffness_diagonal`,
  :func:`stabilisation_weights`, :func:`stabilisation_apply`, :func:`stabilisation_diagonal`,
  here unchanged; the package has one local stage, :mod:`mlv_ros.core.meshless.local`).
"""

from __future__ import annotations

from mlv_ros.core.meshless import quat_to_matrix, svk_stress
from mlv_ros.core.meshless.mls import MLSOperator
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import cg, LinearOperator


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


def tracker_fit_error_matrix(model):
    """Assemble ``Bᵀ W B`` of the MLS fit error (eq. 16), shape (N, N), by sparse products."""
    ph, D = model.phyxels, model.operator.matrix
    n, p = model.num_particles, ph.pair_i.shape[0]
    rows = np.arange(p)
    Ej = sp.csr_matrix((np.ones(p), (rows, ph.pair_j)), shape=(p, n))
    Ei = sp.csr_matrix((np.ones(p), (rows, ph.pair_i)), shape=(p, n))
    X = sp.csr_matrix(
        (ph.xij.ravel(), (np.repeat(rows, 3), (3 * ph.pair_i[:, None] + np.arange(3)).ravel())),
        shape=(p, 3 * n),
    )
    B = (Ej - Ei - X @ D).tocsr()
    return (B.T @ sp.diags(ph.wij / ph.wij.max()) @ B).tocsr()


def tracker_local_solve(tracker, phi, targets, normals, x_global, delta0=None, cache=None):
    """
    Run the old ``MotionTracker._local_solve``.

    ``cache`` (a dict) keeps kdiag and the fit-error matrix between calls as the tracker did.
    Returns (δ (N, 3), CG iterations).
    """
    cache = {} if cache is None else cache
    model = tracker.model
    op, vol = model.operator, model.phyxels.volume
    lam, mu = model.lam, model.mu
    n = model.num_particles
    P = np.eye(3) - np.einsum('ka,kb->kab', normals, normals)
    phi_t = phi.T.tocsr()
    if 'kdiag' not in cache:
        dsq = op.matrix.multiply(op.matrix)
        w = np.repeat(vol, 3)
        cache['kdiag'] = np.asarray(dsq.T @ w).ravel() * (mu + (mu + lam) / 3.0)
    kdiag = cache['kdiag']
    kappa = tracker.data_weight * float(np.median(kdiag))
    eps = 1e-6 * kappa
    if 'L' not in cache:
        cache['L'] = tracker_fit_error_matrix(model)
    L = cache['L']
    alpha = (
        tracker.hourglass_weight
        * float(np.median(kdiag))
        / max(float(np.median(L.diagonal())), 1e-300)
    )
    Fg = np.eye(3) + op.gradient(x_global - tracker.rest)
    H0 = 0.0
    if delta0 is not None and np.any(delta0) and getattr(tracker, 'volume_about_start', False):
        # the volume term linearised about the warm start's deformation (session 19)
        H0 = op.gradient(delta0)
    Jg = np.linalg.det(Fg + H0)
    ok = np.abs(Jg) > 1e-6
    C = np.zeros_like(Fg)
    C[ok] = Jg[ok, None, None] * np.swapaxes(np.linalg.inv((Fg + H0)[ok]), 1, 2)
    offset = Jg - 1.0 - np.einsum('iab,iab->i', C, np.broadcast_to(H0, C.shape))
    kv = tracker.volume_weight * mu
    kl = tracker.longitudinal_weight * mu
    ax = quat_to_matrix(model.params.rotation)[:, 2]
    aa = np.outer(ax, ax)
    # the transmural axial shear ½ k_s Σ v_i (M_i : H_i)² (MotionTracker._axial_shear; its
    # measures M_i = a r_iᵀ), None without axial stiffness
    shear = tracker._axial_shear(ax) if hasattr(tracker, '_axial_shear') else None

    def apply(v):
        d = v.reshape(n, 3)
        H = op.gradient(d)
        tr = np.trace(H, axis1=1, axis2=2)
        S = vol[:, None, None] * (
            mu * (H + np.swapaxes(H, 1, 2)) + lam * tr[:, None, None] * np.eye(3)
        )
        if kv:
            S = S + (kv * vol * np.einsum('iab,iab->i', C, H))[:, None, None] * C
        if kl:
            S = S + (kl * vol * np.einsum('a,iab,b->i', ax, H, ax))[:, None, None] * aa
        if shear is not None:
            ks, ms = shear
            S = S + (ks * vol * np.einsum('iab,iab->i', ms, H))[:, None, None] * ms
        data = phi_t @ np.einsum('kab,kb->ka', P, phi @ d)
        return (op.adjoint(S) + alpha * (L @ d) + kappa * data + eps * d).ravel()

    r = np.einsum('kab,kb->ka', P, targets - phi @ x_global)
    rhs = kappa * (phi_t @ r)
    if kv:
        rhs = rhs - op.adjoint((kv * vol * offset)[:, None, None] * C)
    rhs = rhs.ravel()
    diag_data = np.asarray(phi.multiply(phi).T @ np.ones(phi.shape[0])).ravel()
    vdiag = kdiag * kv / (mu + (mu + lam) / 3.0)
    diag = np.repeat(
        (kdiag + vdiag + alpha * L.diagonal() + kappa * diag_data + eps)[:, None], 3, axis=1
    )
    if kl:
        D = op.matrix.tocsr()
        G = D[0::3] * ax[0] + D[1::3] * ax[1] + D[2::3] * ax[2]
        diag = diag + kl * np.asarray(G.multiply(G).T @ vol).ravel()[:, None] * (ax * ax)[None, :]
    prec = 1.0 / diag.ravel()
    A = LinearOperator((3 * n, 3 * n), matvec=apply, dtype=np.float64)
    M = LinearOperator((3 * n, 3 * n), matvec=lambda v: prec * v, dtype=np.float64)
    count = [0]
    sol, _info = cg(
        A,
        rhs,
        x0=None if delta0 is None else delta0.ravel(),
        rtol=tracker.cg_rtol,
        maxiter=tracker.cg_maxiter,
        M=M,
        callback=lambda _x: count.__setitem__(0, count[0] + 1),
    )
    return sol.reshape(n, 3), count[0]


class PhantomSystemReference:
    """
    The old local-stage system of ``MeshlessModel.fit`` (``local_update="solve"``).

    Matrix-free ``κ ΦᵀQᵀPQΦ + K + S + ε`` on
    :func:`linear_stiffness_apply` and :func:`stabilisation_apply`, Jacobi-preconditioned CG. Same
    interface as :class:`mlv_ros.core.meshless.local.LocalSystem` (``internal``, ``solve``), so
    ``model._local_system = lambda data: PhantomSystemReference(model, data)`` runs a whole fit
    with it.
    """

    def __init__(self, model, data):
        self.model, self.n = model, model.num_particles
        vol = model.phyxels.volume
        kdiag = stiffness_diagonal(model.operator, vol, model.lam, model.mu)
        self.coef = (
            model.stabilisation * model.mu * stabilisation_weights(model.operator, vol)
        )
        kdiag = kdiag + stabilisation_diagonal(model.operator, self.coef)[:, None]
        self.eps = 1e-4 * float(np.median(kdiag))
        self.kappa, self.phi, self.pq = data
        self.phi_t = self.phi.T.tocsr()
        self.prec = (
            self.kappa * ((self.phi.multiply(self.phi)).T @ np.einsum('maa->ma', self.pq))
            + kdiag
            + self.eps
        )

    def internal(self, v):
        m = self.model
        out = linear_stiffness_apply(m.operator, v, m.phyxels.volume, m.lam, m.mu)
        if m.stabilisation:
            out = out + stabilisation_apply(m.operator, v, self.coef)
        return out + self.eps * v

    def matvec(self, v):
        return self.kappa * (
            self.phi_t @ np.einsum('mab,mb->ma', self.pq, self.phi @ v)
        ) + self.internal(v)

    def solve(self, rhs, x0=None, *, rtol=1e-3, atol=0.0, maxiter=100):
        n3 = 3 * self.n
        A = LinearOperator(
            (n3, n3), matvec=lambda v: self.matvec(v.reshape(self.n, 3)).ravel(), dtype=np.float64
        )
        M = LinearOperator((n3, n3), matvec=lambda v: v / self.prec.ravel(), dtype=np.float64)
        count = [0]
        dx, _ = cg(
            A,
            np.ravel(rhs),
            x0=None if x0 is None else np.ravel(x0),
            rtol=rtol,
            atol=atol,
            maxiter=maxiter,
            M=M,
            callback=lambda _x: count.__setitem__(0, count[0] + 1),
        )
        return dx.reshape(self.n, 3), count[0]
