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
Key numbers of a run from its per-phase metrics, with an account of what is missing.

Everything here is a pure function of :class:`~mlv_ros.core.analysis.metrics.PhaseMetrics`
lists; nothing is recomputed from images or point clouds.

Peaks
-----
"Peak" of a signed quantity is its value of largest magnitude over the cycle, sign kept
(so peak Ecc is the most negative Ecc of a normally contracting segment). End-systole (ES) is
the phase of smallest cavity volume (ties: the earliest).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json
import math
from pathlib import Path
from typing import Mapping, Sequence

from mlv_ros.core.analysis.findings import segment_findings
from mlv_ros.core.analysis.frame import levels_outside, LVFrame, twist_extrapolation_note
from mlv_ros.core.analysis.metrics import PhaseMetrics
import numpy as np


@dataclass
class RunData:
    """
    One run for the report.

    Attributes
    ----------
    phases : list of PhaseMetrics
        Any order; sorted by ``phase_index`` (later duplicates replace earlier ones).
    ed_positions : ndarray, shape (N, 3), optional
        ED particle positions, mm (for the 3D displacement figure).
    positions_by_phase : mapping phase_index -> ndarray (N, 3), optional
        Particle positions per phase (a list/tuple indexed by phase is accepted too).
    frame : LVFrame, optional
        ED long-axis frame; estimated from ``ed_positions`` when missing.
    label : str
    twist_span : (float, float), None or False
        Levels (0 apex … 1 base) the SA slices with tag points cross
        (:func:`~mlv_ros.core.analysis.frame.plane_level_span`): twist beyond them is
        extrapolated. None: no SA slice held tag points; False (default): not known.

    """

    phases: list = field(default_factory=list)
    ed_positions: np.ndarray | None = None
    positions_by_phase: Mapping[int, np.ndarray] | Sequence | None = None
    frame: LVFrame | None = None
    label: str = 'run'
    twist_span: tuple | None | bool = False


def sorted_phases(phases: Sequence[PhaseMetrics]) -> tuple[list[PhaseMetrics], list[int]]:
    """Phases sorted by index with duplicates removed (last wins); also the duplicate indices."""
    by: dict[int, PhaseMetrics] = {}
    dup = []
    for p in phases:
        if p.phase_index in by:
            dup.append(int(p.phase_index))
        by[int(p.phase_index)] = p
    return [by[k] for k in sorted(by)], sorted(set(dup))


def signed_peak(v: np.ndarray, axis=None):
    """Value of largest magnitude (sign kept) along ``axis``, ignoring NaN; NaN if none."""
    v = np.asarray(v, dtype=np.float64)
    a = np.where(np.isfinite(v), np.abs(v), -1.0)
    i = np.argmax(a, axis=axis)
    if axis is None:
        return float(v.ravel()[i]) if a.ravel()[i] >= 0 else math.nan
    out = np.take_along_axis(v, np.expand_dims(i, axis), axis).squeeze(axis)
    return np.where(
        np.take_along_axis(a, np.expand_dims(i, axis), axis).squeeze(axis) >= 0, out, np.nan
    )


def level_table(phases: Sequence[PhaseMetrics], name: str) -> tuple[np.ndarray, np.ndarray]:
    """
    Per-level quantity over the cycle as a (phases, levels) table.

    Returns
    -------
    positions : ndarray, shape (L,)
        Union of the phases' level positions, apex → base.
    table : ndarray, shape (P, L)
        ``getattr(phase, name)`` per level; NaN where a phase lacks that level.

    """
    keys = sorted({round(float(v), 6) for p in phases for v in p.level_position})
    col = {k: j for j, k in enumerate(keys)}
    t = np.full((len(phases), len(keys)), np.nan)
    for i, p in enumerate(phases):
        vals = np.asarray(getattr(p, name), dtype=np.float64)
        if vals.shape != p.level_position.shape:
            continue  # inconsistent message: leave the row empty (reported by summarize)
        for pos, v in zip(p.level_position, vals):
            t[i, col[round(float(pos), 6)]] = v
    return np.asarray(keys), t


