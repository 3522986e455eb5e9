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
Analytic, invertible, volume-preserving LV motion over one cardiac cycle.

Local frame
-----------
Origin at the ED epicardial apex ``A``; ``e_L`` the unit long axis (apex → base); ``e_1`` the
in-plane direction toward the middle of the septum; ``e_2 = -e_L × e_1``, so that
``(e_1, e_2, -e_L)`` is right-handed and the angle ``θ = atan2(p·e_2, p·e_1)`` grows
counter-clockwise *as seen from the apex looking toward the base* (the twist sign convention of
the method notes). ``z = p·e_L`` is the height above the apex and ``u = z / L`` the fractional
level (0 apex, 1 base plane); ``r`` is the distance from the axis.

Motion map (ED material point ``(r, θ, z)`` → phase-t position ``(r', θ', z')``)
------------------------------------------------------------------------------
With the activation ``s(t) ∈ [0, 1]`` (0 at ED, 1 at ES; raised-cosine rise and fall, C¹):

* twist:        ``θ' = θ + s φ_ES(u)``, ``φ_ES`` a monotone PCHIP through
  ``(0, φ_apex), (u_0, 0), (1, φ_base)``;
* long axis:    ``z' = Z(z, θ) = z − s L (G(u) − Σ_i k_i a_i(θ) C_i(u))`` with the normal
  long-axis strain profile ``g(u)`` (ES shortening of the material at level u; ``G = ∫_0^u g``,
  ``C_i = ∫_0^u g b_i``), so the local axial stretch is ``Z_z = 1 − s g(u) (1 − Σ k a b)``:
  the apex is fixed and each region scales the normal motion. ``g`` (prolate hearts with
  ``apex_thickening`` τ) is ``−τ`` through the solid apical wall up to ``u_c = min(u_tip, 0.1)``
  (``u_tip`` the endocardial apex's level, 0.1 the AHA cap's top) — the cap *thickens* along its
  wall normal, the axis, by τ at ES — and ``ε_w`` from ``u_c + w`` up (C² blend over
  ``w = 0.1``), ``ε_w`` chosen so that the base still descends ``base_descent_mm``
  (:meth:`LVMotion._init_profile`). Without ``apex_thickening`` (cylinder; presets of studies
  simulated before it existed) ``g = ε = base_descent / L`` everywhere. Each abnormal region i
  (the infarct preset's segment, ``motion.regions``; :mod:`mlv_ros.core.sim.regional`) has a C²
  window ``a_i(θ) b_i(u)`` and ``k_i = 1 − contraction`` the lost share of the normal motion:
  k = 1 stops the region shortening or thickening (akinetic), 0 < k < 1 reduces it
  (hypokinetic), k > 1 reverses it (dyskinetic: the wall lengthens, an apical cap thins and
  stretches in-wall, the aneurysm's bulge);
* radial:       ``r'² = ρ² Q(z) + (r² − Q(z)) / J₂``, with ``Q`` the squared reference
  endocardial radius, ``ρ = 1 − s (1 − ρ_ES)(1 − Σ k a b)`` the endocardial radius ratio (k > 1:
  the endocardium moves outward, the wall thins: a bulge) and
  ``J₂ = ∂(θ', z')/∂(θ, z) = Z_z − φ' Z_θ``.

In the volume coordinates ``(r²/2, θ, z)`` the Jacobian is triangular with determinant
``(1/J₂)·J₂ = 1``: the map is exactly isochoric (det F = 1) for any smooth ``Q, ρ, φ, Z``, and
every step inverts in closed form except ``z`` (a few Newton steps). ``G`` and ``C_i`` are exact
piecewise-polynomial antiderivatives (:func:`_piecewise`), so ``Z_z`` is exactly ``∂Z/∂z``.
Regions do not overlap, so ``Σ k a b ≤ max k ≤ 2`` and
``J₂ ≥ 1 − max(ε_w, τ) − s² |φ'_u Z_θ| > 0`` (τ ≤ 0.8, ε_w < 0.9: :meth:`LVMotion._init_profile`).

Why the apex needs its own profile: with one shortening ε at every level the solid cap (whose
wall normal is the axis) shortened axially, i.e. *thinned*, and the isochoric radial step
stretched it in-wall — the opposite of a heart, whose normal apex thickens and shortens in-wall
while an apical aneurysm thins and bulges. Limitation: ``Z`` depends on the height only, so the
cap's axial thickening lifts all material above it by about ``τ (u_c L)`` (2–3 mm): apical
levels move little along the axis at ES, mid levels about a third of the base's descent.

The geometry (which ED points are myocardium) is independent of the map; material outside the
myocardium moves with the same formula, but the imaging treats the background as static.

References
----------
Apical systolic wall thickening of normal hearts, ~20–60 %: Moore et al., "Three-dimensional
systolic strain patterns in the normal human left ventricle: characterization with tagged MR
imaging", Radiology 214 (2000) 453–466; ASE/EACVI chamber quantification (Lang et al., J Am Soc
Echocardiogr 28 (2015) 1–39: normal segments thicken, akinetic ones < 10 %, dyskinetic ones
thin and move outward). The random draw's 0.2–0.5 lies in that range (citations from memory,
to be checked). The presets have no ``apex_thickening`` yet (legacy cap, docs/benchmarks.md).
Paper §3.2 and Fig. 9–16 (shortening, radial contraction, apex CCW / base CW twist); method
notes "Coordinates and conventions" (twist sign, ≈45 % zero-rotation level); AHA 17-segment
model (Cerqueira et al., Circulation 2002) for the infarct segment and the AHA angles of regions.

"""

from __future__ import annotations

from dataclasses import dataclass

from mlv_ros.core.sim.presets import load_preset
from mlv_ros.core.sim.regional import check_regions
from mlv_ros.core.sim.rv import check_rv, RightVentricle
import numpy as np
from numpy.polynomial import Polynomial
from scipy.interpolate import PchipInterpolator, PPoly

# AHA segment centres in the local angle θ (deg, CCW from apex, 0 = mid-septum): basal and mid
# rings 60° wide in the order anterior, anteroseptal, inferoseptal, inferior, inferolateral,
# anterolateral (counter-clockwise in the apex-view bull's-eye); apical ring 90° wide.
_RING6 = [-90.0, -30.0, 30.0, 90.0, 150.0, -150.0]
_RING4 = [-90.0, 0.0, 90.0, 180.0]
AHA_LEVELS = {'apex': (0.0, 0.1), 'apical': (0.1, 0.4), 'mid': (0.4, 0.7), 'basal': (0.7, 1.0)}
#: A typical ES axial thickening of the solid apical wall (the apex cap), fraction of its ED
#: thickness: normal apical systolic wall thickening is ~20–60 % (module docstring).
DEFAULT_APEX_THICKENING = 0.3
#: Accepted range of ``motion.apex_thickening``.
APEX_THICKENING_RANGE = (0.0, 0.8)
#: Height (fraction of the length) of the C² blend above the endocardial apex over which the
#: cap's thickening turns into the wall's shortening (the AHA cap is 10 % of the length).
APEX_BLEND_FRACTION = 0.1


def aha_segment_window(segment: int) -> tuple[float, float, float, float]:
    """
    Angular centre, half-width (deg) and level range (fractions of L) of an AHA segment.

    Parameters
    ----------
    segment : int
        1–17 (1–6 basal, 7–12 mid, 13–16 apical, 17 apex cap).

    Returns
    -------
    centre_deg, half_width_deg, u0, u1 : float
        ``half_width_deg = 180`` for the apex cap (all angles).

    """
    if not 1 <= int(segment) <= 17:
        raise ValueError(f'AHA segment must be in 1..17, got {segment}')
    s = int(segment)
    if s <= 6:
        return _RING6[s - 1], 30.0, *AHA_LEVELS['basal']
    if s <= 12:
        return _RING6[s - 7], 30.0, *AHA_LEVELS['mid']
    if s <= 16:
        return _RING4[s - 13], 45.0, *AHA_LEVELS['apical']
    return 0.0, 180.0, *AHA_LEVELS['apex']


def infarct_region(infarct: dict) -> dict:
    """
    Return a preset's ``motion.infarct`` (one AHA segment) as a region.

    The region is one of :mod:`mlv_ros.core.sim.regional`, for the ground truth; its motion is the
    original one.

    Parameters
    ----------
    infarct : dict
        ``aha_segment``, optional ``residual_motion``, ``blend_deg``, ``blend_fraction``.

    Returns
    -------
    dict
        ``kind`` (akinetic for residual motion ≤ 0.1, else hypokinetic), ``levels``,
        ``centre_deg`` (in [0, 360)), ``width_deg``, ``contraction`` (the residual motion),
        ``blend_deg``, ``blend_fraction``, ``aha_segment``.

    """
    centre, half, u_lo, u_hi = aha_segment_window(int(infarct['aha_segment']))
    c = float(infarct.get('residual_motion', 0.0))
    return {
        'kind': 'akinetic' if c <= 0.1 else 'hypokinetic',
        'levels': [u_lo, u_hi],
        'centre_deg': centre % 360.0,
        'width_deg': 2.0 * half,
        'contraction': c,
        'blend_deg': float(infarct.get('blend_deg', 20.0)),
        'blend_fraction': float(infarct.get('blend_fraction', 0.06)),
        'aha_segment': int(infarct['aha_segment']),
    }


def _smoothstep(x):
    """
    C² ramp 6x⁵ − 15x⁴ + 10x³ clipped to [0, 1]; returns (value, derivative).

    C² (not just C¹) because F contains second derivatives of the infarct window through J₂.
    """
    x = np.clip(x, 0.0, 1.0)
    return x**3 * (x * (6.0 * x - 15.0) + 10.0), 30.0 * x * x * (1.0 - x) ** 2


def _smoothstep_integral(x):
    """∫_0^x smoothstep, valid for any x (0 below 0, x − ½ above 1)."""
    xc = np.clip(x, 0.0, 1.0)
    return xc**4 * (xc * (xc - 3.0) + 2.5) + np.maximum(x - 1.0, 0.0)


_SMOOTHSTEP = Polynomial([0.0, 0.0, 0.0, 10.0, -15.0, 6.0])


def _ramp_piece(x0: float, w: float, mid: float) -> Polynomial:
    """Polynomial (in u) of the ramp ``smoothstep((u − x0)/w)`` on an interval around ``mid``."""
    if mid <= x0:
        return Polynomial([0.0])
    if mid >= x0 + w:
        return Polynomial([1.0])
    return _SMOOTHSTEP(Polynomial([-x0 / w, 1.0 / w]))


def _piecewise(piece, breaks) -> tuple[PPoly, PPoly]:
    """
    Exact piecewise polynomial of a product of ramps and its antiderivative from u = 0.

    Parameters
    ----------
    piece : callable
        ``piece(mid) -> Polynomial`` in u, the function on the interval around ``mid``
        (constant outside the breaks).
    breaks : sequence of float
        Every level where a factor changes piece.

    Returns
    -------
    f, F : PPoly
        ``f`` and ``F(u) = ∫_0^u f`` (both extrapolate: f is constant beyond the breaks). The
        map uses F for the height and f for its derivative, so ``∂Z/∂z`` is exactly the
        derivative of ``Z`` (det F = 1 needs it) whatever the rounding of the coefficients.

    """
    b = np.unique(np.asarray(breaks, dtype=np.float64))
    x = np.concatenate([[b[0] - 1.0], b, [b[-1] + 1.0]])
    c = np.zeros((11, x.size - 1))  # ramps are degree 5: products of two are degree 10
    for i in range(x.size - 1):
        q = piece(0.5 * (x[i] + x[i + 1]))(Polynomial([x[i], 1.0])).trim()  # t = u − x_i
        c[11 - q.coef.size:, i] = q.coef[::-1]
    f = PPoly(c, x, extrapolate=True)
    F = f.antiderivative()
    F.c[-1] -= F(0.0)  # a constant shift of every piece keeps F continuous
    return f, F


@dataclass(frozen=True)
class CardiacFrame:
    """
    Long-axis frame of the phantom in patient coordinates (ED; the apex and axis stay fixed).

    Attributes
    ----------
    apex : ndarray, shape (3,)
        ED epicardial apex, mm (LPS).
    base_centre : ndarray, shape (3,)
        Centre of the ED base plane, mm.
    long_axis : ndarray, shape (3,)
        Unit vector apex → base.
    septum : ndarray, shape (3,)
        Unit vector ⟂ long axis toward the middle of the septum (θ = 0).
    e2 : ndarray, shape (3,)
        ``-long_axis × septum`` (θ = +90°, anterior → inferior sense; see module docstring).
    length : float
        ``|base_centre − apex|``, mm.

    """

    apex: np.ndarray
    base_centre: np.ndarray
    long_axis: np.ndarray
    septum: np.ndarray
    e2: np.ndarray
    length: float

    def to_local(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Patient points (N, 3) mm → cylindrical ``(r, θ, z)``: mm, rad in (−π, π], mm."""
        p = np.asarray(x, dtype=np.float64) - self.apex
        z = p @ self.long_axis
        p1 = p @ self.septum
        p2 = p @ self.e2
        return np.hypot(p1, p2), np.arctan2(p2, p1), z

    def from_local(self, r, theta, z) -> np.ndarray:
        """Cylindrical ``(r, θ, z)`` (each shape (N,)) → patient points (N, 3), mm."""
        r = np.asarray(r, dtype=np.float64)
        return (
            self.apex
            + np.multiply.outer(z, self.long_axis)
            + np.multiply.outer(r * np.cos(theta), self.septum)
            + np.multiply.outer(r * np.sin(theta), self.e2)
        )


def _cardiac_frame(o: dict, L: float) -> CardiacFrame:
    """
    Return the LV frame a preset's orientation ``o`` and ED length ``L`` (mm) place.

    Raises
    ------
    ValueError
        A zero long axis, or a septum hint parallel to it.

    """
    axis = np.asarray(o['long_axis'], dtype=np.float64)
    if np.linalg.norm(axis) < 1e-9:
        raise ValueError('orientation.long_axis must be a non-zero vector')
    axis = axis / np.linalg.norm(axis)
    hint = np.asarray(o['septum_hint'], dtype=np.float64)
    hint = hint - (hint @ axis) * axis
    if np.linalg.norm(hint) < 1e-6:
        raise ValueError('orientation.septum_hint must not be parallel to long_axis')
    e1 = hint / np.linalg.norm(hint)
    e2 = np.cross(-axis, e1)
    base = np.asarray(o['base_centre_mm'], dtype=np.float64)
    return CardiacFrame(
        apex=base - L * axis, base_centre=base, long_axis=axis, septum=e1, e2=e2, length=L
    )


class LVMotion:
    """
    Ground-truth LV geometry and motion of one preset (see the module docstring).

    Parameters
    ----------
    preset : dict, str or Path
        A preset (see :func:`~mlv_ros.core.sim.presets.load_preset`).
    num_phases : int, optional
        Overrides ``motion.num_phases``; phases are ``t_p = p T / num_phases``.

    Attributes
    ----------
    frame : CardiacFrame
        Apex, base centre, long axis, septal direction.
    num_phases : int
    cycle_duration : float
        RR interval T, s.
    times : ndarray, shape (num_phases,)
        Trigger times, s.
    es_phase : float
        End-systolic phase (fractional index).

    """

    def __init__(self, preset, num_phases: int | None = None):
        self.preset = load_preset(preset)
        g, m, o = self.preset['geometry'], self.preset['motion'], self.preset['orientation']
        self.kind = g['kind']
        self.length = L = float(g['length_mm'])
        self.num_phases = int(num_phases if num_phases is not None else m['num_phases'])
        if self.num_phases < 2:
            raise ValueError(f'num_phases must be >= 2, got {self.num_phases}')
        self.cycle_duration = float(m['cycle_duration_s'])
        self.times = np.arange(self.num_phases) * self.cycle_duration / self.num_phases
        self.es_fraction = float(m['es_fraction'])
        self.relax_fraction = float(m['relaxation_fraction'])
        self.es_phase = self.es_fraction * self.num_phases

        self.frame = _cardiac_frame(o, L)

        self._init_shape(g)

        self.eps = float(m['base_descent_mm']) / L  # nominal; the wall's own: self.eps_wall
        self.rho_es = float(m['endo_radius_ratio_es'])
        u0 = float(m['twist_zero_level'])
        self._twist = PchipInterpolator(
            [0.0, u0, 1.0], np.radians([m['twist_apex_deg'], 0.0, m['twist_base_deg']])
        )
        self._dtwist = self._twist.derivative()

        self._init_regions(m, g)
        self._init_profile(m)
        # Ramp width of the reference radius Q near the endocardial apex (mm²), see _ref_q.
        self._q_soft = 0.02 * (self.endo_a**2 if self.kind == 'prolate' else self.r_in**2)
        # Optional right ventricle (mlv_ros.core.sim.rv): seen in the images, not LV myocardium.
        rv = check_rv(g.get('rv'))
        self.rv = (
            None
            if rv is None
            else RightVentricle(
                rv,
                self.length,
                self.epi_radius,
                self.epi_a if self.kind == 'prolate' else self.r_out,
            )
        )
        #: Farthest any imaged tissue of the heart reaches from the long axis at ED, mm.
        self.reach_radius = self.max_radius + (self.rv.extent_mm if self.rv is not None else 0.0)

    def _init_shape(self, g: dict) -> None:
        """Set the ED shape's sizes (mm) from the preset's geometry ``g``: prolate or cylinder."""
        if self.kind == 'prolate':
            self.endo_a = float(g['endo_radius_mm'])
            self.endo_c = float(g['endo_depth_mm'])
            self.epi_a = float(g['epi_radius_mm'])
            self.epi_c = self.length
            self.septal_extra = float(g.get('septal_extra_mm', 0.0))
            self.atrium_height = float(g.get('atrium_height_mm', 0.0))
            self.max_radius = self.epi_a + self.septal_extra
        else:
            self.r_in = float(g['inner_radius_mm'])
            self.r_out = float(g['outer_radius_mm'])
            self.septal_extra = 0.0
            self.atrium_height = 0.0
            self.max_radius = self.r_out

    def _init_regions(self, m: dict, g: dict) -> None:
        """
        Set the abnormal regions from the preset's motion ``m`` (geometry ``g`` checks them).

        Abnormal regions (mlv_ros.core.sim.regional): the preset's infarct first, then
        motion.regions. Each is (k, centre, half, blend_theta, blend_u, (u_lo, u_hi)) with
        k = 1 − contraction the lost share of the normal motion.

        """
        self._regions: list[tuple] = []
        self.regions: list[dict] = []
        self.infarct_segment = None
        inf = m.get('infarct')
        if inf:
            centre, half, u_lo, u_hi = aha_segment_window(int(inf['aha_segment']))
            k = 1.0 - float(inf.get('residual_motion', 0.0))
            self._regions.append(
                (
                    k,
                    np.radians(centre),
                    np.radians(half),
                    np.radians(float(inf.get('blend_deg', 20.0))),
                    float(inf.get('blend_fraction', 0.06)),
                    (u_lo, u_hi),
                )
            )
            self.regions.append(infarct_region(inf))
            self.infarct_segment = int(inf['aha_segment'])
        for r in check_regions(
            m.get('regions') or [], g, others=self.regions, where='motion.regions'
        ):
            w = r['blend_fraction']
            lo, hi = r['levels']
            # An open end takes the apex tip / the base plane in fully (b = 1 there).
            u_lo = -0.5 * w if lo == 0.0 else lo
            u_hi = 1.0 + 0.5 * w if hi == 1.0 else hi
            self._regions.append(
                (
                    1.0 - r['contraction'],
                    np.radians(r['centre_deg']),
                    np.radians(0.5 * r['width_deg']),
                    np.radians(r['blend_deg']),
                    w,
                    (u_lo, u_hi),
                )
            )
            self.regions.append(r)

    def _init_profile(self, m: dict) -> None:
        """
        Set the normal long-axis strain profile g(u) and each region's ``∫ g b`` (see the map).

        Prolate: ``g = ε_w − (ε_w + τ) h(u)``, ``h = 1`` through the solid apical wall up to
        ``u_c = min(u_tip, 0.1)`` (``u_tip`` the endocardial apex's level, 0.1 the AHA cap's
        top), 0 from ``u_c + w`` up (C² blend, ``w = APEX_BLEND_FRACTION``): the cap thickens
        axially by ``τ`` (``apex_thickening``), the wall above shortens by ``ε_w``, chosen so
        that the base still descends ``base_descent_mm``: ``ε_w (1 − H) − τ H = ε`` with
        ``H = ∫_0^1 h = u_c + w/2``.
        Cylinder (no apex cap), or no ``apex_thickening`` in the preset (the presets today, and
        the ground truth of studies simulated before the cap had a model, rebuilt from their
        stored preset): ``g = ε`` everywhere, every level shortens alike.

        Raises
        ------
        ValueError
            ``apex_thickening`` out of :data:`APEX_THICKENING_RANGE`, or a cap so thick that the
            wall above it would have to shorten by 100 % or more.

        """
        tau = m.get('apex_thickening')
        lo, hi = APEX_THICKENING_RANGE
        if tau is not None and (
            isinstance(tau, bool)
            or not isinstance(tau, (int, float))
            or not lo <= float(tau) <= hi
        ):
            raise ValueError(
                f'motion.apex_thickening = {tau!r}; allowed: a number {lo:g} … {hi:g} (the ES '
                'axial thickening of the apical wall, fraction of its ED thickness)'
            )
        if self.kind == 'prolate' and tau is not None:
            self.apex_thickening = float(tau)
            # The thickening slab: the solid wall below the endocardial apex, at most the AHA
            # cap's height; above that level a thick (hypertrophic) apical wall's flank is the
            # apical segments' oblique wall, which an axial stretch would lengthen in-wall.
            tip = (self.length - self.endo_c) / self.length
            x0, w = min(tip, AHA_LEVELS['apex'][1]), APEX_BLEND_FRACTION
            H = x0 + 0.5 * w
            self.eps_wall = (self.eps + self.apex_thickening * H) / (1.0 - H)
            if self.eps_wall >= 0.9:
                raise ValueError(
                    f'motion: base_descent_mm {self.eps * self.length:g} with apex_thickening '
                    f'{tau:g} of a {x0 * self.length:g} mm apical wall needs the wall above it '
                    f'to shorten by {100 * self.eps_wall:.0f} % (at most 90 %)'
                )
            gain = self.eps_wall + self.apex_thickening

            def g_piece(mid):
                return gain * _ramp_piece(x0, w, mid) - self.apex_thickening

            g_breaks = [x0, x0 + w]
        else:  # no cap model: every level shortens by ε (the map before the cap had one)
            self.apex_thickening = None
            self.eps_wall = self.eps

            def g_piece(mid):
                return Polynomial([self.eps])

            g_breaks = [0.0]
        self._g, self._G = _piecewise(g_piece, g_breaks)
        self._region_gb = []
        for reg in self._regions:
            w, (u_lo, u_hi) = reg[4], reg[5]
            a0, a1 = u_lo - 0.5 * w, u_hi - 0.5 * w  # b = ramp(a0) − ramp(a1), as _window

            def gb_piece(mid, a0=a0, a1=a1, w=w):
                return g_piece(mid) * (_ramp_piece(a0, w, mid) - _ramp_piece(a1, w, mid))

            self._region_gb.append(_piecewise(gb_piece, [*g_breaks, a0, a0 + w, a1, a1 + w]))

    # ----------------------------------------------------------------- time course
    def activation(self, phase) -> np.ndarray:
        """
        Activation ``s`` at a (fractional) phase: 0 at ED, 1 at ES, raised-cosine (C¹).

        Parameters
        ----------
        phase : float or array_like
            Phase index (0 = ED); periodic with ``num_phases``.

        """
        f = np.mod(np.asarray(phase, dtype=np.float64) / self.num_phases, 1.0)
        es, rel = self.es_fraction, self.relax_fraction
        rise = 0.5 * (1.0 - np.cos(np.pi * np.clip(f / es, 0.0, 1.0)))
        fall = 0.5 * (1.0 + np.cos(np.pi * np.clip((f - es) / rel, 0.0, 1.0)))
        return np.where(f <= es, rise, fall)

    # ----------------------------------------------------------------- ED geometry
    def endo_radius(self, z) -> np.ndarray:
        """ED endocardial radius at height z (mm; 0 where there is no cavity)."""
        z = np.asarray(z, dtype=np.float64)
        if self.kind == 'cylinder':
            return np.where((z >= 0) & (z <= self.length), self.r_in, 0.0)
        d = (self.length - np.minimum(z, self.length)) / self.endo_c
        return self.endo_a * np.sqrt(np.clip(1.0 - d * d, 0.0, None))

    def epi_radius(self, z, theta=0.0) -> np.ndarray:
        """ED epicardial radius at height z and angle θ (mm; septal bulge included)."""
        z = np.asarray(z, dtype=np.float64)
        if self.kind == 'cylinder':
            return np.where((z >= 0) & (z <= self.length), self.r_out, 0.0)
        d = (self.length - np.minimum(z, self.length)) / self.epi_c
        r = self.epi_a * np.sqrt(np.clip(1.0 - d * d, 0.0, None))
        if self.septal_extra:
            # cos²θ bump on the septal half, absent in the apical 15 %, full from 40 % up.
            bump = np.where(np.cos(theta) > 0, np.cos(theta) ** 2, 0.0)
            taper, _ = _smoothstep((z / self.length - 0.15) / 0.25)
            r = r + self.septal_extra * bump * taper
        return r

    def inside_myocardium(self, X_ed: np.ndarray) -> np.ndarray:
        """
        Whether ED points are myocardium.

        Parameters
        ----------
        X_ed : ndarray, shape (N, 3)
            ED positions, mm (LPS).

        Returns
        -------
        ndarray of bool, shape (N,)

        """
        r, th, z = self.frame.to_local(np.asarray(X_ed, dtype=np.float64).reshape(-1, 3))
        return (
            (z >= 0)
            & (z <= self.length)
            & (r <= self.epi_radius(z, th))
            & (r >= self.endo_radius(z))
        )

    def inside_blood(self, X_ed: np.ndarray) -> np.ndarray:
        """
        Whether ED points are blood: the LV cavity or the atrial cylinder above the base.

        Parameters
        ----------
        X_ed : ndarray, shape (N, 3)
            ED positions, mm.

        Returns
        -------
        ndarray of bool, shape (N,)

        """
        r, _, z = self.frame.to_local(np.asarray(X_ed, dtype=np.float64).reshape(-1, 3))
        cav = (z >= 0) & (z <= self.length) & (r < self.endo_radius(z))
        if self.atrium_height > 0:
            cav |= (z > self.length) & (z <= self.length + self.atrium_height) & (r < self.endo_a)
        return cav

    def tissue(self, X_ed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Return ``(myocardium, blood)`` at ED points as the images show them.

        Myocardium: :meth:`inside_myocardium` or the RV free wall; blood: :meth:`inside_blood`
        or RV blood (:meth:`inside_rv`). The same values, to the bit, from one change of frame
        and one endocardial radius instead of three and two.

        Parameters
        ----------
        X_ed : ndarray, shape (N, 3)
            ED positions, mm (LPS).

        Returns
        -------
        myocardium, blood : ndarray of bool, shape (N,)

        """
        r, th, z = self.frame.to_local(np.asarray(X_ed, dtype=np.float64).reshape(-1, 3))
        endo = self.endo_radius(z)
        lv = (z >= 0) & (z <= self.length)
        myo = lv & (r <= self.epi_radius(z, th)) & (r >= endo)
        blood = lv & (r < endo)
        if self.atrium_height > 0:
            top = self.length + self.atrium_height
            blood |= (z > self.length) & (z <= top) & (r < self.endo_a)
        if self.rv is not None:  # the RV's wall is tagged, its blood is not
            myo, blood = myo | self.rv.free_wall(r, th, z), blood | self.rv.blood(r, th, z)
        return myo, blood

    def inside_rv(self, X_ed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        Return ``(wall, blood)``: whether ED points are RV free wall and RV blood.

        ``X_ed`` (N, 3), mm; each result bool (N,) (all False without an RV;
        :mod:`mlv_ros.core.sim.rv`).
        """
        X = np.asarray(X_ed, dtype=np.float64).reshape(-1, 3)
        if self.rv is None:
            return np.zeros(len(X), bool), np.zeros(len(X), bool)
        r, th, z = self.frame.to_local(X)
        return self.rv.free_wall(r, th, z), self.rv.blood(r, th, z)

    def rv_insertions(self) -> dict | None:
        """
        Return the RV's true insertion points (None without an RV).

        Returns
        -------
        dict
            ``anterior_deg``, ``inferior_deg``: θ of the insertions in the local frame (deg, CCW
            seen from the apex, 0 at ``frame.septum``); ``anterior_direction``,
            ``inferior_direction``, ``septum_direction``: unit vectors ⟂ the long axis, LPS (the
            septum's is the bisector of the two insertions).

        """
        if self.rv is None:
            return None
        f = self.frame
        a, b = self.rv.insertions_deg

        def direction(deg):
            t = np.radians(deg)
            return (np.cos(t) * f.septum + np.sin(t) * f.e2).tolist()

        return {
            'anterior_deg': a,
            'inferior_deg': b,
            'anterior_direction': direction(a),
            'inferior_direction': direction(b),
            'septum_direction': direction(0.5 * (a + b)),
            'params': dict(self.rv.params),
        }

    def sample_myocardium(self, n: int, seed: int = 0) -> np.ndarray:
        """
        Uniform random ED myocardial points (rejection sampling in the bounding cylinder).

        Parameters
        ----------
        n : int
            Number of points.
        seed : int
            ``numpy.random.default_rng`` seed.

        Returns
        -------
        ndarray, shape (n, 3)
            ED positions, mm (LPS).

        """
        if n < 0:
            raise ValueError(f'n must be >= 0, got {n}')
        rng = np.random.default_rng(seed)
        out = np.empty((0, 3))
        R = self.max_radius
        while out.shape[0] < n:
            m = max(4 * (n - out.shape[0]), 1024)
            r = R * np.sqrt(rng.random(m))
            th = rng.uniform(-np.pi, np.pi, m)
            z = rng.uniform(0.0, self.length, m)
            x = self.frame.from_local(r, th, z)
            out = np.concatenate([out, x[self.inside_myocardium(x)]])
        return out[:n]

    # ----------------------------------------------------------------- map components
    def _ref_q(self, z):
        """
        Squared reference endocardial radius Q(z) = q · S(q/δ) with q = R_en², mm².

        Q ≤ R_en² and Q = 0 wherever the wall reaches the axis (below the endocardial apex), so
        ``r'² = ρ²Q + (r² − Q)/J₂ ≥ ρ²Q ≥ 0`` for all myocardium (the map never clamps there);
        the C² ramp S over δ = 0.02 a² keeps Q smooth at the endocardial apex.
        """
        if self.kind == 'cylinder':
            return np.full_like(z, self.r_in**2)
        d = (self.length - np.minimum(z, self.length)) / self.endo_c
        q = np.maximum(self.endo_a**2 * (1.0 - d * d), 0.0)
        return q * _smoothstep(q / self._q_soft)[0]

    @staticmethod
    def _window(region, theta, u):
        """Window a(θ), a'(θ), b(u), B(u) of one region (C² in θ and u; B = ∫_0^u b)."""
        _, centre, half, bt, w, (lo, hi) = region
        d = np.angle(np.exp(1j * (theta - centre)))  # wrapped to (−π, π]
        a, da = _smoothstep((half + 0.5 * bt - np.abs(d)) / bt)
        if half >= np.pi:  # a whole ring (the apex cap): every angle
            a, da = np.ones_like(theta), np.zeros_like(theta)
        else:
            da = -np.sign(d) * da / bt
        x0 = (u - lo + 0.5 * w) / w
        x1 = (u - hi + 0.5 * w) / w
        b = _smoothstep(x0)[0] - _smoothstep(x1)[0]
        B = w * (
            _smoothstep_integral(x0)
            - _smoothstep_integral((0.5 * w - lo) / w)
            - _smoothstep_integral(x1)
            + _smoothstep_integral((0.5 * w - hi) / w)
        )
        return a, da, b, B

    def _components(self, theta, z, s):
        """
        Twist φ, its z-derivative, Z, Z_z, Z_θ, J₂ and ρ at ED (θ, z) and activation s.

        Regions enter through sums over their windows (they do not overlap, so at most one
        term is non-zero anywhere). Without an apex profile each term keeps the single-infarct
        expression's operation order, so the infarct preset's motion is bit-identical to its
        one-region original; with one the heights come from the exact piecewise polynomials of
        :meth:`_init_profile`.
        """
        L = self.length
        u = z / L
        uc = np.clip(u, 0.0, 1.0)
        inside = (u > 0.0) & (u < 1.0)
        phi = s * self._twist(uc)
        dphi = np.where(inside, s * self._dtwist(uc) / L, 0.0)
        zero = np.zeros_like(u)
        if self.apex_thickening is None:
            # g = ε: the closed forms (C_i = ε B_i), bit-identical to the map before the apex
            # profile and cheaper than the piecewise polynomials (the imaging inverts per pixel).
            kab, kLaB, zt = zero, zero, zero
            for reg in self._regions:
                k = reg[0]
                a, da, b, B = self._window(reg, theta, u)
                kab = kab + k * a * b
                kLaB = kLaB + k * L * a * B
                zt = zt + s * self.eps * k * L * da * B
            Z = z - s * self.eps * (z - kLaB)
            Zz = 1.0 - s * self.eps * (1.0 - kab)
            Zt = zt
        else:
            kab, kagb, kaC, kdaC = zero, zero, zero, zero
            for reg, (gb, C) in zip(self._regions, self._region_gb):
                k = reg[0]
                a, da, b, _ = self._window(reg, theta, u)
                Cu = C(u)
                kab = kab + k * a * b
                kagb = kagb + k * a * gb(u)
                kaC = kaC + k * a * Cu
                kdaC = kdaC + k * da * Cu
            # Z = z − s L (G(u) − Σ k a C_i(u)), G = ∫_0^u g, C_i = ∫_0^u g b_i: the local axial
            # stretch is 1 − s g (1 − Σ k a b), the normal profile scaled by the contraction kept.
            Z = z - s * L * (self._G(u) - kaC)
            Zz = 1.0 - s * (self._g(u) - kagb)
            Zt = s * L * kdaC
        J2 = Zz - dphi * Zt
        rho = 1.0 - s * (1.0 - self.rho_es) * (1.0 - kab)
        return phi, dphi, Z, Zz, Zt, J2, rho

    def contraction(self, X_ed: np.ndarray) -> np.ndarray:
        """
        Prescribed share of the normal systolic motion kept at ED points.

        Parameters
        ----------
        X_ed : ndarray, shape (N, 3)
            ED positions, mm.

        Returns
        -------
        ndarray, shape (N,)
            ``1 − Σ k a b``: 1 normal, 0 akinetic, below 0 dyskinetic (smooth across blends).

        """
        _, th, z = self.frame.to_local(np.asarray(X_ed, dtype=np.float64).reshape(-1, 3))
        u = z / self.length
        c = np.ones_like(u)
        for reg in self._regions:
            a, _, b, _ = self._window(reg, th, u)
            c = c - reg[0] * a * b
        return c

    # ----------------------------------------------------------------- public map
    def _s(self, phase):
        s = np.asarray(self.activation(phase), dtype=np.float64)
        if s.ndim:
            raise ValueError('phase must be a scalar (int or float)')
        return float(s)

    def position(self, X_ed: np.ndarray, phase) -> np.ndarray:
        """
        Position at ``phase`` of material points given by their ED positions.

        Parameters
        ----------
        X_ed : ndarray, shape (N, 3) or (3,)
            ED positions, mm (LPS).
        phase : int or float
            Phase index (0 = ED), fractional allowed, periodic.

        Returns
        -------
        ndarray, same shape as ``X_ed``
            Positions, mm (LPS).

        """
        X = np.asarray(X_ed, dtype=np.float64)
        flat = X.reshape(-1, 3)
        s = self._s(phase)
        r, th, z = self.frame.to_local(flat)
        phi, _, Z, _, _, J2, rho = self._components(th, z, s)
        q = self._ref_q(z)
        r2 = np.maximum(rho * rho * q + (r * r - q) / J2, 0.0)
        return self.frame.from_local(np.sqrt(r2), th + phi, Z).reshape(X.shape)

    def inverse(self, x: np.ndarray, phase, tol: float = 1e-9, max_iter: int = 30) -> np.ndarray:
        """
        ED material position of the points at ``x`` at ``phase`` (inverse of :meth:`position`).

        Parameters
        ----------
        x : ndarray, shape (N, 3) or (3,)
            Positions at ``phase``, mm (LPS).
        phase : int or float
            Phase index.
        tol : float
            Newton tolerance on the height z, mm.
        max_iter : int
            Newton iteration cap.

        Returns
        -------
        ndarray, same shape as ``x``
            ED positions, mm. Exact inverse for points whose ED position is outside the
            forward map's clamp (``r'² = 0``), i.e. for all myocardium.

        """
        xa = np.asarray(x, dtype=np.float64)
        local = self.frame.to_local(xa.reshape(-1, 3))
        return self.inverse_local(local, phase, tol, max_iter).reshape(xa.shape)

    def inverse_local(
        self, local: tuple, phase, tol: float = 1e-9, max_iter: int = 30
    ) -> np.ndarray:
        """
        :meth:`inverse` of points given in the LV frame (``frame.to_local`` of them).

        The change of frame does not depend on the phase: a renderer that maps the same pixels
        at every phase computes it once (the same numbers as :meth:`inverse`, to the bit).

        Parameters
        ----------
        local : tuple of ndarray, each shape (N,)
            ``(r, θ, z)`` of the positions at ``phase``: mm, rad, mm.
        phase, tol, max_iter
            As :meth:`inverse`'s.

        Returns
        -------
        ndarray, shape (N, 3)
            ED positions, mm (LPS).

        """
        rp, thp, zp = local
        s = self._s(phase)
        # Z is monotone in z (J₂ > 0); start from the wall's uniform shortening, exact (one step)
        # for a heart without an apex profile or regions, where Z = (1 − sε) z.
        z = zp / (1.0 - s * self.eps_wall)
        linear = self.apex_thickening is None and not self._regions
        for _ in range(1 if linear else max_iter):
            th = thp - s * self._twist(np.clip(z / self.length, 0.0, 1.0))
            _, _, Z, _, _, J2, _ = self._components(th, z, s)
            step = (Z - zp) / J2
            z = z - step
            if np.max(np.abs(step), initial=0.0) < tol:
                break
        th = thp - s * self._twist(np.clip(z / self.length, 0.0, 1.0))
        _, _, _, _, _, J2, rho = self._components(th, z, s)
        q = self._ref_q(z)
        r2 = np.maximum(q + J2 * (rp * rp - rho * rho * q), 0.0)
        return self.frame.from_local(np.sqrt(r2), th, z)

    def deformation_gradient(self, X_ed: np.ndarray, phase, h: float = 1e-3) -> np.ndarray:
        """
        Deformation gradient ``F = ∂x/∂X`` at ED points.

        Central differences of the analytic map (step ``h`` mm, truncation error O(h²) ≈ 1e-8):
        the closed form in cylindrical coordinates is singular on the axis, which the apical cap
        crosses, while the Cartesian map is smooth there.

        Parameters
        ----------
        X_ed : ndarray, shape (N, 3)
            ED positions, mm.
        phase : int or float
            Phase index.
        h : float
            Difference step, mm.

        Returns
        -------
        ndarray, shape (N, 3, 3)
            ``F[n, i, j] = ∂x_i/∂X_j`` (dimensionless).

        """
        X = np.asarray(X_ed, dtype=np.float64).reshape(-1, 3)
        F = np.empty((X.shape[0], 3, 3))
        for j in range(3):  # three axes, not a loop over points
            d = np.zeros(3)
            d[j] = h
            F[:, :, j] = (self.position(X + d, phase) - self.position(X - d, phase)) / (2 * h)
        return F

    def displacement(self, X_ed: np.ndarray, phase) -> np.ndarray:
        """``position(X_ed, phase) − X_ed``, shape like ``X_ed``, mm."""
        return self.position(X_ed, phase) - np.asarray(X_ed, dtype=np.float64)

    # ----------------------------------------------------------------- ground-truth curves
    def twist_deg(self, level, phase) -> np.ndarray:
        """
        Prescribed rotation about the long axis of the material at ED level ``level``.

        Parameters
        ----------
        level : float or array_like
            Fraction of the length from the apex (0 apex, 1 base plane).
        phase : int or float
            Phase index.

        Returns
        -------
        ndarray, shape of ``level``
            Degrees, counter-clockwise seen from the apex positive.

        """
        u = np.clip(np.asarray(level, dtype=np.float64), 0.0, 1.0)
        return np.degrees(self._s(phase) * self._twist(u))

    def level_curves(self, levels, phases=None, n_theta: int = 72) -> dict:
        """
        Per-level twist, radii and thickness measured on forward-mapped rings of material.

        Rings of ``n_theta`` ED points at the endocardium, mid-wall and epicardium of each level
        are moved with :meth:`position`; angles and radii are measured about the (fixed) long
        axis, so these numbers check the map rather than restate its parameters.

        Parameters
        ----------
        levels : array_like, shape (K,)
            Fractions of the length from the apex, in [0, 1].
        phases : array_like of shape (P,), optional
            Phase indices; all phases by default.
        n_theta : int
            Ring resolution.

        Returns
        -------
        dict of ndarray
            ``levels`` (K,), ``phases`` (P,), ``twist_deg`` (P, K) mean rotation of the mid-wall
            ring (CCW from apex positive), ``endo_radius_mm``, ``epi_radius_mm``,
            ``mid_radius_mm``, ``thickness_mm`` (P, K) ring means (endo is 0 below the cavity),
            ``height_mm`` (P, K) mean height of the mid-wall ring above the apex.

        """
        lv = np.atleast_1d(np.asarray(levels, dtype=np.float64))
        ph = (
            np.arange(self.num_phases)
            if phases is None
            else np.atleast_1d(np.asarray(phases, float))
        )
        th = np.linspace(-np.pi, np.pi, n_theta, endpoint=False)
        TH, U = np.meshgrid(th, lv)  # (K, n_theta)
        Z = U * self.length
        r_en = self.endo_radius(Z)
        r_ep = self.epi_radius(Z, TH)
        r_mid = 0.5 * (r_en + r_ep)
        pts = np.concatenate(
            [
                self.frame.from_local(rr.ravel(), TH.ravel(), Z.ravel())
                for rr in (r_en, r_mid, r_ep)
            ]
        )
        n = TH.size
        out = {
            k: np.empty((ph.size, lv.size))
            for k in (
                'twist_deg',
                'endo_radius_mm',
                'epi_radius_mm',
                'mid_radius_mm',
                'thickness_mm',
                'height_mm',
            )
        }
        for i, p in enumerate(ph):
            r, t, z = self.frame.to_local(self.position(pts, p))
            r = r.reshape(3, *TH.shape)
            dth = np.angle(np.exp(1j * (t[n:2 * n].reshape(TH.shape) - TH)))
            out['twist_deg'][i] = np.degrees(dth.mean(axis=1))
            out['endo_radius_mm'][i] = r[0].mean(axis=1)
            out['mid_radius_mm'][i] = r[1].mean(axis=1)
            out['epi_radius_mm'][i] = r[2].mean(axis=1)
            out['thickness_mm'][i] = (r[2] - r[0]).mean(axis=1)
            out['height_mm'][i] = z[n:2 * n].reshape(TH.shape).mean(axis=1)
        out['levels'] = lv
        out['phases'] = ph
        return out

    def base_descent_mm(self, phase) -> float:
        """Mean displacement of the base-plane mid-wall ring toward the apex, mm."""
        c = self.level_curves([1.0], [phase])
        return float(self.length - c['height_mm'][0, 0])


def make_motion(preset, num_phases: int | None = None) -> LVMotion:
    """Build a preset's ground-truth motion (name, YAML path or dict); see :class:`LVMotion`."""
    return LVMotion(preset, num_phases=num_phases)
