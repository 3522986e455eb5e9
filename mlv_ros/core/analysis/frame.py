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
LV long-axis frame and per-particle cardiac coordinates.

Conventions (all in DICOM patient coordinates, mm)
---------------------------------------------------
* ``axis`` (``e_l``) is the unit long axis from the apex to the base centre. The normalised
  level ``h = (X − apex)·axis / length`` is 0 at the apex and 1 at the base plane.
  Longitudinal displacement is positive toward the base (MotionMetrics.msg).
* ``e1`` is the reference direction (circumferential angle 0) made orthogonal to the axis;
  by default it points at the inferior RV–LV junction, the origin of the paper's angle β
  (§2.1). ``e2 = e1 × axis``.
* The circumferential angle ``θ = atan2((X−apex)·e2, (X−apex)·e1)`` increases
  **counter-clockwise seen from the apex looking toward the base** (method notes). Check: a
  viewer at the apex looks along +axis; a right-handed rotation about +axis looks clockwise to
  that viewer, so CCW-from-apex is a right-handed rotation about −axis, which carries e1 to
  ``(−axis) × e1 = e1 × axis = e2``.
* ``e_r`` points from the long axis outward; ``e_c = e_r × e_l`` is the direction of
  increasing θ, so positive circumferential displacement and positive twist agree. (The
  tempting ``e_l × e_r`` is clockwise from the apex.) With e_l apex → base the triple
  (e_r, e_c, e_l) is left-handed; it is the right-handed (R, C, L) triple of the tagging
  literature with L flipped to point toward the base. Normal strains do not depend on the
  handedness; the signs of the shears E_rl and E_cl do, and follow these vectors.
* AHA angles: ``aha_origin_deg`` is θ of the anterior RV–LV insertion. Seen from the apex the
  septum runs counter-clockwise from the anterior to the inferior insertion and spans 120°,
  so with the default reference (inferior junction, θ = 0) the anterior insertion is at
  θ = −120°. If your reference points at the mid-septum instead, pass ``aha_origin_deg=-60``.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

from mlv_ros.core.meshless.globals import quat_to_matrix
import numpy as np

_AXIS_TOL = 1e-6  # mm: apex and base must be distinct
_PARALLEL_TOL = 1e-3  # |sin| between reference and axis below which the reference is unusable
# Twist error per 0.1 of the LV's length by which a level lies beyond the SA slices with tag
# points (twist_extrapolation_note), apical and basal: the largest ES error over distance of the
# extrapolated levels on 24 randomized-protocol studies (bench/retrack.py --twist), degrees.
TWIST_EXTRAPOLATION_DEG_PER_TENTH = {'apical': 2.4, 'basal': 0.6}


def as_points(a, name: str, *, allow_empty: bool = False) -> np.ndarray:
    """
    Validate and return a float64 array of shape (N, 3) with finite entries.

    Raises
    ------
    ValueError
        On a wrong shape, an empty array (unless ``allow_empty``) or a NaN/inf entry; the
        message names the argument and the first bad row.

    """
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f'{name} must have shape (N, 3), got {arr.shape}')
    if arr.shape[0] == 0 and not allow_empty:
        raise ValueError(f'{name} is empty (0 points)')
    bad = ~np.all(np.isfinite(arr), axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f'{name} has {int(bad.sum())} non-finite rows (first: row {i} = {arr[i]})'
        )
    return arr


def _vec3(v, name: str) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(-1)
    if v.shape != (3,):
        raise ValueError(f'LVFrame.{name} must have 3 components, got {v.shape[0]}')
    if not np.all(np.isfinite(v)):
        raise ValueError(f'LVFrame.{name} is not finite: {v}')
    return v


