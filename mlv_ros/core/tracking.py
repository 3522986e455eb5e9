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
Phase-by-phase dense motion from tracked tag points: the solver node's core (no rclpy).

Tag intersections give sparse 2D constraints: a track seen at ED at 3D position ``p0`` (in its
image plane) and at phase t at ``m_t`` (in the same, fixed plane). SPAMM tag planes run through
the slab, so the intersection seen at phase t is the material *line* ``p0 + s·n`` (n = slice
normal) where it crosses the plane now — with through-plane motion (the base descends ≈ 12 mm)
that is not the material point ``p0``. Each control point is therefore attached at
``p0 + s·n`` with ``s`` chosen so that the model puts it back in the plane ("slice following"),
re-estimated between fits, and only its in-plane residual acts (paper §2.2, method notes).

Classes
-------
PhaseAssembler
    Collects :class:`~mlv_ros.core.types.TagPointSet` per phase as slices arrive in any order
    (duplicates replace earlier copies) and says when a phase is complete.
MotionTracker
    Holds the meshless model built from the registered ED cloud and solves phases in order,
    warm-starting each from the previous one.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from itertools import chain

from mlv_ros.core.analysis.frame import lv_frame_axes, LVFrame
from mlv_ros.core.analysis.strain import AHA_SEGMENT_NAMES, aha_segments
from mlv_ros.core.analysis.tag_strain import TagEdges
from mlv_ros.core.meshless import (
    ControlPoints,
    GlobalParameters,
    MeshlessModel,
    ModelCoordinates,
    ModelFrame,
    plane_projectors,
    polar_frame,
    quat_to_matrix,
    thick_wall_frame,
)
from mlv_ros.core.meshless.local import (
    CoarseSpace,
    cofactors_3x3,
    LocalOperators,
    rigid_mode_eps,
)
from mlv_ros.core.meshless.solver import control_weights
from mlv_ros.core.tags.gabor import MIN_DIRECTION_SEPARATION
from mlv_ros.core.types import ModelState, PAIR_MISREGISTERED, TagPointSet, VIEW_NAMES, VIEW_SA
from mlv_ros.core.verdict import DEGRADED, MIN_SLICE_POINTS, phase_verdict
from mlv_ros.settings import check_keywords, SOLVER_MODEL
import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

# The twist function of height (MotionTracker._twist_function): fitted only from this many SA
# slices spanning this fraction of the LV's height (beyond them the twist continues linearly).
TWIST_MIN_SA, TWIST_MIN_SPAN = 4, 0.3
# A slice's own in-plane shift is fitted with its rotation only from this many of its tag points:
# from 2–3 (4–6 equations for 3 unknowns) the rotation is those points' noise (study 1009, 2–8
# points per slice: ES twist error 1.64° → 1.95° with a shift on every slice, 1.63° without them).
TWIST_SHIFT_MIN_POINTS = 4
# The local stage's coarse space (MotionTracker's coarse_aggregates): one aggregate per this many
# particles, at most this many aggregates (12 coarse unknowns each; a dense Cholesky per solve).
COARSE_PARTICLES, COARSE_MAX_AGGREGATES = 96, 64
# Where the longitudinal coupling acts (MotionTracker._outward_points, _coupling_weight): near tag
# points the previous pass left inward of their targets by more than COUPLING_Z robust z-scores of
# the phase's own residuals (weight 0 at the first, 1 at the second), within COUPLING_REACH SA
# slice spacings of them; a region keeps COUPLING_MEMORY of its weight into the next phase.
COUPLING_Z = (2.0, 4.0)
COUPLING_REACH = 2.0
COUPLING_MEMORY = 0.8
# Each slice's tag-point noise (MotionTracker._noise_scale): from the second differences in time
# of its tracks seen at three consecutive phases, less an affine fit over the slice (the wall's
# own acceleration), at a phase with at least NOISE_MIN_TRACKS of them; a difference beyond
# NOISE_SLIP times the slice's median one is a slipped track, not noise. A slice's estimate is the
# median of its last NOISE_SAMPLES samples once it has NOISE_MIN_SAMPLES, else the study's.
NOISE_MIN_TRACKS, NOISE_SLIP = 6, 5.0
NOISE_MIN_SAMPLES, NOISE_SAMPLES = 8, 400


def second_difference_noise(x, d2) -> np.ndarray | None:
    """
    Return one slice's squared noise samples from its tracks' second differences in time, mm².

    A track's second difference ``t_p − 2 t_{p−1} + t_{p−2}`` over three consecutive phases holds
    6 times its position variance plus the wall's acceleration, which is smooth over the slice:
    an affine fit in position removes it. The squared residuals are scaled by ``m / (m − rank)``
    (the fit's degrees of freedom), so that each has expectation ``6 × 2 σ²`` for white noise of
    σ per in-plane axis. Slipped tracks (beyond ``NOISE_SLIP`` times the median residual) are
    left out of the fit and the samples.

    Parameters
    ----------
    x : ndarray, shape (K, 3)
        The tracks' measured positions at the latest phase, mm.
    d2 : ndarray, shape (K, 3)
        Their second differences in time, mm.

    Returns
    -------
    ndarray, shape (M,) or None
        Squared residuals, mm²; None with fewer than ``NOISE_MIN_TRACKS`` tracks or too few left
        beyond the fit's own parameters.

    """
    n = len(x)
    if n < NOISE_MIN_TRACKS:
        return None
    A = np.column_stack([np.ones(n), x - x.mean(axis=0)])
    keep, fitted = np.ones(n, dtype=bool), None
    for _ in range(2):
        if fitted is None or not np.array_equal(keep, fitted):  # else the same fit again
            coef, _, rank, _ = np.linalg.lstsq(A[keep], d2[keep], rcond=None)
            r = np.sum((d2 - A @ coef) ** 2, axis=1)
            fitted = keep
        keep = r <= NOISE_SLIP**2 * np.median(r)
    m = int(keep.sum())
    if not np.array_equal(keep, fitted):  # else lstsq's rank (matrix_rank's SVD threshold)
        rank = np.linalg.matrix_rank(A[keep])
    rank = int(rank)
    if m <= rank + 2:
        return None
    return r[keep] * (m / (m - rank))


def noise_sigma(samples) -> float | None:
    """
    Return the noise σ per in-plane axis (mm) from squared second-difference samples (mm²).

    For white noise of σ per axis a sample is ``6 σ² χ²₂`` (two axes), whose median is
    ``12 σ² ln 2``; the median keeps what slipped tracks are left from pulling it.

    Parameters
    ----------
    samples : array_like, shape (M,)
        Squared samples (:func:`second_difference_noise`), mm².

    Returns
    -------
    float or None
        σ, mm; None when there is no sample.

    """
    if not len(samples):
        return None
    return float(np.sqrt(np.median(np.asarray(samples, dtype=np.float64)) / (12.0 * np.log(2.0))))


def data_weights(confidence) -> np.ndarray:
    """
    Return the data weight of each tag point from its detection confidence (0..1), shape (K,).

    A tag point's position error is its phase error times λ/2π, and the phase error falls as
    the Gabor response rises above the noise; the confidence is that response relative to the
    local intensity spread, so its square stands in for the inverse variance. Weights are
    relative (the fits scale them to mean 1): a faded point still counts, just less than a sharp
    one. Confidences are floored at 0.1 so that no measured point is ignored.
    """
    c = np.clip(np.nan_to_num(np.asarray(confidence, np.float64), nan=1.0), 0.1, 1.0)
    return c * c


# --------------------------------------------------------------------------- assembling
@dataclass
class PhaseAssembler:
    """
    Per-phase buffer of tag point sets.

    Parameters
    ----------
    expected_slices : int
        Slices (SA + LA) whose sets make a phase complete; 0 = unknown yet (taken from the sets'
        ``num_sa_slices + num_la_slices``).

    """

    expected_slices: int = 0
    phases: dict = field(default_factory=dict)  # phase → {(view, slice): TagPointSet}
    duplicates: int = 0

    def add(self, points: TagPointSet) -> bool:
        """Store a set; returns True if it replaced one already held (a duplicate)."""
        if not self.expected_slices and (points.num_sa_slices or points.num_la_slices):
            self.expected_slices = int(points.num_sa_slices + points.num_la_slices)
        slot = self.phases.setdefault(int(points.phase_index), {})
        key = (int(points.view), int(points.slice_index))
        dup = key in slot
        slot[key] = points
        self.duplicates += dup
        return dup

    def complete(self, phase: int) -> bool:
        return (
            bool(self.expected_slices) and len(self.phases.get(phase, {})) >= self.expected_slices
        )

    def sets(self, phase: int) -> dict:
        return self.phases.get(phase, {})

    def missing(self, phase: int, all_keys) -> list:
        """Slice keys of ``all_keys`` with no set at ``phase``."""
        have = self.phases.get(phase, {})
        return [k for k in all_keys if k not in have]


# --------------------------------------------------------------------------- solving
@dataclass
class PhaseSolution:
    """
    Dense motion at one phase.

    Attributes
    ----------
    positions : ndarray, shape (N, 3)
        Particle positions, mm (patient).
    displacement : ndarray, shape (N, 3)
        From ED, mm.
    strain : ndarray, shape (N, 3, 3)
        Green–Lagrange strain ``E = ½(FᵀF − I)`` relative to ED (patient axes).
    state : ModelState
        Global parameters and convergence record.
    num_constraints : int
        Control points used.

    """

    phase_index: int
    positions: np.ndarray
    displacement: np.ndarray
    strain: np.ndarray
    state: ModelState
    num_constraints: int


def twist_knots_error(twist_knots) -> str | None:
    """
    Why ``twist_knots`` cannot define :class:`MotionTracker`'s twist function, else None.

    0 is the paper's single twist factor τ; a piecewise-linear function of height needs at least
    2 knots (one knot is no function of height) and at most 100.
    """
    if isinstance(twist_knots, bool) or not isinstance(twist_knots, (int, np.integer)):
        return f'twist_knots must be an integer, got {type(twist_knots).__name__}'
    if int(twist_knots) not in (0, *range(2, 101)):
        return (
            'twist_knots must be 0 (the single twist factor) or 2..100 (one knot is no '
            'function of height)'
        )
    return None


def _knot_hats(height, knots: int) -> np.ndarray:
    """Hat functions of ``knots`` uniform knots on [0, 1] at each height, shape (N, knots)."""
    h = np.asarray(height, dtype=np.float64).reshape(-1)
    knot = np.linspace(0.0, 1.0, knots)
    return np.clip(1.0 - np.abs(h[:, None] - knot) * (knots - 1), 0.0, None)


def _pspline(J: np.ndarray, r: np.ndarray, lam: float, free: int = 0) -> np.ndarray:
    """
    Return ``c`` minimising ``|J c − r|² + lam |D² c[:m]|²``; never fails when singular.

    The last ``free`` columns of ``J`` are unknowns without a penalty (m = columns − free).
    """
    m = J.shape[1] - free
    D2 = np.hstack([np.diff(np.eye(m), 2, axis=0), np.zeros((m - 2, free))])
    # Least squares on the stacked system (e.g. all SA points at one level).
    return np.linalg.lstsq(
        np.vstack([J, np.sqrt(lam) * D2]), np.concatenate([r, np.zeros(m - 2)]), rcond=None
    )[0]


def _slice_shifts(shift: np.ndarray, sa_slice: np.ndarray) -> np.ndarray:
    """
    Return the in-plane residual per unit shift of each SA slice, shape (3K, 2 S).

    Two columns per SA slice with at least ``TWIST_SHIFT_MIN_POINTS`` points (``sa_slice`` ≥ 0;
    S such slices), a shift along each of two directions ⟂ the axis, non-zero only on that
    slice's rows; ``shift`` (K, 3, 2) is each row's weighted in-plane motion per mm of those
    shifts (:meth:`MotionTracker._twist_rows`).
    """
    slices, count = np.unique(sa_slice[sa_slice >= 0], return_counts=True)
    slices = slices[count >= TWIST_SHIFT_MIN_POINTS]
    on = (sa_slice[:, None] == slices[None, :]).astype(np.float64)  # (K, S)
    return (shift[:, :, None, :] * on[:, None, :, None]).reshape(len(shift) * 3, 2 * len(slices))


def _line_fit(x, y) -> tuple[float, float]:
    """
    Return the least-squares line ``y ≈ slope x + intercept`` (np.polyfit's, degree 1).

    From the centred sums (x must not be constant): the same line as polyfit's SVD to rounding,
    without its Vandermonde matrix and LAPACK call (0.02 against 0.1 ms at 500 points).
    """
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    xm, ym = float(x.mean()), float(y.mean())
    dx = x - xm
    slope = float(dx @ (y - ym)) / float(dx @ dx)
    return slope, ym - slope * xm


def _twist_gradient(height, twist, lo: float, hi: float) -> float:
    """
    Least-squares slope of the particles' twist (rad) over those with a height in [lo, hi].

    Heights are material (0 apex … 1 base), so the slope is in radians per LV height; 0 when
    fewer than two heights are there.
    """
    inside = (height >= lo) & (height <= hi)
    if inside.sum() < 2 or np.ptp(height[inside]) <= 0.0:
        return 0.0
    return _line_fit(height[inside], twist[inside])[0]


