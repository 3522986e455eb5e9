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
  (``local_update="solve"``) on :func:`mlv_ros.core.meshless.elastic.linear_stiffness_apply` +
  :func:`~mlv_ros.core.meshless.elastic.stabilisation_apply`.
"""

from __future__ import annotations

from mlv_ros.core.meshless import elastic, quat_to_matrix
import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import cg, LinearOperator


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
    Jg = np.linalg.det(Fg)
    ok = np.abs(Jg) > 1e-6
    C = np.zeros_like(Fg)
    C[ok] = Jg[ok, None, None] * np.swapaxes(np.linalg.inv(Fg[ok]), 1, 2)
    kv = tracker.volume_weight * mu
    kl = tracker.longitudinal_weight * mu
    ax = quat_to_matrix(model.params.rotation)[:, 2]
    aa = np.outer(ax, ax)

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
        data = phi_t @ np.einsum('kab,kb->ka', P, phi @ d)
        return (op.adjoint(S) + alpha * (L @ d) + kappa * data + eps * d).ravel()

    r = np.einsum('kab,kb->ka', P, targets - phi @ x_global)
    rhs = kappa * (phi_t @ r)
    if kv:
        rhs = rhs - op.adjoint((kv * vol * (Jg - 1.0))[:, None, None] * C)
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
    :func:`~mlv_ros.core.meshless.elastic.linear_stiffness_apply` and
    :func:`~mlv_ros.core.meshless.elastic.stabilisation_apply`, Jacobi-preconditioned CG. Same
    interface as :class:`mlv_ros.core.meshless.local.LocalSystem` (``internal``, ``solve``), so
    ``model._local_system = lambda data: PhantomSystemReference(model, data)`` runs a whole fit
    with it.
    """

    def __init__(self, model, data):
        self.model, self.n = model, model.num_particles
        vol = model.phyxels.volume
        kdiag = elastic.stiffness_diagonal(model.operator, vol, model.lam, model.mu)
        self.coef = (
            model.stabilisation * model.mu * elastic.stabilisation_weights(model.operator, vol)
        )
        kdiag = kdiag + elastic.stabilisation_diagonal(model.operator, self.coef)[:, None]
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
        out = elastic.linear_stiffness_apply(m.operator, v, m.phyxels.volume, m.lam, m.mu)
        if m.stabilisation:
            out = out + elastic.stabilisation_apply(m.operator, v, self.coef)
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
