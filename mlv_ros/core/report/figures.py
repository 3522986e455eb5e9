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
Matplotlib figures in the spirit of the paper's Fig. 9–16 (Agg, no pyplot state).

Every function takes arrays / :class:`PhaseMetrics` lists and writes one PNG; they never
recompute motion from images. Units: mm, degrees, ml, time as a fraction of the cycle (as in
the paper). Sign conventions are those of :mod:`mlv_ros.core.analysis`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib
from matplotlib import cm, colors
from matplotlib.figure import Figure
from mlv_ros.core.analysis.findings import segment_findings
from mlv_ros.core.analysis.frame import LVFrame
from mlv_ros.core.analysis.motion import decompose_displacement
from mlv_ros.core.report.summary import level_table, peak_segment_strain, RunData, sorted_phases
from mlv_ros.core.types import SEGMENT_ORIGIN_CODES
import numpy as np

DPI = 110
_MAX_SCATTER = 4000  # points drawn per 3D panel (deterministic subsample beyond this)
_COMPONENTS = (
    ('longitudinal', 'long-axis displacement (mm, + toward base)'),
    ('radial', 'radial displacement (mm, + outward)'),
    ('circumferential', 'circumferential displacement (mm, + CCW from apex)'),
)


def _save(fig: Figure, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI)
    return path


def _time(phases) -> np.ndarray:
    return np.array([p.time_fraction for p in phases], dtype=np.float64)


def _gapped(phases, t, values):
    """
    Return ``t`` and ``values`` with a NaN row after each missing phase index.

    ``values``' first axis is the phases; a failed phase is left out of the report, so a line
    breaks there instead of bridging it.
    """
    idx = [int(p.phase_index) for p in phases]
    v = np.asarray(values, dtype=np.float64)
    cut = [k + 1 for k in range(len(idx) - 1) if idx[k + 1] - idx[k] > 1]
    if not cut:
        return t, v
    gap = np.full((1, *v.shape[1:]), np.nan)
    return (
        np.insert(np.asarray(t, np.float64), cut, np.nan),
        np.concatenate(
            [
                np.concatenate([piece, gap]) if k < len(cut) else piece
                for k, piece in enumerate(np.split(v, cut))
            ]
        ),
    )


def plot_displacement_3d(
    ed_positions,
    es_positions,
    frame: LVFrame,
    path,
    *,
    title: str = '',
    compare: tuple | None = None,
) -> Path:
    """
    3D particles at ES coloured by each displacement component (Fig. 9b–d / 10b–d).

    Parameters
    ----------
    ed_positions, es_positions : array_like, shape (N, 3)
        Same particles at ED and ES, mm.
    frame : LVFrame
        ED frame used for the decomposition; the plot is drawn in frame coordinates
        (ξ along the reference direction, η, long axis up).
    path : path-like
        PNG to write.
    title : str
        Row label (e.g. "normal").
    compare : (ed, es, frame, title), optional
        A second run drawn as a second row with the same colour limits per component.

    """
    rows = [(ed_positions, es_positions, frame, title)]
    if compare is not None:
        rows.append(compare)
    data = []
    for X, x, fr, t in rows:
        X = np.asarray(X, dtype=np.float64)
        x = np.asarray(x, dtype=np.float64)
        d = decompose_displacement(X, x, fr)
        keep = np.arange(len(x))
        if len(x) > _MAX_SCATTER:
            keep = np.linspace(0, len(x) - 1, _MAX_SCATTER).astype(int)
        loc = np.c_[fr.inplane(x[keep]), fr.axial(x[keep])]
        data.append((loc, d[keep], t))
    lim = [max(float(np.max(np.abs(dd[:, j]))) for _, dd, _ in data) or 1.0 for j in range(3)]
    fig = Figure(figsize=(15, 4.8 * len(rows)), layout='constrained')
    for r, (loc, d, t) in enumerate(data):
        for j, (name, label) in enumerate(_COMPONENTS):
            ax = fig.add_subplot(len(rows), 3, 3 * r + j + 1, projection='3d')
            sc = ax.scatter(
                loc[:, 0],
                loc[:, 1],
                loc[:, 2],
                c=d[:, j],
                cmap='coolwarm',
                s=4,
                vmin=-lim[j],
                vmax=lim[j],
                depthshade=False,
            )
            ax.set_xlabel('ξ (mm)')
            ax.set_ylabel('η (mm)')
            ax.set_zlabel('long axis (mm)')
            ax.set_title(f'{t}: {name} at ES' if t else f'{name} at ES', fontsize=10)
            fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.12, label=label)
    fig.suptitle(
        'Displacement components at end-systole relative to end-diastole (cf. paper Fig. 9–10)'
    )
    return _save(fig, path)


