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
Where and why a study's short-axis tag tracks are lost before end-systole, per sector.

Tracks every slice of a recorded run again as ``bench/retrack.py`` does (the tag detector's own
:class:`SliceTracker` calls) with each step's outcome recorded, and follows every short-axis ED
track phase by phase up to end-systole against where the truth puts it (its ED material line's
crossing of the image plane, ``retrack.ideal_targets``). At each phase a live track is kept or
missed by one of the tracker's steps, and a track missed ``max_gap + 1`` phases in a row is
dropped:

- ``no detection within gate``: the first pass (inside the ED mask warped through the
  predictions) detected nothing within ``gate`` of the prediction; split by whether the truth lies
  inside that mask and whether a detection at the slice's threshold lies within 0.25 periods of
  the truth when the same phase is detected inside the ED mask itself (``ed mask finds it``);
- ``unconfirmed``: the second pass (inside the mask warped through the matches) has no point
  within ``confirm_px`` of the match; split by whether it has one within 0.25 periods of the truth
  (the passes disagree by more than ``confirm_px``), whether the truth lies inside its mask, and
  whether the second pass run again without its tuned refinement has a point within 0.25 periods
  of the truth (``untuned has it``: the refinement moved the intersection off its accept mask or
  beyond ``FOLLOW_TUNED_MOVE``, and dropped it);
- ``register rejected``: the match's own ED neighbourhood does not register there; split by
  whether the match lay more than 0.2 periods from the truth.

Tracks are pooled by the truth's class of their ED point's AHA segment: ``still`` (akinetic or
dyskinetic) and ``other``; ``--segments K,...`` pools the tracks of those AHA segments (the
truth's) as ``still`` instead. Prints one JSON line per case (ED tracks, dropped by ES, per reason
the miss events and the drops they ended, and the prediction's and matches' errors in periods),
then one line pooled over the cases. ``--view la`` follows the long-axis views' tracks instead of
the short axis's (the only tracks that see the wall above the basal SA slice move along the axis).

    python bench/track_losses.py CASE_DIR [CASE_DIR ...] [--tracker KEY=VALUE ...]
        [--view sa|la] [--segments K,...]
"""

from __future__ import annotations

import argparse
import collections
import json
from pathlib import Path

from mlv_ros.core.io.groundtruth import motion_from_groundtruth
from mlv_ros.core.registration.streaming import StreamingMasker
from mlv_ros.core.sim.regional import truth_segments
from mlv_ros.core.tags import SliceTracker
from mlv_ros.core.tags.intersections import detect_intersections
from mlv_ros.core.tags.tracker import FOLLOW_TUNED_MOVE
from mlv_ros.core.types import VIEW_LA, VIEW_SA
import numpy as np
from retrack import ideal_targets, keyword_option, keywords, recorded
from scipy.spatial import cKDTree

# A detection this close to the truth, in tag periods, is the track's intersection.
NEAR = 0.25


class LoggingTracker(SliceTracker):
    """:class:`SliceTracker` that keeps each phase's predictions, detections and match steps."""

    def update(self, frame, mask=None):
        """
        Process the next phase as :class:`SliceTracker` does, keeping what each step did.

        Parameters
        ----------
        frame : Frame
            Image and geometry of the next phase of this slice.
        mask : array_like of bool, optional
            Myocardium mask (ED only, as the node passes it).

        """
        self.log = {'dets': [], 'first': None, 'final': None, 'live': None, 'ed_det': None}
        self.log['dead'] = self._dead.copy()
        out = super().update(frame, mask)
        self.log['dead_after'] = self._dead.copy()
        return out

    def _detect_following(self, image, region, accept, roi, tuned=True):
        det = super()._detect_following(image, region, accept, roi, tuned)
        self.log['dets'].append((det, region))
        # Kept to run the second pass again untuned (``_reason``).
        self.log['again'] = lambda: super(LoggingTracker, self)._detect_following(
            image, region, accept, roi, tuned=False
        )
        return det

    def _match(self, image, mask, live, pred, sp, view=VIEW_SA):
        self.log['dets'] = []
        m = super()._match(image, mask, live, pred, sp, view)
        self.log.update(live=live.copy(), pred=pred.copy(), sp=sp)
        if m is not None:
            self.log['first'] = (m.hit.copy(), m.unconfirmed.copy(), m.new.copy())
            if mask is None and self.ed_mask is not None and not m.hit.all():
                lo = np.floor(pred.min(0) - 2 * sp)
                hi = np.ceil(pred.max(0) + 2 * sp) + 1
                self.log['ed_det'] = detect_intersections(
                    image,
                    mask=self.ed_mask,
                    params=self.params,
                    roi=(lo[0], hi[0], lo[1], hi[1]),
                    coverage_normalised=self.follow_coverage,
                    tuned=False,
                    max_tuned_move_periods=FOLLOW_TUNED_MOVE,
                    **{**self.detect_kwargs, 'min_confidence': self.follow_threshold()},
                )
        return m

    def _register_matches(self, frame, image, live, pred, sp, m):
        super()._register_matches(frame, image, live, pred, sp, m)
        self.log['final'] = m.hit.copy()


