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
A right ventricle for the phantom: a crescent of blood with a thin tagged free wall.

The RV only has to be *seen* (its blood pool and where its wall meets the LV, the RV insertion
points that anchor the AHA segments); it is not part of the ground-truth myocardium, which stays
the LV. Its geometry is written in the ED local frame of :mod:`mlv_ros.core.sim.motion`
(``θ`` CCW seen from the apex, 0 at the mid-septum, ``u = z / L``):

* angular span: ``|θ − centre| ≤ span / 2``; the anterior insertion is at ``centre − span/2``
  (toward θ = −90°, anterior) and the inferior one at ``centre + span/2``;
* blood: ``R_epi(z, θ) < r < R_epi + t(θ, u)`` with the crescent's depth
  ``t = D(u) · sqrt(1 − ((θ − centre) / (span/2))²)``, ``D(u) = depth · S((u − u_0) / 0.25)``
  (``S`` a smoothstep from 0 to 1, ``u_0`` = ``apex_level``: the RV ends above the LV apex);
* free wall: ``R_epi + t < r < R_epi + t + w`` with ``w = min(wall, D(u))`` over the same span, so
  at the insertion points (t = 0) the wall meets the LV epicardium;
* nothing above the base plane (``u ≤ 1``).

Motion: RV material moves with the LV map (every ED point does, see the motion module): it
twists, descends and is drawn inward with the LV, which is plausible, not RV mechanics.
Intensities: the wall is tagged like myocardium, the blood untagged like the LV's
(:class:`mlv_ros.core.sim.imaging.ImageSynthesizer`).
"""

from __future__ import annotations

import math

import numpy as np

#: Defaults of ``geometry.rv`` (mm, degrees, fraction of the LV length).
RV_DEFAULTS = {
    'span_deg': 120.0,
    'centre_deg': 0.0,
    'depth_scale': 0.6,
    'wall_mm': 3.0,
    'apex_level': 0.2,
}
#: Accepted ranges of the ``geometry.rv`` keys.
RV_RANGES = {
    'span_deg': (60.0, 200.0),
    'centre_deg': (-90.0, 90.0),
    'depth_scale': (0.2, 1.2),
    'wall_mm': (1.0, 8.0),
    'apex_level': (0.0, 0.7),
}
_RAMP = 0.25  # level span of the RV's apical taper


def check_rv(rv, where: str = 'geometry.rv') -> dict | None:
    """
    ``geometry.rv`` with defaults filled in (None / False: no RV; True or {}: the defaults).

    Keys: ``span_deg`` (angle between the insertion points, deg), ``centre_deg`` (centre of the
    span from the mid-septum, CCW seen from the apex, deg), ``depth_scale`` (the crescent's
    largest depth as a share of the LV epicardial base radius), ``wall_mm`` (free-wall thickness,
    mm), ``apex_level`` (level 0 apex … 1 base where the RV begins).

    Raises
    ------
    ValueError
        An unknown key or a value outside :data:`RV_RANGES`.

    """
    if rv is None or rv is False:
        return None
    if rv is True:
        rv = {}
    if not isinstance(rv, dict):
        raise ValueError(f'{where} must be a mapping, true or null, got {rv!r}')
    unknown = sorted(set(rv) - set(RV_DEFAULTS))
    if unknown:
        raise ValueError(f'{where}: unknown key(s) {unknown}; known: {sorted(RV_DEFAULTS)}')
    out = dict(RV_DEFAULTS)
    for k, v in rv.items():
        lo, hi = RV_RANGES[k]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= float(v) <= hi:
            raise ValueError(f'{where}.{k} must be a number in [{lo:g}, {hi:g}], got {v!r}')
        out[k] = float(v)
    return out


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


class RightVentricle:
    """
    RV geometry of one phantom (module docstring).

    Parameters
    ----------
    rv : dict
        :func:`check_rv` output.
    length : float
        LV length, mm.
    epi_radius : callable
        ``(z, θ) → R_epi`` of the LV, mm.
    base_radius : float
        LV epicardial radius at the base, mm (scales the depth).

    """

    def __init__(self, rv: dict, length: float, epi_radius, base_radius: float):
        self.params = dict(rv)
        self.length = float(length)
        self._epi = epi_radius
        self.half = math.radians(rv['span_deg']) / 2.0
        self.centre = math.radians(rv['centre_deg'])
        self.depth = rv['depth_scale'] * float(base_radius)
        self.wall = rv['wall_mm']
        self.u0 = rv['apex_level']
        #: Farthest the RV reaches from the long axis at ED, mm (beyond the LV's own radius).
        self.extent_mm = self.depth + self.wall

    @property
    def insertions_deg(self) -> tuple[float, float]:
        """θ of the anterior and inferior insertion points (local frame, deg)."""
        c, h = math.degrees(self.centre), math.degrees(self.half)
        return c - h, c + h

    def _layers(self, r, th, z):
        """(inside the span and levels, R_epi, crescent depth t, wall thickness w)."""
        d = np.angle(np.exp(1j * (th - self.centre)))  # wrapped to (−π, π]
        u = z / self.length
        D = self.depth * _smoothstep((u - self.u0) / _RAMP)
        inside = (np.abs(d) <= self.half) & (u <= 1.0) & (D > 0.0)
        t = D * np.sqrt(np.clip(1.0 - (d / self.half) ** 2, 0.0, None))
        return inside, self._epi(z, th), t, np.minimum(self.wall, D)

    def blood(self, r, th, z) -> np.ndarray:
        """Whether local ED points ``(r, θ, z)`` lie in the RV cavity."""
        inside, R, t, _ = self._layers(r, th, z)
        return inside & (r > R) & (r < R + t)

    def free_wall(self, r, th, z) -> np.ndarray:
        """Whether local ED points lie in the RV free wall."""
        inside, R, t, w = self._layers(r, th, z)
        return inside & (r >= R + t) & (r < R + t + w) & (r > R)
