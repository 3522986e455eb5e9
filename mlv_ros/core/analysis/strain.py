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
Lagrangian strain in the cardiac frame and AHA 17-segment averages.

Strain is Green–Lagrange ``E = ½(FᵀF − I)`` relative to ED, with ``F = ∂x/∂X`` the
deformation gradient (the paper's eq. 18 Jacobian ``J = I + ∇uᵀ``; its eq. 19 drops the ½,
we keep it, as the method notes ask). Components are taken in the ED cardiac frame of each
particle: ``E_ab = e_a · E e_b`` with e_r, e_c, e_l from
:func:`mlv_ros.core.analysis.frame.cardiac_coordinates` (normal strains do not depend on the
basis signs; shears E_rc, E_rl, E_cl follow them). Negative = shortening. A uniform in-plane
scaling by s gives ``E_rr = E_cc = ½(s² − 1)``.

AHA segments (Cerqueira et al., Circulation 2002), numbered 1–17:

* Longitudinal: the apical cap (17) is ``h < apex_cap`` (default 0.1 of the ED apex–base
  length); the rest, [apex_cap, 1], is split in equal thirds: apical (13–16), mid (7–12),
  basal (1–6).
* Circumferential: ``ψ = (θ − aha_origin) mod 360°`` with θ CCW seen from the apex and
  ``aha_origin`` the anterior RV–LV insertion (:class:`LVFrame.aha_origin_deg`), so ψ runs
  anterior insertion → septum → inferior → lateral, the bull's-eye order seen from the apex.
  Basal/mid 60° sectors from ψ = 0: anteroseptal, inferoseptal, inferior, inferolateral,
  anterolateral, anterior (segments 2, 3, 4, 5, 6, 1 and 8, 9, 10, 11, 12, 7). Apical 90°
  sectors centred on the septum (ψ = 60°): septal [15°, 105°) = 14, inferior = 15,
  lateral = 16, anterior [285°, 15°) = 13.
