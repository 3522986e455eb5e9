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
Quality verdicts: ``ok``, ``degraded`` or ``failed`` for every phase's result, with reasons.

A number delivered as if right when it is not is the worst failure this product can have, so
each solved phase says how far its data supported it (:func:`phase_verdict`, from the solver)
and whether the result is physiologically possible at all (:func:`metrics_verdict`, from the
analyzer). Every threshold is relative (a fraction of the ED tag points, of the SA slices, of
the LV's size, of a pixel) so that it means the same on any scanner, protocol or heart size.

Calibration (24 randomized-protocol studies of ``mlv-ros bench robustness``, seeds 1000–1015 and
2000–2007, 710 solved phases, median 3D error against the analytic truth): the 5 phases more than
2 mm off are all flagged (4 degraded, 1 failed), 10 of the 14 between 1 and 2 mm are (degraded);
of the 691 within 1 mm, 11 are flagged (degraded: 1.6 %, 10 of them by a lost end slice of the
stack). The physiological bounds are a second line: in the earlier
calibration they fired on 4 phases only, all failed by the data already (10–129 mm off).

The sector check (:func:`weakest_sector`) was added for a regional error the whole-phase checks
pass as ok: an akinetic sector loses its SA tracks and the solver carries it with its neighbours
(1012: 0 of 22 phases flagged while its akinetic segment is 1.6–3.0 mm off at phases 6–12). It
was first calibrated with the outlier screen against the global fit on
(``MotionTracker.screen_global``), and is re-measured here with today's default (off):
``bench/retrack.py --phases`` of main bec0921 (its re-track and re-solve) on the same 24 studies
(686 solved phases; each phase's verdict against its median 3D error and its worst AHA segment's
median error, the truth's segments) and on 16 held-out ones (3000–3007 and 4000–4007, 428
phases); "before": the whole-phase checks alone:

=====================================================  =======  ==============  =============
phases (median 3D error)                               count    flagged before  flagged after
=====================================================  =======  ==============  =============
24 studies, phase within 1 mm                          669      21              27
24 studies, 1–2 mm / over 2 mm                         16 / 1   16 / 1          16 / 1
24 studies, worst segment over 2 mm                    24       15              18
24 studies, within 1 mm, every segment within 1.5 mm   639      13              15
held out, phase within 1 mm                            428      12              16
held out, worst segment over 2 mm                      9        2               2
held out, within 1 mm, every segment within 1.5 mm     402      8               11
=====================================================  =======  ==============  =============

Newly flagged within 1 mm: 1012's phases 9–12 (a segment 1.6–2.7 mm off) and 1014's 9–10 (every
segment within 1.0 mm); held out 3001's phase 11 (a segment 1.8 mm off) and 3003's 22–24 (every
segment within 0.8 mm). Not flagged: 1012's phase 8 (2.2 mm off), 2006's akinetic segment
(2.1–2.8 mm off at phases 6–10: it keeps 10 of its 13 SA tracks at phase 7, and its weakest
3-slice × 90° sector 0.55–0.76 of the heart's share) and, held out, 4006's (2.2–2.9 mm off at
phases 5–10) and 3001's phase 18. The window (90°, 3 slices) is
about one AHA segment; without the motion gate, over the 24 studies (screen on), 120° windows
miss all of 1012 (they dilute its 60–90° gap), and smaller ones hold too few points to tell a gap
from chance: phases within 1 mm with every segment within 1.5 mm newly flagged by 3 slices × 90°:
19, 2 slices × 90°: 57, 3 slices × 60°: 86. The motion gate (:data:`SECTOR_MOTION_SHARE`) leaves
ok late phases, within 1 mm, that the sector check alone would flag (screen on: 16 of 26).

The regional fit check (:func:`worst_fit_sector`) is for the sectors that keep some tracks (4006,
2006): a region that moves unlike its neighbours loses more tracks than the heart, and the
elastic model, carrying it with its neighbours, leaves the tracks that are left farther off than
elsewhere. 4006's akinetic segment 7 keeps 7 of its 25 SA tracks at ES, left 0.47 mm off
(median; 0.08–0.20 mm in the other segments, localisation noise σ 0.08 mm), while it is 2.2 mm
off and its basal neighbour 2.9 mm, both along the long axis, where no LA view has a track.
Neither sign alone tells it from good phases. It was calibrated on per-track residuals dumped
from ``bench/retrack.py``'s track and solve of the 24 studies (each SA track re-attached at its
final slice offset; the rule evaluated offline on them): the largest median residual of a
sector's used points over the phase's (2 slices × 60°, 4+ points) is 3.1–3.8 at 4006's off
phases and 2.2–2.9 at 2006's, but beyond 3 in 32 of 201 good phases of 8 of the studies (16 %;
21 of them in the normal hearts 1001, 1003, 1004 and 1005); in units of the slices'
localisation noise 4006's read 4.5–7.1, 1004's good ones up to 6.6. Together (2 SA slices × 60°
holding 8+ ED tag points, still using 4 or more but fewer than 0.6 × the heart's share, whose
used points' median residual is above 2.5 × the heart's, under the same motion gate; constants
chosen on the 24 studies' dumped residuals; the table: ``bench/retrack.py --phases`` with the
check, "before": today's verdict with the sector check):

=====================================================  =======  ==============  =============
phases (median 3D error)                               count    flagged before  flagged after
=====================================================  =======  ==============  =============
24 studies, worst segment over 2 mm                    24       18              20
24 studies, within 1 mm, every segment within 1.5 mm   639      15              27
held out, worst segment over 2 mm                      9        2               7
held out, within 1 mm, every segment within 1.5 mm     402      11              16
=====================================================  =======  ==============  =============

Newly flagged with a segment over 2 mm: 1012's phase 8, 2006's 6 and, held out, 4006's 6–10 (5 not:
2.2 mm off; 11 too, 1.7 mm). Newly flagged within 1 mm, every segment within 1.5 mm: 12 of 639 (1.9
%; 4 in the infarcts 1002, 1011, 1012) and 5 of 402 held out (1.2 %: 3002's 14, 3003's 14, 3005's
15 and, in the infarct 3006, 7 and 9). 2006's phases 7–10 (2.1–2.8 mm off) stay ok: its akinetic
segment keeps most of its SA tracks, their residual 2.2–2.7 × the phase's; its error is along the
long axis, which no SA track measures. On the dumped residuals, 0.75 × the share and 3 × the
residual newly flag 3.6 % of the good phases, and 3 slices × 90° no off phase. The segments named
are the analysis frame's (4006: mid anterior / anteroseptal, apical anterior; the truth's segment 7
is mid anterior, its basal neighbour 1 the one most off).

