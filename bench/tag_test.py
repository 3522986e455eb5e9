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
The DICOM reader's tag test on random protocols: tagged studies against untagged twins (issue 15).

For each protocol seed a random acquisition protocol is drawn
(:func:`mlv_ros.core.sim.protocol.draw_protocol`; the surroundings cycle through ``none`` and
``untagged``, i.e. tags on the heart alone, and ``tagged``) and three studies of it are simulated
with 2 phases: **tagged** as drawn, **untagged** (the same anatomy, contrast and noise with zero
tag contrast: tag period 10⁶ mm) and **ssfp** (untagged, bright blood 1.5–3 × myocardium,
untagged surroundings 0.1–0.6: a bright-blood cine). Each ED image is quantised as the
protocol's DICOM encoding stores it (8/12/16 bits, its range fill and intercept).

Measured, per kind and surroundings:

* ``cine_clear``: each cine's whole-image grid score (``dicom._tag_grid``, a cine is clearly
  tagged at ``dicom._TAG_CLEAR``);
* ``study_votes``: each study's common-grid score (``dicom._heart_grid``: the largest over tag
  periods of its cines' median windowed grid score; tagged on the heart alone at
  ``dicom._TAG_STUDY``), and whether its period is the protocol's within 10 %.

``margin`` = smallest tagged heart-only study score / largest untagged study score (> 1:
separated by the threshold); ``over_twins`` = per heart-only protocol, its tagged study's score
over the larger of its two untagged twins' (what decides a folder holding both: > 1, the tagged
one is taken). JSON on stdout.

Usage: ``mlv-ros bench tag_test [-- --protocols 30 --seed 0]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from mlv_ros.core.io import dicom
from mlv_ros.core.sim import simulate_study
from mlv_ros.core.sim.protocol import dicom_options, draw_protocol, protocol_preset
import numpy as np

KINDS = ('tagged', 'untagged', 'ssfp')


def _stored(image: np.ndarray, opts: dict) -> np.ndarray:
    """``image`` as the DICOM writer stores it (rounded, clipped to BitsStored), float32."""
    top = (1 << int(opts['bits_stored'])) - 1
    return np.clip(
        np.round((image - opts['rescale_intercept']) * opts['pixel_scale']), 0, top
    ).astype(np.float32)


def _study(seed: int, kind: str, protocol: dict):
    preset = protocol_preset(protocol)
    if kind != 'tagged':
        preset['imaging']['tag_spacing_mm'] = 1e6
    if kind == 'ssfp':
        r = np.random.default_rng([seed, 7])
        preset['imaging'].update(
            blood_m0=float(r.uniform(1.5, 3.0)),
            background_m0=float(r.uniform(0.1, 0.6)),
            background_tagged=False,
        )
    study = simulate_study(
        preset,
        snr=protocol['snr'],
        size=protocol['size'],
        num_phases=2,
        seed=seed,
        subplanes=3,
        pixel_spacing=protocol['pixel_spacing_mm'],
    )
    opts = dicom_options(protocol, study)
    return [_stored(f.image, opts) for f in study.frames if f.phase_index == 0]


def _stats(v) -> dict:
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
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--protocols', type=int, default=30, help='protocol seeds (default 30)')
    ap.add_argument('--seed', type=int, default=0, help='first protocol seed (default 0)')
    args = ap.parse_args(argv)
    cine: dict[str, list] = {}
    study: dict[str, list] = {}
    wrong_period: list = []
    over_twins: list = []
    t_votes, n_votes = 0.0, 0
    for seed in range(args.seed, args.seed + args.protocols):
        bg = ('none', 'untagged', 'tagged')[seed % 3]
        p = draw_protocol(
            seed,
            {'background': bg, 'num_phases': 2, 'abnormal_regions': [], 'right_ventricle': False},
        )
        where = 'heart_only' if bg != 'tagged' else 'surrounded'
        scores = {}
        for kind in KINDS:
            images = _study(seed, kind, p)
            cine.setdefault(f'{kind}/{where}', []).extend(
                dicom._tag_grid(im, p['pixel_spacing_mm'])[0] for im in images
            )
            t0 = time.perf_counter()
            score, period, _ = dicom._heart_grid([(im, p['pixel_spacing_mm']) for im in images])
            t_votes += time.perf_counter() - t0
            n_votes += len(images)
            study.setdefault(f'{kind}/{where}', []).append(score)
            scores[kind] = score
            if kind == 'tagged' and abs(period / p['tag_spacing_mm'] - 1.0) > 0.1:
                wrong_period.append(
                    {
                        'seed': seed,
                        'found_mm': round(period, 2),
                        'protocol_mm': p['tag_spacing_mm'],
                    }
                )
        if where == 'heart_only':
            over_twins.append(scores['tagged'] / max(scores['untagged'], scores['ssfp']))
    untagged = [s for k, v in study.items() if not k.startswith('tagged/') for s in v]
    out = {
        'protocols': args.protocols,
        'first_seed': args.seed,
        'thresholds': {'cine_clear': dicom._TAG_CLEAR, 'study_votes': dicom._TAG_STUDY},
        'cine_clear': {k: _stats(v) for k, v in sorted(cine.items())},
        'study_votes': {k: _stats(v) for k, v in sorted(study.items())},
        'margin': round(min(study['tagged/heart_only']) / max(untagged), 3),
        'over_twins': _stats(over_twins),
        'heart_only_above_every_untagged': int(
            sum(s > max(untagged) for s in study['tagged/heart_only'])
        ),
        'untagged_studies_passing': int(sum(s >= dicom._TAG_STUDY for s in untagged)),
        'heart_only_studies_failing': int(
            sum(s < dicom._TAG_STUDY for s in study['tagged/heart_only'])
        ),
        'tagged_period_off_by_10pct': wrong_period,
        'ms_per_image_votes': round(1000.0 * t_votes / max(n_votes, 1), 1),
    }
    json.dump(out, sys.stdout, indent=2)
    print()
    return 0


if __name__ == '__main__':
    sys.exit(main())