def _near(det, x, sp):
    """Return the distance from ``x`` to the nearest of ``det``'s points, tag periods."""
    if det is None or not det.ok or not len(det):
        return np.inf
    return float(cKDTree(det.pixel_rc).query(x)[0]) / sp


def _inside(region, x) -> bool:
    """Return whether the pixel nearest ``x`` lies in ``region`` (None: no mask)."""
    if region is None:
        return True
    r, c = np.clip(np.round(x).astype(int), 0, np.array(region.shape) - 1)
    return bool(region[r, c])


def _reason(lg, j, x) -> tuple[str, dict]:
    """Return why live track ``j`` (row of ``lg['live']``) was missed, and its errors."""
    sp = lg['sp']
    err = {'pred': float(np.linalg.norm(lg['pred'][j] - x)) / sp}
    if lg['first'] is None:
        return 'no detection at all', err
    hit, unconfirmed, new = lg['first']
    dets = lg['dets']
    if not hit[j]:
        where = 'truth in 1st-pass mask' if _inside(dets[0][1], x) else 'truth outside it'
        ed = 'ed mask finds it' if _near(lg['ed_det'], x, sp) <= NEAR else 'ed mask does not'
        return f'no detection within gate; {where}; {ed}', err
    err['match'] = float(np.linalg.norm(new[j] - x)) / sp
    if unconfirmed[j]:
        second = dets[-1]
        if _near(second[0], x, sp) <= NEAR:
            return 'unconfirmed; 2nd pass has it, beyond confirm_px of the 1st', err
        where = 'truth in 2nd-pass mask' if _inside(second[1], x) else 'truth outside it'
        untuned = 'untuned has it' if _near(lg['again'](), x, sp) <= NEAR else 'untuned does not'
        return f'unconfirmed; 2nd pass has nothing near the truth; {where}; {untuned}', err
    if not lg['final'][j]:
        off = 'match off > 0.2 periods' if err['match'] > 0.2 else 'match right'
        return f'register rejected; {off}', err
    return 'kept', err


