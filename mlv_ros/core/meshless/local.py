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
The local stage of the meshless model.

Quadratic energy terms on the MLS gradient and one block-Jacobi preconditioned CG solve (paper eq.
6, 16, 20–23, linearised at rest).

The local deformation ``u`` (N, 3) minimises ``½ uᵀ A u − bᵀ u`` with ``A`` the sum of

- **linear St Venant–Kirchhoff elasticity**: ``Σ_i v_i (μ |sym H_i|² + ½ λ tr(H_i)²)``;
- **MLS fit error** (eq. 16), the zero-energy-mode penalty
  ``½ Σ_i s_i Σ_j w_ij |u_j − u_i − H_i x_ij|²``. ``H_i`` is the weighted least-squares fit of the
  differences, so the penalty equals ``½ Σ_i s_i (Σ_j w_ij |u_j − u_i|² − H_i : H_i A_i)``
  (``A_i`` the moment matrix): a graph Laplacian on the pairs plus a per-phyxel term in ``H``,
  with no product of the gradient operator with itself to assemble;
- **near-incompressibility** ``½ k_v Σ_i v_i (C_i : H_i + g_i)²`` (``C_i`` the cofactor of the
  global deformation gradient, ``g_i = J_i − 1``);
- **axial stiffness** ``½ k_l Σ_i v_i (aᵀ H_i a)²`` along the long axis ``a``;
- **data springs** ``½ κ Σ_k |P_k^½ Σ_j φ_kj u_j|²`` (in-plane tag forces: ``P_k`` the in-plane
  projector, or ``QᵀP_kQ`` when ``u`` is expressed in a rotated frame);
- ``½ ε |u|²``, which removes the rigid modes that every other term but the data is blind to
  (one rule for every caller: :func:`rigid_mode_eps`).

Every per-phyxel term is a linear map of ``H_i`` to a stress-like ``S_i`` (a 9 × 9 tangent per
particle, summed over the terms once per system), so one matrix–vector product is one sparse
gradient, one batched 9 × 9 product, one sparse adjoint, one Laplacian product and the data
springs — each a pass over the compact pair layout of
:class:`~mlv_ros.core.meshless.mls.MLSOperator` — or, where ``make bootstrap`` built it, all of
them in one compiled pass over the pairs (:mod:`~mlv_ros.core.meshless._fused`, the same sums
to 1e-15). The preconditioner is the exact 3 × 3 diagonal block per particle (the
incompressibility block uses the particle's own cofactor for its neighbours', which only the
preconditioner sees), optionally plus an additive coarse correction (:class:`CoarseSpace`:
affine fields per aggregate of particles, built once per model) that removes the smooth error
block-Jacobi is slow on.

Everything is float64: the fit-error penalty is a difference of two terms that nearly cancel
for smooth fields, and float32 sparse products measured no faster here (1.6 vs 1.5 ms at 3000
particles).

