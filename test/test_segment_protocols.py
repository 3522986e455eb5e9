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
ED segmentation on tagged studies unlike our default phantom.

Each case is a preset with some imaging or geometry keys overridden, as another scanner or
simulator would acquire it: grid at 45° with only the heart tagged, bright blood, a 17 mm wall,
coarse pixels under a long tag period, an arbitrary intensity scale. Only phase 0 (ED) is
rendered, 3 sub-planes, ~180 mm field of view. Both paths are scored against the simulator's ED
myocardium (slab fraction ≥ 0.5, as ``simulate_study`` builds ``ed_masks``): the streaming
masker fed SA base → apex then LA (the tag detector), and :func:`segment_sa` /
:func:`segment_la` around the geometric long axis (:func:`register_ed`).
"""

import dataclasses

from mlv_ros.core.registration import segment as seg
from mlv_ros.core.registration import segment_around_axis
from mlv_ros.core.registration.streaming import StreamingMasker
from mlv_ros.core.sim.imaging import ImageSynthesizer, plan_slices
from mlv_ros.core.sim.motion import LVMotion
from mlv_ros.core.sim.presets import load_preset
from mlv_ros.core.types import Frame, VIEW_LA, VIEW_SA
import numpy as np
import pytest

#: Acceptance: every slice segmented, Dice ≥ 0.8 SA and ≥ 0.75 LA.
MIN_DICE = {VIEW_SA: 0.80, VIEW_LA: 0.75}

CASES = {
    # Another simulator's study: 8 mm grid at 45°, 1.4 mm pixels, only the heart tagged.
    'grid45_dark': {
        'imaging': {
            'tag_angle_deg': 45.0,
            'tag_spacing_mm': 8.0,
            'pixel_spacing_mm': 1.4,
            'background_m0': 0.0,
        }
    },
    # Blood 1.3 × the untagged myocardium (5 × the tagged wall's mean).
    'bright_blood': {'imaging': {'blood_m0': 1.3}},
    # 17 mm wall (hypertrophic preset, cavity narrowed).
    'wall17': {
        'preset': 'hypertrophic',
        'geometry': {'endo_radius_mm': 23.0, 'endo_depth_mm': 68.0},
    },
    # 1.9 mm pixels under a 10 mm grid: 5.3 px per period, a 9 mm wall is 4.7 px.
    'px1.9_period10': {'imaging': {'pixel_spacing_mm': 1.9, 'tag_spacing_mm': 10.0}},
    # Any intensity unit.
    'scale1000': {'scale': 1000.0},
}


def render_ed(spec: dict, seed: int = 0):
    """ED frames (SA base → apex, then LA) and true masks of a preset with overrides."""
    p = load_preset(spec.get('preset', 'normal'))
    p['geometry'].update(spec.get('geometry', {}))
    im = p['imaging']
    im.update(spec.get('imaging', {}))
    im['subplanes'] = 3
    n = int(np.clip(round(180.0 / float(im['pixel_spacing_mm'])), 96, 160))
    im['size'] = n
    motion = LVMotion(p)
    rng = np.random.default_rng(seed)
    frames, truth = [], {}
    for sl in plan_slices(motion, im, n):
        syn = ImageSynthesizer(motion, sl, n, im)
        img = syn.render(0, 0.0, float(im['snr']), rng) * float(spec.get('scale', 1.0))
        frames.append(
            Frame(
                image=img,
                geometry=sl.geometry,
                view=sl.view,
                slice_index=sl.index,
                phase_index=0,
                num_phases=motion.num_phases,
                trigger_time=0.0,
                cycle_duration=motion.cycle_duration,
            )
        )
        truth[(sl.view, sl.index)] = syn.tissue_fractions(0)[0] >= 0.5
    return frames, truth


@pytest.fixture(scope='module')
def rendered():
    return {name: render_ed(spec) for name, spec in CASES.items()}


def _check(masks, truth):
    for k, (mask, why) in masks.items():
        assert mask is not None, f'{k}: {why}'
        d = seg.dice(mask, truth[k])
        assert d >= MIN_DICE[k[0]], f'{k}: Dice {d:.3f}'


@pytest.mark.parametrize('case', list(CASES))
def test_streaming_masker(rendered, case):
    frames, truth = rendered[case]
    m = StreamingMasker()
    _check({(f.view, f.slice_index): m.ed_mask(f) for f in frames}, truth)
    assert not m.failures


@pytest.mark.parametrize('case', ['grid45_dark', 'px1.9_period10'])
def test_around_the_geometric_axis(rendered, case):
    frames, truth = rendered[case]
    _check(segment_around_axis(frames), truth)


def test_intensity_scale_changes_nothing(rendered):
    frames, _ = rendered['bright_blood']
    for f in (frames[3], frames[-1]):  # a mid SA slice, an LA plane
        masks = [
            StreamingMasker().ed_mask(dataclasses.replace(f, image=f.image * s))[0]
            for s in (1.0, 0.01, 1000.0)
        ]
        if f.view == VIEW_LA:  # LA needs the axis from SA centres: use the axis path
            masks = [
                segment_around_axis(
                    [g for g in frames if g.view == VIEW_SA]
                    + [dataclasses.replace(f, image=f.image * s)]
                )[(f.view, f.slice_index)][0]
                for s in (1.0, 0.01, 1000.0)
            ]
        assert masks[0] is not None
        for m in masks[1:]:
            assert np.array_equal(m, masks[0])


def test_failure_is_reported_once_per_slice(rendered):
    frames, _ = rendered['grid45_dark']
    la = next(f for f in frames if f.view == VIEW_LA)
    m = StreamingMasker()
    mask, why = m.ed_mask(la)  # no SA centre yet
    assert mask is None and 'no SA slice' in why
    assert m.failures == {(VIEW_LA, la.slice_index): why}
    assert m.ed_mask(la) == (None, why)  # the same frame again: the same answer, kept
    noise = dataclasses.replace(
        frames[0], image=np.random.default_rng(1).normal(size=frames[0].image.shape)
    )
    mask, why = m.ed_mask(noise)
    assert mask is None and why.count('no tagged tissue around the long axis') == 1, why
    # Once the SA slices are in, the LA frame is segmented after all and leaves the failures.
    for f in frames:
        if f.view == VIEW_SA:
            assert m.ed_mask(f)[0] is not None
    assert m.ed_mask(la)[0] is not None
    assert (VIEW_LA, la.slice_index) not in m.failures
