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
The meshless deformable model and its fitting scheme (paper §2, eq. 5–15 and 22–23).

A :class:`MeshlessModel` holds the rest (end-diastolic) particle cloud, its phyxels and MLS
operator, the model frame (material coordinates + rest global parameters) and the current state:
global parameters ``q_g = (c, θ, a0..a3, τ)`` and the local deformation ``d``. World positions
are ``x = c + R (s(q_s) + d)``.

:meth:`MeshlessModel.fit` alternates the two stages of the paper:

1. **Global stage** — eq. 15, ``q ← q + D⁻¹ f_q`` with the generalised force
   ``f_q = Σ_k L_kᵀ f_k`` (eq. 9–14; the force ``f_k = P_k (t_k − x_k)`` at control point k is
   spread to particles with kernel weights, so ``L_k = Σ_j φ_kj L_j``). The default damping
   metric is ``D = Σ_k L_kᵀ P_k L_k`` with Levenberg–Marquardt regularisation, i.e. one
   Gauss–Newton step per iteration (``global_update="gauss-newton"``); the paper's constant
   diagonal ``D`` with step ``dt`` is available as ``global_update="explicit"``.
2. **Local stage** — eq. 6, ``D ḋ = f_ext + f_int`` for the local deformation. The default
   (``local_update="solve"``) takes the step to equilibrium at once: it minimises
   ``½ κ Σ_k |P_k (t_k − x_k)|² + ½ δᵀ K δ + ½ ε |δ|²`` over δ with the St Venant–Kirchhoff
   stiffness ``K`` linearised at rest (plus the zero-energy-mode penalty), by the block-Jacobi
   preconditioned conjugate gradients of :mod:`mlv_ros.core.meshless.local` (inexact,
   ``cg_rtol``; δ accumulates over iterations). ε = 1e-4 ×
   median diag(K) only removes the rigid-mode ambiguity between δ and (c, R).
   ``local_update="explicit"`` is the paper-literal explicit step
   ``δ ← δ + dt D⁻¹ (f_ext + f_int(δ))`` with the full non-linear internal force and diagonal
   damping ``D = diag(κ ΦᵀQᵀPQΦ + K + ε)``.

