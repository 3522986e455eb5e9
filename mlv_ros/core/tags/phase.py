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
Wrapped-phase fields: gradients and sub-pixel evaluation by local linearisation.

Both the Gabor intersection finder and the HARP baseline need the wrapped phase ``ψ(x)`` of two
complex fields at sub-pixel positions and its Jacobian. Interpolating a complex exponential
bilinearly biases its phase (≈ 0.02 px at 5 px tag spacing), so instead the phase at ``x`` is
extrapolated from the nearest pixel ``q``: ``ψ(x) ≈ ψ(q) + J(q)(x − q)``, exact for locally linear
phase, with ``J`` the mean of the wrapped forward and backward differences (exact for linear phase
while ``|∇ψ| < π`` rad/px, i.e. spacing > 2 px; a wrapped central difference would fold already at
spacing 4 px, and a derivative of the complex field would shrink it by sin(k)/k).
"""

from __future__ import annotations

import numpy as np


class PhaseField:
    """
    Two wrapped phases on a pixel grid with their Jacobian.

    Attributes
    ----------
    psi : ndarray of float32, shape (2, H, W)
        Wrapped phases, rad, in (−π, π]. From :meth:`from_complex` computed when first asked
        for: :meth:`psi_at` (what the detector and :meth:`sample` read) takes the few pixels it
        needs (issue 17: ~11 % of a tracked frame's window is valid, and ``np.angle`` costs
        ~36 ns a pixel, a third of the field's cost), the same values to the bit.
    jac : ndarray of float32, shape (2, 2, H, W)
        ``jac[d, a]`` = ∂ψ_d/∂(row, col)[a], rad/px; zero on the one-pixel border.

    """

    def __init__(self, psi: np.ndarray | None, jac: np.ndarray, z: np.ndarray | None = None):
        if psi is None and z is None:
            raise ValueError('PhaseField needs its phases psi or the complex maps z')
        self._psi, self._z, self.jac = psi, z, jac

    @property
    def psi(self) -> np.ndarray:
        if self._psi is None:
            self._psi = np.angle(self._z).astype(np.float32)
        return self._psi

    def psi_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Return ``psi[:, rows, cols]``, shape (2, N), float32, without the whole map."""
        if self._psi is not None:
            return self._psi[:, rows, cols]
        # np.angle of the same complex64 values, element by element: psi's values to the bit.
        return np.angle(self._z[:, rows, cols]).astype(np.float32)

    @classmethod
    def from_complex(cls, z: np.ndarray) -> 'PhaseField':
        """
        Build the phase field of complex maps ``z``, shape (2, H, W).

        Phase 0 where the quantity of interest is.
        """
        z = np.asarray(z)
        jac = np.zeros((2, 2) + z.shape[1:], np.float32)
        # Mean of the wrapped one-pixel differences: each is unambiguous up to |∇ψ| < π rad/px
        # (tag spacing > 2 px), where angle(z(x+1) conj z(x−1)) would fold beyond π/2 (4 px).
        d0 = np.angle(z[:, 1:, :] * np.conj(z[:, :-1, :]))
        d1 = np.angle(z[:, :, 1:] * np.conj(z[:, :, :-1]))
        jac[:, 0, 1:-1, :] = (d0[:, 1:, :] + d0[:, :-1, :]) / 2
        jac[:, 1, :, 1:-1] = (d1[:, :, 1:] + d1[:, :, :-1]) / 2
        jac[:, :, 0, :] = 0
        jac[:, :, -1, :] = 0
        jac[:, :, :, 0] = 0
        jac[:, :, :, -1] = 0
        return cls(None, jac, z=z)

    @property
    def shape(self):
        return self.psi.shape[1:]

    def nearest(self, pts: np.ndarray):
        """
        Nearest interior pixel of each point and whether the point lies inside the image.

        Parameters
        ----------
        pts : ndarray, shape (N, 2)
            (row, col), px.

        Returns
        -------
        q : ndarray of int, shape (N, 2)
        inside : ndarray of bool, shape (N,)
            True where the nearest pixel is not on the border (its Jacobian is defined).

        """
        h, w = self.shape
        # Non-finite points land on the clipped corner pixel (``inside`` says they are not in the
        # image); np.where, not np.nan_to_num: the same pixels at a fraction of its cost.
        q = np.rint(np.where(np.isfinite(pts), pts, -1.0)).astype(np.int64)
        inside = (q[:, 0] >= 1) & (q[:, 0] <= h - 2) & (q[:, 1] >= 1) & (q[:, 1] <= w - 2)
        q[:, 0] = np.clip(q[:, 0], 1, h - 2)
        q[:, 1] = np.clip(q[:, 1], 1, w - 2)
        return q, inside & np.all(np.isfinite(pts), axis=1)

    def sample(self, pts: np.ndarray):
        """
        Return wrapped phases and Jacobians at sub-pixel points (linearised from nearest pixels).

        Parameters
        ----------
        pts : ndarray, shape (N, 2)
            (row, col), px.

        Returns
        -------
        psi : ndarray, shape (N, 2)
            Wrapped phases, rad.
        jac : ndarray, shape (N, 2, 2)
            ``jac[n, d, a]`` = ∂ψ_d/∂x_a at the nearest pixel, rad/px.
        inside : ndarray of bool, shape (N,)

        """
        pts = np.asarray(pts, float).reshape(-1, 2)
        q, inside = self.nearest(pts)
        j = np.moveaxis(self.jac[:, :, q[:, 0], q[:, 1]], -1, 0).astype(float)  # (N, 2, 2)
        dx = pts - q
        # J·(x − q) spelled out: the same products and sums as an einsum, half its time at 3000 pts
        lin = np.stack(
            [
                j[:, 0, 0] * dx[:, 0] + j[:, 0, 1] * dx[:, 1],
                j[:, 1, 0] * dx[:, 0] + j[:, 1, 1] * dx[:, 1],
            ],
            -1,
        )
        psi = self.psi_at(q[:, 0], q[:, 1]).T.astype(float) + lin
        return wrap(psi), j, inside


def wrap(phi):
    """Wrap angles to (−π, π]."""
    return np.pi - np.mod(np.pi - np.asarray(phi), 2 * np.pi)


def solve_phase(
    field: PhaseField,
    start: np.ndarray,
    target: np.ndarray | None = None,
    iterations: int = 4,
    max_step: float | None = None,
):
    """
    Newton iterations for ``wrap(ψ(x) − target) = 0`` from ``start``.

    Parameters
    ----------
    field : PhaseField
        Wrapped phases of both directions and their Jacobian.
    start : ndarray, shape (N, 2)
        Initial (row, col), px.
    target : ndarray, shape (N, 2), optional
        Target wrapped phases, rad (default 0).
    iterations : int
        Newton steps; each evaluates the linearisation at the current nearest pixel.
    max_step : float, optional
        Largest allowed step length per iteration, px (steps are clipped, not rejected).

    Returns
    -------
    x : ndarray, shape (N, 2)
        Solution, px.
    residual : ndarray, shape (N,)
        ``|wrap(ψ(x) − target)|`` (Euclidean over the two phases), rad.
    ok : ndarray of bool, shape (N,)
        Inside the image and the Jacobian invertible (tags not parallel) at every step.

    """
    x = np.array(start, float).reshape(-1, 2)
    tgt = np.zeros_like(x) if target is None else np.asarray(target, float).reshape(-1, 2)
    ok = np.ones(len(x), bool)
    for _ in range(max(1, iterations)):
        psi, j, inside = field.sample(x)
        r = wrap(psi - tgt)
        det = j[:, 0, 0] * j[:, 1, 1] - j[:, 0, 1] * j[:, 1, 0]
        scale = np.linalg.norm(j[:, 0], axis=1) * np.linalg.norm(j[:, 1], axis=1)
        good = inside & (np.abs(det) > 0.2 * scale) & (scale > 0)
        ok &= good
        safe = np.where(good, det, 1.0)
        step = (
            -np.stack(
                [
                    j[:, 1, 1] * r[:, 0] - j[:, 0, 1] * r[:, 1],
                    -j[:, 1, 0] * r[:, 0] + j[:, 0, 0] * r[:, 1],
                ],
                -1,
            )
            / safe[:, None]
        )
        if max_step is not None:
            n = np.linalg.norm(step, axis=1, keepdims=True)
            step = step * np.minimum(1.0, max_step / np.maximum(n, 1e-12))
        x = np.where(good[:, None], x + step, x)
    psi, _, inside = field.sample(x)
    ok &= inside
    return x, np.linalg.norm(wrap(psi - tgt), axis=1), ok
