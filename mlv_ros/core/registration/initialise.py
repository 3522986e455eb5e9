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
Model initialisation (paper §2.1): 3-D myocardium from SA/LA contours, particles, polar frame.

Shape reconstruction
--------------------
In the long-axis cylindrical frame (origin ``axis_point``, ``z`` along the axis apex → base,
``θ = atan2(p·e2, p·e1)`` with ``e2 = axis × e1``, i.e. right-handed about the apex → base axis,
the convention of :func:`mlv_ros.core.meshless.polar_frame`) each wall surface is written as

    r²_S(z, θ) = Σ_m Σ_f c_mf B_m(z) F_f(θ),   S ∈ {endo, epi},

with cubic B-splines ``B_m`` in z and a real Fourier basis ``F_f`` in θ. Fitting r² rather than r
makes a prolate cap exact to first order (r² of an ellipsoid is quadratic in z, and vanishes at
the apex), so the apex is simply where r²_epi reaches 0. A second-difference penalty in z keeps
the fit smooth and extrapolates r² linearly beyond the data (apex without LA views). SA contour
points constrain every θ at their slice level; LA contour points (six half-planes for three LA
planes) constrain the apical cap and the base.

Myocardium = ``max(r²_endo, 0) ≤ r² ≤ r²_epi`` and ``z_apex ≤ z ≤ z_base``; the base level comes
from the LA horseshoe cuts (else half a slab above the most basal SA slice).

Polar frame (eq. 1)
-------------------
Centre ``c`` on the axis at ``z_apex + H / (1 + sin 45°)`` (H = base − apex height), so that an
ellipsoid through the epicardial apex (α = −π/2) reaches the base rim at α = π/4.
``A_3 = c_z − z_apex``; ``A_1``, ``A_2`` are least-squares fits of the epicardial points to that
ellipsoid; ``a = (w_max A_3, A_1/A_3, A_2/A_3, 1)`` with ``w_max`` making max w = 1 (a0 in mm,
a1..a3 dimensionless, τ = 0).
Each particle's ``(α, β, w)`` solves ``w a0 (a1 cos α cos β, a2 cos α sin β, a3 sin α) = p``
exactly (``q = p / (A_1, A_2, A_3)``, ``w = |q|``, ``α = asin(q_3 / w)``, ``β = atan2(q_2, q_1)``),
so the rest global shape reproduces the particles (``d_rest = 0``) and global scaling acts on
the whole shape. α ≤ π/4 holds on the epicardial base rim; endocardial base particles lie a
little above (≈ π/3.5 for a normal LV). β = 0 is the documented anatomical reference (see
:func:`default_reference`).
"""

from __future__ import annotations

from dataclasses import dataclass

from mlv_ros.core.meshless import GlobalParameters, matrix_to_quat, ModelCoordinates, ModelFrame
import numpy as np
from scipy.interpolate import BSpline

#: Fourier order in θ of the wall surfaces.
FOURIER_ORDER = 3
#: B-spline intervals along the long axis.
Z_INTERVALS = 6
#: Second-difference penalty weight (relative to the data term's scale).
SMOOTHING = 1e-2


def default_reference(
    axis: np.ndarray, septum_hint=(-1.0, 0.0, 0.0), rotate_deg: float = 60.0
) -> np.ndarray:
    """
    β = 0 direction: the inferior RV–LV junction from an anatomical prior.

    The septum lies toward the patient's right (LPS −x) of the LV; projected ⟂ the axis it gives
    the mid-septum, and the inferior RV–LV insertion is 60° from it (the septum spans 120°
    between the insertions), counter-clockwise seen from the apex, i.e. a right-handed rotation
    about ``−axis`` (the convention of :mod:`mlv_ros.core.analysis.frame`).

    Parameters
    ----------
    axis : array_like, shape (3,)
        Unit long axis apex → base.
    septum_hint : array_like, shape (3,)
        Patient direction toward the septum (default: patient right).
    rotate_deg : float
        Rotation from the mid-septum to the reference, degrees CCW seen from the apex.

    Returns
    -------
    ndarray, shape (3,)
        Unit vector ⟂ axis.

    """
    ax = np.asarray(axis, dtype=np.float64)
    ax = ax / np.linalg.norm(ax)
    s = np.asarray(septum_hint, dtype=np.float64)
    s = s - (s @ ax) * ax
    if np.linalg.norm(s) < 1e-6:  # axis along the hint: any perpendicular will do
        s = np.eye(3)[int(np.argmin(np.abs(ax)))]
        s = s - (s @ ax) * ax
    s /= np.linalg.norm(s)
    t = np.radians(rotate_deg)
    # Right-handed rotation by t about −axis (Rodrigues).
    k = -ax
    return s * np.cos(t) + np.cross(k, s) * np.sin(t) + k * (k @ s) * (1 - np.cos(t))


@dataclass
class AxisFrame:
    """
    Long-axis cylindrical frame.

    ``origin`` (3,), unit ``axis`` (apex → base), ``e1`` (β = 0), ``e2 = axis × e1``. All mm / unit
    vectors in patient coordinates.
    """

    origin: np.ndarray
    axis: np.ndarray
    e1: np.ndarray

    @property
    def e2(self) -> np.ndarray:
        return np.cross(self.axis, self.e1)

    @property
    def matrix(self) -> np.ndarray:
        """Columns (e1, e2, axis): model axes in patient coordinates, shape (3, 3)."""
        return np.stack([self.e1, self.e2, self.axis], axis=1)

    def to_cylindrical(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Patient points (N, 3) → ``(r, θ, z)``: mm, rad in (−π, π], mm."""
        p = (np.asarray(x, dtype=np.float64) - self.origin) @ self.matrix
        return np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0]), p[:, 2]

    def from_cylindrical(self, r, theta, z) -> np.ndarray:
        r, theta, z = (np.asarray(v, dtype=np.float64) for v in (r, theta, z))
        p = np.stack([r * np.cos(theta), r * np.sin(theta), z], axis=-1)
        return self.origin + p @ self.matrix.T