def peak_segment_strain(phases: Sequence[PhaseMetrics]) -> dict[str, np.ndarray] | None:
    """
    Return the signed peak over the cycle of each AHA segment's Err, Ecc, Ell, shape (17,) each.

    None when no phase carries strain. Segments never populated (count 0 where counts are known)
    are NaN here (and drawn as "n/a").
    """
    ph = [p for p in phases if p.has_strain]
    if not ph:
        return None
    out = {}
    for key, f in (('err', 'segment_err'), ('ecc', 'segment_ecc'), ('ell', 'segment_ell')):
        t = np.stack([getattr(p, f) for p in ph])
        for i, p in enumerate(ph):
            if p.segment_count.size == 17:
                t[i, p.segment_count == 0] = np.nan
        out[key] = signed_peak(t, axis=0)
    return out


def _row_nanmean(t: np.ndarray) -> np.ndarray:
    """Mean of each row over its finite entries (NaN for a row without any, no warning)."""
    ok = np.isfinite(t)
    n = ok.sum(axis=1)
    return np.where(n > 0, np.where(ok, t, 0.0).sum(axis=1) / np.maximum(n, 1), np.nan)


def _f(v) -> float | None:
    """JSON-safe float (None for NaN/inf)."""
    v = float(v)
    return v if math.isfinite(v) else None


_ORIGIN_NOTES = {
    0: ('unknown', "where the segments' circumferential origin came from is not recorded"),
    1: (
        'prior',
        'no right ventricle was found in the images: the segments are placed by an anatomical '
        "prior (septum toward the patient's right), not tied to this heart's anatomy",
    ),
    2: (
        'detected',
        'the segments start at the RV insertion points found in the ED short-axis images',
    ),
    3: ('given', 'the segments follow a reference direction given to the registration'),
}


def segment_origin_note(phases: Sequence[PhaseMetrics]) -> dict:
    """
    Return where the AHA segments' circumferential origin came from.

    The phases' ``segment_origin``, the last phase's: ``source`` unknown / prior / detected /
    given, ``confidence``, a sentence ``note`` for the reader and ``names_uncertain`` (True when
    the source is the prior: the classes are this heart's, which segment each names is not).
    """
    last = phases[-1] if phases else None
    code = int(getattr(last, 'segment_origin', 0)) if last is not None else 0
    source, note = _ORIGIN_NOTES.get(code, _ORIGIN_NOTES[0])
    conf = float(getattr(last, 'segment_origin_confidence', 0.0)) if last is not None else 0.0
    if code == 2:
        note += f' (confidence {conf:.2f})'
    return {
        'source': source,
        'confidence': _f(conf),
        'note': note,
        'names_uncertain': source == 'prior',
    }


def summarize(phases: Sequence[PhaseMetrics], label: str = 'run', twist_span=False) -> dict:
    """
    Key numbers of a run and a list of what is missing.

    Returns
    -------
    dict
        ``label``, ``num_phases`` (expected), ``phases_present``, ``missing_phases``,
        ``missing`` (sentences), ``key`` (headline numbers, None where not computable:
        edv_ml, esv_ml, ejection_fraction, es_phase_index, es_time_fraction,
        peak_twist_apex_deg, peak_twist_base_deg, peak_torsion_deg_per_cm,
        peak_sa_radius_change_mm, peak_base_longitudinal_mm, la_radius_ed_mm,
        la_radius_es_mm, peak_global_err/ecc/ell), ``peak_segment_strain`` (17 each or
        None), ``segment_findings`` (per AHA segment: peak and ES strain with uncertainties,
        function index, wall-motion class and the thresholds used,
        :meth:`mlv_ros.core.analysis.findings.Findings.to_dict`, plus ``segment_origin``,
        :func:`segment_origin_note`; None without strain) and
        ``phases`` (every field of every phase). With ``twist_span`` known (see
        :class:`RunData`): ``twist_measured_levels`` and ``twist_extrapolated`` (a sentence, ''
        when nothing is), and ``key["extrapolated"]``: which of the twist keys (apex, base,
        torsion) come from levels no SA slice measured.

    """
    ph, dup = sorted_phases(phases)
    missing: list[str] = []
    out: dict = {
        'label': label,
        'missing': missing,
        'key': {},
        'peak_segment_strain': None,
        'segment_findings': None,
        'phases': [],
    }
    if not ph:
        missing.append('no phases: nothing to report')
        out.update(num_phases=0, phases_present=[], missing_phases=[])
        return out
    n_exp = max(int(max(p.num_phases for p in ph)), len(ph), max(p.phase_index for p in ph) + 1)
    present = [p.phase_index for p in ph]
    gaps = sorted(set(range(n_exp)) - set(present))
    out.update(
        num_phases=n_exp,
        phases_present=present,
        missing_phases=gaps,
        phases=[p.to_dict() for p in ph],
    )
    missing += _missing_notes(ph, n_exp, gaps, dup)
    pos, tw = level_table(ph, 'twist_deg')
    out['key'] = _key_numbers(ph, pos, tw)
    if twist_span is not False:
        _add_twist_span(out, ph, pos, twist_span)
    _add_strain(out, ph)
    return out