def _slice_twists(moved, residual, shift, sa_slice, height, psi):
    """
    Return each SA slice's own twist, its variance and its height, from its tag points alone.

    Each slice with at least two points gets a rotation about the long axis and an in-plane
    shift (three unknowns) fitted to its in-plane residuals; the rotation's variance is the
    slice's residual variance (at least the median slice's: a slice of two or three points fits
    them nearly exactly, which says nothing of its noise) times the rotation's diagonal entry of
    ``(AᵀA)⁻¹``. It grows as the points are few or bunched on one side of the slice, where a
    shift and a rotation look alike.

    Parameters
    ----------
    moved : ndarray, shape (K, 3)
        Each point's in-plane motion per radian of rotation (weighted), mm/rad.
    residual : ndarray, shape (K, 3)
        Each point's in-plane residual to the global fit (weighted), mm.
    shift : ndarray, shape (K, 3, 2)
        Each point's in-plane motion per mm of a shift ⟂ the long axis along two directions.
    sa_slice : ndarray of int, shape (K,)
        The SA slice of each point, -1 on LA views.
    height : ndarray, shape (K,)
        Each point's material height, 0 apex … 1 base.
    psi : ndarray, shape (K,)
        The global stage's own twist at each point, radians.

    Returns
    -------
    height, twist, variance : ndarray, shape (S,) each
        Per SA slice with a determined rotation: its points' mean height, its total twist (the
        global stage's plus its own rotation, radians) and that twist's variance (rad²).

    """
    fits = []  # (mask, A) of each slice with two points or more
    for s in np.unique(sa_slice[sa_slice >= 0]):
        k = sa_slice == s
        if k.sum() >= 2:
            A = np.concatenate([moved[k][:, :, None], shift[k]], axis=2).reshape(-1, 3)
            fits.append((k, A))
    if fits:
        # the slices' 3 × 3 normal matrices' conditions and inverses each in one LAPACK loop
        # (per matrix the same calls as one slice at a time)
        normal = np.stack([A.T @ A for _, A in fits])
        good = np.flatnonzero(~(np.linalg.cond(normal) > 1e12))
        fits = [(*fits[i], inv) for i, inv in zip(good, np.linalg.inv(normal[good]))]
    rows = []
    for k, A, inv in fits:
        b = residual[k].ravel()
        z = inv @ (A.T @ b)
        rss = float(np.sum((A @ z - b) ** 2))
        rows.append((height[k].mean(), z[0] + psi[k].mean(), rss / (2 * k.sum() - 3), inv[0, 0]))
    if not rows:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    h, twist, noise, unit = np.array(rows).T
    return h, twist, np.maximum(noise, np.median(noise)) * unit


def _slope_rows(height, variance, keep) -> np.ndarray:
    """Return the weights (1 / variance) least-squares slope's row over ``keep`` slices, (S,)."""
    w = np.where(keep, 1.0 / variance, 0.0)
    d = height - (w @ height) / w.sum()
    return w * d / float(w @ (d * d))


def _end_intervals(slices, band: float):
    """
    Return what the SA slices' own twists allow of each end gradient's difference from the mean.

    From the slices' twists and variances (:func:`_slice_twists`): the end gradient (a weighted
    line through the slices within ``band`` of the end, at least the last two) differs from the
    mean gradient (the line through all of them) by ``d`` with standard error ``σ_d``; the
    slices support a difference within ``d ± 2 σ_d``.

    Parameters
    ----------
    slices : (ndarray, ndarray, ndarray)
        Per SA slice: height, twist (rad) and its variance (rad²); at least three slices.
    band : float
        The end's band of heights (one knot interval).

    Returns
    -------
    list of (float, float, float)
        Apical and basal: the interval's low and high end (rad per LV height) and the slices'
        end gradient's standard error (rad per LV height).

    """
    h, twist, var = slices
    order = np.argsort(h)
    mean = _slope_rows(h, var, np.ones(len(h), bool))
    out = []
    for ends in (order[:2], order[-2:]):
        keep = np.abs(h - h[ends[0]]) <= band
        keep[ends] = True
        end = _slope_rows(h, var, keep)
        g = end - mean
        d, sd = float(g @ twist), float(np.sqrt(g @ (var * g)))
        out.append((d - 2.0 * sd, d + 2.0 * sd, float(np.sqrt(end @ (var * end)))))
    return out


def _twist_angle(height, psi, hat, coefficients, lo: float, hi: float, slices=None):
    """
    Return each particle's twist Δφ: the P-spline within the SA span, a line in height beyond.

    Beyond the span, the *total* twist ``psi + Δφ`` continues linearly from its value at the
    span's end, with the gradients chosen in :meth:`MotionTracker._twist_function`.

    Parameters
    ----------
    height : ndarray, shape (N,)
        Material heights, 0 apex … 1 base.
    psi : ndarray, shape (N,)
        The global stage's own twist of each particle since ED, radians.
    hat : ndarray, shape (N, m)
        The knots' hat functions at ``height`` (:func:`_knot_hats`).
    coefficients : ndarray, shape (m,)
        The fitted knot values, radians.
    lo, hi : float
        Heights of the lowest and the highest SA tag point.
    slices : (ndarray, ndarray, ndarray), optional
        Per SA slice its height, twist and variance (:func:`_slice_twists`); None, fewer than
        three slices or a variance of 0 (points fitted exactly) = each end gradient as the
        P-spline has it.

    Returns
    -------
    angle : ndarray, shape (N,)
        Δφ, radians.
    standard_errors : (float, float) or None
        Of the slices' apical and basal end gradient, radians per LV height (None without
        three slices).

    """
    m = len(coefficients)
    total = psi + hat @ coefficients
    band = 1.0 / (m - 1)
    mean = _twist_gradient(height, total, lo, hi)
    apical = _twist_gradient(height, total, lo, min(hi, lo + band))
    basal = _twist_gradient(height, total, max(lo, hi - band), hi)
    se = None
    if slices is not None and len(slices[0]) >= 3 and np.all(slices[2] > 0.0):
        (a_lo, a_hi, a_se), (b_lo, b_hi, b_se) = _end_intervals(slices, band)
        # the P-spline's end gradient only as far as the slices' own twists support it
        apical = mean + float(np.clip(apical - mean, a_lo, a_hi))
        basal = mean + float(np.clip(basal - mean, b_lo, b_hi))
        se = (a_se, b_se)
    # An end gradient of the other sign than the mean is noise; the apex turns steeper, the
    # base shallower.
    if apical * mean <= 0.0 or abs(apical) < abs(mean):
        apical = mean
    basal = min(basal, mean, key=abs) if basal * mean > 0.0 else 0.0
    angle = _knot_hats(np.clip(height, lo, hi), m) @ coefficients
    for end, side, gradient in ((lo, height < lo, apical), (hi, height > hi, basal)):
        near = np.abs(height - end) <= band
        if not side.any() or near.sum() < 2 or np.ptp(height[near]) <= 0.0:
            continue
        # the global twist at the end's height: a line through the particles near it
        slope, intercept = _line_fit(height[near], psi[near])
        at_end = float(_knot_hats([end], m)[0] @ coefficients)
        at_end += intercept + slope * end
        angle[side] = at_end + gradient * (height[side] - end) - psi[side]
    return angle, se


def _rotate_about_axis(x, centre, axis, angle) -> np.ndarray:
    """
    Rotate each point about the axis through ``centre`` by its own angle.

    Parameters
    ----------
    x : ndarray, shape (N, 3)
        Points, mm.
    centre : ndarray, shape (3,)
        A point on the axis, mm.
    axis : ndarray, shape (3,)
        Unit direction of the axis.
    angle : ndarray, shape (N,)
        Angles, radians (right-handed about ``axis``).

    Returns
    -------
    ndarray, shape (N, 3)
        The rotated points, mm.

    """
    v = x - centre
    along = (v @ axis)[:, None] * axis
    perp = v - along
    return (
        centre
        + along
        + perp * np.cos(angle)[:, None]
        + np.cross(axis, perp) * np.sin(angle)[:, None]
    )


