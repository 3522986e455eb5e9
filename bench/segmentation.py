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
ED segmentation over a range of tagged-study protocols (prints JSON).

Each case is the ``normal`` preset (or another) with some keys overridden, one item varied at a
time (grid angle, tag period, pixel size, SNR, T1, tagged or dark surroundings, blood
brightness, wall thickness, intensity scale), plus random combinations. Only phase 0 (ED) of
every planned slice is rendered (3 sub-planes, ~180 mm field of view). Two paths are scored
against the simulator's ED myocardium (slab fraction ≥ 0.5, as ``simulate_study.ed_masks``):

* ``stream`` — :class:`StreamingMasker` fed SA base → apex then LA (the tag detector's path);
* ``batch`` — :func:`segment_sa` / :func:`segment_la` around the long axis that
  :func:`register_ed` estimates from the plane geometry.

Drawn protocols (``--protocols``): the ED frames of ``mlv-ros simulate --random SEED`` studies
(the protocol's own size, sub-planes and noise; abnormal regions off, as ``bench/robustness.py``
draws them), each with the right ventricle forced on and/or off (``--rv``), scored on the batch
path, plus the fraction of :func:`register_ed`'s ED particles inside the true myocardium
(``--particles``; what ``bench/robustness.py`` reports as ``inside_myocardium``).

Usage: .venv/bin/python bench/segmentation.py [--cases NAME ...] [--random N] [--seed S]
       [--paths stream batch]
       .venv/bin/python bench/segmentation.py --protocols 2000-2020 [--rv on off] [--particles]
       .venv/bin/mlv-ros bench segmentation -- --cases normal foreign
(all cases, both paths: ~80 s on one core; 21 protocols with and without the RV: ~5 min).
"""

from __future__ import annotations

import argparse
import json
import time

from mlv_ros.core.registration import register_ed, segment_around_axis
from mlv_ros.core.registration import segment as seg
from mlv_ros.core.registration.streaming import StreamingMasker
from mlv_ros.core.sim.imaging import ImageSynthesizer, plan_slices
from mlv_ros.core.sim.motion import LVMotion
from mlv_ros.core.sim.presets import load_preset
from mlv_ros.core.sim.protocol import draw_protocol, protocol_preset
from mlv_ros.core.types import Frame, VIEW_LA, VIEW_SA
import numpy as np

#: Field of view of the rendered images, mm (size = FOV / pixel, clipped to [96, 192] px).
FOV_MM = 180.0

#: Thin-wall variant of the normal LV: 6 mm wall (endo 33 / epi 39 mm, apical wall 6 mm).
THIN = {'endo_radius_mm': 33.0, 'epi_radius_mm': 39.0, 'endo_depth_mm': 79.0}

#: Another simulator's study: 9 mm wall, 8 mm grid at 45°, 1.4 mm pixels, only the heart tagged.
FOREIGN = {
    'tag_angle_deg': 45.0,
    'tag_spacing_mm': 8.0,
    'pixel_spacing_mm': 1.4,
    'background_m0': 0.0,
}


def cases() -> dict:
    """Named cases: ``{name: {"preset", "imaging", "geometry", "scale", "time_s"}}``."""
    c = {'normal': {}}
    for a in (20, 45, 70, 90, 135, 160):
        c[f'angle{a}'] = {'imaging': {'tag_angle_deg': float(a)}}
    for p in (5.0, 6.0, 8.0, 10.0):
        c[f'period{p:g}'] = {'imaging': {'tag_spacing_mm': p}}
    for px in (1.0, 1.6, 2.0):
        c[f'pixel{px:g}'] = {'imaging': {'pixel_spacing_mm': px}}
    for s in (10.0, 40.0):
        c[f'snr{s:g}'] = {'imaging': {'snr': s}}
    for t1 in (
        0.8,
        1.2,
    ):  # at t = 0 (ED) T1 does not matter; at 60 ms the tags have faded a little
        c[f't1_{t1:g}'] = {'imaging': {'t1_s': t1}, 'time_s': 0.06}
    for b in (0.0, 0.2, 0.5):
        c[f'bg{b:g}'] = {'imaging': {'background_m0': b}}
    for b in (0.3, 0.8, 1.3):
        c[f'blood{b:g}'] = {'imaging': {'blood_m0': b}}
    c['blood0.3_bg0'] = {'imaging': {'blood_m0': 0.3, 'background_m0': 0.0}}
    c['wall6'] = {'geometry': THIN}
    c['wall6_period10'] = {'geometry': THIN, 'imaging': {'tag_spacing_mm': 10.0}}
    c['hypertrophic'] = {'preset': 'hypertrophic'}
    c['scale1000'] = {'scale': 1000.0}
    c['scale0.01'] = {'scale': 0.01}
    c['foreign'] = {'imaging': dict(FOREIGN)}
    c['px1.9_period10'] = {'imaging': {'pixel_spacing_mm': 1.9, 'tag_spacing_mm': 10.0}}
    return c


def random_cases(n: int, seed: int) -> dict:
    """``n`` random combinations over the supported ranges."""
    rng = np.random.default_rng(seed)
    out = {}
    for i in range(n):
        px = float(rng.uniform(1.0, 2.0))
        period = float(rng.uniform(max(5.0, 3.5 * px), 10.0))
        im = {
            'tag_angle_deg': float(rng.uniform(0, 180)),
            'tag_spacing_mm': round(period, 2),
            'pixel_spacing_mm': round(px, 2),
            'snr': float(rng.uniform(10, 40)),
            'background_m0': float(rng.choice([0.0, rng.uniform(0.2, 0.5)])),
            'blood_m0': float(rng.uniform(0.3, 1.3)),
        }
        wall = rng.choice(['normal', 'thin', 'hypertrophic'])
        out[f'random{i}'] = {
            'preset': 'hypertrophic' if wall == 'hypertrophic' else 'normal',
            'geometry': THIN if wall == 'thin' else {},
            'imaging': im,
            'scale': float(10 ** rng.uniform(-2, 3)),
        }
    return out


def ed_frames(motion, imaging: dict, size: int, rng, time_s: float = 0.0, scale: float = 1.0):
    """
    Render phase 0 of every planned slice and its true myocardium mask.

    Parameters
    ----------
    motion : LVMotion
        The study's motion.
    imaging : dict
        Its preset's ``imaging`` section.
    size : int
        Rows = columns, px.
    rng : numpy.random.Generator
        Noise draws, in slice order.
    time_s : float
        Time of the frame after the tagging, s (tags fade with T1).
    scale : float
        Intensity scale applied to every image.

    Returns
    -------
    frames : list of Frame
        SA base → apex, then LA.
    truth : dict
        ``(view, slice_index) -> bool (rows, cols)``.

    """
    frames, truth = [], {}
    for sl in plan_slices(motion, imaging, size):
        syn = ImageSynthesizer(motion, sl, size, imaging)
        img = syn.render(0, time_s, float(imaging['snr']), rng) * scale
        frames.append(
            Frame(
                image=img,
                geometry=sl.geometry,
                view=sl.view,
                slice_index=sl.index,
                phase_index=0,
                num_phases=motion.num_phases,
                trigger_time=time_s,
                cycle_duration=motion.cycle_duration,
            )
        )
        truth[(sl.view, sl.index)] = syn.tissue_fractions(0)[0] >= 0.5
    return frames, truth


def render_ed(spec: dict, seed: int = 0):
    """
    ED frames of every planned slice of a named case and their true myocardium masks.

    The preset with the case's overrides, 3 sub-planes, a ~180 mm field of view; returns
    ``(frames, truth)`` as :func:`ed_frames`.
    """
    p = load_preset(spec.get('preset', 'normal'))
    p['geometry'].update(spec.get('geometry', {}))
    im = p['imaging']
    im.update(spec.get('imaging', {}))
    im['subplanes'] = 3
    n = int(np.clip(round(FOV_MM / float(im['pixel_spacing_mm'])), 96, 192))
    im['size'] = n
    motion = LVMotion(p)
    frames, truth = ed_frames(
        motion,
        im,
        n,
        np.random.default_rng(seed),
        float(spec.get('time_s', 0.0)),
        float(spec.get('scale', 1.0)),
    )
    return frames, truth


def render_protocol(seed: int, rv: bool):
    """
    ED frames of a drawn protocol, their true myocardium masks and the motion.

    Parameters
    ----------
    seed : int
        Protocol seed (:func:`draw_protocol`); also seeds the noise.
    rv : bool
        Right ventricle beside the LV or not (the other items as drawn; abnormal regions off).

    Returns
    -------
    protocol : dict
    frames : list of Frame
    truth : dict
        ``(view, slice_index) -> bool (rows, cols)``.
    motion : LVMotion

    """
    protocol = draw_protocol(seed, {'right_ventricle': bool(rv), 'abnormal_regions': []})
    pre = protocol_preset(protocol)
    motion = LVMotion(pre)
    im = pre['imaging']
    frames, truth = ed_frames(motion, im, im['size'], np.random.default_rng(seed))
    return protocol, frames, truth, motion


def protocol_rows(seeds: list, rvs: list, particles: bool) -> dict:
    """
    Score the batch path (and optionally the registered particles) on drawn protocols.

    Parameters
    ----------
    seeds : list of int
        Protocol seeds.
    rvs : list of str
        ``"on"`` and/or ``"off"``: the right ventricle forced.
    particles : bool
        Also register the ED model (3000 particles) and report the fraction inside the truth.

    Returns
    -------
    dict
        ``{"rows": [...], "summary": {rv: {...}}}``.

    """
    rows = []
    for rv in rvs:
        for seed in seeds:
            protocol, frames, truth, motion = render_protocol(seed, rv == 'on')
            t0 = time.perf_counter()
            row = {'seed': seed, 'rv': rv, **score(segment_around_axis(frames), truth)}
            row['seconds'] = round(time.perf_counter() - t0, 2)
            row['pixel_mm'] = protocol['pixel_spacing_mm']
            row['tag_mm'] = protocol['tag_spacing_mm']
            if particles:
                try:
                    reg = register_ed(frames, num_particles=3000)
                    row['inside_myocardium'] = round(
                        float(np.mean(motion.inside_myocardium(reg.particles))), 3
                    )
                except ValueError as exc:
                    row['inside_myocardium'] = None
                    row['registration_error'] = str(exc)
            rows.append(row)
    summary = {}
    for rv in rvs:
        mine = [r for r in rows if r['rv'] == rv]
        summary[rv] = {}
        for view in ('SA', 'LA'):
            d = [x for r in mine for x in r[view]['per_slice']]
            summary[rv][view] = {
                'mean_dice': round(float(np.mean(d)), 3),
                'failed': sum(len(r[view]['failed']) for r in mine),
                'slices': len(d),
            }
        inside = [r['inside_myocardium'] for r in mine if r.get('inside_myocardium') is not None]
        if inside:
            summary[rv]['inside_myocardium'] = {
                'mean': round(float(np.mean(inside)), 3),
                'min': round(float(np.min(inside)), 3),
            }
    return {'rows': rows, 'summary': summary}


def _seed_list(text: str) -> list:
    """``"2000-2020"`` or ``"1009,2007"`` (or a mix) -> the seeds."""
    out = []
    for part in text.split(','):
        lo, _, hi = part.partition('-')
        out += list(range(int(lo), int(hi or lo) + 1))
    return out


def stream_masks(frames: list) -> dict:
    """``{key: (mask or None, reason)}`` from a :class:`StreamingMasker` fed in order."""
    m = StreamingMasker()
    return {(f.view, f.slice_index): m.ed_mask(f) for f in frames}


def score(masks: dict, truth: dict) -> dict:
    """Per-view Dice summary; a failed slice scores 0 and its reason is kept."""
    out = {}
    for view, name in ((VIEW_SA, 'SA'), (VIEW_LA, 'LA')):
        keys = sorted(k for k in truth if k[0] == view)
        d = [seg.dice(masks[k][0], truth[k]) if masks[k][0] is not None else 0.0 for k in keys]
        fails = {f'{name}{k[1]}': masks[k][1] for k in keys if masks[k][0] is None}
        out[name] = {
            'min': round(min(d), 3),
            'mean': round(float(np.mean(d)), 3),
            'per_slice': [round(x, 3) for x in d],
            'failed': fails,
        }
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument('--cases', nargs='*', default=None, help='case names (default: all)')
    ap.add_argument('--random', type=int, default=6, help='random combinations to add')
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--paths', nargs='+', default=['stream', 'batch'], choices=['stream', 'batch'])
    ap.add_argument(
        '--protocols',
        type=_seed_list,
        default=None,
        help='drawn protocol seeds instead of the named cases, e.g. 2000-2020 or 1009,2007',
    )
    ap.add_argument(
        '--rv', nargs='+', default=['on', 'off'], choices=['on', 'off'], help='with --protocols'
    )
    ap.add_argument(
        '--particles',
        action='store_true',
        help='with --protocols: also the registered particles inside the true myocardium',
    )
    a = ap.parse_args()
    if a.protocols:
        t_all = time.perf_counter()
        out = protocol_rows(a.protocols, a.rv, a.particles)
        out['seconds'] = round(time.perf_counter() - t_all, 1)
        print(json.dumps(out, indent=1))
        return
    allc = {**cases(), **random_cases(a.random, a.seed)}
    names = a.cases if a.cases else list(allc)
    results = []
    t_all = time.perf_counter()
    for name in names:
        spec = allc[name]
        frames, truth = render_ed(spec)
        row = {'case': name, 'spec': spec, 'size': int(frames[0].image.shape[0])}
        for path in a.paths:
            t0 = time.perf_counter()
            masks = stream_masks(frames) if path == 'stream' else segment_around_axis(frames)
            row[path] = score(masks, truth)
            row[path]['seconds'] = round(time.perf_counter() - t0, 2)
        results.append(row)
    worst = {p: {v: min(r[p][v]['min'] for r in results) for v in ('SA', 'LA')} for p in a.paths}
    failed = {
        p: sum(len(r[p][v]['failed']) for r in results for v in ('SA', 'LA')) for p in a.paths
    }
    print(
        json.dumps(
            {
                'cases': results,
                'worst_min_dice': worst,
                'failed_slices': failed,
                'seconds': round(time.perf_counter() - t_all, 1),
            },
            indent=1,
        )
    )


if __name__ == '__main__':
    main()