Units: moduli in any pressure unit P, volumes mm³, displacements mm, forces P·mm².
"""

from __future__ import annotations

from mlv_ros.core.meshless import _fused
from mlv_ros.core.meshless.mls import MLSOperator
import numpy as np
import scipy.linalg as sla
from scipy.linalg import lapack
import scipy.sparse as sp
from scipy.spatial import cKDTree

_I3 = np.eye(3)

#: The rigid-mode regulariser ``ε`` as a share of the data springs' stiffness ``κ``
#: (:func:`rigid_mode_eps`).
RIGID_MODE_EPS = 1e-6


def rigid_mode_eps(kappa: float) -> float:
    """
    Return the rigid-mode regulariser ``ε = 10⁻⁶ κ`` of ``½ ε |u|²`` (P·mm).

    Elasticity, the fit-error penalty, incompressibility and the axial term are blind to rigid
    ``u`` (translations, rotations), which the global stage already expresses; the data springs
    see them only as far as the control points do. ``ε`` makes the split unique and the system
    positive definite while staying far below the stiffness of any mode the data or the material
    sets: one millionth of the data springs' stiffness ``κ`` (P·mm; each caller's ``κ`` is its
    ``data_weight`` times the median of its stiffness diagonal, so ``ε`` scales with the
    material and the particle spacing as the other terms do). Both callers use this rule:
    ``MotionTracker`` (``data_weight`` 10⁴: ``ε = 10⁻² ×`` the median elastic diagonal) and
    ``MeshlessModel.fit`` (default ``data_weight`` 100: ``ε = 10⁻⁴ ×`` the median diagonal).

    Parameters
    ----------
    kappa : float
        The data springs' stiffness ``κ`` of the solve, P·mm (finite, >= 0).

    Returns
    -------
    float
        ``ε``, P·mm.

    Raises
    ------
    ValueError
        ``kappa`` negative or not finite.

    """
    kappa = float(kappa)
    if not np.isfinite(kappa) or kappa < 0:
        raise ValueError(f'the data stiffness kappa must be finite and >= 0, got {kappa}')
    return RIGID_MODE_EPS * kappa


def elastic_tangent(lam: float, mu: float) -> np.ndarray:
    """
    Return ``∂S/∂H`` of linear elasticity, ``S = μ (H + Hᵀ) + λ tr(H) I``.

    Shape (3, 3, 3, 3), index ``[a, b, c, d] = ∂S_ab/∂H_cd``.
    """
    return mu * (
        np.einsum('ac,bd->abcd', _I3, _I3) + np.einsum('ad,bc->abcd', _I3, _I3)
    ) + lam * np.einsum('ab,cd->abcd', _I3, _I3)


class LocalOperators:
    """
    The rest-configuration parts of the local stage, built once per set of phyxels.

    Parameters
    ----------
    operator : MLSOperator
        MLS gradient on the rest configuration.
    volume : ndarray, shape (N,)
        Phyxel volumes ``v_i``, mm³.
    lam, mu : float
        Lamé constants.
    fit_error_weights : ndarray, shape (N,) or float
        ``s_i`` of the fit-error penalty (per phyxel, multiplying its kernel weights ``w_ij``).

    Attributes
    ----------
    volume_moment : ndarray, shape (N, 3, 3)
        ``Q_j = Σ_i v_i d_ij d_ijᵀ`` (mm): with a per-volume tangent it gives the exact diagonal
        block of any term ``Σ_i v_i S(H_i) : H_i`` whose tangent is the same in j's phyxels.
    laplacian : scipy.sparse.csr_matrix, shape (N, N)
        ``Σ_ij s_i w_ij (e_j − e_i)(e_j − e_i)ᵀ``, the first part of the fit-error penalty.
    fit_error_moment : ndarray, shape (N, 3, 3)
        ``s_i A_i``: the second part is ``−½ Σ_i H_i : H_i s_i A_i``.
    fit_error_diagonal : ndarray, shape (N,)
        Exact diagonal of the fit-error penalty (the same for the three components).

    """

    def __init__(self, operator: MLSOperator, volume, lam: float, mu: float, fit_error_weights):
        ph = operator.phyxels
        n = operator.n
        self.operator, self.n = operator, n
        self.volume = np.asarray(volume, dtype=np.float64)
        self.lam, self.mu = float(lam), float(mu)
        s = np.broadcast_to(np.asarray(fit_error_weights, dtype=np.float64), (n,))
        ei, ej, d = operator.entry_i, operator.entry_j, operator.entry_d
        vd = self.volume[ei, None] * d
        q = np.empty((n, 3, 3))
        for a in range(3):
            for b in range(a, 3):
                q[:, a, b] = q[:, b, a] = np.bincount(ej, weights=vd[:, a] * d[:, b], minlength=n)
        self.volume_moment = q
        pi, pj = ph.pair_i, ph.pair_j
        c = s[pi] * ph.wij
        deg = np.bincount(pi, weights=c, minlength=n) + np.bincount(pj, weights=c, minlength=n)
        half = sp.csr_matrix((c, (pi, pj)), shape=(n, n))
        self.laplacian = (sp.diags(deg) - half - half.T).tocsr()
        self.fit_error_moment = s[:, None, None] * ph.moment
        # Diagonal: a unit u_j moves e_ij' = δ_jj' − δ_ij − x_ij'·d_ij over phyxel i's members j';
        # summed with the weights that is w_ij (1 − 2 x_ij·d_ij) + d_ijᵀ A_i d_ij for a member j,
        # and W_i + 2 b_i·d_ii + d_iiᵀ A_i d_ii for the centre (W_i = Σ w, b_i = Σ w x).
        npair = pi.size
        mom = ph.moment
        dAd = sum(
            (2.0 - (a == b)) * mom[ei, a, b] * d[:, a] * d[:, b]
            for a in range(3)
            for b in range(a, 3)
        )
        xd = np.einsum('pa,pa->p', ph.xij, d[:npair]) if npair else np.zeros(0)
        wsum = np.bincount(pi, weights=ph.wij, minlength=n)
        bvec = np.stack(
            [np.bincount(pi, weights=ph.wij * ph.xij[:, a], minlength=n) for a in range(3)], axis=1
        )
        t_pair = ph.wij * (1.0 - 2.0 * xd) + dAd[:npair]
        t_self = wsum + 2.0 * np.einsum('na,na->n', bvec, d[npair:]) + dAd[npair:]
        self.fit_error_diagonal = np.bincount(pj, weights=s[pi] * t_pair, minlength=n) + s * t_self
        self._elastic = elastic_tangent(self.lam, self.mu)
        # Products with Dᵀ and L as CSC views of D and L: scipy's CSC kernel streams through the
        # stresses and scatters into the (N, 3) result, measured 1.5–2.5× faster than CSR here.
        self._adjoint = operator.matrix.T
        self._laplacian_csc = self.laplacian.T
        self._fixed = None  # (fit_error, tangent, block) of the last system (see fixed_terms)
        self._stacked = None  # (fit_error, [Dᵀ | fit_error L]) (see adjoint_with_laplacian)
        # The product as one compiled pass over the pairs when it is built (_fused): the
        # gradient operator by phyxel and each entry's fit-error pair weight s_i w_ij.
        self.fused = _fused.kernel()
        ptr, cols, vals, pair = operator.blocks
        weight = np.zeros(cols.size)
        weight[pair >= 0] = c[pair[pair >= 0]]
        self.fused_layout = (*_fused.checked_rows(ptr, cols, n), vals, weight)

    def adjoint_with_laplacian(self, fit_error: float) -> sp.csc_matrix:
        """
        Return ``[Dᵀ | fit_error · L]``, shape (N, 4N), kept for the last multiplier asked for.

        Its product with the stacked ``(S; u)`` ((3N, k) stresses in the operator's layout over
        (N, k) displacements) is ``Dᵀ S + fit_error · L u``.

        Parameters
        ----------
        fit_error : float
            Multiplier of the fit-error penalty.

        """
        fit_error = float(fit_error)
        if self._stacked is None or self._stacked[0] != fit_error:
            matrix = sp.hstack([self._adjoint, fit_error * self._laplacian_csc], format='csc')
            self._stacked = (fit_error, matrix)
        return self._stacked[1]

    def fixed_terms(self, fit_error: float) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the tangent and diagonal block of the terms that are the same in every system.

        Elasticity and the fit-error penalty (multiplier ``fit_error``) do not depend on the
        solve; only the volume, axial and data terms do. Kept for the last multiplier asked for
        (a tracker asks for one): with them kept, a system's setup at 3000 particles took 3.1–3.7
        instead of 6.5–7.0 ms (load 8–10).

        Parameters
        ----------
        fit_error : float
            Multiplier of the fit-error penalty.

        Returns
        -------
        tangent : ndarray, shape (N, 9, 9)
            ``v_i`` × the elastic tangent less ``fit_error`` × ``s_i A_i ⊗ I``, in the operator's
            layout (flat index ``3b + a`` holds ``H[a, b]``). Read-only.
        block : ndarray, shape (N, 3, 3)
            Their exact 3 × 3 diagonal blocks: ``μ tr(Q) I + (μ + λ) Q`` plus ``fit_error`` × the
            fit-error diagonal. Read-only.

        """
        fit_error = float(fit_error)
        if self._fixed is None or self._fixed[0] != fit_error:
            n, q = self.n, self.volume_moment
            elastic = self._elastic.transpose(1, 0, 3, 2).reshape(9, 9)
            tangent = self.volume[:, None, None] * elastic
            if fit_error:
                # −s_i H A_i: ∂S_ab/∂H_cd = −s_i δ_ac A_i[d, b], i.e. −s_i A_i ⊗ I in the layout
                fm = self.fit_error_moment
                kron = fm[:, :, None, :, None] * _I3[None, None, :, None, :]
                tangent -= fit_error * kron.reshape(n, 9, 9)
            trace = np.trace(q, axis1=1, axis2=2)[:, None, None]
            block = self.mu * trace * _I3 + (self.mu + self.lam) * q
            block += (fit_error * self.fit_error_diagonal)[:, None, None] * _I3
            tangent.flags.writeable = block.flags.writeable = False
            self._fixed = (fit_error, tangent, block)
        return self._fixed[1], self._fixed[2]

    def fit_error_apply(self, u: np.ndarray) -> np.ndarray:
        """Gradient of the fit-error penalty (weights ``s_i``, multiplier 1) at ``u`` (N, 3)."""
        op = self.operator
        h = (op.matrix_csc @ u).reshape(self.n, 3, 3)  # [i, b, a] = H_i[a, b]
        return self._laplacian_csc @ u - self._adjoint @ np.matmul(
            self.fit_error_moment, h
        ).reshape(3 * self.n, 3)

    def elastic_diagonal(self) -> np.ndarray:
        """Diagonal of the linear elastic stiffness, shape (N, 3)."""
        blocks = np.einsum('abcd,nbd->nac', self._elastic, self.volume_moment)
        return np.einsum('naa->na', blocks).copy()

    def system(
        self,
        *,
        fit_error: float = 0.0,
        volume: tuple | None = None,
        axial: tuple | None = None,
        data: tuple | None = None,
        eps: float = 0.0,
        coarse: 'CoarseSpace | None' = None,
        coarse_correction=None,
        shear: tuple | None = None,
    ) -> 'LocalSystem':
        """
        Build the local-stage system of one solve (elasticity always included, weight 1).

        Parameters
        ----------
        fit_error : float
            Multiplier of the fit-error penalty (its per-phyxel weights were given at build).
        volume : (k_v, C, g) or None
            ``k_v`` (P), cofactors ``C`` shape (N, 3, 3), offsets ``g`` shape (N,) or None.
        axial : (k_l, a) or (k_l, a, e) or None
            ``k_l`` (P) and the unit axis ``a`` shape (3,), or per particle a strain measure
            ``M`` shape (N, 3, 3): the term is then ``½ k_l Σ_i v_i (M_i : H_i)²``; with targets
            ``e`` shape (N,) (strain, or None) ``½ k_l Σ_i v_i (M_i : H_i − e_i)²``.
        data : (κ, Φ, P) or None
            ``κ`` (P·mm), weights ``Φ`` sparse (M, N), metrics ``P`` shape (M, 3, 3).
        eps : float
            Rigid-mode regulariser ``ε`` (P·mm), :func:`rigid_mode_eps` of ``κ``.
        coarse : CoarseSpace, optional
            Add its coarse correction to the block-Jacobi preconditioner (its internal part was
            built for these multipliers; see :class:`CoarseSpace`).
        coarse_correction : callable, optional
            Instead of ``coarse``: the :attr:`LocalSystem.coarse_correction` of an earlier system
            of these operators, reused without factoring again. Any SPD preconditioner keeps PCG
            converging to this system's solution; a correction factored for nearby data springs
            (the pass before, in the same phase) costs next to no iterations (default study: 492
            → 495 over 48 solves) and saves its projection and Cholesky factor (3.5 ms).
        shear : (k_s, M) or None
            A second strain-measure term ``½ k_s Σ_i v_i (M_i : H_i)²``, as ``axial``'s per
            particle form: ``k_s`` (P), ``M`` shape (N, 3, 3) (the thick-walled global shape's
            transmural axial shear, ``MotionTracker._axial_shear``).

        """
        if coarse is not None and coarse_correction is not None:
            raise ValueError('give coarse or coarse_correction, not both')
        system = LocalSystem(self, fit_error, volume, axial, data, eps, coarse, shear)
        if coarse_correction is not None:
            system.coarse_correction = coarse_correction
        return system