class MotionTracker:
    """
    Dense LV motion through the cycle from tracked tag points.

    Parameters
    ----------
    particles : array_like, shape (N, 3)
        Registered ED particles, mm (patient).
    centre : array_like, shape (3,)
        Model origin c, mm.
    rotation : array_like, shape (4,)
        Unit quaternion (w, x, y, z) of R: its z axis is the long axis (apex → base), its x axis
        the β = 0 reference.
    a0 : float, optional
        Model scale, mm (default from the particles).
    polar : tuple of ndarray (alpha, beta, w), each shape (N,), optional
        The registration's polar model coordinates; with ``shape`` they rebuild its model
        frame exactly. Default: :func:`~mlv_ros.core.meshless.polar_frame` of the particles.
    shape : sequence (a0, a1, a2, a3, tau), optional
        Rest global shape parameters that go with ``polar``.
    data_weight : float
        External-force stiffness relative to the elastic stiffness (larger follows the tags
        more closely).
    slice_following : int
        Re-attachment passes per phase that keep each control point on its image plane.
    max_attach_mm : float
        Tag points farther than this from every particle (outside the model) are not used.
    cg_rtol : float
        Relative residual at which the local stage's conjugate gradients stop. Each solve is
        warm-started from the previous phase's δ; at 2e-3 the iterate is 6–20 µm RMS (86 µm at
        worst) from the converged solution, a tenth of a phase's own in-plane tag residual
        (0.10–0.22 mm RMS); the ES median, p95, twist and radius error of the normal,
        hypertrophic and infarct presets move by at most 0.004 mm and 0.014° from 1e-3, itself
        within 0.005 mm and 0.011° of 1e-6. A tighter tolerance costs iterations the data cannot
        repay.
    cg_maxiter : int
        Most CG iterations per local solve; one that reaches it keeps its last iterate.
    cg_rtol_following : float
        CG tolerance of the slice-following passes before a phase's last (the looser of it and
        ``cg_rtol``): they only place the tag points' material lines for the next pass, which
        starts from their δ. The iterations a looser first pass saves the last pass mostly
        repays: over the default study's 24 phases 189 + 201 iterations at 1e-2, 93 + 243 at
        5e-2, 2 + 310 with no first-pass CG at all. At 5e-2 the ES median, p95, twist and
        radius errors of the normal, hypertrophic and infarct presets move by at most 0.008 mm
        and 0.013° from 1e-2, of the kept robustness studies 1000, 1004, 1007 and 1012
        (``bench/retrack.py``) by at most 0.008 mm and 0.023°; without the first pass's CG the
        infarct's p95 moved by 0.09 mm and the hypertrophic radius by 0.04 mm.
    outlier_mm : float
        In-plane tag residual (mm) never counted an outlier: below it, a point is within the
        motion's own error however tight the other residuals are. In mm, not pixels: on nine
        kept bench studies (1.05–1.97 mm pixels) the residuals of the points kept grow far less
        than the pixel (p99 1.6–2.9 mm) and the ``outlier_sigmas`` threshold, which carries each
        study's own spread, grows with it (median 0.56–2.03 mm). The floor must stay below a
        slip, one tag period λ (5–10 mm); a region that moves unlike the global fit (an akinetic
        sector) leaves real residuals of 3–5 mm, which a floor nearer λ / 2 keeps: study 1012
        (λ 7.9 mm) ES p95 2.88 mm at 3 mm, 2.13 mm at 6 mm; the other eight within 0.004 mm
        (README, Outlier floor).
    outlier_sigmas : float
        A tag point whose in-plane residual exceeds the median by this many robust standard
        deviations (1.4826 MAD) is an outlier (a track that slipped or swapped identity): it is
        dropped and the global stage refitted.
    follow_step_mm : float
        Largest move (mm) of a tag point's material line along its plane normal per
        slice-following pass: it bounds the Newton step where the motion along the normal is far
        from linear.
    hourglass_weight : float
        Stiffness of the MLS fit-error penalty (paper eq. 16) that removes the zero-energy modes
        of the local strain energy, relative to the elastic stiffness.
    volume_weight : float
        Near-incompressibility: penalty on the linearised volume change of the whole deformation,
        in units of μ (0 = off). Myocardium keeps its volume to a few percent; with tags spaced
        like the wall is thick this is what recovers radial thickening (Err). 4000 (1000 before
        session 17): tracked SA points read the wall 1–2 mm thinner at end-systole than it is
        (docs/benchmarks.md, 'Issue 20 acceptance'), and against the tag springs 1000 let the
        solved wall lose 2–3 % of its volume (median det F 0.97–0.98 at ES, 10th percentile
        0.89; the truth 1.00) and global Err read 0.07–0.10 low; 4000 takes 30–45 % of that
        off on fresh studies and leaves the presets' ES error within 0.015 mm.
    longitudinal_weight : float
        Stiffness against local stretch along the long axis, in units of μ (0 = off). The global
        stage carries the longitudinal shortening (axial scale and translation); only LA tag
        points measure its local variation, SA points see none of it. Without this term the
        incompressibility penalty turns any in-plane area error into axial stretch wherever no
        LA track constrains it: at the free basal end above the last SA slice the wall was
        pushed up to 20 mm toward the atria (randomized protocols whose LA tracks faded on one
        side). With it, the volume is kept by thickening, as the myocardium keeps it.
    longitudinal_coupling : float
        κ in [0, 2]; 0 keeps the axial term on the local longitudinal strain alone. κ > 0 couples
        it to the local circumferential strain where the data say a region contracts less than
        the wall around it: the term then holds ``E_ll − w_i ρ E_cc`` of the local deformation,
        ρ = κ × the heart's own global E_ll / E_cc at this phase, w_i the particle's regional
        weight (``regional_coupling``). Only LA planes measure longitudinal motion, at a few
        angles; without the coupling an akinetic sector between them is held to its neighbours'
        shortening by the axial stiffness, thickens by incompressibility (its wall pulled inward:
        1012's sector −2.2 mm radially at ES) and the basal wall above it descends with the rest
        of the base. The stiffness of ~3000 μ is what fights the region's own motion.
    regional_coupling : bool
        True (default): the coupling acts only near tag points the previous pass left outward of
        the motion beyond the phase's own residual spread (:meth:`_outward_points`), i.e. where
        the wall contracts less than its neighbours; elsewhere the plain axial term holds.
        False: everywhere (the coupling at κ = 0.5 everywhere took healthy 1007 from 0.61 / 1.41
        to 0.67 / 1.48 mm). Measured on kept bench cases (offline re-solve of the recorded runs,
        ES median / p95 mm, off → regional κ = 1): akinetic 1012 0.771 / 2.522 → 0.809 / 2.295,
        2006 0.418 / 2.543 → 0.428 / 2.262; healthy 1001 0.474 / 1.042 → 0.475 / 1.041, 1004
        0.610 / 1.325 → 0.602 / 1.308, 1007 0.707 / 1.530 → 0.711 / 1.548, 1014 0.516 / 1.005 →
        0.521 / 1.005, 2004 0.419 / 1.014 → 0.420 / 1.011.
    coupling_plateau : float
        In [0, 1): the share of the coupling's reach ℓ within which a flagged tag point gives the
        particles its whole weight, tapering linearly to 0 at ℓ (0: the hat ``1 − d / ℓ`` from the
        point itself). With the hat, a sector whose every tag point is flagged still averages
        about half its points' weight (study 4006's akinetic AHA 7 at ES: median 0.43), so the
        coupling there asks for half the longitudinal deviation the circumferential one implies.
        Off: measured on the kept studies (README, Longitudinal coupling's reach).
    global_prior : float
        Weight of the prior that holds the global parameters at the previous phase
        (:meth:`MeshlessModel.fit`'s ``global_prior``): with few or one-sided tag points a weakly
        seen parameter otherwise wanders (a randomized dilated study: axial scale 0.7 → 0.06 in
        one phase, every particle 126 mm off, the in-plane residual 0.08 mm).
    twist_knots : int
        Knots (uniform in height, apex to base) of the twist parameter function fitted after the
        global stage; 0 = the paper's single twist factor τ only. The LV twists non-linearly
        along its axis, and below the last SA slice only the LA planes see the wall, which do
        not measure circumferential motion: there the total twist continues linearly in height
        with the measured gradient (:meth:`_twist_function`) instead of being left to the local
        elasticity, which would continue it as a rigid rotation.
    twist_smoothing : float
        Curvature penalty of the twist function relative to its data term (dimensionless).
    confidence_weights : bool
        Weight each tag point's spring by :func:`data_weights` of its detection confidence
        (False: all points alike).
    tag_noise_mm : float
        Tag-point localisation noise (mm, standard deviation per in-plane axis) for which
        ``data_weight`` holds; 0 = off. Each slice's own noise σ is measured from its tracks'
        second differences in time (:func:`second_difference_noise`: white noise adds 6 σ² per
        axis to them, the wall's smooth acceleration is fitted out), and a point of a slice with
        σ > ``tag_noise_mm`` gets the spring ``data_weight × (tag_noise_mm / σ)²``, its inverse
        variance relative to a point of ``tag_noise_mm`` (a slice measured below it keeps
        ``data_weight``: its error is then the tracker's systematic one, which differences in
        time do not see, and a stiffer spring only follows that). Until a slice has
        ``NOISE_MIN_SAMPLES`` samples it takes the study's pooled σ; before any (the first two
        phases), every point keeps ``data_weight``. The factor also weights the point in the
        global fit and the twist function (relative there). In mm, so it holds for any pixel
        size, SNR and tracker: 0.15 mm is the noise of the presets the default ``data_weight``
        was chosen on (normal preset: 0.12 mm study-wide, 0.09–0.16 mm by slice). Measured on
        the kept bench runs (offline re-solve, ES median / p95 mm, off → 0.15 mm): see the
        README (Data weights).
    coarse_aggregates : int, optional
        Aggregates of the local stage's coarse space
        (:class:`~mlv_ros.core.meshless.local.CoarseSpace`, built once with the model; 0 =
        block-Jacobi alone). Default: one per ``COARSE_PARTICLES`` particles, at most
        ``COARSE_MAX_AGGREGATES``. It changes only how fast CG converges, not what it converges to.
    global_thickening : bool
        Global shape that keeps the wall's volume (:func:`~mlv_ros.core.meshless.thick_wall_frame`,
        the incompressible thick-walled cylinder per level): the wall thickens as the fitted
        shape contracts, with no new parameter. False: the paper's affine shape, whose volume
        changes by ``a0³ a1 a2 a3`` (J − 1 ≈ −0.43 at ES), which the local stage's volume term
        must then restore. Either way the local stage costs the transmural axial shear
        (:meth:`_axial_shear`), through which the volume term otherwise repays that volume
        (affine shape) or the thickening the tracked points miss (thick-walled map): the wall
        moved toward the base between the LA planes. Off: the global Err error is smaller with
        it on every kept study measured, the ES p95 is not (README, Global stage).

    """

    def __init__(
        self,
        particles,
        centre,
        rotation,
        a0: float | None = None,
        *,
        polar=None,
        shape=None,
        data_weight: float = 1.0e4,
        slice_following: int = 1,
        max_attach_mm: float = 3.0,
        max_iterations: int = 100,
        tol: float = 1e-3,
        cg_rtol: float = 2e-3,
        cg_maxiter: int = 400,
        cg_rtol_following: float = 5e-2,
        outlier_mm: float = 3.0,
        outlier_sigmas: float = 5.0,
        follow_step_mm: float = 5.0,
        local: bool = True,
        hourglass_weight: float = 1.0e3,
        volume_weight: float = 4.0e3,
        longitudinal_weight: float = 3.0e3,
        global_prior: float = 1.0,
        twist_knots: int = 11,
        twist_smoothing: float = 0.3,
        confidence_weights: bool = True,
        coarse_aggregates: int | None = None,
        longitudinal_coupling: float = 1.0,
        regional_coupling: bool = True,
        coupling_plateau: float = 0.0,
        tag_noise_mm: float = 0.15,
        global_thickening: bool = False,
    ):
        # The node's ranges (one table for both), before the model is built: a mistake costs
        # nothing. locals() holds the arguments alone here.
        check_keywords(SOLVER_MODEL, locals())
        pts = np.asarray(particles, dtype=np.float64)
        R = quat_to_matrix(np.asarray(rotation, dtype=np.float64))
        frame = _model_frame(pts, centre, rotation, R, a0, polar, shape)
        self.global_thickening = bool(global_thickening)
        self._radial = None  # rest radial directions of the transmural shear (_axial_shear)
        if self.global_thickening:
            frame = thick_wall_frame(frame)
        self.model = MeshlessModel(pts, frame)
        self.rest = self.model.rest_points
        self._tree = cKDTree(self.rest)
        self.data_weight = float(data_weight)
        self.confidence_weights = bool(confidence_weights)
        self.slice_following = int(slice_following)
        self.max_attach_mm = float(max_attach_mm)
        self.max_iterations = int(max_iterations)
        self.tol = float(tol)
        self.local = bool(local)
        self.cg_rtol, self.cg_maxiter = float(cg_rtol), int(cg_maxiter)
        self.cg_rtol_following = float(cg_rtol_following)
        self.outlier_mm, self.outlier_sigmas = float(outlier_mm), float(outlier_sigmas)
        self.follow_step_mm = float(follow_step_mm)
        self.prescreen = True
        self.screen_global = False  # see _robust_global_fit and README (Which motion screens)
        self.screened: list = []  # (view, slice, track_id) the last phase's last pass rejected
        self.rejected = 0
        self._init_local_stage(hourglass_weight, volume_weight)
        self._init_coupling(longitudinal_weight, longitudinal_coupling, regional_coupling)
        self.coupling_plateau = _coupling_plateau(coupling_plateau)
        self.contraction_prior = 0.0  # see _contraction_prior
        self._la_rest = None  # ED positions of the LA tag points of the pass (_contraction_prior)
        self._columns = None  # the transmural averaging matrix (_contraction_prior)
        self._far = None  # per particle, the last local solve's share of the prior (diagnostics)
        self.global_prior = float(global_prior)
        self.twist_knots, self.twist_smoothing = int(twist_knots), float(twist_smoothing)
        self.twist_coefficients = np.zeros(0)  # radians at the knots, last phase solved
        # standard errors of the apical and basal gradient the twist continues with beyond the SA
        # slices, radians per LV height, last phase solved (None: not known)
        self.twist_gradient_se = None
        self.twist_mean_gradient = 0.0  # the SA slices' mean twist gradient then, rad per height
        t = (self.rest - self.rest.mean(axis=0)) @ R[:, 2]
        self._height = (t - t.min()) / max(float(np.ptp(t)), 1e-9)  # material, 0 apex → 1 base
        self._hats = None  # _knot_hats of _height, built at the first twist fit
        self.positions = self.rest.copy()
        self._gradient = None  # (positions, their H): see _positions_gradient
        self.largest_motion_mm = 0.0  # median displacement from ED, largest phase so far
        self.reference: dict = {}  # (view, slice) → {track_id: ED position (3,)}
        self._reference_rows: dict = {}  # (view, slice) → its reference as _track_rows
        self.normals: dict = {}  # (view, slice) → (normal (3,), point on plane (3,))
        self._one_family: dict = {}  # (view, slice) → its ED points lie on one tag-line family
        self._tag_edges = None  # the SA tracks' ED edges (:meth:`_tag_evidence`)
        self._pair_notes: dict = {}  # (view, slice) → why its line pair's two series disagree
        self._sectors = None  # SA slice → (θ°, track ids, segments) of its ED points: see
        # _sector_tracks; set_reference clears it
        self.offsets: dict = {}  # (view, slice, track_id) → s, mm along the normal
        self._coarse = self._phase_coarse = None
        self._init_coarse_space(coarse_aggregates)
        self.tag_noise_mm = float(tag_noise_mm)
        self._history: dict = {}  # (view, slice) → {phase: _track_rows of measured positions}
        self._noise_samples: dict = {}  # (view, slice) → deque of squared noise samples, mm²
        self._noise_phase = -1  # the last phase whose second differences were sampled
        self.noise_mm: dict = {}  # (view, slice) → σ of the last phase's scale, mm (diagnostics)

    def _init_local_stage(self, hourglass_weight, volume_weight):
        """
        Set the local stage's operators and penalty weights.

        Parameters
        ----------
        hourglass_weight : float
            Fit-error penalty relative to the elastic diagonal (kept as given).
        volume_weight : float
            Near-incompressibility penalty, in units of μ.

        """
        self.cg_iterations = deque(
            maxlen=1000
        )  # CG iterations of the latest local solves (benchmarks)
        self.delta = None
        # (x_global, D(x_global − X), δ, D δ) of the last local solve, D the MLS gradient in its
        # layout: the warm start's gradient for the next solve and, summed, the positions'.
        self._local_gradients = None
        # The local stage's operators, built with the model; the fit-error penalty is weighted by
        # the kernel weights w_ij (uniform s_i) and scaled against the elastic diagonal per solve.
        # MeshlessModel weights the same penalty by v_i w_ij / (W_i h_i²) (see its
        # local_operators): the weighting hourglass_weight was validated with on the 40 studies
        # is kept. Rigid modes: rigid_mode_eps(κ), one rule for both.
        ph, lam, mu = self.model.phyxels, self.model.lam, self.model.mu
        self._local = LocalOperators(self.model.operator, ph.volume, lam, mu, 1.0 / ph.wij.max())
        self._kdiag = np.trace(self._local.volume_moment, axis1=1, axis2=2) * (
            mu + (mu + lam) / 3.0
        )
        # the medians :meth:`_multipliers` scales against, once per model (0.2 ms a solve)
        self._diagonal_medians = (
            float(np.median(self._kdiag)),
            max(float(np.median(self._local.fit_error_diagonal)), 1e-300),
        )
        self.hourglass_weight = hourglass_weight
        self.volume_weight = float(volume_weight)
        # True: the volume term linearised about the warm start's deformation F_g + ∇δ₀ instead
        # of the global fit's F_g alone (see _local_solve). Off: it keeps the solved wall's
        # volume (median det F 0.975 → 0.998 on 7303 from exact points) and reads more
        # thickening from exact points, but on tracked points it moved the global Err little and
        # turned the volume into axial motion (infarct preset ES p95 +0.075 mm at the base; the
        # dilated 2007 1.33 → 5.29 mm): docs/benchmarks.md, 'The volume term's linearisation'.
        self.volume_about_start = False

    def _init_coupling(self, longitudinal_weight, longitudinal_coupling, regional_coupling):
        """
        Check and set the local stage's axial stiffness and its longitudinal coupling.

        Parameters
        ----------
        longitudinal_weight : float
            Local longitudinal stiffness, in units of μ (checked with the other keywords).
        longitudinal_coupling : float
            Coupling factor, in [0, 2] (see the class docstring).
        regional_coupling : bool
            Whether the coupling is weighted by region (:meth:`_coupling_weight`).

        Raises
        ------
        ValueError
            The coupling factor outside its range.

        """
        self.longitudinal_weight = float(longitudinal_weight)
        if not 0.0 <= longitudinal_coupling <= 2.0:
            raise ValueError(
                f'longitudinal_coupling must be in [0, 2], got {longitudinal_coupling}'
            )
        self.longitudinal_coupling = float(longitudinal_coupling)
        self.regional_coupling = bool(regional_coupling)
        self.coupling_weight = np.zeros(0)  # per particle, the last local solve's (diagnostics)
        self._coupling_map = None
        self._flagged = None

    def _init_coarse_space(self, coarse_aggregates):
        """
        Build the local stage's coarse space once, with the model (none when 0 aggregates).

        Parameters
        ----------
        coarse_aggregates : int or None
            Aggregates; None: one per ``COARSE_PARTICLES`` particles, at most
            ``COARSE_MAX_AGGREGATES``.

        Raises
        ------
        ValueError
            ``coarse_aggregates`` not an integer >= 0.

        """
        if coarse_aggregates is None:
            coarse_aggregates = min(COARSE_MAX_AGGREGATES, self.rest.shape[0] // COARSE_PARTICLES)
        if not isinstance(coarse_aggregates, (int, np.integer)) or coarse_aggregates < 0:
            raise ValueError(
                'coarse_aggregates must be an integer >= 0 (0 = block-Jacobi only), got '
                f'{coarse_aggregates}'
            )
        if coarse_aggregates:
            # The reference at rest: cofactors I, the rest long axis (see CoarseSpace).
            kappa, alpha = self._multipliers()
            axis = quat_to_matrix(self.model.rest_params.rotation)[:, 2]
            kl = self.longitudinal_weight * self.model.mu
            self._coarse = CoarseSpace(
                self._local,
                min(int(coarse_aggregates), self.rest.shape[0]),
                fit_error=alpha,
                volume_weight=self.volume_weight * self.model.mu,
                axial=(kl, axis),
                eps=rigid_mode_eps(kappa),
                shear=(kl, axis, self._rest_radial()) if kl else None,
            )

    @property
    def num_particles(self) -> int:
        return self.rest.shape[0]

    def set_reference(self, points: TagPointSet) -> int:
        """Record a slice's ED tag points (phase 0); returns how many lie inside the model."""
        key = (int(points.view), int(points.slice_index))
        self._sectors = self._tag_edges = None
        if len(points) == 0:
            self.reference[key] = {}
            self._reference_rows.pop(key, None)
            return 0
        dist, _ = self._tree.query(points.position)
        keep = (dist <= self.max_attach_mm) & (points.track_id >= 0)
        self.reference[key] = {
            int(t): p for t, p in zip(points.track_id[keep], points.position[keep])
        }
        self._reference_rows[key] = _track_rows(
            np.fromiter(self.reference[key], dtype=np.int64, count=len(self.reference[key])),
            np.asarray(list(self.reference[key].values())).reshape(-1, 3),
        )
        self.normals[key] = (points.geometry.normal, points.geometry.image_position)
        # At ED the lines are straight: one family's normals agree there.
        self._one_family[key] = _one_line_family(points)
        notes = [x for x in points.status.split('; ') if x.startswith(PAIR_MISREGISTERED)]
        self._pair_notes[key] = notes[0][len(PAIR_MISREGISTERED) + 2:] if notes else ''
        return int(keep.sum())

    def _constraints(self, sets: dict):
        """
        Collect ED positions, targets, normals, keys and data weights of every track at this phase.

        ``normals`` are the image-plane normals (K, 3), or, when some point lies on a single
        family of tag lines, (ν, n) pairs (K, 2, 3) with n its tag-line normal (NaN: grid;
        :func:`~mlv_ros.core.meshless.plane_projectors`).

        Slice by slice in (view, slice) order: the solution must not depend on the order the slices
        arrived in (float sums in another order, then an extra CG iteration, moved a phase by 0.015
        mm when the same sets were taken in another order). Within a slice, the set's order.
        """
        keys, rest, targets, normals, conf, lines = [], [], [], [], [], []
        for key, pts in sorted(sets.items(), key=lambda item: item[0]):
            ref = self._reference_rows.get(key)
            if ref is None or len(pts) == 0:
                continue
            tid = np.asarray(pts.track_id, dtype=np.int64)
            hit, p0 = ref.lookup(tid)
            if not hit.any():
                continue
            keys.extend((*key, t) for t in tid[hit].tolist())
            rest.append(p0[hit])
            targets.append(np.asarray(pts.position)[hit])
            normals.append(np.repeat(np.asarray(pts.geometry.normal)[None], int(hit.sum()), 0))
            lines.append(_line_rows(pts, hit))
            c = pts.confidence if len(pts.confidence) == len(pts) else np.ones(len(pts))
            conf.append(np.asarray(c)[hit])
        if not keys:
            return keys, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
        conf = np.concatenate(conf)
        weights = data_weights(conf) if self.confidence_weights else np.ones(len(keys))
        rest, targets, normals = (np.concatenate(a) for a in (rest, targets, normals))
        if any(np.isfinite(n).any() for n in lines):  # 1-D points: (ν, n) pairs
            normals = np.stack([normals, np.concatenate(lines)], axis=1)
        return keys, rest, targets, normals, weights

    def _record_noise(self, phase_index, keys, targets, groups=None):
        """
        Sample each slice's tag-point noise from its tracks' second differences in time.

        Parameters
        ----------
        phase_index : int
            The phase being solved; a phase not after the last one sampled adds no sample (a
            phase solved again must not count twice).
        keys : list of tuple
            (view, slice, track_id) of every tag point, shape (K,).
        targets : ndarray, shape (K, 3)
            Their measured positions, mm.
        groups : list, optional
            :func:`_slice_groups` of ``keys`` (computed here when not given).

        """
        p = int(phase_index)
        x = np.asarray(targets, dtype=np.float64)
        fresh = p > self._noise_phase
        rows = []
        for key, idx, tid in _slice_groups(keys) if groups is None else groups:
            hist = self._history.setdefault(key, {})
            # A phase solved again keeps what its earlier solve held for tracks not seen now.
            hist[p] = _track_rows(tid, x[idx], hist.get(p))
            for old in [q for q in hist if q < p - 2]:
                del hist[old]
            if fresh and p - 1 in hist and p - 2 in hist:
                hit1, x1 = hist[p - 1].lookup(tid)
                hit2, x2 = hist[p - 2].lookup(tid)
                both = hit1 & hit2
                if both.any():
                    xb = x[idx][both]
                    rows.append((key, xb, xb - 2.0 * x1[both] + x2[both]))
        if not fresh:
            return
        self._noise_phase = p
        for key, xs, d2 in rows:
            r = second_difference_noise(xs, d2)
            if r is not None:
                self._noise_samples.setdefault(key, deque(maxlen=NOISE_SAMPLES)).extend(r)

    def _noise_scale(self, keys, groups=None) -> np.ndarray:
        """
        Return each tag point's spring factor ``min(1, (tag_noise_mm / σ)²)``, shape (K,).

        σ is the point's slice's measured noise (mm, per in-plane axis; :func:`noise_sigma` of
        its samples, the study's pooled samples while it has fewer than ``NOISE_MIN_SAMPLES``),
        so a point's spring is ``data_weight`` times its inverse variance relative to a point of
        ``tag_noise_mm``. 1 everywhere when ``tag_noise_mm`` is 0 or nothing is measured yet.

        Parameters
        ----------
        keys : list of tuple
            (view, slice, track_id) of every tag point, shape (K,).
        groups : list, optional
            :func:`_slice_groups` of ``keys`` (computed here when not given).

        Returns
        -------
        ndarray, shape (K,)
            Factors in (0, 1].

        """
        scale = np.ones(len(keys))
        if not self.tag_noise_mm:
            return scale
        pooled = [np.asarray(q, dtype=np.float64) for q in self._noise_samples.values() if q]
        study = noise_sigma(np.concatenate(pooled)) if pooled else None
        self.noise_mm = {}
        for key, idx, _ in _slice_groups(keys) if groups is None else groups:
            q = self._noise_samples.get(key, ())
            sigma = self.noise_mm[key] = (
                noise_sigma(q) if len(q) >= NOISE_MIN_SAMPLES else study
            )
            if sigma is not None and sigma > self.tag_noise_mm:
                scale[idx] = (self.tag_noise_mm / sigma) ** 2
        return scale

    def _attach(self, rest, normals, offsets):
        """
        Return the material positions ``p0 + s n``, which lie inside the model, and their nearest.

        The nearest particles (:meth:`MeshlessModel.nearest`) are what the attachment queries.
        """
        pos = rest + offsets[:, None] * _plane_normals(normals)
        near = self.model.nearest(pos)
        inside = near[0][:, 0] <= self.max_attach_mm
        return pos, inside, near

    def _drop(self, inside, ctrl, bad):
        """
        Return ``inside`` and ``ctrl`` without the attached points flagged ``bad``.

        ``bad`` is boolean over the attached points (``inside``'s true entries, in order); they
        are counted as rejected.
        """
        keep = np.flatnonzero(inside)[~bad]
        inside = np.zeros_like(inside)
        inside[keep] = True
        self.rejected += int(bad.sum())
        return inside, _control_rows(ctrl, ~bad)

    def _fit_global(self, ctrl, targets, normals, weights):
        """Fit the global parameters alone (no local stage) to the attached tag points."""
        return self.model.fit(
            ctrl,
            targets,
            normals,
            max_iterations=self.max_iterations,
            tol=self.tol,
            local=False,
            global_prior=self.global_prior,
            weights=weights,
        )

    def solve(self, phase_index: int, sets: dict, num_phases: int = 0) -> PhaseSolution:
        """
        Fit the model to one phase's tag points (``sets``: (view, slice) → TagPointSet).

        Raises
        ------
        ValueError
            No usable constraint at this phase (nothing inside the model, or no reference).

        """
        keys, rest, targets, normals, weights = self._constraints(sets)
        if not keys:
            raise ValueError(
                f'phase {phase_index}: no tag point matches an ED reference inside the model'
            )
        groups = _slice_groups(keys)
        self._record_noise(phase_index, keys, targets, groups)
        scale = self._noise_scale(keys, groups)
        offsets = np.array([self.offsets.get(k, 0.0) for k in keys])
        self._phase_coarse = None  # the first local solve of the phase factors its coarse part
        self._flagged = None  # tag points the last pass's motion left outward of their targets
        worst = (0, 0)  # (rejected, attached) of the pass that rejected the largest share
        passes = max(1, self.slice_following + 1)
        for pass_index in range(passes):
            rejected_before = self.rejected
            pos, inside, near = self._attach(rest, normals, offsets)
            attached = int(inside.sum())
            if attached < 4:
                raise ValueError(
                    f'phase {phase_index}: only {attached} tag points lie inside the model'
                )
            attached_before = inside
            inside, ctrl, result = self._robust_global_fit(
                pos, inside, targets, normals, weights * scale, near
            )
            self._pass_motion(
                keys,
                inside,
                ctrl,
                targets,
                normals,
                (weights, scale),
                pass_index == passes - 1,
                result.positions,
            )
            offsets = self._follow_slices(offsets, rest, normals, targets, inside, ctrl)
            worst = _larger_rejected_share(worst, self.rejected - rejected_before, attached)
        for k, s in zip(keys, offsets):
            self.offsets[k] = float(s)
        self.screened = [keys[i] for i in np.flatnonzero(attached_before & ~inside)]
        return self._phase_solution(
            phase_index, num_phases, sets, keys, inside, ctrl, targets, normals, result, worst
        )

    def _robust_global_fit(self, pos, inside, targets, normals, weights, near=None):
        """
        Attach the tag points, screen out slipped tracks and fit the global parameters.

        Parameters
        ----------
        pos : ndarray, shape (K, 3)
            The tag points' material positions at ED (``p0 + s n``), mm.
        inside : ndarray of bool, shape (K,)
            Which of them lie within ``max_attach_mm`` of the model.
        targets, normals : ndarray, shape (K, 3)
            Measured positions (mm) and their image-plane normals.
        weights : ndarray, shape (K,)
            Data weights (:func:`data_weights`).
        near : (dist, idx), optional
            :meth:`MeshlessModel.nearest` of ``pos`` (queried here when not given).

        Returns
        -------
        inside : ndarray of bool, shape (K,)
            ``inside`` less the points rejected as outliers.
        ctrl : ControlPoints
            The attachment of the points kept (in their order).
        result : FitResult
            The global fit to them (the model holds its parameters).

        """
        ctrl = self.model.attach(
            pos[inside], None if near is None else (near[0][inside], near[1][inside])
        )
        if self.prescreen:
            # A track that slipped by a tag period sits a period away from where the previous
            # phase's motion puts it, while its neighbours sit within the phase-to-phase
            # motion: screen against that prediction before the first fit can be dragged.
            pre = self._outliers(ctrl.weights @ self.positions, targets[inside], normals[inside])
            if pre.any() and (~pre).sum() >= max(4, pre.size // 2):
                inside, ctrl = self._drop(inside, ctrl, pre)
        result = self._fit_global(ctrl, targets[inside], normals[inside], weights[inside])
        if not self.screen_global:
            return inside, ctrl, result
        # Robustness: a track that swapped identity or drifted leaves a residual far beyond
        # what the global fit leaves elsewhere; drop such points and refit. The 12 global
        # parameters cannot follow a sector that does not contract: its consistent tracks
        # leave 3-5 mm here and are dropped too (``screen_global`` False: the prescreen alone,
        # against the previous phase's motion and, in later passes, the previous pass's).
        outlier = self._outliers(
            ctrl.weights @ result.positions, targets[inside], normals[inside]
        )
        if outlier.any() and (~outlier).sum() >= 4:
            inside, ctrl = self._drop(inside, ctrl, outlier)
            result = self._fit_global(ctrl, targets[inside], normals[inside], weights[inside])
        return inside, ctrl, result

    def _pass_motion(self, keys, inside, ctrl, targets, normals, weights, last, x_global=None):
        """
        Set ``positions`` to the global fit plus the twist function and the local deformation δ.

        Parameters
        ----------
        keys : list of tuple
            (view, slice, track_id) of every tag point, shape (K,).
        inside : ndarray of bool, shape (K,)
            The points used (attached and not rejected).
        ctrl : ControlPoints
            Their attachment, in their order.
        targets, normals : ndarray, shape (K, 3)
            Measured positions (mm) and their image-plane normals.
        weights : tuple of ndarray, each shape (K,)
            The confidence weights (:func:`data_weights`, relative) and the noise scale
            (:meth:`_noise_scale`, absolute): the global fit and the twist take their product
            relative, the local stage the confidences relative times the scale.
        last : bool
            Whether this is the phase's last pass (the full CG tolerance; no coupling to flag
            for a next pass).
        x_global : ndarray, shape (N, 3), optional
            The global fit's particle positions (mm) when the caller has them (its
            ``FitResult.positions``): the model's :meth:`~MeshlessModel.positions`, not taken
            again.

        """
        weights, scale = weights
        x_global = self.model.positions() if x_global is None else x_global
        if self.twist_knots:
            sa_slice = np.array([k[1] if k[0] == VIEW_SA else -1 for k in keys])[inside]
            x_global = self._twist_function(
                ctrl.weights,
                targets[inside],
                normals[inside],
                x_global,
                sa_slice,
                (weights * scale)[inside],
            )
        self.positions = x_global
        if not self.local:
            return
        la = np.array([k[0] != VIEW_SA for k in keys])[inside]
        self._la_rest = ctrl.rest_positions[la]
        # The passes before the last only place the material lines for the next one.
        rtol = self.cg_rtol if last else max(self.cg_rtol, self.cg_rtol_following)
        self.delta = self._local_solve(
            ctrl.weights,
            targets[inside],
            normals[inside],
            x_global,
            weights[inside],
            rtol=rtol,
            scale=scale[inside],
        )
        self.positions = x_global + self.delta
        known = self._local_gradients
        if known is not None and known[0] is x_global and known[2] is self.delta:
            # the positions' displacement gradient as the sum of the two the solve has (in place
            # of a product of D with x_global + δ − X; the same to rounding, 1e-16 relative)
            n = self.rest.shape[0]
            H = (known[1] + known[3]).reshape(n, 3, 3).transpose(0, 2, 1)
            self._gradient = (self.positions, H)
        if self.longitudinal_coupling and self.regional_coupling and not last:
            self._flagged = self._outward_points(ctrl, targets[inside], normals[inside])

    def _phase_solution(
        self, phase_index, num_phases, sets, keys, inside, ctrl, targets, normals, result, worst
    ) -> PhaseSolution:
        """
        Return the phase's solution: positions, displacement, Green strain, state and verdict.

        Parameters
        ----------
        phase_index, num_phases : int
            The phase solved and the phases per cycle (0: unknown).
        sets : dict
            (view, slice) → TagPointSet of the phase.
        keys : list of tuple
            (view, slice, track_id) of every tag point, shape (K,).
        inside : ndarray of bool, shape (K,)
            The points the last pass used.
        ctrl : ControlPoints
            Their attachment, in their order.
        targets, normals : ndarray, shape (K, 3)
            Measured positions (mm) and their image-plane normals.
        result : FitResult
            The last pass's global fit (its state is completed and returned).
        worst : tuple of int
            (rejected, attached) of the pass that rejected the largest share.

        Returns
        -------
        PhaseSolution
            The phase's solution.

        """
        x = self.positions
        H = self._positions_gradient()  # H[i, a, b] = ∂u_a/∂X_b
        F = np.eye(3) + H
        E = 0.5 * (np.swapaxes(F, 1, 2) @ F - np.eye(3))
        P = plane_projectors(normals[inside], int(inside.sum()))
        res = np.einsum('kab,kb->ka', P, targets[inside] - ctrl.weights @ x)
        state = result.state
        state.residual = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
        state.phase_index, state.num_phases = int(phase_index), int(num_phases)
        state.num_control_points = int(inside.sum())
        used = [k for k, ok in zip(keys, inside) if ok]
        verdict = self._verdict(
            sets, inside, state.residual, keys, *worst,
            residuals=dict(zip(used, np.linalg.norm(res, axis=1))),
        )
        state.verdict, state.verdict_reasons = verdict.level, verdict.text
        # The sector check names AHA segments (:meth:`_sector_tracks`); a phase degraded by it
        # alone is less sure there only.
        state.degraded_segments = tuple(
            sorted(AHA_SEGMENT_NAMES.index(n) + 1 for n in verdict.confined_to)
        )
        state.tag_ecc, state.tag_ecc_unc = self._tag_evidence(sets)
        return PhaseSolution(int(phase_index), x, x - self.rest, E, state, int(inside.sum()))

    def _verdict(self, sets, inside, residual_mm, keys, rejected, attached, residuals=None):
        """
        Return the phase's data support (:func:`mlv_ros.core.verdict.phase_verdict`).

        ``residuals``: (view, slice, track_id) → in-plane residual (mm) of each point used, for
        the regional fit check (None: not checked).
        """
        used_per_slice: dict = {}
        for k, ok in zip(keys, inside):
            if ok:
                used_per_slice[k[:2]] = used_per_slice.get(k[:2], 0) + 1
        sa_points = {
            key[1]: used_per_slice.get(key, 0)
            for key, ref in self.reference.items()
            if key[0] == VIEW_SA and ref
        }
        # Tag points found on each SA slice, inside the model or not: a basal slice the base
        # moves out of keeps its tags (beyond the model) and is no level lost.
        sa_found = {
            k: len(sets[(VIEW_SA, k)].track_id) if (VIEW_SA, k) in sets else 0 for k in sa_points
        }
        motion = float(np.median(np.linalg.norm(self.positions - self.rest, axis=1)))
        self.largest_motion_mm = max(self.largest_motion_mm, motion)
        spacing = [
            min(p.geometry.row_spacing, p.geometry.column_spacing)
            for p in sets.values()
            if getattr(p, 'geometry', None) is not None
        ]
        verdict = phase_verdict(
            int(inside.sum()),
            sum(len(r) for r in self.reference.values()),
            sa_points,
            residual_mm,
            float(np.median(spacing)) if spacing else 0.0,
            rejected=int(rejected),
            candidates=int(attached),
            sa_found=sa_found,
            sa_tracks=self._sector_tracks({k for k, ok in zip(keys, inside) if ok}, residuals),
            motion_share=motion / self.largest_motion_mm if self.largest_motion_mm > 0 else 1.0,
        )
        one_d = [key for key in sets if self._one_family.get(key)]
        if one_d:
            verdict.flag(
                DEGRADED,
                f'single-line tags on {len(one_d)} of {len(sets)} slices (1-D data): motion '
                "measured only across the tag lines; along them (and the heart's translation "
                'along them) it is not',
            )
        pairs = sorted(key for key in sets if self._pair_notes.get(key))
        if pairs:
            first = pairs[0]
            verdict.flag(
                DEGRADED,
                f'{PAIR_MISREGISTERED} on {len(pairs)} of {len(sets)} slices (two breath-holds, '
                f'{VIEW_NAMES[first[0]]} {first[1]}: {self._pair_notes[first]})',
            )
        return verdict

    def _tag_evidence(self, sets: dict) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the SA tag tracks' own circumferential strain per AHA segment and its uncertainty.

        Every SA slice's tracks with an ED reference, ED → this phase, in the analysis frame
        (:meth:`_rest_sectors`' frame), with each slice's measured localisation noise
        (``noise_mm``, else the default; :mod:`mlv_ros.core.analysis.tag_strain`). The model
        plays no part: what the data say where its smoothing may not.

        Parameters
        ----------
        sets : dict
            (view, slice) → TagPointSet of the phase.

        Returns
        -------
        tuple of ndarray
            ``tag_ecc``, ``tag_ecc_unc``, shape (17,) each (NaN: too few tracked edges).

        """
        if self._tag_edges is None:  # the ED edges: once per reference
            frame = LVFrame(*lv_frame_axes(self.rest, self.model.rest_params.rotation))
            keys = [k for k, ref in sorted(self.reference.items()) if k[0] == VIEW_SA and ref]
            self._tag_edges = (
                keys,
                [np.fromiter(self.reference[k], dtype=np.int64) for k in keys],
                TagEdges(
                    [(np.asarray(list(self.reference[k].values())), self.normals[k][0])
                     for k in keys],
                    frame,
                ),
            )
        keys, tids, edges = self._tag_edges
        now = np.full((edges.num_tracks, 3), np.nan)
        row = 0
        for key, tid in zip(keys, tids):
            pts = sets.get(key)
            if pts is not None and len(pts):
                hit, x = _track_rows(np.asarray(pts.track_id, dtype=np.int64),
                                     np.asarray(pts.position)).lookup(tid)
                now[row:row + len(tid)][hit] = x[hit]
            row += len(tid)
        sigma = [np.nan if self.noise_mm.get(k) is None else self.noise_mm[k] for k in keys]
        ev = edges.segment_strain(now, sigma)
        return ev['ecc'], ev['ecc_unc']

    def _sector_tracks(self, used: set, residuals: dict | None = None) -> dict:
        """
        Return per SA slice its ED tag points' angle (degrees), use, AHA segment and residual.

        The angle and segment are the analysis frame's (:func:`lv_frame_axes` of the model at
        rest), so that a sector the verdict names is the one the findings report.

        Parameters
        ----------
        used : set of tuple
            (view, slice, track_id) of the points this phase uses.
        residuals : dict, optional
            (view, slice, track_id) → in-plane residual of a used point, mm; without it the
            entries have no residuals.

        Returns
        -------
        dict
            SA slice index → (theta_deg, used, segment names[, residual_mm: NaN where not
            used]), for :func:`mlv_ros.core.verdict.weakest_sector` and
            :func:`~mlv_ros.core.verdict.worst_fit_sector`.

        """
        if self._sectors is None:  # the ED points' angles and segments: once per reference
            self._sectors = {}
            for (view, index), ref in self.reference.items():
                if view != VIEW_SA or not ref:
                    continue
                theta, seg, _ = self._rest_sectors(np.asarray(list(ref.values())))
                deg = np.degrees(theta)
                deg.flags.writeable = False
                self._sectors[index] = (deg, tuple(ref), [AHA_SEGMENT_NAMES[k - 1] for k in seg])
        out = {
            index: (deg, [(VIEW_SA, index, t) in used for t in tids], list(names))
            for index, (deg, tids, names) in self._sectors.items()
        }
        if residuals is not None:
            for index, (_, tids, _) in self._sectors.items():
                out[index] += ([residuals.get((VIEW_SA, index, t), np.nan) for t in tids],)
        return out

    def _multipliers(self) -> tuple[float, float]:
        """
        Return the data springs' κ and the fit-error penalty's multiplier.

        Both are scaled against the median elastic diagonal.
        """
        kscale, fit_scale = self._diagonal_medians
        return self.data_weight * kscale, self.hourglass_weight * kscale / fit_scale

    def _local_solve(self, phi, targets, normals, x_global, weights=None, rtol=None, scale=None):
        """
        Solve for the local deformation δ at elastic equilibrium under the in-plane tag forces.

        Paper: internal forces act on the local part only. Minimise ``κ Σ_k |P_k(Φ_k(x_g + δ) −
        t_k)|² + Σ_i v_i (μ |sym ∇δ_i|² + λ/2 tr(∇δ_i)²)`` plus the MLS fit error,
        near-incompressibility and axial stiffness (:mod:`mlv_ros.core.meshless.local`),
        warm-started from the previous phase.

        Parameters
        ----------
        phi : sparse (K, N)
            Control-point interpolation weights.
        targets, normals : ndarray, shape (K, 3)
            Measured positions (mm) and their image-plane normals.
        x_global : ndarray, shape (N, 3)
            Global-model particle positions, mm.
        weights : ndarray, shape (K,), optional
            Data weights (:func:`data_weights`); default all 1.
        rtol : float, optional
            CG tolerance; default ``cg_rtol``.
        scale : ndarray, shape (K,), optional
            Each point's noise scale (:meth:`_noise_scale`), multiplying its spring after the
            weights are scaled to mean 1; default all 1.

        Returns
        -------
        ndarray, shape (N, 3)
            δ, mm.

        """
        op, mu = self.model.operator, self.model.mu
        kappa, alpha = self._multipliers()
        # Near-incompressibility of the whole deformation (myocardium keeps its volume): the
        # linearised volume change of F = F_g + ∇δ, J_g (1 + F_g⁻ᵀ : ∇δ) − 1, is penalised
        # (about the warm start's F_g + ∇δ₀ when there is one: volume_about_start).
        # The global field's gradient and the warm start's (CG's first residual) in one pass.
        start = self.delta is not None and np.any(self.delta)
        known = self._local_gradients
        if start and known is not None and known[2] is self.delta:  # the start's, from its solve
            grads = [op.apply(x_global - self.rest)[0], known[3]]
        else:
            fields = (x_global - self.rest, self.delta) if start else (x_global - self.rest,)
            grads = op.apply(*fields)
        Fg = np.eye(3) + grads[0].reshape(-1, 3, 3).transpose(0, 2, 1)
        C, J0 = cofactors_3x3(Fg)  # cofactor J_g F_g⁻ᵀ of F_g
        offset = J0 - 1.0
        if start and self.volume_about_start:
            # Linearised about the warm start F₀ = F_g + ∇δ₀ instead of F_g alone:
            # det(F₀ + ∇(δ − δ₀)) ≈ J₀ + C₀ : ∇δ − C₀ : ∇δ₀. About F_g the δ that restores the
            # affine shape's lost wall volume (J_g − 1 ≈ −0.4 at ES) is itself large, and the
            # neglected second-order terms of det leave the solved wall 2–3 % short of its volume
            # whatever the weight (7303 with exact points: median det F 0.975 at volume_weight
            # 4000, 16000 and 64000); about the start only the phase's change is linearised.
            hd = grads[1].reshape(-1, 3, 3).transpose(0, 2, 1)
            C, J0 = cofactors_3x3(Fg + hd)
            offset = J0 - 1.0 - np.einsum('nab,nab->n', C, hd)
        C[np.abs(J0) <= 1e-6] = 0.0
        # Local longitudinal stretch (along the fitted long axis) costs kl; see
        # longitudinal_weight.
        ax = quat_to_matrix(self.model.params.rotation)[:, 2]
        shear = self._axial_shear(ax)
        target = None
        if self.contraction_prior:
            hd = grads[1].reshape(-1, 3, 3).transpose(0, 2, 1) if start else None
            target = self._contraction_prior(ax, Fg, hd, x_global)
        if self.longitudinal_coupling:
            ax = self._coupled_axial(ax, Fg, x_global)
        w = control_weights(weights, len(targets))
        if scale is not None:
            w = w * scale  # absolute: the noise scale is not renormalised, confidences are
        P = plane_projectors(normals, len(normals)) * w[:, None, None]
        # The phase's later passes reuse its first pass's coarse factor (LocalOperators.system).
        reuse = self._phase_coarse
        system = self._local.system(
            fit_error=alpha,
            volume=(self.volume_weight * mu, C, offset),
            axial=(self.longitudinal_weight * mu, ax, target),
            data=(kappa, phi, P),
            eps=rigid_mode_eps(kappa),
            coarse=self._coarse if reuse is None else None,
            coarse_correction=reuse,
            shear=shear,
        )
        self._phase_coarse = system.coarse_correction
        r = np.einsum('kab,kb->ka', P, targets - phi @ x_global)
        rhs, residual = system.right_hand_side(
            kappa * (phi.T @ r), self.delta if start else None, grads[-1] if start else None
        )
        delta, its = system.solve(
            rhs,
            self.delta,
            rtol=self.cg_rtol if rtol is None else rtol,
            maxiter=self.cg_maxiter,
            residual=residual,
            gradient_x0=grads[-1] if start else np.zeros((3 * len(x_global), 3)),
        )
        self.cg_iterations.append(its)
        self._local_gradients = (x_global, grads[0], delta, system.solution_gradient)
        return delta

    def _axial_shear(self, ax):
        """
        Return the local stage's transmural axial shear term ``(k_s, M)``, or None.

        Only the LA planes measure axial motion, and a plane measures it only where it cuts the
        wall: the local stage's transmural axial shear ``∂δ_a/∂r`` is seen by no SA point and by
        an LA point only at its own angle, and against the elasticity alone (μ) it is the
        cheapest way to repay the volume the global stage leaves to the local one (the paper's
        affine shape loses ~42 % of the wall's volume at ES; with ``global_thickening``, what the
        tracked points miss of the thickening, issue 20). The wall then moved along the axis
        between the LA planes, more the more one plane's points held it at that plane: study
        2007 (one LA view tracked), every tracked point where the truth puts it, ES median / p95
        0.288 / 0.878 mm, 0.321 / 0.986 with a confirm variant keeping six more of that view's
        tracks at ES (docs/benchmarks.md, la19), its error along the axis +0.6…+1.0 mm 90° from
        the plane and ≈ 0 at it, the global stage's ±0.03 mm everywhere. The term
        ``½ k_s Σ_i v_i (aᵀ H_i r_i)²`` (``r_i`` the particle's rest radial direction about the
        long axis, ``a`` the fitted axis) costs that shear as the axial term costs the local
        longitudinal stretch, for the same reason and with the same stiffness
        (``longitudinal_weight``). It is in the coarse space as well
        (:class:`~mlv_ros.core.meshless.local.CoarseSpace`, ``shear``).

        Parameters
        ----------
        ax : ndarray, shape (3,)
            The fitted long axis (unit).

        Returns
        -------
        (float, ndarray of shape (N, 3, 3)) or None
            ``k_s`` (P) and the measures ``M_i = a r_iᵀ``; None with ``longitudinal_weight`` 0.

        """
        if not self.longitudinal_weight:
            return None
        return (
            self.longitudinal_weight * self.model.mu,
            ax[None, :, None] * self._rest_radial()[:, None, :],
        )

    def _rest_radial(self) -> np.ndarray:
        """Return each particle's rest radial direction about the rest long axis, (N, 3) unit."""
        if self._radial is None:
            rest = self.model.rest_params
            axis = quat_to_matrix(rest.rotation)[:, 2]
            v = self.rest - rest.translation
            v = v - np.outer(v @ axis, axis)
            self._radial = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)
            self._radial.flags.writeable = False
        return self._radial

    def _coupled_axial(self, ax, Fg, x_global) -> np.ndarray:
        """
        Return the per-particle measure ``M_i = a aᵀ − w_i ρ c_i c_iᵀ`` of the axial term, (N,3,3).

        See ``longitudinal_coupling``. ``M_i : H_i`` is the local longitudinal strain less w_i ρ
        times the local circumferential one (``c_i`` the circumferential direction about the
        fitted axis ``a``). ρ = ``longitudinal_coupling`` × the global fit's median longitudinal
        over circumferential linear strain, within [0, 2]; 0 while the global circumferential
        strain is above −0.02 (near ED: no ratio to read, no deviation to couple). ``w_i`` is the
        region's weight (:meth:`_coupling_weight`; 1 everywhere when ``regional_coupling`` is
        off).
        """
        circ = np.cross(ax, x_global - self.model.params.translation)
        circ /= np.maximum(np.linalg.norm(circ, axis=1, keepdims=True), 1e-9)
        hg = Fg - np.eye(3)
        ell = float(np.median(np.einsum('a,nab,b->n', ax, hg, ax)))
        ecc = float(np.median(np.einsum('na,nab,nb->n', circ, hg, circ)))
        rho = (
            self.longitudinal_coupling * float(np.clip(ell / ecc, 0.0, 2.0))
            if ecc < -0.02
            else 0.0
        )
        w = self._coupling_weight() if rho and self.regional_coupling else 1.0
        if self._far is not None and self.contraction_prior:
            w = w * (1.0 - self._far)  # where the contraction prior holds the axial strain
        self.coupling_weight = np.broadcast_to(np.asarray(w, np.float64), (len(circ),))
        return np.outer(ax, ax)[None] - (rho * self.coupling_weight)[
            :, None, None
        ] * circ[:, :, None] * circ[:, None, :]

    def _contraction_prior(self, ax, Fg, hd, x_global):
        """
        Return the axial term's targets: far from LA tag points, Ell follows the column's Ecc.

        Only LA planes measure the long-axis motion. Far from their tag points (between the SA
        planes) a region's local longitudinal strain is held to ``κ (Ēcc_i − m_i)`` (``m_i`` the
        median of ``Ēcc`` over the particle's level; :meth:`_long_axis_support`: ``Ēcc`` the
        transmural mean of the local circumferential
        linear strain of the start δ, κ the heart's own Ell / Ecc near LA tag points) instead of
        0 (the global fit's): an akinetic sector that no LA plane crosses is not given its
        neighbours' shortening. A deviation from the level (:meth:`_level_median`), since the
        base-to-apex gradient of Ecc is no sector's (apical Ecc is larger, Ell is not). Weight
        ``contraction_prior`` (0: off).

        Parameters
        ----------
        ax : ndarray, shape (3,)
            The fitted long axis (unit).
        Fg : ndarray, shape (N, 3, 3)
            The global fit's deformation gradients.
        hd : ndarray, shape (N, 3, 3) or None
            The displacement gradients of the start δ (None: no start, no prior).
        x_global : ndarray, shape (N, 3)
            The global fit's positions, mm.

        Returns
        -------
        ndarray, shape (N,) or None
            The targets of ``aᵀ H_i a`` (local, strain); None where there is no prior.

        """
        self._far = None
        if hd is None:
            return None
        support = self._long_axis_support(ax, Fg - np.eye(3) + hd, x_global)
        if support is None:
            return None
        far, kappa, columns, circ = support
        dev = columns @ np.einsum('na,nab,nb->n', circ, hd, circ)
        dev = dev - self._level_median(dev)
        self._far = self.contraction_prior * far
        return self._far * kappa * dev

    def _long_axis_support(self, ax, h, x):
        """
        Return where no LA tag point sees the long-axis motion, and what the SA tags say there.

        Parameters
        ----------
        ax : ndarray, shape (3,)
            The fitted long axis (unit).
        h : ndarray, shape (N, 3, 3)
            Displacement gradients of the motion.
        x : ndarray, shape (N, 3)
            Particle positions, mm (the circumferential directions about the fitted axis).

        Returns
        -------
        tuple or None
            ``far`` (N,): 0 within half an SA spacing of the nearest LA tag point (ED), rising to
            1 at one spacing, 0 outside the SA planes' span (the apical cap's Ecc is
            ill-defined); κ: ``Σ Ēll Ēcc / Σ Ēcc²`` over the particles near LA points, in [0, 2]
            (``Ēcc``, ``Ēll`` the linear strains' transmural means, :meth:`_column_matrix`);
            the column matrix; the circumferential directions (N, 3). None
            without LA points, SA spacing or contraction (median Ecc > −0.02), or with fewer
            than 10 particles near LA points or none far.

        """
        spacing = self._sa_spacing()
        if self._la_rest is None or len(self._la_rest) < 4 or spacing is None:
            return None
        circ = np.cross(ax, x - self.model.params.translation)
        circ /= np.maximum(np.linalg.norm(circ, axis=1, keepdims=True), 1e-9)
        ecc = np.einsum('na,nab,nb->n', circ, h, circ)
        if float(np.median(ecc)) > -0.02:
            return None
        columns = self._column_matrix(spacing)
        mean_ecc = columns @ ecc
        mean_ell = columns @ np.einsum('a,nab,b->n', ax, h, ax)
        d, _ = cKDTree(self._la_rest).query(self.rest)
        far = np.clip(2.0 * d / spacing - 1.0, 0.0, 1.0)
        axis = quat_to_matrix(self.model.rest_params.rotation)[:, 2]
        levels = [
            float(np.dot(pt, axis)) for (v, _), (_, pt) in self.normals.items() if v == VIEW_SA
        ]
        z = self.rest @ axis
        far[(z < min(levels)) | (z > max(levels))] = 0.0
        near = far == 0.0
        den = float(mean_ecc[near] @ mean_ecc[near])
        if not far.any() or near.sum() < 10 or den <= 0.0:
            return None
        kappa = float(np.clip(mean_ell[near] @ mean_ecc[near] / den, 0.0, 2.0))
        return far, kappa, columns, circ

    def _particle_segments(self):
        """Return each particle's AHA segment (N,) and ED axial coordinate (N,), mm (cached)."""
        if getattr(self, '_segments', None) is None:
            _, seg, frame = self._rest_sectors(self.rest, clip_levels=True)
            self._segments = (seg, frame.axial(self.rest))
        return self._segments

    def _rest_sectors(self, X, clip_levels: bool = False):
        """
        Return ED points' angle about the axis (rad), AHA segment and the LV frame they are in.

        The frame is the registered model's at rest (:func:`lv_frame_axes`); ``clip_levels``
        puts points beyond the apex or the base into the end rings.
        """
        frame = LVFrame(*lv_frame_axes(self.rest, self.model.rest_params.rotation))
        ie = frame.inplane(X)
        theta = np.arctan2(ie[:, 1], ie[:, 0])
        level = frame.level(X)
        if clip_levels:
            level = np.clip(level, 0.0, 1.0)
        return theta, aha_segments(level, theta, frame.aha_origin_deg), frame

    def _level_median(self, values) -> np.ndarray:
        """
        Return per particle the median of ``values`` over its level, shape (N,).

        Levels: bins of half an SA spacing along the ED axis, so that a deviation from it is
        the sector's, not the wall's base-to-apex gradient (the apex's Ecc is larger).
        """
        _, z = self._particle_segments()
        spacing = self._sa_spacing() or 1.0
        bins = np.floor((z - z.min()) / (0.5 * spacing)).astype(np.int64)
        out = np.empty(len(values))
        for b in np.unique(bins):
            m = bins == b
            out[m] = np.median(values[m])
        return out

    def _sa_spacing(self) -> float | None:
        """Return the median spacing of the SA planes along the fitted axis, mm (None: < 2)."""
        axis = quat_to_matrix(self.model.params.rotation)[:, 2]
        levels = sorted(
            float(np.dot(pt, axis))
            for (view, _), (_, pt) in self.normals.items()
            if view == VIEW_SA
        )
        gaps = np.diff(levels)
        gaps = np.abs(gaps[np.abs(gaps) > 1e-3])
        return float(np.median(gaps)) if gaps.size else None

    def _column_matrix(self, spacing):
        """
        Return the sparse (N, N) mean over each particle's wall column (built once).

        The particles whose ED positions, moved radially onto the median radius about the ED
        axis, lie within a quarter SA spacing of the particle's: the wall through it, not its
        endo–epicardial gradient.
        """
        if self._columns is None:
            rest = self.model.rest_params
            axis = quat_to_matrix(rest.rotation)[:, 2]
            v = self.rest - rest.translation
            z = v @ axis
            r = v - np.outer(z, axis)
            rad = np.linalg.norm(r, axis=1)
            q = np.outer(z, axis) + float(np.median(rad)) * r / np.maximum(rad, 1e-9)[:, None]
            tree = cKDTree(q)
            pairs = tree.sparse_distance_matrix(tree, 0.25 * spacing, output_type='ndarray')
            n = len(q)
            m = sp.csr_matrix(
                (np.ones(len(pairs) + n), (np.r_[pairs['i'], np.arange(n)],
                                           np.r_[pairs['j'], np.arange(n)])),
                shape=(n, n),
            )
            m.sum_duplicates()
            m.data[:] = 1.0
            self._columns = sp.diags(1.0 / np.asarray(m.sum(axis=1)).ravel()) @ m
        return self._columns

    def _coupling_weight(self) -> np.ndarray:
        """
        Return each particle's share of the coupling: near tag points the motion left inward.

        ``max(COUPLING_MEMORY × the previous weight, max_k w_k t(d_ik))`` over the points k the
        previous pass flagged (:meth:`_outward_points`, their weights ``w_k`` and reach ℓ) at ED
        distance ``d_ik < ℓ``, with the taper ``t(d) = min(1, (1 − d / ℓ) / (1 − p))``, p =
        ``coupling_plateau`` (0: the hat ``1 − d / ℓ``); the memory carries a region found at one
        phase into the next, where its points may fall short of the threshold.

        Returns
        -------
        ndarray, shape (N,)
            Weights in [0, 1].

        """
        w = np.zeros(self.rest.shape[0])
        if COUPLING_MEMORY and self._coupling_map is not None:
            w = COUPLING_MEMORY * self._coupling_map
        if self._flagged is None:
            return w
        pts, wk, ell = self._flagged
        # every flagged point's particles at once; a maximum is the same in any order
        lists = self._tree.query_ball_point(pts, ell)
        counts = np.fromiter(map(len, lists), dtype=np.int64, count=len(lists))
        idx = np.fromiter(chain.from_iterable(lists), dtype=np.int64, count=int(counts.sum()))
        k = np.repeat(np.arange(len(lists)), counts)
        d = np.linalg.norm(self.rest[idx] - pts[k], axis=1)
        taper = 1.0 - d / ell
        if self.coupling_plateau:
            taper = np.minimum(1.0, taper / (1.0 - self.coupling_plateau))
        np.maximum.at(w, idx, wk[k] * taper)
        self._coupling_map = w
        return w

    def _outward_points(self, ctrl, targets, normals):
        """
        Flag the tag points the motion leaves inward of their targets, beyond the study's spread.

        The outward (away from the long axis) component of each in-plane residual, as robust
        z-scores over the phase's points (median, 1.4826 × MAD): weight 0 at ``COUPLING_Z[0]``
        rising to 1 at ``COUPLING_Z[1]``. Returns None when no point is flagged, else their ED
        positions (M, 3), weights (M,) and the reach ℓ (mm): ``COUPLING_REACH`` × the median
        spacing of the SA planes.

        A region that contracts less than the wall around it (akinetic, hypokinetic, or stretching)
        leaves its few tag points outward of the smoothed motion; a tracking error has no preferred
        direction. Relative to the phase's own residual spread, so it holds for any noise level,
        pixel size and tag period.

        Parameters
        ----------
        ctrl : ControlPoints
            The pass's attachment of the tag points used.
        targets, normals : ndarray, shape (K, 3)
            Their measured positions (mm) and image-plane normals.

        """
        x = ctrl.weights @ self.positions
        res = np.einsum('kab,kb->ka', plane_projectors(normals, len(normals)), targets - x)
        axis = quat_to_matrix(self.model.params.rotation)[:, 2]
        v = x - self.model.params.translation
        radial = v - (v @ axis)[:, None] * axis
        radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9)
        out = np.einsum('ka,ka->k', res, radial)
        med = float(np.median(out))
        sigma = max(1.4826 * float(np.median(np.abs(out - med))), 1e-6)
        z0, z1 = COUPLING_Z
        wk = np.clip(((out - med) / sigma - z0) / (z1 - z0), 0.0, 1.0)
        spacing = self._sa_spacing()
        if not wk.any() or spacing is None:
            return None
        keep = wk > 0
        return ctrl.rest_positions[keep], wk[keep], COUPLING_REACH * spacing

    def _twist_function(self, phi, targets, normals, x, sa_slice, weights=None):
        """
        Fit the twist as a parameter function of height and rotate the particles by it.

        The parameter functions of Park et al., which the paper's model builds on: rotate each
        particle about the model's long axis by ``Δφ(h)``, piecewise linear between ``twist_knots``
        uniform knots in the material height h, fitted to the in-plane tag residuals of the global
        fit by penalised least squares (second differences of the knot values, a P-spline). It
        follows the data between the lowest and the highest SA tag point, and only when at least
        ``TWIST_MIN_SA`` SA slices spanning ``TWIST_MIN_SPAN`` of the height measure it: from two
        close slices a gradient extrapolated to the apex is noise times a lever (measured: 60°
        apical twist, p95 error 10 mm).

        The twist is each level's rotation about its own centre (as the analysis measures it), so
        each SA slice with at least ``TWIST_SHIFT_MIN_POINTS`` tag points also gets a free
        in-plane shift in the fit (:func:`_slice_shifts`, two unknowns per slice, not applied).
        The global stage moves every level alike; whatever shift of a slice it leaves, with that
        slice's tracks not spread evenly round it (a thin apical wall that loses tracks), read as
        rotation about the one long axis. Measured on study 1011 (infarct, stack ending at 0.23
        of the height), ES: with the truth's tag points the apical level was 1.30° off, 0.06°
        with the shifts; with the tracked ones 3.14° → 2.45°, the rest being the tracker's
        apical slices (their ES twist ±0.3° off the truth's points, phase-to-phase noise, which
        the extrapolation's lever multiplies).

        Beyond that span only LA planes see the wall, and they do not measure circumferential
        motion. There each particle's *total* twist (the global stage's ``π τ g`` since ED plus
        ``Δφ``) continues linearly in height from its value at the span's end. The global twist
        alone flattens toward the apex (``g = sin α``), and the P-spline's own end slope rests on
        the last slices' residuals: with exact tags and the stack ending at 0.36–0.45 of the
        height, holding it turned the apex 10–12° the wrong way. The gradient follows what is
        known of the LV: rotation changes monotonically from base to apex and its gradient grows
        toward the apex (end-systole: apex ≈ +10°, base ≈ −3°, zero rotation near mid-ventricle;
        Young & Cowan, J Cardiovasc Magn Reson 2012;14:49, and the paper's Fig. 9). So beyond
        the apical end the gradient is the steeper of the span's mean gradient (a least-squares
        line through the total twist of the particles within the span) and the gradient over
        the span's last knot interval, beyond the basal end the shallower; an end gradient of the
        other sign than the mean is noise, and is replaced by the mean (apical) or by none
        (basal). The result stays labelled extrapolated, with how far beyond the slices and how
        uncertain (:func:`~mlv_ros.core.analysis.frame.twist_extrapolation_note`, with
        ``twist_gradient_se``).

        The last knot interval's gradient is used only as far as the SA slices support it. Each
        slice's own twist at this phase, with its standard error from its tag points (their
        count, their spread round the slice, their residual: :func:`_slice_twists`), gives an end
        gradient (the lowest two slices, or highest two) and a mean gradient; the P-spline's end
        gradient may differ from its mean by no more than the slices' difference ± two standard
        errors (:func:`_end_intervals`). The P-spline's end gradient can rest on what no slice
        measures: the heights of one slice's points (its points span 0.09 of the height) and the
        knots below the stack. Fresh study 5007 (stack from 0.41, 1.74 mm pixels, ES): the
        P-spline's apical gradient was 45°/height against the slices' 5.7 ± 6.9 and their mean
        5.4; apex 10.99° off, 2.63° capped (truth 7.6°, steepening below the stack to 13–24°/h).

        Chosen against the truth over the randomized-protocol studies (ES, each rule solving the
        same phase from the same state; the largest twist error over the levels): on the 24 of
        1000–1015 and 2000–2007 this rule's median / max is 0.40° / 1.83°, against 0.85° / 2.37°
        for the mean gradient, 0.61° / 2.11° for the gradient over the half span nearest the
        end, 0.63° / 2.10° for the average of the end and mean gradients and 1.69° / 3.16° for
        the span's least-squares line itself (the end gradient was the steeper in all 24); on
        the unseen 3000–3005 0.72° / 1.94° against 0.92° / 2.39° at best. Their truth steepens
        toward the apex; on synthetic profiles that are linear or flatten there, with the lowest
        slice's twist misread by 1°, the rule stays within the stated uncertainty
        (``test_extrapolated_twist_stays_within_its_stated_uncertainty``). Redone on 48 studies
        (issue 14: the 40 kept of 1000–1015, 2000–2007, 3000–3007, 4000–4007 and the fresh
        5000–5007; ES solved from the same state, recorded tag points; median / max of the
        largest level error, studies within 2°): this rule 0.43° / 2.63°, 46 (the kept 40
        unchanged, 0.41° / 2.15°, 39; only 5007 changes), against 0.43° / 10.99°, 46 without
        the cap; 0.70° / 4.07°, 42 shrinking the end gradient toward the mean by its
        significance (``d² / (d² + σ_d²)``, from the slices); 0.52° / 4.07°, 45 the slices' own
        end gradient in place of the P-spline's; a cap of one standard error 0.43° / 2.15°, 47
        (5007 1.48°; not taken: it is that study that would choose it). What leaves the largest
        apical errors is not the extrapolation but the local stage after it: the apical level
        bin of 3001 / 1001 / 1012 is −1.94° / −1.83° / −1.30° off, −0.56° / −0.10° / −0.32°
        with the global stage and this function alone, and with the same tracks at their true
        positions −0.81° / −0.53° / −0.36° (+0.33° / +0.50° / −0.01° alone): the tag springs
        follow the apical tracks' error and the local stage takes about 1° off the apex even
        from exact points (``bench/retrack.py --twist``, ``--ideal``).

        Why, measured on those exact points (issue 14, ``bench/local_twist.py --ideal``: each
        variant re-solves the ES local stage from the same global configuration, CG to 1e-6; apical
        bin error default → variant, 3001 / 1001 / 1012): no one term, and none that a weight would
        mend. The apical cap's rotation is a soft mode of the local stage: no SA point measures it
        and the LA springs do not (with the SA points' weights 0 every level errs by +6 to +10°),
        so target offsets of 0.005–0.05 mm (median) or a volume force move it by 0.5–2°. (1) The
        volume term's offset: the global stage does not conserve volume (its ES J − 1 is −0.43 at
        every level on all three, the truth's −0.001…−0.007), so the local stage restores the 43 %
        through the linearised ``J_g(1 + F_g⁻ᵀ : ∇δ)``; dropping only the offset ``J_g − 1`` swings
        3001's apex −0.93 → +1.19° (1001 −0.54 → −0.58, 1012 −0.36 → −0.48), the whole volume term
        off −0.61 / −0.52 / −0.35°. With the tracked points 3001's apex is −2.00°, −0.19° without
        the offset. The local stage overshoots the apical cap's volume (J − 1 +0.07 / +0.11 / +0.08
        in the apical bin) and the offset's pull there is not through δ's rotations coupling to
        ``F_g⁻ᵀ``: the cofactor's symmetric part alone makes it worse (3001 −0.93 → −1.47°, tracked
        −2.00 → −3.27°). (2) The apical SA targets against the material point the slice following
        attached (median through-plane miss 0.07 mm on 1001's lowest slice): the truth of the
        attached points as targets mends 1001 (−0.54 → −0.12°), not 3001 (−0.92) or 1012 (−0.35); a
        second following pass (``slice_following=2``, every phase) leaves 1001 at −0.54°. (3) Data
        weight ×10 / ÷10: −0.67 / −0.71, −1.53 / −0.20, −0.21 / −0.55, no common direction; the
        fit-error weight ×10 −0.52° on 3001, −0.60° on 1012; the axial stiffness or its coupling
        off within 0.13° of the default on all three.

        Parameters
        ----------
        phi : sparse (K, N)
            Control-point interpolation weights.
        targets, normals : ndarray, shape (K, 3)
            Measured positions (mm) and their image-plane normals.
        x : ndarray, shape (N, 3)
            Global-model particle positions, mm.
        sa_slice : ndarray of int, shape (K,)
            The SA slice of each control point, -1 on LA views (SA slices are the ones that
            measure circumferential motion).
        weights : ndarray, shape (K,), optional
            Data weights (:func:`data_weights`); default all 1.

        Returns
        -------
        ndarray, shape (N, 3)
            ``x`` with the fitted twist applied (``x`` itself when the SA data cannot support it),
            mm.

        """
        sa_slice = np.asarray(sa_slice)
        h_points = np.asarray(phi @ self._height).ravel()  # each point's material height
        h_sa = h_points[sa_slice >= 0]
        num_sa_slices = len(np.unique(sa_slice[sa_slice >= 0]))
        if num_sa_slices < TWIST_MIN_SA or np.ptp(h_sa) < TWIST_MIN_SPAN:
            self.twist_coefficients, self.twist_gradient_se = np.zeros(0), None
            return x
        R = quat_to_matrix(self.model.params.rotation)
        axis, centre = R[:, 2], self.model.params.translation
        m, height = self.twist_knots, self._height
        if self._hats is None or self._hats.shape[1] != m:  # material: once per model
            self._hats = _knot_hats(height, m)  # (N, m)
            self._hats.flags.writeable = False
        hat = self._hats
        # Each tag point's weighted projector, in-plane residual and shift basis: the knots'
        # fit and the slices' own twists share them.
        P, residual, shift = self._twist_rows(phi, targets, normals, x, weights, axis)
        tang = np.cross(axis, x - centre)  # ∂x/∂φ, each particle's motion per radian, mm/rad
        self.twist_coefficients = self._fit_twist_knots(
            phi, tang, P, residual, shift, hat, sa_slice
        )
        # The global stage's own twist of each particle since ED (φ = π τ g, eq. 2–3), radians.
        psi = (
            np.pi * (self.model.params.tau - self.model.rest_params.tau) * self.model.coords.twist
        )
        slices = _slice_twists(
            np.einsum('kab,kb->ka', P, phi @ tang),
            residual,
            shift,
            sa_slice,
            h_points,
            np.asarray(phi @ psi).ravel(),
        )
        angle, self.twist_gradient_se = _twist_angle(
            height, psi, hat, self.twist_coefficients, float(h_sa.min()), float(h_sa.max()),
            slices,
        )
        if self.twist_gradient_se is not None:
            every = np.ones(len(slices[0]), bool)
            self.twist_mean_gradient = float(_slope_rows(slices[0], slices[2], every) @ slices[1])
        return _rotate_about_axis(x, centre, axis, angle)

    @staticmethod
    def _twist_rows(phi, targets, normals, x, weights, axis):
        """
        Return each tag point's weighted in-plane projector, residual and shifts.

        Parameters
        ----------
        phi, targets, normals, x, weights
            As in :meth:`_twist_function`.
        axis : ndarray, shape (3,)
            The long axis, unit.

        Returns
        -------
        P : ndarray, shape (K, 3, 3)
            In-plane projectors, each scaled by the square root of its point's data weight.
        residual : ndarray, shape (K, 3)
            In-plane residual ``P (target − Φ x)``, mm.
        shift : ndarray, shape (K, 3, 2)
            In-plane motion per mm of shift along two directions ⟂ the axis.

        """
        P = (
            plane_projectors(normals, len(normals))
            * np.sqrt(control_weights(weights, len(targets)))[:, None, None]
        )
        e1 = np.cross(axis, np.eye(3)[int(np.argmin(np.abs(axis)))])
        e1 /= np.linalg.norm(e1)
        residual = np.einsum('kab,kb->ka', P, targets - phi @ x)
        shift = np.einsum('kab,eb->kae', P, np.stack([e1, np.cross(axis, e1)]))
        return P, residual, shift

    def _fit_twist_knots(self, phi, tang, P, residual, shift, hat, sa_slice):
        """
        Return the twist's knot values fitted to the in-plane tag residuals (P-spline), radians.

        Parameters
        ----------
        phi : sparse matrix, shape (K, N)
            The control points' weights.
        tang : ndarray, shape (N, 3)
            Each particle's motion per radian of twist about the long axis, mm/rad.
        P, residual, shift
            Each control point's weighted in-plane projector (K, 3, 3), residual (K, 3) and
            shift basis (K, 3, 2) (:meth:`_twist_rows`).
        hat : ndarray, shape (N, m)
            The knots' hat functions at each particle's height (:func:`_knot_hats`).
        sa_slice : ndarray of int, shape (K,)
            The SA slice of each control point, -1 on LA views.

        Returns
        -------
        ndarray, shape (m,)
            Knot values, radians.

        """
        m = hat.shape[1]
        # ∂(P Φ x)/∂(knot j) for all knots from one sparse product with 3m columns
        moved = (phi @ (tang[:, :, None] * hat[:, None, :]).reshape(len(tang), 3 * m)).reshape(
            -1, 3, m
        )
        J = np.matmul(P, moved).reshape(-1, m)
        lam = self.twist_smoothing * float(np.sum(J * J)) / m  # relative to the data term's scale
        shifts = _slice_shifts(shift, sa_slice)
        return _pspline(np.hstack([J, shifts]), residual.ravel(), lam, free=shifts.shape[1])[:m]

    def _outliers(self, x, targets, normals) -> np.ndarray:
        """Return which in-plane residuals exceed ``max(outlier_mm, med + outlier_sigmas σ)``."""
        P = plane_projectors(normals, len(normals))
        r = np.linalg.norm(np.einsum('kab,kb->ka', P, targets - x), axis=1)
        med = float(np.median(r))
        sigma = 1.4826 * float(np.median(np.abs(r - med)))
        return r > max(self.outlier_mm, med + self.outlier_sigmas * sigma)

    def _positions_gradient(self) -> np.ndarray:
        """
        Return the displacement gradient of :attr:`positions`, shape (N, 3, 3).

        ``H[i, a, b] = ∂u_a/∂X_b``, computed once per positions array (a phase's last slice
        following and its solution share it).
        """
        if self._gradient is None or self._gradient[0] is not self.positions:
            H = self.model.operator.gradient(self.positions - self.rest)
            self._gradient = (self.positions, H)
        return self._gradient[1]

    def _follow_slices(self, offsets, rest, normals, targets, inside, ctrl):
        """
        Take a Newton step on s per control point.

        Bring the model position of the material line ``p0 + s n`` back onto the image plane (the
        plane through the measured target).

        ``ctrl``: the pass's attachment of ``p0 + s n`` for the points ``inside`` (in their
        order). The step's derivative ``n · F n`` at ``p0 + s n`` takes the particles' deformation
        gradients ``F = I + H`` (:meth:`_positions_gradient`) interpolated with the attachment's
        weights: exact for an affine motion, and no second attachment. It replaced the secant
        through a probe attached 1 mm along the normal (5 ms a pass at 3000 particles); a point
        whose probe lies beyond ``max_attach_mm`` of the model still takes no step (stepping
        them too moved the infarct preset's ES p95 and radius errors by 0.055 mm).
        """
        new = offsets.copy()
        idx = np.flatnonzero(inside)
        if idx.size == 0:
            return new
        n = _plane_normals(normals)[idx]
        x0 = ctrl.weights @ self.positions
        Hk = (ctrl.weights @ self._positions_gradient().reshape(-1, 9)).reshape(-1, 3, 3)
        f0 = np.einsum('ij,ij->i', x0 - targets[idx], n)
        df = 1.0 + np.einsum('ka,kab,kb->k', n, Hk, n)
        probe_in = self._tree.query(rest[idx] + (offsets[idx, None] + 1.0) * n)[0]
        good = np.isfinite(f0) & np.isfinite(df) & (np.abs(df) > 0.2)
        good &= probe_in <= self.max_attach_mm
        step = np.zeros(idx.size)
        step[good] = -f0[good] / df[good]
        new[idx] = offsets[idx] + np.clip(step, -self.follow_step_mm, self.follow_step_mm)
        return new


