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
The DICOM reader's tag tests on random protocols: tagged studies against untagged ones.

For each protocol seed a random acquisition protocol is drawn
(:func:`mlv_ros.core.sim.protocol.draw_protocol`, its RV drawn as usual; the surroundings cycle
through ``none``, ``untagged`` (tags on the heart alone) and ``tagged``) and, per noise draw, four
studies of it are simulated: **tagged** as drawn (a tag grid), **single** (one family of tag
lines, protocol item ``tag_lines: single``), **untagged** (the same anatomy, contrast and noise
with zero tag contrast) and **ssfp** (untagged, bright blood 1.5–3 × myocardium, untagged
surroundings 0.1–0.6: a bright-blood cine). What the reader's vote looks at is rendered: the
first two images of every cine at the protocol's own phase count (ED and the next), stored as
the protocol's DICOM encoding stores them (8/12/16 bits, range fill over these images,
intercept).

Measured, per kind and surroundings (``heart_only`` or ``surrounded``):

* ``cine_clear``: each cine's whole-image grid score (``dicom._tag_grid``, clearly tagged at
  ``dicom._TAG_CLEAR``);
* ``grid``, ``line``: each study's vote (``dicom._study_vote``): the median over its cines of
  their strongest windowed grid / tag line at one period, in units of the image's own spectral
  background (thresholds ``dicom._TAG_STUDY`` and ``dicom._TAG_LINES``);
* ``score``: the vote in units of its threshold (≥ 1: tagged), what ranks studies.

``grid_margin`` = smallest tagged (grid) heart-only grid vote / largest untagged grid vote;
``line_margin`` = smallest single-line line vote / largest untagged line vote;
``pairwise``: every tagged or single-line study of a draw against every untagged study of that
draw (what decides a folder holding both): the worst ``score`` ratio and the pairs lost;
``single_line_found`` / ``grid_called_single``: how the vote names tag lines. JSON on stdout.

Usage: ``mlv-ros bench tag_test [-- --protocols 60 --draws 2 --seed 0]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from mlv_ros.core.io import dicom
from mlv_ros.core.sim.imaging import ImageSynthesizer, plan_slices
from mlv_ros.core.sim.motion import LVMotion
from mlv_ros.core.sim.presets import load_preset
from mlv_ros.core.sim.protocol import draw_protocol, LEGACY_PIXEL_SCALE, protocol_preset
import numpy as np

KINDS = ('tagged', 'single', 'untagged', 'ssfp')
TAGGED = ('tagged', 'single')


def _stored(images: np.ndarray, p: dict) -> np.ndarray:
    """
    Return ``images`` as the protocol's DICOM encoding stores them, float32.

    Parameters
    ----------
    images : ndarray
        The study's rendered images, any shape.
    p : dict
        The protocol (``dicom_bits``, ``dicom_rescale_intercept``, ``dicom_range_fill``: the
        range fill is taken over these images, as ``dicom_options`` takes it over the study's).

    Returns
    -------
    ndarray
        Rounded, clipped to BitsStored.

    """
    bits, inter, fill = p['dicom_bits'], p['dicom_rescale_intercept'], p['dicom_range_fill']
    top = (1 << int(bits)) - 1
    if fill is None:
        scale = LEGACY_PIXEL_SCALE
    else:
        scale = fill * top / max(float(images.max()) - inter, 1e-6)
    return np.clip(np.round((images - inter) * scale), 0, top).astype(np.float32)


def _study(seed: int, draw: int, kind: str, p: dict) -> list[list[np.ndarray]]:
    """
    Return the vote images (ED and the next) of each cine of one simulated study.

    Parameters
    ----------
    seed : int
        Protocol seed (seeds the bright-blood contrast).
    draw : int
        Noise draw.
    kind : str
        One of :data:`KINDS`.
    p : dict
        The drawn protocol.

    Returns
    -------
    list of [ndarray, ndarray]
        Per cine, its first two stored images.

    """
    preset = protocol_preset(p)
    im = preset['imaging']
    if kind == 'single':
        im['tag_lines'] = 'single'
    if kind in ('untagged', 'ssfp'):
        im['tag_spacing_mm'] = 1e6
    if kind == 'ssfp':
        r = np.random.default_rng([seed, 7])
        im.update(
            blood_m0=float(r.uniform(1.5, 3.0)),
            background_m0=float(r.uniform(0.1, 0.6)),
            background_tagged=False,
        )
    im['subplanes'] = 3
    preset = load_preset(preset)
    im = preset['imaging']
    motion = LVMotion(preset)
    rng = np.random.default_rng([seed, draw, KINDS.index(kind)])
    n = int(im['size'])
    images = []
    for sl in plan_slices(motion, im, n):
        syn = ImageSynthesizer(motion, sl, n, im)
        images.append([syn.render(ph, float(motion.times[ph]), p['snr'], rng) for ph in range(2)])
    images = np.array(images)
    return [list(c) for c in _stored(images, p)]