@dataclass(frozen=True)
class LVFrame:
    """
    Long-axis frame of the LV at end-diastole.

    Parameters
    ----------
    apex : array_like, shape (3,)
        Apex point (level 0), mm, patient coordinates.
    base : array_like, shape (3,)
        Centre of the basal (mitral) plane (level 1), mm.
    reference : array_like, shape (3,)
        Direction of circumferential angle 0 (default: toward the inferior RV–LV junction,
        the paper's β = 0). Need not be unit or orthogonal to the axis; its axial part is
        removed.
    aha_origin_deg : float
        Circumferential angle θ (degrees, CCW from the apex) of the anterior RV–LV insertion,
        the origin of the AHA segment angles. Default −120° (see the module docstring).

    Attributes
    ----------
    axis : ndarray, shape (3,)
        Unit long axis apex → base (``e_l``).
    length : float
        ED apex–base distance, mm.
    e1, e2 : ndarray, shape (3,)
        In-plane basis: e1 = reference ⟂ axis (θ = 0), e2 = e1 × axis (θ = +90°).

    """

    apex: np.ndarray
    base: np.ndarray
    reference: np.ndarray
    aha_origin_deg: float = -120.0

    def __post_init__(self):
        for name in ('apex', 'base', 'reference'):
            object.__setattr__(self, name, _vec3(getattr(self, name), name))
        d = self.base - self.apex
        length = float(np.linalg.norm(d))
        if length < _AXIS_TOL:
            raise ValueError(f'LVFrame apex and base coincide (distance {length:.3g} mm)')
        axis = d / length
        rn = float(np.linalg.norm(self.reference))
        if rn == 0.0:
            raise ValueError('LVFrame.reference is the zero vector')
        r = self.reference / rn
        perp = r - (r @ axis) * axis
        pn = float(np.linalg.norm(perp))
        if pn < _PARALLEL_TOL:
            raise ValueError(
                'LVFrame.reference is parallel to the long axis; it must point across it'
            )
        e1 = perp / pn
        aha = float(self.aha_origin_deg)
        if not np.isfinite(aha):
            raise ValueError(f'LVFrame.aha_origin_deg must be finite, got {aha}')
        object.__setattr__(self, 'aha_origin_deg', aha)
        object.__setattr__(self, 'axis', axis)
        object.__setattr__(self, 'length', length)
        object.__setattr__(self, 'e1', e1)
        object.__setattr__(self, 'e2', np.cross(e1, axis))

    # -- projections -------------------------------------------------------------------------
    def axial(self, points: np.ndarray) -> np.ndarray:
        """Signed distance along the long axis from the apex, mm; shape (N,)."""
        return (np.asarray(points, dtype=np.float64) - self.apex) @ self.axis

    def level(self, points: np.ndarray) -> np.ndarray:
        """Normalised level ``h`` (0 apex … 1 base; not clipped), shape (N,)."""
        return self.axial(points) / self.length

    def inplane(self, points: np.ndarray) -> np.ndarray:
        """Coordinates (ξ, η) along (e1, e2) in the plane ⟂ axis through the apex; (N, 2) mm."""
        p = np.asarray(points, dtype=np.float64) - self.apex
        return np.stack([p @ self.e1, p @ self.e2], axis=-1)

    def to_dict(self) -> dict:
        """JSON-friendly dict (lists of floats); inverse of :meth:`from_dict`."""
        return {
            'apex': self.apex.tolist(),
            'base': self.base.tolist(),
            'reference': self.reference.tolist(),
            'aha_origin_deg': self.aha_origin_deg,
        }

    @classmethod
    def from_dict(cls, d: dict) -> 'LVFrame':
        return cls(d['apex'], d['base'], d['reference'], d.get('aha_origin_deg', -120.0))


@dataclass
class CardiacCoordinates:
    """
    Per-particle cardiac coordinates at ED (see :func:`cardiac_coordinates`).

    Attributes
    ----------
    h : ndarray, shape (N,)
        Normalised level, 0 apex … 1 base (not clipped).
    axial : ndarray, shape (N,)
        Distance from the apex along the axis, mm.
    theta : ndarray, shape (N,)
        Circumferential angle, rad in (−π, π], CCW from the apex, 0 at the reference.
    rho : ndarray, shape (N,)
        Distance from the long axis, mm.
    xi, eta : ndarray, shape (N,)
        In-plane coordinates along e1, e2, mm.
    e_r, e_c, e_l : ndarray, shape (N, 3)
        Radial, circumferential, longitudinal unit vectors. Particles on the axis
        (ρ < 1e-9 mm) get e_r = e1.
    transmural : ndarray, shape (N,)
        0 at the endocardium … 1 at the epicardium (see :func:`cardiac_coordinates`).

    """

    h: np.ndarray
    axial: np.ndarray
    theta: np.ndarray
    rho: np.ndarray
    xi: np.ndarray
    eta: np.ndarray
    e_r: np.ndarray
    e_c: np.ndarray
    e_l: np.ndarray
    transmural: np.ndarray


