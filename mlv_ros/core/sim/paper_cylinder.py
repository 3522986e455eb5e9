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
Cylinder-shell phantom of the paper's §3.1 with analytic deformations (Fig. 4).

Particles fill the shell between two nested coaxial cylinders — outer radius 15 mm, **inner
radius 9 mm** (a 6 mm wall, LV-like), height 30 mm — centred at the origin with the axis along z.
Deformations map rest positions to deformed positions analytically:

* ``scaling``   — radial ×0.85, axial ×0.90 (contraction and shortening);
* ``rotation``  — rigid 20° about the oblique axis (1, 1, 1)/√3 through the centre;
* ``twisting``  — rotation about z by θ(z) = 15° · z / 15 mm (±15° at the ends, 30° net);
* ``combination`` — twist, then scaling, then the rotation, then a translation (1.5, −1, 2) mm;
* ``bulge``     — the scaling plus a local outward radial bulge
  ``2 mm · exp(−Δβ²/(2·0.5²) − z²/(2·5²))`` centred on β = 0, z = 0: not expressible by the
  global parameters (a regional dyskinetic patch).

The first four are exactly representable by the cylindrical global model
(``mlv_ros.core.meshless.globals.cylindrical_frame``), so a fit can drive the dense error to zero.
"""

from __future__ import annotations

import numpy as np

R_OUTER = 15.0  # mm
R_INNER = 9.0  # mm
H_CYL = 30.0  # mm

SCALE_RADIAL, SCALE_AXIAL = 0.85, 0.90
ROT_AXIS, ROT_ANGLE = np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0), np.deg2rad(20.0)
TWIST_MAX = np.deg2rad(15.0)
TRANSLATION = np.array([1.5, -1.0, 2.0])
BULGE_AMPLITUDE, BULGE_SIGMA_BETA, BULGE_SIGMA_Z = 2.0, 0.5, 5.0

FIG4_DEFORMATIONS = ('scaling', 'rotation', 'twisting', 'combination')
DEFORMATIONS = FIG4_DEFORMATIONS + ('bulge',)


def sample_cylinder_shell(
    n: int,
    r_inner: float = R_INNER,
    r_outer: float = R_OUTER,
    height: float = H_CYL,
    seed: int = 0,
    jitter: float = 0.25,
) -> np.ndarray:
    """
    Particles filling the shell ``r_inner ≤ ρ ≤ r_outer``, ``|z| ≤ height/2``.

    A cubic lattice with spacing ``(V / n)^(1/3)`` (V the shell volume), each site jittered
    uniformly by ±``jitter`` spacings, keeping sites inside the shell: close to uniform density
    without the near-coincident pairs of i.i.d. sampling. The count is ≈ n (within a few %).

    Parameters
    ----------
    n : int
        Target particle count, ≥ 10.
    r_inner, r_outer, height : float
        Shell geometry, mm (0 ≤ r_inner < r_outer, height > 0).
    seed : int
        Jitter seed.
    jitter : float
        Jitter amplitude in lattice spacings, in [0, 0.5).

    Returns
    -------
    ndarray, shape (≈n, 3)
        Positions, mm, centred at the origin, axis z.

    """
    if int(n) < 10:
        raise ValueError(f'need at least 10 particles, got {n}')
    if not (0 <= r_inner < r_outer and height > 0 and 0 <= jitter < 0.5):
        raise ValueError(
            'cylinder shell needs 0 <= r_inner < r_outer, height > 0, 0 <= jitter < 0.5'
        )
    vol = np.pi * (r_outer**2 - r_inner**2) * height
    a = (vol / n) ** (1.0 / 3.0)
    xs = np.arange(-r_outer + a / 2, r_outer, a)
    zs = np.arange(-height / 2 + a / 2, height / 2, a)
    g = np.stack(np.meshgrid(xs, xs, zs, indexing='ij'), -1).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    g = g + rng.uniform(-jitter * a, jitter * a, g.shape)
    rho = np.hypot(g[:, 0], g[:, 1])
    keep = (rho >= r_inner) & (rho <= r_outer) & (np.abs(g[:, 2]) <= height / 2)
    return g[keep]


def _rotate(v: np.ndarray, axis: np.ndarray, angle) -> np.ndarray:
    """Rodrigues rotation of rows of v about a unit axis by angle (scalar or per row)."""
    angle = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    return v * c + np.cross(axis, v) * s + np.outer(v @ axis, axis) * (1 - c)


def deform(points: np.ndarray, name: str, height: float = H_CYL) -> np.ndarray:
    """
    Analytic deformation ``name`` (see module docstring) of rest positions.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        Rest positions, mm (phantom frame).
    name : str
        One of :data:`DEFORMATIONS`.
    height : float
        Phantom height, mm (sets the twist profile θ(z) = θ_max · z / (height/2)).

    Returns
    -------
    ndarray, shape (N, 3)
        Deformed positions, mm.

    """
    x = np.asarray(points, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f'points must have shape (N, 3), got {x.shape}')
    ez = np.array([0.0, 0.0, 1.0])
    scale = np.array([SCALE_RADIAL, SCALE_RADIAL, SCALE_AXIAL])
    twist = TWIST_MAX * x[:, 2] / (height / 2)
    if name == 'scaling':
        return x * scale
    if name == 'rotation':
        return _rotate(x, ROT_AXIS, ROT_ANGLE)
    if name == 'twisting':
        return _rotate(x, ez, twist)
    if name == 'combination':
        return _rotate(_rotate(x, ez, twist) * scale, ROT_AXIS, ROT_ANGLE) + TRANSLATION
    if name == 'bulge':
        beta = np.arctan2(x[:, 1], x[:, 0])
        rho = np.maximum(np.hypot(x[:, 0], x[:, 1]), 1e-12)
        e_rho = np.stack([x[:, 0] / rho, x[:, 1] / rho, np.zeros(len(x))], 1)
        amp = BULGE_AMPLITUDE * np.exp(
            -(beta**2) / (2 * BULGE_SIGMA_BETA**2) - x[:, 2] ** 2 / (2 * BULGE_SIGMA_Z**2)
        )
        return x * scale + amp[:, None] * e_rho
    raise ValueError(f'unknown deformation {name!r}; choose from {", ".join(DEFORMATIONS)}')


def control_subset(n: int, fraction: float, seed: int = 0) -> np.ndarray:
    """
    Seeded random subset of ``round(fraction · n)`` particle indices (sorted).

    Parameters
    ----------
    n : int
        Particle count.
    fraction : float
        In [0, 1]; 0 gives an empty array (which the solver rejects with a ValueError).
    seed : int
        Seed of :func:`numpy.random.default_rng`.

    Returns
    -------
    ndarray of int64, shape (M,)

    """
    if not (0.0 <= float(fraction) <= 1.0):
        raise ValueError(f'control fraction must lie in [0, 1], got {fraction}')
    m = int(round(float(fraction) * n))
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=m, replace=False)).astype(np.int64)
