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
