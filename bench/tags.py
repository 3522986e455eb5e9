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
Tag detection/tracking benchmark on simulated tagged-MRI studies.

For each preset (normal, hypertrophic) and SNR (inf, 20, 10) one study is simulated with
:func:`mlv_ros.core.sim.simulate_study`; every slice's cine goes through
:class:`mlv_ros.core.tags.SliceTracker` (ED myocardium mask at phase 0 only) and, from the same
ED points, the HARP baseline (:func:`mlv_ros.core.tags.harp_track`).

Ground truth
------------
* ED intersections: the simulator lays the grid in each image plane with dark tag planes
  through the image centre, one family ⟂ each of the row and column directions, at multiples of
  the tag spacing (``mlv_ros.core.sim.imaging.tag_pattern``). In pixels they sit at
  ``centre + (i·λ/Δr, j·λ/Δc)``; those whose nearest pixel lies in the ED myocardium mask are
  the truth set.
* Later phases: the ED intersection ``X_ed`` (patient mm) moves to ``motion.position(X_ed, t)``;
  its projection onto the fixed image plane is the true in-plane position (the through-plane
  component is not observable and is ignored).

Metrics (JSON on stdout)
------------------------
``ed_error_px`` (median / p90 distance of detections to the nearest true intersection, matched
within 0.3·λ), ``precision`` (detections within 0.3·λ of a true intersection whose nearest pixel
is in the mask, dilated by 1 px to forgive border rounding), ``recall`` (truth inside the mask
found), ``track_error_mm`` (in-plane distance to truth over all phases > 0, median / p90 / p99),
``harp_error_mm`` on the same points and ``gabor_over_harp`` (median ratio, < 1 = better than
HARP), ``kept_to_es`` (fraction of ED tracks still reported at ES), ``ms_per_image_tracking``
(one tracker update: two detections on the heart's window + RPM), ED detection with spectrum
estimation, and stateless detection on a whole 256² frame. Wall-clock on a shared machine.

Usage: ``mlv-ros bench tags [-- --quick --out DIR --presets normal,hypertrophic --snr inf,20,10]``
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys
import time

import cv2
from mlv_ros.core.tags import detect_intersections, harp_track, SliceTracker
import numpy as np
from scipy.spatial import cKDTree


def truth_intersections(geometry, shape, spacing_mm, mask):
    """Return true ED intersections (pixel rc) whose nearest pixel is in ``mask`` (module doc)."""
    rows, cols = shape
    c = np.array([(rows - 1) / 2.0, (cols - 1) / 2.0])
    step = np.array([spacing_mm / geometry.row_spacing, spacing_mm / geometry.column_spacing])
    n = int(np.ceil(max(rows, cols) / step.min())) + 1
    i, j = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing='ij')
    rc = c + np.stack([i.ravel(), j.ravel()], -1) * step
    q = np.rint(rc).astype(int)
    ok = np.all((q >= 0) & (q < np.array(shape)), axis=1)
    rc, q = rc[ok], q[ok]
    return rc[mask[q[:, 0], q[:, 1]]]


def in_plane_error_mm(geometry, rc, truth_xyz):
    """In-plane distance (mm) between pixel positions and patient points projected on the plane."""
    t_rc, _ = geometry.patient_to_pixel(truth_xyz)
    d = (np.asarray(rc) - t_rc) * np.array([geometry.row_spacing, geometry.column_spacing])
    return np.linalg.norm(d, axis=-1)