def _shade_degraded(ax, phases, t) -> bool:
    """
    Draw grey bands behind the phases whose verdict is degraded; True if there were any.

    Failed phases are never passed in.
    """
    flagged = [k for k, p in enumerate(phases) if int(getattr(p, 'verdict', 0)) == 1]
    half = 0.5 * float(np.median(np.diff(t))) if len(t) > 1 else 0.02
    for k in flagged:
        ax.axvspan(t[k] - half, t[k] + half, color='0.85', zorder=0, lw=0)
    return bool(flagged)


def plot_level_curves(runs: Sequence[RunData], path) -> Path:
    """
    Per-level curves over the cycle (Fig.

    11–16): average SA radius, long-axis motion and twist angle; one column per run, one line per
    level (apex dark → base light).
    """
    quantities = (
        ('sa_radius_mm', 'average SA radius (mm)'),
        ('longitudinal_displacement_mm', 'long-axis motion (mm, + toward base)'),
        ('twist_deg', 'twist (°, + CCW from apex)'),
    )
    fig = Figure(figsize=(6.2 * len(runs) + 1.5, 10), layout='constrained')
    axes = fig.subplots(3, len(runs), squeeze=False, sharex=True)
    for j, run in enumerate(runs):
        ph, _ = sorted_phases(run.phases)
        t = _time(ph)
        for i, (name, ylabel) in enumerate(quantities):
            ax = axes[i, j]
            pos, table = level_table(ph, name)
            if _shade_degraded(ax, ph, t) and i == 0:
                ax.text(
                    0.01,
                    0.98,
                    'grey: degraded phases (use with care)',
                    transform=ax.transAxes,
                    va='top',
                    fontsize=7,
                    color='0.3',
                )
            cmap = cm.viridis
            tg, tab = _gapped(ph, t, table) if pos.size else (t, table)
            for k, h in enumerate(pos):
                ax.plot(tg, tab[:, k], marker='.', ms=3, color=cmap(h), label=f'{h:.2f}')
            ax.set_ylabel(ylabel)
            ax.grid(alpha=0.3)
            if i == 0:
                ax.set_title(run.label)
            if i == 2:
                ax.set_xlabel('time (fraction of cardiac cycle)')
            if not pos.size:
                ax.text(0.5, 0.5, 'no per-level data', ha='center', transform=ax.transAxes)
        for i in range(3):  # share y per quantity across runs so differences read directly
            lo = min(a.get_ylim()[0] for a in axes[i])
            hi = max(a.get_ylim()[1] for a in axes[i])
            for a in axes[i]:
                a.set_ylim(lo, hi)
    handles, labels = axes[0, -1].get_legend_handles_labels()
    if handles:
        fig.legend(
            handles,
            labels,
            title='level\n(0 apex,\n1 base)',
            loc='outside right center',
            fontsize=8,
        )
    fig.suptitle('Per-level motion over the cardiac cycle (cf. paper Fig. 11–16)')
    return _save(fig, path)