def _missing_notes(ph: list, n_exp: int, gaps: list, dup: list) -> list[str]:
    """
    Return what the phases lack, a sentence each (for :func:`summarize`'s ``missing``).

    Parameters
    ----------
    ph : list of PhaseMetrics
        The phases present, in phase order (:func:`sorted_phases`).
    n_exp : int
        Phases expected.
    gaps : list of int
        The phases missing.
    dup : list of int
        Phases received more than once.

    Returns
    -------
    list of str
        The sentences.

    """
    missing = []
    present = [p.phase_index for p in ph]
    if gaps:
        missing.append(f'{len(gaps)} of {n_exp} phases missing: {gaps}')
    if 0 not in present:
        missing.append(
            'phase 0 (end-diastole) missing: ED-relative numbers use the first phase present'
        )
    if dup:
        missing.append(f'duplicate phases {dup}: the last received was kept')
    bad = [
        p.phase_index
        for p in ph
        if any(
            np.asarray(getattr(p, f)).shape != p.level_position.shape
            for f in ('twist_deg', 'sa_radius_mm', 'longitudinal_displacement_mm')
        )
    ]
    if bad:
        missing.append(
            f'phases {bad}: per-level arrays of inconsistent length (left out of level curves)'
        )
    no_strain = [p.phase_index for p in ph if not p.has_strain]
    if len(no_strain) == len(ph):
        missing.append("no strain in any phase: AHA bull's-eye and peak strains not available")
    elif no_strain:
        missing.append(f'strain missing in phases {no_strain}: peaks use the other phases')
    if all(p.level_position.size == 0 for p in ph):
        missing.append('no per-level metrics in any phase')
    return missing


def _key_numbers(ph: list, pos: np.ndarray, tw: np.ndarray) -> dict:
    """
    Return the headline numbers: volumes, ES, LA radius, torsion, twist, radius, base motion.

    Parameters
    ----------
    ph : list of PhaseMetrics
        The phases present, in phase order; the first is ED.
    pos, tw : ndarray
        :func:`level_table` of ``twist_deg``: level positions and the twist per phase, deg.

    Returns
    -------
    dict
        :func:`summarize`'s ``key`` less the strain and twist-span entries (None where not
        computable).

    """
    vol = np.array([p.cavity_volume_ml for p in ph])
    es = int(np.argmin(vol))
    ed = ph[0]
    _, rad = level_table(ph, 'sa_radius_mm')
    _, lon = level_table(ph, 'longitudinal_displacement_mm')
    key = {}
    key['edv_ml'] = _f(ed.cavity_volume_ml)
    key['esv_ml'] = _f(vol[es])
    key['ejection_fraction'] = (
        _f((ed.cavity_volume_ml - vol[es]) / ed.cavity_volume_ml)
        if ed.cavity_volume_ml > 0
        else None
    )
    key['es_phase_index'] = int(ph[es].phase_index)
    key['es_time_fraction'] = _f(ph[es].time_fraction)
    key['la_radius_ed_mm'] = _f(ed.la_radius_mm)
    key['la_radius_es_mm'] = _f(ph[es].la_radius_mm)
    key['peak_torsion_deg_per_cm'] = _f(signed_peak([p.torsion_deg_per_cm for p in ph]))
    if pos.size:
        key['peak_twist_apex_deg'] = _f(signed_peak(tw[:, 0]))
        key['peak_twist_base_deg'] = _f(signed_peak(tw[:, -1]))
        key['peak_sa_radius_change_mm'] = _f(signed_peak(_row_nanmean(rad - rad[0])))
        key['peak_base_longitudinal_mm'] = _f(signed_peak(lon[:, -1]))
    else:
        for k in (
            'peak_twist_apex_deg',
            'peak_twist_base_deg',
            'peak_sa_radius_change_mm',
            'peak_base_longitudinal_mm',
        ):
            key[k] = None
    return key