def run_slice(study, key, spacing_mm, overlay=None):
    """Track one slice; returns per-slice metric arrays."""
    frames = study.cine(*key)
    geom = frames[0].geometry
    mask = study.ed_masks[key]
    motion = study.motion
    es = int(motion.es_phase)
    truth = truth_intersections(geom, mask.shape, spacing_mm, mask)
    dil = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    truth_wide = truth_intersections(geom, mask.shape, spacing_mm, dil)
    lam_px = spacing_mm / geom.row_spacing
    tracker = SliceTracker(geom)
    t_track = []
    sets = []
    for f in frames:
        t0 = time.perf_counter()
        sets.append(tracker.update(f, mask=mask if f.phase_index == 0 else None))
        t_track.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    detect_intersections(frames[0].image, mask)
    t_ed = time.perf_counter() - t0
    # Stateless detection on a whole frame (no mask, no crop, parameters known): the
    # worst case per image for a caller that does not track.
    t0 = time.perf_counter()
    detect_intersections(frames[es].image, params=tracker.params)
    t_full = time.perf_counter() - t0
    out = {'t_track': t_track, 't_ed': t_ed, 't_full': t_full, 'n_truth': len(truth)}
    ed = sets[0]
    if len(ed) == 0 or len(truth_wide) == 0:
        out.update(
            n_det=0,
            tp=0,
            found=0,
            ed_err=np.zeros(0),
            trk=np.zeros(0),
            harp=np.zeros(0),
            pair_g=np.zeros(0),
            pair_h=np.zeros(0),
            kept=np.nan,
            status=ed.status,
        )
        return out, None
    d, i = cKDTree(truth_wide).query(ed.pixel_rc)
    good = d <= 0.3 * lam_px
    out['n_det'] = len(ed)
    out['tp'] = int(good.sum())
    out['found'] = (
        int(np.sum(cKDTree(ed.pixel_rc).query(truth)[0] <= 0.3 * lam_px)) if len(truth) else 0
    )
    out['ed_err'] = d[good]
    # Material point of each track: the true intersection its ED detection matched.
    x_ed = geom.pixel_to_patient(truth_wide[i])
    ids = ed.track_id
    tid_ok = dict(zip(ids.tolist(), good.tolist()))
    trk, kept = [], np.nan
    harp = harp_track([f.image for f in frames], ed.pixel_rc, tracker.params)
    pair_g, pair_h = [], []
    for p in range(1, len(frames)):
        s = sets[p]
        xt = motion.position(x_ed, p)
        if len(s):
            sel = np.array([tid_ok[t] for t in s.track_id.tolist()], bool)
            e = in_plane_error_mm(geom, s.pixel_rc[sel], xt[s.track_id[sel]])
            trk.append(e)
        hv = harp.valid[p] & good
        if len(s):
            both = np.zeros(len(ids), bool)
            both[s.track_id[sel]] = True
            both &= hv
            g_rc = np.full((len(ids), 2), np.nan)
            g_rc[s.track_id] = s.pixel_rc
            if both.any():
                pair_g.append(in_plane_error_mm(geom, g_rc[both], xt[both]))
                pair_h.append(in_plane_error_mm(geom, harp.pixel_rc[p][both], xt[both]))
        if p == es:
            kept = len(s) / max(len(ed), 1)
    hv_all = [
        in_plane_error_mm(
            geom,
            harp.pixel_rc[p][harp.valid[p] & good],
            motion.position(x_ed, p)[harp.valid[p] & good],
        )
        for p in range(1, len(frames))
    ]
    out.update(
        trk=np.concatenate(trk) if trk else np.zeros(0),
        harp=np.concatenate(hv_all) if hv_all else np.zeros(0),
        pair_g=np.concatenate(pair_g) if pair_g else np.zeros(0),
        pair_h=np.concatenate(pair_h) if pair_h else np.zeros(0),
        kept=kept,
        status=ed.status,
    )
    vis = None
    if overlay is not None:
        vis = {
            'ed_img': frames[0].image,
            'ed_rc': ed.pixel_rc,
            'truth': truth,
            'es_img': frames[es].image,
            'es_rc': sets[es].pixel_rc,
            'es_truth': geom.patient_to_pixel(motion.position(x_ed, es))[0][good],
            'harp_es': harp.pixel_rc[es][harp.valid[es]],
        }
    return out, vis


