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
Per-slice temporal tracking of tag intersections (Gabor detection + TPS-RPM matching).

At end-diastole (phase 0) the tracker detects the intersections inside the myocardium and gives
each a track id. At every later phase it predicts each live track by its previous displacement,
detects intersections near the prediction (the ED myocardium mask carried along by a TPS fitted
to the tracks), and matches prediction to detections with TPS-RPM. Matched tracks take the
detected position (refined where their ED neighbourhood registers, ``register``); optionally, on
short-axis views, a track the detector missed is still seen where its own ED neighbourhood
registers as well as the slice's confirmed tracks do (``register_missed``). Unmatched ones are
coasted on the RPM warp for at most ``max_gap`` phases and then dropped: a tag intersection that
fades or leaves the slice (through-plane motion) is never invented, and material that enters the
slice is not a continuation of an ED track. A dropped
track is taken up again only where the grid identifies it: near where the live tracks' warp puts
it (``_revive``), or, once the slice has lost its tracks (fewer than ``MIN_LIVE_TRACKS``), where
its ED grid is seen again as the cycle closes (``_reacquire``).

References
----------
Chen, T. et al. IEEE TMI 29(1):1–11, 2010 (Gabor + RPM tag tracking).
Chui, H., Rangarajan, A. CVIU 89:114–141, 2003 (TPS-RPM).

"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.types import Frame, TagPointSet, VIEW_SA
import numpy as np
from scipy.spatial import cKDTree

from .gabor import (
    MAX_SPACING_PX,
    MIN_SPACING_PX,
    TAG_PERIOD_RANGE_MM,
    TagInputError,
    TagParameters,
    validate_image,
)
from .intersections import DEFAULT_MIN_CONFIDENCE, detect_intersections, Detection
from .register import MAP_PRIOR, register_points
from .rpm import ThinPlateSpline, tps_rpm

# A dropped track is taken up again only by a detection this close to its predicted place, in tag
# spacings (a different intersection is ≥ 1 spacing away; the warp's prediction is ~0.1 off).
REVIVE_GATE = 0.25
REVIVE_BELOW = 0.5
# A slice whose tracks are all lost is taken up again where its ED grid is seen again (the cycle
# closes: late diastole returns toward the ED configuration). Each ED track is matched to the
# nearest unclaimed detection within REVIVE_GATE spacings of its ED position, and the slice is
# taken up only when at least this share of its ED tracks (and REACQUIRE_MIN of them) match at
# once: chance detections near a few ED positions do not make a grid.
REACQUIRE_SHARE = 0.5
REACQUIRE_MIN = 6
# ED detection: a slice whose plain-confidence detection finds fewer than this share of the
# intersections its own mask holds (mask area over the grid's cell area) is detected again with
# the coverage-normalised confidence (see ``ed_coverage``).
ED_THIN_SHARE = 0.5
# Following a live track, the tuned refinement may move its detection by this many tag periods (a
# phase disagreement of 0.4π between the bank's and the tuned kernels; the match itself is gated
# at ``gate`` = 0.4 periods). In periods, not pixels: phase noise sets how far the two filters
# fall apart. The detector's default of 0.5 px was 0.09 periods at 5.3 px tags: at 1.87 mm
# pixels and SNR 11 it dropped about one in five matched points on a 7 mm wall, most on the right
# intersection (bench seed 1009), and two misses in a row end a track.
FOLLOW_TUNED_MOVE = 0.2
# Following, the passes accept points this far beyond the mask warped to the phase, px: the warped
# mask is the ED segmentation (a pixel raster, its border ±1 px) carried by a spline and sampled
# to the nearest pixel, and the first pass's is warped through the ~0.5 px uncertain prediction.
# A border is a pixel-raster quantity, not a tag-period one, hence pixels.
FOLLOW_ACCEPT_PX = 2
# On the views of ``confirm_border_views`` the second pass confirms a first-pass match within this
# many tag periods. The first pass reads the untuned bank's intersection, the second the tuned
# refinement's, which may move it by up to FOLLOW_TUNED_MOVE periods, so the two passes read one
# intersection up to that far apart whatever the pixel size; the nearest other intersection is a
# period or more away, so within 0.2 periods no wrong one is confirmed. ``confirm_px`` (0.5 px) was
# 0.08-0.12 periods on the bench's 4.1-6.6 px tags: it dropped right matches the passes read
# 0.5-1.5 px apart at the wall's border (bench seed 6507, docs/benchmarks.md la14).
CONFIRM_BORDER_PERIODS = FOLLOW_TUNED_MOVE
# A slice's tracks are followed only while at least this many are alive: fewer cannot propagate
# the wall mask (a thin-plate warp needs 4 points) nor check each other through the RPM warp, and
# an isolated track then takes whatever lies within its gate. Measured on bench seed 1009 (tracks
# against the truth): with 6+ tracks alive 1461 reported points right and 14 on a wrong
# intersection; with fewer than 4 alive 70 right and 171 wrong (3–50 mm off).
MIN_LIVE_TRACKS = 4
# A matched point is moved to where its ED neighbourhood registers (``register``) only within
# this many tag periods of the detection: farther, the two disagree on which intersection it is.
REGISTER_MAX_MOVE = 0.25
# On the views of ``register_missed_views``, a live track the detector missed (no match within the
# gate, or a first-pass match the second pass does not confirm within ``confirm_px``) is kept
# where its own ED neighbourhood registers, within REGISTER_MAX_MOVE periods of its start, when
# the fit's normalised cross-correlation reaches this percentile of the slice's confirmed tracks'
# at the same phase: the bar is the image's own noise and contrast at that phase, not a number.
# An akinetic sector's thin wall (bench seed 1012: 19 SA tracks, the constant-velocity prediction
# within 0.05–0.3 periods of the truth) has its intersections detected unreliably at its border,
# and two misses end a track: 14 of its 19 were lost by end-systole.
RECOVER_NCC_PERCENTILE = 25.0
# A fit whose local map degenerates (area ratio outside [1/4, 4]: a template of a thin wall can
# shrink onto one dark intersection) is tried again with the map held at the track's own
# (``map_prior`` of :func:`register_points` this large): position and intensity only.
HELD_MAP_PRIOR = 100.0