def _fourier(theta: np.ndarray, order: int) -> np.ndarray:
    cols = [np.ones_like(theta)]
    for k in range(1, order + 1):
        cols += [np.cos(k * theta), np.sin(k * theta)]
    return np.stack(cols, axis=1)


class WallSurface:
    """
    ``r²(z, θ)`` as a penalised tensor B-spline × Fourier fit (module docstring).

    Parameters
    ----------
    z, theta, r : ndarray, shape (M,)
        Surface samples in the cylindrical frame (mm, rad, mm).
    z_range : (float, float)
        Domain of the B-splines, mm (beyond it the fit is clamped to the end values' linear
        trend).
    weights : ndarray, shape (M,), optional
        Per-sample weights.

    """

    def __init__(
        self,
        z,
        theta,
        r,
        z_range,
        weights=None,
        order: int = FOURIER_ORDER,
        intervals: int = Z_INTERVALS,
        smoothing: float = SMOOTHING,
    ):
        z0, z1 = float(z_range[0]), float(z_range[1])
        self.z0, self.z1, self.order = z0, z1, order
        k = 3
        inner = np.linspace(z0, z1, intervals + 1)
        self.knots = np.concatenate([[z0] * k, inner, [z1] * k])
        self.nb = len(self.knots) - k - 1
        a = self._design(np.asarray(z, float), np.asarray(theta, float))
        w = np.ones(len(z)) if weights is None else np.asarray(weights, float)
        y = np.asarray(r, float) ** 2
        nf = 2 * order + 1
        d2 = np.diff(np.eye(self.nb), n=2, axis=0)
        pen = np.kron(d2, np.eye(nf))
        scale = float(np.sum(w)) / max(self.nb, 1)
        lhs = (
            (a * w[:, None]).T @ a
            + smoothing * scale * pen.T @ pen
            + 1e-9 * scale * np.eye(a.shape[1])
        )
        self.coef = np.linalg.solve(lhs, (a * w[:, None]).T @ y)

    def _design(self, z, theta):
        zc = np.clip(z, self.z0, self.z1)
        bz = BSpline.design_matrix(zc, self.knots, 3).toarray()
        # Linear extrapolation of each basis beyond the domain (matches the penalty's null space).
        for end, sign in ((self.z0, -1), (self.z1, 1)):
            out = (z - end) * sign > 0
            if out.any():
                h = 1e-3 * (self.z1 - self.z0)
                zz = np.array([end, end - sign * h])
                b2 = BSpline.design_matrix(np.clip(zz, self.z0, self.z1), self.knots, 3).toarray()
                slope = (b2[0] - b2[1]) / (sign * h)
                bz[out] = b2[0] + (z[out] - end)[:, None] * slope
        f = _fourier(theta, self.order)
        return (bz[:, :, None] * f[:, None, :]).reshape(len(z), -1)

    def r2(self, z, theta) -> np.ndarray:
        """``r²`` at (z, θ), mm² (negative beyond the apex), shape like ``z``."""
        z = np.asarray(z, float)
        th = np.broadcast_to(np.asarray(theta, float), z.shape)
        return (self._design(z.ravel(), th.ravel()) @ self.coef).reshape(z.shape)