def _line_rows(pts: TagPointSet, hit) -> np.ndarray:
    """Return the tag-line normals of ``pts``' rows ``hit``, NaN rows for grid points, (H, 3)."""
    line = np.asarray(pts.line_normal, dtype=np.float64)
    if line.shape != (len(pts), 3):
        return np.full((int(np.count_nonzero(hit)), 3), np.nan)
    return line[hit]


def _one_line_family(pts: TagPointSet) -> bool:
    """
    Return whether a slice's points lie on one family of tag lines only (1-D data).

    Its line normals' in-plane angles (mod 180°) are compared with their dominant one (the
    angle with the most normals within half of ``MIN_DIRECTION_SEPARATION`` of it): fewer than
    ``MIN_SLICE_POINTS`` at least ``MIN_DIRECTION_SEPARATION`` (30°, the tag estimate's least
    angle between two families) away from it is one family. (The doubled-angle mean lies
    midway between two families as large as each other, under 30° from both when they are
    under 60° apart.) A grid slice (no line normals) is not. Meant for the ED points (straight
    lines): deformed lines turn by more than that where the wall shears.
    """
    line = np.asarray(pts.line_normal, dtype=np.float64).reshape(-1, 3)
    line = line[np.isfinite(line).all(axis=1)]
    if line.shape[0] == 0 or pts.geometry is None:
        return False
    g = pts.geometry
    angle = np.arctan2(line @ g.column_direction, line @ g.row_direction)
    apart = np.abs(np.angle(np.exp(2j * (angle[:, None] - angle[None, :])))) / 2  # 0..π/2
    dominant = angle[int(np.argmax((apart < 0.5 * MIN_DIRECTION_SEPARATION).sum(axis=1)))]
    off = np.abs(np.angle(np.exp(2j * (angle - dominant)))) / 2  # 0..π/2
    return int(np.count_nonzero(off >= MIN_DIRECTION_SEPARATION)) < MIN_SLICE_POINTS