def cardiac_coordinates(
    X, frame: LVFrame, *, endo_radius=None, epi_radius=None, levels: int = 10, angle_bins: int = 12
) -> CardiacCoordinates:
    """
    Cardiac coordinates of ED positions.

    Parameters
    ----------
    X : array_like, shape (N, 3)
        ED positions, mm.
    frame : LVFrame
        Long-axis frame of the LV at ED (apex, long axis, circumferential reference).
    endo_radius, epi_radius : float or array_like of shape (N,), optional
        Endo- and epicardial radii (distance from the long axis, mm) at each particle, e.g.
        from the model's transmural coordinate. If both are given,
        ``transmural = (ρ − endo)/(epi − endo)`` clipped to [0, 1]. Otherwise the radius is
        normalised per (level, angle) bin: ``(ρ − min)/(max − min)`` over the bin's particles
        (0 for a bin with a single radius).
    levels, angle_bins : int
        Bins used by the per-bin normalisation.

    Returns
    -------
    CardiacCoordinates

    """
    X = as_points(X, 'X')
    a = frame.axis
    axial = frame.axial(X)
    ie = frame.inplane(X)
    xi, eta = ie[:, 0], ie[:, 1]
    rho = np.hypot(xi, eta)
    theta = np.arctan2(eta, xi)
    on_axis = rho < 1e-9
    safe = np.where(on_axis, 1.0, rho)
    cr = np.where(on_axis, 1.0, xi / safe)
    sr = np.where(on_axis, 0.0, eta / safe)
    e_r = np.outer(cr, frame.e1) + np.outer(sr, frame.e2)
    # e_c = e_r × e_l: in (e1, e2) coordinates a +90° turn, (c, s) -> (−s, c).
    e_c = np.outer(-sr, frame.e1) + np.outer(cr, frame.e2)
    e_l = np.broadcast_to(a, X.shape).copy()

    if endo_radius is not None and epi_radius is not None:
        endo = np.broadcast_to(np.asarray(endo_radius, dtype=np.float64), rho.shape)
        epi = np.broadcast_to(np.asarray(epi_radius, dtype=np.float64), rho.shape)
        if not (np.all(np.isfinite(endo)) and np.all(np.isfinite(epi))):
            raise ValueError('endo_radius/epi_radius must be finite')
        if np.any(epi <= endo):
            raise ValueError('epi_radius must exceed endo_radius at every particle')
        transmural = np.clip((rho - endo) / (epi - endo), 0.0, 1.0)
    else:
        key = level_bin(axial / frame.length, levels) * angle_bins + angle_bin(theta, angle_bins)
        nb = levels * angle_bins
        lo = np.full(nb, np.inf)
        hi = np.full(nb, -np.inf)
        np.minimum.at(lo, key, rho)
        np.maximum.at(hi, key, rho)
        span = hi[key] - lo[key]
        transmural = np.where(span > 0, (rho - lo[key]) / np.where(span > 0, span, 1.0), 0.0)
    return CardiacCoordinates(
        h=axial / frame.length,
        axial=axial,
        theta=theta,
        rho=rho,
        xi=xi,
        eta=eta,
        e_r=e_r,
        e_c=e_c,
        e_l=e_l,
        transmural=transmural,
    )


#: Level bins of the apical half (0 … 0.5 of the length) the epicardial profile is read in.
PROFILE_BINS = 20