@dataclass
class LVShape:
    """
    Reconstructed ED myocardium (module docstring).

    Attributes
    ----------
    frame : AxisFrame
    endo, epi : WallSurface
    z_apex_epi, z_apex_endo, z_base : float
        Epicardial / endocardial apex and base levels along the axis, mm from ``frame.origin``.

    """

    frame: AxisFrame
    endo: WallSurface
    epi: WallSurface
    z_apex_epi: float
    z_apex_endo: float
    z_base: float

    def inside(self, x: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """
        Check whether patient points (N, 3) lie in the reconstructed myocardium.

        At least ``margin`` mm (radially, and axially at the apex and base) inside its walls.
        """
        r, th, z = self.frame.to_cylindrical(x)
        ok = (z >= self.z_apex_epi + margin) & (z <= self.z_base - margin)
        r_epi = np.sqrt(np.clip(self.epi.r2(z, th), 0.0, None))
        r2_endo = self.endo.r2(z, th)
        r_endo = np.where(r2_endo > 0, np.sqrt(np.clip(r2_endo, 0.0, None)) + margin, 0.0)
        return ok & (r <= r_epi - margin) & (r >= r_endo)

    def surface_points(self, which: str, n_z: int = 40, n_theta: int = 72) -> np.ndarray:
        """
        Sample the ``"endo"`` or ``"epi"`` surface between its apex and the base.

        Returns points of shape (n_z·n_theta, 3), mm.
        """
        s = self.endo if which == 'endo' else self.epi
        za = self.z_apex_endo if which == 'endo' else self.z_apex_epi
        # Denser near the apex where r changes fastest: z = za + H (1 − cos) spacing.
        u = np.linspace(0.0, 1.0, n_z)
        z = za + (self.z_base - za) * (1 - np.cos(0.5 * np.pi * u))
        th = np.linspace(-np.pi, np.pi, n_theta, endpoint=False)
        Z, T = np.meshgrid(z, th, indexing='ij')
        r = np.sqrt(np.clip(s.r2(Z, T), 0.0, None))
        return self.frame.from_cylindrical(r.ravel(), T.ravel(), Z.ravel())

    def transmural(self, x: np.ndarray) -> np.ndarray:
        """
        Return the transmural depth (0 endo, 1 epi) of patient points (N, 3).

        In the apical cap below the cavity the endocardial radius is taken as 0.
        """
        r, th, z = self.frame.to_cylindrical(x)
        ren = np.sqrt(np.clip(self.endo.r2(z, th), 0.0, None))
        rep = np.sqrt(np.clip(self.epi.r2(z, th), 0.0, None))
        return np.clip((r - ren) / np.maximum(rep - ren, 1e-6), 0.0, 1.0)


def _apex_level(surf: WallSurface, z_top: float, z_min: float) -> float:
    """Highest z below ``z_top`` where the θ-mean of r² reaches 0 (linear interpolation)."""
    zz = np.linspace(z_top, z_min, 600)
    th = np.linspace(-np.pi, np.pi, 24, endpoint=False)
    m = surf.r2(zz[:, None] + 0 * th[None], th[None] + 0 * zz[:, None]).mean(axis=1)
    neg = np.flatnonzero(m <= 0)
    if neg.size == 0:
        return float(z_min)
    i = int(neg[0])
    if i == 0:
        return float(z_top)
    return float(zz[i - 1] + (zz[i] - zz[i - 1]) * m[i - 1] / (m[i - 1] - m[i]))


def reconstruct_shape(
    frame: AxisFrame,
    endo_pts: list[np.ndarray],
    epi_pts: list[np.ndarray],
    z_base: float,
    weights_endo=None,
    weights_epi=None,
) -> LVShape:
    """
    Fit the endo and epi wall surfaces to contour points.

    Parameters
    ----------
    frame : AxisFrame
        Long-axis cylindrical frame the surfaces are fitted in.
    endo_pts, epi_pts : list of ndarray, each shape (M_i, 3)
        Contour points in patient coordinates, mm (SA and LA together).
    z_base : float
        Base level along the axis, mm from ``frame.origin``.
    weights_endo, weights_epi : list of ndarray, optional
        Per-point weights, parallel to the point lists.

    Returns
    -------
    LVShape

    Raises
    ------
    ValueError
        Too few points, or a reconstruction without an epicardial apex below the base.

    """

    def stack(pts, wts):
        p = (
            np.concatenate([np.asarray(a, float).reshape(-1, 3) for a in pts])
            if pts
            else np.zeros((0, 3))
        )
        w = np.concatenate(wts) if wts is not None and pts else np.ones(len(p))
        return p, w

    pe, we = stack(epi_pts, weights_epi)
    pn, wn = stack(endo_pts, weights_endo)
    if len(pe) < 50:
        raise ValueError(
            f'too few epicardial contour points to reconstruct the LV ({len(pe)} < 50)'
        )
    re, te, ze = frame.to_cylindrical(pe)
    z_lo = float(min(ze.min(), z_base - 1.0)) - 30.0
    epi = WallSurface(ze, te, re, (z_lo, z_base), we)
    z_apex_epi = _apex_level(epi, float(np.max(ze)), z_lo - 60.0)
    if not z_apex_epi < z_base - 5.0:
        raise ValueError('reconstructed epicardium has no apex below the base')
    if len(pn) >= 20:
        rn, tn, zn = frame.to_cylindrical(pn)
        endo = WallSurface(zn, tn, rn, (z_lo, z_base), wn)
        z_apex_endo = max(_apex_level(endo, float(np.max(zn)), z_lo - 60.0), z_apex_epi)
    else:  # no cavity seen anywhere: a solid cone (degenerate but usable)
        endo = WallSurface(ze, te, 0.0 * re, (z_lo, z_base), we)
        z_apex_endo = z_base
    return LVShape(frame, endo, epi, float(z_apex_epi), float(z_apex_endo), float(z_base))


def sample_particles(
    shape: LVShape, n: int, seed: int = 0, margin_fraction: float = 0.25
) -> np.ndarray:
    """
    ``n`` particles filling the reconstructed myocardium: a jittered cubic lattice.

    A lattice (spacing from the estimated volume) gives even phyxels; jitter of ±0.25 spacing
    keeps MLS moment matrices well conditioned (no exactly coplanar neighbourhoods).

    Parameters
    ----------
    shape : LVShape
        Reconstructed endo and epi wall surfaces the particles fill.
    n : int
        Number of particles (≥ 100).
    seed : int
        Seed of :func:`numpy.random.default_rng` (volume sampling, lattice jitter and the subset
        kept).
    margin_fraction : float
        Particles keep ``margin_fraction × spacing`` mm from the reconstructed walls: a particle
        stands for a cell of that spacing, and the margin absorbs sub-millimetre wall error so
        that particles stay inside the true myocardium.

    Returns
    -------
    ndarray, shape (n, 3)
        Patient coordinates, mm.

    Raises
    ------
    ValueError
        ``n`` < 100, or the reconstructed volume is empty.

    """
    if n < 100:
        raise ValueError(f'num_particles must be >= 100, got {n}')
    rng = np.random.default_rng(seed)
    th = np.linspace(-np.pi, np.pi, 36, endpoint=False)
    zz = np.linspace(shape.z_apex_epi, shape.z_base, 40)
    rmax = (
        float(
            np.sqrt(
                np.clip(shape.epi.r2(zz[:, None] + 0 * th, th[None] + 0 * zz[:, None]), 0, None)
            ).max()
        )
        + 1.0
    )
    box_lo = np.array([-rmax, -rmax, shape.z_apex_epi])
    box_hi = np.array([rmax, rmax, shape.z_base])
    # Volume estimate by Monte Carlo, then the lattice spacing that yields ≈ 1.15 n points.
    u = box_lo + (box_hi - box_lo) * rng.random((20000, 3))
    frac = shape.inside(shape.frame.origin + u @ shape.frame.matrix.T).mean()
    if frac <= 0:
        raise ValueError('reconstructed myocardium is empty')
    vol = frac * np.prod(box_hi - box_lo)
    for factor in (1.5, 1.9, 2.5):
        h = (vol / (factor * n)) ** (1.0 / 3.0)
        axes = [np.arange(lo + 0.5 * h, hi, h) for lo, hi in zip(box_lo, box_hi)]
        g = np.stack(np.meshgrid(*axes, indexing='ij'), -1).reshape(-1, 3)
        g = g + rng.uniform(-0.25 * h, 0.25 * h, g.shape)
        # Each lattice point draws its rank before the inside test: the n lowest-ranked inside
        # points are kept, so a point entering or leaving the volume (a sub-micrometre change of
        # the walls) changes one particle, not the whole draw.
        rank = rng.random(len(g))
        x = shape.frame.origin + g @ shape.frame.matrix.T
        inside = shape.inside(x, margin_fraction * h)
        if inside.sum() >= n:
            keep = np.flatnonzero(inside)[np.argsort(rank[inside], kind='stable')[:n]]
            return x[np.sort(keep)]
    raise ValueError(f'could not place {n} particles in the reconstructed myocardium')


def model_frame(shape: LVShape, particles: np.ndarray) -> tuple[ModelFrame, dict]:
    """
    Polar model frame of the particles (module docstring, paper eq. 1).

    Parameters
    ----------
    shape : LVShape
        Reconstructed wall surfaces (their frame gives the model centre and axes).
    particles : ndarray, shape (N, 3)
        Rest particle positions, mm.

    Returns
    -------
    frame : ModelFrame
        Rest parameters ``(c, R, a0..a3, τ = 0)`` and per-particle polar coordinates.
    polar : dict
        ``alpha``, ``beta``, ``w`` (N,) each (rad, rad, dimensionless).

    """
    f = shape.frame
    height = shape.z_base - shape.z_apex_epi
    cz = shape.z_apex_epi + height / (1.0 + np.sin(np.pi / 4))
    centre = f.origin + cz * f.axis
    a3 = cz - shape.z_apex_epi
    # Epicardial ellipsoid radii in e1/e2 from (p1/A1)² + (p2/A2)² = 1 − (p3/A3)².
    ep = shape.surface_points('epi', 30, 48)
    p = (ep - centre) @ f.matrix
    keep = np.abs(p[:, 2]) < 0.95 * a3
    rhs = 1.0 - (p[keep, 2] / a3) ** 2
    sol, *_ = np.linalg.lstsq(np.stack([p[keep, 0] ** 2, p[keep, 1] ** 2], 1), rhs, rcond=None)
    sol = np.clip(sol, 1e-8, None)
    a1, a2 = 1.0 / np.sqrt(sol)
    pp = (np.asarray(particles, float) - centre) @ f.matrix
    radii = np.array([a1, a2, a3])
    q = pp / radii
    w_raw = np.linalg.norm(q, axis=1)
    w_max = float(w_raw.max())
    w = w_raw / w_max
    alpha = np.arcsin(np.clip(q[:, 2] / np.maximum(w_raw, 1e-12), -1.0, 1.0))
    beta = np.arctan2(q[:, 1], q[:, 0])
    coords = ModelCoordinates.polar(alpha, beta, w)
    # a0 carries the scale (mm), a1..a3 the dimensionless radii relative to the long radius.
    params = GlobalParameters(
        centre, matrix_to_quat(f.matrix), [w_max * a3, a1 / a3, a2 / a3, 1.0], 0.0
    )
    return ModelFrame(params, coords), {'alpha': alpha, 'beta': beta, 'w': w}


def polar_to_patient(frame: ModelFrame, alpha, beta, w) -> np.ndarray:
    """
    Inverse of :func:`model_frame`'s coordinates: eq. 1 with τ = 0, then ``x = c + R e``.

    Returns
    -------
    ndarray, shape (N, 3)
        Patient coordinates, mm.

    """
    a = frame.params.a
    alpha, beta, w = (np.asarray(v, float) for v in (alpha, beta, w))
    e = (w * a[0])[:, None] * np.stack(
        [
            a[1] * np.cos(alpha) * np.cos(beta),
            a[2] * np.cos(alpha) * np.sin(beta),
            a[3] * np.sin(alpha),
        ],
        1,
    )
    return frame.params.translation + e @ frame.params.matrix.T