The internal force acts on the local deformation only (the paper: "the internal force is only
considered in local deformation"): the elastic energy is that of the displacement field ``δ``
(``d = d_rest + R₀ᵀ δ``, δ expressed in the rest world frame) on the rest configuration.

**Convergence criterion**: an iteration is the global step followed (once the global stage has
settled, i.e. its step moved control points by < ``local_start`` mm RMS) by the local step. The
fit stops when, after a local step, the RMS change of all particle positions in that iteration
is below ``tol`` mm (with the local stage disabled: when the global step moved control points by
less than ``tol`` mm RMS), or when the control residual RMS is below ``residual_tol`` mm.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from itertools import chain
import time
from typing import Callable

from mlv_ros.core.meshless import elastic
from mlv_ros.core.meshless.globals import (
    control_jacobian,
    global_shape,
    GlobalParameters,
    ModelCoordinates,
    ModelFrame,
    reduce_rotation,
    shape_jacobian,
    shape_terms,
    tangent_gram,
    twist_cos_sin,
)
from mlv_ros.core.meshless.kernel import (
    build_phyxels,
    NUM_NEIGHBOURS,
    poly6,
    poly6_norm,
    SUPPORT_FACTOR,
    validate_points,
)
from mlv_ros.core.meshless.local import LocalOperators, rigid_mode_eps
from mlv_ros.core.meshless.mls import MLSOperator
from mlv_ros.core.types import ModelState
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree


# --------------------------------------------------------------------------- control points
@dataclass
class ControlPoints:
    """
    Control points attached to particles by kernel weights.

    Attributes
    ----------
    weights : scipy.sparse.csr_matrix, shape (M, N)
        ``φ_kj``: a control point moves as ``x_k = Σ_j φ_kj x_j``. Rows sum to 1. For control
        points given as particle indices the row is the unit vector of that particle; for
        positions it holds linear-MLS shape functions (poly6 weights, support ``3 r̄`` from the 10
        nearest particles), which reproduce any affine motion exactly.
    rest_positions : ndarray, shape (M, 3)
        Positions at rest (ED), mm.
    indices : ndarray of int or None
        Particle indices when the control points are particles.
    shepard : ndarray of bool, shape (M,)
        Control points whose MLS moment matrix was degenerate (e.g. all nearby particles
        coplanar); they fall back to normalised kernel (Shepard) weights.

    """

    weights: sp.csr_matrix
    rest_positions: np.ndarray
    indices: np.ndarray | None = None
    shepard: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def __len__(self) -> int:
        return int(self.weights.shape[0])


def particle_support_radii(
    points: np.ndarray,
    tree: cKDTree,
    k: int = NUM_NEIGHBOURS,
    support_factor: float = SUPPORT_FACTOR,
) -> np.ndarray:
    """
    Return each particle's own support radius, shape (N,).

    ``support_factor`` × the mean distance to its ``k`` nearest other particles: what
    :func:`attach_control_points` tests a control point's nearest particle against (compute once
    per cloud and pass it as ``support_radii``).
    """
    n = points.shape[0]
    d_pp, _ = tree.query(points, k=min(k + 1, n))
    return support_factor * d_pp.reshape(n, -1)[:, 1:].mean(axis=1)


def attach_control_points(
    points: np.ndarray,
    control,
    tree: cKDTree | None = None,
    k: int = NUM_NEIGHBOURS,
    support_factor: float = SUPPORT_FACTOR,
    support_radii: np.ndarray | None = None,
    neighbours: tuple | None = None,
) -> ControlPoints:
    """
    Attach control points to the particle cloud.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Rest particle positions, mm.
    control : array_like
        Either integer particle indices, shape (M,), or rest positions, shape (M, 3), mm.
    tree : cKDTree, optional
        Tree on ``points``.
    k : int
        Number of nearest particles that define a support radius (default
        :data:`~mlv_ros.core.meshless.kernel.NUM_NEIGHBOURS`).
    support_factor : float
        Support radius = ``support_factor`` × the mean distance to those ``k`` particles (default
        :data:`~mlv_ros.core.meshless.kernel.SUPPORT_FACTOR`).
    support_radii : ndarray, shape (N,), optional
        :func:`particle_support_radii` of ``points`` (with the same ``k`` and
        ``support_factor``), when attaching repeatedly to one cloud.
    neighbours : (dist, idx), optional
        ``tree.query(control, k)`` of the control positions, each shape (M, k), when the caller
        has queried them already (the same numbers, so the same weights).

    Returns
    -------
    ControlPoints

    Raises
    ------
    ValueError
        No control points; indices out of range; non-finite positions; a position outside the
        particle cloud (farther from its nearest particle than that particle's support radius).

    """
    n = points.shape[0]
    c = np.asarray(control)
    if c.size == 0:
        raise ValueError(
            'no control points: at least one control point (index or position) is required'
        )
    if c.ndim == 1 and np.issubdtype(c.dtype, np.integer):
        idx = c.astype(np.int64)
        if idx.min() < 0 or idx.max() >= n:
            raise ValueError(
                f'control point indices must lie in [0, {n}), got range [{idx.min()}, {idx.max()}]'
            )
        m = idx.size
        w = sp.csr_matrix((np.ones(m), (np.arange(m), idx)), shape=(m, n))
        return ControlPoints(w, points[idx].copy(), idx, np.zeros(m, dtype=bool))
    y = validate_points(c, 'control point positions')
    m = y.shape[0]
    tree = cKDTree(points) if tree is None else tree
    dist, nn = tree.query(y, k=min(k, n)) if neighbours is None else neighbours
    dist, nn = dist.reshape(m, -1), nn.reshape(m, -1)
    h = support_factor * dist.mean(axis=1)
    # Outside the cloud: farther from its nearest particle than that particle's own support
    # radius (3 × its mean 10-NN spacing).
    if support_radii is None:
        d_pp, _ = tree.query(points[nn[:, 0]], k=min(k + 1, n))
        h_near = support_factor * d_pp.reshape(m, -1)[:, 1:].mean(axis=1)
    else:
        h_near = support_radii[nn[:, 0]]
    far = dist[:, 0] > h_near
    if far.any():
        bad = int(np.flatnonzero(far)[0])
        raise ValueError(
            f'control point {bad} at {y[bad].tolist()} lies outside the particle cloud: '
            f'no particle within {h_near[bad]:.3g} mm (nearest {dist[bad, 0]:.3g} mm)'
        )
    lists = tree.query_ball_point(y, r=h, return_sorted=False)
    counts = np.fromiter(map(len, lists), dtype=np.int64, count=m)
    pj = np.fromiter(chain.from_iterable(lists), dtype=np.int64, count=int(counts.sum()))
    phi, shepard = _mls_shape_functions(points, y, h, pj, counts)
    # Rows are already grouped (pk is sorted): the CSR arrays directly, then column-sorted as
    # the COO conversion left them.
    w = sp.csr_matrix((phi, pj, np.concatenate([[0], np.cumsum(counts)])), shape=(m, n))
    w.sort_indices()
    return ControlPoints(w, y.copy(), None, shepard)


#: (a, b) of the 10 distinct entries of a symmetric 4 × 4 moment matrix, row by row.
_MOMENT_ENTRIES = np.array([(a, b) for a in range(4) for b in range(a, 4)])


def _mls_shape_functions(points, y, h, pj, counts):
    """
    Return the linear-MLS shape functions of control points and which fell back to Shepard.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Rest particle positions, mm.
    y : ndarray, shape (M, 3)
        Control positions, mm.
    h : ndarray, shape (M,)
        Their support radii, mm.
    pj : ndarray of int, shape (P,)
        The particles within each support, grouped by control point in order.
    counts : ndarray of int, shape (M,)
        How many of ``pj`` belong to each control point.

    Returns
    -------
    phi : ndarray, shape (P,)
        ``φ`` of each pair (poly6 weights ``w``, ``φ_j = w_j p_jᵀ M⁻¹ p(y)``, ``p = (1, x − y)``:
        they reproduce affine fields), or normalised kernel weights where ``M`` is degenerate.
    shepard : ndarray of bool, shape (M,)
        Control points whose moment matrix was degenerate (e.g. all nearby particles coplanar).

    """
    m = y.shape[0]
    # Per-control values spread to their pairs with np.repeat (the pairs are grouped), and the
    # particles gathered with np.take: the same numbers as indexing with the pairs' control
    # index, in a third of the time (the distance is the same sum as np.linalg.norm's). Pairs
    # run along the rows' contiguous axis (component-major (3, P) and (4, P)): the same
    # element-wise numbers as pair-major rows, 1.45 against 1.8 ms a call (253 control points,
    # 69 pairs each).
    rel = np.take(points.T, pj, axis=1)
    rel -= np.repeat(y.T, counts, axis=1)
    hk = np.repeat(h, counts)
    sq = rel * rel
    # the kernel's normalisation once per control point, not per pair
    wk = poly6(np.sqrt(sq[0] + sq[1] + sq[2]), hk, np.repeat(poly6_norm(h), counts))
    basis = np.empty((4, pj.size))
    basis[0] = 1.0
    np.divide(rel, hk, out=basis[1:])
    wb = wk * basis
    # Σ w p pᵀ per control point, its 10 distinct entries as one product with the (M, P) matrix
    # of ones that groups the pairs: each row sums its pairs in order, as a bincount per entry
    # did, in 0.55 against 0.94 ms (330 control points, 68 pairs each).
    prod = np.empty((pj.size, len(_MOMENT_ENTRIES)))
    for e, (a, b) in enumerate(_MOMENT_ENTRIES):
        np.multiply(wb[a], basis[b], out=prod[:, e])
    ptr = np.concatenate([[0], np.cumsum(counts)])
    sums = sp.csr_matrix((np.ones(pj.size), np.arange(pj.size), ptr), shape=(m, pj.size)) @ prod
    ea, eb = _MOMENT_ENTRIES.T
    mom = np.empty((m, 4, 4))
    mom[:, ea, eb] = sums
    mom[:, eb, ea] = sums
    sv = np.abs(np.linalg.eigvalsh(mom))  # symmetric positive semi-definite: its singular values
    shepard = ~(sv.min(axis=1) > 1e-8 * sv.max(axis=1))
    rhs = np.zeros((m, 4, 1))
    rhs[:, 0, 0] = 1.0
    coef = np.zeros((m, 4))
    ok = ~shepard
    if ok.any():
        coef[ok] = np.linalg.solve(mom[ok], rhs[ok])[:, :, 0]
    # einsum on pair-major rows, as before: its sum over the 4 terms in its own order
    pair_major = np.ascontiguousarray(basis.T)
    phi = wk * np.einsum('pa,pa->p', pair_major, np.repeat(coef, counts, axis=0))
    if shepard.any():
        pk = np.repeat(np.arange(m), counts)
        wsum = np.bincount(pk, weights=wk, minlength=m)
        phi = np.where(shepard[pk], wk / wsum[pk], phi)
    return phi, shepard


def plane_projectors(normals, m: int) -> np.ndarray:
    """
    Return the data springs' projectors, shape (M, 3, 3): in-plane ``I − ν νᵀ`` or 1-D ``n nᵀ``.

    A tag intersection (grid) measures the in-plane motion, ``P = I − ν νᵀ`` with ν the image
    plane's normal. A point on a single family of tag lines measures only the motion along the
    lines' normal n (in the image plane): ``P = n nᵀ``, the 1-D analogue (the paper's external
    force, §2.4, with a line instead of an intersection). Identity if ``normals`` is None.

    Parameters
    ----------
    normals : array_like, shape (M, 3), (3,) or (M, 2, 3), or None
        Plane normals ν (any length > 0; normalised here), or per point the pair (ν, n): the
        image plane's normal and the tag lines' normal, n a row of NaN for a grid point. n is
        made orthogonal to ν and normalised here. A NaN ν is not allowed; to constrain a point
        fully pass ``normals=None`` or use separate calls.
    m : int
        Number of control points M.

    Raises
    ------
    ValueError
        Wrong shape, NaN/inf plane normals, a zero-length plane normal, a line normal that is
        partly NaN or has no component in the image plane.

    """
    if normals is None:
        return np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
    nrm = np.asarray(normals, dtype=np.float64)
    if nrm.shape == (m, 2, 3):
        return _line_projectors(nrm)
    if nrm.shape == (3,):
        nrm = np.broadcast_to(nrm, (m, 3))
    if nrm.shape != (m, 3):
        raise ValueError(
            f'plane_normals must have shape ({m}, 3), (3,) or ({m}, 2, 3), got {nrm.shape}'
        )
    if not np.all(np.isfinite(nrm)):
        raise ValueError('plane_normals contain NaN/inf')
    ln = np.linalg.norm(nrm, axis=1)
    if np.any(ln < 1e-12):
        raise ValueError(f'plane normal {int(np.argmin(ln))} has zero length')
    nrm = nrm / ln[:, None]
    return np.eye(3) - nrm[:, :, None] * nrm[:, None, :]


def _line_projectors(pairs) -> np.ndarray:
    """Return ``I − ν νᵀ`` (grid) or ``n nᵀ`` (tag line) per (ν, n) pair of shape (M, 2, 3)."""
    proj = plane_projectors(pairs[:, 0], len(pairs))
    line = pairs[:, 1]
    is_line = np.isfinite(line).all(axis=1)
    if np.any(~is_line & ~np.isnan(line).all(axis=1)):
        raise ValueError('a tag-line normal must be finite or all NaN (grid point)')
    if is_line.any():
        # n in the image plane: (I − ν νᵀ) n, normalised
        n = np.einsum('kab,kb->ka', proj[is_line], line[is_line])
        ln = np.linalg.norm(n, axis=1)
        if np.any(ln < 1e-6):
            raise ValueError(
                f'tag-line normal {int(np.flatnonzero(is_line)[np.argmin(ln)])} has no '
                'component in its image plane'
            )
        n /= ln[:, None]
        proj[is_line] = n[:, :, None] * n[:, None, :]
    return proj


def control_weights(weights, m: int) -> np.ndarray:
    """
    Per-control-point data weights scaled to mean 1, shape (M,); all 1 when ``weights`` is None.

    Raises
    ------
    ValueError
        Wrong shape, NaN/inf, negative, or all zero.

    """
    if weights is None:
        return np.ones(m)
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (m,):
        raise ValueError(
            f'weights must have shape ({m},) to match the control points, got {w.shape}'
        )
    if not np.all(np.isfinite(w)) or np.any(w < 0.0) or not np.any(w > 0.0):
        raise ValueError('weights must be finite, >= 0 and not all zero')
    return w * (m / float(np.sum(w)))


# --------------------------------------------------------------------------- result
@dataclass
class FitResult:
    """
    Outcome of :meth:`MeshlessModel.fit`.

    Attributes
    ----------
    positions : ndarray, shape (N, 3)
        Current particle positions, mm (world).
    state : ModelState
        Global parameters and convergence record.
    iterations : int
    residual : float
        RMS over control points of the (in-plane projected) residual ``|P_k (t_k − x_k)|``, mm.
    converged : bool
    history : list of dict
        Per iteration: ``iteration``, ``residual`` (mm), ``global_step`` and ``local_step``
        (RMS position change, mm), ``local`` (whether the local stage ran), ``cg_iterations``,
        ``seconds`` (wall time of the iteration).
    wall_time : float
        Seconds spent in the fit.

    """

    positions: np.ndarray
    state: ModelState
    iterations: int
    residual: float
    converged: bool
    history: list = field(default_factory=list)
    wall_time: float = 0.0


def _check_fit_options(global_update, local_update, global_prior) -> None:
    """Raise ValueError for an unknown update scheme or a negative or non-finite prior."""
    if global_update not in ('gauss-newton', 'explicit'):
        raise ValueError(
            f"global_update must be 'gauss-newton' or 'explicit', got {global_update!r}"
        )
    if local_update not in ('solve', 'explicit'):
        raise ValueError(f"local_update must be 'solve' or 'explicit', got {local_update!r}")
    if not (np.isfinite(global_prior) and global_prior >= 0.0):
        raise ValueError(f'global_prior must be finite and >= 0, got {global_prior}')


class _FitData:
    """
    One fit's control points, targets and projectors, and its residual (eq. 10–13).

    ``proj`` is ``√w P`` (it enters the residual, squared in ``D`` and the cost), ``proj_local``
    ``w P`` (the local stage applies the projector once). ``support`` are the particles some
    control point's kernel reaches; the global stage works on them only.
    """

    @classmethod
    def build(cls, model, control, targets, plane_normals, weights) -> '_FitData':
        """Check and gather a fit's input (see :meth:`MeshlessModel.fit` for the errors)."""
        data = cls()
        data.ctrl = control if isinstance(control, ControlPoints) else model.attach(control)
        data.m = m = len(data.ctrl)
        data.tgt = np.asarray(targets, dtype=np.float64)
        if data.tgt.shape != (m, 3):
            raise ValueError(
                f'targets must have shape ({m}, 3) to match the control points, '
                f'got {data.tgt.shape}'
            )
        if not np.all(np.isfinite(data.tgt)):
            raise ValueError(
                'targets contain NaN/inf (first bad row '
                f'{int(np.flatnonzero(~np.isfinite(data.tgt).all(1))[0])})'
            )
        proj = plane_projectors(plane_normals, m)
        data.w = control_weights(weights, m)
        data.proj_local = proj * data.w[:, None, None]
        data.proj = proj * np.sqrt(data.w)[:, None, None]
        return data

    def restrict(self, model) -> None:
        """Restrict the kernel weights and coordinates to the supported particles."""
        phi = sp.csr_matrix(self.ctrl.weights)
        n = phi.shape[1]
        self.support = np.flatnonzero(np.bincount(phi.indices, minlength=n))
        # The columns renumbered in place of phi[:, support]: the same entries in the same order
        # (the support keeps the columns' order), without scipy's column indexing.
        column = np.zeros(n, dtype=phi.indices.dtype)
        column[self.support] = np.arange(self.support.size, dtype=phi.indices.dtype)
        self.phi_s = sp.csr_matrix(
            (phi.data, column[phi.indices], phi.indptr), shape=(phi.shape[0], self.support.size)
        )
        self.coords_s = model.coords.subset(self.support)
        self._shape = None  # [key, cos_sin, s, jac or None] on the support, at one (a, τ)

    def shape(self, params, jacobian: bool = False) -> tuple:
        """
        Return ``(cos_sin, s, jac)`` of the supported particles at ``params`` (``jac`` if asked).

        :func:`~mlv_ros.core.meshless.globals.shape_terms` on the support, kept for the last
        ``(a, τ)`` asked: a Gauss–Newton step's Jacobian is taken where the step before took its
        accepted residual, and the prior's terms over all particles (:meth:`seed`) serve the first
        residual and Jacobian. Only ``a`` and ``τ`` enter the shape.
        """
        key = (np.asarray(params.a, dtype=np.float64).tobytes(), float(params.tau))
        c = self._shape
        if c is None or c[0] != key:
            cs = twist_cos_sin(self.coords_s, params.tau)
            s = global_shape(self.coords_s, params.a, params.tau, cs)
            c = self._shape = [key, cs, s, None]
        if jacobian and c[3] is None:
            c[3] = shape_jacobian(self.coords_s, params.a, params.tau, c[1])
        return c[1], c[2], c[3]

    def seed(self, params, terms) -> None:
        """Keep :func:`shape_terms` of all particles at ``params`` for :meth:`shape` (its rows)."""
        (c, s_), s, jac = terms
        sup = self.support
        key = (np.asarray(params.a, dtype=np.float64).tobytes(), float(params.tau))
        self._shape = [key, (c[sup], s_[sup]), s[sup], jac[sup]]

    @cached_property
    def phi_t(self):
        """
        Return ``Φᵀ`` as CSR, shape (N, M), built on first use.

        The local stage spreads forces with it; global-only fits never need it.
        """
        return self.ctrl.weights.T.tocsr()

    def positions(self, params, d_s):
        """Return the control points' world positions under ``params`` and ``d_s``, mm."""
        p = self.shape(params)[1] + d_s
        return self.phi_s @ (params.translation + p @ params.matrix.T)

    def residual(self, params, d_s):
        """Return the projected, weighted residuals ``√w_k P_k (t_k − x_k)``, shape (M, 3)."""
        return np.matmul(self.proj, (self.tgt - self.positions(params, d_s))[:, :, None])[:, :, 0]


class _GlobalStage:
    """
    The global stage (eq. 15): a Gauss–Newton/Levenberg–Marquardt step or the paper's.

    'gauss-newton' damps with ``D = LᵀPL`` (+ μ, and the optional prior ``(G, s)``);
    'explicit' with the paper's constant diagonal, a step of ``dt``.
    """

    def __init__(self, scheme, dt, prior):
        self.scheme, self.dt, self.prior = scheme, dt, prior
        self.mu_lm = 1e-3
        self.d_diag_const = None
        self.residual = None  # the residual at the stepped parameters, when the step took it

    def step(self, model, data, d_s, res) -> float:
        """
        Step ``model.params``; return the RMS control-point motion of the step, mm.

        A Gauss–Newton step leaves the residual it accepted the step with in :attr:`residual`
        (None otherwise).
        """
        self.residual = None
        m = data.m
        lk = reduce_rotation(  # L_k = Σ_j φ_kj L_j (eq. 14)
            control_jacobian(
                model.params, data.coords_s, d_s, data.phi_s, data.shape(model.params, True)
            ),
            model.params.rotation,
        )
        # (batched and plain matrix products: einsum's loops were a third of the fit's time)
        plk = np.matmul(data.proj, lk).reshape(3 * m, -1)
        dmat = plk.T @ plk  # D = Σ L_kᵀ P_k L_k
        fq = plk.T @ res.ravel()  # f_q = Σ L_kᵀ f_k (eq. 10–13)
        if self.scheme == 'gauss-newton':
            step, self.mu_lm, accepted = model._lm_step(
                dmat, fq, res, self.mu_lm, lambda p: data.residual(p, d_s), self.prior
            )
            if self.prior is not None:
                self.prior = (self.prior[0], self.prior[1] + step)
        else:
            if self.d_diag_const is None:  # paper: D diagonal and constant over time
                dd = np.diag(dmat)
                self.d_diag_const = np.maximum(dd, 1e-12 * max(dd.max(), 1e-300))
            step, accepted = self.dt * fq / self.d_diag_const, None
        if accepted is None:
            model.params = model.params.stepped(step)
        else:  # the parameters the residual was taken at (the same numbers as stepping again)
            model.params, self.residual = accepted
        return float(np.sqrt(np.mean(np.sum((lk @ step) ** 2, axis=1))))


# --------------------------------------------------------------------------- model
class MeshlessModel:
    """
    Meshless deformable model on a rest particle cloud.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Rest (ED) particle positions, mm (world / patient), best in a spatially coherent order
        (a lattice's, as the samplers give them): the local stage's sparse products follow it,
        and a random order made a CG iteration 4.1× slower at 100k particles (Morton order was
        no faster than the lattice's; ``bench/phantom.py --order``).
    frame : ModelFrame
        Rest global parameters and material coordinates of each particle (see
        :func:`~mlv_ros.core.meshless.globals.polar_frame`,
        :func:`~mlv_ros.core.meshless.globals.cylindrical_frame`). Any mismatch between the
        frame's rest shape and ``points`` is kept as a constant ``d_rest``.
    youngs_modulus, poisson_ratio : float
        Material (eq. 20). Only the ratio to ``data_weight`` matters for the fit.
    k, support_factor, cond_max :
        Phyxel parameters (:func:`~mlv_ros.core.meshless.kernel.build_phyxels`).
    stabilisation : float
        Weight (× μ) of the zero-energy-mode penalty (the MLS fit error of eq. 16,
        :attr:`local_operators`) added to the local stage's stiffness; 0 = pure St
        Venant–Kirchhoff. Without it particles without a control point do not follow their
        neighbours.

    Raises
    ------
    ValueError
        Bad points (shape, NaN/inf, duplicates, < 5), frame size mismatch, bad material.

    """

    def __init__(
        self,
        points,
        frame: ModelFrame,
        youngs_modulus: float = 1.0,
        poisson_ratio: float = 0.45,
        *,
        k: int = NUM_NEIGHBOURS,
        support_factor: float = SUPPORT_FACTOR,
        cond_max: float = 1.0e4,
        stabilisation: float = 1000.0,
    ):
        self.rest_points = validate_points(points, 'particle positions', min_count=5)
        n = self.rest_points.shape[0]
        if not isinstance(frame, ModelFrame):
            raise ValueError('frame must be a ModelFrame (see polar_frame / cylindrical_frame)')
        if len(frame.coords) != n:
            raise ValueError(f'frame has {len(frame.coords)} particles, points has {n}')
        self.lam, self.mu = elastic.lame_parameters(youngs_modulus, poisson_ratio)
        self.stabilisation = float(stabilisation)
        if not np.isfinite(self.stabilisation) or self.stabilisation < 0:
            raise ValueError(f'stabilisation must be finite and >= 0, got {stabilisation}')
        self._k, self._support_factor, self._cond_max = k, support_factor, cond_max
        self.coords: ModelCoordinates = frame.coords
        self.rest_params: GlobalParameters = frame.params.copy()
        s_rest = global_shape(self.coords, self.rest_params.a, self.rest_params.tau)
        self.d_rest = (
            self.rest_points - self.rest_params.translation
        ) @ self.rest_params.matrix - s_rest
        self._tree = cKDTree(self.rest_points)
        self._support_radii = None  # per particle, for attach (built on first use)
        self._build_phyxels(None)
        self.params = self.rest_params.copy()
        self.delta = np.zeros((n, 3))
        self._controls_cache: tuple | None = None

    # ---------------------------------------------------------------- structure
    def _build_phyxels(self, h):
        self.phyxels = build_phyxels(
            self.rest_points, self._k, self._support_factor, self._cond_max, h=h
        )
        self.operator = MLSOperator(self.phyxels)
        self._local_ops = None

    @property
    def local_operators(self) -> LocalOperators:
        """
        Return the local stage's operators on the current phyxels (built on first use).

        Linear SVK and the MLS fit-error penalty (eq. 16) with per-pair weights
        ``s_i w_ij = v_i ŵ_ij / h_i²`` (``ŵ_ij = w_ij / W_i``, ``W_i = Σ_j w_ij``) times
        ``stabilisation × μ``: normalised per phyxel and scaled by ``v_i / h_i²``, the penalty is
        an energy like the elastic one (P·mm³), so ``stabilisation`` is in units of μ for any
        particle spacing. ``MotionTracker`` puts the same penalty on the same operators with
        uniform ``s_i`` (``w_ij`` alone, its multiplier set against the median elastic
        diagonal); the two weightings differ where ``W_i`` and ``h_i`` do (enlarged supports at
        the wall's edges), and each caller's weight was validated with its own: the phantom bench
        (this one, to the last digit since session 13) and the 40 randomized LV studies (the
        tracker's ``hourglass_weight``). The rigid-mode regulariser is one rule for both,
        :func:`~mlv_ros.core.meshless.local.rigid_mode_eps`.
        """
        if self._local_ops is None:
            ph = self.phyxels
            wsum = np.bincount(ph.pair_i, weights=ph.wij, minlength=ph.num_particles)
            s = ph.volume / np.where(wsum > 0, wsum, 1.0) / ph.h**2
            ops = LocalOperators(self.operator, ph.volume, self.lam, self.mu, s)
            # Stiffness scale: the elastic diagonal plus the penalty's direct (u_j − u_i) part.
            self._kdiag = (
                ops.elastic_diagonal()
                + (self.stabilisation * self.mu * ops.laplacian.diagonal())[:, None]
            )
            self._local_ops = ops
        return self._local_ops

    @property
    def num_particles(self) -> int:
        return int(self.rest_points.shape[0])

    def refresh_support(self, tol: float = 0.25) -> bool:
        """
        Re-estimate ``h_i = 3 r̄_i`` on the current local configuration and rebuild the phyxels.

        Paper: every five iterations. The phyxels are rebuilt only if any ``h_i`` changed by more
        than ``tol`` (relative). Strain stays Lagrangian: the MLS gradient is always taken on rest
        positions.

        Returns
        -------
        bool
            Whether the phyxels were rebuilt.

        """
        cur = self.rest_points + self.delta
        knn = self.phyxels.knn
        rbar = np.linalg.norm(cur[knn] - cur[:, None, :], axis=2).mean(axis=1)
        h_new = self._support_factor * rbar
        h_old = self._support_factor * self.phyxels.rbar
        if np.max(np.abs(h_new / h_old - 1.0)) <= tol:
            return False
        self._build_phyxels(self.phyxels.h * (h_new / h_old))  # keeps regrouped enlargements
        return True

    # ---------------------------------------------------------------- state
    def reset(self) -> None:
        """Back to the rest configuration (global parameters = rest, no local deformation)."""
        self.params = self.rest_params.copy()
        self.delta[:] = 0.0

    @property
    def local_deformation(self) -> np.ndarray:
        """``d`` in the model-centred frame, shape (N, 3), mm."""
        return self.d_rest + self.delta @ self.rest_params.matrix

    def positions(self) -> np.ndarray:
        """Return the current world positions ``x = c + R (s + d)``, shape (N, 3), mm."""
        p = global_shape(self.coords, self.params.a, self.params.tau) + self.local_deformation
        return self.params.translation + p @ self.params.matrix.T

    def displacement(self) -> np.ndarray:
        """``x − x_rest``, shape (N, 3), mm."""
        return self.positions() - self.rest_points

    def displacement_gradient(self) -> np.ndarray:
        """
        MLS displacement gradient relative to the rest (ED) configuration.

        Returns
        -------
        ndarray, shape (N, 3, 3)
            ``H[i, a, b] = ∂u_a/∂X_b`` in world axes; ``J = I + H`` (eq. 18).

        """
        return self.operator.gradient(self.displacement())

    def green_lagrange_strain(self) -> np.ndarray:
        """
        Return the Lagrangian strain ``E = ½(JᵀJ − I)`` relative to rest, shape (N, 3, 3).

        ½ convention, world axes. Project onto a local cardiac frame ``(e_r, e_c, e_l)`` as ``eᵀ E
        e``.
        """
        return elastic.green_lagrange(self.displacement_gradient())

    def state(self, **kw) -> ModelState:
        """Return the current global parameters as a :class:`~mlv_ros.core.types.ModelState`."""
        return self.params.state(self.num_particles, **kw)

    def attach(self, control, neighbours: tuple | None = None) -> ControlPoints:
        """
        Attach control points (particle indices or rest positions).

        See :func:`attach_control_points`. Reuse the result across phases to skip the kernel work.
        ``neighbours``: :meth:`nearest` of the positions, when the caller has it already.
        """
        if self._support_radii is None:
            self._support_radii = particle_support_radii(
                self.rest_points, self._tree, self._k, self._support_factor
            )
        return attach_control_points(
            self.rest_points,
            control,
            self._tree,
            self._k,
            self._support_factor,
            self._support_radii,
            neighbours,
        )

    def nearest(self, points) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the distances (mm) and indices of each point's nearest rest particles.

        Parameters
        ----------
        points : ndarray, shape (M, 3)
            Positions at rest, mm.

        Returns
        -------
        dist, idx : ndarray, shape (M, k)
            The ``k`` (the model's support neighbours) nearest, nearest first: what
            :meth:`attach` queries, so ``attach(points[s], (dist[s], idx[s]))`` skips the query.

        """
        dist, idx = self._tree.query(points, k=min(self._k, self.num_particles))
        m = len(points)
        return dist.reshape(m, -1), idx.reshape(m, -1)

    # ---------------------------------------------------------------- fitting
    def _local_system(self, data):
        """
        Build the local system: linear SVK + zero-energy-mode penalty + data springs + ε.

        ``data`` is ``(κ, Φ, QᵀPQ)``; ``ε`` is :func:`~mlv_ros.core.meshless.local.rigid_mode_eps`
        of its ``κ`` (½ ε |δ|² makes the split between the global parameters and δ unique: K is
        blind to rigid δ, which c and R already express).
        """
        return self.local_operators.system(
            fit_error=self.stabilisation * self.mu, data=data, eps=rigid_mode_eps(data[0])
        )

    def _local_metric(self, proj, phi, kappa):
        """
        Return ``Q = R R₀ᵀ`` (∂x/∂δ), per-control ``QᵀP_kQ`` and the local stage's Jacobi diagonal.

        The diagonal is ``κ diag(ΦᵀQᵀPQΦ) + diag(K) + ε``, shape (N, 3).
        """
        q = self.params.matrix @ self.rest_params.matrix.T
        pq = np.einsum('ba,mbc,cd->mad', q, proj, q)
        diag_data = (phi.multiply(phi)).T @ np.einsum('maa->ma', pq)
        prec = kappa * diag_data + self._kdiag + rigid_mode_eps(kappa)
        return q, pq, prec

    def _lm_step(self, dmat, fq, res, mu_lm, residual_fn, prior=None):
        """
        One Levenberg–Marquardt step ``Δ = (D + μ)⁻¹ f_q`` in Jacobi-scaled coordinates.

        Directions the data cannot see (the a0 ↔ a1..a3 gauge; parameters left unconstrained by
        too few or in-plane-only control points) are dropped instead of inverted. μ shrinks
        after a step that lowers the residual and grows (up to 12 tries) otherwise. ``prior``
        ``(G, s)`` adds ``(s + Δ)ᵀ G (s + Δ)`` to the cost (``s``: the steps taken so far).

        Returns ``(step, μ, accepted)``: ``accepted`` is ``(parameters, residual)`` after the step
        when one lowered the cost, else None (the step is then zero).
        """

        def prior_cost(step):
            return (
                0.0 if prior is None else float((prior[1] + step) @ prior[0] @ (prior[1] + step))
            )

        if prior is not None:
            dmat, fq = dmat + prior[0], fq - prior[0] @ prior[1]
        cost = float(np.einsum('ma,ma->', res, res)) + prior_cost(np.zeros_like(fq))
        scale = np.sqrt(np.diag(dmat))
        scale = np.where(scale > 1e-12 * max(scale.max(), 1e-300), scale, np.inf)
        evals, evecs = np.linalg.eigh(dmat / np.outer(scale, scale))
        keep = evals > 1e-10 * max(evals.max(), 1e-300)
        fn = evecs.T @ (fq / scale)
        for _ in range(12):
            step = (evecs[:, keep] @ (fn[keep] / (evals[keep] + mu_lm))) / scale
            params = self.params.stepped(step)
            res_t = residual_fn(params)
            if float(np.einsum('ma,ma->', res_t, res_t)) + prior_cost(step) <= cost:
                return step, max(mu_lm / 3.0, 1e-9), (params, res_t)
            mu_lm *= 4.0
        return np.zeros_like(fq), mu_lm, None

    def fit(
        self,
        control,
        targets,
        plane_normals=None,
        *,
        max_iterations: int = 200,
        tol: float = 5e-4,
        residual_tol: float = 0.0,
        warm_start: bool = True,
        local: bool = True,
        data_weight: float = 100.0,
        global_update: str = 'gauss-newton',
        local_update: str = 'solve',
        dt: float = 1.0,
        local_start: float = 1e-3,
        cg_maxiter: int = 100,
        cg_rtol: float = 1e-3,
        refresh_every: int = 5,
        global_prior: float = 0.0,
        weights=None,
        callback: Callable[[int, 'MeshlessModel'], None] | None = None,
    ) -> FitResult:
        """
        Fit the model to control-point targets (one cardiac phase).

        Parameters
        ----------
        control : ControlPoints or array_like
            From :meth:`attach`, or integer particle indices (M,), or rest positions (M, 3), mm.
        targets : array_like, shape (M, 3)
            Target world positions of the control points, mm.
        plane_normals : array_like, shape (M, 3), (3,) or (M, 2, 3), optional
            If given, only the in-plane part ``(I − ν νᵀ)(t − x)`` of each residual acts (a 2D
            image measures in-plane motion only); given as (ν, n) pairs, a point with a tag-line
            normal n (not NaN) acts along n only, ``n nᵀ (t − x)`` (:func:`plane_projectors`).
        max_iterations : int
            Upper bound on iterations (global step + local step).
        tol : float
            Convergence: RMS change of all particle positions in one iteration, mm.
        residual_tol : float
            Also stop when the control residual RMS falls below this, mm (0 = off).
        warm_start : bool
            Start from the current state (previous phase) instead of the rest state.
        local : bool
            Enable the local stage (off: global parameters only, ``d = d_rest``).
        data_weight : float
            Spring constant of the external forces relative to the median diagonal of the
            stiffness: larger follows the data more closely, smaller smooths more.
        global_update : {"gauss-newton", "explicit"}
            Damping metric of eq. 15: ``D = LᵀPL`` (+ LM) or the paper's constant diagonal
            (``dt`` step).
        local_update : {"solve", "explicit"}
            Equilibrium solve (PCG, linearised stiffness) or paper-literal explicit step.
        dt : float
            Step of the explicit updates.
        local_start : float
            The local stage starts once a global step moves control points < this, mm RMS.
        cg_maxiter, cg_rtol :
            Limits of the Jacobi-preconditioned CG per local step (inexact solves; δ accumulates
            over iterations).
        refresh_every : int
            Re-estimate the kernel support every this many iterations (0 = never).
        global_prior : float
            Gauss–Newton only: weight of a prior holding the global parameters where the fit
            started (the previous phase when warm-started): the mean squared particle motion
            their change causes, counted like this many control points' squared residuals
            (0 = off). Directions many control points constrain barely feel it; directions few
            or none see (axial scale from SA-only points, a rotation from points on one side)
            stay put instead of wandering to whatever fits the in-plane residuals a hair better.
        weights : array_like, shape (M,), optional
            Relative weight of each control point's residual (e.g. its measurement's inverse
            variance); scaled to mean 1, so ``data_weight`` keeps its meaning. Default: all 1.
            The reported residual is then the weighted RMS.
        callback : callable, optional
            ``callback(iteration, model)`` after every iteration.

        Returns
        -------
        FitResult

        Raises
        ------
        ValueError
            No control points, target/normal shape mismatch, NaN/inf targets or normals, unknown
            update scheme, negative or non-finite ``global_prior``, weights of the wrong shape,
            negative, non-finite or all zero.

        """
        t0 = time.perf_counter()
        data = _FitData.build(self, control, targets, plane_normals, weights)
        _check_fit_options(global_update, local_update, global_prior)
        if not warm_start:
            self.reset()
        data.restrict(self)
        kappa = None
        if local and self.local_operators is not None:  # built on first use, with its diagonal
            kappa = data_weight * float(np.median(self._kdiag))
        stage = _GlobalStage(
            global_update, dt, self._global_prior_matrix(global_prior, global_update, data)
        )
        history = []
        converged = False
        local_active = not local
        it = 0
        d_s = self.local_deformation[data.support]
        res = data.residual(self.params, d_s)
        for it in range(1, max_iterations + 1):
            t_it = time.perf_counter()
            x_prev = self.positions() if (local and local_active) else None
            g_step = stage.step(self, data, d_s, res)
            res = data.residual(self.params, d_s) if stage.residual is None else stage.residual
            cg_its, ran_local, l_step = 0, False, 0.0
            if local and not local_active and g_step < local_start:
                local_active = True
            elif local and local_active:
                ran_local = True
                cg_its = self._local_step(
                    data, res, kappa, local_update, dt, cg_rtol, cg_maxiter
                )
                # Step measure of a local iteration: RMS change of ALL particle positions (δ
                # alone can trade rigid modes with c and R without moving anything).
                l_step = float(np.sqrt(np.mean(np.sum((self.positions() - x_prev) ** 2, axis=1))))
                d_s = self.local_deformation[data.support]
                res = data.residual(self.params, d_s)
                if refresh_every and it % refresh_every == 0:
                    self.refresh_support()
            rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
            history.append(
                {
                    'iteration': it,
                    'residual': rms,
                    'global_step': g_step,
                    'local_step': l_step,
                    'local': ran_local,
                    'cg_iterations': cg_its,
                    'seconds': time.perf_counter() - t_it,
                }
            )
            if callback is not None:
                callback(it, self)
            if rms < residual_tol or (ran_local and l_step < tol) or (not local and g_step < tol):
                converged = True
                break
        rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
        state = self.state(
            iterations=it, residual=rms, converged=converged, num_control_points=data.m
        )
        return FitResult(
            self.positions(), state, it, rms, converged, history, time.perf_counter() - t0
        )

    def _global_prior_matrix(self, global_prior, global_update, data=None):
        """
        Return the Gauss–Newton prior ``(G, s)`` holding the global parameters, or None.

        ``G`` is ``global_prior`` times the mean ``L_nᵀ L_n`` over all particles (the mean
        squared particle motion a parameter change causes); ``s`` the steps taken so far.
        ``data`` (the fit's :class:`_FitData`) keeps the shape terms taken here for its support.
        """
        if not (global_prior > 0.0 and global_update == 'gauss-newton'):
            return None
        terms = shape_terms(self.coords, self.params)
        if data is not None:
            data.seed(self.params, terms)
        gram = tangent_gram(self.params, self.coords, self.local_deformation, terms)  # Σ L_nᵀL_n
        gmat = float(global_prior) * gram / self.num_particles
        return gmat, np.zeros(gmat.shape[0])

    def _local_step(self, data, res, kappa, scheme, dt, cg_rtol, cg_maxiter) -> int:
        """
        Take one local-stage step (eq. 6, 22–23) with the global parameters held.

        ``scheme`` 'solve' reaches the equilibrium of ``D ḋ = f_ext + f_int`` in one step,
        solving ``(κ ΦᵀQᵀPQΦ + K + ε) Δδ = f_ext − K δ − ε δ`` by PCG; 'explicit' is the
        paper's step ``dt (f_ext + f_int) / D``. Returns the CG iterations taken.
        """
        phi = data.ctrl.weights
        q, pq, prec = self._local_metric(data.proj_local, phi, kappa)
        force = kappa * (
            data.phi_t @ ((res * np.sqrt(data.w)[:, None]) @ q)
        )  # f_ext spread by the kernel
        cg_its = 0
        if scheme == 'explicit':
            fint = elastic.internal_forces(
                self.operator, self.delta, self.phyxels.volume, self.lam, self.mu
            )
            if self.stabilisation:
                fint = fint - self.stabilisation * self.mu * self.local_operators.fit_error_apply(
                    self.delta
                )
            dx = dt * (force + fint - rigid_mode_eps(kappa) * self.delta) / prec
        else:
            system = self._local_system((kappa, phi, pq))
            dx, cg_its = system.solve(
                force - system.internal(self.delta),
                rtol=cg_rtol,
                atol=1e-9 * kappa * np.sqrt(data.m),
                maxiter=cg_maxiter,
            )
        if np.all(np.isfinite(dx)):
            self.delta += dx
        return cg_its
