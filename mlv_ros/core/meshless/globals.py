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
Global deformation of the deformable model (paper §2.1–2.2, eq. 1–3, 7–8, 13).

World position of a particle: ``x = c + R p`` with ``p = s + d`` (model-centred frame), where
``s`` is the global shape and ``d`` the local deformation. ``R`` comes from a unit quaternion
``q = (w, x, y, z)`` (model-centred → world).

Both shape variants are written with a per-particle *basis* ``b`` and *twist coordinate* ``g``
(material coordinates, fixed for the life of the model):

* polar (eq. 1): ``b = w (cos α cos β, cos α sin β, sin α)``, ``g = sin α``;
* cylindrical: ``b = (w cos β, w sin β, ζ)``, ``g = ζ`` (ζ ∈ [−1, 1] along the axis).

Then ``e = a0 (a1 b1, a2 b2, a3 b3)`` and ``s = Rz(φ) e`` with ``φ = π τ g`` (eq. 2). For the
polar variant this is exactly eq. 1–2 (φ = π τ sin α); the cylindrical variant twists linearly
with height, which is what a twisted cylinder does.

The generalised coordinates used by the solver are ``q_g = (c [3], θ = q [4], a0..a3, τ)``, 12
numbers; ``L = [I, B, R J]`` (eq. 8) is their Jacobian.

Thick-walled variant (optional, :func:`thick_wall_frame`; not the paper's): the affine
``e`` changes the wall's volume by ``J_a = a0³ a1 a2 a3 / (a0³ a1 a2 a3)_rest``, so a
contracting shape thins its wall as it shrinks the cavity, where myocardium keeps its volume and
thickens. With a cavity fraction ``κ = ρ_c² / ρ²`` per particle (``ρ`` its rest distance from the
long axis, ``ρ_c(z, θ)`` the rest endocardial radius at its level and angle) the in-plane part of
``e`` is scaled by ``k = √(κ + (1 − κ) / J_a)`` before the twist. Per level this is the
inflation and extension of an incompressible thick-walled cylinder (textbook kinematics, e.g.
Humphrey, *Cardiovascular Solid Mechanics*, Springer 2002; a derivation, not the paper's):
``r'² − r_c'² = (r² − r_c²) / λ_z`` with ``r_c' = λ r_c`` the endocardium scaled by the fit's
in-plane scale λ and ``λ_z`` its axial scale. In the volume coordinates ``(ρ²/2, θ, z)`` the map
``ρ → kρ`` has Jacobian ``1 / J_a`` whatever ``ρ_c(z, θ)`` is, so the global map keeps every
volume exactly (``det = 1``) for any ``a``; the twist ``R_z(π τ g)`` keeps it too where ``a1 = a2``
and ``ρ_c`` does not vary with θ (otherwise its volume change is of order τ times the in-plane
anisotropy). No new parameter: the thickening follows from ``a0..a3``. The endocardium (κ = 1)
moves as in the paper's form.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mlv_ros.core.meshless.kernel import validate_points
from mlv_ros.core.types import ModelState
import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates

#: Layout of the 12-vector of global parameters.
NUM_GLOBAL = 12
SLICE_C = slice(0, 3)
SLICE_Q = slice(3, 7)
SLICE_S = slice(7, 12)
GLOBAL_NAMES = ('cx', 'cy', 'cz', 'qw', 'qx', 'qy', 'qz', 'a0', 'a1', 'a2', 'a3', 'tau')
#: Tangent space used for updates: (Δc [3], body rotation vector ω [3], Δa0..Δa3, Δτ).
NUM_TANGENT = 11
#: Thick-walled variant: the wall-volume ratio ``J_a`` of the affine part is floored here (a trial
#: step of the global fit toward a collapsed shape; a real heart's is 0.5–1.3), and ``k²`` at
#: ``K2_MIN``, so the map stays finite; the derivative is that of the floored value.
JA_MIN = 0.05
K2_MIN = 1e-4
#: Angular bins of the endocardial radius ``ρ_c(z, θ)`` (:func:`thick_wall_coordinates`), 15° each,
#: and the particle spacings per level bin; the binned minimum is smoothed over ``CAVITY_SMOOTH``
#: bins (Gaussian σ).
CAVITY_ANGLES = 24
CAVITY_LEVEL_SPACINGS = 2.0
CAVITY_SMOOTH = 1.0
#: Largest cavity fraction kept: a particle a little inside the smoothed endocardium (κ > 1) moves
#: inward of it as it contracts, with the volume kept, while ``J_a > 1 − 1 / KAPPA_MAX``.
KAPPA_MAX = 1.5


# --------------------------------------------------------------------------- quaternions
def quat_normalize(q) -> np.ndarray:
    """Return the unit quaternion (w, x, y, z), w ≥ 0; ValueError for zero or non-finite input."""
    q = np.asarray(q, dtype=np.float64).reshape(4)
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f'rotation quaternion must be finite and non-zero, got {q}')
    q = q / n
    return -q if q[0] < 0 else q


def quat_to_matrix(q) -> np.ndarray:
    """Rotation matrix (3, 3) of the quaternion ``q = (w, x, y, z)`` (normalised first)."""
    w, x, y, z = quat_normalize(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(r) -> np.ndarray:
    """Return the unit quaternion (w, x, y, z) of a rotation matrix (Shepperd's method)."""
    r = np.asarray(r, dtype=np.float64)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise ValueError('rotation must be a finite 3x3 matrix')
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise ValueError('rotation matrix must be orthonormal with determinant +1')
    tr = np.trace(r)
    cands = np.array([tr, r[0, 0], r[1, 1], r[2, 2]])
    k = int(np.argmax(cands))
    if k == 0:
        w = 0.5 * np.sqrt(1 + tr)
        q = [
            w,
            (r[2, 1] - r[1, 2]) / (4 * w),
            (r[0, 2] - r[2, 0]) / (4 * w),
            (r[1, 0] - r[0, 1]) / (4 * w),
        ]
    else:
        i, j, m = k - 1, k % 3, (k + 1) % 3
        v = np.zeros(3)
        v[i] = 0.5 * np.sqrt(1 + r[i, i] - r[j, j] - r[m, m])
        v[j] = (r[j, i] + r[i, j]) / (4 * v[i])
        v[m] = (r[m, i] + r[i, m]) / (4 * v[i])
        q = [(r[m, j] - r[j, m]) / (4 * v[i]), *v]
    return quat_normalize(q)


def quat_from_axis_angle(axis, angle: float) -> np.ndarray:
    """Quaternion of a rotation by ``angle`` rad (right hand) about ``axis``."""
    a = np.asarray(axis, dtype=np.float64).reshape(3)
    n = np.linalg.norm(a)
    if not np.isfinite(n) or n == 0:
        raise ValueError(f'rotation axis must be finite and non-zero, got {axis}')
    return quat_normalize(np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * a / n]))


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices ``[v]×``, shape (..., 3, 3), for ``v`` of shape (..., 3)."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def quat_multiply(p, q) -> np.ndarray:
    """Hamilton product ``p ⊗ q`` of (w, x, y, z) quaternions."""
    p, q = np.asarray(p, dtype=np.float64), np.asarray(q, dtype=np.float64)
    return np.concatenate(
        [[p[0] * q[0] - p[1:] @ q[1:]], p[0] * q[1:] + q[0] * p[1:] + np.cross(p[1:], q[1:])]
    )


