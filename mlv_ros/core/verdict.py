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
    """``level`` (OK / DEGRADED / FAILED) and the reasons for anything but OK."""

    level: int = OK
    reasons: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return LEVEL_NAMES[self.level]

    def flag(self, level: int, reason: str) -> None:
        self.level = max(self.level, int(level))
        self.reasons.append(reason)

    def merge(self, other: 'Verdict') -> 'Verdict':
        """Return the worse of both levels, with both sets of reasons."""
        return Verdict(max(self.level, other.level), [*self.reasons, *other.reasons])

    @property
    def text(self) -> str:
        return '; '.join(self.reasons)

    @classmethod
    def from_parts(cls, level: int, text: str) -> 'Verdict':
        return cls(checked_level(level), [r for r in str(text).split('; ') if r])


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


def phase_verdict(
    tracked: int,
    tracked_at_ed: int,
    sa_points: dict,
    residual_mm: float,
    pixel_mm: float,
    rejected: int = 0,
    candidates: int = 0,
    sa_found: dict | None = None,
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
    return v
