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
Particles and phyxels: poly6 kernel, support radii, neighbourhoods, masses and volumes.

Paper §2.1 (eq. 4) and Müller et al. 2004. A *phyxel* is a particle ``i`` together with the
particles ``j`` within its support radius ``h_i``; ``h_i = 3 r̄_i`` where ``r̄_i`` is the mean
distance to its 10 nearest neighbours. Neighbourhoods come from :class:`scipy.spatial.cKDTree`
(the paper's hash table) and are stored as flat pair lists (CSR order, ``i`` ascending), so every
per-phyxel sum is a vectorised ``np.add.reduceat``/``bincount`` instead of a Python loop.

Units: positions in mm; the kernel has units mm⁻³ (it integrates to 1 over its ball).
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import chain

import numpy as np
from scipy.spatial import cKDTree

#: Mean-distance neighbour count and support factor of the paper (h = 3 r̄ over 10 neighbours).
NUM_NEIGHBOURS = 10
SUPPORT_FACTOR = 3.0
#: A phyxel whose moment matrix has condition number above this is "ill-shaped" (§2.1).
COND_MAX = 1.0e4
#: Duplicate particles: closer than this fraction of the median 1-NN distance.
DUPLICATE_FRACTION = 1.0e-6


def poly6(r: np.ndarray, h: np.ndarray | float, norm: np.ndarray | None = None) -> np.ndarray:
    """
    Normalised poly6 kernel (paper eq. 4 divided by its integral).

    ``W(r, h) = 315 / (64 π h⁹) · (h² − r²)³`` for ``r < h``, else 0.

    Parameters
    ----------
    r : array_like
        Distances, mm (broadcast against ``h``).
    h : array_like or float
        Support radii, mm, > 0.
    norm : array_like, optional
        :func:`poly6_norm` of ``h``, when the caller has it (e.g. taken once per support and
        indexed per pair: the same numbers without a power per pair).

    Returns
    -------
    ndarray
        Kernel values, mm⁻³; ``∫ W(|x|, h) dx = 1`` over R³.

    """
    r = np.asarray(r, dtype=np.float64)
    h = np.asarray(h, dtype=np.float64)
    q = np.clip(h * h - r * r, 0.0, None)
    return (poly6_norm(h) if norm is None else norm) * q**3


def poly6_norm(h: np.ndarray | float) -> np.ndarray:
    """
    Return the poly6 kernel's normalisation ``315 / (64 π h⁹)``, mm⁻⁹.

    Parameters
    ----------
    h : array_like or float
        Support radii, mm, > 0.

    """
    return 315.0 / (64.0 * np.pi * np.asarray(h, dtype=np.float64) ** 9)


def validate_points(points, name: str = 'points', min_count: int = 1) -> np.ndarray:
    """Return ``points`` as a float64 (N, 3) array or raise a ValueError saying what is wrong."""
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f'{name} must have shape (N, 3), got {p.shape}')
    if p.shape[0] < min_count:
        raise ValueError(f'{name} needs at least {min_count} rows, got {p.shape[0]}')
    bad = ~np.all(np.isfinite(p), axis=1)
    if bad.any():
        idx = np.flatnonzero(bad)
        raise ValueError(
            f'{name} has {idx.size} non-finite (NaN/inf) rows, first at index {idx[0]}'
        )
    return p