def _stats(v) -> dict:
    """Return n, min, p10, median, p90 and max of ``v``, rounded."""
    v = np.asarray(v, np.float64)
    return {
        'n': int(v.size),
        'min': round(float(v.min()), 3),
        'p10': round(float(np.percentile(v, 10)), 3),
        'median': round(float(np.median(v)), 3),
        'p90': round(float(np.percentile(v, 90)), 3),
        'max': round(float(v.max()), 3),
    }


def main(argv=None) -> int:
    """
    Run the tag-test bench and print its JSON.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        0.

    """
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--protocols', type=int, default=60, help='protocol seeds (default 60)')
    ap.add_argument('--draws', type=int, default=2, help='noise draws per protocol (default 2)')
    ap.add_argument('--seed', type=int, default=0, help='first protocol seed (default 0)')
    args = ap.parse_args(argv)
    cine: dict[str, list] = {}
    votes: dict[str, dict[str, list]] = {'grid': {}, 'line': {}, 'score': {}}
    by_draw: dict[int, dict[str, list]] = {}
    wrong_period, single_found, grid_single = [], 0, 0
    t_votes, n_cines = 0.0, 0
    for seed in range(args.seed, args.seed + args.protocols):
        bg = ('none', 'untagged', 'tagged')[seed % 3]
        p = draw_protocol(seed, {'background': bg, 'abnormal_regions': []})
        where = 'heart_only' if bg != 'tagged' else 'surrounded'
        px = p['pixel_spacing_mm']
        for draw in range(args.draws):
            for kind in KINDS:
                cines = _study(seed, draw, kind, p)
                key = f'{kind}/{where}'
                cine.setdefault(key, []).extend(dicom._tag_grid(c[0], px)[0] for c in cines)
                t0 = time.perf_counter()
                v = dicom._study_vote([(c, px) for c in cines])
                t_votes += time.perf_counter() - t0
                n_cines += len(cines)
                for name, value in (('grid', v.grid), ('line', v.line), ('score', v.score)):
                    votes[name].setdefault(key, []).append(value)
                entry = {'seed': seed, 'draw': draw, 'kind': kind, 'score': v.score}
                by_draw.setdefault(draw, {}).setdefault(kind, []).append(entry)
                if kind == 'single':
                    single_found += int(v.single_line)
                if kind == 'tagged':
                    grid_single += int(v.single_line)
                if kind in TAGGED and v.score >= 1.0:
                    if abs(v.period_mm / p['tag_spacing_mm'] - 1.0) > 0.1:
                        wrong_period.append(
                            {
                                'seed': seed,
                                'draw': draw,
                                'kind': kind,
                                'found_mm': round(v.period_mm, 2),
                                'protocol_mm': p['tag_spacing_mm'],
                            }
                        )
    untagged = {
        name: [s for k, v in d.items() if k.split('/')[0] not in TAGGED for s in v]
        for name, d in votes.items()
    }
    worst, lost, n_pairs = np.inf, [], 0
    for draw, kinds in by_draw.items():
        for t in kinds['tagged'] + kinds['single']:
            for u in kinds['untagged'] + kinds['ssfp']:
                n_pairs += 1
                ratio = t['score'] / max(u['score'], 1e-12)
                if ratio < worst:
                    worst = ratio
                    pair = {'tagged': t, 'untagged': u}
                if ratio <= 1.0:
                    lost.append({'tagged': t, 'untagged': u})
    n_single = len(by_draw[0]['single']) * len(by_draw)
    out = {
        'protocols': args.protocols,
        'draws': args.draws,
        'first_seed': args.seed,
        'thresholds': {
            'cine_clear': dicom._TAG_CLEAR,
            'grid': dicom._TAG_STUDY,
            'line': dicom._TAG_LINES,
            'single_line_ratio': dicom._SINGLE_LINE_RATIO,
        },
        'cine_clear': {k: _stats(v) for k, v in sorted(cine.items())},
        'votes': {n: {k: _stats(v) for k, v in sorted(d.items())} for n, d in votes.items()},
        'grid_margin': round(
            min(votes['grid']['tagged/heart_only']) / max(untagged['grid']), 3
        ),
        'line_margin': round(
            min(min(v) for k, v in votes['line'].items() if k.startswith('single/'))
            / max(untagged['line']),
            3,
        ),
        'pairwise': {
            'pairs': n_pairs,
            'lost': len(lost),
            'worst_ratio': round(float(worst), 3),
            'worst_pair': pair,
            'lost_pairs': lost[:10],
        },
        'untagged_passing': int(sum(s >= 1.0 for s in untagged['score'])),
        'tagged_failing': int(
            sum(s < 1.0 for k, v in votes['score'].items() if k.split('/')[0] in TAGGED for s in v)
        ),
        'single_line_found': f'{single_found} of {n_single}',
        'grid_called_single': grid_single,
        'tagged_period_off_by_10pct': wrong_period,
        'ms_per_cine_vote': round(1000.0 * t_votes / max(n_cines, 1), 1),
    }
    json.dump(out, sys.stdout, indent=2)
    print()
    return 0


if __name__ == '__main__':
    sys.exit(main())