def plot_global_curves(runs: Sequence[RunData], path) -> Path:
    """Cavity volume, LA radius and torsion over the cycle; one line per run."""
    fig = Figure(figsize=(15, 4.2), layout='constrained')
    axes = fig.subplots(1, 3)
    specs = (
        ('cavity_volume_ml', 'cavity volume (ml)'),
        ('la_radius_mm', 'LA radius (mm)'),
        ('torsion_deg_per_cm', 'torsion (°/cm, base − apex)'),
    )
    for run, style in zip(runs, ('-o', '--s', ':^', '-.v')):
        ph, _ = sorted_phases(run.phases)
        t = _time(ph)
        for ax, (name, _) in zip(axes, specs):
            _shade_degraded(ax, ph, t)
            v = np.array([getattr(p, name) for p in ph], dtype=np.float64)
            lab = run.label
            if name == 'cavity_volume_ml' and len(v) and v[0] > 0:
                lab = f'{run.label} (EF {100 * (v[0] - v.min()) / v[0]:.0f} %)'
            ax.plot(*_gapped(ph, t, v), style, ms=4, label=lab)
    for ax, (_, ylabel) in zip(axes, specs):
        ax.set_xlabel('time (fraction of cardiac cycle)')
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle('Global function over the cardiac cycle')
    return _save(fig, path)


# AHA bull's-eye: rings from the centre: apex (17), apical, mid, basal. Display seen from the
# apex: anterior at the top, septum on the left; ψ (from the anterior RV–LV insertion, CCW from
# the apex) maps to the display angle 90° + (ψ − 330°), so segment 1 (ψ 300–360°) is centred
# on the top and segments run counter-clockwise on the page.
def _aha_wedges():
    wedges = []
    for ring, first in ((3, 1), (2, 7)):  # basal outermost
        for i in range(6):
            psi0 = (300 + 60 * i) % 360
            wedges.append((first + i, ring, psi0, 60.0))
    for i in range(4):
        wedges.append((13 + i, 1, (285 + 90 * i) % 360, 90.0))
    return wedges


def _bullseye_frame(ax, title: str = '') -> None:
    ax.set_ylim(0, 4)
    ax.set_axis_off()
    ax.text(np.pi / 2, 4.35, 'anterior', ha='center', fontsize=7)
    ax.text(np.pi, 4.45, 'septal', ha='center', va='center', rotation=90, fontsize=7)
    ax.text(-np.pi / 2, 4.4, 'inferior', ha='center', va='center', fontsize=7)
    ax.text(0, 4.45, 'lateral', ha='center', va='center', rotation=-90, fontsize=7)
    if title:
        ax.set_title(title, fontsize=10, pad=14)


def draw_bullseye(ax, values, *, vlim: float | None = None, title: str = '', cmap='coolwarm'):
    """
    Draw a 17-segment AHA bull's-eye on a polar Axes.

    Parameters
    ----------
    ax : matplotlib polar Axes
        Axes to draw on.
    values : array_like, shape (17,)
        Segment values in AHA order; NaN segments are drawn grey and labelled "n/a".
    vlim : float, optional
        Symmetric colour limit (default max |value|).
    title : str
        Panel title (none when empty).
    cmap : str or Colormap
        Diverging colour map (default ``'coolwarm'``).

    Returns
    -------
    ScalarMappable for a colorbar.

    """
    v = np.asarray(values, dtype=np.float64)
    if v.shape != (17,):
        raise ValueError(f"bull's-eye needs 17 values, got {v.shape}")
    fin = v[np.isfinite(v)]
    vlim = vlim or (float(np.max(np.abs(fin))) if fin.size else 1.0) or 1.0
    norm = colors.Normalize(-vlim, vlim)
    cmap = matplotlib.colormaps[cmap] if isinstance(cmap, str) else cmap

    def colour(x):
        return cmap(norm(x)) if np.isfinite(x) else (0.85, 0.85, 0.85, 1.0)

    for seg, ring, psi0, width in _aha_wedges():
        ang0 = np.radians(90.0 + psi0 - 330.0)
        w = np.radians(width)
        ax.bar(
            ang0 + w / 2,
            1.0,
            width=w,
            bottom=ring,
            color=colour(v[seg - 1]),
            edgecolor='k',
            lw=0.8,
        )
        txt = 'n/a' if not np.isfinite(v[seg - 1]) else f'{v[seg - 1]:.2f}'
        ax.text(ang0 + w / 2, ring + 0.5, f'{seg}\n{txt}', ha='center', va='center', fontsize=6.5)
    ax.bar(0, 1.0, width=2 * np.pi, bottom=0, color=colour(v[16]), edgecolor='none')
    ring = np.linspace(0, 2 * np.pi, 181)
    ax.plot(ring, np.ones_like(ring), color='k', lw=0.8)
    ax.text(
        0,
        0,
        f'17\n{"n/a" if not np.isfinite(v[16]) else f"{v[16]:.2f}"}',
        ha='center',
        va='center',
        fontsize=6.5,
    )
    _bullseye_frame(ax, title)
    return cm.ScalarMappable(norm=norm, cmap=cmap)