def wall_normal_frame(coords: CardiacCoordinates, length: float) -> tuple:
    """
    Wall-normal frame of ED particles from the LV's epicardial profile.

    Near the apex the wall turns until it is perpendicular to the long axis, so the cylindrical
    radial direction is no longer transmural: there it measures in-wall stretch, and the
    longitudinal one measures thickening. This frame follows the wall instead. The epicardium's
    profile is read from the particles of the apical half: in each of :data:`PROFILE_BINS` level
    bins (at least 10 particles) the mean axial position and mean ρ² of the particles at or
    beyond the bin's 90th percentile of ρ. A quadratic ``P(z) = a + b z + c z²`` is fitted to
    ρ² (exact for a spheroid, a sphere, a cylinder). The wall's surfaces are taken as the level
    sets of ``ρ² − P(z)``; their normal ``e_n ∝ 2ρ e_r − P'(z) e_l`` is e_r where the wall is
    parallel to the axis (a cylinder everywhere) and −e_l at the apex tip. With fewer than 3
    profile bins the frame is the cylindrical one.

    Parameters
    ----------
    coords : CardiacCoordinates
        ED cardiac coordinates of the particles (:func:`cardiac_coordinates`).
    length : float
        ED apex–base length, mm (``LVFrame.length``).

    Returns
    -------
    e_n, e_c, e_m : ndarray, shape (N, 3)
        Unit wall normal (outward), circumferential (``coords.e_c``, in the wall) and meridional
        in-wall direction ``e_m = e_c × e_n`` (e_l where the wall is parallel to the axis).

    Raises
    ------
    ValueError
        ``length`` not positive and finite.

    """
    length = float(length)
    if not (math.isfinite(length) and length > 0.0):
        raise ValueError(f'length must be positive and finite, got {length}')
    z, rho = coords.axial, coords.rho
    zs, r2s = [], []
    edges = np.linspace(0.0, 0.5 * length, PROFILE_BINS + 1)
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (z >= lo) & (z < hi)
        if np.count_nonzero(m) < 10:
            continue
        outer = m & (rho >= np.percentile(rho[m], 90))
        zs.append(float(np.mean(z[outer])))
        r2s.append(float(np.mean(rho[outer] ** 2)))
    if len(zs) < 3:
        return coords.e_r.copy(), coords.e_c, coords.e_l.copy()
    c2, c1, _ = np.polyfit(np.asarray(zs) / length, np.asarray(r2s) / length**2, 2)
    nr = 2.0 * rho / length
    nl = -(c1 + 2.0 * c2 * z / length)
    norm = np.hypot(nr, nl)
    flat = norm < 1e-12
    nr = np.where(flat, 1.0, nr / np.where(flat, 1.0, norm))
    nl = np.where(flat, 0.0, nl / np.where(flat, 1.0, norm))
    e_n = nr[:, None] * coords.e_r + nl[:, None] * coords.e_l
    e_m = np.cross(coords.e_c, e_n)
    return e_n, coords.e_c, e_m


_BIN_EPS = 1e-9  # in bin units: a point this close below a boundary goes to the upper bin


def level_bin(h: np.ndarray, levels: int) -> np.ndarray:
    """
    Return the bin index 0 … levels−1 of normalised level ``h``.

    Equal bins on [0, 1]; values outside are clipped into the end bins. Points within 1e-9 bin
    widths of a boundary go to the upper bin, so a lattice layer lying exactly on a boundary is not
    split between two bins by rounding.
    """
    if int(levels) < 1:
        raise ValueError(f'levels must be >= 1, got {levels}')
    return np.clip(np.floor(np.asarray(h) * levels + _BIN_EPS).astype(np.int64), 0, levels - 1)


def angle_bin(theta: np.ndarray, bins: int) -> np.ndarray:
    """Bin index 0 … bins−1 of angle θ (rad), bin 0 starting at θ = 0, increasing CCW."""
    if int(bins) < 1:
        raise ValueError(f'angle bins must be >= 1, got {bins}')
    t = np.mod(np.asarray(theta), 2 * np.pi)
    return np.minimum((t * (bins / (2 * np.pi))).astype(np.int64), bins - 1)


def estimate_frame(points, reference=None, *, end_fraction: float = 0.15) -> LVFrame:
    """
    Fallback LV frame from an ED point cloud when no landmarks are known.

    The long axis is the principal axis of largest variance. Of its two ends, the base is the
    one where the particles in the outer ``end_fraction`` of the axial extent lie farther from
    the axis (the basal ring is open and wide, the apex tapers). Apex and base are the points
    of the axis (through the centroid) at the extreme axial projections of the cloud.

    Parameters
    ----------
    points : array_like, shape (N, 3)
        ED positions, mm; N >= 4.
    reference : array_like, shape (3,), optional
        Circumferential reference direction. If None, the second principal axis is used, which
        has no anatomical meaning: AHA segment orientation is then arbitrary.
    end_fraction : float
        Fraction of the axial extent at each end whose particles' mean distance from the axis
        decides which end is the base (default 0.15).

    Returns
    -------
    LVFrame

    """
    X = as_points(points, 'points')
    if X.shape[0] < 4:
        raise ValueError(f'estimate_frame needs at least 4 points, got {X.shape[0]}')
    c = X.mean(axis=0)
    _, s, vt = np.linalg.svd(X - c, full_matrices=False)
    if s[0] <= 0:
        raise ValueError('estimate_frame: points are all identical')
    a = vt[0]
    t = (X - c) @ a
    lo, hi = t.min(), t.max()
    span = hi - lo
    radial = np.linalg.norm((X - c) - np.outer(t, a), axis=1)
    low_end = t <= lo + end_fraction * span
    high_end = t >= hi - end_fraction * span
    if radial[low_end].mean() > radial[high_end].mean():
        a, t, lo, hi = -a, -t, -hi, -lo
        low_end, high_end = high_end, low_end
    apex = c + lo * a
    base = c + hi * a
    ref = vt[1] if reference is None else reference
    return LVFrame(apex, base, ref)