def case_losses(case: Path, tracker_kwargs=None, view: int = VIEW_SA, segments=None) -> list:
    """
    Return one record per ED track of ``view`` and phase (1..ES) it enters alive.

    Each record: case, slice, track id, phase, group (``still`` / ``other``), the step's outcome
    (``kept`` or the reason it missed, see the module docstring), whether the track was dropped
    there, and the prediction's and match's errors against the truth, tag periods. ``segments``
    (AHA numbers, the truth's): the tracks whose ED point lies in them are ``still`` instead of
    those of the truth's akinetic and dyskinetic segments.
    """
    frames, _, _ = recorded(case / 'run' / 'run.mcap')
    motion = motion_from_groundtruth(case / 'study')
    gt = json.loads((case / 'study' / 'groundtruth.json').read_text())['regional']
    still = (
        {s['segment'] for s in gt['segments'] if s['class'] in ('akinetic', 'dyskinetic')}
        if segments is None
        else {int(k) for k in segments}
    )
    es = int(gt['phase'])
    masker, trackers, sets, logs = StreamingMasker(), {}, {}, []
    for f in frames:
        masker.observe_geometry(f)
    for f in frames:
        key = (f.view, f.slice_index)
        mask = None
        if f.phase_index == 0 or key not in trackers:
            trackers[key] = LoggingTracker(f.geometry, **(tracker_kwargs or {}))
            mask, _ = masker.ed_mask(f)
        tr = trackers[key]
        sets.setdefault(int(f.phase_index), {})[key] = tr.update(f, mask=mask)
        if 0 < f.phase_index <= es and f.view == view and tr.log['live'] is not None:
            logs.append((key, int(f.phase_index), tr, tr.log))
    every, _ = ideal_targets(sets, motion, every_track=True)
    group = {}
    for key, pts in sets[0].items():
        if key[0] == view and len(pts.track_id):
            seg = truth_segments(motion, pts.position)
            group |= {
                (key, int(t)): 'still' if int(s) in still else 'other'
                for t, s in zip(pts.track_id, seg)
            }
    out = []
    for key, phase, tr, lg in logs:
        now = every.get(phase, {}).get(key)
        if now is None or not len(now.track_id):
            continue
        truth = dict(zip(map(int, now.track_id), tr.geometry.patient_to_pixel(now.position)[0]))
        for j, i in enumerate(lg['live']):
            t = int(tr.track_id[i])
            if t not in truth or (key, t) not in group:
                continue
            why, err = _reason(lg, j, truth[t])
            out.append(
                {
                    'case': case.name,
                    'slice': int(key[1]),
                    'track': t,
                    'phase': phase,
                    'group': group[(key, t)],
                    'step': why,
                    'dropped': bool(lg['dead_after'][i]),
                    **{k: round(v, 3) for k, v in err.items()},
                }
            )
    return out


def summary(records: list) -> dict:
    """
    Return, per group, ED tracks, tracks dropped by ES, and per reason its misses and drops.

    A drop is counted against both misses that ended it (the phase it was dropped at and the
    one before, with ``max_gap`` 1), so a reason's drops add up to more than the tracks dropped.
    """
    out = {}
    for g in ('still', 'other'):
        rec = [r for r in records if r['group'] == g]
        if not rec:
            continue
        by_track = collections.defaultdict(list)
        for r in rec:
            by_track[(r['case'], r['slice'], r['track'])].append(r)
        misses = collections.Counter(r['step'] for r in rec if r['step'] != 'kept')
        ended = collections.Counter()
        for lst in by_track.values():
            lst.sort(key=lambda r: r['phase'])
            k = next((n for n, r in enumerate(lst) if r['dropped']), None)
            if k is not None:
                ended.update(r['step'] for r in lst[max(0, k - 1):k + 1] if r['step'] != 'kept')
        n = len(rec)
        out[g] = {
            'ed_tracks': len(by_track),
            'dropped_by_es': sum(any(r['dropped'] for r in v) for v in by_track.values()),
            'track_phases': n,
            'miss_share': round(sum(misses.values()) / n, 3),
            'reasons': {
                s: [c, round(c / n, 3), ended[s]] for s, c in sorted(misses.items())
            },
            'pred_err_missed_median': round(
                float(np.median([r['pred'] for r in rec if r['step'] != 'kept'] or [np.nan])), 3
            ),
            'pred_err_kept_median': round(
                float(np.median([r['pred'] for r in rec if r['step'] == 'kept'] or [np.nan])), 3
            ),
        }
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('cases', nargs='+', type=Path)
    keyword_option(ap, '--tracker', 'SliceTracker')
    ap.add_argument('--events', type=Path, help='write every record (JSON lines) here')
    ap.add_argument(
        '--view', choices=('sa', 'la'), default='sa', help='the views whose tracks are followed'
    )
    ap.add_argument(
        '--segments',
        type=lambda v: [int(k) for k in v.split(',')],
        help='AHA segments (K,...; the truth\'s) pooled as "still" instead of the akinetic and '
        'dyskinetic ones',
    )
    args = ap.parse_args()
    view = VIEW_LA if args.view == 'la' else VIEW_SA
    kw = keywords(args.tracker)
    everything = []
    for case in args.cases:
        rec = case_losses(case, kw, view, args.segments)
        everything += rec
        print(json.dumps({'case': case.name, **summary(rec)}), flush=True)
    if len(args.cases) > 1:
        print(json.dumps({'case': 'all', **summary(everything)}))
    if args.events:
        args.events.write_text(''.join(json.dumps(r) + '\n' for r in everything))


if __name__ == '__main__':
    main()