def save_overlay(vis, path, title):
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(12, 6))
    for a, img, pts, tru, extra, name in (
        (ax[0], vis['ed_img'], vis['ed_rc'], vis['truth'], None, 'ED'),
        (ax[1], vis['es_img'], vis['es_rc'], vis['es_truth'], vis['harp_es'], 'ES'),
    ):
        a.imshow(img, cmap='gray')
        a.plot(tru[:, 1], tru[:, 0], 'o', mfc='none', mec='lime', ms=7, label='truth')
        if extra is not None and len(extra):
            a.plot(extra[:, 1], extra[:, 0], 'x', color='orange', ms=4, label='HARP')
        a.plot(pts[:, 1], pts[:, 0], '+', color='red', ms=6, label='Gabor+RPM')
        allp = np.vstack([tru, pts]) if len(pts) else tru
        if len(allp):
            lo, hi = allp.min(0) - 12, allp.max(0) + 12
            a.set_xlim(lo[1], hi[1])
            a.set_ylim(hi[0], lo[0])
        a.set_title(f'{title} {name}')
        a.legend(loc='lower right', fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def summarise(rows):
    def cat(k):
        return np.concatenate([r[k] for r in rows]) if rows else np.zeros(0)

    ed_err, trk, harp = cat('ed_err'), cat('trk'), cat('harp')
    pg, ph = cat('pair_g'), cat('pair_h')
    n_det = sum(r['n_det'] for r in rows)
    tp = sum(r['tp'] for r in rows)
    n_truth = sum(r['n_truth'] for r in rows)
    found = sum(r['found'] for r in rows)
    tt = np.concatenate([r['t_track'][1:] for r in rows])

    def q(a, p):
        return float(np.percentile(a, p)) if len(a) else None

    kept = [r['kept'] for r in rows if np.isfinite(r['kept'])]
    return {
        'slices': len(rows),
        'ed_points': n_det,
        'ed_truth_in_mask': n_truth,
        'ed_error_px': {'median': q(ed_err, 50), 'p90': q(ed_err, 90)},
        'precision': tp / n_det if n_det else None,
        'recall': found / n_truth if n_truth else None,
        'track_error_mm': {
            'median': q(trk, 50),
            'p90': q(trk, 90),
            'p99': q(trk, 99),
            'n': int(len(trk)),
        },
        'harp_error_mm': {'median': q(harp, 50), 'p90': q(harp, 90), 'n': int(len(harp))},
        'same_points': {
            'gabor_median_mm': q(pg, 50),
            'harp_median_mm': q(ph, 50),
            'gabor_over_harp': (q(pg, 50) / q(ph, 50)) if len(pg) and q(ph, 50) else None,
            'n': int(len(pg)),
        },
        'kept_to_es': float(np.mean(kept)) if kept else None,
        'ms_per_image_tracking': {'median': q(tt * 1e3, 50), 'p90': q(tt * 1e3, 90)},
        'ms_ed_detection_with_estimation': q(np.array([r['t_ed'] for r in rows]) * 1e3, 50),
        'ms_detection_whole_frame_no_mask': q(np.array([r['t_full'] for r in rows]) * 1e3, 50),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--out', default='out/bench/tags', help='directory for PNG overlays')
    ap.add_argument('--presets', default='normal,hypertrophic')
    ap.add_argument('--snr', default='inf,20,10')
    ap.add_argument('--quick', action='store_true', help='128² images, 10 phases (smoke run)')
    ap.add_argument('--phases', type=int, default=None)
    args = ap.parse_args(argv)
    from mlv_ros.core.sim import load_preset, simulate_study

    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    result = {'benchmark': 'tags', 'quick': bool(args.quick), 'runs': {}}
    for preset in args.presets.split(','):
        spacing = float(load_preset(preset)['imaging']['tag_spacing_mm'])
        for snr_s in args.snr.split(','):
            snr = float(snr_s)
            t0 = time.perf_counter()
            study = simulate_study(
                preset,
                snr=None if not np.isfinite(snr) else snr,
                quick=args.quick,
                num_phases=args.phases,
                seed=1,
            )
            t_sim = time.perf_counter() - t0
            rows = []
            for key in sorted(study.ed_masks):
                want_png = key[1] in (3,) or (key[0] == 1 and key[1] == 0)
                r, vis = run_slice(study, key, spacing, overlay=want_png)
                rows.append(r)
                if vis is not None:
                    view = 'SA' if key[0] == 0 else 'LA'
                    save_overlay(
                        vis,
                        out_dir / f'{preset}_snr{snr_s}_{view}{key[1]}.png',
                        f'{preset} SNR {snr_s} {view}{key[1]}',
                    )
            s = summarise(rows)
            s['simulation_s'] = t_sim
            s['image_size'] = int(study.frames[0].image.shape[0])
            s['num_phases'] = int(study.motion.num_phases)
            result['runs'][f'{preset}/snr{snr_s}'] = s
            print(
                f'[tags bench] {preset} snr {snr_s}: ED {s["ed_error_px"]["median"]} px, '
                f'track {s["track_error_mm"]["median"]} mm, P {s["precision"]}, R {s["recall"]}',
                file=sys.stderr,
            )
    r20 = [v for k, v in result['runs'].items() if k.endswith('snr20')]
    rinf = [v for k, v in result['runs'].items() if k.endswith('snrinf')]

    def worst(runs, f):
        vals = [f(v) for v in runs if f(v) is not None]
        return max(vals) if vals else None

    result['acceptance'] = {
        'must_ed_median_px_at_snr20<=0.25': worst(r20, lambda v: v['ed_error_px']['median']),
        'must_track_median_mm_at_snr20<=0.5': worst(r20, lambda v: v['track_error_mm']['median']),
        'must_precision>=0.98 (min over runs)': -worst(
            list(result['runs'].values()),
            lambda v: -v['precision'] if v['precision'] is not None else None,
        )
        if result['runs']
        else None,
        'goal_ed_median_px_clean<=0.1': worst(rinf, lambda v: v['ed_error_px']['median']),
        'goal_track_median_mm_at_snr20<=0.3': worst(r20, lambda v: v['track_error_mm']['median']),
        'goal_ms_per_image<=20 (median tracking)': worst(
            list(result['runs'].values()), lambda v: v['ms_per_image_tracking']['median']
        ),
        'goal_gabor_over_harp<=1 (worst run)': worst(
            list(result['runs'].values()), lambda v: v['same_points']['gabor_over_harp']
        ),
    }
    result['png_dir'] = str(out_dir)
    json.dump(result, sys.stdout, indent=2)
    print()


if __name__ == '__main__':
    main()