A phase flagged by the sector check alone is confined to the segments its reason names
(:attr:`Verdict.confined_to`, ``ModelState.degraded_segments``): the findings inflate only
those (:data:`mlv_ros.core.analysis.findings.VERDICT_INFLATION`) and, at ES, leave them
unclassed (:mod:`mlv_ros.core.analysis.findings`); a whole-heart reason beside it keeps the
whole phase less sure. ``bench/retrack.py --strain`` on main bec0921: at 1014's ES (phase 10,
flagged for segments 2–4, every segment within 1 mm) 8 segments read indeterminate (2–4
unsupported, 13–17 as in an ok phase), where inflating every segment read all 17; 1012's ES
(phase 8) is not flagged on this main (its sector is at phases 9–12, named segments 11, 12, 16
of a run whose segments come from the anatomical prior: the truth's akinetic 7 lies in them)
and reads as before. Found / missed / false counts are unchanged on both.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

OK, DEGRADED, FAILED = 0, 1, 2
LEVEL_NAMES = ('ok', 'degraded', 'failed')

# Data support (solver).
#: Below this fraction of the ED tag points still constraining the model: degraded / failed.
TRACKED_DEGRADED, TRACKED_FAILED = 0.3, 0.1
#: Below this fraction of the SA slices (those with ED tag points) still holding
#: MIN_SLICE_POINTS control points: degraded. No SA slice at all: failed (twist and
#: circumferential motion are measured only in short-axis planes). An end slice of the stack
#: below MIN_SLICE_POINTS: degraded (the levels beyond the last measured one are extrapolated).
SA_SLICES_DEGRADED = 0.6
MIN_SLICE_POINTS = 3
#: RMS in-plane residual at the control points above this, in pixels: degraded (intersections
#: are localised to ~0.1–0.2 px; a model that cannot come within half a pixel of them is
#: fighting inconsistent tracks).
RESIDUAL_DEGRADED_PX = 0.5
#: More than this fraction of the tag points inside the model rejected as outliers (slipped or
#: swapped tracks): degraded, the identities of the rest being in doubt.
REJECTED_DEGRADED = 0.2
#: Regional data support. A sector is SECTOR_SLICES consecutive SA slices (those with ED tag
#: points, in stack order) × SECTOR_DEG of circumferential angle about the model's long axis,
#: at any start angle. A sector holding SECTOR_MIN_POINTS or more ED tag points of which the
#: share still used at this phase is below SECTOR_SHARE_DEGRADED × the share over all SA slices:
#: degraded. The solver carries such a sector with its neighbours' motion (the elastic model
#: smooths across it), which is wrong by millimetres exactly where the wall moves unlike its
#: neighbours (an akinetic or dyskinetic region, whose tracks the tracker loses first), and
#: nothing else in the phase shows it: the residual is at the points that are there.
SECTOR_SLICES = 3
SECTOR_DEG = 90.0
SECTOR_MIN_POINTS = 10
SECTOR_SHARE_DEGRADED = 0.3
#: ... checked only while the heart is at least this fraction of its largest displacement so far
#: from ED (median over the model): a sector carried by its neighbours is off by about how
#: differently it moves, which vanishes as every sector returns to its ED place (late diastole).
SECTOR_MOTION_SHARE = 0.5
# weakest_sector compares this many (start angle, point) pairs at once, at most (memory only).
_SECTOR_BLOCK = 1 << 20
#: Regional fit. A sector of FIT_SECTOR_SLICES consecutive SA slices × FIT_SECTOR_DEG holding
#: FIT_SECTOR_MIN_POINTS or more ED tag points, of which it still uses less than
#: FIT_SECTOR_SHARE × the heart's share but FIT_SECTOR_MIN_USED or more, whose used points are
#: left, at their median, more than FIT_SECTOR_RATIO × the median over all SA slices' used
#: points from the solved motion (in-plane residual): degraded, under the same motion gate. A
#: region that moves unlike its neighbours (an akinetic segment) loses tracks but keeps some;
#: the elastic model pulls it along with its neighbours (along the long axis too, where no LA
#: view measures it), and cannot come as close to the tracks left there as it does elsewhere.
#: Either sign alone is common in good phases (a sector's share or its residual, see below).
FIT_SECTOR_SLICES = 2
FIT_SECTOR_DEG = 60.0
FIT_SECTOR_MIN_POINTS = 8
FIT_SECTOR_MIN_USED = 4
FIT_SECTOR_SHARE = 0.6
FIT_SECTOR_RATIO = 2.5

# Physiological bounds (analyzer).
#: Ejection fraction outside these bounds: degraded / failed (the cavity grew by more than 10 %
#: / 30 % over ED, or shrank beyond what a ventricle does).
EF_DEGRADED = (-0.1, 0.85)
EF_FAILED = (-0.3, 0.95)
#: Largest particle displacement from ED above this fraction of the ED long-axis length: failed
#: (the whole LV shortens by ~15 %; a wall point never travels half the ventricle).
DISPLACEMENT_FAILED = 0.5
#: A segment's mean Green–Lagrange strain beyond this magnitude: degraded.
STRAIN_DEGRADED = 1.0
#: ED cavity volume outside the adult human range (small to severely dilated ventricles):
#: degraded (check pixel spacing and the segmentation); beyond any heart: failed.
EDV_DEGRADED_ML = (20.0, 700.0)
EDV_FAILED_ML = (0.01, 2000.0)

# Registration.
#: Fewer than this share of the SA slices segmented at ED: degraded.
SA_SEGMENTED_DEGRADED = 0.5
#: ED wall thickness of the registered model (:meth:`RegistrationResult.wall_thickness_mm`), mm.
#: Mean outside WALL_MEAN_DEGRADED_MM: degraded (adult LVs: mean 6–11 mm, down to ~5 mm in
#: dilated cardiomyopathy, up to ~20 mm in concentric hypertrophy, hypertrophic cardiomyopathy
#: 15–30+ mm in its thickest segments); outside WALL_MEAN_FAILED_MM: failed, no heart (check the
#: pixel spacing and the segmentation). Its 5th percentile below WALL_THIN_DEGRADED_MM: degraded
#: (a thinned infarct scar is still 3–4 mm; thinner is the model missing the wall). Measured on
#: our registrations (quick studies): presets normal / infarct 8.8 mean, 8.5 5th percentile;
#: dilated 7.3 / 6.8; hypertrophic 15.8 / 14.4; the cylinder 6.2 / 2.2; random protocols
#: 1000, 1003 16.0 / 14.7 and 8.8 / 8.3.
WALL_MEAN_DEGRADED_MM = (4.0, 30.0)
WALL_MEAN_FAILED_MM = (1.5, 50.0)
WALL_THIN_DEGRADED_MM = 1.5


@dataclass
class Verdict:
    """
    ``level`` (OK / DEGRADED / FAILED) and the reasons for anything but OK.

    Attributes
    ----------
    level : int
        OK, DEGRADED or FAILED.
    reasons : list of str
        Why, one sentence each (empty when OK).
    regions : dict
        Reason → the regions (e.g. AHA segments) it is confined to, for a regional reason (a
        sector of the heart the data no longer support, :func:`weakest_sector`); a reason not
        in it concerns the whole heart. Read it through :attr:`confined_to`.

    """

    level: int = OK
    reasons: list[str] = field(default_factory=list)
    regions: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return LEVEL_NAMES[self.level]

    def flag(self, level: int, reason: str, region=()) -> None:
        """
        Raise the level to ``level`` for ``reason``.

        Parameters
        ----------
        level : int
            DEGRADED or FAILED (the level never drops).
        reason : str
            Why, one sentence.
        region : sequence, optional
            The regions a regional reason is confined to (e.g. the AHA segments of a sector,
            :attr:`Sector.labels`); empty: the reason concerns the whole heart.

        """
        self.level = max(self.level, int(level))
        self.reasons.append(reason)
        if len(region):
            self.regions[reason] = tuple(region)

    def merge(self, other: 'Verdict') -> 'Verdict':
        """Return the worse of both levels, with both sets of reasons and regions."""
        return Verdict(
            max(self.level, other.level),
            [*self.reasons, *other.reasons],
            {**self.regions, **other.regions},
        )

    @property
    def text(self) -> str:
        return '; '.join(self.reasons)

    @property
    def confined_to(self) -> tuple:
        """
        Return the regions a degraded verdict is confined to, in the order first named.

        Empty unless the level is DEGRADED and every reason is regional: a phase degraded for
        a whole-heart reason (or failed) is less sure everywhere.
        """
        if self.level != DEGRADED or not self.reasons:
            return ()
        if any(r not in self.regions for r in self.reasons):
            return ()
        return tuple(dict.fromkeys(x for r in self.reasons for x in self.regions[r]))

    @classmethod
    def from_parts(cls, level: int, text: str, confined_to=()) -> 'Verdict':
        """
        Return the verdict of a message's ``verdict`` / ``verdict_reasons`` fields.

        Parameters
        ----------
        level : int
            OK, DEGRADED or FAILED.
        text : str
            ``"; "``-separated reasons.
        confined_to : sequence, optional
            The regions the verdict is confined to (:attr:`confined_to` of the verdict sent,
            e.g. ModelState.degraded_segments); every reason is then regional, confined to
            them. Ignored unless ``level`` is DEGRADED.

        Raises
        ------
        ValueError
            ``level`` is none of OK, DEGRADED, FAILED.

        """
        v = cls(checked_level(level), [r for r in str(text).split('; ') if r])
        region = tuple(confined_to)
        if v.level == DEGRADED and region:
            v.regions = {r: region for r in v.reasons}
        return v


def checked_level(level) -> int:
    """
    ``level`` as an int if it is OK, DEGRADED or FAILED.

    Raises
    ------
    ValueError
        Any other value.

    """
    if int(level) not in (OK, DEGRADED, FAILED):
        raise ValueError(f'verdict must be 0 (ok), 1 (degraded) or 2 (failed), got {level}')
    return int(level)


def _where(sector) -> str:
    """Return where a :class:`Sector` or :class:`FitSector` lies: its slices, θ and regions."""
    where = (
        f'SA slice {sector.slices[0]}'
        if len(sector.slices) == 1
        else f'SA slices {sector.slices[0]}–{sector.slices[-1]}'
    )
    names = f' ({", ".join(sector.labels)})' if sector.labels else ''
    return f'{where}, θ {sector.start_deg:.0f}–{sector.end_deg % 360:.0f}°{names}'


@dataclass
class Sector:
    """
    The SA sector a phase's data support least (:func:`weakest_sector`).

    Attributes
    ----------
    slices : tuple of int
        Its SA slice indices, in stack order.
    start_deg, end_deg : float
        Circumferential extent of its lost ED tag points, degrees (counter-clockwise from
        ``start_deg`` in [0, 360) to ``end_deg``, which may exceed 360).
    used, points : int
        Its ED tag points still used at this phase, and all of them.
    share : float
        ``used / points`` relative to the same share over all SA slices (1: as well supported
        as the heart, 0: no point left).
    heart_share : float
        The share of all SA slices' ED tag points still used.
    labels : tuple of str
        Names of the (at most 3) regions most of its lost points lie in, most first (empty if
        not given).

    """

    slices: tuple
    start_deg: float
    end_deg: float
    used: int
    points: int
    share: float
    heart_share: float
    labels: tuple = ()

    @property
    def reason(self) -> str:
        """Return the verdict's reason: the sector, its lost points and the heart's."""
        return (
            f'{_where(self)}: {self.points - self.used} of {self.points} ED tag points lost '
            f'({1.0 - self.heart_share:.0%} over all SA slices): the model carries it with its '
            'neighbours'
        )


def _sector_arrays(sa_tracks: dict) -> tuple:
    """
    Return the slices in stack order and per slice the angles, use flags, labels and residuals.

    Parameters
    ----------
    sa_tracks : dict
        As :func:`weakest_sector` and :func:`worst_fit_sector` take it.

    Returns
    -------
    keys : list
        The slice indices, sorted.
    theta, used, labels, residual : dict
        Slice index → its points' angles in [0, 360) (degrees), use flags, region names ('' if
        not given) and in-plane residuals (mm; NaN if not given).

    Raises
    ------
    ValueError
        A slice's arrays of unequal length.

    """
    keys = sorted(sa_tracks)
    theta, used, labels, residual = {}, {}, {}, {}
    for k in keys:
        entry = sa_tracks[k]
        theta[k] = np.mod(np.asarray(entry[0], dtype=np.float64).ravel(), 360.0)
        used[k] = np.asarray(entry[1], dtype=bool).ravel()
        labels[k] = np.asarray(entry[2] if len(entry) > 2 else [''] * len(used[k]), dtype=str)
        residual[k] = np.asarray(
            entry[3] if len(entry) > 3 else np.full(len(used[k]), np.nan), dtype=np.float64
        ).ravel()
        if not theta[k].shape == used[k].shape == labels[k].shape == residual[k].shape:
            raise ValueError(
                f'SA slice {k}: {theta[k].size} angles, {used[k].size} used flags, '
                f'{labels[k].size} labels and {residual[k].size} residuals'
            )
    return keys, theta, used, labels, residual


def _check_window(slices, width_deg, min_points) -> None:
    """Raise ValueError unless ``slices``, ``min_points`` >= 1 and ``width_deg`` in (0, 360]."""
    if int(slices) < 1 or int(min_points) < 1 or not 0.0 < float(width_deg) <= 360.0:
        raise ValueError(
            f'slices and min_points must be >= 1 and width_deg in (0, 360], got {slices}, '
            f'{min_points}, {width_deg}'
        )


def _windows(keys: list, theta: dict, slices: int, width_deg: float, *per_slice: dict):
    """
    Yield every sector, a block of start angles at a time, with its run's per-point arrays.

    A sector is ``slices`` consecutive slices × ``width_deg`` from one of their points' angles.
    Every start angle of a run at once, in blocks of at most ``_SECTOR_BLOCK`` (start, point)
    pairs: the offset ``θ − a0`` lies in (−360, 360), where ``np.mod(·, 360)`` is it, or it + 360
    below 0, bit for bit.

    Parameters
    ----------
    keys : list
        Slice indices in stack order.
    theta : dict
        Slice index → its points' angles in [0, 360), degrees.
    slices : int
        Consecutive slices per sector (all of them if fewer).
    width_deg : float
        Circumferential width, degrees.
    *per_slice : dict
        Further slice index → per-point arrays, concatenated over each run as ``theta`` is.

    Yields
    ------
    run : list
        The sectors' slices.
    a0 : ndarray, shape (S,)
        The block's start angles, ascending, degrees.
    inside : ndarray of bool, shape (S, P)
        Per start, over the run's points (concatenated in slice order), those in the sector.
    offset : ndarray, shape (S, P)
        Their angles from each start in [0, 360), degrees.
    *arrays : ndarray, shape (P,)
        ``per_slice`` concatenated over the run.

    """
    m = min(int(slices), len(keys))
    for j in range(len(keys) - m + 1):
        run = keys[j:j + m]
        th = np.concatenate([theta[k] for k in run])
        arrays = [np.concatenate([d[k] for k in run]) for d in per_slice]
        starts = np.unique(th)
        step = max(1, _SECTOR_BLOCK // max(th.size, 1))
        for b in range(0, starts.size, step):
            a0 = starts[b:b + step]
            offset = th[None, :] - a0[:, None]
            np.add(offset, 360.0, out=offset, where=offset < 0.0)
            yield (run, a0, offset < width_deg, offset, *arrays)


def _main_labels(labels: np.ndarray) -> tuple:
    """Return the (at most 3) non-empty names most frequent in ``labels``, most first."""
    names, counts = np.unique(labels, return_counts=True)
    return tuple([str(names[i]) for i in np.argsort(-counts, kind='stable') if names[i]][:3])


def weakest_sector(
    sa_tracks: dict,
    slices: int = SECTOR_SLICES,
    width_deg: float = SECTOR_DEG,
    min_points: int = SECTOR_MIN_POINTS,
) -> Sector | None:
    """
    Return the SA sector whose ED tag points are least used at this phase.

    Sectors are ``slices`` consecutive SA slices (all of them if fewer) × ``width_deg`` of
    circumferential angle, starting at every point's angle; only those holding ``min_points``
    or more ED tag points count. Of these, the one whose share of points still used, relative
    to the share over all SA slices, is smallest (the larger one on a tie).

    Parameters
    ----------
    sa_tracks : dict
        SA slice index → ``(theta_deg, used)``, ``(theta_deg, used, labels)`` or ``(theta_deg,
        used, labels, residual_mm)``, one entry per ED tag point of the slice: its
        circumferential angle about the model's long axis (degrees), whether this phase still
        uses it (bool), the name of the region it lies in (e.g. its AHA segment; for the reason)
        and its in-plane residual (:func:`worst_fit_sector`; not read here). Indices run in
        stack order.
    slices : int
        Consecutive SA slices per sector, >= 1.
    width_deg : float
        Circumferential width of a sector, degrees, in (0, 360].
    min_points : int
        Fewest ED tag points a sector must hold to count, >= 1.

    Returns
    -------
    Sector or None
        None if no sector holds ``min_points`` points or no SA point is used at all (the
        whole-phase checks cover that).

    Raises
    ------
    ValueError
        ``slices``, ``width_deg`` or ``min_points`` out of range; a slice's arrays of unequal
        length.

    """
    _check_window(slices, width_deg, min_points)
    keys, theta, used, labels, _ = _sector_arrays(sa_tracks)
    total = sum(u.size for u in used.values())
    heart = sum(int(u.sum()) for u in used.values()) / total if total else 0.0
    if heart <= 0.0:
        return None
    best = None  # (share, n, run, a0)
    # The first start of the smallest (share, −n) wins, as in stack and angle order one start
    # at a time; a share is the used count over n, as the mean of the used flags divides it.
    for run, a0, inside, _, u in _windows(keys, theta, slices, width_deg, used):
        n = inside.sum(axis=1)
        ok = np.flatnonzero(n >= min_points)
        if ok.size == 0:
            continue
        share = np.count_nonzero(inside[ok] & u, axis=1) / n[ok] / heart
        least = ok[share == share.min()]
        i = int(least[np.argmax(n[least])])  # the first of the largest n among them
        cand = (float(share.min()), int(n[i]), run, float(a0[i]))
        if best is None or (cand[0], -cand[1]) < (best[0], -best[1]):
            best = cand
    if best is None:
        return None
    share, n, run, a0 = best
    th = np.concatenate([theta[k] for k in run])
    offset = np.mod(th - a0, 360.0)
    inside = offset < width_deg
    u = np.concatenate([used[k] for k in run])
    lab = np.concatenate([labels[k] for k in run])
    lost = inside & ~u
    span = offset[lost] if lost.any() else offset[inside]
    return Sector(
        tuple(int(k) for k in run),
        float(np.mod(a0 + span.min(), 360.0)),
        float(np.mod(a0 + span.min(), 360.0) + np.ptp(span)),
        int(u[inside].sum()),
        n,
        share,
        heart,
        _main_labels(lab[lost]),
    )


@dataclass
class FitSector(Sector):
    """
    The SA sector that lost tracks and whose tracks left the model fits worst.

    :func:`worst_fit_sector`'s result: a :class:`Sector` (``labels``: the regions most of its
    ED tag points lie in) with the residuals of its used points.

    Attributes
    ----------
    residual_mm, heart_residual_mm : float
        Median in-plane residual of its used points and of all SA slices' used points, mm.
    ratio : float
        ``residual_mm / heart_residual_mm``.

    """

    residual_mm: float = 0.0
    heart_residual_mm: float = 0.0
    ratio: float = 0.0

    @property
    def reason(self) -> str:
        """Return the verdict's reason: the sector, its lost points and its tracks' residual."""
        return (
            f'{_where(self)}: {self.points - self.used} of {self.points} ED tag points lost, '
            f'the {self.used} left {self.residual_mm:.2f} mm from the model (median), '
            f'{self.ratio:.1f}× the {self.heart_residual_mm:.2f} mm over all SA slices: the '
            'model moves it unlike its tracks'
        )


def worst_fit_sector(
    sa_tracks: dict,
    slices: int = FIT_SECTOR_SLICES,
    width_deg: float = FIT_SECTOR_DEG,
    min_points: int = FIT_SECTOR_MIN_POINTS,
    min_used: int = FIT_SECTOR_MIN_USED,
    max_share: float = FIT_SECTOR_SHARE,
) -> FitSector | None:
    """
    Return the SA sector that lost tracks and whose tracks left are farthest from the model.

    Sectors are as in :func:`weakest_sector`; only those holding ``min_points`` or more ED tag
    points, of which ``min_used`` or more are used (with a finite residual) but a share below
    ``max_share`` × the share over all SA slices, count. Of these, the one whose used points'
    median residual, relative to the median over all SA slices' used points, is largest (on a
    tie the one with the larger mean residual, then the one with more used points).

    Parameters
    ----------
    sa_tracks : dict
        SA slice index → ``(theta_deg, used, labels, residual_mm)`` per ED tag point
        (:func:`weakest_sector`); ``residual_mm`` is the point's in-plane distance from where
        the solved motion puts it, mm (NaN where not used). Entries without residuals have no
        point judged.
    slices, width_deg, min_points : int, float, int
        The sector's consecutive SA slices (>= 1) and circumferential width (degrees, in
        (0, 360]), and the fewest ED tag points it must hold to count (>= 1), as in
        :func:`weakest_sector`.
    min_used : int
        Fewest used points with a residual a sector must hold to count, >= 1.
    max_share : float
        A sector counts only if its share of points used is below this fraction of the heart's.

    Returns
    -------
    FitSector or None
        None if no sector counts or the median over all SA slices' used points is not
        positive.

    Raises
    ------
    ValueError
        ``slices``, ``width_deg``, ``min_points`` or ``min_used`` out of range; a slice's
        arrays of unequal length.

    """
    _check_window(slices, width_deg, min(int(min_points), int(min_used)))
    keys, theta, used, labels, residual = _sector_arrays(sa_tracks)
    total = sum(u.size for u in used.values())
    heart = sum(int(u.sum()) for u in used.values()) / total if total else 0.0
    judged = {k: used[k] & np.isfinite(residual[k]) for k in keys}
    every = np.concatenate([residual[k][judged[k]] for k in keys]) if keys else np.zeros(0)
    heart_mm = float(np.median(every)) if every.size else 0.0
    if not heart_mm > 0.0:
        return None
    best = None
    # Every start of a run at once; the median and mean only of the sectors that count, in
    # stack and angle order (the first of equal scores wins).
    for run, a0, inside, offset, judged_run, res_run in _windows(
        keys, theta, slices, width_deg, judged, residual
    ):
        n = inside.sum(axis=1)
        w = inside & judged_run
        u = w.sum(axis=1)
        ok = np.flatnonzero((n >= min_points) & (u >= min_used))
        ok = ok[u[ok] / n[ok] < max_share * heart]
        for i in ok:
            r = res_run[w[i]]
            score = (float(np.median(r)), float(r.mean()), int(u[i]))
            if best is None or score > best[0]:
                best = (score, run, float(a0[i]), int(n[i]), inside[i], offset[i])
    if best is None:
        return None
    (med, _, u), run, a0, n, inside, offset = best
    span = offset[inside]
    return FitSector(
        tuple(int(k) for k in run),
        float(np.mod(a0 + span.min(), 360.0)),
        float(np.mod(a0 + span.min(), 360.0) + np.ptp(span)),
        u,
        n,
        u / n / heart,
        heart,
        _main_labels(np.concatenate([labels[k] for k in run])[inside]),
        med,
        heart_mm,
        med / heart_mm,
    )


def phase_verdict(
    tracked: int,
    tracked_at_ed: int,
    sa_points: dict,
    residual_mm: float,
    pixel_mm: float,
    rejected: int = 0,
    candidates: int = 0,
    sa_found: dict | None = None,
    sa_tracks: dict | None = None,
    motion_share: float | None = None,
) -> Verdict:
    """
    How far one phase's tag data supports its solution.

    Parameters
    ----------
    tracked : int
        Control points used at this phase (inside the model, outliers removed).
    tracked_at_ed : int
        ED tag points inside the model (the references tracks are matched to).
    sa_points : dict
        SA slice index → control points used on it at this phase, for every SA slice that has
        ED references (0 for a slice whose tracks are all lost). Indices run in stack order
        (by position along the LV's long axis, either way), so the lowest and highest are the
        stack's ends.
    residual_mm : float
        RMS in-plane residual at the control points, mm.
    pixel_mm : float
        In-plane pixel size of the tagged images, mm (the residual is judged in pixels).
    rejected, candidates : int
        Tag points rejected as outliers, of the ``candidates`` inside the model (the solver pass
        that rejected the largest share).
    sa_found : dict, optional
        SA slice index → tag points the tag detector found on it at this phase, inside the
        model or not (default: ``sa_points``). An end slice is lost when it has fewer than
        ``MIN_SLICE_POINTS`` of these: a basal slice the base moves out of keeps its tags.
    sa_tracks : dict, optional
        SA slice index → per ED tag point its angle (degrees), whether it is used at this
        phase, and optionally its region's name and its in-plane residual, mm
        (:func:`weakest_sector`): a sector whose share of points used is below
        ``SECTOR_SHARE_DEGRADED`` × the heart's is degraded, and one that lost tracks and whose
        used points' median residual is above ``FIT_SECTOR_RATIO`` × the heart's
        (:func:`worst_fit_sector`). None: not checked.
    motion_share : float, optional
        The model's median displacement from ED at this phase over the largest of the phases
        solved so far; the sector checks only run from ``SECTOR_MOTION_SHARE`` on (None:
        always).

    Returns
    -------
    Verdict

    """
    v = Verdict()
    frac = tracked / tracked_at_ed if tracked_at_ed > 0 else 0.0
    if frac < TRACKED_FAILED:
        v.flag(
            FAILED,
            f'{tracked} of {tracked_at_ed} ED tag points tracked ({frac:.0%} < '
            f'{TRACKED_FAILED:.0%})',
        )
    elif frac < TRACKED_DEGRADED:
        v.flag(
            DEGRADED,
            f'{tracked} of {tracked_at_ed} ED tag points tracked ({frac:.0%} < '
            f'{TRACKED_DEGRADED:.0%})',
        )
    if sa_points:
        live = sorted(k for k, n in sa_points.items() if n >= MIN_SLICE_POINTS)
        share = len(live) / len(sa_points)
        if not live:
            v.flag(
                FAILED,
                f'no SA slice with {MIN_SLICE_POINTS}+ tag points (of {len(sa_points)}): twist '
                'and '
                f'circumferential motion unmeasured',
            )
        elif share < SA_SLICES_DEGRADED:
            v.flag(
                DEGRADED,
                f'{len(live)} of {len(sa_points)} SA slices with {MIN_SLICE_POINTS}+ tag points '
                f'({share:.0%} < {SA_SLICES_DEGRADED:.0%})',
            )
        found = sa_points if sa_found is None else sa_found
        kept = [k for k in sorted(sa_points) if found.get(k, 0) >= MIN_SLICE_POINTS]
        lost = [k for k in sorted(sa_points) if kept and (k < kept[0] or k > kept[-1])]
        if lost:
            # The stack's measured span has shrunk: the model goes on past its last measured
            # level unconstrained, however many slices inside the span still hold points.
            v.flag(
                DEGRADED,
                f'SA slice{"s" if len(lost) > 1 else ""} {", ".join(map(str, lost))} at the end '
                f'of the stack without {MIN_SLICE_POINTS}+ tag points: the motion beyond slice'
                f' {kept[0] if lost[0] < kept[0] else kept[-1]} is extrapolated',
            )
    else:
        v.flag(
            FAILED, 'no SA slice has ED tag points: twist and circumferential motion unmeasured'
        )
    if pixel_mm > 0 and np.isfinite(residual_mm) and residual_mm / pixel_mm > RESIDUAL_DEGRADED_PX:
        v.flag(
            DEGRADED,
            f'fit residual {residual_mm:.2f} mm = {residual_mm / pixel_mm:.2f} px '
            f'(> {RESIDUAL_DEGRADED_PX:g} px): tracks and model disagree',
        )
    moving = motion_share is None or motion_share >= SECTOR_MOTION_SHARE
    sector = weakest_sector(sa_tracks) if sa_tracks and moving else None
    if sector is not None and sector.share < SECTOR_SHARE_DEGRADED:
        # Regional: the findings mark the sector's segments, not the whole heart's.
        v.flag(DEGRADED, sector.reason, region=sector.labels)
    misfit = worst_fit_sector(sa_tracks) if sa_tracks and moving else None
    if misfit is not None and misfit.ratio > FIT_SECTOR_RATIO:
        v.flag(DEGRADED, misfit.reason, region=misfit.labels)
    if candidates > 0 and rejected / candidates > REJECTED_DEGRADED:
        v.flag(
            DEGRADED,
            f'{rejected} of {candidates} tag points rejected as outliers '
            f'(> {REJECTED_DEGRADED:.0%})',
        )
    return v


def metrics_verdict(
    ejection_fraction: float,
    max_displacement_mm: float,
    long_axis_mm: float,
    segment_strains=(),
    edv_ml: float | None = None,
) -> Verdict:
    """
    Whether one phase's motion is physiologically possible.

    Parameters
    ----------
    ejection_fraction : float
        (EDV − V) / EDV at this phase.
    max_displacement_mm : float
        Largest particle displacement from ED, mm.
    long_axis_mm : float
        ED long-axis length of the model, mm.
    segment_strains : sequence of ndarray
        Per-segment mean strains (e.g. E_rr, E_cc, E_ll over the AHA segments), any may be empty.
    edv_ml : float, optional
        ED cavity volume of the registered model, ml.

    Returns
    -------
    Verdict

    """
    v = Verdict()
    if edv_ml is not None:
        if not np.isfinite(edv_ml) or not EDV_FAILED_ML[0] <= edv_ml <= EDV_FAILED_ML[1]:
            v.flag(
                FAILED,
                f'ED cavity volume {edv_ml:.4g} ml: not a heart (check pixel spacing and '
                'segmentation)',
            )
        elif not EDV_DEGRADED_ML[0] <= edv_ml <= EDV_DEGRADED_ML[1]:
            v.flag(
                DEGRADED,
                f'ED cavity volume {edv_ml:.4g} ml outside [{EDV_DEGRADED_ML[0]:g}, '
                f'{EDV_DEGRADED_ML[1]:g}] ml (check pixel spacing and segmentation)',
            )
    ef = float(ejection_fraction)
    if not np.isfinite(ef) or not EF_FAILED[0] <= ef <= EF_FAILED[1]:
        v.flag(
            FAILED,
            f'ejection fraction {ef:.2f} outside [{EF_FAILED[0]:g}, {EF_FAILED[1]:g}]: not a '
            "ventricle's volume",
        )
    elif not EF_DEGRADED[0] <= ef <= EF_DEGRADED[1]:
        v.flag(
            DEGRADED,
            f'ejection fraction {ef:.2f} outside [{EF_DEGRADED[0]:g}, {EF_DEGRADED[1]:g}]',
        )
    if long_axis_mm > 0 and max_displacement_mm > DISPLACEMENT_FAILED * long_axis_mm:
        v.flag(
            FAILED,
            f'a wall point moved {max_displacement_mm:.1f} mm, more than '
            f'{DISPLACEMENT_FAILED:.0%} of '
            f'the {long_axis_mm:.0f} mm long axis',
        )
    worst = max((float(np.max(np.abs(s))) for s in segment_strains if np.size(s)), default=0.0)
    if worst > STRAIN_DEGRADED:
        v.flag(DEGRADED, f'segment strain {worst:.2f} beyond ±{STRAIN_DEGRADED:g}')
    return v


def registration_verdict(slice_reports, wall_thickness_mm=None) -> Verdict:
    """
    How well the ED model is supported by the segmented slices, and whether its wall is a heart's.

    Parameters
    ----------
    slice_reports : sequence
        One per ED slice, with ``view`` (0 SA, 1 LA), ``slice_index``, ``ok`` and ``reason``
        (:class:`mlv_ros.core.registration.SliceReport`).
    wall_thickness_mm : array_like, optional
        The registered model's ED wall thickness samples, mm
        (:meth:`~mlv_ros.core.registration.RegistrationResult.wall_thickness_mm`); checked
        against :data:`WALL_MEAN_DEGRADED_MM`, :data:`WALL_MEAN_FAILED_MM` and
        :data:`WALL_THIN_DEGRADED_MM`. None or empty: not checked.

    Returns
    -------
    Verdict

    """
    v = Verdict()
    wall = np.asarray(wall_thickness_mm if wall_thickness_mm is not None else [], float).ravel()
    wall = wall[np.isfinite(wall)]
    if wall.size:
        mean, thin = float(wall.mean()), float(np.percentile(wall, 5))
        if not WALL_MEAN_FAILED_MM[0] <= mean <= WALL_MEAN_FAILED_MM[1]:
            v.flag(
                FAILED,
                f'ED wall thickness {mean:.1f} mm on average, outside '
                f'[{WALL_MEAN_FAILED_MM[0]:g}, '
                f'{WALL_MEAN_FAILED_MM[1]:g}] mm: not a heart (check pixel spacing and '
                'segmentation)',
            )
        elif not WALL_MEAN_DEGRADED_MM[0] <= mean <= WALL_MEAN_DEGRADED_MM[1]:
            v.flag(
                DEGRADED,
                f'ED wall thickness {mean:.1f} mm on average, outside the adult range '
                f'[{WALL_MEAN_DEGRADED_MM[0]:g}, {WALL_MEAN_DEGRADED_MM[1]:g}] mm '
                '(check pixel spacing and segmentation)',
            )
        if thin < WALL_THIN_DEGRADED_MM:
            v.flag(
                DEGRADED,
                f'ED wall {thin:.1f} mm thin over 5 % of the model (< '
                f'{WALL_THIN_DEGRADED_MM:g} mm): '
                'the model misses part of the wall',
            )
    sa = [r for r in slice_reports if int(r.view) == 0]
    la = [r for r in slice_reports if int(r.view) != 0]
    sa_ok = sum(bool(r.ok) for r in sa)
    if sa and sa_ok / len(sa) < SA_SEGMENTED_DEGRADED:
        v.flag(
            DEGRADED,
            f'{sa_ok} of {len(sa)} SA slices segmented at ED (< {SA_SEGMENTED_DEGRADED:.0%})',
        )
    if la and not any(r.ok for r in la):
        v.flag(
            DEGRADED,
            f'none of the {len(la)} LA views segmented at ED: base and apex from the SA stack '
            'alone',
        )
    elif la and not any(r.ok and getattr(r, 'base_shown', True) for r in la):
        # Every segmented LA horseshoe closed over the atrium: the base is not seen, and the
        # model stops above the most basal SA slice (register._reconstruct).
        v.flag(
            DEGRADED,
            'no LA view shows the base (each horseshoe closes over the atrium): the model ends '
            'half a slice above the most basal SA slice and leaves out the wall above it',
        )
    return v