"""

from __future__ import annotations

from mlv_ros.core.analysis.frame import as_points
import numpy as np
from scipy.spatial import cKDTree

AHA_SEGMENT_NAMES = (
    'basal anterior',
    'basal anteroseptal',
    'basal inferoseptal',
    'basal inferior',
    'basal inferolateral',
    'basal anterolateral',
    'mid anterior',
    'mid anteroseptal',
    'mid inferoseptal',
    'mid inferior',
    'mid inferolateral',
    'mid anterolateral',
    'apical anterior',
    'apical septal',
    'apical inferior',
    'apical lateral',
    'apex',
)

STRAIN_COMPONENTS = ('rr', 'cc', 'll', 'rc', 'rl', 'cl')

_COND_MIN = 1e-8  # smallest eigenvalue ratio of the MLS moment matrix accepted as regular


def _as_tensors(F, name: str = 'F') -> np.ndarray:
    F = np.asarray(F, dtype=np.float64)
    if F.ndim != 3 or F.shape[1:] != (3, 3):
        raise ValueError(f'{name} must have shape (N, 3, 3), got {F.shape}')
    return F


def green_lagrange(F) -> np.ndarray:
    """
    Green–Lagrange strain ``E = ½(FᵀF − I)``.

    Parameters
    ----------
    F : array_like, shape (N, 3, 3)
        Deformation gradients ``∂x/∂X`` (patient axes). Rows with NaN give NaN strain.

    Returns
    -------
    ndarray, shape (N, 3, 3)
        Symmetric strain tensors in patient axes (dimensionless).

    """
    F = _as_tensors(F)
    return 0.5 * (np.swapaxes(F, 1, 2) @ F - np.eye(3))


def cardiac_strain(E, e_r, e_c, e_l) -> dict:
    """
    Components of strain tensors in the local cardiac frame.

    Parameters
    ----------
    E : array_like, shape (N, 3, 3)
        Strain tensors in patient axes.
    e_r, e_c, e_l : array_like, shape (N, 3)
        Radial, circumferential, longitudinal unit vectors at ED
        (:class:`~mlv_ros.core.analysis.frame.CardiacCoordinates`).

    Returns
    -------
    dict of ndarray, shape (N,)
        Keys ``rr, cc, ll, rc, rl, cl`` (E_rr, E_cc, E_ll and the tensor shears).

    """
    E = _as_tensors(E, 'E')
    Q = np.stack([np.asarray(e_r, float), np.asarray(e_c, float), np.asarray(e_l, float)], axis=1)
    if Q.shape != E.shape:
        raise ValueError(f'frame vectors must have shape ({E.shape[0]}, 3), got {Q.shape[0::2]}')
    C = Q @ E @ np.swapaxes(Q, 1, 2)
    return {k: C[:, 'rcl'.index(k[0]), 'rcl'.index(k[1])] for k in STRAIN_COMPONENTS}


class MLSNeighbourhood:
    """
    Precomputed MLS neighbourhoods of ED positions (paper eq. 16–17, Müller et al. 2004).

    Each particle i uses its ``k`` nearest ED neighbours j with the paper's kernel
    ``w_ij = (h² − r²)³`` (eq. 4; the constant 1/h⁹ cancels), ``h = 3 r̄_i`` and r̄_i the
    mean distance to those neighbours, and the moment matrix ``A_i = Σ_j w_ij X_ij X_ijᵀ``.

    Attributes
    ----------
    index : ndarray of int, shape (N, k)
    dX : ndarray, shape (N, k, 3)
        ED offsets ``X_j − X_i``, mm.
    weight : ndarray, shape (N, k)
    A_inv : ndarray, shape (N, 3, 3)
        Inverse moment matrices (zeros where not ``valid``).
    valid : ndarray of bool, shape (N,)
        False where the neighbours are (near) coplanar: eigenvalue ratio of A below 1e-8.

    """

    def __init__(self, X: np.ndarray, k: int = 12):
        X = as_points(X, 'X')
        n = X.shape[0]
        k = int(k)
        if k < 3:
            raise ValueError(f'MLS needs k >= 3 neighbours, got {k}')
        if n < k + 1:
            raise ValueError(
                f'MLS with k={k} neighbours needs at least {k + 1} particles, got {n}'
            )
        dist, idx = cKDTree(X).query(X, k=k + 1)
        self.index = idx[:, 1:]
        dist = dist[:, 1:]
        self.dX = X[self.index] - X[:, None, :]
        h = 3.0 * dist.mean(axis=1, keepdims=True)
        self.weight = (h * h - dist * dist) ** 3 / np.maximum(h, 1e-300) ** 6  # /h⁶: dimensionless
        self._wdX_T = np.ascontiguousarray((self.dX * self.weight[:, :, None]).transpose(0, 2, 1))
        A = self._wdX_T @ self.dX  # Σ_j w X_ij X_ijᵀ, (N, 3, 3)
        self._wdX_sum = self._wdX_T.sum(axis=2)
        ev = np.linalg.eigvalsh(A)
        self.valid = ev[:, 0] > _COND_MIN * np.maximum(ev[:, 2], 1e-300)
        self.A_inv = np.zeros_like(A)
        if self.valid.any():
            self.A_inv[self.valid] = np.linalg.inv(A[self.valid])

    def gradient(self, x: np.ndarray) -> np.ndarray:
        """Deformation gradients F at current positions x (N, 3); NaN where not ``valid``."""
        # F = B A⁻¹ with B = Σ_j w x_ij X_ijᵀ. Expanding x_ij = x_j − x_i avoids an (N, k, 3)
        # temporary: Bᵀ = Σ_j w X_ij x_jᵀ − (Σ_j w X_ij) x_iᵀ.
        Bt = (
            self._wdX_T @ np.take(x, self.index, axis=0)
            - self._wdX_sum[:, :, None] * x[:, None, :]
        )
        F = np.swapaxes(Bt, 1, 2) @ self.A_inv
        F[~self.valid] = np.nan
        return F


def mls_neighbourhood(X, k: int = 12) -> MLSNeighbourhood:
    """Build the reusable MLS neighbourhoods of ED positions (see :class:`MLSNeighbourhood`)."""
    return MLSNeighbourhood(X, k)


def deformation_gradient_mls(
    X, x, k: int = 12, neighbourhood: MLSNeighbourhood | None = None
) -> np.ndarray:
    """
    Estimate per-particle deformation gradients from positions by weighted least squares.

    Solves ``min_F Σ_j w_ij |x_ij − F X_ij|²`` (first-order MLS, the paper's eq. 16–17 with
    ``F = I + ∇uᵀ``), so ``F_i = (Σ_j w_ij x_ij X_ijᵀ) A_i⁻¹``. Exact for affine motion.

    Parameters
    ----------
    X, x : array_like, shape (N, 3)
        ED and current positions, mm.
    k : int
        Neighbours per particle (ignored when ``neighbourhood`` is given).
    neighbourhood : MLSNeighbourhood, optional
        Precomputed for ``X`` (reuse it across phases).

    Returns
    -------
    ndarray, shape (N, 3, 3)
        F per particle; NaN rows where the neighbourhood is degenerate (coplanar).

    """
    X = as_points(X, 'X')
    x = as_points(x, 'x')
    if X.shape != x.shape:
        raise ValueError(f'X and x must have the same shape, got {X.shape} and {x.shape}')
    nb = neighbourhood if neighbourhood is not None else MLSNeighbourhood(X, k)
    if nb.index.shape[0] != X.shape[0]:
        raise ValueError('neighbourhood was built for a different number of particles')
    return nb.gradient(x)


def aha_segments(h, theta, aha_origin_deg: float = -120.0, apex_cap: float = 0.1) -> np.ndarray:
    """
    AHA 17-segment number of each particle (convention in the module docstring).

    Parameters
    ----------
    h : array_like, shape (N,)
        ED normalised level, 0 apex … 1 base (values outside are clipped).
    theta : array_like, shape (N,)
        ED circumferential angle, rad, CCW seen from the apex.
    aha_origin_deg : float
        θ of the anterior RV–LV insertion, degrees (``LVFrame.aha_origin_deg``).
    apex_cap : float
        Level below which particles belong to the apex segment 17; in [0, 1).

    Returns
    -------
    ndarray of int, shape (N,)
        Segment numbers 1 … 17.

    """
    h = np.asarray(h, dtype=np.float64)
    theta = np.asarray(theta, dtype=np.float64)
    if h.shape != theta.shape or h.ndim != 1:
        raise ValueError(f'h and theta must be 1-D of equal length, got {h.shape}, {theta.shape}')
    if not 0.0 <= apex_cap < 1.0:
        raise ValueError(f'apex_cap must be in [0, 1), got {apex_cap}')
    if not (np.all(np.isfinite(h)) and np.all(np.isfinite(theta))):
        raise ValueError('h and theta must be finite')
    psi = np.mod(np.degrees(theta) - aha_origin_deg, 360.0)
    third = np.clip(
        np.floor((np.clip(h, 0, 1) - apex_cap) / ((1.0 - apex_cap) / 3.0)), 0, 2
    ).astype(int)
    # 60° sectors from the anterior insertion: anteroseptal, inferoseptal, inferior,
    # inferolateral, anterolateral, anterior -> offsets 1..5, 0 within a ring of six
    six = np.array([1, 2, 3, 4, 5, 0])[np.minimum((psi // 60).astype(int), 5)]
    # 90° apical sectors centred on the septum (ψ = 60°): septal, inferior, lateral, anterior
    four = np.array([1, 2, 3, 0])[np.minimum((np.mod(psi - 15.0, 360.0) // 90).astype(int), 3)]
    seg = np.where(third == 2, 1 + six, np.where(third == 1, 7 + six, 13 + four))
    return np.where(np.clip(h, 0, 1) < apex_cap, 17, seg)


def segment_means(values, segments, fill: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """
    Average a per-particle quantity over the 17 AHA segments.

    Parameters
    ----------
    values : array_like, shape (N,)
        Per-particle values; non-finite entries are skipped.
    segments : array_like of int, shape (N,)
        Segment numbers 1 … 17 (:func:`aha_segments`).
    fill : float
        Value reported for a segment without finite values (default 0.0; check ``count``).

    Returns
    -------
    means : ndarray, shape (17,)
    count : ndarray of int, shape (17,)
        Particles that contributed to each segment.

    """
    v = np.asarray(values, dtype=np.float64)
    s = np.asarray(segments)
    if v.shape != s.shape or v.ndim != 1:
        raise ValueError(
            f'values and segments must be 1-D of equal length, got {v.shape}, {s.shape}'
        )
    if s.size and (s.min() < 1 or s.max() > 17):
        raise ValueError('segment numbers must lie in 1..17')
    ok = np.isfinite(v)
    cnt = np.bincount(s[ok] - 1, minlength=17)
    tot = np.bincount(s[ok] - 1, weights=v[ok], minlength=17)
    means = np.where(cnt > 0, tot / np.maximum(cnt, 1), fill)
    return means, cnt
