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
A phantom frame rendered on demand, in any order, equals the same frame of the whole study.

The study's noise is one generator drawn slice-major (:func:`simulate_study`); the frame source
renders phase-major, one frame at a time (:class:`StudyRenderer`), and must publish the very
images the whole study holds.
"""

from mlv_ros.core.sim import simulate_study
from mlv_ros.core.sim.study import SliceMajorNoise, StudyRenderer
import numpy as np
import pytest

SMALL = {'snr': 20.0, 'size': 40, 'num_phases': 3, 'seed': 7, 'subplanes': 1}


@pytest.fixture(scope='module')
def whole():
    return {
        (f.view, f.slice_index, f.phase_index): f for f in simulate_study('normal', **SMALL).frames
    }


def _assert_same(frame, ref):
    assert frame.image.dtype == np.float32 and frame.image.shape == ref.image.shape
    np.testing.assert_array_equal(frame.image, ref.image)
    for attr in ('view', 'slice_index', 'phase_index', 'num_phases', 'series_uid'):
        assert getattr(frame, attr) == getattr(ref, attr)
    assert frame.trigger_time == ref.trigger_time
    np.testing.assert_array_equal(frame.geometry.image_position, ref.geometry.image_position)


@pytest.mark.parametrize('order', ['phase_major', 'reversed', 'alone'])
def test_frames_rendered_in_any_order_equal_the_whole_study(whole, order):
    keys = sorted(whole, key=lambda k: (k[2], k[0], k[1]))  # phase-major, as the source sends
    if order == 'reversed':
        keys = keys[::-1]
    elif order == 'alone':
        keys = [keys[-1], keys[0]]  # the last slice's last phase first, in a fresh renderer
    r = StudyRenderer('normal', **SMALL)
    for k in keys:
        _assert_same(r.frame(*k), whole[k])
    # noise is drawn: another seed gives other images, the plan (metadata only) stays
    other = StudyRenderer('normal', **{**SMALL, 'seed': 8}).frame(*keys[0])
    assert not np.array_equal(other.image, whole[keys[0]].image)
    assert r.frame(*keys[0], image=False).image is None


def test_noise_positions_follow_one_generator_slice_major():
    shape, phases = (3, 2), 4
    rng = np.random.default_rng(11)
    expected = [[rng.standard_normal(shape) for _ in range(2 * phases)] for _ in range(3)]
    slice_major = [(pos, ph) for pos in range(3) for ph in range(phases)]
    for order in ([(2, 3), (0, 0), (0, 1), (1, 2), (0, 0), (2, 1)], slice_major):
        noise = SliceMajorNoise(11, phases, shape)
        for pos, ph in order:
            g = noise.generator(pos, ph)
            np.testing.assert_array_equal(g.standard_normal(shape), expected[pos][2 * ph])
            np.testing.assert_array_equal(g.standard_normal(shape), expected[pos][2 * ph + 1])


def test_renderer_refuses_frames_outside_the_study():
    r = StudyRenderer('normal', **SMALL)
    with pytest.raises(ValueError, match='no slice'):
        r.frame(0, 99, 0)
    with pytest.raises(ValueError, match='phase must be in 0..2'):
        r.frame(0, 0, 3)