def tag_period_range_px(pixel_mm: float) -> tuple[float, float]:
    """
    Return the tag periods worth searching in an image of ``pixel_mm`` pixels, px.

    Within the spectrum estimate's own limits.
    """
    lo, hi = TAG_PERIOD_RANGE_MM
    return max(MIN_SPACING_PX, lo / pixel_mm), max(
        min(MAX_SPACING_PX, hi / pixel_mm), MIN_SPACING_PX + 1.0
    )


@dataclass
class _Matches:
    """
    One phase's matching of a slice's live tracks, shape (L,) per track (L live tracks).

    ``res`` is the TPS-RPM result (its ``warped`` is where a track not kept is coasted),
    ``final`` the detection revivals are drawn from; ``hit`` whether a track is kept,
    ``unconfirmed`` a first-pass match the second pass did not confirm, ``new`` the tracks'
    positions (px, row/column), ``conf`` / ``follow`` their plain / following confidences.
    """

    res: object
    final: Detection
    hit: np.ndarray
    unconfirmed: np.ndarray
    new: np.ndarray
    conf: np.ndarray
    follow: np.ndarray


class SliceTracker:
    """
    Stateful tag-intersection tracker for one slice (one per (view, slice) in the node).

    Parameters
    ----------
    geometry : SliceGeometry, optional
        Plane of the slice; patient positions use it (the frame's own geometry when None).
    spacing_px, angles : optional
        Tag parameter overrides passed to :func:`detect_intersections` at ED.
    max_gap : int
        Phases a track may go undetected (coasting on the RPM warp) before it is dropped.
    gate : float
        Largest distance between a prediction and its matched detection, in tag spacings.
    rpm_t_init, rpm_t_final : float
        RPM temperatures as (fractions of the tag spacing)²: the seeded prediction is already
        within a fraction of a spacing, so annealing starts local rather than at the global
        largest distance (which on a periodic grid would allow whole-period slips).
    propagate_mask : bool
        Carry the ED mask to later phases (TPS fitted from current to ED positions); used to
        restrict and normalise detection when :meth:`update` gets no mask.
    mask_erosion_px : int
        Erode the mask propagated through the matched points by this radius before the final
        (second) detection pass, px (negative dilates).
    confirm_px : float
        A first-pass match counts only if the second pass finds a point within this distance, px.
    register_missed : bool
        With ``register``, on the views in ``register_missed_views``: a live track the detector
        missed at this phase (no detection within ``gate`` of its prediction, or a first-pass
        match the second pass does not confirm within ``confirm_px``) is kept where its own ED
        neighbourhood registers, from the unconfirmed match or else from its own
        constant-velocity prediction, when the registration correlates as well as the lower
        quartile of the slice's confirmed tracks at that phase (``RECOVER_NCC_PERCENTILE``).
        Its reported confidence is the lowest of those tracks'. A thin wall that moves unlike
        its neighbours (an akinetic sector) has its intersections detected unreliably near its
        border, and two misses end a track. Off by default: on the kept bench studies it keeps
        the akinetic sectors' tracks (1012 and 2006 then meet the must) but the healthy studies'
        recovered endocardial tracks read 1.1–1.5 mm outward and their ES error rises (README,
        'Tag tracking against the truth').
    register_missed_views : tuple of int
        Views (``VIEW_SA``, ``VIEW_LA``) on which ``register_missed`` applies. Short axis only by
        default: on the bench's long-axis views (2–3 per study, ~10 tracks each, carrying the
        solver's longitudinal motion) the extra points cost accuracy (seed 2007 ES p95
        1.13 → 1.26 mm short axis only, 1.55 with the long axis too in a variant that also
        confirmed within 0.2 periods).
    confirm_border_views : tuple of int
        Views (``VIEW_SA``, ``VIEW_LA``) whose second pass accepts points as far beyond its
        warped mask as the first pass does (``FOLLOW_ACCEPT_PX``) and confirms a first-pass
        match within ``CONFIRM_BORDER_PERIODS`` tag periods instead of ``confirm_px``. The tuned
        refinement moves an intersection lying near the warped mask's border off a mask
        accepting nothing beyond it, and reads it up to 0.2 periods from the untuned first pass:
        the second pass dropped right long-axis matches at the wall's border (bench seed 6507:
        21 of 23 long-axis ED tracks lost by ES; ES p95 3.18 → 1.68 mm with it). The points it
        keeps are right (normal preset: 84 of 101 long-axis tracks kept at ES instead of 63,
        none wrong, median error 0.29 mm), but a healthy heart's solve reads slightly worse with
        them (normal preset ES p95 0.48 → 0.54 mm; docs/benchmarks.md, v3la). Off by default:
        with a random protocol's thickening apex cap (``motion.apex_thickening``) the extra
        long-axis points there pulled the apical twist (seed 502, hypertrophic, τ 0.45: twist
        error at level 0.05 −1.17 → −2.00°, 1.56× the uncertainty the run states for it), and
        the solver does not yet follow such a cap; ``(VIEW_LA,)`` turns it on (the short axis is
        unmeasured).
    revive : bool
        Offer dropped tracks again at the position the live tracks' warp predicts for them; a
        detection matching it (within ``gate``) resumes the track. Once the slice has lost its
        tracks, offer them at their ED positions (``REACQUIRE_SHARE``).
    follow_coverage : bool
        After ED, detect with the confidence normalised for the share of the filter inside the
        propagated wall mask (``coverage_normalised`` of :func:`detect_intersections`): a track
        on a wall thinner than a tag period is kept while its tags stand above the noise as
        far as a thick wall's must. ED detection (new tracks) keeps the plain confidence, and
        every reported point carries its plain confidence (the solver weights by it: a point
        seen through little wall is the more biased by the wall's border).
    follow_relative : float
        Live tracks are followed down to this fraction of the median (following) confidence of
        the slice's matched tracks at the previous phase, never above the ED threshold
        (``min_confidence``) nor below ``follow_floor``: tags fade with T1 over the cycle, and a
        fixed threshold loses a whole faded slice at once. 0 keeps the fixed threshold.
    follow_floor : float
        Lowest threshold for following (a match must still fall within ``gate`` of its
        prediction and be confirmed by the second pass).
    ed_coverage : bool
        At ED, when the plain confidence finds fewer than ``ED_THIN_SHARE`` of the intersections
        the mask holds (its area over the grid's cell area), detect again with the
        coverage-normalised confidence and keep whichever finds more. The masked image is zero
        outside the wall, so a wall thinner than the filter's envelope scales the tags' response
        by the share of the envelope inside it but the noise only by its square root: on a 7 mm
        wall at 1.87 mm pixels the plain confidence of the true intersections had a median of
        0.37–0.44 and the 0.4 threshold found 32 % of them (bench seed 1009). Thick walls
        (≈ the expected count found) keep the plain detection unchanged. Reported points carry
        their plain confidence either way.
    register : bool
        Move each matched point to where its own ED neighbourhood (inside the ED wall mask)
        registers in the image by a local affine map and a linear intensity change
        (:func:`~mlv_ros.core.tags.register.register_points`), within ``REGISTER_MAX_MOVE``
        periods of the detection; a match that does not register counts as not seen. The
        Gabor phase averages tags over about a period and reads intersections toward mid-wall
        where the wall thickens unevenly (end-systole); the registration follows the point's
        own material. ED points stay the detections. On by default: over the 24 kept bench
        studies it lowers the ES median in 23 and the presets' ES error by 0.14–0.18 mm; it
        lengthens the extrapolated apical twist on some and loses an akinetic sector's tracks on
        one (README, 'Tag tracking against the truth').
    confirm_still : bool
        On short-axis views, a first-pass match the second pass does not confirm, lying within
        ``gate`` periods of its own ED position and nearer it than where the smooth warp through
        the confirmed matches (ED → now) puts it, is detected again in the ED mask itself and
        confirmed there within ``confirm_px``: an akinetic sector stays where the ED mask has
        it while the warped mask follows its contracting neighbours. Off by default (README,
        'Tag tracking against the truth': it keeps more of an akinetic sector's tracks but the
        solved sector barely moves).
    match_still : bool
        On short-axis views, the live tracks the first pass missed (no detection within ``gate``
        of the prediction) are offered the intersections detected in the ED mask itself: the
        first pass filters inside the ED mask warped through the predictions by a smooth
        spline, which carries a still (akinetic) sector inward with its contracting neighbours,
        and 17 of the 30 first-pass misses of the akinetic SA tracks of three kept studies were
        detected there at the slice's threshold (``bench/track_losses.py``). The second pass
        confirms these matches as any other. Off by default (docs/benchmarks.md: with
        ``confirm_still`` it keeps more of the sectors' tracks, but their ES error barely moves).
    **detect_kwargs
        Extra keywords for :func:`detect_intersections` (e.g. ``min_confidence``).

    Examples
    --------
    >>> tracker = SliceTracker(frames[0].geometry)
    >>> sets = [tracker.update(f, mask=ed_mask if f.phase_index == 0 else None) for f in frames]

    """

    def __init__(
        self,
        geometry: SliceGeometry | None = None,
        *,
        spacing_px=None,
        angles=None,
        max_gap: int = 1,
        gate: float = 0.4,
        rpm_t_init: float = 0.3,
        rpm_t_final: float = 0.08,
        propagate_mask: bool = True,
        mask_erosion_px: int = 0,
        confirm_px: float = 0.5,
        register_missed: bool = False,
        register_missed_views=(VIEW_SA,),
        revive: bool = True,
        follow_coverage: bool = True,
        follow_relative: float = 0.6,
        follow_floor: float = 0.25,
        ed_coverage: bool = True,
        register: bool = True,
        confirm_still: bool = False,
        match_still: bool = False,
        confirm_border_views=(),
        **detect_kwargs,
    ):
        self.geometry = geometry
        self.spacing_px = spacing_px
        self.angles = angles
        self.max_gap = int(max_gap)
        self.gate = float(gate)
        self.rpm_t_init = float(rpm_t_init)
        self.rpm_t_final = float(rpm_t_final)
        self.propagate_mask = bool(propagate_mask)
        self.mask_erosion_px = int(mask_erosion_px)
        self.confirm_px = float(confirm_px)
        self.register_missed = bool(register_missed)
        self.register_missed_views = tuple(int(v) for v in register_missed_views)
        self.revive = bool(revive)
        self.follow_coverage = bool(follow_coverage)
        self.follow_relative = float(follow_relative)
        self.follow_floor = float(follow_floor)
        self.ed_coverage = bool(ed_coverage)
        self.register = bool(register)
        self.confirm_still = bool(confirm_still)
        self.match_still = bool(match_still)
        self.confirm_border_views = tuple(int(v) for v in confirm_border_views)
        if not (0.0 <= self.follow_relative <= 1.0 and 0.0 < self.follow_floor <= 1.0):
            raise ValueError(
                f'follow_relative must be in [0, 1] and follow_floor in (0, 1]; '
                f'got {follow_relative}, {follow_floor}'
            )
        self.detect_kwargs = detect_kwargs
        self.reset()

    def reset(self) -> None:
        """Forget all tracks (the next :meth:`update` must be an ED frame)."""
        self.params: TagParameters | None = None
        self.ed_mask: np.ndarray | None = None
        self.ed_image: np.ndarray | None = None
        self._map = np.zeros((0, 2, 2))  # each track's local map ∂x/∂x_ED (register)
        self.track_id = np.zeros(0, np.int32)
        self.ed_rc = np.zeros((0, 2))
        self.labels = np.zeros((0, 2), np.int32)
        self._pos = np.zeros((0, 2))
        self._step = np.zeros((0, 2))
        self._gap = np.zeros(0, int)
        self._dead = np.zeros(0, bool)
        self._follow_conf = np.nan  # median following confidence of the last phase's matches
        self.last_phase = -1
        self.last_detection: Detection | None = None
        self._started = False
        self._ed_failure = ''

    @property
    def alive(self) -> np.ndarray:
        """Ids of the tracks still followed, int32 (K,)."""
        return self.track_id[~self._dead]

    def update(self, frame: Frame, mask=None) -> TagPointSet:
        """
        Process the next phase of the slice (phase 0 = ED starts a new cine).

        Parameters
        ----------
        frame : Frame
            Image and geometry of the next phase of this slice.
        mask : array_like of bool, shape (H, W), optional
            Myocardium mask for this frame; required for a clean ED set (otherwise tag energy
            decides), optional later (the ED mask is propagated).

        Returns
        -------
        TagPointSet
            Detected intersections carrying ED track ids; empty with ``status`` set when the frame
            is unusable. Never raises.

        """
        try:
            return self._update(frame, mask)
        except Exception as exc:  # the node must survive any bad frame; report instead of raising
            return self._result(
                frame, None, None, None, f'tag tracker error: {type(exc).__name__}: {exc}'
            )

    # -- internals -----------------------------------------------------------------------------

    def _result(self, frame, rc, ids, conf, status) -> TagPointSet:
        geom = self.geometry if self.geometry is not None else getattr(frame, 'geometry', None)
        out = TagPointSet(
            view=int(getattr(frame, 'view', 0)),
            slice_index=int(getattr(frame, 'slice_index', 0)),
            phase_index=int(getattr(frame, 'phase_index', 0)),
            num_phases=int(getattr(frame, 'num_phases', 0)),
            geometry=geom,
            status=status,
            stamp=float(getattr(frame, 'trigger_time', 0.0)),
        )
        if rc is not None and len(rc):
            out.pixel_rc = np.asarray(rc, float)
            out.position = (
                geom.pixel_to_patient(out.pixel_rc)
                if geom is not None
                else np.full((len(rc), 3), np.nan)
            )
            out.track_id = np.asarray(ids, np.int32)
            out.confidence = np.asarray(conf, np.float32)
        return out

    def _update(self, frame: Frame, mask) -> TagPointSet:
        image = frame.image
        if frame.phase_index == 0 or not self._started:
            return self._start(frame, mask)
        if self.params is None:
            return self._result(frame, None, None, None, f'no ED reference: {self._ed_failure}')
        note = ''
        if frame.phase_index != self.last_phase + 1:
            note = f'phase jump {self.last_phase} -> {frame.phase_index}; '
        self.last_phase = frame.phase_index
        live = np.nonzero(~self._dead)[0]
        if live.size < MIN_LIVE_TRACKS:
            return self._too_few_live(frame, live, note)
        pred = self._pos[live] + self._step[live]
        sp = float(np.mean(self.params.spacing_px))
        m = self._match(image, mask, live, pred, sp, int(getattr(frame, 'view', VIEW_SA)))
        if m is None:
            self._coast(live, pred, pred)
            return self._result(
                frame,
                None,
                None,
                None,
                note + f'phase {frame.phase_index}: {self.last_detection.reason}',
            )
        self._register_matches(frame, image, live, pred, sp, m)
        return self._report(frame, live, pred, sp, m, note)

    def _too_few_live(self, frame: Frame, live, note: str) -> TagPointSet:
        """
        End a slice's last few tracks and look for its ED grid again (``MIN_LIVE_TRACKS``).

        Too few tracks cannot check each other: they are ended rather than left to wander onto
        noise, and the slice is taken up again where its ED grid returns (``_reacquire``).
        """
        image = frame.image
        self._dead[live] = True
        back = self._reacquire(image)
        if back is not None:
            idx, pts, cf = back
            return self._result(
                frame,
                pts,
                self.track_id[idx],
                cf,
                note + f'{len(idx)} of {len(self.track_id)} ED tracks found again at their '
                'ED configuration',
            )
        # Nothing left to track, but an unusable image is still worth naming.
        try:
            validate_image(image)
        except TagInputError as exc:
            note += f'phase {frame.phase_index}: {exc}; '
        return self._result(
            frame,
            None,
            None,
            None,
            note
            + (
                'all tracks lost'
                if live.size == 0
                else f'{live.size} of {len(self.track_id)} ED tracks left, fewer than '
                f'{MIN_LIVE_TRACKS}: too few to check each other'
            ),
        )

    def _match(self, image, mask, live, pred, sp: float, view: int = VIEW_SA):
        """
        Detect near the predicted tracks and match them (TPS-RPM), in two passes when masks move.

        Returns a :class:`_Matches` (``None`` when nothing was detected: the detection, with its
        reason, is ``last_detection``).
        """
        region = accept = None
        if mask is not None:
            region = np.asarray(mask, bool)
        elif self.propagate_mask and self.ed_mask is not None:
            # First pass, for matching only: the mask from the prediction is ~0.5 px uncertain, so
            # filter with it as is and accept points up to FOLLOW_ACCEPT_PX beyond it.
            region, accept = self._propagated_mask(
                pred, live, np.shape(image), erode=0, dilate=FOLLOW_ACCEPT_PX
            )
        lo = np.floor(pred.min(0) - 2 * sp)
        hi = np.ceil(pred.max(0) + 2 * sp) + 1
        roi = (lo[0], hi[0], lo[1], hi[1])
        two_pass = mask is None and region is not None
        det = self._detect_following(image, region, accept, roi, tuned=not two_pass)
        self.last_detection = det
        if not det.ok or len(det) == 0:
            return None
        res = tps_rpm(
            pred,
            det.pixel_rc,
            t_init=(self.rpm_t_init * sp) ** 2,
            t_final=(self.rpm_t_final * sp) ** 2,
            anneal=0.75,
            iterations_per_t=1,
            sinkhorn_iterations=10,
            outlier_distance=self.gate * sp,
            gate=self.gate * sp,
        )
        hit = res.match >= 0
        m = _Matches(
            res=res,
            final=det,
            hit=hit,
            unconfirmed=np.zeros(hit.shape, bool),
            new=np.where(hit[:, None], det.pixel_rc[np.maximum(res.match, 0)], res.warped),
            conf=det.plain_confidence[np.maximum(res.match, 0)],
            follow=det.confidence[np.maximum(res.match, 0)],
        )
        if two_pass and self.match_still and view == VIEW_SA and hit.sum() >= 4 and not hit.all():
            self._match_still(image, pred, sp, roi, m)
        if two_pass and hit.sum() >= 4:
            self._confirm(
                image,
                live,
                roi,
                m,
                still=self.confirm_still and view == VIEW_SA,
                border=view in self.confirm_border_views,
            )
        return m

    def _detect_following(self, image, region, accept, roi, tuned: bool = True) -> Detection:
        """Detect a later phase's intersections at the live tracks' ``follow_threshold``."""
        kwargs = {
            'max_tuned_move_periods': FOLLOW_TUNED_MOVE,
            **self.detect_kwargs,
            'min_confidence': self.follow_threshold(),
        }
        if not tuned:  # the first of two passes only matches: its points are replaced
            kwargs['tuned'] = False
        return detect_intersections(
            image,
            mask=region,
            params=self.params,
            roi=roi,
            accept_mask=accept,
            coverage_normalised=self.follow_coverage,
            **kwargs,
        )

    def _confirm(
        self, image, live, roi, m: '_Matches', still: bool = False, border: bool = False
    ) -> None:
        """
        Detect again inside the mask warped through the matches and confirm each match there.

        The mask warped through the matched detections (≈ 0.1 px) instead of the
        constant-velocity prediction (≈ 0.5 px off mid-systole) filters without leaking blood or
        static background tags into the phase near the wall's border. A first-pass match the
        second pass confirms (within ``confirm_px``) takes the second pass's point. One it does
        not may have come from tags just outside the predicted border: it is marked
        ``unconfirmed`` (dropped, or on the views of ``register_missed_views`` kept only where
        its own ED neighbourhood registers, ``RECOVER_NCC_PERCENTILE``).

        With ``border`` (the views of ``confirm_border_views``) the second pass accepts points
        up to ``FOLLOW_ACCEPT_PX`` beyond its mask, as the first does (the filter mask is
        unchanged), and confirms within ``CONFIRM_BORDER_PERIODS`` tag periods.
        """
        hit, new = m.hit, m.new
        region2, accept2 = self._propagated_mask(
            new[hit],
            live[hit],
            np.shape(image),
            erode=self.mask_erosion_px,
            dilate=FOLLOW_ACCEPT_PX if border else 0,
        )
        if region2 is None:
            return
        det2 = m.final = self._detect_following(image, region2, accept2, roi)
        found = np.zeros(int(hit.sum()), bool)
        j2 = np.zeros(int(hit.sum()), int)
        tol = self.confirm_px
        if border:
            tol = CONFIRM_BORDER_PERIODS * float(np.mean(self.params.spacing_px))
        if det2.ok and len(det2):
            d2, j2 = cKDTree(det2.pixel_rc).query(new[hit], distance_upper_bound=tol)
            found = np.isfinite(d2)
        idx = np.nonzero(hit)[0]
        new[idx[found]] = det2.pixel_rc[j2[found]]
        m.conf[idx[found]] = det2.plain_confidence[j2[found]]
        m.follow[idx[found]] = det2.confidence[j2[found]]
        if still:
            found[~found] = self._confirm_still(image, live, new, idx[~found], m)
        m.unconfirmed[idx[~found]] = True

    def _match_still(self, image, pred, sp: float, roi, m: '_Matches') -> None:
        """
        Match the tracks the first pass missed to intersections detected in the ED mask itself.

        The first pass filters inside the ED mask warped through the predictions by a smooth
        thin-plate spline: a sector that stays still while its neighbours contract (akinetic) is
        carried inward with them, and the masked filter then loses its intersections although
        the prediction is right. Detected again in the ED mask (the hypothesis that the wall
        stays where it was), a detection no matched track holds (farther than ``REVIVE_GATE``
        periods from every match) within ``gate`` of a missed track's prediction matches it.
        Updates ``m`` in place; the second pass confirms these matches as any other.
        """
        det = self._detect_following(image, self.ed_mask, None, roi, tuned=False)
        if not det.ok or not len(det):
            return
        d, _ = cKDTree(m.new[m.hit]).query(det.pixel_rc)
        free = np.nonzero(d > REVIVE_GATE * sp)[0]
        miss = np.nonzero(~m.hit)[0]
        if not free.size:
            return
        k, j = _nearest_unique(pred[miss], det.pixel_rc[free], self.gate * sp)
        if not len(k):
            return
        got, jj = miss[k], free[j]
        m.hit[got] = True
        m.new[got] = det.pixel_rc[jj]
        m.conf[got] = det.plain_confidence[jj]
        m.follow[got] = det.confidence[jj]

    def _confirm_still(self, image, live, new, idx, m: '_Matches') -> np.ndarray:
        """
        Confirm, in the ED mask itself, the unconfirmed matches still where they were at ED.

        A sector that does not contract while its neighbours do (akinetic) is not followed by a
        smooth warp through the matches: its wall stays where the ED mask has it, off the
        warped mask. A match within ``gate`` tag periods of its own ED position is detected
        again in the ED mask (a check independent of the match, as the warped mask is) and
        confirmed within ``confirm_px``. Updates ``new``, ``m.conf`` and ``m.follow`` at the
        confirmed ones; returns which of ``idx`` are confirmed, bool (len(idx),).
        """
        ok = np.zeros(len(idx), bool)
        sp = float(np.mean(self.params.spacing_px))
        conf = np.setdiff1d(np.nonzero(m.hit)[0], idx)
        if len(conf) < 4 or not len(idx):
            return ok
        ed = self.ed_rc[live[idx]]
        moved = ThinPlateSpline.fit(self.ed_rc[live[conf]], new[conf], lam=300.0)(ed)
        d_ed = np.linalg.norm(new[idx] - ed, axis=1)
        still = (d_ed <= self.gate * sp) & (d_ed < np.linalg.norm(new[idx] - moved, axis=1))
        if not still.any():
            return ok
        at = new[idx[still]]
        lo = np.floor(at.min(0) - 2 * sp)
        hi = np.ceil(at.max(0) + 2 * sp) + 1
        det = self._detect_following(image, self.ed_mask, None, (lo[0], hi[0], lo[1], hi[1]))
        if not det.ok or not len(det):
            return ok
        d, j = cKDTree(det.pixel_rc).query(at, distance_upper_bound=self.confirm_px)
        got = np.isfinite(d)
        k = idx[still][got]
        new[k] = det.pixel_rc[j[got]]
        m.conf[k] = det.plain_confidence[j[got]]
        m.follow[k] = det.confidence[j[got]]
        ok[np.nonzero(still)[0][got]] = True
        return ok

    def _register_matches(self, frame: Frame, image, live, pred, sp: float, m: '_Matches'):
        """
        Keep a match only where its own ED neighbourhood registers there (``register``).

        With ``register_missed`` (on its views) a live track the detector missed, or whose match
        was not confirmed, is recovered where its ED neighbourhood registers as well as the
        slice's confirmed tracks do. Updates ``m`` in place; a track not kept is coasted.
        """
        res, hit, unconfirmed, new, conf, follow = (
            m.res,
            m.hit,
            m.unconfirmed,
            m.new,
            m.conf,
            m.follow,
        )
        recover = (
            self.register and self.register_missed and int(getattr(frame, 'view', VIEW_SA)) in
            self.register_missed_views
        )
        if not recover:
            new[unconfirmed] = res.warped[unconfirmed]
            hit[unconfirmed] = False
        if not (self.register and hit.any()):
            new[unconfirmed] = res.warped[unconfirmed]
            hit[unconfirmed] = False
            return
        # A match whose own ED neighbourhood does not register there is not its material.
        idx = np.nonzero(hit & ~unconfirmed)[0]
        new[idx], seen, ncc = self._registered(image, live[idx], new[idx], sp, held=recover)
        new[idx[~seen]] = res.warped[idx[~seen]]
        hit[idx[~seen]] = False
        extra = np.nonzero(unconfirmed | ~hit)[0] if recover else np.zeros(0, int)
        if extra.size and seen.sum() >= MIN_LIVE_TRACKS:
            # A live track whose match the second pass did not confirm, or that no detection
            # matched, is still seen where its own ED neighbourhood registers, from that match or
            # else from its own prediction, as well as the slice's confirmed tracks register at
            # this phase (the image's own noise and contrast set the bar). Its confidence is the
            # lowest of theirs.
            start = np.where(unconfirmed[extra, None], new[extra], pred[extra])
            rc, ok, _ = self._registered(
                image,
                live[extra],
                start,
                sp,
                min_ncc=float(np.percentile(ncc[seen], RECOVER_NCC_PERCENTILE)),
                held=True,
            )
            low = np.min(conf[idx[seen]]), np.min(follow[idx[seen]])
            got = extra[ok]
            new[got] = rc[ok]
            conf[got[~unconfirmed[got]]] = low[0]
            follow[got[~unconfirmed[got]]] = low[1]
            hit[got] = True
            lost = extra[~ok]
            new[lost] = res.warped[lost]
            hit[lost] = False
        elif extra.size:
            new[unconfirmed] = res.warped[unconfirmed]
            hit[unconfirmed] = False

    def _report(self, frame: Frame, live, pred, sp: float, m: '_Matches', note: str):
        """Move the kept tracks, coast the rest, revive dropped ones and report the phase's set."""
        hit, new = m.hit, m.new
        self._coast(live[~hit], pred[~hit], new[~hit])
        prev = self._pos[live[hit]]
        self._step[live[hit]] = new[hit] - prev
        self._pos[live[hit]] = new[hit]
        self._gap[live[hit]] = 0
        if hit.any():
            self._follow_conf = float(np.median(m.follow[hit]))
        back = self._revive(live[hit], new[hit], m.final, sp)
        n_ed = len(self.track_id)
        n_out = int(hit.sum()) + len(back[0])
        status = note
        if n_out < n_ed:
            status += (
                f'{n_out} of {n_ed} ED tracks reported; {int(self._dead.sum())} dropped '
                f'(faded or through-plane; {len(back[0])} found again at this phase)'
            )
        if n_out == 0:
            status = note + 'no detection matched any track'
        ids = np.concatenate([self.track_id[live[hit]], self.track_id[back[0]]])
        pts = np.concatenate([new[hit], back[1]])
        cf = np.concatenate([m.conf[hit], back[2]])
        return self._result(frame, pts, ids, cf, status)

    def _registered(
        self, image, idx, rc, spacing: float, min_ncc: float = -1.0, held: bool = False
    ):
        """
        Return matched points moved to where their ED neighbourhoods register (``register``).

        See :func:`~mlv_ros.core.tags.register.register_points`: each track's ED neighbourhood
        inside the ED wall, mapped by a local affine map that starts from (and is held toward)
        the track's own map of the previous phase (``held``: a degenerate fit is tried again with
        the map held there, ``HELD_MAP_PRIOR``). Returns ``(positions, seen, ncc)``: ``seen`` is
        False where the fit fails, would move the point more than ``REGISTER_MAX_MOVE`` periods
        (the detection is then not taken as the track's material) or correlates below
        ``min_ncc``; ``ncc`` is the fit's normalised cross-correlation. Updates the seen tracks'
        maps.
        """
        if (
            self.ed_image is None
            or self.ed_mask is None
            or self.ed_image.shape != np.shape(image)
        ):
            return rc, np.ones(len(rc), bool), np.ones(len(rc))

        def fit(rows, prior):
            return register_points(
                self.ed_image,
                self.ed_mask,
                image,
                self.ed_rc[idx[rows]],
                rc[rows],
                self._map[idx[rows]],
                period_px=spacing,
                map_prior=prior,
            )

        out, local_map, ok, ncc = fit(np.arange(len(idx)), MAP_PRIOR)
        if held and not ok.all():
            bad = np.nonzero(~ok)[0]
            o2, m2, ok2, n2 = fit(bad, HELD_MAP_PRIOR)
            out[bad], local_map[bad], ok[bad], ncc[bad] = o2, m2, ok2, n2
        ok &= (np.linalg.norm(out - rc, axis=1) <= REGISTER_MAX_MOVE * spacing) & (ncc >= min_ncc)
        self._map[idx[ok]] = local_map[ok]
        return np.where(ok[:, None], out, rc), ok, ncc

    def follow_threshold(self) -> float:
        """Confidence a detection needs to continue a live track at the next phase (0..1)."""
        base = float(self.detect_kwargs.get('min_confidence', DEFAULT_MIN_CONFIDENCE))
        if self.follow_relative <= 0 or not np.isfinite(self._follow_conf):
            return base
        return float(
            np.clip(self.follow_relative * self._follow_conf, min(self.follow_floor, base), base)
        )

    def _revive(self, matched, positions, det: Detection, spacing: float):
        """
        Revive dropped tracks that are seen again.

        A track is revived by a detection no live track claimed, within ``REVIVE_GATE`` spacings
        of where the matched tracks' warp (ED → now) puts the dropped track. An intersection of two
        tag planes ⟂ the ED image is one material line however the heart moves through the slab,
        so that detection is the same line (a wrong one would be a whole spacing away). Returns
        ``(indices, positions, confidences)`` of the revived tracks (already updated).
        """
        lost = np.nonzero(self._dead)[0]
        none = (np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, np.float32))
        if not self.revive or lost.size == 0 or len(matched) < 6 or not det.ok or len(det) == 0:
            return none
        # Tracks are mostly dropped where the phase is least reliable (the wall's border), and
        # taken up again they are less accurate than followed ones (default study, in-plane: median
        # 0.54 vs 0.25 mm; ES p95 in 3D 1.59 → 1.77 mm when reviving at every phase), so only a
        # slice starved of points (fewer than REVIVE_BELOW of its ED tracks alive) revives.
        if (~self._dead).sum() >= REVIVE_BELOW * len(self.track_id):
            return none
        # Taking a track up again is an association without a path to it: the detection must be
        # as sure as a new track's (the plain confidence), not only stand out of the noise.
        free = det.plain_confidence >= self.detect_kwargs.get(
            'min_confidence', DEFAULT_MIN_CONFIDENCE
        )
        d, _ = cKDTree(positions).query(det.pixel_rc)
        free &= d > self.confirm_px
        if not free.any():
            return none
        pred = ThinPlateSpline.fit(self.ed_rc[matched], positions, lam=300.0)(self.ed_rc[lost])
        cand = np.nonzero(free)[0]
        k, j = _nearest_unique(pred, det.pixel_rc[cand], REVIVE_GATE * spacing)
        if not len(k):
            return none
        idx, pos = lost[k], det.pixel_rc[cand[j]]
        conf = det.plain_confidence[cand[j]]
        self._dead[idx] = False
        self._gap[idx] = 0
        # Its own velocity is unknown: take its nearest matched neighbour's (in ED position).
        _, nb = cKDTree(self.ed_rc[matched]).query(self.ed_rc[idx])
        self._step[idx] = self._step[matched[nb]]
        self._map[idx] = self._map[matched[nb]]
        self._pos[idx] = pos
        return idx, pos, np.array(conf, np.float32)

    def _reacquire(self, image):
        """
        Take a lost slice's tracks up again where its grid is back at the ED configuration.

        See ``REACQUIRE_SHARE``. Detection as for following (the ED wall mask, the slice's
        following threshold); every ED track is offered at its ED position, and the matches
        count only when enough come at once. Returns ``(indices, positions, plain confidences)``
        of the tracks taken up (already live, at rest), or None.
        """
        n_ed = len(self.track_id)
        need = max(REACQUIRE_MIN, int(np.ceil(REACQUIRE_SHARE * n_ed)))
        if not self.revive or self.ed_mask is None or n_ed < need:
            return None
        if self.ed_mask.shape != np.shape(image):
            return None
        sp = float(np.mean(self.params.spacing_px))
        lo = np.floor(self.ed_rc.min(0) - 2 * sp)
        hi = np.ceil(self.ed_rc.max(0) + 2 * sp) + 1
        det = detect_intersections(
            image,
            mask=self.ed_mask,
            params=self.params,
            roi=(lo[0], hi[0], lo[1], hi[1]),
            coverage_normalised=self.follow_coverage,
            **{
                'max_tuned_move_periods': FOLLOW_TUNED_MOVE,
                **self.detect_kwargs,
                'min_confidence': self.follow_threshold(),
            },
        )
        if not det.ok or len(det) < need:
            return None
        k, j = _nearest_unique(self.ed_rc, det.pixel_rc, REVIVE_GATE * sp)
        if len(k) < need:
            return None
        self._dead[k] = False
        self._gap[k] = 0
        self._step[k] = 0.0
        self._map[k] = np.eye(2)
        self._pos[k] = det.pixel_rc[j]
        self._follow_conf = float(np.median(det.confidence[j]))
        return k, det.pixel_rc[j], det.plain_confidence[j]

    def _coast(self, idx, pred, warped):
        """Unmatched tracks: keep an internal prediction, count the gap, drop after max_gap."""
        if len(idx) == 0:
            return
        self._step[idx] = warped - self._pos[idx]
        self._pos[idx] = warped
        self._gap[idx] += 1
        self._dead[idx] |= self._gap[idx] > self.max_gap

    def _start(self, frame: Frame, mask) -> TagPointSet:
        self.reset()
        self._started = True
        self.last_phase = frame.phase_index
        kwargs = dict(self.detect_kwargs)
        geom = self.geometry if self.geometry is not None else getattr(frame, 'geometry', None)
        if geom is not None and 'spacing_range_px' not in kwargs:
            kwargs['spacing_range_px'] = tag_period_range_px(
                min(geom.row_spacing, geom.column_spacing)
            )
        det = detect_intersections(
            frame.image, mask=mask, spacing_px=self.spacing_px, angles=self.angles, **kwargs
        )
        if self.ed_coverage and mask is not None and det.params is not None:
            p = det.params
            cell = float(np.prod(p.spacing_px) / max(abs(np.sin(p.angles[0] - p.angles[1])), 1e-6))
            if len(det) < ED_THIN_SHARE * np.count_nonzero(mask) / cell:
                thin = detect_intersections(
                    frame.image, mask=mask, params=p, **{**kwargs, 'coverage_normalised': True}
                )
                if len(thin) > len(det):
                    det = thin
        self.last_detection = det
        note = (
            ''
            if frame.phase_index == 0
            else f'no ED frame: started at phase {frame.phase_index}; '
        )
        if not det.ok:
            self._ed_failure = f'detection at phase {frame.phase_index} failed: {det.reason}'
            return self._result(
                frame, None, None, None, note + f'ED detection failed: {det.reason}'
            )
        self.params = det.params
        if mask is not None:
            self.ed_mask = np.asarray(mask, bool).copy()
            self.ed_image = np.asarray(frame.image, np.float32).copy()
        n = len(det)
        self._map = np.tile(np.eye(2), (n, 1, 1))
        self.track_id = np.arange(n, dtype=np.int32)
        self.ed_rc = det.pixel_rc.copy()
        self.labels = det.labels.copy()
        self._pos = det.pixel_rc.copy()
        self._step = np.zeros((n, 2))
        self._gap = np.zeros(n, int)
        self._dead = np.zeros(n, bool)
        self._follow_conf = float(np.median(det.confidence)) if n else np.nan
        return self._result(
            frame, det.pixel_rc, self.track_id, det.plain_confidence, note.rstrip('; ')
        )

    def _propagated_mask(self, pred, live, shape, erode: int = 0, dilate: int = 0):
        """
        ED mask warped to the predicted configuration (TPS from predicted to ED positions).

        Returns ``(filter_mask, accept_mask)``: the warped mask eroded by ``erode`` px
        (filtering support) and dilated by ``dilate`` px (where points may lie); ``(None, None)``
        when it cannot be built.
        """
        if len(live) < 4 or self.ed_mask is None or self.ed_mask.shape != tuple(shape):
            return None, None
        # Smoothing keeps the extrapolation to the wall's border (outside the points) near-affine.
        inv = ThinPlateSpline.fit(pred, self.ed_rc[live], lam=300.0)
        sp = float(np.mean(self.params.spacing_px))
        lo = np.maximum(np.floor(pred.min(0) - 3 * sp), 0).astype(int)
        hi = np.minimum(np.ceil(pred.max(0) + 3 * sp) + 1, np.array(shape)).astype(int)
        if np.any(hi - lo < 2):
            return None, None
        # The warp is smooth on the scale of a tag spacing: evaluate it every 4 px and
        # interpolate bilinearly (the TPS kernel on every pixel would dominate the frame time).
        step = 4
        rows = np.arange(lo[0], hi[0] + step, step, dtype=float)
        cols = np.arange(lo[1], hi[1] + step, step, dtype=float)
        grid = np.empty((len(rows), len(cols), 2))
        grid[..., 0] = rows[:, None]
        grid[..., 1] = cols[None, :]
        src = inv(grid.reshape(-1, 2)).reshape(grid.shape).astype(np.float32)
        fr, fc = _coarse_index(int(hi[0] - lo[0]), int(hi[1] - lo[1]), step)
        map_r = cv2.remap(src[..., 0], fc, fr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        map_c = cv2.remap(src[..., 1], fc, fr, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        warped = cv2.remap(
            self.ed_mask.astype(np.uint8),
            map_c,
            map_r,
            cv2.INTER_NEAREST,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        if not warped.any():
            return None, None

        def disk(r):
            return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))

        acc_w = cv2.dilate(warped, disk(dilate)) if dilate > 0 else warped
        # The propagated border is uncertain: static background tags or blood just outside it
        # bias the phase more than a lost rim of myocardium does, hence the erosion.
        filt_w = (
            cv2.erode(warped, disk(erode))
            if erode > 0
            else cv2.dilate(warped, disk(-erode))
            if erode < 0
            else warped
        )
        if not filt_w.any():
            filt_w = warped
        accept = np.zeros(shape, bool)
        accept[lo[0]:hi[0], lo[1]:hi[1]] = acc_w > 0
        filt = np.zeros(shape, bool)
        filt[lo[0]:hi[0], lo[1]:hi[1]] = filt_w > 0
        return filt, accept


@lru_cache(maxsize=64)
def _coarse_index(h: int, w: int, step: int):
    """
    Return each pixel of an (h, w) window's place on a grid of every ``step``-th pixel.

    ``(rows, cols)``, float32 (h, w) each, read-only (``cv2.remap`` maps): remembered, since
    a slice's windows keep their sizes from phase to phase.
    """
    fr, fc = np.meshgrid(
        np.arange(h, dtype=np.float32) / step,
        np.arange(w, dtype=np.float32) / step,
        indexing='ij',
    )
    for a in (fr, fc):
        a.setflags(write=False)
    return fr, fc


def _nearest_unique(pred: np.ndarray, rc: np.ndarray, gate: float):
    """
    Pair predicted positions with detections one to one, nearest pairs first, within ``gate``.

    Parameters
    ----------
    pred : ndarray, shape (K, 2)
        Predicted (row, col) positions, px.
    rc : ndarray, shape (M, 2)
        Detected (row, col) positions, px (M ≥ 1).
    gate : float
        Largest distance of a pair, px.

    Returns
    -------
    k, j : ndarray of int, shape (P,)
        Indices into ``pred`` and ``rc`` of the pairs.

    """
    dist, j = cKDTree(rc).query(pred, distance_upper_bound=gate)
    ok = np.isfinite(dist)
    taken, ks, js = set(), [], []
    for k in np.argsort(np.where(ok, dist, np.inf))[:int(ok.sum())]:
        if j[k] in taken:
            continue
        taken.add(j[k])
        ks.append(k)
        js.append(j[k])
    return np.array(ks, int), np.array(js, int)