class LocalSystem:
    """One local-stage system ``A u = b`` (see :meth:`LocalOperators.system`)."""

    def __init__(
        self,
        ops: LocalOperators,
        fit_error,
        volume,
        axial,
        data,
        eps,
        coarse=None,
        shear=None,
    ):
        n = ops.n
        self.ops, self.n = ops, n
        self.fit_error, self.eps = float(fit_error), float(eps)
        # The 9 × 9 tangent per particle in the operator's layout (flat index 3b + a holds
        # H[a, b]: S = T · H) and the exact 3 × 3 diagonal block per particle, written term by
        # term (each a rank-one or Kronecker product per particle, no 3⁴ tensor per particle):
        # elasticity, volume ``k_v vec(C) vec(C)ᵀ``, axial ``k_l vec(M) vec(M)ᵀ`` (``M = a aᵀ``
        # or given per particle) and the fit error's ``−s_i A_i ⊗ I``. Each term's block is its
        # tangent contracted with the volume moment ``Q``: ``μ tr(Q) I + (μ + λ) Q``,
        # ``k_v C Q Cᵀ``, ``k_l M Q Mᵀ``.
        vol = ops.volume
        q = ops.volume_moment
        fixed_tangent, block = ops.fixed_terms(self.fit_error)
        rank_one = []  # (weight (N,), vector (N, 9)): tangent terms w_i c_i c_iᵀ of this solve
        self._offset = None
        if volume is not None and volume[0]:
            kv, C = float(volume[0]), np.asarray(volume[1], dtype=np.float64)
            c = np.swapaxes(C, 1, 2).reshape(n, 9)  # vec in the layout: [3b + a] = C[a, b]
            rank_one.append((kv * vol, c))
            block = block + kv * sandwich_3x3(C, q)
            if volume[2] is not None:  # stress k_v v_i g_i C_i, kept in the layout (as c)
                self._offset = (kv * vol * np.asarray(volume[2], dtype=np.float64))[:, None] * c
        if axial is not None and axial[0]:
            kl, a = float(axial[0]), np.asarray(axial[1], dtype=np.float64)
            if a.ndim == 1:
                m = np.outer(a, a)
                rank_one.append((kl * vol, np.broadcast_to(m.T.ravel(), (n, 9))))
                block = block + (kl * np.einsum('a,nab,b->n', a, q, a))[:, None, None] * m
            else:  # per particle: ½ k_l Σ_i v_i (M_i : H_i)²
                rank_one.append((kl * vol, np.swapaxes(a, 1, 2).reshape(n, 9)))
                block = block + kl * sandwich_3x3(a, q)
            if len(axial) > 2 and axial[2] is not None:  # targets: stress −k_l v_i e_i M_i
                target = (-kl * vol * np.asarray(axial[2], dtype=np.float64))[:, None]
                target = target * rank_one[-1][1]
                self._offset = target if self._offset is None else self._offset + target
        if shear is not None and shear[0]:
            ks, m = float(shear[0]), np.asarray(shear[1], dtype=np.float64)
            rank_one.append((ks * vol, np.swapaxes(m, 1, 2).reshape(n, 9)))
            block = block + ks * sandwich_3x3(m, q)
        tangent = fixed_tangent  # read-only; a new array once a term of this solve is added
        if rank_one:
            # Σ_t w_t c_t c_tᵀ per particle as one batched (9 × r)(r × 9) product: a third of the
            # time of a broadcast product and a sum per term (0.35 against 3.1 ms at 3000
            # particles and two terms; each (N, 9, 9) temporary was a fresh allocation).
            cols = np.stack([c for _, c in rank_one], axis=2)
            rows = np.stack([w[:, None] * c for w, c in rank_one], axis=1)
            tangent = np.matmul(cols, rows)
            tangent += fixed_tangent
        self._tangent = tangent
        if self.eps:
            block = block + self.eps * _I3
        self._data = None
        self._springs = None  # the data springs in the compiled pass's form, once asked for
        if data is not None:
            kappa, phi, metric = (
                float(data[0]),
                sp.csr_matrix(data[1]),
                np.asarray(data[2], dtype=np.float64),
            )
            # Φᵀ as CSR only where the scipy products ask for it (data_force): the compiled
            # pass reads Φ alone (0.3–1 ms a system at 3000 particles, load 10–17)
            self._data = (kappa, phi, None, metric)
            block = block + kappa * (phi.multiply(phi).T @ metric.reshape(-1, 9)).reshape(n, 3, 3)
        self.block_diagonal = block
        self._block_inv = symmetric_inverse_3x3(block)
        # Entry-major (3, 3, N) for precondition: nine vector products over the particles, 0.026
        # against 0.095 ms for the batched (N, 3, 3) matmul at 3000 particles.
        self._block_inv_cols = np.ascontiguousarray(np.moveaxis(self._block_inv, 0, -1))
        self.coarse_correction = None  # r ↦ Z A_c⁻¹ Zᵀ r for residuals (N, 3), or None
        self._last_gradient = None  # D u of the last internal(u)
        self.solution_gradient = None  # D u of the last solve's solution (see solve)
        if coarse is not None:
            if coarse.ops is not ops:
                raise ValueError('coarse space was built on other local operators')
            self.coarse_correction = coarse.factor(
                None if self._data is None else (self._data[0], self._data[1], self._data[3])
            )

    def internal(self, u: np.ndarray) -> np.ndarray:
        """Return ``A u`` without the data springs, shape (N, 3)."""
        ops, n = self.ops, self.n
        if ops.fused is not None and u.shape == (n, 3):
            return self._fused(u, False)
        g = (ops.operator.matrix_csc @ u).reshape(n, 9, -1)
        self._last_gradient = g  # D u, for solve's gradient of its iterate
        if self.fit_error:
            # Dᵀ S + α L u as one product of [Dᵀ | α L] with the stacked (S; u): one pass of
            # scipy's kernel instead of two (1.5 against 2.0 ms at 3000 particles, load 10).
            stacked = np.empty((4 * n, u.shape[1]))
            np.matmul(self._tangent, g, out=stacked[:3 * n].reshape(n, 9, -1))
            stacked[3 * n:] = u.reshape(n, -1)
            out = ops.adjoint_with_laplacian(self.fit_error) @ stacked
        else:
            out = ops._adjoint @ np.matmul(self._tangent, g).reshape(3 * n, -1)
        if self.eps:
            out += self.eps * u
        return out

    def _fused(self, u: np.ndarray, with_data: bool, offset_out=None) -> np.ndarray:
        """
        Return ``A u`` (with or without the data springs) by the compiled pass, (N, 3).

        With ``offset_out`` (N, 3) zeros, ``Dᵀ`` of the incompressibility offsets is added to it
        in the same pass (:meth:`right_hand_side`).
        """
        # the same sums as the scipy products to 1e-15 (mlv_ros.core.meshless._fused)
        ops, n = self.ops, self.n
        u = np.ascontiguousarray(u, dtype=np.float64)
        out, g = np.zeros((n, 3)), np.empty((n, 9))
        tangent = self._tangent
        if not tangent.flags.writeable:  # one compiled signature: a writable tangent
            tangent = self._tangent = tangent.copy()
        springs = _fused.NO_SPRINGS
        if with_data and self._data is not None:
            if self._springs is None:
                kappa, phi, _, metric = self._data
                self._springs = _fused.springs(kappa, phi, metric)
            springs = self._springs
        extra = _fused.NO_OFFSET
        if offset_out is not None:
            extra = (np.ascontiguousarray(self._offset, dtype=np.float64), offset_out)
        ops.fused(*ops.fused_layout, tangent, self.fit_error, self.eps, springs, u, out, g, *extra)
        self._last_gradient = g[:, :, None]
        return out

    def data_force(self, u: np.ndarray) -> np.ndarray:
        """Return the data springs' part of ``A u``, shape (N, 3) (zero without data)."""
        if self._data is None:
            return np.zeros_like(u)
        kappa, phi, phi_t, metric = self._data
        if phi_t is None:
            phi_t = phi.T.tocsr()
            self._data = (kappa, phi, phi_t, metric)
        m = metric.shape[0]
        return kappa * (phi_t @ np.matmul(metric, (phi @ u).reshape(m, 3, -1)).reshape(m, -1))

    def matvec(self, u: np.ndarray) -> np.ndarray:
        """Return ``A u``, shape (N, 3)."""
        if self.ops.fused is not None and u.shape == (self.n, 3):
            return self._fused(u, True)
        out = self.internal(u)
        if self._data is not None:
            out += self.data_force(u)
        return out

    def constant_force(self) -> np.ndarray:
        """
        Return ``−∂/∂u`` of the energy's linear part in u other than the data's, shape (N, 3).

        That part is the incompressibility offsets ``g``; add it to the right-hand side.
        """
        if self._offset is None:
            return np.zeros((self.n, 3))
        return -(self.ops._adjoint @ self._offset.reshape(3 * self.n, 3))

    def right_hand_side(self, force: np.ndarray, x0=None, gradient_x0=None):
        """
        Return ``b = force +`` :meth:`constant_force` and the residual ``b − A x0`` of a start.

        Both from one adjoint product: the stresses of ``x0`` and the incompressibility offsets
        stacked as six columns (scipy's kernel then reads the matrix once; each column's sums
        are the ones :meth:`matvec` and :meth:`constant_force` make, bit for bit). 2.1 against
        3.0 ms for the two products at 3000 particles.

        Parameters
        ----------
        force : ndarray, shape (N, 3)
            The data springs' part of the right-hand side.
        x0 : ndarray, shape (N, 3), optional
            The start :meth:`solve` will take; None or zero: no residual (CG starts from b).
        gradient_x0 : ndarray, shape (3N, 3), optional
            ``D x0`` in the operator's layout, when the caller has it
            (:meth:`~mlv_ros.core.meshless.mls.MLSOperator.apply`).

        Returns
        -------
        b : ndarray, shape (N, 3)
        residual : ndarray, shape (N, 3) or None
            ``b − A x0``; None without a non-zero start.

        """
        n, ops = self.n, self.ops
        force = np.asarray(force, dtype=np.float64)
        if x0 is None or not np.any(x0):
            return force + self.constant_force(), None
        u = np.asarray(x0, dtype=np.float64).reshape(n, 3)
        if ops.fused is not None:  # A x0 as matvec takes it, bit for bit, and Dᵀ g alongside
            if self._offset is None:
                b = force + self.constant_force()
                return b, b - self.matvec(u)
            offset = np.zeros((n, 3))
            ax = self._fused(u, True, offset)
            b = force - offset
            return b, b - ax
        g = ops.operator.matrix_csc @ u if gradient_x0 is None else gradient_x0
        cols = 3 if self._offset is None else 6
        rows = 4 * n if self.fit_error else 3 * n
        stacked = np.zeros((rows, cols))
        stacked[:3 * n, :3] = np.matmul(self._tangent, g.reshape(n, 9, -1)).reshape(3 * n, 3)
        if self._offset is not None:
            stacked[:3 * n, 3:] = self._offset.reshape(3 * n, 3)
        if self.fit_error:
            stacked[3 * n:, :3] = u
            out = ops.adjoint_with_laplacian(self.fit_error) @ stacked
        else:
            out = ops._adjoint @ stacked
        ax = np.array(out[:, :3])  # A x0, summed as matvec sums it
        if self.eps:
            ax += self.eps * u
        if self._data is not None:
            ax += self.data_force(u)
        b = force + (np.zeros((n, 3)) if self._offset is None else -out[:, 3:])
        return b, b - ax

    def precondition(self, r: np.ndarray) -> np.ndarray:
        """
        Return ``M⁻¹ r`` for a flat residual (3N,).

        Block-Jacobi, plus the coarse correction ``Z A_c⁻¹ Zᵀ r`` when the system has a coarse
        space (additive two-level).
        """
        n, inv = self.n, self._block_inv_cols
        r0, r1, r2 = r[0::3], r[1::3], r[2::3]
        z = np.empty(3 * n)
        for a in range(3):
            z[a::3] = inv[a, 0] * r0 + inv[a, 1] * r1 + inv[a, 2] * r2
        if self.coarse_correction is not None:
            z += self.coarse_correction(r.reshape(n, 3)).ravel()
        return z

    def solve(
        self,
        rhs: np.ndarray,
        x0: np.ndarray | None = None,
        *,
        rtol: float = 1e-3,
        atol: float = 0.0,
        maxiter: int = 400,
        residual: np.ndarray | None = None,
        gradient_x0: np.ndarray | None = None,
    ) -> tuple[np.ndarray, int]:
        """
        Preconditioned CG on ``A u = rhs`` (:func:`pcg`, :meth:`precondition`).

        Parameters
        ----------
        rhs : ndarray, shape (N, 3)
            Right-hand side of ``A u = rhs``.
        x0 : ndarray, shape (N, 3), optional
            Warm start.
        rtol, atol, maxiter :
            Stop when ``‖r‖ ≤ max(rtol ‖rhs‖, atol)`` or after ``maxiter`` iterations.
        residual : ndarray, shape (N, 3), optional
            ``rhs − A x0`` (:meth:`right_hand_side`), instead of a product here.
        gradient_x0 : ndarray, shape (3N, 3), optional
            ``D x0`` in the operator's layout (zeros for no start): then
            :attr:`solution_gradient` is ``D u`` of the solution, updated with each step from
            the product ``D p`` the step's ``A p`` takes (no product of its own; the same as
            ``D u`` to rounding).

        Returns
        -------
        u : ndarray, shape (N, 3)
        iterations : int

        """
        n = self.n
        self.solution_gradient = on_step = None
        if gradient_x0 is not None and not np.any(rhs):  # pcg's zero solution
            self.solution_gradient = np.zeros((n, 9))
        elif gradient_x0 is not None:
            self.solution_gradient = grad = np.array(gradient_x0, dtype=np.float64).reshape(n, 9)

            def step_gradient(alpha):  # x += α p: D x += α D p
                np.add(grad, alpha * self._last_gradient[:, :, 0], out=grad)

            on_step = step_gradient

        x, its = pcg(
            lambda v: self.matvec(v.reshape(n, 3)).ravel(),
            self.precondition,
            np.asarray(rhs, dtype=np.float64).ravel(),
            None if x0 is None else np.ravel(x0),
            rtol=rtol,
            atol=atol,
            maxiter=maxiter,
            r0=None if residual is None else np.ravel(residual),
            on_step=on_step,
        )
        if self.solution_gradient is not None:
            self.solution_gradient = self.solution_gradient.reshape(3 * n, 3)
        return x.reshape(n, 3), its