def _plane_normals(normals) -> np.ndarray:
    """Return the image-plane normals (K, 3) of (K, 3) normals or (K, 2, 3) (ν, n) pairs."""
    return normals[:, 0] if normals.ndim == 3 else normals


def _model_frame(pts, centre, rotation, R, a0, polar, shape) -> ModelFrame:
    """
    Return the model's frame: from given polar coordinates and shape, or fitted to the particles.

    Parameters
    ----------
    pts : ndarray, shape (N, 3)
        Particle positions at ED, mm.
    centre : array_like, shape (3,)
        Model centre, mm.
    rotation : array_like, shape (4,)
        Model orientation quaternion.
    R : ndarray, shape (3, 3)
        ``rotation`` as a matrix (its columns the model's axes).
    a0 : float or None
        Model scale, mm.
    polar : tuple or None
        Given polar coordinates (:meth:`ModelCoordinates.polar`'s arguments); None: fitted.
    shape : sequence of 5 floats or None
        Shape parameters (4 scales, taper) with ``polar``; None: ``(a0 or 1, 1, 1, 1, 0)``.

    Returns
    -------
    ModelFrame
        The frame.

    """
    if polar is not None:
        a = shape if shape is not None else (a0 or 1.0, 1.0, 1.0, 1.0, 0.0)
        params = GlobalParameters(
            np.asarray(centre, float), np.asarray(rotation, float), a[:4], a[4]
        )
        return ModelFrame(params, ModelCoordinates.polar(*polar))
    return polar_frame(pts, centre, R[:, 2], R[:, 0], a0)


