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
Offline re-track and re-solve of a recorded run, with the code the nodes use.

Reads a run's recorded frames and registration (``run.mcap`` of ``mlv-ros run --dicom``),
tracks every slice again as the tag detector does (:class:`StreamingMasker` ED masks +
:class:`SliceTracker`, or :class:`LineSliceTracker` on a single-line study's slices), solves
every phase as the solver node does (:class:`MotionTracker` with the node's default parameters)
and scores the result against the study's ``groundtruth.json`` as ``bench/robustness.py``
does. A tracking or solving change can then be compared on the same
studies without the graph (seconds to a minute per study instead of minutes).

    python bench/retrack.py CASE_DIR [CASE_DIR ...]     # CASE_DIR holds run/run.mcap and study/

Prints one JSON line per case: ES median / p95 (mm), twist error (all levels and where SA slices
are), phases solved / degraded / failed, worst phase median, seconds, and the ES median / p95 3D
error of the worst AHA segment and of each abnormal one (the truth's segments,
``groundtruth.json`` ``regional``) with its tracks at ED and ES (:func:`segment_tracks`).

``--ideal`` replaces every tracked point by where the truth puts it (its ED material line, the
line through its ED position along the slice normal, crossing the image plane at that phase):
the same tracks, none of their tracking error. ``--ideal every-track`` also keeps every ED
track at every phase (a tracker that loses nothing). Solving those separates what the tracker
loses from what the solver does with perfect tag points. ``--ideal-segments K,...`` replaces
only the tracks whose ED point lies in those AHA segments (the truth's): whose tracking error
moves a segment's solved motion, its own tracks' or the rest's.

``--tracks`` adds the tracker's own error against the truth (:func:`track_errors`): per view at
ES, the tracks kept, the in-plane error of each reported point against its ED material line's
crossing, split radial / circumferential and pooled by ED wall quarter and AHA segment, and by
distance to the nearest true ES wall border in tag periods (``sa_border_bands``: how far the
points near the endo- and epicardium read toward mid-wall), and the median error per phase;
``--no-solve`` only tracks (seconds per study).

``--strain`` adds ``bench/strain.py``'s ES strain comparison and wall-motion findings
(:func:`strain_errors`) of the re-solved motion and, beside it, of the truth's motion of the same
particles: with ``--ideal`` it tells a strain error of the tracker (ideal points right) from one
of the solver (ideal points wrong) and from one of the analysis and its frame (truth motion
wrong).

``--phases`` adds, per phase, the median 3D error, the worst AHA segment (the truth's) and its
median error, and the solver's verdict with its reasons (:func:`phase_errors`): what the
verdicts in ``mlv_ros/core/verdict.py`` were calibrated on.

``--twist`` adds the ES twist per analysis level (:func:`twist_levels`): the solved and the
true twist, their difference, the levels the SA stack spans and each extrapolated level's
distance beyond it (its lever), and the same difference with the twist function alone (the
global stage and the twist function, no local stage), which separates what the extrapolation
does from what the local stage does to it.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import json
from pathlib import Path
import sys
import time

from mlv_msgs.msg import ModelState, TaggedFrame
from mlv_ros import bagio, conversions, qos
from mlv_ros.core.io.groundtruth import motion_from_groundtruth
from mlv_ros.core.registration.streaming import StreamingMasker
from mlv_ros.core.tags import LineSliceTracker, SliceTracker
from mlv_ros.core.tracking import MotionTracker
from mlv_ros.core.types import TAGS_GRID
from mlv_ros.core.verdict import FAILED, OK
from mlv_ros.recording import motion_accuracy
import numpy as np
from pipeline import recorded_tracker
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import PointCloud2
import yaml


def recorded(mcap: Path):
    """Frames in recorded order, the registered cloud and state."""
    frames, cloud, state = [], None, None
    for m in bagio.read_bag(
        mcap, topics=[qos.FRAMES, qos.REGISTERED_CLOUD, qos.REGISTERED_STATE], any_namespace=True
    ):
        if m.topic == qos.FRAMES:
            frames.append(
                conversions.msg_to_frame(
                    bagio.deserialize(m.data, TaggedFrame, m.missing), allow_nonfinite=True
                )
            )
        elif m.topic == qos.REGISTERED_CLOUD:
            cloud = conversions.msg_to_cloud(deserialize_message(m.data, PointCloud2))
        else:
            state = conversions.msg_to_model_state(
                bagio.deserialize(m.data, ModelState, m.missing)
            )
    return frames, cloud, state


def track(frames, **tracker_kwargs) -> dict:
    """``{phase: {(view, slice): TagPointSet}}`` as the tag detector node makes them."""
    masker, trackers, sets = StreamingMasker(), {}, {}
    pending: dict = {}
    for f in frames:
        masker.observe_geometry(f)
        key = (f.view, f.slice_index)
        pending.setdefault(key, []).append(f)
    # The node processes each slice's frames in phase order as they come; the masker has seen
    # every geometry by then only if the frames came slice-major, so observe them in order.
    for f in frames:
        key = (f.view, f.slice_index)
        mask = None
        if f.phase_index == 0 or key not in trackers:
            # As the tag detector node (its _tracker): a single-line study's slices (one family
            # or a line pair) are read by the line tracker, which takes no grid options.
            trackers[key] = (
                SliceTracker(f.geometry, **tracker_kwargs)
                if f.tag_lines == TAGS_GRID
                else LineSliceTracker(f.geometry, spacing_px=tracker_kwargs.get('spacing_px'))
            )
            mask, _ = masker.ed_mask(f)
        pts = trackers[key].update(f, mask=mask)
        sets.setdefault(int(f.phase_index), {})[key] = pts
    return sets


def solve(sets: dict, cloud, state, **solver_kwargs):
    """
    Solve every phase as the solver node does.

    Keywords MotionTracker does not take are set as its attributes (``prescreen``, ...). Returns
    the tracker, phase → positions and phase → (verdict level, reasons, RMS residual mm, degraded
    segments: ``ModelState.degraded_segments``; a phase not solved has no fourth entry).
    """
    import inspect

    known = inspect.signature(MotionTracker).parameters
    attrs = {k: solver_kwargs.pop(k) for k in list(solver_kwargs) if k not in known}
    tr = recorded_tracker(cloud, state, **solver_kwargs)
    for k, v in attrs.items():
        if not hasattr(tr, k):
            raise ValueError(f'MotionTracker has no parameter or attribute {k!r}')
        setattr(tr, k, v)
    for pts in sets.get(0, {}).values():
        tr.set_reference(pts)
    n = max(sets) + 1
    positions, verdicts = {0: tr.rest}, {}
    for p in range(1, n):
        try:
            sol = tr.solve(p, sets.get(p, {}), n)
        except ValueError as exc:
            verdicts[p] = (FAILED, f'not solved: {exc}', 0.0)
            continue
        positions[p] = sol.positions
        verdicts[p] = (
            sol.state.verdict,
            sol.state.verdict_reasons,
            sol.state.residual,
            sol.state.degraded_segments,
        )
    return tr, positions, verdicts


def ideal_targets(
    sets: dict,
    motion,
    reach_mm: float = 20.0,
    step_mm: float = 0.25,
    every_track: bool = False,
    segments=None,
) -> tuple[dict, int]:
    """
    Return ``sets`` with every tracked point moved to where the truth puts it.

    See the module docstring: the crossing of its ED material line ``p0 + s n`` with the image
    plane nearest ``s = 0`` within ±``reach_mm``, located to ``step_mm`` and interpolated linearly.
    Points whose line does not cross the plane within reach, and tracks without an ED point, keep
    their measured position. ``every_track``: every ED track at every phase (a tracker that loses
    nothing), those whose line does not cross left out. ``segments``: only the tracks whose ED
    point lies in these AHA segments (the truth's) move, the others keep their measured position
    (and are counted so); not with ``every_track``. Returns the new sets and how many points kept
    their measured position (or were left out).
    """
    from mlv_ros.core.sim.regional import truth_segments

    if segments is not None and every_track:
        raise ValueError('segments: only the tracked points move, not with every_track')
    ed = {
        key: dict(zip(map(int, pts.track_id), pts.position))
        for key, pts in sets.get(0, {}).items()
    }
    if segments is not None:
        ed = {
            key: {
                t: x
                for (t, x), sg in zip(
                    pts.items(), truth_segments(motion, np.array(list(pts.values())))
                )
                if int(sg) in set(segments)
            }
            if pts
            else pts
            for key, pts in ed.items()
        }
    s = np.arange(-reach_mm, reach_mm + 0.5 * step_mm, step_mm)
    out, kept = {0: sets.get(0, {})}, 0
    for phase, by_key in sets.items():
        if phase == 0:
            continue
        out[phase] = {}
        for key, pts in (sets[0] if every_track else by_key).items():
            new = copy.copy(pts)
            if every_track:
                new.phase_index = phase
            ref = ed.get(key, {})
            has = np.array([int(t) in ref for t in pts.track_id], dtype=bool)
            pos = np.array(pts.position, dtype=np.float64, copy=True)
            if has.any():
                n = pts.geometry.normal
                p0 = np.array([ref[int(t)] for t in pts.track_id[has]])
                line = motion.position(
                    (p0[:, None, :] + s[None, :, None] * n).reshape(-1, 3), phase
                ).reshape(len(p0), s.size, 3)
                f = (line - p0[:, None, :]) @ n  # signed distance to the plane, mm
                cross = np.diff(np.sign(f), axis=1) != 0
                j = np.argmin(np.where(cross, np.abs(s[:-1]), np.inf), axis=1)
                ok = cross[np.arange(len(p0)), j]
                r = np.arange(len(p0))
                a = (f[r, j] / np.where(ok, f[r, j] - f[r, j + 1], 1.0))[:, None]
                crossing = line[r, j] + a * (line[r, j + 1] - line[r, j])
                rows = np.flatnonzero(has)
                pos[rows[ok]] = crossing[ok]
                kept += int((~ok).sum())
            kept += int((~has).sum())
            new.position = pos
            if every_track and has.any() and not ok.all():
                new = _subset(new, np.flatnonzero(has)[ok])
            out[phase][key] = new
    return out, kept


def _subset(pts, rows):
    """``pts`` with only the points ``rows`` (every per-point array indexed alike)."""
    return dataclasses.replace(
        pts,
        pixel_rc=pts.pixel_rc[rows],
        position=pts.position[rows],
        track_id=pts.track_id[rows],
        confidence=pts.confidence[rows] if len(pts.confidence) else pts.confidence,
    )


def segment_errors(case: Path, rest, positions, motion) -> dict:
    """
    Return the ES median / p95 3D error (mm) of the worst and of each abnormal AHA segment.

    The worst is the AHA segment (the truth's) with the largest median, ``worst_segment``; each
    abnormal segment of the truth is ``segment_K_CLASS``, with ``segment_K_CLASS_rcl``: the median
    signed error (ours − truth, mm) along the truth's radial, circumferential and longitudinal
    directions (an akinetic sector pulled inward with its neighbours reads a negative radial one).
    """
    from mlv_ros.core.analysis.frame import cardiac_coordinates
    from mlv_ros.core.sim.regional import truth_frame, truth_segments

    gt = json.loads((case / 'study' / 'groundtruth.json').read_text()).get('regional') or {}
    es = int(gt.get('phase', -1))
    if es not in positions:
        return {}
    seg = truth_segments(motion, rest)
    vec = positions[es] - motion.position(rest, es)
    err = np.linalg.norm(vec, axis=1)
    cc = cardiac_coordinates(rest, truth_frame(motion))
    rcl = np.stack([np.einsum('na,na->n', vec, e) for e in (cc.e_r, cc.e_c, cc.e_l)], axis=1)

    def stats(k):
        return [
            round(float(np.median(err[seg == k])), 3),
            round(float(np.percentile(err[seg == k], 95)), 3),
        ]

    present = [k for k in range(1, 18) if np.any(seg == k)]
    worst = max(present, key=lambda k: float(np.median(err[seg == k])))
    return {
        'worst_segment': [worst, *stats(worst)],
        **{
            f'segment_{sg["segment"]}_{sg["class"]}{suffix}': value(sg['segment'])
            for sg in gt.get('segments', ())
            if sg['class'] != 'normal' and sg['segment'] in present
            for suffix, value in (
                ('', stats),
                ('_rcl', lambda k: np.round(np.median(rcl[seg == k], axis=0), 2).tolist()),
            )
        },
    }


def phase_errors(rest, positions, verdicts, motion) -> list:
    """
    Return each phase's error against the truth beside its verdict.

    Parameters
    ----------
    rest : ndarray, shape (N, 3)
        ED particle positions, mm.
    positions : dict
        Phase → solved positions, mm.
    verdicts : dict
        Phase → (verdict level, reasons, RMS residual mm[, degraded segments]), as :func:`solve`
        returns them.
    motion : LVMotion
        The study's true motion.

    Returns
    -------
    list
        Per phase ``[phase, median 3D error, worst AHA segment, its median error, verdict,
        reasons]`` (mm; the truth's segments; errors None where the phase was not solved).

    """
    from mlv_ros.core.sim.regional import truth_segments

    seg = truth_segments(motion, rest)
    out = []
    for p, (level, reasons, *_) in sorted(verdicts.items()):
        row = [int(p), None, None, None, int(level), reasons]
        if p in positions:
            err = np.linalg.norm(positions[p] - motion.position(rest, p), axis=1)
            med = {int(k): float(np.median(err[seg == k])) for k in np.unique(seg)}
            worst = max(med, key=med.get)
            row[1:4] = [round(float(np.median(err)), 3), worst, round(med[worst], 3)]
        out.append(row)
    return out


def segment_tracks(case: Path, sets: dict, motion) -> dict:
    """
    Return how many tracks each abnormal AHA segment (the truth's) holds at ED and at ES.

    ``segment_K_CLASS_tracks``: ``[SA at ED, SA at ES, LA at ED, LA at ES]``, the tracks whose ED
    point lies in segment K (the truth's segments of the ED positions), and ``sa_tracks_kept``:
    the share of SA ED tracks still reported at ES in the akinetic and dyskinetic segments and in
    the normal ones. The solver can
    follow a region only where tag points are; a tracker that ends the tracks of a region moving
    unlike its neighbours leaves that region to the neighbours' motion.
    """
    from mlv_ros.core.sim.regional import truth_segments

    gt = json.loads((case / 'study' / 'groundtruth.json').read_text()).get('regional') or {}
    es = int(gt.get('phase', -1))
    abnormal = [sg['segment'] for sg in gt.get('segments', ()) if sg['class'] != 'normal']
    if es not in sets or not abnormal:
        return {}
    count = {}  # (segment or 0 = elsewhere, view, phase) -> tracks
    for key, pts in sets[0].items():
        if not len(pts.track_id):
            continue
        seg = truth_segments(motion, np.asarray(pts.position))
        seg = np.where(np.isin(seg, abnormal), seg, 0)
        later = sets[es].get(key)
        alive = np.isin(pts.track_id, later.track_id if later is not None else ())
        for phase, keep in ((0, np.ones(seg.size, bool)), (es, alive)):
            for k in np.unique(seg):
                c = (int(k), int(key[0]) != TaggedFrame.VIEW_SA, phase)
                count[c] = count.get(c, 0) + int(np.sum(keep & (seg == k)))
    out = {}
    for sg in gt['segments']:
        k = sg['segment']
        if k in abnormal:
            out[f'segment_{k}_{sg["class"]}_tracks'] = [
                count.get((k, la, ph), 0) for la in (False, True) for ph in (0, es)
            ]

    still = {sg['segment'] for sg in gt['segments'] if sg['class'] in ('akinetic', 'dyskinetic')}

    def kept(segments):
        ed, now = (
            sum(v for (k, la, p), v in count.items() if p == ph and not la and k in segments)
            for ph in (0, es)
        )
        return round(now / ed, 2) if ed else None

    out['sa_tracks_kept'] = {'akinetic_dyskinetic': kept(still), 'normal_segments': kept({0})}
    return out


def track_errors(sets: dict, motion, period_mm: float | None = None) -> dict:
    """
    Return the tracker's own error against the truth, per track, at end-systole and per phase.

    Every reported point is compared with where the truth puts its track (its ED material line
    crossing the image plane, :func:`ideal_targets`); the in-plane error is split along the
    truth's radial and circumferential directions (cylindrical, about the true long axis, at the
    true position; radial positive outward) and pooled by the track's ED wall quarter (the
    truth's transmural depth ``(r − r_endo)/(r_epi − r_endo)`` at its ED point, endo → epi) and
    by AHA segment (the truth's). Survival counts, per quarter, the ED tracks still reported at
    ES among those whose material line still crosses the plane then (the others cannot be seen).

    Parameters
    ----------
    sets : dict
        ``{phase: {(view, slice): TagPointSet}}`` as :func:`track` makes them.
    motion : LVMotion
        The study's true motion.
    period_mm : float, optional
        Tag period, mm: a point more than half a period off is counted ``wrong`` (another
        intersection); None leaves the count out.

    Returns
    -------
    dict
        ``es_phase``; per view (``sa``, ``la``): ``ed`` tracks, ``visible`` at ES, ``kept`` at ES,
        ES in-plane error median / p95 (mm), ``wrong``, ``radial_mm`` / ``circ_mm`` (median
        signed), and ``quarters``: per wall quarter ``[ED tracks, kept share, radial median,
        circumferential median, |error| median]`` (mm); ``sa_segments``: per AHA segment present
        ``[ED tracks, kept share, radial median]``; ``sa_phase_err_mm``: per phase ≥ 1 the median
        SA in-plane error (mm) and the points reported; ``sa_border_bands`` (with
        ``period_mm``): per nearest ES border (``endo``, ``epi``) and band of distance to it
        (``BORDER_BANDS``, periods) ``[from, to, points, median error toward mid-wall mm]``
        (:func:`_toward_mid_wall`; positive: the wall read thinner there).

    """
    from mlv_ros.core.sim.regional import truth_segments

    es = int(round(motion.es_phase))
    fr = motion.frame
    ideal, _ = ideal_targets(sets, motion)
    every, _ = ideal_targets(sets, motion, every_track=True)

    def depth(x):
        r, th, z = fr.to_local(x)
        endo, epi = motion.endo_radius(z), motion.epi_radius(z, th)
        return (r - endo) / np.maximum(epi - endo, 1e-9)

    def radial_circ(x):
        _, th, _ = fr.to_local(x)
        e_r = np.cos(th)[:, None] * fr.septum + np.sin(th)[:, None] * fr.e2
        e_c = -np.sin(th)[:, None] * fr.septum + np.cos(th)[:, None] * fr.e2
        return e_r, e_c

    rows = []  # view (0 SA), phase, quarter, segment, |err|, radial, circ
    bands = []  # SA at ES: (side 0 endo / 1 epi, distance to that border in periods, error
    # toward mid-wall mm), the points whose true place is inside the ES wall
    visible, ed_rows = set(), []
    for key, pts in sets.get(0, {}).items():
        if not len(pts.track_id):
            continue
        la = int(key[0] != TaggedFrame.VIEW_SA)
        q = np.clip((depth(pts.position) * 4).astype(int), 0, 3)
        seg = truth_segments(motion, pts.position)
        info = {int(t): (qq, sg) for t, qq, sg in zip(pts.track_id, q, seg)}
        later = every.get(es, {}).get(key)
        if later is not None:
            visible |= {(key, int(t)) for t in later.track_id}
        ed_rows += [(key, int(t), la, *map(int, info[int(t)])) for t in pts.track_id]
        for phase in sorted(p for p in sets if p > 0):
            got, want = sets[phase].get(key), ideal.get(phase, {}).get(key)
            if got is None or not len(got.track_id):
                continue
            err = np.asarray(got.position) - np.asarray(want.position)
            e_r, e_c = radial_circ(np.asarray(want.position))
            for t, e, er, ec in zip(got.track_id, err, e_r, e_c):
                if int(t) in info:
                    rows.append((la, phase, *info[int(t)], np.linalg.norm(e), e @ er, e @ ec))
            if phase == es and not la and period_mm:
                known = np.array([int(t) in info for t in got.track_id], dtype=bool)
                bands += _toward_mid_wall(
                    motion, np.asarray(want.position)[known], err[known], e_r[known],
                    pts.geometry.normal, es, period_mm,
                )
    if not rows:
        return {}
    r = np.array(rows, float)
    kept = {
        (key, int(t)) for key, pts in sets.get(es, {}).items() for t in pts.track_id
    }

    def med(x):
        return round(float(np.median(x)), 2) if len(x) else None

    out = {'es_phase': es}
    for la, name in ((0, 'sa'), (1, 'la')):
        at = r[(r[:, 0] == la) & (r[:, 1] == es)]
        eds = [e for e in ed_rows if e[2] == la]
        if not eds:
            continue
        seen = [e for e in eds if (e[0], e[1]) in visible]

        def share(group):
            if not group:
                return None
            return round(sum((e[0], e[1]) in kept for e in group) / len(group), 2)

        out[name] = {
            'ed': len(eds),
            'visible': len(seen),
            'kept': int(sum((e[0], e[1]) in kept for e in eds)),
            'err_median_mm': med(at[:, 4]),
            'err_p95_mm': round(float(np.percentile(at[:, 4], 95)), 2) if len(at) else None,
            **(
                {'wrong': int(np.sum(at[:, 4] > 0.5 * period_mm))} if period_mm else {}
            ),
            'radial_mm': med(at[:, 5]),
            'circ_mm': med(at[:, 6]),
            'quarters': [
                [
                    int(sum(e[3] == k for e in eds)),
                    share([e for e in seen if e[3] == k]),
                    med(at[at[:, 2] == k, 5]),
                    med(at[at[:, 2] == k, 6]),
                    med(at[at[:, 2] == k, 4]),
                ]
                for k in range(4)
            ],
        }
        if la == 0:
            sa_seen = seen
            out['sa_segments'] = {
                int(k): [
                    int(sum(e[4] == k for e in eds)),
                    share([e for e in sa_seen if e[4] == k]),
                    med(at[at[:, 3] == k, 5]),
                ]
                for k in sorted({e[4] for e in eds})
            }
    if bands:
        b = np.array(bands, float)
        out['sa_border_bands'] = {
            side: [
                [lo, hi, int(np.sum(sel)), med(b[sel, 2])]
                for lo, hi in zip(BORDER_BANDS[:-1], BORDER_BANDS[1:])
                for sel in [(b[:, 0] == k) & (b[:, 1] >= lo) & (b[:, 1] < hi)]
            ]
            for k, side in enumerate(('endo', 'epi'))
        }
    sa = r[r[:, 0] == 0]
    out['sa_phase_err_mm'] = [
        [int(p), med(sa[sa[:, 1] == p, 4]), int(np.sum(sa[:, 1] == p))]
        for p in sorted(set(sa[:, 1].astype(int)))
    ]
    return out


#: Bands of distance to the nearest ES wall border, tag periods (:func:`_toward_mid_wall`).
BORDER_BANDS = (0.0, 0.25, 0.5, 1.0, float('inf'))


def _toward_mid_wall(motion, true_pos, err, e_r, normal, phase, period_mm: float) -> list:
    """
    Return each point's nearest ES wall border, its distance and its error toward mid-wall.

    From each point's true place (mm, (N, 3)) the in-plane radial line (``e_r`` projected onto
    the image plane) is walked inward and outward in steps of 1/40 period, up to one period,
    until the material there (the truth's inverse map at ``phase``) leaves the myocardium: the
    endocardial and epicardial borders' distances. Returns ``(side, distance in periods, error
    toward mid-wall in mm)`` per point whose true place lies inside the wall (side 0: the
    endocardium is nearer, the radial error counts outward; 1: the epicardium, inward); a
    border farther than a period counts as one period away. ``err`` (N, 3) the tracked minus
    the true position, mm.
    """
    if not len(true_pos):
        return []
    n = np.asarray(normal, float)
    d = e_r - (e_r @ n)[:, None] * n
    d /= np.maximum(np.linalg.norm(d, axis=1), 1e-12)[:, None]
    steps = np.arange(0.0, 1.0 + 1e-9, 1.0 / 40.0) * period_mm
    dist = []
    for sign in (-1.0, 1.0):
        pts = true_pos[:, None, :] + sign * steps[None, :, None] * d[:, None, :]
        inside = motion.inside_myocardium(
            motion.inverse(pts.reshape(-1, 3), phase)
        ).reshape(len(true_pos), steps.size)
        first_out = np.where(inside.all(axis=1), steps.size, np.argmax(~inside, axis=1))
        dist.append(np.where(inside[:, 0], np.minimum(first_out * steps[1], period_mm), np.nan))
    radial = np.einsum('ij,ij->i', err, d)
    out = []
    for de, dp, er in zip(dist[0], dist[1], radial):
        if np.isfinite(de):
            side = int(dp < de)
            out.append((side, min(de, dp) / period_mm, er if side == 0 else -er))
    return out


def twist_levels(tr, sets, cloud, state, positions, truth, span) -> dict:
    """
    Return the ES twist per analysis level against the truth, with and without the local stage.

    Parameters
    ----------
    tr : MotionTracker
        The tracker that solved every phase.
    sets : dict
        ``{phase: {(view, slice): TagPointSet}}``, as solved.
    cloud, state
        The registered cloud and model state (to solve again up to ES without the local stage).
    positions : dict
        Solved positions per phase, mm.
    truth : LVMotion
        The ground truth.
    span : (float, float) or None
        Levels the SA planes with tag points cross (0 apex … 1 base).

    Returns
    -------
    dict
        ``twist_levels``: level centres; ``twist_true_deg``, ``twist_level_error_deg`` and
        ``twist_level_error_no_local_deg`` per level (degrees, solved − true);
        ``twist_span``; ``twist_lever``: per level, its distance beyond the span (0 inside),
        in fractions of the LV's length.

    """
    from mlv_ros.core.analysis import LVAnalyzer, LVFrame
    from mlv_ros.core.analysis.frame import lv_frame_axes

    es, n = int(round(truth.es_phase)), max(sets) + 1
    if es not in positions:
        return {}
    analyzer = LVAnalyzer(tr.rest, LVFrame(*lv_frame_axes(tr.rest, state.rotation)))

    def twist(x):
        return analyzer.phase(x, phase_index=es, num_phases=n).twist_deg

    true = twist(truth.position(tr.rest, es))
    _, global_only, _ = solve(
        {p: sets[p] for p in sets if p <= es}, cloud, state, local=False
    )
    levels = analyzer.phase(positions[es], phase_index=es, num_phases=n).level_position
    lever = (
        np.zeros(len(levels))
        if span is None
        else np.maximum(np.maximum(span[0] - levels, levels - span[1]), 0.0)
    )
    return {
        'twist_levels': np.round(levels, 3).tolist(),
        'twist_true_deg': np.round(true, 2).tolist(),
        'twist_level_error_deg': np.round(twist(positions[es]) - true, 2).tolist(),
        'twist_level_error_no_local_deg': (
            np.round(twist(global_only[es]) - true, 2).tolist() if es in global_only else None
        ),
        'twist_span': None if span is None else [round(v, 3) for v in span],
        'twist_lever': np.round(lever, 3).tolist(),
    }


def protocol_period_mm(case: Path) -> float | None:
    """Tag period of a simulated study (its ``protocol.yaml``), mm; None when not recorded."""
    f = case / 'study' / 'protocol.yaml'
    if not f.is_file():
        return None
    value = (yaml.safe_load(f.read_text()) or {}).get('tag_spacing_mm')
    return float(value) if value else None


def strain_errors(case: Path, rest, rotation, positions, verdicts, motion, origin=0) -> dict:
    """
    Return the ES strain errors and the findings of the re-solve, and of the truth's motion.

    ``strain``: ``bench/strain.py``'s comparison (:func:`strain.brief`) of the solved motion,
    analysed as the analysis node does (:func:`strain.ours_from_positions`); ``strain_truth``:
    the same for the truth's motion of the same ED particles in the same frame (no motion error:
    what the analysis, its frame and its segments make of perfect motion); ``strain``'s
    ``missed_why`` names each missed abnormal segment's cause (:func:`strain.explain_abnormal`;
    ``origin``: the recorded state's ``segment_origin``, 1 when the septum is the prior's).
    Empty when the study has no regional truth or its ES phase was not solved.
    """
    import strain as bench_strain

    gt = json.loads((case / 'study' / 'groundtruth.json').read_text()).get('regional')
    if not gt or int(gt['phase']) not in positions:
        return {}
    es = int(gt['phase'])
    exact = {p: motion.position(rest, p) for p in positions}
    out = {}
    for name, pos, states in (('strain', positions, verdicts), ('strain_truth', exact, None)):
        ours = bench_strain.ours_from_positions(rest, rotation, pos, es, states)
        ours['segment_origin'] = int(origin)
        result = bench_strain.compare(
            gt, ours, cap_scored=motion.apex_thickening is not None
        )
        if name == 'strain':
            result['explained'] = bench_strain.explain_abnormal(
                gt, ours, motion, rest, rotation, positions
            )
        out[name] = bench_strain.brief(result)
    return out


def replay_case(
    case: Path,
    tracker_kwargs=None,
    solver_kwargs=None,
    ideal: str | None = None,
    tracks: bool = False,
    ideal_segments=None,
    solve_phases: bool = True,
    strain: bool = False,
    twist: bool = False,
    phases: bool = False,
) -> dict:
    t0 = time.monotonic()
    frames, cloud, state = recorded(case / 'run' / 'run.mcap')
    sets = track(frames, **(tracker_kwargs or {}))
    truth = motion_from_groundtruth(case / 'study')
    report = (
        {'tracks': track_errors(sets, truth, protocol_period_mm(case))} if tracks else {}
    )
    if not solve_phases:
        return {'case': case.name, **report, 'track_s': round(time.monotonic() - t0, 1)}
    not_ideal = None
    if ideal:
        sets, not_ideal = ideal_targets(
            sets, truth, every_track=ideal == 'every-track', segments=ideal_segments
        )
    t1 = time.monotonic()
    tr, positions, verdicts = solve(sets, cloud, state, **(solver_kwargs or {}))
    sa_planes = [
        (p.geometry.image_position, p.geometry.normal)
        for (v, _), p in sets.get(0, {}).items()
        if v == TaggedFrame.VIEW_SA and len(p.track_id)
    ]
    run = {
        'ed': tr.rest,
        'rotation': state.rotation,
        'positions': positions,
        'sa_planes': sa_planes,
    }
    acc = motion_accuracy(run, truth)
    es = acc['es'] or {}
    if twist:
        from mlv_ros.core.analysis import LVFrame
        from mlv_ros.core.analysis.frame import lv_frame_axes, plane_level_span

        span = plane_level_span(LVFrame(*lv_frame_axes(tr.rest, state.rotation)), sa_planes)
        report |= twist_levels(tr, sets, cloud, state, positions, truth, span)
    return {
        'case': case.name,
        **({'ideal': ideal, 'points_not_ideal': not_ideal} if ideal else {}),
        **({'ideal_segments': sorted(ideal_segments)} if ideal and ideal_segments else {}),
        **{
            k: round(es[k], 3)
            for k in (
                'median_mm',
                'p95_mm',
                'twist_error_deg',
                'twist_error_measured_deg',
                'twist_extrapolated_over_stated',
            )
            if k in es
        },
        'coverage': round(acc['coverage'], 3),
        'solved': f'{len(positions)}/{max(sets) + 1}',
        'degraded': sorted(p for p, (v, *_) in verdicts.items() if OK < v < FAILED),
        'failed': sorted(p for p, (v, *_) in verdicts.items() if v >= FAILED),
        'worst_phase_median_mm': round(max(r['median_mm'] for r in acc['per_phase']), 3),
        **segment_errors(case, tr.rest, positions, truth),
        **segment_tracks(case, sets, truth),
        **(
            strain_errors(
                case, tr.rest, state.rotation, positions, verdicts, truth, state.segment_origin
            )
            if strain
            else {}
        ),
        **report,
        **({'phases': phase_errors(tr.rest, positions, verdicts, truth)} if phases else {}),
        'track_s': round(t1 - t0, 1),
        'solve_s': round(time.monotonic() - t1, 1),
    }


def keyword_option(ap, flag: str, what: str) -> None:
    """
    Add a repeatable ``flag KEY=VALUE`` option of ``what``'s keyword arguments to ``ap``.

    Parameters
    ----------
    ap : argparse.ArgumentParser
        The parser.
    flag : str
        The option, e.g. ``--solver``.
    what : str
        The class whose keywords it sets, for the help text.

    """
    ap.add_argument(
        flag,
        action='append',
        default=[],
        metavar='KEY=VALUE',
        help=f'{what} keyword (a number or true/false), repeatable',
    )


def keywords(opts) -> dict:
    """Return ``KEY=VALUE`` strings as a dict, each value read as YAML (numbers, booleans)."""
    return {k: yaml.safe_load(v) for k, v in (a.split('=', 1) for a in opts)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('cases', nargs='+', type=Path)
    keyword_option(ap, '--tracker', 'SliceTracker')
    keyword_option(ap, '--solver', 'MotionTracker')
    ap.add_argument(
        '--ideal',
        nargs='?',
        const='tracks',
        choices=('tracks', 'every-track'),
        default=None,
        help='replace the tracked points by where the truth puts them (no tracking error); '
        'every-track: every ED track at every phase as well (no track lost)',
    )
    ap.add_argument(
        '--ideal-segments',
        type=lambda v: {int(k) for k in v.split(',')},
        default=None,
        metavar='K,...',
        help='with --ideal (implied): only the tracks whose ED point lies in these AHA segments '
        "(the truth's)",
    )
    ap.add_argument(
        '--tracks',
        action='store_true',
        help="report the tracker's own error against the truth (track_errors): per wall "
        'quarter and AHA segment, radial / circumferential, survival to ES',
    )
    ap.add_argument(
        '--no-solve', action='store_true', help='track only (with --tracks: the tracker alone)'
    )
    ap.add_argument(
        '--strain',
        action='store_true',
        help='add the ES strain errors and wall-motion findings against the truth '
        '(bench/strain.py), of the re-solve and of the truth motion',
    )
    ap.add_argument(
        '--twist',
        action='store_true',
        help='report the ES twist per level against the truth, its lever beyond the SA stack, '
        'and the same without the local stage (twist_levels)',
    )
    ap.add_argument(
        '--phases',
        action='store_true',
        help='report per phase the median 3D error, the worst AHA segment and its error, and the '
        "solver's verdict with its reasons (phase_errors)",
    )
    args = ap.parse_args()
    if args.ideal_segments and args.ideal == 'every-track':
        ap.error('--ideal-segments moves the tracked points only: use it with --ideal tracks')
    ideal = 'tracks' if args.ideal_segments and not args.ideal else args.ideal
    kw = [keywords(opts) for opts in (args.tracker, args.solver)]
    for case in args.cases:
        print(
            json.dumps(
                replay_case(
                    case,
                    *kw,
                    ideal=ideal,
                    tracks=args.tracks,
                    solve_phases=not args.no_solve,
                    ideal_segments=args.ideal_segments,
                    strain=args.strain,
                    twist=args.twist,
                    phases=args.phases,
                )
                | ({'tracker': kw[0]} if kw[0] else {})
                | ({'solver': kw[1]} if kw[1] else {})
            ),
            flush=True,
        )


if __name__ == '__main__':
    sys.exit(main())