def plane_level_span(frame: LVFrame, planes) -> tuple[float, float] | None:
    """
    Levels (0 apex → 1 base) at which image planes cross the ED long axis.

    Twist is circumferential motion, which only short-axis tags measure (a long-axis view holds
    the axis, so its tags move with twist only through-plane). Beyond the SA planes that hold tag
    points, twist and torsion are extrapolated by the solver's twist function, not measured.

    Parameters
    ----------
    frame : LVFrame
        ED long-axis frame (level ``h = (X − apex)·axis / length``).
    planes : iterable of (point, normal)
        A point on each plane (e.g. DICOM ImagePositionPatient) and its normal, mm /
        any length, patient coordinates. Planes parallel to the axis (within 1e-6) are skipped.

    Returns
    -------
    (float, float) or None
        Lowest and highest level crossed (may lie outside [0, 1]); None without a crossing plane.

    Raises
    ------
    ValueError
        A point or normal without 3 finite components.

    """
    levels = []
    for point, normal in planes:
        p, n = _vec3(point, 'plane point'), _vec3(normal, 'plane normal')
        along = float(frame.axis @ n)
        if abs(along) > 1e-6 * max(float(np.linalg.norm(n)), 1e-300):
            levels.append(float((p - frame.apex) @ n / along) / frame.length)
    return (min(levels), max(levels)) if levels else None


def levels_outside(level_position, span, levels: int | None = None) -> np.ndarray:
    """
    Which level bins lie beyond ``span`` (:func:`plane_level_span`) by more than half a bin.

    Parameters
    ----------
    level_position : array_like, shape (L,)
        Level bin centres, 0 apex → 1 base (``MotionMetrics.level_position``).
    span : (float, float) or None
        Measured levels; None = nothing measured (every bin outside).
    levels : int, optional
        Number of bins on [0, 1] (half a bin is the tolerance); default ``len(level_position)``.

    Returns
    -------
    ndarray of bool, shape (L,)

    """
    pos = np.asarray(level_position, dtype=np.float64).reshape(-1)
    if span is None:
        return np.ones(pos.shape, bool)
    half = 0.5 / max(int(levels or pos.size), 1)
    return (pos < span[0] - half) | (pos > span[1] + half)


def twist_extrapolation_bound(level_position, span, levels: int | None = None) -> np.ndarray:
    """
    Return the twist uncertainty a run states for each level bin, degrees (0 where measured).

    The rate part of :func:`twist_extrapolation_note`'s sentence, per level: a bin beyond the SA
    span by more than half a bin (:func:`levels_outside`) is uncertain by
    ``TWIST_EXTRAPOLATION_DEG_PER_TENTH`` (apical or basal) per 0.1 of the length its centre lies
    beyond the span. The run's sentence adds the study's own gradient noise, so this is the
    least it states: an error within it is one the run said it might make.

    Parameters
    ----------
    level_position : array_like, shape (L,)
        Level bin centres, 0 apex → 1 base.
    span : (float, float) or None
        Measured levels (:func:`plane_level_span`); None = nothing measured (every bin
        unbounded: ``inf``).
    levels : int, optional
        Number of bins on [0, 1]; default ``len(level_position)``.

    Returns
    -------
    ndarray, shape (L,)
        Stated uncertainty per bin, degrees.

    """
    pos = np.asarray(level_position, dtype=np.float64).reshape(-1)
    if span is None:
        return np.full(pos.shape, np.inf)
    out = levels_outside(pos, span, levels)
    below = np.maximum(span[0] - pos, 0.0) * TWIST_EXTRAPOLATION_DEG_PER_TENTH['apical']
    above = np.maximum(pos - span[1], 0.0) * TWIST_EXTRAPOLATION_DEG_PER_TENTH['basal']
    return np.where(out, (below + above) / 0.1, 0.0)