@dataclass(frozen=True)
class _TrackRows:
    """
    One slice's positions per track id, sorted by id: what a dict per track held, as arrays.

    Parameters
    ----------
    track_id : ndarray of int, shape (T,)
        Track ids, ascending and distinct.
    position : ndarray, shape (T, 3)
        Their positions, mm.

    """

    track_id: np.ndarray
    position: np.ndarray

    def lookup(self, track_id):
        """
        Return which of ``track_id`` (shape (K,)) are held, and their positions (K, 3) in mm.

        Rows of ids not held are the first held position (meaningless; mask them).
        """
        if self.track_id.size == 0:
            return np.zeros(len(track_id), dtype=bool), np.zeros((len(track_id), 3))
        j = np.minimum(np.searchsorted(self.track_id, track_id), self.track_id.size - 1)
        return self.track_id[j] == track_id, self.position[j]


def _track_rows(track_id, position, before=None) -> _TrackRows:
    """
    Return ``position`` (K, 3) per ``track_id`` (K,), a repeated id's last kept (as a dict would).

    ``before``: rows held already, which keep the ids that ``track_id`` lacks.
    """
    tid = np.asarray(track_id, dtype=np.int64)
    pos = np.asarray(position)
    if before is not None and before.track_id.size:
        old = ~np.isin(before.track_id, tid)
        tid = np.concatenate([before.track_id[old], tid])
        pos = np.concatenate([before.position[old], pos])
    # np.unique keeps the first of equal ids: on the reversed arrays, the last assigned
    u, first = np.unique(tid[::-1], return_index=True)
    return _TrackRows(u, pos[::-1][first])