#: Colours of the wall-motion classes (bull's-eye of findings): normal white, worsening to red;
#: indeterminate hatched grey (no class claimed).
CLASS_COLOURS = {
    'normal': '#ffffff',
    'hypokinetic': '#f6d55c',
    'akinetic': '#ed7d31',
    'dyskinetic': '#c00000',
    'indeterminate': '#d0d0d0',
}
#: Edge colour of a segment the ES phase's tag data do not support (cross-hatched, "unsupported").
UNSUPPORTED_EDGE = '#c00000'
#: Added to a wall-motion panel's title when the segments are placed by the anatomical prior.
PRIOR_NAMES_NOTE = '\nsegment names uncertain: no RV found, septum from the anatomical prior'


def draw_class_bullseye(ax, classes, labels=None, *, title: str = '', unsupported=()):
    """
    Draw the 17 segments' wall-motion classes on a polar Axes (layout of :func:`draw_bullseye`).

    Parameters
    ----------
    ax : matplotlib polar Axes
        Axes to draw on.
    classes : sequence of str, length 17
        Class per segment (AHA order), keys of :data:`CLASS_COLOURS`.
    labels : sequence of str, length 17, optional
        Text under each segment's number (default the class's first four letters).
    title : str
        Panel title (none when empty).
    unsupported : sequence of int, optional
        AHA segments (1–17) the ES phase's tag data do not support
        (:attr:`~mlv_ros.core.analysis.findings.Findings.unsupported`): cross-hatched with a
        red edge.

    """
    if len(classes) != 17:
        raise ValueError(f"bull's-eye needs 17 classes, got {len(classes)}")
    labels = list(labels) if labels is not None else [c[:4] for c in classes]
    carried = {int(k) for k in unsupported}

    def paint(seg, theta, width, bottom):
        c = classes[seg - 1]
        ax.bar(
            theta,
            1.0,
            width=width,
            bottom=bottom,
            color=CLASS_COLOURS.get(c, '#d0d0d0'),
            edgecolor='k',
            lw=0.8,
            hatch='xx' if seg in carried else '//' if c == 'indeterminate' else None,
        )
        if seg in carried:
            ax.bar(
                theta, 1.0, width=width, bottom=bottom, fill=False, edgecolor=UNSUPPORTED_EDGE,
                lw=1.6,
            )

    for seg, ring, psi0, width in _aha_wedges():
        ang0 = np.radians(90.0 + psi0 - 330.0)
        w = np.radians(width)
        paint(seg, ang0 + w / 2, w, ring)
        ax.text(
            ang0 + w / 2,
            ring + 0.5,
            f'{seg}\n{labels[seg - 1]}',
            ha='center',
            va='center',
            fontsize=6,
        )
    paint(17, 0, 2 * np.pi, 0)
    ax.text(0, 0, f'17\n{labels[16]}', ha='center', va='center', fontsize=6)
    _bullseye_frame(ax, title)


