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
Synthetic LV-like point clouds and analytic motions with exact deformation gradients.

For tests, demos and report previews; independent of the simulator, so an analysis test does
not share a model of the heart with the code it checks. Clouds are lattices in cylindrical
coordinates (ρ, θ, z) about the long axis of an :class:`LVFrame`, z measured from the apex
toward the base, θ CCW seen from the apex (the frame's convention), so analytic expectations
are exact up to rounding.

The analytic motion (:func:`cylindrical_motion`) is

    ρ' = s_r ρ,   θ' = θ + φ(z),   z' = s_l z,   φ(z) = φ_apex + (φ_base − φ_apex) z / L

(uniform radial scaling about the axis, linear twist from apex to base, uniform longitudinal
scaling about the apex), whose Green–Lagrange strain in the cardiac frame is
``E_rr = E_cc = ½(s_r² − 1)``, ``E_ll = ½(s_l² + (s_r ρ φ′)² − 1)``.
"""

from __future__ import annotations

from mlv_ros.core.analysis.frame import LVFrame
import numpy as np


def oblique_frame(length: float = 80.0, origin=(12.0, -30.0, 45.0)) -> LVFrame:
    """
    Return an LV frame whose axes are not aligned with the patient axes (catches basis mix-ups).

    The long axis points mostly toward −y/+z (a typical LPS orientation is not needed here).
    """
    a = np.array([0.3, -0.5, 0.8])
    a /= np.linalg.norm(a)
    ref = np.array([1.0, 0.2, 0.0])
    o = np.asarray(origin, dtype=np.float64)
    return LVFrame(o, o + length * a, ref)


def to_patient(frame: LVFrame, rho, theta, z) -> np.ndarray:
    """Patient positions (N, 3) of cylindrical coordinates about the frame's long axis."""
    rho, theta, z = (np.asarray(v, dtype=np.float64).ravel() for v in (rho, theta, z))
    return (
        frame.apex
        + np.outer(rho * np.cos(theta), frame.e1)
        + np.outer(rho * np.sin(theta), frame.e2)
        + np.outer(z, frame.axis)
    )


def to_cylindrical(frame: LVFrame, X) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`to_patient`: (ρ, θ, z) of positions (N, 3)."""
    p = frame.inplane(X)
    return np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0]), frame.axial(X)


def cylinder_shell(
    frame: LVFrame,
    r_in: float = 20.0,
    r_out: float = 30.0,
    n_r: int = 5,
    n_theta: int = 72,
    n_z: int = 40,
) -> tuple[np.ndarray, np.ndarray]:
    """
    Lattice of a thick cylindrical shell from the apex plane to the base plane.

    Radii equally spaced on [r_in, r_out], angles ``2π(j + ½)/n_theta``, levels at the centres
    of ``n_z`` equal slabs of [0, frame.length] (so every slab and level bin is filled evenly).

    Returns
    -------
    X : ndarray, shape (n_r·n_theta·n_z, 3)
    endo : ndarray of bool
        True on the inner surface ρ = r_in.

    """
    r = np.linspace(r_in, r_out, n_r)
    t = 2 * np.pi * (np.arange(n_theta) + 0.5) / n_theta
    z = frame.length * (np.arange(n_z) + 0.5) / n_z
    R, T, Z = np.meshgrid(r, t, z, indexing='ij')
    return to_patient(frame, R, T, Z), (R == r_in).ravel()


def prolate_shell(
    frame: LVFrame,
    a_in: float = 25.0,
    c_in: float = 70.0,
    a_out: float = 35.0,
    c_out: float = 80.0,
    n_w: int = 5,
    n_theta: int = 72,
    n_z: int = 80,
) -> tuple[np.ndarray, np.ndarray]:
    """
    Return the lattice of a truncated thick prolate shell.

    The half-ellipsoid cavity of radius ``a_in`` and depth ``c_in`` below the base plane, wall out
    to ``a_out``/``c_out`` (frame.length must equal ``c_out``: the epicardial apex is the frame
    apex).

    Levels at slab centres of [0, c_out]; at each level ``n_w`` radii equally spaced from the
    endocardial to the epicardial radius (below the cavity apex the inner radius is 0: a solid
    cap). Cavity volume: ``(2/3)π a_in² c_in``.

    Returns
    -------
    X : ndarray, shape (M, 3)
    endo : ndarray of bool
        True on the endocardial surface (levels that cut the cavity only).

    """
    if not np.isclose(frame.length, c_out):
        raise ValueError(f'frame.length ({frame.length}) must equal c_out ({c_out})')
    z = c_out * (np.arange(n_z) + 0.5) / n_z
    d = c_out - z  # depth below the base plane
    r_o = a_out * np.sqrt(np.clip(1 - (d / c_out) ** 2, 0, None))
    r_i = a_in * np.sqrt(np.clip(1 - (d / c_in) ** 2, 0, None))
    w = np.linspace(0.0, 1.0, n_w)
    t = 2 * np.pi * (np.arange(n_theta) + 0.5) / n_theta
    W, T, K = np.meshgrid(w, t, np.arange(n_z), indexing='ij')
    rho = r_i[K] + W * (r_o[K] - r_i[K])
    endo = (W == 0) & (r_i[K] > 0)
    return to_patient(frame, rho, T, z[K]), endo.ravel()


def cylindrical_motion(
    frame: LVFrame,
    X,
    s_r: float = 1.0,
    s_l: float = 1.0,
    twist_apex_deg: float = 0.0,
    twist_base_deg: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """
    Apply the analytic motion of the module docstring.

    Parameters
    ----------
    frame : LVFrame
        LV frame the motion is defined in (z along its long axis from the apex, length L).
    X : array_like, shape (N, 3)
        ED positions, mm.
    s_r, s_l : float
        Radial and longitudinal scale factors (< 1 = contraction / shortening).
    twist_apex_deg, twist_base_deg : float
        Rotation at z = 0 and z = L, degrees, CCW seen from the apex.

    Returns
    -------
    x : ndarray, shape (N, 3)
        Current positions.
    F : ndarray, shape (N, 3, 3)
        Exact deformation gradients ∂x/∂X in patient axes.

    """
    rho, th, z = to_cylindrical(frame, X)
    pa, pb = np.radians(twist_apex_deg), np.radians(twist_base_deg)
    k = (pb - pa) / frame.length
    phi = pa + k * z
    x = to_patient(frame, s_r * rho, th + phi, s_l * z)
    # Local Cartesian (ξ, η, z) -> (ξ', η', z'); M maps local to patient axes.
    c, s = np.cos(phi), np.sin(phi)
    xi, eta = rho * np.cos(th), rho * np.sin(th)
    F = np.zeros((X.shape[0], 3, 3))
    F[:, 0, 0], F[:, 0, 1] = s_r * c, -s_r * s
    F[:, 1, 0], F[:, 1, 1] = s_r * s, s_r * c
    F[:, 0, 2] = s_r * k * (-s * xi - c * eta)
    F[:, 1, 2] = s_r * k * (c * xi - s * eta)
    F[:, 2, 2] = s_l
    M = np.stack([frame.e1, frame.e2, frame.axis], axis=1)
    return x, M @ F @ M.T


def synthetic_cycle(
    frame: LVFrame,
    X,
    num_phases: int = 20,
    *,
    es_fraction: float = 0.35,
    s_r_es: float = 0.85,
    s_l_es: float = 0.88,
    twist_apex_es_deg: float = 10.0,
    twist_base_es_deg: float = -3.0,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """
    Return a smooth cycle of :func:`cylindrical_motion` with end-systole at ``es_fraction``.

    The contraction profile is ``g(t) = sin²(π t / (2 t_es))`` up to ES and relaxes as
    ``cos²(π (t − t_es) / (2 (1 − t_es)))`` after it (g = 0 at ED, 1 at ES); every parameter
    interpolates linearly from its ED value by g. A larger ``es_fraction`` and milder ES
    values give a slower, weaker (hypertrophic-like) cycle.

    Returns
    -------
    list of (x, F), one per phase 0 … num_phases−1 (phase 0 is ED: x = X, F = I)

    """
    out = []
    for p in range(num_phases):
        t = p / num_phases
        if t <= es_fraction:
            g = np.sin(0.5 * np.pi * t / es_fraction) ** 2
        else:
            g = np.cos(0.5 * np.pi * (t - es_fraction) / (1 - es_fraction)) ** 2
        out.append(
            cylindrical_motion(
                frame,
                X,
                1 + g * (s_r_es - 1),
                1 + g * (s_l_es - 1),
                g * twist_apex_es_deg,
                g * twist_base_es_deg,
            )
        )
    return out