def _slice_groups(keys) -> list:
    """
    Group tag-point keys by slice, in the order each slice first appears.

    Parameters
    ----------
    keys : list of tuple
        (view, slice, track_id) of every tag point, shape (K,).

    Returns
    -------
    list of tuple
        ``((view, slice), indices into keys (ascending), their track ids)`` per slice.

    """
    if not keys:
        return []
    arr = np.asarray(keys, dtype=np.int64).reshape(len(keys), 3)
    _, first, inverse = np.unique(arr[:, :2], axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    out = []
    for g in np.argsort(first):
        idx = np.flatnonzero(inverse == g)
        out.append(((int(arr[idx[0], 0]), int(arr[idx[0], 1])), idx, arr[idx, 2]))
    return out


def _coupling_plateau(value) -> float:
    """
    Return ``coupling_plateau`` checked: a number in [0, 1).

    Raises
    ------
    ValueError
        The value is not a finite number in [0, 1).

    """
    value = float(value)
    if not 0.0 <= value < 1.0:
        raise ValueError(
            f'coupling_plateau must be in [0, 1) (0 = the hat from each flagged point), '
            f'got {value}'
        )
    return value


def _larger_rejected_share(worst, rejected, attached):
    """
    Return whichever of ``worst`` and ``(rejected, attached)`` rejected the larger share.

    Parameters
    ----------
    worst : tuple of int
        (rejected, attached) of the worst pass so far; ``(0, 0)`` before the first.
    rejected, attached : int
        Tag points this pass rejected as outliers, and those it attached.

    Returns
    -------
    tuple of int
        (rejected, attached); a tie keeps ``worst`` (compared by cross-multiplying, no division).

    """
    if worst[1] == 0 or rejected * worst[1] > worst[0] * attached:
        return (rejected, attached)
    return worst


def _control_rows(ctrl: ControlPoints, keep) -> ControlPoints:
    """
    Return the control points ``keep`` (boolean, shape (M,)) of ``ctrl``.

    Each point's weights depend on its own position only, so this equals attaching those points
    again.
    """
    return ControlPoints(ctrl.weights[keep], ctrl.rest_positions[keep], None, ctrl.shepard[keep])