def _add_twist_span(out: dict, ph: list, pos: np.ndarray, twist_span) -> None:
    """
    Add where twist is measured, and which twist keys come from levels no SA slice measured.

    Parameters
    ----------
    out : dict
        :func:`summarize`'s result so far; gets ``twist_measured_levels``,
        ``twist_extrapolated`` and ``key["extrapolated"]``.
    ph : list of PhaseMetrics
        The phases present.
    pos : ndarray
        Level positions (:func:`level_table`).
    twist_span : tuple of float or None
        As :func:`summarize`'s (None: no SA slice measured twist).

    """
    levels = max((p.level_position.size for p in ph), default=0)
    out['twist_measured_levels'] = None if twist_span is None else [_f(v) for v in twist_span]
    out['twist_extrapolated'] = twist_extrapolation_note(twist_span, levels) if levels else ''
    outside = levels_outside(pos, twist_span, levels) if pos.size else np.zeros(0, bool)
    ends = {
        'peak_twist_apex_deg': bool(outside[:1].any()),
        'peak_twist_base_deg': bool(outside[-1:].any()),
    }
    ends['peak_torsion_deg_per_cm'] = twist_span is None or any(ends.values())
    out['key']['extrapolated'] = sorted(k for k, v in ends.items() if v)


def _add_strain(out: dict, ph: list) -> None:
    """
    Add the peak segment strains, the segment findings and the peak global strains.

    Parameters
    ----------
    out : dict
        :func:`summarize`'s result so far; gets ``peak_segment_strain``, ``segment_findings``
        and ``key``'s ``peak_global_err/ecc/ell`` (None without strain) and
        ``akinetic_segments`` / ``dyskinetic_segments``.
    ph : list of PhaseMetrics
        The phases present.

    """
    key = out['key']
    seg = peak_segment_strain(ph)
    for c in ('err', 'ecc', 'ell'):
        key[f'peak_global_{c}'] = None
    if seg is None:
        return
    out['peak_segment_strain'] = {k: [_f(x) for x in v] for k, v in seg.items()}
    found = segment_findings(ph)
    out['segment_findings'] = found.to_dict()
    out['segment_findings']['segment_origin'] = segment_origin_note(ph)
    for kind in ('akinetic', 'dyskinetic'):
        key[f'{kind}_segments'] = found.abnormal((kind,))
    for c in ('err', 'ecc', 'ell'):
        g = []
        for p in ph:
            if not p.has_strain:
                continue
            v = getattr(p, f'segment_{c}')
            w = p.segment_count if p.segment_count.size == 17 else np.ones(17)
            g.append(float(v @ w / w.sum()) if w.sum() > 0 else math.nan)
        key[f'peak_global_{c}'] = _f(signed_peak(g))


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    return str(o)


def _clean(o):
    """Replace NaN/inf floats by None recursively (strict JSON)."""
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    if isinstance(o, (float, np.floating)):
        return float(o) if math.isfinite(o) else None
    return o


def write_summary_json(path, summary: dict) -> Path:
    """Write ``summary`` as strict JSON (NaN → null), UTF-8, indented; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(
        json.dumps(_clean(summary), indent=1, default=_json_default, allow_nan=False),
        encoding='utf-8',
    )
    return path
