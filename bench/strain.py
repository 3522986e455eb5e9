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
Benchmark: regional strain at end-systole against the analytic truth, randomized protocols.

Each case draws a protocol (``mlv-ros simulate --random SEED``, abnormal regions included: the
``abnormal_regions`` item), runs the whole graph on the DICOM files (``mlv-ros run --dicom``) and
compares, at the ES phase ``round(es_phase)``, our strain with the truth's
(``groundtruth.json`` ``regional``: Green–Lagrange Err, Ecc, Ell per AHA segment in the
cylindrical frame of the true axis and septum; :mod:`mlv_ros.core.sim.regional`).

Ours: the per-segment Err/Ecc/Ell the run published on ``/lv/metrics`` at ES (what a user reads;
the run's own frame and segments), and the global means from re-analysing the recorded
``/lv/motion`` positions with the analyzer (:class:`mlv_ros.core.analysis.LVAnalyzer`, MLS
strain, as ``mlv_ros.recording.groundtruth_accuracy`` does); ``reanalysis_segment_max_diff``
says how far the published segments are from that re-analysis.

Per case (JSON): the regions, ``global`` (truth, ours, error per component), ``segments``
(per component: median / p95 / max |error|; ``ecc_within_0.05``: fraction of segments with
|Ecc error| ≤ 0.05), ``signs`` (segments with true |Err| > 0.05 or |Ecc| > 0.03 reported with
the right sign: fraction and the wrong ones), ``abnormal`` (truth class per abnormal segment
with truth and ours), ``classification`` (sensitivity / specificity of akinetic + dyskinetic
segments 1–16 — the apex cap is scored apart, ``cap``: the simulator's cap motion contradicts its
label, :data:`CAP` — from the findings :mod:`mlv_ros.core.analysis.findings` makes of the recorded
metrics as ``mlv-ros report`` does; an indeterminate segment is no finding: a missed abnormal
one, counted apart too; ``possibly_akinetic``: the segments the findings name "hypokinetic or
akinetic", no class claimed, per truth class), ``segment_origin`` (1: the septum is the
anatomical prior's, the segment names are not tied to the anatomy), ``explained`` (per
abnormal segment of the truth: found, or why not, :func:`explain_abnormal`: the truth's own
motion of our particles analysed in our frame and in the truth's tells the motion from the
frame, the names and the rule) and
``cap`` (the apex cap's truth and ours in the wall-normal frame our findings use there, the
truth's cylindrical values beside: :func:`truth_in_our_cap_frame`; the segment comparisons use
the wall-frame truth for 17) and
``must`` (the issue's criteria: global Ecc, Ell within 0.02 and Err within 0.05; Ecc error
≤ 0.05 in ≥ 95 % of segments; every sign right). The summary pools the segments of all cases:
sensitivity and specificity with their counts (``found`` tp/(tp+fn), ``normal_not_flagged``
tn/(tn+fp), segments 1–16; ``found_cap`` and ``found_with_cap`` beside), the same where the RV
was found and where the septum is the prior's, the causes of the misses (``missed_why``), the
found by the share of the segment the abnormal core covers (``found_by_coverage``, split at
:data:`PARTIAL_COVERAGE`), the abnormal segments the ES verdict names as carried
(``not_assessable``: still misses by the issue's criterion) and the cap's error (``cap_error``:
median and worst per component).

    mlv-ros bench strain [-- --cases 3 --seed 2000 --abnormal-only --phases 16 --out DIR]
    python bench/strain.py --summarise RUN1.json RUN2.json   # pool earlier runs' cases
    python bench/strain.py --rescore OUT/case-2001 ...       # score kept cases again

``summary.items`` lists the issue's musts and goals one by one (:func:`acceptance_items`).

About 1–3 minutes per case on 2 cores.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _graph_case import add_case_options, cases_folder, run_dicom, simulate  # noqa: E402, I100

COMPONENTS = ('err', 'ecc', 'ell')
#: The issue's must-criteria.
MUST_GLOBAL = {'err': 0.05, 'ecc': 0.02, 'ell': 0.02}
MUST_ECC_SEGMENT = 0.05
MUST_ECC_FRACTION = 0.95
#: A segment's sign must be right where the truth is at least this large.
SIGN_ERR, SIGN_ECC = 0.05, 0.03
#: The issue's goal per segment: the spread between experienced readers of tagged MRI.
GOAL_SEGMENT = {'ecc': 0.02, 'err': 0.05}
ABNORMAL = ('akinetic', 'dyskinetic')
#: The apex cap (17) of a study whose simulator cap is the legacy one is scored apart from the
#: sensitivity and specificity (``classification``'s ``cap``, ``cap_scored`` false): that label
#: contradicts its own motion. Below the endocardial apex the legacy map shortens the solid tip
#: along the axis with the rest of the wall (``z' = (1 − sε) z``, the apex fixed) and, without a
#: cavity (``Q = 0``), widens it isochorically (``r' = r / √J₂``), so in the wall-normal frame a
#: normal cap that is all solid tip (the normal, infarct and hypertrophic shapes) thins (Err
#: −0.04…−0.08) and stretches in the wall (Ecc +0.045…+0.082), which a reader would call
#: dyskinetic ("systolic thinning or stretching", Lang et al. 2015), while a dyskinetic region
#: (k > 1) lengthens the tip: its cap thickens (Err +0.03…+0.05) and shortens (Ecc −0.02…−0.03)
#: (docs/benchmarks.md, "Abnormal segments one by one"). Studies drawn with a physiological cap
#: (``motion.apex_thickening``, every random protocol since session 19: a normal cap thickens
#: and shortens, a dyskinetic one thins and stretches) score their cap with the rest: the
#: criterion counts every segment, and the product claims no class there yet, so an abnormal cap
#: is a miss.
CAP = 17
#: A truth-abnormal segment whose abnormal core covers less than this share of its volume is
#: counted as partial (``found_by_coverage``): its class is its median's (at least half of it), a
#: reader's predominant motion, but its mean motion is a blend of the core and the normal rest.
PARTIAL_COVERAGE = 0.6


def ours_at_es(mcap: Path, es: int) -> dict:
    """
    Return published per-segment strain at phase ``es`` and the re-analysed global means.

    Returns
    -------
    dict
        ``segments`` {component: (17,) array}, ``count`` (17,) (None when not published),
        ``global`` {component: float}, ``reanalysis`` {component: (17,)}, ``classes``
        (17 names, or None when the run does not classify segments), ``findings``,
        ``segment_origin`` (the ES metrics' :data:`~mlv_ros.core.types.SEGMENT_ORIGIN_CODES`
        code) and ``run`` (:func:`mlv_ros.recording.read_run` of the recording).

    """
    from mlv_ros.core.analysis import LVAnalyzer, LVFrame
    from mlv_ros.core.analysis.frame import lv_frame_axes
    from mlv_ros.recording import read_run

    run = read_run(mcap)
    if run['ed'] is None or es not in run['positions']:
        raise ValueError(f'the run has no registered model or no motion at the ES phase {es}')
    apex, base, ref = lv_frame_axes(run['ed'], run['rotation'])
    an = LVAnalyzer(run['ed'], LVFrame(apex, base, ref))
    x = run['positions'][es]
    st = an.strain(x)
    re = an.phase(x, phase_index=es)
    reanalysis = {c: np.asarray(getattr(re, f'segment_{c}')) for c in COMPONENTS}
    met = run['metrics'].get(es) or {}
    published = all(np.asarray(met.get(f'segment_{c}', ())).size == 17 for c in COMPONENTS)
    segs = {c: np.asarray(met[f'segment_{c}']) for c in COMPONENTS} if published else reanalysis
    count = np.asarray(met.get('segment_count', ())) if published else np.asarray(re.segment_count)
    # The findings a user reads (mlv-ros report): the recorded metrics of every phase, their
    # per-segment uncertainties as recorded (recomputed from the recorded motion for recordings
    # made before MotionMetrics carried them), streamed phase by phase as the analysis does.
    from mlv_ros.core.analysis import PhaseMetrics, segment_findings
    from mlv_ros.recording import with_segment_uncertainty

    phases = with_segment_uncertainty(
        [PhaseMetrics.from_dict(d) for _, d in sorted(run['metrics'].items())], run, an.frame
    )
    found = segment_findings(phases)
    return {
        'segments': segs,
        'count': count if count.size == 17 else None,
        'published': published,
        'global': {c: float(np.nanmean(st[c[1:]])) for c in COMPONENTS},
        'reanalysis': reanalysis,
        'classes': found.classes if phases else None,
        'findings': found,
        'segment_origin': int(met.get('segment_origin', 0)),
        'run': run,
    }


def ours_from_positions(ed, rotation, positions: dict, es: int, states=None, frame=None) -> dict:
    """
    Return :func:`compare`'s ``ours`` for motion not published by a run (an offline re-solve).

    The analysis node's steps, offline: :class:`LVAnalyzer` on the ED cloud and its frame, MLS
    strain of every phase's positions, the solver's verdict merged with the analysis', the
    findings streamed in phase order.

    Parameters
    ----------
    ed : ndarray, shape (N, 3)
        ED particle positions, mm.
    rotation : array_like, shape (4,)
        The registered model's rotation quaternion (w, x, y, z): the LV frame's axes.
    positions : dict
        phase → positions, shape (N, 3), mm (phases not solved are left out).
    es : int
        The phase compared (the truth's ES).
    states : dict, optional
        phase → (verdict level, verdict text, RMS residual mm[, degraded segments]) of the
        solver (``ModelState``'s fields); default ok and 0.
    frame : LVFrame, optional
        Analyse in this frame instead of the registered model's (e.g. the truth's,
        :func:`mlv_ros.core.sim.regional.truth_frame`).

    Returns
    -------
    dict
        As :func:`ours_at_es`: the segments and globals from the analysis of ``positions[es]``.

    Raises
    ------
    ValueError
        ``es`` not among the phases of ``positions``.

    """
    from mlv_ros.core.analysis import LVAnalyzer, LVFrame, segment_findings
    from mlv_ros.core.analysis.frame import lv_frame_axes
    from mlv_ros.core.verdict import Verdict

    if es not in positions:
        raise ValueError(f'no motion at the ES phase {es}')
    an = LVAnalyzer(ed, frame or LVFrame(*lv_frame_axes(ed, rotation)))
    n = max(positions) + 1
    phases = []
    for p in sorted(positions):
        level, text, residual, *segments = (states or {}).get(p, (0, '', 0.0))
        m = an.phase(positions[p], phase_index=p, num_phases=n, residual_mm=residual)
        v = Verdict.from_parts(level, text, *segments[:1]).merge(
            Verdict.from_parts(m.verdict, m.verdict_reasons)
        )
        m.verdict, m.verdict_reasons, m.degraded_segments = v.level, v.text, v.confined_to
        phases.append(m)
    at = next(m for m in phases if m.phase_index == es)
    st = an.strain(positions[es])
    segs = {c: np.asarray(getattr(at, f'segment_{c}')) for c in COMPONENTS}
    found = segment_findings(phases)
    return {
        'segments': segs,
        'count': np.asarray(at.segment_count),
        'published': False,
        'global': {c: float(np.nanmean(st[c[1:]])) for c in COMPONENTS},
        'reanalysis': segs,
        'classes': found.classes,
        'findings': found,
    }


#: Why an abnormal segment of the truth was not found (:func:`explain_abnormal`), in the order
#: the causes are tested.
MISS_REASONS = {
    'cap': 'the apex cap, where the product claims no class (a legacy simulator cap: apart)',
    'unsupported': "the ES verdict names the segment's sector as carried by the model",
    'rule': "the truth's own motion, in the truth's frame, is not read abnormal either",
    'names': "the septum is the prior's, and the segment named so is mostly not the truth's",
    'frame': "the truth's motion in our frame (levels, sectors) is not read abnormal",
    'indeterminate': "σ_f beyond its bound; the truth's motion in our frame is read abnormal",
    'motion': "our motion is read normal or hypokinetic where the truth's motion is not",
}


def explain_abnormal(truth: dict, ours: dict, motion, ed, rotation, phases) -> list[dict]:
    """
    Return, per abnormal segment of the truth, our class and why it was missed (if it was).

    The truth's motion of our ED particles is analysed as ours is (:func:`ours_from_positions`),
    once in our frame and once in the truth's (:func:`mlv_ros.core.sim.regional.truth_frame`):
    what the frame, the segment names and the rule cost is then told apart from the motion.

    Parameters
    ----------
    truth : dict
        ``groundtruth.json``'s ``regional``.
    ours : dict
        :func:`ours_at_es` / :func:`ours_from_positions` of the run (``findings``,
        ``classes``; ``segment_origin`` 1 = the septum from the prior, absent: detected).
    motion : LVMotion
        The study's ground-truth motion
        (:func:`mlv_ros.core.io.groundtruth.motion_from_groundtruth`).
    ed : ndarray, shape (N, 3)
        The run's ED particles, mm.
    rotation : array_like, shape (4,)
        The registered model's rotation quaternion (w, x, y, z).
    phases : iterable of int
        The phases the run solved (the truth's motion is analysed at the same ones).

    Returns
    -------
    list of dict
        Per truth-abnormal segment (akinetic or dyskinetic): ``segment``, ``truth``, ``ours``,
        ``f`` / ``f_unc`` (ours), ``truth_motion_our_frame`` and ``truth_motion_truth_frame``
        (the class each gives), ``named_share`` (share of the particles we name so that lie in
        the truth's segment of that number), ``held_by`` (our segment holding most of the
        truth's, and our class of it: under a prior septum a region found under another name)
        ``coverage`` and ``median_contraction`` (the truth's ``abnormal_fraction`` and
        ``median_contraction``), ``unsupported`` (the ES verdict names it as carried), ``tag``
        (its own tag reading at ES: ``ecc``, ``ecc_unc``, ``f``, ``f_unc``,
        ``class_from_tags``; None without one) and ``why``: ``found`` or a :data:`MISS_REASONS`
        key.

    """
    from mlv_ros.core.analysis import LVFrame
    from mlv_ros.core.analysis.frame import cardiac_coordinates, lv_frame_axes
    from mlv_ros.core.analysis.strain import aha_segments
    from mlv_ros.core.sim.regional import truth_frame, truth_segments

    es = int(truth['phase'])
    exact = {int(p): motion.position(ed, int(p)) for p in phases}
    tf = truth_frame(motion)
    in_ours = ours_from_positions(ed, rotation, exact, es)['findings']
    in_truth = ours_from_positions(ed, rotation, exact, es, frame=tf)['findings']
    fr = LVFrame(*lv_frame_axes(ed, rotation))
    c = cardiac_coordinates(ed, fr)
    named = aha_segments(c.h, c.theta, fr.aha_origin_deg)
    true_seg = truth_segments(motion, ed, tf)
    found = ours['findings']
    classes = ours['classes'] or ['indeterminate'] * 17
    out = []
    for s in truth['segments']:
        if s['class'] not in ABNORMAL:
            continue
        k = s['segment'] - 1
        mine = named == k + 1
        share = float(np.mean(true_seg[mine] == k + 1)) if mine.any() else 0.0
        # Where our names put the truth's segment: the segment of ours holding most of it.
        held = np.bincount(named[true_seg == k + 1], minlength=18)
        main = int(np.argmax(held))
        cls = classes[k]
        if cls in ABNORMAL:
            why = 'found'
        elif k + 1 == CAP:
            why = 'cap'
        elif k + 1 in found.unsupported:
            why = 'unsupported'
        elif in_truth.classes[k] not in ABNORMAL:
            why = 'rule'
        elif in_ours.classes[k] not in ABNORMAL:
            why = 'names' if ours.get('segment_origin') == 1 and share < 0.5 else 'frame'
        else:
            why = 'indeterminate' if cls == 'indeterminate' else 'motion'
        out.append(
            {
                'segment': k + 1,
                'truth': s['class'],
                'ours': cls,
                'f': round(float(found.function_index[k]), 3),
                'f_unc': round(float(found.function_unc[k]), 3),
                'truth_motion_our_frame': in_ours.classes[k],
                'truth_motion_truth_frame': in_truth.classes[k],
                'named_share': round(share, 3),
                'held_by': {'segment': main, 'class': classes[main - 1]} if held.any() else None,
                'coverage': s.get('abnormal_fraction'),
                'median_contraction': s.get('median_contraction'),
                'unsupported': k + 1 in found.unsupported,
                'tag': _tag_evidence(found, k),
                'why': why,
            }
        )
    return out


def _tag_evidence(found, k: int) -> dict | None:
    """Return segment ``k``'s (0-based) own tag reading at ES, or None where it has none."""
    te = np.asarray(found.tag_ecc, dtype=np.float64).reshape(-1)
    if te.size != 17 or not np.isfinite(te[k]):
        return None
    return {
        'ecc': round(float(te[k]), 4),
        'ecc_unc': round(float(np.asarray(found.tag_ecc_unc)[k]), 4),
        'f': round(float(found.tag_function_index[k]), 3),
        'f_unc': round(float(found.tag_function_unc[k]), 3),
        'class_from_tags': k + 1 in found.from_tags,
    }


def truth_in_our_cap_frame(truth: dict, motion, ed, rotation) -> dict:
    """
    Return ``truth`` with the apex cap's (17) strain in the frame our findings use there.

    Our cap's Err / Ecc / Ell are taken in the wall-normal frame
    (:func:`mlv_ros.core.analysis.frame.wall_normal_frame`), the truth's in the cylindrical one;
    the cap is compared like with like: the truth's deformation gradient at ES
    (``motion.deformation_gradient``) of our cap's particles, in our frame. The cylindrical
    values are kept as ``cylindrical`` in the cap's entry.

    Parameters
    ----------
    truth : dict
        ``groundtruth.json``'s ``regional``.
    motion : LVMotion
        The study's ground-truth motion.
    ed : ndarray, shape (N, 3)
        The run's ED particles, mm.
    rotation : array_like, shape (4,)
        The registered model's rotation quaternion (w, x, y, z).

    Returns
    -------
    dict
        A copy of ``truth`` whose segment 17 holds the wall-frame means.

    """
    from mlv_ros.core.analysis import LVAnalyzer, LVFrame
    from mlv_ros.core.analysis.frame import lv_frame_axes

    es = int(truth['phase'])
    an = LVAnalyzer(ed, LVFrame(*lv_frame_axes(ed, rotation)))
    cap = an.segments == 17
    out = dict(truth)
    out['segments'] = [dict(s) for s in truth['segments']]
    if not cap.any():
        return out
    st = an.strain(
        motion.position(ed, es), motion.deformation_gradient(ed, es), segment_frame=True
    )
    s17 = out['segments'][16]
    s17['cylindrical'] = {c: s17[c] for c in COMPONENTS}
    for c in COMPONENTS:
        s17[c] = round(float(np.nanmean(st[c[1:]][cap])), 5)
    return out


def brief(result: dict) -> dict:
    """
    Return the headline of a :func:`compare` result (one JSON line).

    ``global_error`` per component, ``ecc_within_0.05``, ``signs`` right / checked, the
    akinetic + dyskinetic segments found (``tp``, ``fn``, ``fp``, indeterminate abnormal),
    ``classes``: truth -> our class of every segment that is abnormal in either,
    ``missed_why`` (:func:`explain_abnormal`'s cause per missed segment, when explained) and
    ``must``.
    """
    cls = result['classification'] or {}
    return {
        'global_error': {c: result['global'][c]['error'] for c in COMPONENTS},
        'ecc_within_0.05': result['segments']['ecc_within_0.05'],
        'signs': f'{result["signs"]["right"]}/{result["signs"]["checked"]}',
        'found': {
            k: cls.get(v)
            for k, v in (
                ('tp', 'true_positive'),
                ('fn', 'false_negative'),
                ('fp', 'false_positive'),
                ('indeterminate', 'indeterminate_abnormal'),
            )
        },
        'classes': {
            s['segment']: f'{s["truth"]} -> {s["ours"]}' for s in cls.get('per_segment', ())
        },
        'missed_why': {
            e['segment']: e['why'] for e in result.get('explained', ()) if e['why'] != 'found'
        },
        'must': result['must'],
    }


def _possibly_by_truth(seg: list, ours: dict, ok) -> dict:
    """Count the segments the findings name possibly akinetic, per truth class."""
    named = getattr(ours.get('findings'), 'possibly_akinetic', ())
    out = {k: 0 for k in ('normal', 'hypokinetic', *ABNORMAL)}
    for k in named:
        if ok[k - 1]:
            out[seg[k - 1]['class']] += 1
    return out


def compare(truth: dict, ours: dict, cap_scored: bool = False) -> dict:
    """Strain errors of one case (see the module docstring; ``cap_scored``: :data:`CAP`)."""
    seg = truth['segments']
    t = {c: np.array([s[c] for s in seg]) for c in COMPONENTS}
    ok = np.array([s['count'] > 0 for s in seg])
    if ours['count'] is not None:
        ok &= ours['count'] > 0
    out = {
        'global': {
            c: {
                'truth': round(truth['global'][c], 4),
                'ours': round(ours['global'][c], 4),
                'error': round(ours['global'][c] - truth['global'][c], 4),
            }
            for c in COMPONENTS
        },
        'segments_compared': int(ok.sum()),
        'segments': {},
    }
    for c in COMPONENTS:
        e = np.abs(ours['segments'][c] - t[c])[ok]
        out['segments'][c] = {
            'median': round(float(np.median(e)), 4),
            'p95': round(float(np.percentile(e, 95)), 4),
            'max': round(float(e.max()), 4),
            'worst_segment': int(np.flatnonzero(ok)[np.argmax(e)] + 1),
        }
    ecc_err = np.abs(ours['segments']['ecc'] - t['ecc'])[ok]
    out['segments']['ecc_within_0.05'] = round(float(np.mean(ecc_err <= MUST_ECC_SEGMENT)), 4)
    # The goal (the spread between experienced readers): per segment Ecc within 0.02, Err
    # within 0.05; and every compared segment's signed error, so that the summary pools them.
    for c, lim in GOAL_SEGMENT.items():
        e = np.abs(ours['segments'][c] - t[c])[ok]
        out['segments'][f'{c}_within_{lim}'] = round(float(np.mean(e <= lim)), 4)
    out['segments']['signed_error'] = {
        c: {
            int(k + 1): round(float(ours['segments'][c][k] - t[c][k]), 4)
            for k in np.flatnonzero(ok)
        }
        for c in COMPONENTS
    }
    out['reanalysis_segment_max_diff'] = round(
        float(
            max(
                np.max(np.abs(ours['segments'][c] - ours['reanalysis'][c])[ok]) for c in COMPONENTS
            )
        ),
        4,
    )
    wrong, checked = [], 0
    for k in np.flatnonzero(ok):
        for c, lim in (('err', SIGN_ERR), ('ecc', SIGN_ECC)):
            if abs(t[c][k]) > lim:
                checked += 1
                if np.sign(ours['segments'][c][k]) != np.sign(t[c][k]):
                    wrong.append(
                        {
                            'segment': int(k + 1),
                            'component': c,
                            'truth': round(float(t[c][k]), 4),
                            'ours': round(float(ours['segments'][c][k]), 4),
                        }
                    )
    out['signs'] = {
        'checked': checked,
        'checked_err': int(sum(abs(t['err'][k]) > SIGN_ERR for k in np.flatnonzero(ok))),
        'right': checked - len(wrong),
        'fraction': round((checked - len(wrong)) / checked, 4) if checked else None,
        'wrong': wrong,
    }
    out['abnormal'] = [
        {
            'segment': s['segment'],
            'class': s['class'],
            **{f'{c}_truth': s[c] for c in COMPONENTS},
            **{
                f'{c}_ours': round(float(ours['segments'][c][s['segment'] - 1]), 4)
                for c in COMPONENTS
            },
        }
        for s in seg
        if s['class'] != 'normal'
    ]
    out['truth_classes'] = {
        k: sum(s['class'] == k for s in seg) for k in ('normal', 'hypokinetic', *ABNORMAL)
    }
    out['classification'] = None
    if ours['classes'] is not None and len(ours['classes']) == 17:
        # A legacy apex cap is scored apart (CAP): its label is not what its motion shows.
        scored = ok.copy()
        if not cap_scored:
            scored[CAP - 1] = False
        pos = np.array([s['class'] in ABNORMAL for s in seg])[scored]
        got = np.array([c in ABNORMAL for c in ours['classes']])[scored]
        ind = np.array([c == 'indeterminate' for c in ours['classes']])[scored]
        # An indeterminate segment is not a finding: a missed abnormal one counts as a false
        # negative, a normal one as a true negative; how many there were is said beside.
        out['classification'] = {
            'cap': {'truth': seg[CAP - 1]['class'], 'ours': ours['classes'][CAP - 1]}
            if ok[CAP - 1] and not cap_scored
            else None,
            'cap_scored': bool(cap_scored),
            'true_positive': int(np.sum(pos & got)),
            'false_negative': int(np.sum(pos & ~got)),
            'true_negative': int(np.sum(~pos & ~got)),
            'false_positive': int(np.sum(~pos & got)),
            'indeterminate_abnormal': int(np.sum(pos & ind)),
            'indeterminate_other': int(np.sum(~pos & ind)),
            # Named "hypokinetic or akinetic" (no class claimed): per truth class, among the
            # segments compared.
            'possibly_akinetic': _possibly_by_truth(seg, ours, ok),
            'per_segment': [
                {'segment': int(k + 1), 'truth': seg[k]['class'], 'ours': ours['classes'][k]}
                for k in np.flatnonzero(ok)
                if seg[k]['class'] != 'normal' or ours['classes'][k] != 'normal'
            ],
        }
    out['must'] = bool(
        all(abs(out['global'][c]['error']) <= v for c, v in MUST_GLOBAL.items())
        and out['segments']['ecc_within_0.05'] >= MUST_ECC_FRACTION
        and not wrong
    )
    return out


def run_case(seed: int, out: Path, timeout: float, phases: int | None) -> dict:
    study, run_dir = out / 'study', out / 'run'
    case = {'seed': seed}
    t0 = time.monotonic()
    error = simulate(seed, study, *(['--phases', str(phases)] if phases else []))
    if error:
        return case | {'error': error}
    truth = json.loads((study / 'groundtruth.json').read_text())['regional']
    case['shape'] = json.loads((study / 'groundtruth.json').read_text())['protocol']['shape']
    case['regions'] = truth['regions']
    run_exit, error = run_dicom(study, run_dir, timeout)
    case['seconds'] = round(time.monotonic() - t0, 1)
    case['run_exit'] = run_exit
    if error:
        return case | {'error': error}
    return score_case(case, study, run_dir)


def score_case(case: dict, study: Path, run_dir: Path) -> dict:
    """
    Score a kept case: the study's truth against its run's recording (:func:`compare`).

    Parameters
    ----------
    case : dict
        What is known of the case so far (``seed``, ...); returned with the scores added.
    study, run_dir : Path
        The case's ``study/`` (``groundtruth.json``) and ``run/`` (``run.mcap``) folders.

    Returns
    -------
    dict
        ``case`` with :func:`compare`'s fields, or with ``error`` where the recording has no
        motion at the truth's ES.

    """
    gt = json.loads((study / 'groundtruth.json').read_text())
    truth = gt['regional']
    case.setdefault('shape', gt['protocol']['shape'])
    case.setdefault('regions', truth['regions'])
    try:
        ours = ours_at_es(run_dir / 'run.mcap', int(truth['phase']))
    except ValueError as exc:
        return case | {'error': str(exc)}
    case['es_phase'] = int(truth['phase'])
    case['published'] = ours['published']
    case['segment_origin'] = ours['segment_origin']
    from mlv_ros.core.io.groundtruth import motion_from_groundtruth

    run = ours['run']
    motion = motion_from_groundtruth(study)
    case['explained'] = explain_abnormal(
        truth, ours, motion, run['ed'], run['rotation'], run['positions']
    )
    truth = truth_in_our_cap_frame(truth, motion, run['ed'], run['rotation'])
    case['cap'] = {
        'truth': {c: truth['segments'][16][c] for c in COMPONENTS},
        'truth_cylindrical': truth['segments'][16].get('cylindrical'),
        'ours': {c: round(float(ours['segments'][c][16]), 4) for c in COMPONENTS},
    }
    # A physiological simulator cap (motion.apex_thickening) is scored with the rest (CAP).
    return case | compare(truth, ours, cap_scored=motion.apex_thickening is not None)


def acceptance_items(good: list[dict], summary: dict) -> dict:
    """
    Return the issue's musts and goals one by one over the cases (pooled segments).

    Parameters
    ----------
    good : list of dict
        The cases that ran (:func:`run_case` without ``error``).
    summary : dict
        :func:`summarise`'s counts so far (``sensitivity``, ``specificity``, ``found``,
        ``normal_not_flagged``).

    Returns
    -------
    dict
        Per item: ``cases_meeting`` ("k/n") or the pooled value and ``met`` (bool). Global
        items: |error| within :data:`MUST_GLOBAL` per case. ``ecc_segment``: pooled fraction of
        segments with |Ecc error| ≤ 0.05 (must ≥ 0.95) and the pooled 95th percentile of
        |Ecc error|. ``signs``: right / checked (must: all). ``goal_ecc_segment`` /
        ``goal_err_segment``: pooled fraction within :data:`GOAL_SEGMENT` and the pooled
        95th percentile. Cases recorded before the signed errors were kept give no pooled
        quantile (None).

    """
    n = len(good)
    items = {}
    for c, lim in MUST_GLOBAL.items():
        e = [abs(x['global'][c]['error']) for x in good]
        k = sum(v <= lim for v in e)
        items[f'global_{c}'] = {
            'limit': lim,
            'cases_meeting': f'{k}/{n}',
            'worst': round(max(e), 4),
            'met': k == n,
        }
    signed = [x['segments'].get('signed_error', {}) for x in good]
    pooled = {c: [abs(v) for s in signed for v in s.get(c, {}).values()] for c in COMPONENTS}

    def p95(c):
        return round(float(np.percentile(pooled[c], 95)), 4) if pooled[c] else None

    frac = summary['ecc_within_0.05']
    ecc_ok = [x['segments']['ecc_within_0.05'] >= MUST_ECC_FRACTION for x in good]
    items['ecc_segment'] = {
        'limit': MUST_ECC_SEGMENT,
        'fraction_within': frac,
        'p95': p95('ecc'),
        'cases_meeting': f'{sum(ecc_ok)}/{n}',
        'met': frac >= MUST_ECC_FRACTION,
    }
    right = sum(x['signs']['right'] for x in good)
    checked = sum(x['signs']['checked'] for x in good)
    items['signs'] = {
        'right': f'{right}/{checked}',
        'wrong': [dict(w, seed=x['seed']) for x in good for w in x['signs']['wrong']],
        'cases_meeting': f'{sum(not x["signs"]["wrong"] for x in good)}/{n}',
        'met': right == checked,
    }
    for key in ('sensitivity', 'specificity'):
        v = summary.get(key)
        items[key] = {
            'value': v,
            'counts': summary.get('found' if key == 'sensitivity' else 'normal_not_flagged'),
            'met': v is not None and v >= 0.9,
        }
    for c, lim in GOAL_SEGMENT.items():
        within = [v <= lim for v in pooled[c]]
        items[f'goal_{c}_segment'] = {
            'limit': lim,
            'fraction_within': round(float(np.mean(within)), 4) if within else None,
            'p95': p95(c),
            'met': bool(within) and p95(c) <= lim,
        }
    items['goal_ell_segment_p95'] = p95('ell')
    return items


def summarise(cases: list[dict]) -> dict:
    good = [c for c in cases if 'error' not in c]
    out = {
        'cases': len(cases),
        'passing_must': sum(c['must'] for c in good),
        'errors': [f'seed {c["seed"]}: {c["error"]}' for c in cases if 'error' in c],
    }
    if not good:
        return out
    for comp in COMPONENTS:
        g = [abs(c['global'][comp]['error']) for c in good]
        out[f'global_{comp}_error'] = {'worst': max(g), 'median': round(statistics.median(g), 4)}
        out[f'segment_{comp}_p95'] = {'worst': max(c['segments'][comp]['p95'] for c in good)}
    n = sum(c['segments_compared'] for c in good)
    out['ecc_within_0.05'] = round(
        sum(c['segments']['ecc_within_0.05'] * c['segments_compared'] for c in good) / n, 4
    )
    checked = sum(c['signs']['checked'] for c in good)
    out['signs_right'] = (
        round(sum(c['signs']['right'] for c in good) / checked, 4) if checked else None
    )
    # Every scored segment (a legacy apex cap apart, CAP).
    out['abnormal_segments'] = sum(
        c['truth_classes']['akinetic'] + c['truth_classes']['dyskinetic'] for c in good
    ) - sum(
        bool((c.get('classification') or {}).get('cap'))
        and c['classification']['cap']['truth'] in ABNORMAL
        for c in good
    )
    cls = [c['classification'] for c in good if c['classification']]
    if cls:
        tp, fn = sum(c['true_positive'] for c in cls), sum(c['false_negative'] for c in cls)
        tn, fp = sum(c['true_negative'] for c in cls), sum(c['false_positive'] for c in cls)
        out['sensitivity'] = round(tp / (tp + fn), 4) if tp + fn else None
        out['specificity'] = round(tn / (tn + fp), 4) if tn + fp else None
        out['found'] = f'{tp}/{tp + fn}'
        out['normal_not_flagged'] = f'{tn}/{tn + fp}'
        # The same counts where the septum came from the RV in the images (segment names tied to
        # the anatomy) and where it is the prior's (names not tied to it: said in the report).
        for name, keep in (('rv_found', lambda c: c.get('segment_origin') != 1),
                           ('septum_prior', lambda c: c.get('segment_origin') == 1)):
            sub = [c['classification'] for c in good if c['classification'] and keep(c)]
            out[f'found_{name}'] = (
                f'{sum(c["true_positive"] for c in sub)}/'
                f'{sum(c["true_positive"] + c["false_negative"] for c in sub)}'
            )
            out[f'normal_not_flagged_{name}'] = (
                f'{sum(c["true_negative"] for c in sub)}/'
                f'{sum(c["true_negative"] + c["false_positive"] for c in sub)}'
            )
        out['indeterminate'] = {
            k: sum(c[f'indeterminate_{k}'] for c in cls) for k in ('abnormal', 'other')
        }
        # Legacy apex caps, scored apart (CAP), and the counts with them (earlier figures).
        caps = [c['cap'] for c in cls if c.get('cap') and c['cap']['truth'] in ABNORMAL]
        cap_tp = sum(c['ours'] in ABNORMAL for c in caps)
        out['found_cap'] = f'{cap_tp}/{len(caps)}'
        cap_fp = sum(
            1 for c in cls if c.get('cap') and c['cap']['truth'] not in ABNORMAL
            and c['cap']['ours'] in ABNORMAL
        )
        out['found_with_cap'] = f'{tp + cap_tp}/{tp + fn + len(caps)}'
        out['cap_flagged_not_abnormal'] = cap_fp
        # Segments named "hypokinetic or akinetic" (findings.possibly_akinetic), by truth class.
        out['possibly_akinetic'] = {
            k: sum(c.get('possibly_akinetic', {}).get(k, 0) for c in cls)
            for k in ('normal', 'hypokinetic', *ABNORMAL)
        }
    else:
        out['sensitivity'] = out['specificity'] = None  # no run had metrics to classify
    cap = [c['cap'] for c in good if c.get('cap')]
    if cap:
        err = {comp: [abs(x['ours'][comp] - x['truth'][comp]) for x in cap] for comp in COMPONENTS}
        out['cap_error'] = {
            comp: {'median': round(statistics.median(e), 4), 'worst': round(max(e), 4)}
            for comp, e in err.items()
        }
    out['items'] = acceptance_items(good, out)
    why = [e['why'] for c in good for e in c.get('explained', ()) if e['why'] != 'found']
    out['missed_why'] = {k: why.count(k) for k in MISS_REASONS if k in why}
    # Segments 1–16 by how much of them the abnormal core covers (PARTIAL_COVERAGE), and those
    # the ES verdict names as carried: a reader's "not assessable", still a miss by the issue's
    # criterion (it counts every akinetic or dyskinetic segment, assessable or not).
    ex = [e for c in good for e in c.get('explained', ()) if e['segment'] != CAP]
    for name, keep in (
        (f'>={PARTIAL_COVERAGE}', lambda e: (e.get('coverage') or 0.0) >= PARTIAL_COVERAGE),
        (f'<{PARTIAL_COVERAGE}', lambda e: (e.get('coverage') or 0.0) < PARTIAL_COVERAGE),
    ):
        sub = [e for e in ex if e.get('coverage') is not None and keep(e)]
        out.setdefault('found_by_coverage', {})[name] = (
            f'{sum(e["why"] == "found" for e in sub)}/{len(sub)}'
        )
    out['not_assessable'] = sum(e.get('unsupported', False) for e in ex)
    # Under a prior septum a region can be found under another segment's name.
    out['names_missed_but_region_found'] = sum(
        e['why'] == 'names' and (e['held_by'] or {}).get('class') in ABNORMAL
        for c in good
        for e in c.get('explained', ())
    )
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--cases', type=int, default=3)
    ap.add_argument('--seed', type=int, default=2000, help='first protocol seed')
    ap.add_argument(
        '--abnormal-only',
        action='store_true',
        help='skip seeds whose protocol draws no abnormal region (cases still --cases)',
    )
    ap.add_argument('--phases', type=int, default=None, help='fix the phase count (shorter runs)')
    ap.add_argument(
        '--summarise',
        nargs='+',
        metavar='JSON',
        default=None,
        help="pool the cases of earlier runs' JSON outputs and print their summary (no run)",
    )
    ap.add_argument(
        '--rescore',
        nargs='+',
        metavar='CASE_DIR',
        default=None,
        help='score kept cases (case-SEED folders of --out) again with this bench (no run)',
    )
    add_case_options(ap)
    args = ap.parse_args()
    if args.rescore:
        cases = []
        for d in map(Path, args.rescore):
            seed = int(d.name.rsplit('-', 1)[-1]) if d.name.startswith('case-') else None
            cases.append(score_case({'seed': seed}, d / 'study', d / 'run'))
        print(json.dumps({'summary': summarise(cases), 'cases': cases}, indent=1))
        return 0
    if args.summarise:
        cases = [c for f in args.summarise for c in json.loads(Path(f).read_text())['cases']]
        print(json.dumps({'summary': summarise(cases)}, indent=1))
        return 0
    if args.cases < 1:
        ap.error('--cases must be >= 1')
    from mlv_ros.core.sim.protocol import draw_protocol

    seeds, s = [], args.seed
    while len(seeds) < args.cases:
        if not args.abnormal_only or draw_protocol(s)['abnormal_regions']:
            seeds.append(s)
        s += 1
    cases = []
    with cases_folder(args, 'strain') as root:
        for seed in seeds:
            case = run_case(seed, root / f'case-{seed}', args.timeout, args.phases)
            print(
                json.dumps(
                    {k: case.get(k) for k in ('seed', 'must', 'global', 'error') if k in case}
                ),
                file=sys.stderr,
                flush=True,
            )
            cases.append(case)
    print(
        json.dumps(
            {
                'summary': summarise(cases),
                'must': {
                    'global': MUST_GLOBAL,
                    'ecc_segment': MUST_ECC_SEGMENT,
                    'ecc_fraction': MUST_ECC_FRACTION,
                    'sign_where': {'err': SIGN_ERR, 'ecc': SIGN_ECC},
                },
                'cases': cases,
                'out': str(root) if (args.out or args.keep) else None,
            },
            indent=1,
        )
    )
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