def quat_from_rotvec(omega) -> np.ndarray:
    """Quaternion of the rotation vector ``omega`` (axis × angle, rad)."""
    omega = np.asarray(omega, dtype=np.float64).reshape(3)
    angle = float(np.linalg.norm(omega))
    if angle < 1e-12:
        return quat_normalize(np.concatenate([[1.0], 0.5 * omega]))
    return quat_from_axis_angle(omega, angle)


def quat_rate_matrix(q) -> np.ndarray:
    """``G = [−q⃗, q0 I − [q⃗]×]`` (3, 4): body angular velocity ``ω = 2 G q̇``."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([-q[1:, None], q[0] * np.eye(3) - skew(q[1:])], axis=1)


def rotation_jacobian(q, p: np.ndarray) -> np.ndarray:
    """
    ``B = ∂(R p)/∂q = −2 R [p]× G`` (eq. 7), shape (N, 3, 4).

    Exact derivative of ``R(q/|q|) p`` at a unit ``q`` (it annihilates the radial direction
    ``q``, so the normalisation after each update costs nothing to first order).

    Parameters
    ----------
    q : array_like, shape (4,)
        Unit quaternion (w, x, y, z).
    p : ndarray, shape (N, 3)
        Model-centred positions, mm.

    """
    r = quat_to_matrix(q)
    # R [p]× = [R p]× R, so column k of B is −2 (R p) × (R G)[:, k]: one cross product per column
    # instead of a three-operand einsum over per-particle skew matrices (2.0 → 0.3 ms at 3000).
    k = r @ quat_rate_matrix(q)
    return -2.0 * np.cross((p @ r.T)[:, None, :], k.T[None, :, :]).transpose(0, 2, 1)


# --------------------------------------------------------------------------- shape
@dataclass
class ModelCoordinates:
    """
    Material (parametric) coordinates of particles, fixed for the model's lifetime.

    Attributes
    ----------
    kind : str
        ``"polar"`` or ``"cylindrical"``.
    basis : ndarray, shape (N, 3)
        ``b`` (see module docstring), dimensionless.
    twist : ndarray, shape (N,)
        ``g``: twist angle is ``φ = π τ g``.
    cavity : ndarray, shape (N,), optional
        Thick-walled variant (module docstring): ``κ = ρ_c² / ρ²``, dimensionless (1 on the
        endocardium, smaller outward). None: the paper's affine shape.
    rest_volume : float
        ``(a0 a1)(a0 a2)(a0 a3)`` of the rest parameters, mm³ (the thick-walled variant's
        reference of ``J_a``).

    """

    kind: str
    basis: np.ndarray
    twist: np.ndarray
    cavity: np.ndarray | None = None
    rest_volume: float = 1.0

    def __post_init__(self):
        self.basis = np.asarray(self.basis, dtype=np.float64)
        self.twist = np.asarray(self.twist, dtype=np.float64)
        if self.cavity is not None:
            self.cavity = np.asarray(self.cavity, dtype=np.float64)
            if self.cavity.shape != self.twist.shape or not np.all(
                np.isfinite(self.cavity) & (self.cavity >= 0)
            ):
                raise ValueError(
                    'cavity fraction must be finite and >= 0 with one value per particle'
                )
            if not (np.isfinite(self.rest_volume) and self.rest_volume > 0):
                raise ValueError(f'rest_volume must be finite and > 0, got {self.rest_volume}')
        if self.kind not in ('polar', 'cylindrical'):
            raise ValueError(
                f"coordinate kind must be 'polar' or 'cylindrical', got {self.kind!r}"
            )
        validate_points(self.basis, 'model coordinate basis')
        if self.twist.shape != (self.basis.shape[0],) or not np.all(np.isfinite(self.twist)):
            raise ValueError('twist coordinate must be finite with one value per particle')

    def __len__(self) -> int:
        return int(self.basis.shape[0])

    @classmethod
    def polar(cls, alpha, beta, w) -> 'ModelCoordinates':
        """From polar coordinates (eq. 1): α ∈ [−π/2, π/2] (rad), β (rad), transmural w ≥ 0."""
        alpha, beta, w = (np.asarray(v, dtype=np.float64).reshape(-1) for v in (alpha, beta, w))
        if not (alpha.shape == beta.shape == w.shape):
            raise ValueError('alpha, beta and w must have the same length')
        ca = np.cos(alpha)
        basis = w[:, None] * np.stack([ca * np.cos(beta), ca * np.sin(beta), np.sin(alpha)], 1)
        return cls('polar', basis, np.sin(alpha))

    @classmethod
    def cylindrical(cls, beta, w, zeta) -> 'ModelCoordinates':
        """From cylindrical coordinates: angle β (rad), radial w, axial ζ (twist ∝ ζ)."""
        beta, w, zeta = (np.asarray(v, dtype=np.float64).reshape(-1) for v in (beta, w, zeta))
        if not (beta.shape == w.shape == zeta.shape):
            raise ValueError('beta, w and zeta must have the same length')
        basis = np.stack([w * np.cos(beta), w * np.sin(beta), zeta], 1)
        return cls('cylindrical', basis, zeta)

    def subset(self, idx) -> 'ModelCoordinates':
        cavity = None if self.cavity is None else self.cavity[idx]
        return ModelCoordinates(
            self.kind, self.basis[idx], self.twist[idx], cavity, self.rest_volume
        )


def twist_cos_sin(coords: ModelCoordinates, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """
    Return ``cos φ`` and ``sin φ`` of each particle's twist angle ``φ = π τ g`` (eq. 2–3).

    :func:`global_shape` and :func:`shape_jacobian` at one ``τ`` share them (``cos_sin``).

    Parameters
    ----------
    coords : ModelCoordinates
        Material coordinates of the particles (their twist coordinate ``g``).
    tau : float
        Twist factor.

    Returns
    -------
    cos, sin : ndarray, shape (N,)

    """
    phi = np.pi * tau * coords.twist
    return np.cos(phi), np.sin(phi)


def wall_scale(coords: ModelCoordinates, a, derivative: bool = False):
    """
    Return the thick-walled variant's in-plane scale ``k = √(κ + (1 − κ) / J_a)`` per particle.

    ``J_a = a0³ a1 a2 a3 / rest_volume`` is the wall-volume ratio of the affine part (module
    docstring), floored at ``JA_MIN``; ``k²`` is floored at ``K2_MIN``.

    Parameters
    ----------
    coords : ModelCoordinates
        Material coordinates with their cavity fraction ``κ``.
    a : array_like, shape (4,)
        ``a0`` (mm) and ``a1, a2, a3`` (dimensionless).
    derivative : bool
        Also return ``∂k/∂(a0, a1, a2, a3)``.

    Returns
    -------
    k : ndarray, shape (N,) or None
        Dimensionless; None without a cavity fraction (the paper's shape, ``k = 1``).
    dk : ndarray, shape (N, 4)
        With ``derivative``: ``∂k/∂a``, per mm for ``a0``, dimensionless for the others.

    """
    if coords.cavity is None:
        return (None, None) if derivative else None
    a = np.asarray(a, dtype=np.float64)
    kappa = coords.cavity
    # ∂J_a/∂a as products (no division by a parameter that a trial step may take to 0)
    a03 = a[0] ** 3
    grad = np.array(
        [3 * a[0] ** 2 * a[1] * a[2] * a[3], a03 * a[2] * a[3], a03 * a[1] * a[3],
         a03 * a[1] * a[2]]
    ) / coords.rest_volume
    ja = a[0] * grad[0] / 3.0
    floored = ja < JA_MIN
    ja = max(ja, JA_MIN)
    k2 = kappa + (1.0 - kappa) / ja
    low = k2 < K2_MIN
    k = np.sqrt(np.maximum(k2, K2_MIN))
    if not derivative:
        return k
    dk_dj = np.where(low, 0.0, -(1.0 - kappa) / (2.0 * k * ja * ja))
    return k, (0.0 if floored else 1.0) * dk_dj[:, None] * grad[None, :]


def global_shape(coords: ModelCoordinates, a, tau: float, cos_sin=None) -> np.ndarray:
    """
    ``s = T(e(b; a0..a3))`` with twist ``φ = π τ g`` (eq. 1–3).

    With a cavity fraction in ``coords`` the in-plane part of ``e`` is scaled by
    :func:`wall_scale` first (the thick-walled variant, module docstring).

    Parameters
    ----------
    coords : ModelCoordinates
        Material coordinates of the particles: their basis ``b`` and twist coordinate ``g`` (module
        docstring).
    a : array_like, shape (4,)
        ``a0`` (mm) and ``a1, a2, a3`` (dimensionless).
    tau : float
        Twist factor.
    cos_sin : tuple of ndarray, optional
        :func:`twist_cos_sin` of ``coords`` at ``tau``, when the caller has it.

    Returns
    -------
    ndarray, shape (N, 3)
        Model-centred global shape, mm.

    """
    a = np.asarray(a, dtype=np.float64)
    e = a[0] * coords.basis * a[1:]
    k = wall_scale(coords, a)
    if k is not None:
        e[:, :2] *= k[:, None]
    c, s = twist_cos_sin(coords, tau) if cos_sin is None else cos_sin
    out = np.empty_like(e)  # R_z(φ) e, component by component
    np.subtract(c * e[:, 0], s * e[:, 1], out=out[:, 0])
    np.add(s * e[:, 0], c * e[:, 1], out=out[:, 1])
    out[:, 2] = e[:, 2]
    return out


def shape_jacobian(coords: ModelCoordinates, a, tau: float, cos_sin=None) -> np.ndarray:
    """
    Return ``J = ∂s/∂(a0, a1, a2, a3, τ)`` (eq. 7–8, 13), analytic, shape (N, 3, 5).

    Parameters
    ----------
    coords : ModelCoordinates
        Material coordinates of the particles.
    a : array_like, shape (4,)
        ``a0`` (mm) and ``a1, a2, a3``.
    tau : float
        Twist factor.
    cos_sin : tuple of ndarray, optional
        :func:`twist_cos_sin` of ``coords`` at ``tau``, when the caller has it.

    Notes
    -----
    Thick-walled variant: ``s = K ⊙ s₀`` with ``K = (k, k, 1)`` (the twist about z commutes with
    the in-plane scale), so ``∂s/∂a_j = K ⊙ ∂s₀/∂a_j + (∂k/∂a_j) (s₀x, s₀y, 0)`` and
    ``∂s/∂τ = K ⊙ ∂s₀/∂τ``, ``s₀`` the paper's shape.

    """
    a = np.asarray(a, dtype=np.float64)
    k, dk = wall_scale(coords, a, derivative=True)
    if k is not None:
        b = coords.basis.copy()
        b[:, :2] *= k[:, None]
        coords = ModelCoordinates(coords.kind, b, coords.twist)
    b = coords.basis
    c, s_ = twist_cos_sin(coords, tau) if cos_sin is None else cos_sin
    # Entry by entry (the rotated axes R_z(φ) e_x = (c, s, 0), e_y = (−s, c, 0), e_z): the
    # same products as scaling the three axes, without their zero entries.
    jac = np.zeros((b.shape[0], 3, 5))
    t1, t2, t3 = b[:, 0] * a[1], b[:, 1] * a[2], b[:, 2] * a[3]
    np.add(t1 * c, t2 * -s_, out=jac[:, 0, 0])  # = s / a0
    np.add(t1 * s_, t2 * c, out=jac[:, 1, 0])
    jac[:, 2, 0] = t3
    a0b = a[0] * b[:, 0]
    np.multiply(a0b, c, out=jac[:, 0, 1])
    np.multiply(a0b, s_, out=jac[:, 1, 1])
    a0b = a[0] * b[:, 1]
    np.multiply(a0b, -s_, out=jac[:, 0, 2])
    np.multiply(a0b, c, out=jac[:, 1, 2])
    np.multiply(a[0], b[:, 2], out=jac[:, 2, 3])
    pg = np.pi * coords.twist
    np.multiply(pg, -(a[0] * jac[:, 1, 0]), out=jac[:, 0, 4])
    np.multiply(pg, a[0] * jac[:, 0, 0], out=jac[:, 1, 4])
    if k is not None:  # + (∂k/∂a_j) s₀: s₀'s in-plane part is a0 jac[:, :2, 0] / k
        s0 = (a[0] / k)[:, None] * jac[:, :2, 0]
        jac[:, :2, :4] += s0[:, :, None] * dk[:, None, :]
    return jac


@dataclass
class GlobalParameters:
    """
    Global parameters ``q_g = (c, θ, q_s)``.

    Attributes
    ----------
    translation : ndarray, shape (3,)
        c, mm (world).
    rotation : ndarray, shape (4,)
        Unit quaternion (w, x, y, z) of R (model-centred → world).
    a : ndarray, shape (4,)
        a0 (mm), a1, a2, a3.
    tau : float
        Twist factor (φ = π τ g).

    """

    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    a: np.ndarray = field(default_factory=lambda: np.ones(4))
    tau: float = 0.0

    def __post_init__(self):
        self.translation = np.asarray(self.translation, dtype=np.float64).reshape(3)
        self.rotation = quat_normalize(self.rotation)
        self.a = np.asarray(self.a, dtype=np.float64).reshape(4)
        self.tau = float(self.tau)
        if not (
            np.all(np.isfinite(self.translation))
            and np.all(np.isfinite(self.a))
            and np.isfinite(self.tau)
        ):
            raise ValueError('global parameters must be finite')

    @property
    def matrix(self) -> np.ndarray:
        """R, shape (3, 3)."""
        return quat_to_matrix(self.rotation)

    def vector(self) -> np.ndarray:
        """Return the parameters as one 12-vector: c, q, a0..a3, τ."""
        return np.concatenate([self.translation, self.rotation, self.a, [self.tau]])

    @classmethod
    def from_vector(cls, v) -> 'GlobalParameters':
        v = np.asarray(v, dtype=np.float64)
        return cls(v[SLICE_C], v[SLICE_Q], v[7:11], float(v[11]))

    def stepped(self, step) -> 'GlobalParameters':
        """
        Parameters after a step in the 11-dim tangent space ``(Δc, ω, Δa0..Δa3, Δτ)``.

        The rotation is updated on the unit sphere, ``q ← q ⊗ exp(ω/2)`` with ω the body-frame
        rotation vector: the first-order quaternion rate ``q̇ = ½ Gᵀ ω`` followed by
        renormalisation, done exactly (see :func:`reduce_rotation`).
        """
        step = np.asarray(step, dtype=np.float64).reshape(NUM_TANGENT)
        return GlobalParameters(
            self.translation + step[0:3],
            quat_multiply(self.rotation, quat_from_rotvec(step[3:6])),
            self.a + step[6:10],
            self.tau + float(step[10]),
        )

    def state(self, num_particles: int, **values) -> ModelState:
        """
        Return these parameters as a :class:`~mlv_ros.core.types.ModelState`.

        Parameters
        ----------
        num_particles : int
            The model's particle count.
        **values
            Further ModelState fields (phase, convergence record, ...).

        Returns
        -------
        ModelState

        """
        return ModelState(
            translation=self.translation.copy(),
            rotation=self.rotation.copy(),
            a0=float(self.a[0]),
            a1=float(self.a[1]),
            a2=float(self.a[2]),
            a3=float(self.a[3]),
            tau=float(self.tau),
            num_particles=num_particles,
            **values,
        )

    def copy(self) -> 'GlobalParameters':
        return GlobalParameters.from_vector(self.vector())


def world_positions(
    params: GlobalParameters, coords: ModelCoordinates, d: np.ndarray
) -> np.ndarray:
    """``x = c + R (s + d)``, shape (N, 3), mm."""
    p = global_shape(coords, params.a, params.tau) + d
    return params.translation + p @ params.matrix.T


def model_jacobian(
    params: GlobalParameters, coords: ModelCoordinates, d: np.ndarray
) -> np.ndarray:
    """
    ``L = [I, B, R J]`` (eq. 8) for the 12 global parameters, shape (N, 3, 12).

    (The block ``R`` acting on ``d`` is handled by the local stage.)
    """
    cs = twist_cos_sin(coords, params.tau)
    s = global_shape(coords, params.a, params.tau, cs)
    n = s.shape[0]
    lmat = np.empty((n, 3, NUM_GLOBAL))
    lmat[:, :, SLICE_C] = np.eye(3)
    lmat[:, :, SLICE_Q] = rotation_jacobian(params.rotation, s + d)
    jac = shape_jacobian(coords, params.a, params.tau, cs)
    lmat[:, :, SLICE_S] = np.matmul(params.matrix, jac)
    return lmat


def shape_terms(coords: ModelCoordinates, params: GlobalParameters) -> tuple:
    """
    Return the per-particle terms of the global shape at ``params``: ``(cos_sin, s, jac)``.

    :func:`twist_cos_sin`, :func:`global_shape` (mm) and :func:`shape_jacobian` (shape (N, 3,
    5)). Each particle's row depends on its own coordinates only, so the rows of a subset of
    particles are the same numbers as the terms of ``coords.subset``.

    Parameters
    ----------
    coords : ModelCoordinates
        Material coordinates of the particles.
    params : GlobalParameters
        Where the terms are taken (its ``a`` and ``tau``).

    """
    cs = twist_cos_sin(coords, params.tau)
    return (
        cs,
        global_shape(coords, params.a, params.tau, cs),
        shape_jacobian(coords, params.a, params.tau, cs),
    )


def control_jacobian(
    params: GlobalParameters, coords: ModelCoordinates, d: np.ndarray, phi, shape=None
) -> np.ndarray:
    """
    Return ``L_k = Σ_j φ_kj L_j`` (eq. 14) of control points, shape (M, 3, 12).

    The same as ``phi @`` :func:`model_jacobian` per particle, without forming it: the rotation
    block ``B = ∂(R p)/∂q`` is linear in ``p``, so it is taken once per control point at
    ``Σ_j φ_kj p_j``; only the shape block is projected particle by particle.

    Parameters
    ----------
    params : GlobalParameters
        Where the derivative is taken.
    coords : ModelCoordinates
        Material coordinates of the N particles ``phi`` weights.
    d : ndarray, shape (N, 3)
        Their local deformation in the model-centred frame, mm.
    phi : scipy.sparse matrix, shape (M, N)
        The control points' kernel weights.
    shape : (cos_sin, s, jac), optional
        :func:`twist_cos_sin`, :func:`global_shape` and :func:`shape_jacobian` of ``coords`` at
        ``params``, when the caller has them (:func:`shape_terms`).

    """
    cs, s, jac = shape_terms(coords, params) if shape is None else shape
    n, m = s.shape[0], phi.shape[0]
    lk = np.empty((m, 3, NUM_GLOBAL))
    lk[:, :, SLICE_C] = (phi @ np.ones(n))[:, None, None] * np.eye(3)
    lk[:, :, SLICE_Q] = rotation_jacobian(params.rotation, phi @ (s + d))
    jac = (phi @ jac.reshape(n, 15)).reshape(m, 3, 5)
    lk[:, :, SLICE_S] = np.matmul(params.matrix, jac)
    return lk


def tangent_gram(
    params: GlobalParameters, coords: ModelCoordinates, d: np.ndarray, shape=None
) -> np.ndarray:
    """
    Return ``Σ_n L_nᵀ L_n`` of the particles' Jacobians in the tangent space, shape (11, 11).

    The same sum as over :func:`reduce_rotation` of :func:`model_jacobian` (``L_n = [I, −R [p_n]×,
    R J_n]``, ``p_n = s_n + d_n``), from sums over the particles instead of an (N, 3, 11) array:
    ``Σ [p]×ᵀ[p]× = Σ (|p|² I − p pᵀ)``, ``Σ (−R [p]×)ᵀ R J = Σ [p]× J``.

    Parameters
    ----------
    params : GlobalParameters
        Where the derivative is taken.
    coords : ModelCoordinates
        The particles' material coordinates.
    d : ndarray, shape (N, 3)
        Their local deformation in the model-centred frame, mm.
    shape : (cos_sin, s, jac), optional
        :func:`shape_terms` of ``coords`` at ``params``, when the caller has them.

    """
    _, s, jac = shape_terms(coords, params) if shape is None else shape  # jac (N, 3, 5)
    p = s + d
    r = params.matrix
    gram = np.empty((NUM_TANGENT, NUM_TANGENT))
    gram[0:3, 0:3] = p.shape[0] * np.eye(3)
    gram[0:3, 3:6] = -r @ skew(p.sum(axis=0))
    gram[0:3, 6:11] = r @ jac.sum(axis=0)
    gram[3:6, 3:6] = np.einsum('na,na->', p, p) * np.eye(3) - p.T @ p
    for a in range(3):  # Σ_n (p_n × J_n[:, k])_a for the 5 columns k
        b, c = (a + 1) % 3, (a + 2) % 3
        gram[3 + a, 6:11] = p[:, b] @ jac[:, c] - p[:, c] @ jac[:, b]
    jf = jac.reshape(-1, 5)
    gram[6:11, 6:11] = jf.T @ jf
    lower = np.tril_indices(NUM_TANGENT, -1)
    gram[lower] = gram.T[lower]
    return gram


def reduce_rotation(lmat: np.ndarray, q) -> np.ndarray:
    """
    Map ``L`` (…, 3, 12) to the 11-dim tangent space: ``B_ω = B ½ Gᵀ = −R [p]×``.

    The quaternion has 4 numbers but 3 degrees of freedom (``B q = 0``); solving in the body
    rotation vector ω removes that null direction from the generalised-force system (eq. 15).
    """
    half_gt = 0.5 * quat_rate_matrix(q).T  # (4, 3)
    return np.concatenate(
        [lmat[..., SLICE_C], lmat[..., SLICE_Q] @ half_gt, lmat[..., SLICE_S]], axis=-1
    )


# --------------------------------------------------------------------------- frames
@dataclass
class ModelFrame:
    """
    Rest (end-diastolic) model frame.

    Where the model-centred frame sits, and the material coordinates of each particle.

    Attributes
    ----------
    params : GlobalParameters
        Rest global parameters (τ = 0 normally); ``x_rest ≈ c + R s(rest)``.
    coords : ModelCoordinates

    """

    params: GlobalParameters
    coords: ModelCoordinates


def _axis_frame(axis, ref_direction) -> np.ndarray:
    z = np.asarray(axis, dtype=np.float64).reshape(3)
    nz = np.linalg.norm(z)
    if not np.isfinite(nz) or nz == 0:
        raise ValueError(f'axis must be a finite non-zero vector, got {axis}')
    z = z / nz
    if ref_direction is None:
        ref = np.eye(3)[int(np.argmin(abs(z)))]
    else:
        ref = np.asarray(ref_direction, dtype=np.float64).reshape(3)
    x = ref - (ref @ z) * z
    if np.linalg.norm(x) < 1e-9:
        raise ValueError('ref_direction is parallel to the axis')
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)  # columns: model axes in world


def polar_frame(points, centre, axis, ref_direction=None, a0: float | None = None) -> ModelFrame:
    """
    Polar model frame (eq. 1) for a particle cloud.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        Rest particle positions, mm (world).
    centre : array_like, shape (3,)
        Model origin c, mm (LV: the centroid on the long axis).
    axis : array_like, shape (3,)
        Model z axis (LV: apex → base, so α runs from −π/2 at the apex upward).
    ref_direction : array_like, shape (3,), optional
        Direction of β = 0 (LV: the inferior RV insertion); projected ⟂ axis.
    a0 : float, optional
        Scale, mm; default the largest particle distance from the centre, so that w ∈ [0, 1].

    Returns
    -------
    ModelFrame
        Rest parameters (c, R, a = (a0, 1, 1, 1), τ = 0); ``w = |p| / a0``, so the rest shape
        reproduces the particles exactly.

    """
    pts = validate_points(points, 'particle positions')
    c = np.asarray(centre, dtype=np.float64).reshape(3)
    rot = _axis_frame(axis, ref_direction)
    p = (pts - c) @ rot
    r = np.linalg.norm(p, axis=1)
    a0 = float(r.max()) if a0 is None else float(a0)
    if not np.isfinite(a0) or a0 <= 0:
        raise ValueError(f'a0 must be finite and > 0, got {a0}')
    safe = np.where(r > 0, r, 1.0)
    alpha = np.where(r > 0, np.arcsin(np.clip(p[:, 2] / safe, -1, 1)), 0.0)
    beta = np.arctan2(p[:, 1], p[:, 0])
    coords = ModelCoordinates.polar(alpha, beta, r / a0)
    return ModelFrame(GlobalParameters(c, matrix_to_quat(rot), [a0, 1, 1, 1], 0.0), coords)


def cylindrical_frame(
    points,
    centre,
    axis,
    ref_direction=None,
    radius: float | None = None,
    half_height: float | None = None,
) -> ModelFrame:
    """
    Cylindrical model frame: ``w = ρ / radius``, ``ζ = z / half_height``.

    Rest parameters ``a = (radius, 1, 1, half_height / radius)``, τ = 0, so the rest shape
    reproduces the particles exactly and twist ``φ = π τ ζ`` is linear in height.
    Defaults: the largest radial distance and the largest |z| of the particles.
    """
    pts = validate_points(points, 'particle positions')
    c = np.asarray(centre, dtype=np.float64).reshape(3)
    rot = _axis_frame(axis, ref_direction)
    p = (pts - c) @ rot
    rho = np.hypot(p[:, 0], p[:, 1])
    radius = float(rho.max()) if radius is None else float(radius)
    half_height = float(np.abs(p[:, 2]).max()) if half_height is None else float(half_height)
    if not (np.isfinite(radius) and radius > 0 and np.isfinite(half_height) and half_height > 0):
        raise ValueError(
            f'radius and half_height must be finite and > 0, got {radius}, {half_height}'
        )
    coords = ModelCoordinates.cylindrical(
        np.arctan2(p[:, 1], p[:, 0]), rho / radius, p[:, 2] / half_height
    )
    return ModelFrame(
        GlobalParameters(c, matrix_to_quat(rot), [radius, 1, 1, half_height / radius], 0.0), coords
    )


def thick_wall_frame(frame: ModelFrame) -> ModelFrame:
    """
    Return ``frame`` with the thick-walled variant's cavity fraction (module docstring).

    ``ρ_c(z, θ)`` is the smallest rest distance from the long axis of the particles in each bin
    of ``CAVITY_ANGLES`` angles × levels ``CAVITY_LEVEL_SPACINGS`` median particle spacings tall
    (an empty bin takes its angle's nearest level, or the level's smallest), Gaussian-smoothed
    over ``CAVITY_SMOOTH`` bins in θ (periodic; not in z, where the cavity ends at the apex
    within a bin or two) and interpolated bilinearly: a continuous function of ``(z, θ)``, so the
    map keeps volume exactly. A particle a little inside the smoothed surface has ``κ > 1``
    (cut at ``KAPPA_MAX``). In the apical cap below the cavity ``ρ_c`` is the innermost
    particles' small radius, and the cap keeps its volume by widening in-plane as it shortens
    (``k → J_a^(−1/2)``), as a solid incompressible cylinder does.

    Parameters
    ----------
    frame : ModelFrame
        Rest parameters and material coordinates (without a cavity fraction).

    Returns
    -------
    ModelFrame
        The same rest parameters; coordinates with ``cavity`` and ``rest_volume`` set. The rest
        shape is unchanged (``J_a = 1`` there, so ``k = 1``).

    Raises
    ------
    ValueError
        Fewer than 5 particles, or all at one level.

    """
    from scipy.spatial import cKDTree

    coords, params = frame.coords, frame.params
    p = global_shape(coords, params.a, params.tau)
    if len(p) < 5:
        raise ValueError(f'the thick-walled shape needs at least 5 particles, got {len(p)}')
    rho, theta, z = np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0]), p[:, 2]
    height = float(np.ptp(z))
    spacing = float(np.median(cKDTree(p).query(p, k=2)[0][:, 1]))
    if not (height > 0 and spacing > 0):
        raise ValueError('the thick-walled shape needs particles at more than one level')
    nz = int(np.clip(round(height / (CAVITY_LEVEL_SPACINGS * spacing)), 1, 200))
    nt = CAVITY_ANGLES
    u = (z - z.min()) / height * nz  # bin units
    v = (theta + np.pi) / (2 * np.pi) * nt
    grid = np.full((nz, nt), np.inf)
    np.minimum.at(grid, (np.minimum(u.astype(int), nz - 1), v.astype(int) % nt), rho)
    filled = np.isfinite(grid)
    levels = np.arange(nz)
    for j in range(nt):  # an empty bin: its angle's nearest filled level, else the level's min
        if filled[:, j].any() and not filled[:, j].all():
            known = np.flatnonzero(filled[:, j])
            near = known[np.abs(levels[:, None] - known[None, :]).argmin(axis=1)]
            grid[:, j] = grid[near, j]
    row = np.where(np.isfinite(grid), grid, np.inf).min(axis=1, keepdims=True)
    grid = np.where(np.isfinite(grid), grid, row)
    grid = np.where(np.isfinite(grid), grid, float(rho.min()))
    # smoothed in θ only: along z the cavity ends at the apex within a bin or two, and a
    # smoothing across that edge would put the surface outside the cap's particles
    grid = gaussian_filter(grid, (0.0, CAVITY_SMOOTH), mode=('nearest', 'wrap'))
    padded = np.hstack([grid[:, -1:], grid, grid[:, :1]])  # wrap in θ, nearest in z
    rho_c = map_coordinates(padded, [u - 0.5, v + 0.5], order=1, mode='nearest')
    kappa = np.clip((rho_c / np.maximum(rho, 1e-9 * max(spacing, 1.0))) ** 2, 0.0, KAPPA_MAX)
    rest_volume = float(np.prod(params.a[0] * params.a[1:]))
    return ModelFrame(
        params, ModelCoordinates(coords.kind, coords.basis, coords.twist, kappa, rest_volume)
    )