def sandwich_3x3(m: np.ndarray, q: np.ndarray) -> np.ndarray:
    """
    Return ``M_n Q_n M_nᵀ`` for batches of 3 × 3 matrices, shape (N, 3, 3).

    Written out entry by entry over (N,) columns: 0.14 against 0.58 ms for two batched
    ``np.matmul`` at N = 3000 (the sums in another order: within 2e-14 relative).

    Parameters
    ----------
    m : ndarray, shape (N, 3, 3)
        Outer matrices.
    q : ndarray, shape (N, 3, 3)
        Inner matrices.

    """
    mt = np.ascontiguousarray(np.moveaxis(m, 0, -1))  # (3, 3, N)
    qt = np.ascontiguousarray(np.moveaxis(q, 0, -1))
    mq = [[mt[a, 0] * qt[0, d] + mt[a, 1] * qt[1, d] + mt[a, 2] * qt[2, d] for d in range(3)]
          for a in range(3)]
    out = np.empty((3, 3, m.shape[0]))
    for a in range(3):
        for b in range(3):
            out[a, b] = mq[a][0] * mt[b, 0] + mq[a][1] * mt[b, 1] + mq[a][2] * mt[b, 2]
    return np.moveaxis(out, -1, 0)


def cofactors_3x3(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the cofactor matrices and determinants of 3 × 3 matrices, by their 2 × 2 minors.

    ``cof(M) = det(M) M⁻ᵀ`` where M is invertible, defined for any M; one vector pass (batched
    ``np.linalg.det`` and ``inv`` of 3000 matrices took 2 ms, this 0.1 ms).

    Parameters
    ----------
    m : ndarray, shape (N, 3, 3)
        Matrices.

    Returns
    -------
    cof : ndarray, shape (N, 3, 3)
        ``cof[n, a, b] = (−1)^(a+b)`` × the minor of ``m[n]`` without row a and column b.
    det : ndarray, shape (N,)

    """
    cof = np.empty_like(m)
    for a in range(3):
        a1, a2 = (a + 1) % 3, (a + 2) % 3
        for b in range(3):
            b1, b2 = (b + 1) % 3, (b + 2) % 3
            cof[:, a, b] = m[:, a1, b1] * m[:, a2, b2] - m[:, a1, b2] * m[:, a2, b1]
    det = np.einsum('nb,nb->n', m[:, 0], cof[:, 0])
    return cof, det


def symmetric_inverse_3x3(blocks: np.ndarray) -> np.ndarray:
    """
    Return the inverses of symmetric 3 × 3 matrices, shape (N, 3, 3), by their adjugates.

    A matrix that is singular (or whose inverse is not finite) gets its pseudo-inverse: a
    particle no term reaches (``ε = 0``, no phyxel members) has a zero block. Closed form
    (:func:`cofactors_3x3`): ``np.linalg.inv`` of 3000 blocks took 1.0 ms.

    Parameters
    ----------
    blocks : ndarray, shape (N, 3, 3)
        Symmetric matrices.

    """
    cof, det = cofactors_3x3(blocks)
    with np.errstate(divide='ignore', invalid='ignore'):
        inv = cof / det[:, None, None]  # the adjugate is cofᵀ = cof for a symmetric matrix
    bad = ~np.isfinite(inv).all(axis=(1, 2)) | (det == 0.0)
    if bad.any():
        inv[bad] = np.linalg.pinv(blocks[bad], hermitian=True)
    return inv


def farthest_point_aggregates(points: np.ndarray, num_aggregates: int) -> np.ndarray:
    """
    Split a cloud into ``num_aggregates`` compact aggregates.

    Seeds by farthest-point sampling from particle 0 (deterministic), every particle joins its
    nearest seed.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Positions, mm.
    num_aggregates : int
        Aggregates wanted, 1 ≤ it ≤ N.

    Returns
    -------
    ndarray of int, shape (N,)
        Aggregate of each particle, 0 … num_aggregates − 1 (each holds at least its seed).

    """
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    k = int(num_aggregates)
    if not 1 <= k <= n:
        raise ValueError(
            f'num_aggregates must be in [1, {n}] (the particle count), got {num_aggregates}'
        )
    seeds = np.empty(k, dtype=np.int64)
    seeds[0] = 0
    dist = np.linalg.norm(pts - pts[0], axis=1)
    for a in range(1, k):  # a loop over aggregates, each a vector pass over the particles
        seeds[a] = int(np.argmax(dist))
        np.minimum(dist, np.linalg.norm(pts - pts[seeds[a]], axis=1), out=dist)
    _, agg = cKDTree(pts[seeds]).query(pts)
    agg[seeds] = np.arange(k)  # coincident points: a seed keeps its own aggregate
    return agg


class CoarseSpace:
    """
    Coarse space of the local stage.

    The affine displacement fields of each aggregate of particles, with the Galerkin projection of
    the internal terms built once per model.

    Block-Jacobi removes error that varies from particle to particle in a few CG iterations, but
    smooth error — a region of the wall shifting, turning or stretching as a whole against the
    stiff near-incompressibility, fit-error and data terms — only over many. The additive
    correction ``Z A_c⁻¹ Zᵀ r`` (``A_c = Zᵀ A Z``) removes that part each iteration. The basis is
    ``1, x, y, z`` per aggregate and displacement component (the MLS gradient reproduces affine
    fields exactly, so inside an aggregate its strain is exact), orthonormalised per aggregate;
    directions an aggregate cannot span (fewer than four or coplanar particles) are dropped.

    Only the data springs change between solves of a model enough to matter (other control
    points every phase), so the internal part of ``A_c`` is projected once, from the reference
    system at rest — cofactors ``I`` (the volume term is then ``k_v tr(H)²``) and the axis given —
    and the data part per solve (:meth:`factor`). Measured on the default study's recorded tag
    points (12 solves): the reference internal part took 115 CG iterations in all, the exact
    per-solve projection 116, block-Jacobi alone 251. Any SPD coarse matrix keeps PCG correct;
    only the iteration count depends on it.

    Parameters
    ----------
    ops : LocalOperators
    num_aggregates : int
        Aggregates (:func:`farthest_point_aggregates` of the rest positions).
    fit_error : float
        Multiplier of the fit-error penalty in the systems to precondition.
    volume_weight : float
        Their near-incompressibility ``k_v`` (P), 0 = none.
    axial : (k_l, a) or None
        Their axial stiffness (P) and a reference axis, shape (3,).
    eps : float
        Their rigid-mode regulariser ``ε`` (P·mm).
    shear : (k_s, a, r) or None
        Their transmural axial shear term ``½ k_s Σ_i v_i (aᵀ H_i r_i)²``: stiffness (P), the
        reference axis, shape (3,), and each particle's radial direction, shape (N, 3)
        (``MotionTracker._axial_shear``). Without it in ``A_c`` the term's smooth error is left
        to block-Jacobi: twice the CG iterations (study 2007's replay 471 → 1067).

    Attributes
    ----------
    aggregate : ndarray of int, shape (N,)
    basis : scipy.sparse.csr_matrix, shape (N, Q)
        Scalar basis ``Z_s`` (the vector basis is ``Z_s ⊗ I₃``; coarse unknowns are ordered
        component-major, index ``e Q + q``).
    internal : ndarray, shape (3Q, 3Q)
        ``Zᵀ A_ref Z`` of the internal terms (elasticity, volume, axial, shear, fit error, ε).

    """

    def __init__(
        self,
        ops: 'LocalOperators',
        num_aggregates: int,
        *,
        fit_error: float = 0.0,
        volume_weight: float = 0.0,
        axial: tuple | None = None,
        eps: float = 0.0,
        shear: tuple | None = None,
    ):
        self.ops = ops
        n = ops.n
        agg, self.basis = _aggregate_basis(ops.operator.phyxels.points, n, num_aggregates)
        self.aggregate, self.num_basis = agg, self.basis.shape[1]
        self._basis_t = self.basis.T.tocsr()
        psi = (ops.operator.matrix @ self.basis).tocsr()  # rows 3i + b: Σ_j d_ij[b] Z_s[j, q]
        rows_b = [psi[b::3] for b in range(3)]
        vol = sp.diags(ops.volume)
        vpsi = [vol @ r for r in rows_b]
        pp = [[(rows_b[x].T @ vpsi[y]).toarray() for y in range(3)] for x in range(3)]
        fm = ops.fit_error_moment
        fit = sum(
            (rows_b[x].T @ (sp.diags(fm[:, y, x]) @ rows_b[y])).toarray()
            for x in range(3)
            for y in range(3)
        )
        zs, zt = self.basis, self._basis_t
        diag = (
            ops.mu * sum(pp[x][x] for x in range(3))
            - float(fit_error) * fit
            + float(fit_error) * (zt @ (ops.laplacian @ zs)).toarray()
            + float(eps) * (zt @ zs).toarray()
        )
        lam = ops.lam + float(volume_weight)
        blocks = [
            [ops.mu * pp[f][e] + lam * pp[e][f] + (diag if e == f else 0.0) for f in range(3)]
            for e in range(3)
        ]
        if axial is not None and axial[0]:
            ax = np.asarray(axial[1], dtype=np.float64)
            pa = sum(ax[x] * rows_b[x] for x in range(3))
            paa = (pa.T @ (vol @ pa)).toarray() * float(axial[0])
            blocks = [[blocks[e][f] + ax[e] * ax[f] * paa for f in range(3)] for e in range(3)]
        if shear is not None and shear[0]:
            # aᵀ H_i r_i = Σ_e a_e Σ_b r_ib ∂u_e/∂X_b: the axial term's form with the radial
            # derivative in place of the axial one
            ax, rad = np.asarray(shear[1], dtype=np.float64), np.asarray(shear[2], np.float64)
            pr = sum(sp.diags(rad[:, x]) @ rows_b[x] for x in range(3))
            prr = (pr.T @ (vol @ pr)).toarray() * float(shear[0])
            blocks = [[blocks[e][f] + ax[e] * ax[f] * prr for f in range(3)] for e in range(3)]
        self.internal = np.block(blocks)

    def factor(self, data: tuple | None = None):
        """
        Build the coarse correction of one system: ``r ↦ Z A_c⁻¹ Zᵀ r`` for residuals (N, 3).

        Parameters
        ----------
        data : (κ, Φ, P) or None
            The system's data springs (:meth:`LocalOperators.system`), projected here.

        """
        ac = self.internal
        if data is not None:
            # κ Σ_k P_k[e, f] z_k z_kᵀ per block (e, f), z_k = Zᵀ φ_k: the (M, Q) projection is
            # small and dense, so one matrix product gives the six blocks (M × 6Q columns):
            # 2.5 ms against 4.0 ms for six sparse triple products (3000 particles, 262 points).
            kappa, phi, metric = data
            pz = (sp.csr_matrix(phi) @ self.basis).toarray()
            q = self.num_basis
            upper = [(e, f) for e in range(3) for f in range(e, 3)]
            weighted = np.empty((pz.shape[0], len(upper) * q))  # the products, not concatenated
            for b, (e, f) in enumerate(upper):
                np.multiply(pz, metric[:, e, f][:, None], out=weighted[:, b * q:(b + 1) * q])
            blocks = float(kappa) * (pz.T @ weighted)
            ac = ac.copy()
            for b, (e, f) in enumerate(upper):
                blk = blocks[:, b * q:(b + 1) * q]
                ac[e * q:(e + 1) * q, f * q:(f + 1) * q] += blk
                if f != e:
                    ac[f * q:(f + 1) * q, e * q:(e + 1) * q] += blk.T
        try:
            # LAPACK's potrs on the factor directly: what cho_solve calls, bit for bit, without
            # its wrapper (0.067 against 0.12 ms a solve at 372 unknowns, once per CG iteration).
            factor = sla.cho_factor(ac, lower=True, check_finite=False)[0]
            solve = lambda y: lapack.dpotrs(factor, y, lower=1)[0]  # noqa: E731
        except np.linalg.LinAlgError:  # not positive definite (ε = 0 and no data): pseudo-inverse
            val, vec = np.linalg.eigh(ac)
            good = val > 1e-12 * max(float(val[-1]), 1e-300)
            inv = (vec[:, good] / val[good]) @ vec[:, good].T
            solve = inv.__matmul__
        basis, basis_t, q = self.basis, self._basis_t, self.num_basis

        def correct(r: np.ndarray) -> np.ndarray:
            y = solve((basis_t @ r).T.ravel())
            return basis @ y.reshape(3, q).T

        return correct


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.einsum('i,i->', a, b))


def pcg(
    matvec,
    precond,
    b: np.ndarray,
    x0: np.ndarray | None = None,
    *,
    rtol: float = 1e-3,
    atol: float = 0.0,
    maxiter: int = 400,
    r0: np.ndarray | None = None,
    on_step=None,
) -> tuple[np.ndarray, int]:
    """
    Solve ``A x = b`` by preconditioned conjugate gradients without BLAS inner products.

    The iteration and stopping rule of :func:`scipy.sparse.linalg.cg` (``‖r‖ ≤ max(rtol ‖b‖,
    atol)``, tested before each iteration), with inner products that do not call BLAS.

    scipy's loop takes them with ``np.dot``; from 10⁴ unknowns OpenBLAS runs those on a second
    thread that then spins on the core the sparse products need — measured on 2 cores at 10k
    particles: 144 ms per iteration against 43 ms with one BLAS thread.

    Parameters
    ----------
    matvec, precond : callable
        ``A v`` and ``M⁻¹ v`` for 1-D arrays (A symmetric positive definite, M SPD).
    b : ndarray, shape (n,)
        Right-hand side.
    x0 : ndarray, shape (n,), optional
        Start (zero if None).
    rtol, atol : float
        Relative and absolute tolerances on the residual norm ``‖r‖``.
    maxiter : int
        Most iterations.
    r0 : ndarray, shape (n,), optional
        ``b − A x0`` when the caller has it (used only with a non-zero ``x0``).
    on_step : callable, optional
        ``on_step(alpha)`` after each update ``x += alpha p`` (``p`` the direction the last
        ``matvec`` took).

    Returns
    -------
    x : ndarray, shape (n,)
    iterations : int
        Iterations done (``maxiter`` if the tolerance was not reached).

    """
    bnrm = np.sqrt(_dot(b, b))
    if bnrm == 0.0:
        return np.zeros_like(b), 0
    tol = max(float(atol), float(rtol) * bnrm)
    if x0 is None or not np.any(x0):
        x, r = np.zeros_like(b), b.copy()
    else:
        x = np.array(x0, dtype=np.float64)
        r = b - matvec(x) if r0 is None else np.array(r0, dtype=np.float64)
    p = rho_prev = None
    for it in range(int(maxiter)):
        if np.sqrt(_dot(r, r)) < tol:
            return x, it
        z = precond(r)
        rho = _dot(r, z)
        if p is None:
            p = z.copy()
        else:
            p *= rho / rho_prev
            p += z
        q = matvec(p)
        alpha = rho / _dot(p, q)
        x += alpha * p
        if on_step is not None:
            on_step(alpha)
        r -= alpha * q
        rho_prev = rho
    return x, int(maxiter)


def _aggregate_basis(pts: np.ndarray, n: int, num_aggregates: int):
    """
    Return the aggregates of the ``n`` points ``pts`` (N, 3) mm and their scalar coarse basis.

    Per aggregate the functions 1, x, y, z (centred, scaled) made orthonormal over its points,
    dropping dependent ones; returns ``(aggregate (N,) int, Z_s csr (N, Q))``.
    """
    agg = farthest_point_aggregates(pts, num_aggregates)
    na = int(agg.max()) + 1
    count = np.bincount(agg, minlength=na)
    centre = (
        np.stack([np.bincount(agg, weights=pts[:, a], minlength=na) for a in range(3)], axis=1)
        / count[:, None]
    )
    rel = pts - centre[agg]
    scale = max(float(np.sqrt(np.mean(np.sum(rel**2, axis=1)))), 1e-12)
    b = np.concatenate([np.ones((n, 1)), rel / scale], axis=1)  # (N, 4)
    gram = np.zeros((na, 4, 4))
    for a in range(4):
        for c in range(a, 4):
            gram[:, a, c] = gram[:, c, a] = np.bincount(
                agg, weights=b[:, a] * b[:, c], minlength=na
            )
    val, vec = np.linalg.eigh(gram)
    keep = val > 1e-8 * val[:, -1:]
    wmat = (
        vec / np.sqrt(np.where(keep, val, 1.0))[:, None, :]
    )  # orthonormal over each aggregate
    col = np.cumsum(keep.ravel()).reshape(na, 4) - 1
    vals = np.einsum('na,nac->nc', b, wmat[agg])
    k = keep[agg]
    rows = np.broadcast_to(np.arange(n)[:, None], (n, 4))
    q = int(keep.sum())
    return agg, sp.csr_matrix((vals[k], (rows[k], col[agg][k])), shape=(n, q))
