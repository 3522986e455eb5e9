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
Per-segment findings a reader uses: peak strain with an uncertainty and a wall-motion class.

For each AHA segment (1–17) the analysis keeps, phase by phase (streaming: the findings of the
cycle so far), the signed peak Err, Ecc, Ell, their values at end-systole (ES: the phase of
smallest cavity volume so far), an uncertainty of each, and a class ``normal``,
``hypokinetic``, ``akinetic``, ``dyskinetic`` or ``indeterminate``.

Uncertainty of a segment's mean strain (one phase, per component k ∈ rr, cc, ll)
-------------------------------------------------------------------------------
The analyzer does not see the tag points (they reach the solver only), so the uncertainty is
built from what it has; :meth:`LVAnalyzer.phase <mlv_ros.core.analysis.metrics.LVAnalyzer.phase>`
computes it::

    σ_k² = FLOOR_k² + (√2 ρ / ℓ_k)² + s_k² / n_eff        (× VERDICT_INFLATION if degraded)

* ``FLOOR_k`` (:data:`UNCERTAINTY_FLOOR`): what we never claim to beat — the spread between
  experienced readers of tagged MRI (Ecc, Ell 0.02; Err 0.05).
* ``ρ``: the solver's RMS in-plane residual at the control points of this phase, mm
  (``ModelState.residual``, the fit residual: tag motion the model did not explain). A
  displacement error ρ at both ends of a length ℓ changes its mean strain by about √2 ρ / ℓ;
  ℓ_rr is the segment's ED wall thickness (5–95 % span of the distance from the axis), ℓ_cc its
  mid-wall arc (mean radius × sector angle), ℓ_ll its ED long-axis extent (5–95 % span).
  Unknown residual counts as 0.
* ``s_k``: the spread (standard deviation) of the per-particle strain inside the segment — a
  segment across a hinge between moving and still wall, or with a noisy motion field, has a less
  certain mean. ``n_eff = count / mls_k``: particles of one MLS neighbourhood share their data,
  so they are not independent samples.
* Support: a segment with fewer than :data:`MIN_SEGMENT_PARTICLES` particles with strain has no
  uncertainty (NaN: not measured). A *failed* phase is not a measurement and is never used. A
  phase whose verdict is *degraded* (rule below) has uncertainties multiplied by
  :data:`VERDICT_INFLATION`.

Degraded phases: the whole heart or the named segments
------------------------------------------------------
A verdict is degraded for the whole heart (too few tag points or SA slices tracked, an end slice
of the stack lost, a large fit residual, many outliers, a physiological bound) or for a region
only: the solver's sector check (:func:`mlv_ros.core.verdict.weakest_sector`) finds a sector
whose ED tag points are nearly all lost and names its AHA segments; the model carries that
sector with its neighbours, so its strain there is theirs, not a measurement, while the rest of
the heart is as well supported as in an ok phase. The metrics carry the segments a degraded
verdict is confined to (``PhaseMetrics.degraded_segments``, from ``ModelState.degraded_segments``;
empty when any reason, the analyzer's own included, concerns the whole heart):

* degraded, no segments named (whole heart): every segment's uncertainty × VERDICT_INFLATION;
* degraded, segments named (sector only): only those segments' uncertainties × VERDICT_INFLATION,
  and when the phase is the findings' ES they are *unsupported* (:attr:`Findings.unsupported`):
  left out of the heart's references and classed ``indeterminate`` whatever their strain (the
  model carried them; no class is claimed for them), the others keep their class.

