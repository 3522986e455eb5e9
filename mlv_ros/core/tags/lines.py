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
Points on one family of parallel tag lines (single-line SPAMM), tracked along the lines' normal.

A study tagged with one family of lines has no intersections: a point on a tag line measures
only the motion along the line's normal n (the 1-D analogue of an intersection's in-plane
measurement; the solver's data spring is ``n nᵀ``,
:func:`~mlv_ros.core.meshless.plane_projectors`).

Detection: the family's Gabor phase (:mod:`mlv_ros.core.tags.gabor`) with ``ψ = wrap(φ − π)``
is 0 on the dark line centres; seeds on a lattice of one tag period along and across the lines
are brought onto the nearest line by Newton's method on ψ along its gradient, which spaces the
points about one period apart along each line. Tracking: the phase of a material line is
constant in time (HARP's principle), so each point is brought back onto ψ = 0 from its
predicted position (previous position plus previous displacement) by Newton's method along the
current phase gradient: it moves along n only, and its position along the line is not
measured. The filtered region is the same at every phase (disks of one period around the
points), so the blood-pool border biases every phase alike.

Pixel coordinates (row, col) and angles as in :mod:`mlv_ros.core.tags` (the wave vector's angle
θ from the column axis toward the row axis; unit wave vector (sin θ, cos θ)).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from .gabor import (
    estimate_tag_parameters,
    gabor_filter_bank,
    MIN_PEAK_RATIO,
    MIN_WHITENED_PEAK_RATIO,
    TagInputError,
    TagParameters,
    validate_image,
)
from .intersections import masked_normalise
from .line_pair import estimate_pair_shift, LARGE_SHIFT_MM, PairShift
from .phase import PhaseField
from .tracker import tag_period_range_px
from ..types import Frame, PAIR_MISREGISTERED, TagPointSet, TAGS_LINE_PAIR

# |R| / σ_local of an ideal single family ``sin²(π a / λ)``: a cosine of amplitude 1/2 (|R| =
# 1/4) with standard deviation (1/2)/√2, so the ratio is 1/√2 (the grid's is 1/√5).
LINE_CONTRAST_RATIO = 1.0 / np.sqrt(2.0)
DEFAULT_MIN_CONFIDENCE = 0.4  # as detect_intersections'
# A point is on its line when |ψ| after refinement is below this, rad (0.05 of a period).
MAX_PHASE_RESIDUAL = 0.1 * np.pi
NEWTON_STEPS = 6


@dataclass
class LinePoints:
    """
    Points on the tag lines of one image.

    Attributes
    ----------
    pixel_rc : ndarray, shape (N, 2)
        Sub-pixel (row, col), px.
    normal_rc : ndarray, shape (N, 2)
        Unit normal of the line at each point (the phase gradient's direction), (row, col).
    confidence : ndarray of float32, shape (N,)
        0..1: ``|R| / (σ_local/√2)`` clipped to 1 (1 for an ideal noise-free family).
    residual : ndarray of float32, shape (N,)
        ``|ψ|`` after refinement, rad.
    reason : str
        Empty on success; otherwise why there are no points.

    """

    pixel_rc: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    normal_rc: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    confidence: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    residual: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    reason: str = ''

    def __len__(self) -> int:
        return int(self.pixel_rc.shape[0])


def line_parameters(spacing_px: float, angle: float) -> TagParameters:
    """
    Return the :class:`TagParameters` of one family: the family first, its perpendicular second.

    Parameters
    ----------
    spacing_px : float
        Tag period, px (≥ 2).
    angle : float
        Wave-vector angle of the family, rad (module conventions).

    Raises
    ------
    TagInputError
        A period below 2 px or a non-finite period or angle.

    """
    sp, an = float(spacing_px), float(angle)
    if not (np.isfinite(sp) and sp >= 2.0 and np.isfinite(an)):
        raise TagInputError(f'tag line period must be finite and ≥ 2 px, got {spacing_px}')
    return TagParameters(
        spacing_px=np.array([sp, sp]), angles=np.mod(np.array([an, an + np.pi / 2]), np.pi)
    )


def line_phase(image, region, params: TagParameters):
    """
    Return the family's phase field ψ (0 on line centres) and its confidence in ``region``.

    Parameters
    ----------
    image : array_like, shape (H, W)
        The tagged image (any intensity scale).
    region : ndarray of bool, shape (H, W)
        Where the tags are read: zero-meaned locally inside, zeroed outside
        (:func:`~mlv_ros.core.tags.intersections.masked_normalise`).
    params : TagParameters
        :func:`line_parameters` of the family.

    Returns
    -------
    field : PhaseField
        ``psi[0]`` is the family's ψ, rad; ``jac[0]`` its gradient, rad/px.
    confidence : ndarray of float32, shape (H, W)
        0..1 (:class:`LinePoints`).

    """
    img = validate_image(image)
    lam = float(params.spacing_px[0])
    work, std = masked_normalise(img, np.asarray(region, bool), lam)
    maps = gabor_filter_bank(work, params)
    floor = 1e-6 * float(np.ptp(img)) + 1e-30
    conf = np.clip(maps.magnitude[0] / (LINE_CONTRAST_RATIO * np.maximum(std, floor)), 0, 1)
    return PhaseField.from_complex(-maps.response), conf.astype(np.float32)


def onto_lines(field_: PhaseField, start, max_step: float):
    """
    Bring points onto the nearest line (ψ = 0) by Newton's method along the phase gradient.

    Parameters
    ----------
    field_ : PhaseField
        From :func:`line_phase` (direction 0).
    start : ndarray, shape (N, 2)
        Start points (row, col), px.
    max_step : float
        Largest move per step, px (half a period keeps a point on the line it started nearest).

    Returns
    -------
    pts : ndarray, shape (N, 2)
        Refined points, px.
    normal : ndarray, shape (N, 2)
        Unit phase gradient at each (the line normal), (row, col); NaN where it vanishes.
    residual : ndarray, shape (N,)
        ``|ψ|`` at each, rad (inf outside the image).

    """
    pts = np.array(start, dtype=np.float64).reshape(-1, 2)
    for _ in range(NEWTON_STEPS):
        psi, jac, inside = field_.sample(pts)
        g = jac[:, 0, :]
        g2 = np.einsum('ka,ka->k', g, g)
        ok = inside & (g2 > 1e-12)
        step = np.zeros_like(pts)
        step[ok] = -g[ok] * (psi[ok, 0] / g2[ok])[:, None]
        ln = np.linalg.norm(step, axis=1)
        step *= np.minimum(1.0, max_step / np.maximum(ln, 1e-12))[:, None]
        pts += step
    psi, jac, inside = field_.sample(pts)
    g = jac[:, 0, :]
    ln = np.linalg.norm(g, axis=1)
    normal = np.where((ln > 1e-9)[:, None], g / np.maximum(ln, 1e-9)[:, None], np.nan)
    residual = np.where(inside, np.abs(psi[:, 0]), np.inf)
    return pts, normal, residual


def point_disks(shape, points, radius: float) -> np.ndarray:
    """Return the union of disks of ``radius`` px around ``points`` (row, col), bool (H, W)."""
    out = np.zeros(shape, np.uint8)
    for r, c in np.asarray(points, float).reshape(-1, 2):
        if np.isfinite(r) and np.isfinite(c):
            cv2.circle(out, (int(round(c)), int(round(r))), int(np.ceil(radius)), 1, -1)
    return out.astype(bool)


def detect_line_points(image, params: TagParameters, mask, min_confidence=DEFAULT_MIN_CONFIDENCE):
    """
    Find points on the family's tag lines inside ``mask``, about one period apart along each.

    Parameters
    ----------
    image : array_like, shape (H, W)
        The tagged image.
    params : TagParameters
        :func:`line_parameters` of the family.
    mask : array_like of bool, shape (H, W)
        The myocardium (points outside are not kept).
    min_confidence : float
        Smallest confidence kept (relative to the image's own local contrast, 0..1).

    Returns
    -------
    LinePoints
        Empty with ``reason`` set for an unusable image or when no point qualifies; never raises
        for image content.

    """
    try:
        img = validate_image(image)
    except TagInputError as exc:
        return LinePoints(reason=str(exc))
    m = np.asarray(mask, bool)
    if m.shape != img.shape or not m.any():
        return LinePoints(reason='empty or mismatched mask: no region to read tag lines in')
    lam, th = float(params.spacing_px[0]), float(params.angles[0])
    field_, conf = line_phase(img, m, params)
    # Seeds on a lattice of one period along (s) and across (u) the lines, through the mask's
    # centroid; each lands on the line nearest to it.
    u, s = np.array([np.sin(th), np.cos(th)]), np.array([np.cos(th), -np.sin(th)])
    rr, cc = np.nonzero(m)
    centre = np.array([rr.mean(), cc.mean()])
    reach = np.hypot(*img.shape) / lam
    i = np.arange(-np.ceil(reach), np.ceil(reach) + 1)
    seeds = centre + lam * (i[:, None, None] * u + i[None, :, None] * s).reshape(-1, 2)
    q = np.rint(seeds).astype(int)
    on = (q[:, 0] >= 0) & (q[:, 0] < img.shape[0]) & (q[:, 1] >= 0) & (q[:, 1] < img.shape[1])
    seeds = seeds[on][m[q[on, 0], q[on, 1]]]
    return _kept(field_, conf, m, seeds, lam, min_confidence)[0]


def _kept(field_, conf, region, start, lam, min_confidence, dedupe=True):
    """
    Refine ``start`` onto the lines and keep the confident points inside ``region``.

    Returns the :class:`LinePoints` and the indices into ``start`` they came from; with
    ``dedupe``, one point per cell of a third of a period (the first seed's).
    """
    pts, normal, res = onto_lines(field_, start, 0.5 * lam)
    q, inside = field_.nearest(pts)
    c = conf[q[:, 0], q[:, 1]]
    keep = inside & region[q[:, 0], q[:, 1]] & (res < MAX_PHASE_RESIDUAL) & (c >= min_confidence)
    keep &= np.isfinite(normal).all(axis=1)
    idx = np.flatnonzero(keep)
    if dedupe and idx.size:
        cell = np.floor(pts[idx] / max(lam / 3.0, 1.0)).astype(int)
        _, first = np.unique(cell, axis=0, return_index=True)
        idx = idx[np.sort(first)]
    out = LinePoints(
        pixel_rc=pts[idx],
        normal_rc=normal[idx],
        confidence=c[idx].astype(np.float32),
        residual=res[idx].astype(np.float32),
    )
    if not idx.size:
        out.reason = f'no point on a tag line with confidence ≥ {min_confidence}'
    return out, idx


class LineTracker:
    """
    Track points on one family of tag lines through one slice's cine, along the lines' normal.

    Parameters
    ----------
    geometry : SliceGeometry, optional
        The slice's plane (patient coordinates of the points and normals); the frame's when
        None.
    spacing_px : float
        Tag period, px.
    angle : float
        Wave-vector angle of the family, rad (module conventions).
    min_confidence : float
        Smallest confidence a point keeps (0..1, relative to the image's local contrast).
    region_radius : float
        Radius of the disks around the points where the tags are read, in periods.
    follow_relative, follow_floor : float
        After ED a point is kept down to ``follow_relative`` times the median confidence of the
        slice's points at the previous phase, never above ``min_confidence`` nor below
        ``follow_floor``: tags fade with T1 over the cycle (the rule and defaults of
        :class:`~mlv_ros.core.tags.SliceTracker`).

    Attributes
    ----------
    offset_rc : ndarray, shape (2,)
        Subtracted from the tracked pixel positions on output, px: where this family's series
        shows the anatomy off the slice's first series (a line pair's second breath-hold,
        :func:`~mlv_ros.core.tags.line_pair.estimate_pair_shift`); zeros by default.

    """

    def __init__(
        self,
        geometry=None,
        *,
        spacing_px: float,
        angle: float,
        min_confidence: float = DEFAULT_MIN_CONFIDENCE,
        region_radius: float = 0.6,
        follow_relative: float = 0.6,
        follow_floor: float = 0.25,
    ):
        self.geometry = geometry
        self.params = line_parameters(spacing_px, angle)
        self.min_confidence = float(min_confidence)
        self.radius = float(region_radius) * float(self.params.spacing_px[0])
        self.ids = np.zeros(0, np.int32)
        self.rc = np.zeros((0, 2))
        self.velocity = np.zeros((0, 2))
        self.follow = (float(follow_relative), float(follow_floor))
        self._follow_conf = np.nan  # median confidence of the points at the previous phase
        self.offset_rc = np.zeros(2)

    def follow_threshold(self) -> float:
        """Return the confidence a point needs to stay tracked at the next phase (0..1)."""
        base = self.min_confidence
        if not np.isfinite(self._follow_conf):
            return base
        rel, floor = self.follow
        return float(np.clip(rel * self._follow_conf, min(floor, base), base))

    def update(self, frame: Frame, mask=None) -> TagPointSet:
        """
        Return the frame's line points with their ids and normals (phase 0 starts the cine).

        Parameters
        ----------
        frame : Frame
            One phase of the slice, in phase order.
        mask : array_like of bool, optional
            The ED myocardium; required at phase 0, ignored after.

        Returns
        -------
        TagPointSet
            With ``line_normal`` set; empty with ``status`` set when nothing is found or no
            track is left. Never raises for image content.

        """
        lam = float(self.params.spacing_px[0])
        try:
            img = validate_image(frame.image)
        except TagInputError as exc:
            return self._result(frame, None, None, None, str(exc))
        if int(frame.phase_index) == 0:
            if mask is None:
                return self._result(frame, None, None, None, 'line tracking needs the ED mask')
            det = detect_line_points(img, self.params, mask, self.min_confidence)
            self.ids = np.arange(len(det), dtype=np.int32)
            self.rc, self.velocity = det.pixel_rc, np.zeros_like(det.pixel_rc)
            if not len(det):
                return self._result(frame, None, None, None, det.reason)
        pred = self.rc + self.velocity
        if not len(pred):
            return self._result(frame, None, None, None, 'no tag-line track left')
        # The same region at every phase (disks round the points) keeps the blood-pool border's
        # bias on the phase alike at every phase.
        region = point_disks(img.shape, pred, self.radius)
        field_, conf = line_phase(img, region, self.params)
        threshold = self.min_confidence if frame.phase_index == 0 else self.follow_threshold()
        pts, idx = _kept(field_, conf, region, pred, lam, threshold, dedupe=False)
        moved = np.linalg.norm(pts.pixel_rc - pred[idx], axis=1)
        good = moved < 0.5 * lam  # a larger move reached the neighbouring line
        idx = idx[good]
        self.velocity = pts.pixel_rc[good] - self.rc[idx] if frame.phase_index else 0 * pred[idx]
        self.rc, self.ids = pts.pixel_rc[good], self.ids[idx]
        self._follow_conf = float(np.median(pts.confidence[good])) if idx.size else np.nan
        status = '' if idx.size == len(pred) else f'{len(pred) - idx.size} tag-line tracks lost'
        return self._result(
            frame, self.rc, pts.normal_rc[good], pts.confidence[good], status
        )

    def _result(self, frame, rc, normal_rc, conf, status) -> TagPointSet:
        """Return the TagPointSet of ``rc`` (px) with patient positions and line normals."""
        geom = self.geometry if self.geometry is not None else frame.geometry
        out = TagPointSet(
            view=int(frame.view),
            slice_index=int(frame.slice_index),
            phase_index=int(frame.phase_index),
            num_phases=int(frame.num_phases),
            geometry=geom,
            status=status,
            stamp=float(getattr(frame, 'trigger_time', 0.0)),
        )
        if rc is None or not len(rc):
            return out
        out.pixel_rc = np.asarray(rc, float) - self.offset_rc
        out.position = geom.pixel_to_patient(out.pixel_rc)
        out.track_id = self.ids.astype(np.int32)
        out.confidence = np.asarray(conf, np.float32)
        out.line_normal = line_normal_patient(geom, normal_rc)
        return out


def line_normal_patient(geometry, normal_rc) -> np.ndarray:
    """
    Return unit line normals in patient coordinates from pixel-space phase gradients.

    Parameters
    ----------
    geometry : SliceGeometry
        The image plane.
    normal_rc : ndarray, shape (N, 2)
        Phase-gradient directions (row, col) in pixel units.

    Returns
    -------
    ndarray, shape (N, 3)
        ``∇ψ`` in patient coordinates (``g_r / Δr`` along the column direction, ``g_c / Δc``
        along the row direction), normalised.

    """
    g = np.asarray(normal_rc, float).reshape(-1, 2)
    n = np.outer(g[:, 0] / geometry.row_spacing, geometry.column_direction) + np.outer(
        g[:, 1] / geometry.column_spacing, geometry.row_direction
    )
    return n / np.linalg.norm(n, axis=1, keepdims=True)


# Track ids of the second family of a line pair start here (the first family's count from 0).
SECOND_FAMILY_IDS = 100000


def estimate_line_family(image, region=None, pixel_mm: float = 1.0) -> tuple[float, float]:
    """
    Estimate the period and wave-vector angle of one family of tag lines from the spectrum.

    The strongest peak of :func:`~mlv_ros.core.tags.gabor.estimate_tag_parameters` in
    ``region`` (its second, a grid's other direction, is not asked for), measured against the
    band's median (at least :data:`~mlv_ros.core.tags.gabor.MIN_PEAK_RATIO`), else whitened
    against its ring's (at least :data:`~mlv_ros.core.tags.gabor.MIN_WHITENED_PEAK_RATIO`): a
    thin tagged wall spreads its peak over the ring, as :func:`~mlv_ros.core.tags.estimate_grid`
    also tries both.

    Parameters
    ----------
    image : array_like, shape (H, W)
        The ED image.
    region : array_like of bool, shape (H, W), optional
        Where the spectrum is taken (the myocardium); default the whole image.
    pixel_mm : float
        Pixel size, mm (sets the periods searched, ``tag_period_range_px``).

    Returns
    -------
    spacing_px : float
        Tag period, px.
    angle : float
        Wave-vector angle, rad (module conventions).

    Raises
    ------
    TagInputError
        No peak stands out either way (no tags, faded tags, noise), or an unusable image or
        region.

    """
    lo, hi = tag_period_range_px(pixel_mm)
    said = []
    for whiten, need in ((False, MIN_PEAK_RATIO), (True, MIN_WHITENED_PEAK_RATIO)):
        est = estimate_tag_parameters(image, region, lo, hi, min_peak_ratio=0.0, whiten=whiten)
        k = int(np.argmax(est.peak_ratio))
        if est.peak_ratio[k] >= need:
            return float(est.spacing_px[k]), float(est.angles[k])
        said.append(f'{est.peak_ratio[k]:.1f}x (need ≥ {need:g})')
    raise TagInputError(
        f'no tag lines: the strongest spectral peak stands {said[0]} over the band and '
        f'{said[1]} over its ring; no tags, faded tags or noise only'
    )


def merge_line_sets(first: TagPointSet, second: TagPointSet) -> TagPointSet:
    """
    Return the points of two families of one frame as one set (the second's ids + 100000).

    Parameters
    ----------
    first, second : TagPointSet
        :meth:`LineTracker.update` of the two families of one slice at one phase.

    Returns
    -------
    TagPointSet
        ``first`` with ``second``'s points appended (ids offset by :data:`SECOND_FAMILY_IDS`)
        and both statuses joined.

    """
    out = first
    if len(second):
        if not len(out):
            out.pixel_rc, out.position = np.zeros((0, 2)), np.zeros((0, 3))
            out.track_id, out.confidence = np.zeros(0, np.int32), np.zeros(0, np.float32)
            out.line_normal = np.zeros((0, 3))
        out.pixel_rc = np.concatenate([out.pixel_rc, second.pixel_rc])
        out.position = np.concatenate([out.position, second.position])
        ids = np.asarray(second.track_id) + SECOND_FAMILY_IDS
        out.track_id = np.concatenate([out.track_id, ids]).astype(np.int32)
        out.confidence = np.concatenate([out.confidence, second.confidence]).astype(np.float32)
        normals = np.reshape(out.line_normal, (-1, 3))
        out.line_normal = np.concatenate([normals, second.line_normal])
    out.status = '; '.join(x for x in (first.status, second.status) if x)
    return out


class LineSliceTracker:
    """
    Track one slice's single-line tags: one family, or the two families of a line pair.

    At ED each family's period and angle are estimated from its image inside the myocardium
    (:func:`estimate_line_family`) and a :class:`LineTracker` follows it; a line pair's
    second family comes from ``Frame.line_image``. The two families' points go out as one set
    (:func:`merge_line_sets`). The attributes the tag detector reports are those of
    :class:`~mlv_ros.core.tags.SliceTracker`: ``params`` (None when no family was read at ED),
    ``track_id`` (every ED track) and ``alive`` (the tracks at the last phase).

    A pair's two series come from two breath-holds: at ED the second's in-plane shift from the
    first is estimated on the anatomy they share
    (:func:`~mlv_ros.core.tags.line_pair.estimate_pair_shift`, ``pair_shift``). A sure one is
    corrected (the second family is detected in the ED mask moved by it, its points moved back
    onto the first's anatomy); an unsure one is not, and a sure one beyond
    :data:`~mlv_ros.core.tags.line_pair.LARGE_SHIFT_MM` likely came with a through-plane shift
    no in-plane estimate sees: either way the ED status gets a part beginning
    :data:`~mlv_ros.core.types.PAIR_MISREGISTERED` (``pair_note``), which degrades every phase
    the solver solves.

    Parameters
    ----------
    geometry : SliceGeometry
        The slice's plane.
    spacing_px : float, optional
        Tag period override, px (both families); estimated when None.

    """

    def __init__(self, geometry, spacing_px: float | None = None):
        self.geometry = geometry
        self.spacing_px = spacing_px
        self.families: list[LineTracker | None] = []
        self.params = None
        self.track_id = np.zeros(0, np.int32)
        self.alive = np.zeros(0, np.int32)
        self.pair_shift: PairShift | None = None
        self.pair_note = ''
        self._masks: list = []

    def _start(self, images, mask) -> str:
        """Estimate each family at ED and start its tracker; return why none started, or ''."""
        if mask is None or not np.asarray(mask, bool).any():
            return 'no ED myocardium mask: single-line tags are read only inside it'
        m = np.asarray(mask, bool)
        px = float(self.geometry.row_spacing)
        why = []
        self.families = []
        for image in images:
            try:
                lam, angle = estimate_line_family(image, m, px)
                if self.spacing_px:
                    lam = float(self.spacing_px)
                self.families.append(LineTracker(self.geometry, spacing_px=lam, angle=angle))
            except TagInputError as exc:
                self.families.append(None)
                why.append(str(exc))
        live = [f for f in self.families if f is not None]
        if live:
            self.params = [f.params for f in live]
        self._masks = [m] * len(self.families)
        if len(live) == 2:
            self._register_pair(images, m, px)
        return '' if live else '; '.join(why)

    def _register_pair(self, images, mask, px: float) -> None:
        """Estimate the second series' shift, correct it when sure, note it when it is not."""
        lam = max(float(f.params.spacing_px[0]) for f in self.families)
        est = self.pair_shift = estimate_pair_shift(images[0], images[1], mask, lam, px)
        if est.sure:
            self.families[1].offset_rc = est.shift_rc
            moved = np.zeros_like(mask)
            dr, dc = (int(round(v)) for v in est.shift_rc)
            h, w = mask.shape
            moved[max(dr, 0):h + min(dr, 0), max(dc, 0):w + min(dc, 0)] = mask[
                max(-dr, 0):h + min(-dr, 0), max(-dc, 0):w + min(-dc, 0)
            ]
            self._masks[1] = moved
        if not est.sure:
            self.pair_note = (
                f'{PAIR_MISREGISTERED}: the shift between its two series is unsure '
                f"({est.reason}); not corrected, the second family's points may be off along "
                'their normals by it'
            )
        elif est.large:
            self.pair_note = (
                f'{PAIR_MISREGISTERED}: its second series is {est.shift_mm:.1f} mm off the first '
                f'in-plane (more than breath-holds usually differ, {LARGE_SHIFT_MM:g} mm), '
                'corrected in-plane, while a through-plane shift of that order cannot be'
            )

    def update(self, frame: Frame, mask=None) -> TagPointSet:
        """
        Return the frame's line points, both families of a pair in one set.

        Parameters
        ----------
        frame : Frame
            One phase of the slice, in phase order (phase 0 starts the cine).
        mask : array_like of bool, optional
            The ED myocardium; required at phase 0.

        Returns
        -------
        TagPointSet
            With ``line_normal`` set; empty with ``status`` set when nothing is found. Never
            raises for image content.

        """
        images = [frame.image]
        if frame.tag_lines == TAGS_LINE_PAIR and frame.line_image is not None:
            images.append(frame.line_image)
        if int(frame.phase_index) == 0:
            self.params, self.pair_shift, self.pair_note = None, None, ''
            why = self._start(images, mask)
            if why:
                self.families = []
                return LineTracker(self.geometry, spacing_px=2.0, angle=0.0)._result(
                    frame, None, None, None, why
                )
        sets = []
        for k, tracker in enumerate(self.families):
            if tracker is None:
                continue
            if k >= len(images):  # the second series lacks this phase
                continue
            one = tracker.update(
                replace(frame, image=images[k]), self._masks[k] if self._masks else mask
            )
            sets.append((k, one))
        if not sets:
            return LineTracker(self.geometry, spacing_px=2.0, angle=0.0)._result(
                frame, None, None, None, 'no tag-line family tracked'
            )
        out = sets[0][1] if sets[0][0] == 0 else _offset(sets[0][1])
        for _, one in sets[1:]:
            out = merge_line_sets(out, one)
        ids = np.asarray(out.track_id, np.int32)
        self.alive = ids
        if int(frame.phase_index) == 0:
            self.track_id = ids
            if self.pair_note:
                out.status = '; '.join(x for x in (out.status, self.pair_note) if x)
        return out


def _offset(points: TagPointSet) -> TagPointSet:
    """Return a second family's set alone, its ids offset by :data:`SECOND_FAMILY_IDS`."""
    if len(points):
        points.track_id = (np.asarray(points.track_id) + SECOND_FAMILY_IDS).astype(np.int32)
    return points
