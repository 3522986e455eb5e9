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
Thin-plate splines and TPS-RPM point matching (deterministic annealing + softassign).

References
----------
Chui, H., Rangarajan, A. "A new point matching algorithm for non-rigid registration."
Computer Vision and Image Understanding 89(2–3):114–141, 2003.
Bookstein, F. L. "Principal warps: thin-plate splines and the decomposition of deformations."
IEEE TPAMI 11(6):567–585, 1989.

"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.distance import cdist


def _spans_plane(pts: np.ndarray) -> bool:
    """
    Return whether points (K, 2) do not lie on one line: their centred rank is 2.

    ``np.linalg.matrix_rank``'s own test (singular values above the largest times
    ``max(K, 2)·eps``) without its generic wrapper, which cost more than the SVD of so small a
    matrix.
    """
    centred = pts - pts.mean(0)
    sv = np.linalg.svd(centred, compute_uv=False)
    return bool(np.count_nonzero(sv > sv.max() * max(centred.shape) * np.finfo(sv.dtype).eps) == 2)


def _tps_kernel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """2-D TPS radial basis ``U(r) = r² log r`` between rows of ``a`` (N, 2) and ``b`` (M, 2)."""
    r2 = cdist(a, b, 'sqeuclidean')
    # U(0) = 0: log(1) at coincident points (the same values as r² log r with its 0·(−∞) set to
    # 0, at a fraction of np.nan_to_num's cost); non-finite input gives 0 as before.
    u = 0.5 * r2 * np.log(np.where(r2 > 0, r2, 1.0))
    if not np.isfinite(u).all():
        u[~np.isfinite(u)] = 0.0
    return u