def mean_neighbour_distance(
    points: np.ndarray, k: int = NUM_NEIGHBOURS, tree: cKDTree | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """
    Mean distance r̄_i to the ``k`` nearest other particles.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Particle positions, mm.
    k : int
        Neighbour count (paper: 10); clipped to N − 1.
    tree : cKDTree, optional
        A tree already built on ``points``.

    Returns
    -------
    rbar : ndarray, shape (N,)
        Mean neighbour distance, mm.
    knn : ndarray of int, shape (N, k)
        Indices of those neighbours (for cheap re-evaluation of r̄ after motion).

    """
    n = points.shape[0]
    k = min(k, n - 1)
    tree = cKDTree(points) if tree is None else tree
    dist, idx = tree.query(points, k=k + 1, workers=-1)
    return dist[:, 1:].mean(axis=1), idx[:, 1:]


def check_duplicates(
    points: np.ndarray, tree: cKDTree | None = None, tol: float | None = None
) -> None:
    """
    Raise ValueError if two particles coincide (closer than ``tol`` mm).

    ``tol`` defaults to ``DUPLICATE_FRACTION`` × the median nearest-neighbour distance (or 1e-9 mm
    if that is 0). Coincident particles make every MLS moment matrix that contains both of them
    carry a zero-length edge and the two displacements become indistinguishable.
    """
    tree = cKDTree(points) if tree is None else tree
    dist, idx = tree.query(points, k=2, workers=-1)
    if tol is None:
        med = float(np.median(dist[:, 1]))
        tol = max(DUPLICATE_FRACTION * med, 1e-9)
    dup = np.flatnonzero(dist[:, 1] <= tol)
    if dup.size:
        i = int(dup[0])
        raise ValueError(
            f'duplicate particles: {dup.size} particles have a neighbour within {tol:.3g} mm '
            f'(e.g. {i} and {int(idx[i, 1])} at {points[i].tolist()}); remove duplicates first'
        )


@dataclass
class Phyxels:
    """
    Neighbourhood structure of a particle cloud (rest configuration).

    Pairs are stored flat in CSR order: phyxel ``i`` owns ``pair_j[indptr[i]:indptr[i+1]]``
    (``j != i``).

    Attributes
    ----------
    points : ndarray, shape (N, 3)
        Particle positions the phyxels were built on, mm.
    rbar : ndarray, shape (N,)
        Mean distance to the 10 nearest neighbours, mm.
    h : ndarray, shape (N,)
        Support radius, mm; ``3 r̄`` unless regrouping enlarged it.
    knn : ndarray of int, shape (N, k)
        The 10 nearest neighbours (used to re-estimate r̄ cheaply).
    indptr : ndarray of int, shape (N + 1,)
    pair_i, pair_j : ndarray of int, shape (P,)
        Phyxel centre and member indices.
    xij : ndarray, shape (P, 3)
        ``x_j − x_i``, mm.
    wij : ndarray, shape (P,)
        ``W(|x_ij|, h_i)``, mm⁻³.
    moment : ndarray, shape (N, 3, 3)
        ``A_i = Σ_j x_ij x_ijᵀ w_ij`` (eq. 17), mm⁻¹.
    moment_inv : ndarray, shape (N, 3, 3)
        ``A_i⁻¹`` — or its truncated pseudo-inverse where A_i stays degenerate (see ``pinv``).
    cond : ndarray, shape (N,)
        Condition number of A_i after regrouping.
    regrouped : ndarray of bool, shape (N,)
        Phyxels whose support was enlarged because A_i was ill-conditioned (§2.1 regrouping).
    pinv : ndarray of bool, shape (N,)
        Phyxels still degenerate after regrouping (e.g. coplanar neighbourhood): the documented
        fallback uses the pseudo-inverse, so their gradient has no component along the missing
        direction(s) instead of being NaN.
    mass, density, volume : ndarray, shape (N,)
        ``m_i = s r̄_i³ ρ₀`` with ``s`` chosen so the mean density equals ρ₀;
        ``ρ_i = Σ_j m_j W(|x_ij|, h_i)`` (self included); ``v_i = m_i / ρ_i`` (mm³).

    """

    points: np.ndarray
    rbar: np.ndarray
    h: np.ndarray
    knn: np.ndarray
    indptr: np.ndarray
    pair_i: np.ndarray
    pair_j: np.ndarray
    xij: np.ndarray
    wij: np.ndarray
    moment: np.ndarray
    moment_inv: np.ndarray
    cond: np.ndarray
    regrouped: np.ndarray
    pinv: np.ndarray
    mass: np.ndarray
    density: np.ndarray
    volume: np.ndarray

    @property
    def num_particles(self) -> int:
        return int(self.points.shape[0])

    @property
    def num_pairs(self) -> int:
        return int(self.pair_i.shape[0])

    def neighbour_counts(self) -> np.ndarray:
        """Members per phyxel (self excluded), shape (N,)."""
        return np.diff(self.indptr)


def _pairs_within(tree: cKDTree, points: np.ndarray, h: np.ndarray, idx: np.ndarray):
    """Flat (i, j) pairs with |x_j − x_i| < h_i for centres ``idx`` (self excluded)."""
    lists = tree.query_ball_point(points[idx], r=h[idx], return_sorted=False, workers=-1)
    counts = np.fromiter(map(len, lists), dtype=np.int64, count=len(lists))
    pj = np.fromiter(chain.from_iterable(lists), dtype=np.int64, count=int(counts.sum()))
    pi = np.repeat(idx, counts)
    keep = pj != pi
    return pi[keep], pj[keep]


def _moments(pi, xij, wij, n):
    m = np.empty((n, 3, 3))
    wx = xij * wij[:, None]
    for a in range(3):
        for b in range(a, 3):
            m[:, a, b] = m[:, b, a] = np.bincount(pi, weights=wx[:, a] * xij[:, b], minlength=n)
    return m


def _safe_inverse(moment: np.ndarray, cond_max: float):
    """Inverse of each 3×3 A_i, truncated-SVD pseudo-inverse where cond > ``cond_max``."""
    u, s, vt = np.linalg.svd(moment)
    smax = s[:, :1]
    with np.errstate(divide='ignore', invalid='ignore'):
        cond = np.where(s[:, 2] > 0, s[:, 0] / s[:, 2], np.inf)
    keep = s > smax / cond_max
    sinv = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
    inv = np.einsum('nij,nj,nkj->nik', vt.transpose(0, 2, 1), sinv, u)
    return inv, cond, ~keep.all(axis=1)


def build_phyxels(
    points,
    k: int = NUM_NEIGHBOURS,
    support_factor: float = SUPPORT_FACTOR,
    cond_max: float = COND_MAX,
    max_regroup: int = 3,
    regroup_factor: float = 1.5,
    rho0: float = 1.0,
    h: np.ndarray | None = None,
) -> Phyxels:
    """
    Group particles into phyxels (paper §2.1).

    Ill-shaped phyxels — condition number of the moment matrix A_i above ``cond_max`` (long,
    flat or too few members) — are *regrouped*: their support radius is enlarged by
    ``regroup_factor`` (up to ``max_regroup`` times) so that more, better-spread neighbours join.
    A phyxel that is still degenerate (all neighbours coplanar/collinear) keeps the largest
    support and uses the truncated pseudo-inverse of A_i (flag ``pinv``) — never NaN.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Particle positions, mm; finite, no duplicates, N ≥ 5.
    k : int
        Neighbours for the mean distance r̄ (paper: 10).
    support_factor : float
        ``h = support_factor · r̄`` (paper: 3).
    cond_max : float
        Ill-shape threshold on cond(A_i).
    max_regroup : int
        Support enlargements tried per ill-shaped phyxel.
    regroup_factor : float
        Enlargement per try.
    rho0 : float
        Rest density used to scale masses (the volumes do not depend on it).
    h : ndarray, shape (N,), optional
        Support radii to use instead of ``support_factor · r̄`` (mm).

    Returns
    -------
    Phyxels

    Raises
    ------
    ValueError
        Non-finite or wrongly shaped points, fewer than 5 particles, duplicate particles.

    """
    pts = validate_points(points, 'particle positions', min_count=5)
    n = pts.shape[0]
    tree = cKDTree(pts)
    check_duplicates(pts, tree)
    rbar, knn = mean_neighbour_distance(pts, k, tree)
    h = support_factor * rbar if h is None else np.asarray(h, dtype=np.float64).copy()
    if h.shape != (n,) or not np.all(np.isfinite(h)) or np.any(h <= 0):
        raise ValueError('support radii h must be a finite positive array of shape (N,)')

    pi, pj = _pairs_within(tree, pts, h, np.arange(n))
    xij = pts[pj] - pts[pi]
    wij = poly6(np.linalg.norm(xij, axis=1), h[pi])
    moment = _moments(pi, xij, wij, n)
    _, cond, _ = _safe_inverse(moment, cond_max)
    regrouped = np.zeros(n, dtype=bool)
    for _ in range(max_regroup):
        bad = np.flatnonzero(~(cond <= cond_max))
        if bad.size == 0:
            break
        regrouped[bad] = True
        h[bad] *= regroup_factor
        keep = ~np.isin(pi, bad)
        bi, bj = _pairs_within(tree, pts, h, bad)
        pi = np.concatenate([pi[keep], bi])
        pj = np.concatenate([pj[keep], bj])
        order = np.lexsort((pj, pi))
        pi, pj = pi[order], pj[order]
        xij = pts[pj] - pts[pi]
        wij = poly6(np.linalg.norm(xij, axis=1), h[pi])
        moment = _moments(pi, xij, wij, n)
        _, cond, _ = _safe_inverse(moment, cond_max)
    moment_inv, cond, pinv = _safe_inverse(moment, cond_max)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(pi, minlength=n))])

    # Müller: m_i = s r̄_i³ ρ₀, s such that the kernel density averages ρ₀.
    m_unit = rbar**3
    w_self = poly6(0.0, h)
    rho_unit = m_unit * w_self + np.bincount(pi, weights=m_unit[pj] * wij, minlength=n)
    s = 1.0 / float(np.mean(rho_unit))
    mass = s * m_unit * rho0
    density = s * rho_unit * rho0
    volume = mass / density
    return Phyxels(
        points=pts,
        rbar=rbar,
        h=h,
        knn=knn,
        indptr=indptr,
        pair_i=pi,
        pair_j=pj,
        xij=xij,
        wij=wij,
        moment=moment,
        moment_inv=moment_inv,
        cond=cond,
        regrouped=regrouped,
        pinv=pinv,
        mass=mass,
        density=density,
        volume=volume,
    )