def plot_segment_findings(runs: Sequence[RunData], path) -> Path | None:
    """
    Draw the bull's-eye of the wall-motion class per AHA segment, one panel per run.

    Each segment is labelled with its class and function index ``f ± σ_f`` (share of the heart's
    own function, :mod:`mlv_ros.core.analysis.findings`). A run whose segments are placed by the
    anatomical prior (no RV found: ``segment_origin`` 1) says in its panel title that the names
    are uncertain: the classes are the heart's, the ring's rotation is not tied to its septum.
    None (nothing written) when no run carries strain.
    """
    panels = []
    for run in runs:
        ph = [p for p in sorted_phases(run.phases)[0] if p.has_strain]
        if ph:
            origin = int(getattr(ph[-1], 'segment_origin', 0))
            panels.append((run.label, segment_findings(ph), origin))
    if not panels:
        return None
    fig = Figure(figsize=(5.2 * len(panels) + 2.2, 5.6), layout='constrained')
    for j, (lab, f, origin) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), j + 1, projection='polar')
        labels = [
            ('unsup.' if k + 1 in f.unsupported else f'{c[:4]}')
            + (f'\n{fi:+.2f}±{si:.2f}' if np.isfinite(fi) and np.isfinite(si) else '')
            for k, (c, fi, si) in enumerate(zip(f.classes, f.function_index, f.function_unc))
        ]
        es = 'no systolic phase yet' if f.es_phase is None else f'ES phase {f.es_phase}'
        draw_class_bullseye(
            ax,
            f.classes,
            labels,
            title=f'{lab}: wall motion at ES ({es})'
            + (PRIOR_NAMES_NOTE if origin == SEGMENT_ORIGIN_CODES['prior'] else ''),
            unsupported=f.unsupported,
        )
    from matplotlib.patches import Patch

    fig.legend(
        handles=[
            Patch(
                facecolor=c, edgecolor='k', hatch='//' if n == 'indeterminate' else None, label=n
            )
            for n, c in CLASS_COLOURS.items()
        ]
        + [
            Patch(
                facecolor=CLASS_COLOURS['indeterminate'],
                edgecolor=UNSUPPORTED_EDGE,
                hatch='xx',
                label='unsupported: the\nES tag data lost\nthis sector',
            )
        ],
        loc='outside right center',
        fontsize=8,
    )
    fig.suptitle(
        "Regional wall motion by AHA segment\n(f = share of the heart's own function ± σ)",
        fontsize=10,
    )
    return _save(fig, path)


def plot_strain_bullseyes(runs: Sequence[RunData], path) -> Path | None:
    """
    Draw peak Err, Ecc, Ell by AHA segment (signed peak over the cycle), one row per run.

    The colour scale of each strain component is shared across runs. Returns None (and writes
    nothing) when no run carries strain.
    """
    peaks = [(run.label, peak_segment_strain(sorted_phases(run.phases)[0])) for run in runs]
    peaks = [(lab, p) for lab, p in peaks if p is not None]
    if not peaks:
        return None
    comps = (
        ('err', 'peak Err (radial)'),
        ('ecc', 'peak Ecc (circumferential)'),
        ('ell', 'peak Ell (longitudinal)'),
    )
    fig = Figure(figsize=(13, 4.6 * len(peaks)), layout='constrained')
    for j, (c, name) in enumerate(comps):
        allv = np.concatenate([p[c] for _, p in peaks])
        allv = allv[np.isfinite(allv)]
        vlim = float(np.max(np.abs(allv))) if allv.size else 1.0
        for r, (lab, p) in enumerate(peaks):
            ax = fig.add_subplot(len(peaks), 3, 3 * r + j + 1, projection='polar')
            sm = draw_bullseye(ax, p[c], vlim=vlim or 1.0, title=f'{lab}: {name}')
            fig.colorbar(sm, ax=ax, shrink=0.7, label='Green–Lagrange strain (–)')
    fig.suptitle(
        'Peak Lagrangian strain by AHA segment (seen from the apex; negative = shortening)'
    )
    return _save(fig, path)