def twist_extrapolation_note(span, levels: int = 10, gradient_se=None) -> str:
    """
    Say what of the reported twist is extrapolated, how far and how uncertain, in one sentence.

    Beyond the SA slices the solver continues the measured twist linearly in height
    (:meth:`mlv_ros.core.tracking.MotionTracker._twist_function`): what is not measured there is
    the gradient, so the error grows with the distance beyond the slices, the *lever*. The
    sentence names, per end, how far the farthest level bin's centre lies beyond the span (in
    fractions of the LV's length) and the error such a lever had on the randomized-protocol
    studies (``TWIST_EXTRAPOLATION_DEG_PER_TENTH`` per 0.1 of the length, the largest measured
    at that end; their truth's twist steepens toward the apex, and the bound also holds for
    linear profiles and ones that flatten there: ``test_tracking.py``,
    ``test_extrapolated_twist_stays_within_its_stated_uncertainty``). That rate is the truth's
    bend beyond the slices; the gradient's own noise in this study (``gradient_se``, from its SA
    slices' scatter: :func:`mlv_ros.core.tracking._end_intervals`) adds two standard errors times
    the lever.

    Parameters
    ----------
    span : (float, float) or None
        Levels the SA planes with tag points cross (:func:`plane_level_span`); None = no SA
        data (the twist function then stays at the global twist factor).
    levels : int
        Level bins of the analysis on [0, 1] (the motion analyzer's ``levels``).
    gradient_se : (float, float), optional
        Standard errors of the apical and the basal end gradient the solver measured at the
        phase of its steepest twist (where the peak twist is), radians per LV length; None =
        not known (the rate alone).

    Returns
    -------
    str
        '' when every level bin is within half a bin of the span.

    """
    if span is None:
        return (
            'no SA slice holds tag points: twist and torsion are not measured at any level '
            '(only short-axis tags see circumferential motion)'
        )
    centres = (np.arange(int(levels)) + 0.5) / int(levels)
    out = levels_outside(centres, span, levels)
    ends = []
    for name, side, lever, where, se in (
        ('apical', centres < span[0], span[0] - centres, 'below', gradient_se and gradient_se[0]),
        ('basal', centres > span[1], centres - span[1], 'above', gradient_se and gradient_se[1]),
    ):
        if np.any(out & side):
            d = float(np.max(lever[out & side]))
            rate = TWIST_EXTRAPOLATION_DEG_PER_TENTH[name]
            noise = 0.0 if se is None else 0.2 * float(np.degrees(se))  # 2 σ, per 0.1
            ends.append(
                f'the {name} levels (up to {d:.2f} of the length {where} them, uncertain by '
                f'about ±{(rate + noise) * d / 0.1:.1f}°, {rate + noise:.1f}° per 0.1)'
            )
    if not ends:
        return ''
    return (
        f'twist is measured only between levels {span[0]:.2f} and {span[1]:.2f} (0 apex, 1 '
        f'base), where SA slices hold tag points: the twist of {" and ".join(ends)}, and the '
        'torsion, are extrapolated (the measured gradient continued linearly), not measured'
    )


def lv_frame_axes(particles, rotation):
    """
    Apex, base centre and reference of the LV from a registered model (ED).

    The long axis is R's z column (apex → base) through the particles' centroid; apex and base
    are the extreme projections of the particles on it; the reference is R's x column.

    Parameters
    ----------
    particles : array_like, shape (N, 3)
        ED particle positions, mm (patient coordinates).
    rotation : array_like, shape (4,)
        The registered model's rotation quaternion (w, x, y, z).

    Returns
    -------
    apex, base, reference : ndarray, shape (3,)

    """
    pts = np.asarray(particles, dtype=np.float64)
    R = quat_to_matrix(np.asarray(rotation, dtype=np.float64))
    axis, ref = R[:, 2], R[:, 0]
    c = pts.mean(axis=0)
    t = (pts - c) @ axis
    return c + t.min() * axis, c + t.max() * axis, ref
