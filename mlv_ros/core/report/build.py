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
One-page report of a run (optionally against a second run).

PNG figures, summary.json and index.html, built from arrays only (the lead feeds it from recorded
MCAP runs).

Missing data never raises: whatever cannot be drawn is listed under "Missing / not shown" on
the page and in ``summary.json`` (``runs[i].missing`` and ``figures_skipped``).
"""

from __future__ import annotations

from dataclasses import replace
import html
import logging
from pathlib import Path
from typing import Mapping, Sequence

from mlv_ros.core.analysis.frame import as_points, estimate_frame
from mlv_ros.core.report.figures import (
    plot_displacement_3d,
    plot_global_curves,
    plot_level_curves,
    plot_segment_findings,
    plot_strain_bullseyes,
)
from mlv_ros.core.report.summary import RunData, sorted_phases, summarize, write_summary_json
from mlv_ros.core.verdict import DEGRADED, FAILED
import numpy as np

log = logging.getLogger(__name__)

CONVENTIONS = [
    'Positions in DICOM patient coordinates (mm); all motion relative to end-diastole (phase 0).',
    'Levels are material bins of the ED long axis: 0 = apex, 1 = base.',
    'Twist and circumferential displacement: counter-clockwise seen from the apex is positive.',
    'Long-axis displacement positive toward the base; radial positive outward.',
    'Torsion = (twist_base − twist_apex) / ED distance, °/cm (negative for a normal heart).',
    'LA radius = axial distance from the ED apex to the particle centroid (paper: model centre '
    'to apex).',
    'Strain: Green–Lagrange E = ½(FᵀF − I), negative = shortening; peak = largest magnitude '
    'over the cycle.',
    "Bull's-eye seen from the apex: anterior at the top, septum on the left (AHA 17 segments).",
    "Wall motion per segment at end-systole relative to the heart's own median function (f = 1 "
    'as the rest, '
    '0 still, < 0 the wrong way): normal f ≥ 0.6, hypokinetic 0.35–0.6, akinetic −0.2–0.35, '
    'dyskinetic '
    'f < −0.2 or stretching (Ecc > 0, Err < 0) beyond 2σ; indeterminate when σ_f > 0.33 or too '
    'few '
    'particles (mlv_ros/core/analysis/findings.py).',
]

_KEY_ROWS = (
    ('edv_ml', 'EDV (ml)', '{:.1f}'),
    ('esv_ml', 'ESV (ml)', '{:.1f}'),
    ('ejection_fraction', 'ejection fraction (%)', 'pct'),
    ('es_time_fraction', 'end-systole (fraction of cycle)', '{:.2f}'),
    ('peak_twist_apex_deg', 'peak apical twist (°)', '{:+.1f}'),
    ('peak_twist_base_deg', 'peak basal twist (°)', '{:+.1f}'),
    ('peak_torsion_deg_per_cm', 'peak torsion (°/cm)', '{:+.2f}'),
    ('peak_sa_radius_change_mm', 'peak mean SA radius change (mm)', '{:+.2f}'),
    ('peak_base_longitudinal_mm', 'peak basal long-axis motion (mm)', '{:+.2f}'),
    ('la_radius_ed_mm', 'LA radius at ED (mm)', '{:.1f}'),
    ('la_radius_es_mm', 'LA radius at ES (mm)', '{:.1f}'),
    ('peak_global_err', 'peak global Err', '{:+.3f}'),
    ('peak_global_ecc', 'peak global Ecc', '{:+.3f}'),
    ('peak_global_ell', 'peak global Ell', '{:+.3f}'),
)


def _get_positions(positions_by_phase, index: int):
    if positions_by_phase is None:
        return None
    if isinstance(positions_by_phase, Mapping):
        return positions_by_phase.get(index)
    if isinstance(positions_by_phase, Sequence) and 0 <= index < len(positions_by_phase):
        return positions_by_phase[index]
    return None


def _es_view(run: RunData, summary: dict, notes: list[str]):
    """(X_ed, x_es, frame, title) for the 3D figure, or None with a note saying why not."""
    if run.ed_positions is None:
        notes.append(f'{run.label}: no ED positions, 3D displacement figure not drawn')
        return None
    ph, _ = sorted_phases(run.phases)
    vol = {p.phase_index: p.cavity_volume_ml for p in ph}
    es = summary['key'].get('es_phase_index')
    cand = [
        i
        for i in sorted(vol, key=lambda i: vol[i])
        if i != 0 and _get_positions(run.positions_by_phase, i) is not None
    ]
    if es is None or _get_positions(run.positions_by_phase, es) is None:
        if not cand:
            notes.append(
                f'{run.label}: no positions for end-systole or any later phase, 3D figure not '
                'drawn'
            )
            return None
        notes.append(
            f'{run.label}: no positions for the ES phase {es}; 3D figure shows phase {cand[0]} '
            '(smallest volume with positions)'
        )
        es = cand[0]
    try:
        X = as_points(run.ed_positions, f'{run.label} ED positions')
        x = as_points(
            _get_positions(run.positions_by_phase, es), f'{run.label} positions of phase {es}'
        )
        if X.shape != x.shape:
            raise ValueError(
                f'ED positions {X.shape} and phase {es} positions {x.shape} differ in shape'
            )
        frame = run.frame
        if frame is None:
            frame = estimate_frame(X)
            notes.append(
                f'{run.label}: no LV frame given, estimated from the ED cloud (reference angle '
                'arbitrary)'
            )
    except ValueError as e:
        notes.append(f'{run.label}: 3D figure not drawn: {e}')
        return None
    return X, x, frame, f'{run.label} (phase {es})'


def _fmt(v, f: str) -> str:
    if v is None:
        return '—'
    if f == 'pct':
        return f'{100 * v:.1f}'
    return f.format(v)


def _pm(v, u) -> str:
    if v is None:
        return '—'
    return f'{v:+.3f}' + (f' ± {u:.3f}' if u is not None else '')


def _findings_html(summaries: list[dict]) -> str:
    """One table per run: class, function index and ES / peak strain ± uncertainty per segment."""
    e = html.escape
    parts = []
    for s in summaries:
        f = s.get('segment_findings')
        if not f:
            parts.append(f'<p>{e(s["label"])}: no strain, no regional findings.</p>')
            continue
        carried = set(f.get('unsupported') or ())
        tagged = set(f.get('from_tags') or ())
        possible = set(f.get('possibly_akinetic') or ())
        rows = ''.join(
            f'<tr><td>{r["segment"]} {e(r["name"])}</td><td>{e(r["class"])}'
            + (' (unsupported)' if r['segment'] in carried else '')
            + (' (from its tags)' if r['segment'] in tagged else '')
            + (' (or akinetic)' if r['segment'] in possible else '')
            + '</td>'
            f'<td>{e(_pm(r["function_index"], r["function_unc"]))}</td>'
            + ''.join(
                f'<td>{e(_pm(r[f"es_{c}"], r[f"es_{c}_unc"]))}</td>' for c in ('ecc', 'err', 'ell')
            )
            + ''.join(
                f'<td>{e(_pm(r[f"peak_{c}"], r[f"peak_{c}_unc"]))}</td>'
                for c in ('ecc', 'err', 'ell')
            )
            + '</tr>'
            for r in _clean_rows(f['segments'])
        )
        origin = f.get('segment_origin') or {}
        parts.append(
            f'<p><b>{e(s["label"])}</b>: ES phase {f["es_phase"]}; classes '
            + e(', '.join(f'{k} {n}' for k, n in f['counts'].items() if n))
            + (
                f'; unsupported at ES (the tag data lost their sector, the model carried them '
                f'with their neighbours): {e(", ".join(map(str, sorted(carried))))}'
                if carried
                else ''
            )
            + (
                '; classed from their own tag tracks (the model carried them with their '
                'neighbours; the tags show less shortening): '
                + e(', '.join(map(str, sorted(tagged))))
                if tagged
                else ''
            )
            + (
                f'. {"<b>Segment names uncertain</b>: " if origin.get("names_uncertain") else ""}'
                f'Segments: {e(origin["note"])}.'
                if origin.get('note')
                else ''
            )
            + (
                f'. <b>{e(f["global_function"].capitalize())}</b>'
                if f.get('global_function') == 'globally hypokinetic'
                else ''
            )
            + ''.join(f'. {e(n)}' for n in f.get('notes', ()))
            + '</p>'
            '<table><tr><th>segment</th><th>class</th><th>f ± σ</th><th>ES Ecc</th><th>ES Err</th>'
            '<th>ES Ell</th><th>peak Ecc</th><th>peak Err</th><th>peak '
            f'Ell</th></tr>{rows}</table>'
        )
    return ''.join(parts)


def _extrapolated(summary: dict, key: str) -> str:
    """Return ' (extrapolated)' for a twist no SA slice measured (see the note below the table)."""
    return ' (extrapolated*)' if key in summary['key'].get('extrapolated', ()) else ''


def _clean_rows(rows: list[dict]) -> list[dict]:
    """Replace NaN with None in the findings rows (so they print as —)."""
    return [
        {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in r.items()}
        for r in rows
    ]


# The report's style sheet.
_STYLE = """body { font-family: sans-serif; margin: 1.5em auto; max-width: 1500px; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1em; }
td, th { border: 1px solid #bbb; padding: 3px 10px; text-align: right; }
td:first-child { text-align: left; }
figure { margin: 1em 0; } img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #555; }
.missing { background: #fff6e0; padding: 0.3em 1em; border-left: 4px solid #e0a000; }
.verdict { background: #fde8e8; padding: 0.3em 1em; border-left: 4px solid #c00000; }
"""


def _html(
    title: str,
    meta: dict,
    summaries: list[dict],
    figures: list[tuple[str, str]],
    skipped: list[str],
) -> str:
    """Return the report's index.html: key numbers, findings, what is missing, figures."""
    e = html.escape
    head = ''.join(f'<th>{e(s["label"])}</th>' for s in summaries)
    rows = _key_rows(summaries)
    notes = [
        f'* {s["label"]}: {s["twist_extrapolated"]}'
        for s in summaries
        if s.get('twist_extrapolated')
    ]
    twist_html = (
        '<div class="missing"><ul>' + ''.join(f'<li>{e(n)}</li>' for n in notes) + '</ul></div>'
        if notes
        else ''
    )
    miss = [f'{s["label"]}: {m}' for s in summaries for m in s['missing']] + skipped
    miss_html = (
        ('<ul>' + ''.join(f'<li>{e(m)}</li>' for m in miss) + '</ul>')
        if miss
        else '<p>Nothing missing.</p>'
    )
    figs = (
        ''.join(
            f'<figure><img src="{e(f)}" alt="{e(c)}"><figcaption>{e(c)}</figcaption></figure>'
            for f, c in figures
        )
        or '<p>No figures could be drawn.</p>'
    )
    meta_html = ''.join(f'<li><b>{e(str(k))}</b>: {e(str(v))}</li>' for k, v in meta.items())
    banner = _verdict_banner(summaries)
    conv = ''.join(f'<li>{e(c)}</li>' for c in CONVENTIONS)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{e(title)}</title>
<style>
{_STYLE}</style></head><body>
<h1>{e(title)}</h1>
{banner}
<ul>{meta_html}</ul>
<h2>Key numbers</h2>
<table><tr><th></th>{head}</tr>{rows}</table>
{twist_html}
<h2>Regional findings (end-systole)</h2>{_findings_html(summaries)}
<h2>Missing / not shown</h2><div class="missing">{miss_html}</div>
<h2>Figures</h2>{figs}
<h2>Conventions</h2><ul>{conv}</ul>
<p><a href="summary.json">summary.json</a> holds every number of every phase.</p>
</body></html>
"""


def _key_rows(summaries: list[dict]) -> str:
    """Return the key-numbers table's rows: one per key number, one column per run."""
    e = html.escape
    rows = ''.join(
        f'<tr><td>{e(lab)}</td>'
        + ''.join(
            f'<td>{e(_fmt(s["key"].get(k), f))}{_extrapolated(s, k)}</td>' for s in summaries
        )
        + '</tr>'
        for k, lab, f in _KEY_ROWS
    )
    rows += (
        '<tr><td>phases present / expected</td>'
        + ''.join(f'<td>{len(s["phases_present"])} / {s["num_phases"]}</td>' for s in summaries)
        + '</tr>'
    )
    return rows


def _verdict_banner(summaries: list[dict]) -> str:
    """Return the report's red banner listing every failed or degraded phase ('' if none)."""
    e = html.escape
    flagged = [
        f'<li><b>{e(s["label"])} phase {p} {word}</b>: {e(why)}</li>'
        for s in summaries
        for key, word in (
            ('phases_failed', 'failed (not plotted)'),
            ('phases_degraded', 'degraded (use with care)'),
        )
        for p, why in sorted((s.get(key) or {}).items())
    ]
    banner = (
        (
            '<div class="verdict"><b>Not every phase is a trustworthy '
            f'measurement.</b><ul>{"".join(flagged)}'
            '</ul></div>'
        )
        if flagged
        else ''
    )
    return banner


def _flagged_phases(run: RunData) -> dict:
    """Return ``phases_degraded`` / ``phases_failed``: phase index → reasons, of a run."""
    return {
        name: {
            int(p.phase_index): str(getattr(p, 'verdict_reasons', ''))
            for p in run.phases
            if int(getattr(p, 'verdict', 0)) == level
        }
        for level, name in ((DEGRADED, 'phases_degraded'), (FAILED, 'phases_failed'))
    }


def _figures(out: Path, runs: list, summaries: list) -> tuple[list, list]:
    """
    Draw the report's figures into ``out``; a figure that fails is named, never raised.

    Parameters
    ----------
    out : Path
        The report directory.
    runs : list of RunData
        The runs, failed phases left out.
    summaries : list of dict
        Their :func:`summarize` results.

    Returns
    -------
    figures : list of (str, str)
        File name and caption of each figure drawn.
    skipped : list of str
        Each figure not drawn, with why.

    """
    figures: list[tuple[str, str]] = []
    skipped: list[str] = []

    def attempt(name: str, caption: str, fn):
        try:
            p = fn()
        except Exception as exc:  # a figure must never take the report down; say why instead
            log.exception('report figure %s failed', name)
            skipped.append(f'{name} failed: {type(exc).__name__}: {exc}')
            return
        if p is not None:
            figures.append((Path(p).name, caption))

    with_phases = [r for r, s in zip(runs, summaries) if s['phases_present']]
    if with_phases:
        attempt(
            'level_curves.png',
            'Average SA radius, long-axis motion and twist per level over the cycle (cf. Fig. '
            '11–16).',
            lambda: plot_level_curves(with_phases, out / 'level_curves.png'),
        )
        attempt(
            'global_curves.png',
            'Cavity volume (with EF), LA radius and torsion over the cycle.',
            lambda: plot_global_curves(with_phases, out / 'global_curves.png'),
        )
        attempt(
            'strain_bullseye.png',
            "Peak Err / Ecc / Ell by AHA segment (bull's-eye seen from the apex).",
            lambda: plot_strain_bullseyes(with_phases, out / 'strain_bullseye.png'),
        )
        attempt(
            'segment_findings.png',
            'Wall motion by AHA segment at end-systole: normal / hypokinetic / akinetic / '
            'dyskinetic, indeterminate (hatched) where the data cannot tell, unsupported '
            "(cross-hatched, red edge) where the ES tag data lost the segment's sector; f = share "
            "of the heart's own function ± σ.",
            lambda: plot_segment_findings(with_phases, out / 'segment_findings.png'),
        )
    else:
        skipped.append('no phases in any run: no curves')
    views = []
    for r, s in zip(runs, summaries):
        v = _es_view(r, s, skipped) if s['phases_present'] else None
        if v is not None:
            views.append(v)
    if views:
        attempt(
            'displacement_es.png',
            'Particles at end-systole coloured by long-axis, radial and circumferential '
            'displacement (cf. Fig. 9–10).',
            lambda: plot_displacement_3d(
                *views[0][:3],
                out / 'displacement_es.png',
                title=views[0][3],
                compare=views[1] if len(views) > 1 else None,
            ),
        )
    return figures, skipped


def build_report(
    out_dir,
    phases: Sequence,
    ed_positions=None,
    positions_by_phase=None,
    compare=None,
    meta: dict | None = None,
    *,
    frame=None,
    twist_span=False,
) -> Path:
    """
    Write the report of a run (and optionally a comparison run) to ``out_dir``.

    Parameters
    ----------
    out_dir : path-like
        Created if needed; receives ``index.html``, ``summary.json`` and PNGs
        (``level_curves.png``, ``global_curves.png``, ``strain_bullseye.png``,
        ``displacement_es.png``), each only when it can be drawn.
    phases : sequence of PhaseMetrics
        The run's per-phase metrics (any order; gaps allowed).
    ed_positions : array_like, shape (N, 3), optional
        ED particle positions, mm.
    positions_by_phase : mapping or sequence, optional
        Phase index -> (N, 3) array, or a sequence indexed by phase: particle positions per
        phase (at least the ES phase is needed for the 3D figure).
    compare : RunData or sequence of PhaseMetrics, optional
        A second run (e.g. hypertrophic) shown side by side.
    meta : dict, optional
        Free-form description shown on the page and stored in summary.json; the keys
        ``title``, ``label`` and ``compare_label`` are used for headings.
    frame : LVFrame, optional
        ED frame of the main run (estimated from ``ed_positions`` if needed).
    twist_span : (float, float), None or False
        Levels of the main run its SA slices with tag points cross (see :class:`RunData`): twist
        numbers beyond them are marked extrapolated. False: not known.

    Returns
    -------
    Path
        ``out_dir / "index.html"``.

    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta = dict(meta or {})
    runs = [
        RunData(
            list(phases or []),
            ed_positions,
            positions_by_phase,
            frame,
            str(meta.get('label', 'run')),
            twist_span,
        )
    ]
    if compare is not None:
        if isinstance(compare, RunData):
            runs.append(compare)
        else:
            runs.append(RunData(list(compare), label=str(meta.get('compare_label', 'comparison'))))
    # A failed phase is not a measurement: it never enters a curve, a peak or a table; degraded
    # and failed phases are named at the top of the page with their reasons.
    verdicts = [_flagged_phases(r) for r in runs]
    runs = [
        replace(r, phases=[p for p in r.phases if int(getattr(p, 'verdict', 0)) < FAILED])
        for r in runs
    ]
    summaries = [summarize(r.phases, r.label, r.twist_span) | v for r, v in zip(runs, verdicts)]
    figures, skipped = _figures(out, runs, summaries)
    title = str(meta.get('title', 'LV motion report'))
    write_summary_json(
        out / 'summary.json',
        {
            'title': title,
            'meta': meta,
            'conventions': CONVENTIONS,
            'figures': [f for f, _ in figures],
            'figures_skipped': skipped,
            'runs': summaries,
            'frames': [r.frame.to_dict() if r.frame is not None else None for r in runs],
        },
    )
    index = out / 'index.html'
    index.write_text(_html(title, meta, summaries, figures, skipped), encoding='utf-8')
    return index