What it captures: how much model surface covers the segment, how well the model fitted the tags
at that phase and how uniform the segment's motion is. What it does not: the tag-point density
in the segment itself and bias of the motion field (a region smoothed into line with its
neighbours by the solver's penalties looks certain and normal); the tag evidence below (its σ
from the segment's own tracks: their number and localisation noise) is what answers that.

Tag evidence (at ES)
--------------------
The solver reads each segment's own SA tag tracks, with no model
(:mod:`mlv_ros.core.analysis.tag_strain`: ``Ecc_tag`` and ``σ_tag`` per segment, carried by
``ModelState.tag_ecc`` and ``PhaseMetrics.segment_tag_ecc``). The model's penalties carry a narrow
region along with its neighbours (a 60° akinetic sector: the model's f 0.35–0.6, its tags' Ecc
near 0), so where the two disagree the data win:

* the tags' reference ``Ecc_ref_tag`` = median ``Ecc_tag`` of the segments 1–16 with tag
  evidence (at least 3, the unsupported left out; at most ``−REF_MIN['ecc']``) — the tags' own
  2-D strain against the tags' own median, so the tags' bias against the model's 3-D strain
  cancels;
* ``f_tag = Ecc_tag / (P_cc Ecc_ref_tag)`` and ``σ_f_tag = σ_tag / |P_cc Ecc_ref_tag|`` (the
  apex cap has no tag Ecc);
* a segment the model classes ``normal`` or ``hypokinetic`` whose tags read ``f_tag`` below the
  akinetic bound (0.35) takes the tags' class: ``indeterminate`` when ``σ_f_tag > MAX_SIGMA_F``
  (the data disagree with the model but cannot say how much; stretching or not: a slipped
  track's Ecc +0.78 ± 0.36 is no finding), else ``akinetic`` / ``dyskinetic`` by the same bounds
  (dyskinetic also when ``Ecc_tag > Z σ_tag``, stretching). Never ``normal``;
* a segment the model classes ``akinetic`` whose tags read it moving the wrong way, as surely
  (``σ_f_tag ≤ MAX_SIGMA_F`` and ``f_tag < −0.2`` or ``Ecc_tag > Z σ_tag``), is ``dyskinetic``:
  the model reads a narrow bulging region as still (its neighbours pull it in), its own tags
  read the stretch (7308's apical ring: model f −0.05…−0.14, tags −0.27…−0.42 ± 0.24–0.27,
  truth dyskinetic). Both listed in :attr:`Findings.from_tags`.
* Nothing else changes: a segment the model finds abnormal keeps its finding (the tags are not
  used to clear one: where tracks are few the tags see less than the model), and segments
  without tag evidence (too few tracked edges: an apex cap, a sector whose tracks are lost) keep
  the model's.

Classification (at ES)
----------------------
Relative to the heart's own function, so it holds for normal, dilated and hypertrophic hearts:

* References: ``Ecc_ref`` = median ES Ecc of the supported segments 1–16 (at most
  ``−REF_MIN['ecc']``), ``Err_ref`` = their median ES Err (at least ``REF_MIN['err']``): a heart
  with several abnormal segments still has a normal median while fewer than half are abnormal.
* Expected share of the reference per segment, :data:`NORMAL_PATTERN`: the apical ring's wall
  tapers and shortens less. The apex cap (17) is not classified (always ``indeterminate``, said
  in :attr:`Findings.notes`): its strain is taken in the wall-normal frame
  (:func:`mlv_ros.core.analysis.frame.wall_normal_frame`: Err = thickening across the cap, Ecc
  and Ell in the wall), but no class is validated there: the legacy simulator cap (the presets,
  studies drawn before session 19) shortens its solid apex tip along the axis with the wall
  and widens it, so in that frame its normal caps thin (Err −0.04…−0.08) and stretch in the
  wall (Ecc +0.045…+0.08); our cap's Err followed the apical ring's (over 23 graph runs r 0.74
  with our ring's, 0.05 with the truth's cap: docs/benchmarks.md, "Abnormal segments one by
  one"). Against a cap that thickens and shortens as a heart's does (random protocols'
  ``motion.apex_thickening``) the solver does not yet follow it (the normal preset with τ 0.3:
  cap median error 0.34 → 1.40 mm, cap Err +0.12 against the truth's +0.24: docs/benchmarks.md,
  "The simulator's apex cap moves like a heart's"), so no class is claimed there yet.
* Function index ``f`` = inverse-variance weighted mean of ``Ecc / (P_cc Ecc_ref)`` and
  ``Err / (P_rr Err_ref)`` (1 = as the rest of the heart, 0 = no motion, < 0 = moves the wrong
  way), with its uncertainty ``σ_f``. Classes on ``f`` (:data:`CLASS_BOUNDS`): normal
  ``f ≥ 0.6``, hypokinetic ``0.35 ≤ f < 0.6``, akinetic ``−0.2 ≤ f < 0.35``, dyskinetic
  ``f < −0.2``; and dyskinetic whenever the wall stretches beyond its uncertainty at ES:
  ``Err < −Z σ_rr`` (thinning) or, segments 1–16, ``Ecc > Z σ_cc`` (Z = :data:`STRETCH_Z`).
* ``indeterminate`` when the segment has no support or is unsupported at ES (above), no
  systolic phase has been seen yet, or ``σ_f > MAX_SIGMA_F`` (0.33: beyond it a normal segment
  could be read akinetic within 2σ). Never a confident wrong class for lack of data.
* Absolute akinesis (:func:`absolute_akinetic`): a segment 1–16 left indeterminate by σ_f is
  still ``akinetic`` when even 2σ above its reading it moves less than the absolute bounds
  :data:`AKINETIC_ABS` (Err 0.10: < 10 % thickening, the echo criterion; |Ecc| 0.05: 2.5
  reader spreads): e.g. the still segments of a weak heart.
* Possibly akinetic (:func:`possibly_akinetic`, :attr:`Findings.possibly_akinetic`): a
  segment 1–16 classed ``hypokinetic`` or ``indeterminate`` (not unsupported) whose model
  reading is below the normal bound (``f < 0.6``) and within one σ of akinesis
  (``f − σ_f < 0.35``) is named in the notes as "hypokinetic or akinetic", the echo reader's
  "hypokinetic to akinetic" when a segment's thickening is between the two (ASE/EACVI wall-motion
  scoring, Lang et al. 2015): no class is claimed (the class stays), but the reader is told where
  akinesis is as likely as the class read. It names what the 2σ rules leave out: a weak heart's
  still segments, whose reader-spread floors keep σ_f near :data:`MAX_SIGMA_F`, and a narrow
  still sector the model carries part-way with its neighbours (f 0.4–0.5 ± 0.15).
* Heart-level finding (:func:`global_function`): ``globally hypokinetic`` when the heart's
  references are within about three reader spreads of no motion (``Σ (ref_k / FLOOR_k)² <
  1 / MAX_SIGMA_F²``): its segments cannot be told apart relative to it, so they are
  indeterminate unless the absolute bounds or the stretch rule decide, and the findings say so
  (:attr:`Findings.notes`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math

from mlv_ros.core.analysis.strain import AHA_SEGMENT_NAMES
from mlv_ros.core.verdict import DEGRADED, FAILED
import numpy as np

COMPONENTS = ('err', 'ecc', 'ell')
#: Smallest uncertainty of a segment mean, per component: the spread between experienced readers
#: of tagged MRI; we do not claim to measure better than they read.
UNCERTAINTY_FLOOR = {'err': 0.05, 'ecc': 0.02, 'ell': 0.02}
#: Fewer particles with strain than this in a segment: not measured (two MLS neighbourhoods).
MIN_SEGMENT_PARTICLES = 24
#: A degraded phase (the solver's data support or physiological bounds) counts as half as sure:
#: everywhere, or in the segments its verdict is confined to (a sector the data do not support).
VERDICT_INFLATION = 2.0
#: Smallest magnitude of the heart's reference Ecc / Err: below it the heart barely contracts
#: anywhere and "relative to the rest of the heart" would divide by noise.
REF_MIN = {'ecc': 0.03, 'err': 0.05}
#: Expected share of the heart's median Err / Ecc a normal segment reaches (index = segment − 1);
#: None = the component is not used for that segment. From the simulator's normal, dilated and
#: hypertrophic hearts' truth (apical ring 0.6–0.85 of the median in Err, 0.15–0.8 in Ecc; cap Err
#: 0.17–0.24 of the median, cap Ecc of either sign: the cylindrical frame degenerates at the tip).
NORMAL_PATTERN = {
    'err': (1.0,) * 12 + (0.75,) * 4 + (None,),
    'ecc': (1.0,) * 12 + (0.6,) * 4 + (None,),
}
#: Why the apex cap (17) has no class (:attr:`Findings.notes`).
CAP_NOTE = (
    'apex cap (17): strain in the wall-normal frame (Err = thickening across the cap); no class '
    "is claimed there (not validated against a truth whose cap moves as a heart's does)"
)
#: Classes on the function index f (share of the heart's normal function the segment keeps), the
#: first whose lower bound f reaches. Looser than the truth's contraction bounds (0.75 / 0.2 /
#: −0.2, :data:`mlv_ros.core.sim.regional.CLASS_THRESHOLDS`): normal segments vary 0.55–1.45
#: around the median in the truth's own Err, and a segment's mean takes in the blend toward its
#: neighbours, so an akinetic segment's mean keeps up to ~0.35 of normal (truth: 95 % below 0.53,
#: hypokinetic 95 % above 0.38; on the truth's strain the 0.35 bound finds 92 % of akinetic or
#: dyskinetic segments at 96 % specificity).
CLASS_BOUNDS = (
    ('normal', 0.6),
    ('hypokinetic', 0.35),
    ('akinetic', -0.2),
    ('dyskinetic', -math.inf),
)
CLASSES = tuple(n for n, _ in CLASS_BOUNDS) + ('indeterminate',)
#: "Beyond the uncertainty": stretching by more than this many σ makes a segment dyskinetic.
STRETCH_Z = 2.0
#: The per-segment findings arrays of MotionMetrics (17 each or empty; NaN = not measured).
FINDING_ARRAY_FIELDS = tuple(
    f'finding_{w}_{c}{u}' for w in ('peak', 'es') for u in ('', '_unc') for c in COMPONENTS
) + ('finding_function_index', 'finding_function_unc')
#: Wall-motion class codes of MotionMetrics.segment_class (index in :data:`CLASSES`).
CLASS_CODES = {name: k for k, name in enumerate(CLASSES)}
#: Largest σ_f a class is given with: a normal segment (f ≈ 1) is then called akinetic (f < 0.35)
#: only when read 2σ low.
MAX_SIGMA_F = 0.33
#: Absolute akinetic bounds (globally hypokinetic hearts): ES Err below 0.10 is the echo
#: criterion of akinesis, wall thickening below 10 % (ASE/EACVI chamber quantification, Lang et
#: al. 2015; ½(1.1² − 1) = 0.105 in Green–Lagrange); |Ecc| below 0.05 is within 2.5 reader
#: spreads (:data:`UNCERTAINTY_FLOOR`) of no shortening. Not fitted to any study.
AKINETIC_ABS = {'err': 0.10, 'ecc': 0.05}
#: Heart-level findings (:attr:`Findings.global_function`).
GLOBAL_FUNCTIONS = ('measured', 'globally hypokinetic')


def segment_uncertainty(
    values, segments, count, floor: float, length_mm, residual_mm: float = 0.0, mls_k: int = 12
) -> np.ndarray:
    """
    Uncertainty of each segment's mean strain at one phase (module docstring formula).

    Parameters
    ----------
    values : array_like, shape (N,)
        Per-particle strain component (NaN where not estimated).
    segments : array_like of int, shape (N,)
        AHA segment 1–17 per particle.
    count : array_like of int, shape (17,)
        Particles with a finite value per segment.
    floor : float
        :data:`UNCERTAINTY_FLOOR` of the component.
    length_mm : array_like, shape (17,)
        The length ℓ the component's strain is measured over, mm, per segment.
    residual_mm : float
        The solver's RMS residual at the control points for this phase, mm (0 if unknown).
    mls_k : int
        Neighbours of the MLS strain estimate (particles per independent sample).

    Returns
    -------
    ndarray, shape (17,)
        σ (dimensionless); NaN where the segment has fewer than :data:`MIN_SEGMENT_PARTICLES`.

    """
    v = np.asarray(values, dtype=np.float64)
    s = np.asarray(segments)
    cnt = np.asarray(count, dtype=np.float64)
    ok = np.isfinite(v)
    tot = np.bincount(s[ok] - 1, weights=v[ok], minlength=17)
    tot2 = np.bincount(s[ok] - 1, weights=v[ok] ** 2, minlength=17)
    mean = tot / np.maximum(cnt, 1)
    spread2 = np.maximum(tot2 / np.maximum(cnt, 1) - mean**2, 0.0)
    n_eff = np.maximum(cnt / max(int(mls_k), 1), 1.0)
    ell = np.maximum(np.asarray(length_mm, dtype=np.float64), 1e-3)
    sig = np.sqrt(floor**2 + 2.0 * (float(residual_mm) / ell) ** 2 + spread2 / n_eff)
    return np.where(cnt >= MIN_SEGMENT_PARTICLES, sig, np.nan)


def segment_lengths(rho, axial, segments) -> dict:
    """
    ED lengths the segment mean strains are measured over (for :func:`segment_uncertainty`).

    Parameters
    ----------
    rho, axial : array_like, shape (N,)
        ED distance from the long axis and along it, mm.
    segments : array_like of int, shape (N,)
        AHA segment of each particle, 1…17 (other values are ignored).

    Returns
    -------
    dict
        ``err``: wall thickness (5–95 % span of ρ), ``ecc``: mid-wall arc (mean ρ × the sector's
        angle: 60° basal/mid, 90° apical, 360° cap), ``ell``: long-axis extent (5–95 % span of
        the axial position); each shape (17,), mm (NaN for an empty segment).

        The apex cap's (17) ``err`` and ``ell`` lengths are swapped: its strain is taken in the
        wall-normal frame (:func:`~mlv_ros.core.analysis.frame.wall_normal_frame`), where the
        wall across the axis is as thick as its axial span and its meridian runs outward.

    """
    rho = np.asarray(rho, dtype=np.float64)
    axial = np.asarray(axial, dtype=np.float64)
    s = np.asarray(segments)
    angle = np.radians([60.0] * 12 + [90.0] * 4 + [360.0])
    out = {k: np.full(17, np.nan) for k in COMPONENTS}
    for k in range(17):
        m = s == k + 1
        if m.sum() < 2:
            continue
        out['err'][k] = float(np.subtract(*np.percentile(rho[m], [95, 5])))
        out['ecc'][k] = float(np.mean(rho[m]) * angle[k])
        out['ell'][k] = float(np.subtract(*np.percentile(axial[m], [95, 5])))
    out['err'][16], out['ell'][16] = out['ell'][16], out['err'][16]
    return out


def _signed_peak_update(peak, peak_unc, v, unc):
    """Keep the value of largest magnitude (sign kept) and its uncertainty, elementwise."""
    better = np.isfinite(v) & (~np.isfinite(peak) | (np.abs(v) > np.abs(peak)))
    return np.where(better, v, peak), np.where(better, unc, peak_unc)


def global_function(ref: dict) -> str | None:
    """
    Return the heart-level finding from the heart's references (module docstring).

    Parameters
    ----------
    ref : dict
        ``ecc``, ``err``: the heart's ES references (:func:`classify`; None = not available).

    Returns
    -------
    str or None
        ``'globally hypokinetic'`` when the references, in reader spreads
        (:data:`UNCERTAINTY_FLOOR`), are too small for a normal segment's f to be told from 0
        within :data:`MAX_SIGMA_F` (``Σ (ref_k / floor_k)² < 1 / MAX_SIGMA_F²``: the heart's own
        motion is within about three reader spreads of none); ``'measured'`` otherwise; None
        without references.

    """
    have = {c: v for c, v in ref.items() if c in UNCERTAINTY_FLOOR and v is not None}
    if not have:
        return None
    snr2 = sum((v / UNCERTAINTY_FLOOR[c]) ** 2 for c, v in have.items())
    return GLOBAL_FUNCTIONS[1] if snr2 < 1.0 / MAX_SIGMA_F**2 else GLOBAL_FUNCTIONS[0]


def absolute_akinetic(es: dict, unc: dict) -> np.ndarray:
    """
    Return which segments 1–16 are akinetic against absolute bounds, beyond their uncertainty.

    The share of each bound a segment reaches, ``r_k = |E_k| / AKINETIC_ABS[k]`` for Ecc and
    Err, is combined inverse-variance weighted (as ``f``) into ``r ± σ_r``; akinetic when
    ``r + STRETCH_Z σ_r ≤ 1``: even 2σ above its reading the segment moves less than the
    bounds. The cap (17) is never (no class claimed there).

    Parameters
    ----------
    es, unc : dict
        ``err``, ``ecc``: ES segment means and their uncertainties, shape (17,) (NaN = none).

    Returns
    -------
    ndarray of bool, shape (17,)

    """
    num, wsum = np.zeros(17), np.zeros(17)
    for c in ('ecc', 'err'):
        ok = np.isfinite(es[c]) & np.isfinite(unc[c]) & (unc[c] > 0)
        r = np.where(ok, np.abs(es[c]) / AKINETIC_ABS[c], 0.0)
        w = np.where(ok, (AKINETIC_ABS[c] / np.where(ok, unc[c], 1.0)) ** 2, 0.0)
        num += w * r
        wsum += w
    out = np.zeros(17, dtype=bool)
    have = wsum > 0
    out[have] = num[have] / wsum[have] + STRETCH_Z / np.sqrt(wsum[have]) <= 1.0
    out[16] = False
    return out


def tag_function(tag_ecc, tag_unc, unsupported=()) -> tuple[np.ndarray, np.ndarray, float]:
    """
    Return the tags' function index per segment, its uncertainty and the tags' reference.

    Module docstring, "Tag evidence".

    Parameters
    ----------
    tag_ecc, tag_unc : array_like, shape (17,)
        The segments' tag Ecc and its uncertainty (NaN: no evidence).
    unsupported : sequence of int, optional
        AHA segments (1–17) left out of the reference.

    Returns
    -------
    f_tag, f_tag_unc : ndarray, shape (17,)
        NaN where the segment has no tag evidence, for the apex cap, or for every segment when
        fewer than 3 of segments 1–16 have evidence.
    ref : float
        The tags' reference Ecc (NaN when not available).

    """
    e = np.asarray(tag_ecc, dtype=np.float64).reshape(-1)
    u = np.asarray(tag_unc, dtype=np.float64).reshape(-1)
    nan = np.full(17, np.nan)
    if e.size != 17 or u.size != 17:
        return nan, nan.copy(), math.nan
    have = np.isfinite(e) & np.isfinite(u)
    carried = np.zeros(17, dtype=bool)
    carried[np.asarray(unsupported, dtype=np.int64).reshape(-1) - 1] = True
    remote = e[:16][(have & ~carried)[:16]]
    if remote.size < 3:
        return nan, nan.copy(), math.nan
    ref = -max(-float(np.median(remote)), REF_MIN['ecc'])
    p = np.array([np.nan if x is None else x for x in NORMAL_PATTERN['ecc']])
    scale = p * ref
    ok = have & np.isfinite(scale)
    f = np.where(ok, e / np.where(ok, scale, 1.0), np.nan)
    fu = np.where(ok, u / np.abs(np.where(ok, scale, 1.0)), np.nan)
    return f, fu, ref


def _class_of(f: float) -> str:
    """Return the :data:`CLASS_BOUNDS` class of a function index."""
    return next(name for name, bound in CLASS_BOUNDS if f >= bound)


def tag_override(classes, tag_ecc, tag_unc, unsupported=()) -> tuple[np.ndarray, list, tuple]:
    """
    Return the classes after the tag evidence (module docstring, "Tag evidence").

    Parameters
    ----------
    classes : array_like of str, shape (17,)
        The model's classes (:func:`classify`).
    tag_ecc, tag_unc : array_like, shape (17,) or (0,)
        The segments' tag Ecc and its uncertainty at ES (NaN or empty: no evidence).
    unsupported : sequence of int, optional
        AHA segments (1–17) the ES verdict names as carried (left as they are).

    Returns
    -------
    classes : ndarray of str, shape (17,)
        The classes, with the disagreeing segments' changed.
    from_tags : list of int
        The segments (1–17) whose class came from the tags.
    tag : tuple
        ``(f_tag, f_tag_unc, ref)`` of :func:`tag_function`.

    """
    out = np.array(classes, dtype=object)
    f, fu, ref = tag_function(tag_ecc, tag_unc, unsupported)
    if not math.isfinite(ref):
        return out, [], (f, fu, ref)
    e = np.asarray(tag_ecc, dtype=np.float64)
    u = np.asarray(tag_unc, dtype=np.float64)
    bounds = dict(CLASS_BOUNDS)
    carried = {int(k) for k in np.asarray(unsupported).reshape(-1)}
    from_tags = []
    for k in range(17):
        if k + 1 in carried or not np.isfinite(f[k]):
            continue
        # A reading the tags cannot make sure of sets no class of its own: as sure as the
        # model's classes must be (σ_f_tag ≤ MAX_SIGMA_F), stretching included (a slipped track
        # reads Ecc +0.78 ± 0.36: "stretching" at 2σ, 12× the σ_f a class is given with).
        sure = fu[k] <= MAX_SIGMA_F
        wrong_way = sure and (f[k] < bounds['akinetic'] or e[k] > STRETCH_Z * u[k])
        if out[k] == 'akinetic':
            if wrong_way:  # still to the model, moving the wrong way to its own tags
                out[k] = 'dyskinetic'
                from_tags.append(k + 1)
            continue
        if out[k] not in ('normal', 'hypokinetic') or not f[k] < bounds['hypokinetic']:
            continue
        if not sure:
            cls = 'indeterminate'
        elif e[k] > STRETCH_Z * u[k]:
            cls = 'dyskinetic'  # stretching beyond its own uncertainty
        else:
            cls = _class_of(f[k])
        out[k] = cls
        from_tags.append(k + 1)
    return out, from_tags, (f, fu, ref)


def classify(
    es: dict, unc: dict, unsupported=()
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """
    Classes of the 17 segments from their ES strain and its uncertainty (module docstring).

    Parameters
    ----------
    es : dict
        ``err``, ``ecc``: ES segment means, shape (17,) each (NaN = not measured).
    unc : dict
        ``err``, ``ecc``: their uncertainties, shape (17,) (NaN = no support).
    unsupported : sequence of int, optional
        AHA segments (1–17) the ES phase's tag data do not support (the solver's sector): left
        out of the references and classed ``indeterminate``.

    Returns
    -------
    classes : ndarray of str, shape (17,)
        :data:`CLASSES` names.
    f, f_unc : ndarray, shape (17,)
        Function index and its uncertainty (NaN where not computable).
    ref : dict
        ``ecc``, ``err``: the heart's references (None when no segment 1–16 is supported).

    """
    classes = np.full(17, 'indeterminate', dtype=object)
    f = np.full(17, np.nan)
    f_unc = np.full(17, np.nan)
    carried = np.zeros(17, dtype=bool)
    carried[np.asarray(unsupported, dtype=np.int64).reshape(-1) - 1] = True
    sup = {c: np.isfinite(es[c]) & np.isfinite(unc[c]) for c in ('err', 'ecc')}
    ref = {}
    for c, sign in (('ecc', -1.0), ('err', 1.0)):
        remote = es[c][:16][(sup[c] & ~carried)[:16]]
        ref[c] = (
            None if remote.size < 3 else sign * max(sign * float(np.median(remote)), REF_MIN[c])
        )
    if ref['ecc'] is None and ref['err'] is None:
        return classes, f, f_unc, ref
    num = np.zeros(17)
    wsum = np.zeros(17)
    for c in ('ecc', 'err'):
        if ref[c] is None:
            continue
        p = np.array([np.nan if x is None else x for x in NORMAL_PATTERN[c]])
        scale = p * ref[c]
        use = sup[c] & np.isfinite(scale)
        fi = np.where(use, es[c] / np.where(use, scale, 1.0), 0.0)
        si = np.where(use, unc[c] / np.abs(np.where(use, scale, 1.0)), np.inf)
        w = np.where(use, 1.0 / si**2, 0.0)
        num += w * fi
        wsum += w
    have = wsum > 0
    f[have] = num[have] / wsum[have]
    f_unc[have] = 1.0 / np.sqrt(wsum[have])
    for name, bound in reversed(CLASS_BOUNDS):
        classes[have & (f >= bound)] = name
    stretch = np.zeros(17, dtype=bool)
    with np.errstate(invalid='ignore'):
        stretch |= sup['err'] & (es['err'] < -STRETCH_Z * unc['err'])
        stretch[:16] |= (sup['ecc'] & (es['ecc'] > STRETCH_Z * unc['ecc']))[:16]
    classes[have & (f_unc > MAX_SIGMA_F)] = 'indeterminate'
    # Too uncertain against the heart's own function (e.g. a globally hypokinetic heart): the
    # absolute bounds still decide akinesis.
    classes[have & (classes == 'indeterminate') & absolute_akinetic(es, unc)] = 'akinetic'
    classes[stretch] = 'dyskinetic'  # beyond its own uncertainty: a confident call
    classes[carried] = 'indeterminate'  # the model carried them: no class is claimed
    return classes, f, f_unc, ref


@dataclass
class Findings:
    """
    Per-segment findings of the cycle so far (17 entries each, AHA order 1…17).

    Attributes
    ----------
    phases_used : list of int
        Phases with strain that entered (failed phases never do).
    es_phase : int or None
        Phase of smallest cavity volume among them, excluding ED (None: no systolic phase yet).
    peak : dict of ndarray
        ``err``, ``ecc``, ``ell``: signed peak over the phases used (NaN: never measured).
    peak_unc : dict of ndarray
        Uncertainty at the phase of each peak.
    es, es_unc : dict of ndarray
        Values and uncertainties at ``es_phase``.
    function_index, function_unc : ndarray, shape (17,)
        ``f`` and ``σ_f`` of the classification (NaN where not computable).
    classes : list of str
        :data:`CLASSES` names.
    reference : dict
        The heart's ``ecc`` / ``err`` references at ES (None when not available).
    unsupported : list of int
        AHA segments (1–17) the ``es_phase``'s tag data do not support (its verdict degraded for
        their sector only): ``indeterminate``, whatever their strain.
    global_function : str or None
        The heart-level finding (:func:`global_function`): ``'globally hypokinetic'``,
        ``'measured'`` or None (no ES yet).
    notes : list of str
        Sentences for the reader: why segments are indeterminate or classed on absolute bounds.
    tag_ecc, tag_ecc_unc : ndarray, shape (17,) or (0,)
        The tag tracks' own Ecc per segment at ``es_phase`` and its uncertainty (empty: none).
    tag_function_index, tag_function_unc : ndarray, shape (17,)
        ``f_tag`` and ``σ_f_tag`` (NaN where not computable).
    from_tags : list of int
        Segments (1–17) whose class is the tags' (module docstring, "Tag evidence").
    possibly_akinetic : list of int
        Segments (1–16) classed hypokinetic or indeterminate whose reading is within 1σ of
        akinesis (:func:`possibly_akinetic`): said in :attr:`notes`, their class unchanged.

    """

    phases_used: list = field(default_factory=list)
    es_phase: int | None = None
    peak: dict = field(default_factory=dict)
    peak_unc: dict = field(default_factory=dict)
    es: dict = field(default_factory=dict)
    es_unc: dict = field(default_factory=dict)
    function_index: np.ndarray = field(default_factory=lambda: np.full(17, np.nan))
    function_unc: np.ndarray = field(default_factory=lambda: np.full(17, np.nan))
    classes: list = field(default_factory=lambda: ['indeterminate'] * 17)
    reference: dict = field(default_factory=dict)
    unsupported: list = field(default_factory=list)
    global_function: str | None = None
    notes: list = field(default_factory=list)
    tag_ecc: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tag_ecc_unc: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tag_function_index: np.ndarray = field(default_factory=lambda: np.full(17, np.nan))
    tag_function_unc: np.ndarray = field(default_factory=lambda: np.full(17, np.nan))
    from_tags: list = field(default_factory=list)
    possibly_akinetic: list = field(default_factory=list)

    def abnormal(self, kinds=('akinetic', 'dyskinetic')) -> list[int]:
        """Segment numbers (1–17) classed as one of ``kinds``."""
        return [k + 1 for k, c in enumerate(self.classes) if c in kinds]

    def message_fields(self) -> dict:
        """
        Return the MotionMetrics findings fields.

        ``findings_es_phase`` (−1: none yet), the :data:`FINDING_ARRAY_FIELDS` (17 floats each,
        NaN = not measured; empty before any phase with strain) and ``segment_class``
        (17 :data:`CLASS_CODES`).
        """
        out = {'findings_es_phase': -1 if self.es_phase is None else int(self.es_phase)}
        if not self.phases_used:
            out.update({k: np.zeros(0) for k in FINDING_ARRAY_FIELDS})
            out['segment_class'] = np.zeros(0, dtype=np.int64)
            return out
        nan = np.full(17, np.nan)
        for w, d, du in (('peak', self.peak, self.peak_unc), ('es', self.es, self.es_unc)):
            for c in COMPONENTS:
                out[f'finding_{w}_{c}'] = np.asarray(d.get(c, nan), dtype=np.float64)
                out[f'finding_{w}_{c}_unc'] = np.asarray(du.get(c, nan), dtype=np.float64)
        out['finding_function_index'] = np.asarray(self.function_index, dtype=np.float64)
        out['finding_function_unc'] = np.asarray(self.function_unc, dtype=np.float64)
        out['segment_class'] = np.array([CLASS_CODES[c] for c in self.classes], dtype=np.int64)
        return out

    def to_dict(self) -> dict:
        """
        Return a JSON-ready dict: per-segment rows plus the thresholds used.

        NaN stays NaN: write it with :func:`mlv_ros.core.report.summary.write_summary_json`, which
        makes it null.
        """
        rows = []
        for k in range(17):
            row = {'segment': k + 1, 'name': AHA_SEGMENT_NAMES[k], 'class': self.classes[k]}
            for c in COMPONENTS:
                for key, d in (
                    (f'peak_{c}', self.peak),
                    (f'peak_{c}_unc', self.peak_unc),
                    (f'es_{c}', self.es),
                    (f'es_{c}_unc', self.es_unc),
                ):
                    row[key] = float(d[c][k]) if c in d else math.nan
            row['function_index'] = float(self.function_index[k])
            row['function_unc'] = float(self.function_unc[k])
            tag = self.tag_ecc.size == 17
            row['tag_ecc'] = float(self.tag_ecc[k]) if tag else math.nan
            row['tag_ecc_unc'] = float(self.tag_ecc_unc[k]) if tag else math.nan
            row['tag_function_index'] = float(self.tag_function_index[k])
            row['tag_function_unc'] = float(self.tag_function_unc[k])
            row['class_from_tags'] = k + 1 in self.from_tags
            rows.append(row)
        return {
            'es_phase': self.es_phase,
            'phases_used': list(self.phases_used),
            'reference': dict(self.reference),
            'segments': rows,
            'counts': {c: self.classes.count(c) for c in CLASSES},
            'unsupported': list(self.unsupported),
            'global_function': self.global_function,
            'notes': list(self.notes),
            'from_tags': list(self.from_tags),
            'possibly_akinetic': list(self.possibly_akinetic),
            'thresholds': {
                'class_bounds': {
                    n: (None if not math.isfinite(b) else b) for n, b in CLASS_BOUNDS
                },
                'stretch_z': STRETCH_Z,
                'max_sigma_f': MAX_SIGMA_F,
                'akinetic_absolute': dict(AKINETIC_ABS),
                'uncertainty_floor': dict(UNCERTAINTY_FLOOR),
                'min_segment_particles': MIN_SEGMENT_PARTICLES,
                'verdict_inflation': VERDICT_INFLATION,
                'reference_min': dict(REF_MIN),
                'normal_pattern': {c: list(v) for c, v in NORMAL_PATTERN.items()},
            },
        }


class SegmentFindings:
    """
    Streaming per-segment findings: feed each phase's metrics, read :attr:`findings`.

    Examples
    --------
    >>> sf = SegmentFindings()                                  # doctest: +SKIP
    >>> for x in positions: sf.update(analyzer.phase(x, ...))
    >>> sf.findings.classes[16]

    """

    def __init__(self):
        nan = np.full(17, np.nan)
        self._peak = {c: nan.copy() for c in COMPONENTS}
        self._peak_unc = {c: nan.copy() for c in COMPONENTS}
        self._es = None  # (volume, phase, values, unc)
        self._used: list[int] = []
        self.findings = Findings(peak=dict(self._peak), peak_unc=dict(self._peak_unc))

    def update(self, metrics) -> Findings:
        """
        Take one phase and return the findings of the cycle so far.

        ``metrics`` is a :class:`~mlv_ros.core.analysis.metrics.PhaseMetrics`. A failed phase or
        one without strain changes nothing; without the uncertainty arrays (e.g. metrics recorded
        before they existed) each segment gets the support-only uncertainty: the floor, NaN below
        :data:`MIN_SEGMENT_PARTICLES` particles (unknown count: supported). A degraded phase
        inflates the uncertainty of its ``degraded_segments``, or of every segment when it names
        none (module docstring).
        """
        level = int(getattr(metrics, 'verdict', 0))
        if level >= FAILED or not metrics.has_strain:
            return self.findings
        count = np.asarray(metrics.segment_count)
        supported = count >= MIN_SEGMENT_PARTICLES if count.size == 17 else np.ones(17, dtype=bool)
        carried = sorted(int(k) for k in getattr(metrics, 'degraded_segments', ()))
        if level < DEGRADED:
            carried = []
        less_sure = np.full(17, level >= DEGRADED)
        if carried:
            less_sure[:] = False
            less_sure[np.array(carried) - 1] = True
        vals, unc = {}, {}
        for c in COMPONENTS:
            v = np.asarray(getattr(metrics, f'segment_{c}'), dtype=np.float64)
            u = np.asarray(getattr(metrics, f'segment_{c}_unc', np.zeros(0)), dtype=np.float64)
            if u.size != 17:
                u = np.full(17, UNCERTAINTY_FLOOR[c])
            u = np.where(supported, u, np.nan)
            u = np.where(less_sure, u * VERDICT_INFLATION, u)
            vals[c] = np.where(np.isfinite(u), v, np.nan)
            unc[c] = u
            self._peak[c], self._peak_unc[c] = _signed_peak_update(
                self._peak[c], self._peak_unc[c], vals[c], u
            )
        idx = int(metrics.phase_index)
        self._used.append(idx)
        vol = float(metrics.cavity_volume_ml)
        if idx != 0 and (self._es is None or vol < self._es[0]):
            tag = tuple(
                np.asarray(getattr(metrics, n, np.zeros(0)), dtype=np.float64).reshape(-1)
                for n in ('segment_tag_ecc', 'segment_tag_ecc_unc')
            )
            self._es = (vol, idx, vals, unc, carried, tag)
        f = Findings(
            phases_used=sorted(set(self._used)),
            peak={c: v.copy() for c, v in self._peak.items()},
            peak_unc={c: v.copy() for c, v in self._peak_unc.items()},
        )
        if self._es is not None:
            _, f.es_phase, f.es, f.es_unc, f.unsupported, (f.tag_ecc, f.tag_ecc_unc) = self._es
            f.unsupported = list(f.unsupported)
            cls, f.function_index, f.function_unc, f.reference = classify(
                f.es, f.es_unc, f.unsupported
            )
            cls, f.from_tags, (f.tag_function_index, f.tag_function_unc, _) = tag_override(
                cls, f.tag_ecc, f.tag_ecc_unc, f.unsupported
            )
            f.classes = [str(c) for c in cls]
            f.possibly_akinetic = possibly_akinetic(
                f.classes, f.function_index, f.function_unc, f.unsupported
            )
            f.global_function = global_function(f.reference)
            f.notes = findings_notes(f)
        self.findings = f
        return f


def possibly_akinetic(classes, f, f_unc, unsupported=()) -> list[int]:
    """
    Return the segments whose reading is as compatible with akinesis as with their class.

    Module docstring, "Possibly akinetic": segments 1–16 classed ``hypokinetic`` or
    ``indeterminate``, not unsupported, with ``f`` below the normal bound and ``f − σ_f`` below
    the akinetic bound (:data:`CLASS_BOUNDS`). The tags' own ``f_tag`` is not used: where the tags
    read akinesis beyond their uncertainty they already set the class (:func:`tag_override`).

    Parameters
    ----------
    classes : sequence of str, shape (17,)
        The segments' classes.
    f, f_unc : array_like, shape (17,)
        The model's function index and its uncertainty (NaN: not computable).
    unsupported : sequence of int, optional
        AHA segments (1–17) carried by the model at ES (never named: not a measurement).

    Returns
    -------
    list of int
        AHA segment numbers, ascending.

    """
    bounds = dict(CLASS_BOUNDS)
    fi = np.asarray(f, dtype=np.float64).reshape(-1)
    fu = np.asarray(f_unc, dtype=np.float64).reshape(-1)
    if len(classes) != 17 or fi.size != 17 or fu.size != 17:
        raise ValueError(
            f'classes, f and f_unc must have 17 entries, got {len(classes)}, {fi.size}, {fu.size}'
        )
    carried = {int(k) for k in np.asarray(unsupported, dtype=np.int64).reshape(-1)}
    with np.errstate(invalid='ignore'):
        near = (fi < bounds['normal']) & (fi - fu < bounds['hypokinetic'])
    return [
        k + 1
        for k in range(16)
        if classes[k] in ('hypokinetic', 'indeterminate') and k + 1 not in carried and near[k]
    ]


def findings_notes(f: Findings) -> list[str]:
    """
    Return the sentences that say why segments are indeterminate or classed absolutely.

    Parameters
    ----------
    f : Findings
        Findings with their ES values, classes, references and heart-level finding.

    Returns
    -------
    list of str
        The apex cap's :data:`CAP_NOTE`; for a globally hypokinetic heart, its references and
        what that means for its segments; the segments classed akinetic on the absolute bounds;
        the segments read hypokinetic or akinetic (:attr:`Findings.possibly_akinetic`).

    """
    notes = [CAP_NOTE]
    ref = f.reference
    if f.global_function == GLOBAL_FUNCTIONS[1]:
        said = ', '.join(f'{c.capitalize()} {v:+.3f}' for c, v in ref.items() if v is not None)
        notes.append(
            f'globally hypokinetic: the median ES strain of segments 1-16 ({said}) is within '
            'about three reader spreads of no motion, so segments are not compared with the '
            "heart's own function; akinesis is judged on absolute bounds (|Ecc| < "
            f"{AKINETIC_ABS['ecc']}, Err < {AKINETIC_ABS['err']}, 2σ inside)"
        )
    with np.errstate(invalid='ignore'):
        absolute = [
            k + 1
            for k in range(16)
            if f.classes[k] == 'akinetic'
            and k + 1 not in f.from_tags  # the tags' class, said by from_tags
            and not (f.function_unc[k] <= MAX_SIGMA_F and f.function_index[k] < CLASS_BOUNDS[1][1])
        ]
    if absolute:
        notes.append(
            "akinetic on the absolute bounds (too uncertain against the heart's own function): "
            + ', '.join(map(str, absolute))
        )
    if f.possibly_akinetic:
        notes.append(
            'hypokinetic or akinetic (read below normal and within 1σ of akinesis; no akinetic '
            'class is claimed): '
            + ', '.join(
                f'{k} (f {f.function_index[k - 1]:.2f} ± {f.function_unc[k - 1]:.2f})'
                for k in f.possibly_akinetic
            )
        )
    return notes


def segment_findings(phases) -> Findings:
    """
    Return the findings of a whole list of phase metrics.

    The :class:`~mlv_ros.core.analysis.metrics.PhaseMetrics` are taken in phase order; duplicates:
    the last wins.
    """
    by = {int(p.phase_index): p for p in phases}
    sf = SegmentFindings()
    for k in sorted(by):
        sf.update(by[k])
    return sf.findings