@dataclass
class ThinPlateSpline:
    """
    2-D thin-plate spline ``f(x) = A x + t + Σ_a c_a U(|x − p_a|)``.

    Attributes
    ----------
    centres : ndarray, shape (K, 2)
        Control points ``p_a``.
    coef : ndarray, shape (K, 2)
        Non-affine coefficients ``c_a`` (columns sum-free against the affine part).
    affine : ndarray, shape (3, 2)
        ``[1, x, y] @ affine`` is the affine part.

    """

    centres: np.ndarray
    coef: np.ndarray
    affine: np.ndarray

    @classmethod
    def identity(cls, centres=None) -> 'ThinPlateSpline':
        c = np.zeros((0, 2)) if centres is None else np.asarray(centres, float)
        return cls(c, np.zeros_like(c), np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))

    @classmethod
    def fit(
        cls,
        src: np.ndarray,
        dst: np.ndarray,
        lam: float = 0.0,
        weights: np.ndarray | None = None,
        lam_affine: float = 0.0,
        kernel: np.ndarray | None = None,
        basis=None,
    ) -> 'ThinPlateSpline':
        """
        Regularised, weighted TPS with ``f(src) ≈ dst``.

        Minimises ``Σ_a w_a |dst_a − f(src_a)|² + lam·cᵀKc + lam_affine·|A − I|²_F`` (``A`` the
        2×2 linear part; translation is free) subject to ``Pᵀc = 0``, ``P = [1, src]``. The
        constraint is eliminated with ``c = Q₂γ`` where ``Q₂`` spans the null space of ``Pᵀ``
        (Chui & Rangarajan 2003, §4), leaving symmetric normal equations in ``(γ, d)``.

        Parameters
        ----------
        src, dst : ndarray, shape (K, 2)
            Source points and their targets, same units.
        lam : float
            Bending-energy weight, in the squared units of the coordinates (0 = interpolating).
        weights : ndarray, shape (K,), optional
            Per-point weights (> 0); small weights let a point deviate.
        lam_affine : float
            Weight pulling the linear part toward the identity (keeps early, very soft
            correspondences from collapsing the point set).
        kernel : ndarray, shape (K, K), optional
            Precomputed ``U(|src_a − src_b|)``.
        basis : tuple, optional
            Precomputed :meth:`basis` of ``src`` (reused across RPM iterations).

        Returns
        -------
        ThinPlateSpline
            Translation only with < 3 points; affine only when the points are collinear or < 4.

        """
        src = np.asarray(src, float)
        dst = np.asarray(dst, float)
        k = len(src)
        if k == 0:
            return cls.identity()
        w = np.ones(k) if weights is None else np.maximum(np.asarray(weights, float), 1e-9)
        p = np.hstack([np.ones((k, 1)), src])
        d_id = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
        s_aff = np.diag([0.0, 1.0, 1.0]) * lam_affine
        if k < 3:
            t = np.average(dst - src, axis=0, weights=w)
            return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.array([t, [1.0, 0.0], [0.0, 1.0]]))
        if k < 4 or not _spans_plane(src):
            a = p.T @ (w[:, None] * p) + s_aff
            b = p.T @ (w[:, None] * dst) + s_aff @ d_id
            return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.linalg.lstsq(a, b, rcond=None)[0])
        if basis is None:
            kmat = _tps_kernel(src, src) if kernel is None else kernel
            basis = cls.basis(src, kmat)
        return cls._fit_spread(src, dst, lam, w, lam_affine, basis)

    @classmethod
    def _fit_spread(cls, src, dst, lam, w, lam_affine, basis) -> 'ThinPlateSpline':
        """
        Solve :meth:`fit`'s normal equations for ≥ 4 source points that are not collinear.

        Parameters
        ----------
        src, dst : ndarray of float64, shape (K, 2)
            Source points and their targets, same units.
        lam : float
            Bending-energy weight (:meth:`fit`).
        w : ndarray of float64, shape (K,)
            Per-point weights, > 0.
        lam_affine : float
            Pull of the linear part toward the identity (:meth:`fit`).
        basis : tuple
            :meth:`basis` of ``src``.

        Returns
        -------
        ThinPlateSpline

        """
        q2, kq, q2kq = basis
        k = len(src)
        p = np.empty((k, 3))
        p[:, 0] = 1.0
        p[:, 1:] = src
        wkq = w[:, None] * kq
        wp = w[:, None] * p
        # The (K − 3 + 3)² system [[a11, a12], [a12ᵀ, a22]], filled in place; the pull of the
        # linear part toward the identity, diag(0, 1, 1)·lam_affine on both sides, added to
        # the entries it changes.
        lhs = np.empty((k, k))
        lhs[:k - 3, :k - 3] = kq.T @ wkq + lam * q2kq
        lhs[:k - 3, k - 3:] = a12 = wkq.T @ p
        lhs[k - 3:, :k - 3] = a12.T
        lhs[k - 3:, k - 3:] = p.T @ wp
        rhs = np.empty((k, 2))
        rhs[:k - 3] = wkq.T @ dst
        rhs[k - 3:] = p.T @ (w[:, None] * dst)
        if lam_affine:
            lhs[k - 2, k - 2] += lam_affine
            lhs[k - 1, k - 1] += lam_affine
            rhs[k - 2, 0] += lam_affine
            rhs[k - 1, 1] += lam_affine
        try:
            sol = np.linalg.solve(lhs, rhs)
        except np.linalg.LinAlgError:
            sol = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
        return cls(src.copy(), q2 @ sol[:k - 3], sol[k - 3:])

    @staticmethod
    def basis(src: np.ndarray, kernel: np.ndarray | None = None):
        """
        Return the constraint-free basis reused by :meth:`fit` for a fixed ``src``.

        ``src`` has shape (K, 2), K ≥ 4; the basis is ``(Q₂, K Q₂, Q₂ᵀ K Q₂)`` with ``Q₂`` spanning
        the null space of ``[1, src]ᵀ``.
        """
        src = np.asarray(src, float)
        kmat = _tps_kernel(src, src) if kernel is None else kernel
        q, _ = np.linalg.qr(np.hstack([np.ones((len(src), 1)), src]), mode='complete')
        q2 = q[:, 3:]
        kq = kmat @ q2
        return q2, kq, q2.T @ kq

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Warp points ``x``, shape (N, 2) → (N, 2)."""
        x = np.asarray(x, float).reshape(-1, 2)
        out = np.hstack([np.ones((len(x), 1)), x]) @ self.affine
        if len(self.centres):
            out = out + _tps_kernel(x, self.centres) @ self.coef
        return out


@dataclass
class RPMResult:
    """
    Outcome of :func:`tps_rpm`.

    Attributes
    ----------
    match : ndarray of int, shape (K,)
        Index into ``target`` of each source point's correspondence, −1 for outliers.
    transform : ThinPlateSpline
        Final warp, source → target coordinates.
    warped : ndarray, shape (K, 2)
        ``transform(source)``.
    soft : ndarray, shape (K + 1, N + 1)
        Final softassign matrix, last row/column = outliers.
    iterations : int
        Temperature steps taken.

    """

    match: np.ndarray
    transform: ThinPlateSpline
    warped: np.ndarray
    soft: np.ndarray
    iterations: int


def _sinkhorn(m: np.ndarray, iterations: int) -> np.ndarray:
    """
    Alternate row/column normalisation of the inlier block of ``m`` (shape (K+1, N+1)).

    The outlier row and column absorb mass and are not normalised themselves.
    """
    rows, cols = m[:-1], m[:, :-1]
    for _ in range(iterations):
        s = rows.sum(axis=1, keepdims=True)
        rows /= np.maximum(s, 1e-300, out=s)
        s = cols.sum(axis=0, keepdims=True)
        cols /= np.maximum(s, 1e-300, out=s)
    return m


def tps_rpm(
    source,
    target,
    *,
    init: ThinPlateSpline | None = None,
    t_init: float | None = None,
    t_final: float | None = None,
    anneal: float = 0.93,
    lam_init: float = 30.0,
    lam_final: float = 1e-3,
    lam_affine_init: float = 0.01,
    iterations_per_t: int = 3,
    sinkhorn_iterations: int = 30,
    outlier_distance: float | None = None,
    gate: float | None = None,
) -> RPMResult:
    """
    Non-rigid point matching by TPS-RPM (Chui & Rangarajan 2003).

    Alternates softassign — ``m_ai ∝ exp(−|x_i − f(v_a)|² / 2T)`` with an outlier row and column,
    Sinkhorn-normalised — and a weighted TPS fit of ``f`` to the soft targets
    ``y_a = Σ_i m_ai x_i / Σ_i m_ai``, while the temperature ``T`` falls geometrically from
    ``t_init`` to ``t_final`` and the TPS smoothing falls with it (``λ ∝ T``). Coordinates are
    normalised internally (centred, unit RMS radius), so ``lam_*`` are dimensionless.

    Parameters
    ----------
    source : ndarray, shape (K, 2)
        Points to warp (e.g. tracked positions at the previous phase).
    target : ndarray, shape (N, 2)
        Points to match (e.g. detections at the current phase).
    init : ThinPlateSpline, optional
        Initial warp in the original coordinates (the tracker's seed); default identity.
    t_init, t_final : float, optional
        Temperatures, squared units of the input coordinates. Defaults: the largest squared
        distance between warped source and target points, and the mean squared
        nearest-neighbour distance among targets divided by 16.
    anneal : float
        Temperature factor per step (0 < anneal < 1).
    lam_init, lam_final : float
        Bending weight per source point at ``t_init`` (it falls ∝ T) and its floor.
    lam_affine_init : float
        Weight per source point of the pull of the linear part toward the identity at
        ``t_init`` (falls ∝ T).
    iterations_per_t : int
        Softassign/TPS alternations per temperature.
    sinkhorn_iterations : int
        Row/column normalisation sweeps of each softassign matrix.
    outlier_distance : float, optional
        Distance (input units) at which a point is as likely an outlier as a match at
        ``t_final``; default 3·sqrt(t_final).
    gate : float, optional
        Final hard matches farther than this (input units) are rejected; default
        ``outlier_distance``.

    Returns
    -------
    RPMResult
        Hard matches are mutual maxima of the final softassign matrix that beat the outlier
        entry and pass the gate.

    """
    v = np.asarray(source, float).reshape(-1, 2)
    x = np.asarray(target, float).reshape(-1, 2)
    k, n = len(v), len(x)
    f0 = init if init is not None else ThinPlateSpline.identity()
    if k == 0 or n == 0:
        return RPMResult(
            np.full(k, -1), f0, f0(v) if k else np.zeros((0, 2)), np.zeros((k + 1, n + 1)), 0
        )
    # Normalise: centre on the targets, scale to unit RMS radius.
    mu = x.mean(0)
    s = float(np.sqrt(np.mean(np.sum((x - mu) ** 2, 1)))) or 1.0
    xn = (x - mu) / s
    vn = (v - mu) / s
    yn = (f0(v) - mu) / s
    t_init, t_final = _temperature_range(xn, yn, s, t_init, t_final)
    if outlier_distance is None:
        outlier_distance = 3.0 * np.sqrt(t_final)
    if gate is None:
        gate = outlier_distance
    tn, tfn = t_init / s**2, t_final / s**2
    od2 = (outlier_distance / s) ** 2
    kv = _tps_kernel(vn, vn)
    basis = ThinPlateSpline.basis(vn, kv) if k >= 4 else None
    # ≥ 4 points not on one line (fit's own test, taken once for the fixed source points): each
    # step solves the spline's normal equations directly.
    spread = basis is not None and _spans_plane(vn)
    m = np.zeros((k + 1, n + 1))
    steps = 0
    t = tn
    lams = (lam_init, lam_final, lam_affine_init, tn)
    while True:
        for _ in range(iterations_per_t):
            yn = _rpm_step(m, (vn, kv, basis, spread), yn, xn, (t, od2), lams, sinkhorn_iterations)
        steps += 1
        if t <= tfn * (1 + 1e-9):
            break
        t = max(t * anneal, tfn)
    # Back to input units: U(r) = r² log r is not scale-invariant, so re-fit the interpolating
    # spline through the final warped points instead of rescaling coefficients.
    warped = yn * s + mu
    transform = ThinPlateSpline.fit(v, warped, lam=0.0)
    return RPMResult(_hard_matches(m, warped, x, gate), transform, warped, m.copy(), steps)


def _temperature_range(xn, yn, s, t_init, t_final):
    """
    Fill in the annealing's first and last temperatures, input units².

    Default start: the largest squared distance between warped sources and targets; default
    end: 1/16 of the targets' mean squared nearest-neighbour distance.
    """
    if t_init is None:
        t_init = float(cdist(yn, xn, 'sqeuclidean').max()) * s * s
    if t_final is None:
        if len(xn) > 1:
            d2 = cdist(xn, xn, 'sqeuclidean')
            np.fill_diagonal(d2, np.inf)
            t_final = float(np.mean(d2.min(1))) * s * s / 16
        else:
            t_final = t_init / 100
    return max(float(t_init), float(t_final)), t_final


def _rpm_step(m, source, yn, xn, temperature, lams, sinkhorn_iterations):
    """
    One softassign (into ``m``, in place) and spline fit at temperature ``t``, normalised units.

    ``source`` is ``(vn, kv, basis, spread)``: the source points, their kernel, the spline basis
    and whether they span the plane; ``lams`` is ``(lam_init, lam_final, lam_affine_init,
    t_init)`` (:func:`tps_rpm`; both weights shrink with t). Returns the warped sources.
    """
    vn, kv, basis, spread = source
    t, od2 = temperature
    k = len(vn)
    d2 = cdist(yn, xn, 'sqeuclidean')
    # Work relative to the outlier level: the outlier entry is exp(−od²/2T)·(T/T) so that
    # at every temperature a point at distance od is as likely a match as an outlier.
    m[:-1, :-1] = np.exp(-(d2 - od2) / (2 * t))
    m[-1, :] = 1.0
    m[:, -1] = 1.0
    np.minimum(m, 1e200, out=m)
    _sinkhorn(m, sinkhorn_iterations)
    w = m[:-1, :-1].sum(1)
    tgt = np.where(
        w[:, None] > 1e-9, (m[:-1, :-1] @ xn) / np.maximum(w, 1e-12)[:, None], yn
    )
    lam_init, lam_final, lam_affine_init, tn = lams
    lam = k * max(lam_init * t / tn, lam_final)
    lam_aff = k * lam_affine_init * t / tn
    f = (
        ThinPlateSpline._fit_spread(vn, tgt, lam, np.maximum(w, 1e-3), lam_aff, basis)
        if spread
        else ThinPlateSpline.fit(
            vn,
            tgt,
            lam=lam,
            weights=np.maximum(w, 1e-3),
            lam_affine=lam_aff,
            kernel=kv,
            basis=basis,
        )
    )
    return f.affine[0] + vn @ f.affine[1:] + (kv @ f.coef if len(f.centres) else 0.0)


def _hard_matches(m, warped, x, gate):
    """Index into ``x`` of each source's mutual-maximum match beating its outlier entry, or −1."""
    inl = m[:-1, :-1]
    best_i = inl.argmax(1)
    best_a = inl.argmax(0)
    ar = np.arange(len(warped))
    mutual = best_a[best_i] == ar
    beats = inl[ar, best_i] > m[ar, -1]
    dist = np.linalg.norm(warped - x[best_i], axis=1)
    ok = mutual & beats & (dist <= gate)
    return np.where(ok, best_i, -1)
