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
The shared running median (``mlv_ros.core.filters``) against scipy's median filter.

The shared running median (``mlv_ros.core.filters``): scipy's median filter exactly, taken once
per image and window (the tag detector and the registration both ask for it of each ED frame).
"""

from mlv_ros.core import filters
import numpy as np
import pytest
from scipy import ndimage as ndi


def test_running_median_is_scipys_and_is_taken_once_per_image():
    rng = np.random.default_rng(0)
    img = rng.normal(size=(40, 48))
    before = dict(filters.stats)
    first = filters.running_median(img, 7)
    assert np.array_equal(first, ndi.median_filter(img, size=7, mode='reflect'))
    again = filters.running_median(img.copy(), 7)  # same pixels, another array: the kept result
    assert again is first and filters.stats['hits'] == before['hits'] + 1
    assert not first.flags.writeable  # shared: callers cannot change it for the next one
    other = img.copy()
    other[3, 4] += 1e-9  # one pixel differs in its last bits: computed anew
    assert np.array_equal(
        filters.running_median(other, 7), ndi.median_filter(other, size=7, mode='reflect')
    )
    assert not np.array_equal(filters.running_median(img, 9), first)  # another window
    assert filters.stats['misses'] == before['misses'] + 3


def test_running_median_keeps_a_bounded_number_of_images(monkeypatch):
    monkeypatch.setattr(filters, 'CACHE_SIZE', 2)
    imgs = [np.full((8, 8), float(i)) + np.eye(8) for i in range(4)]
    for im in imgs:
        filters.running_median(im, 3)
    assert len(filters._cache) <= 2
    with pytest.raises(ValueError):
        filters.running_median(imgs[0], 3)[0, 0] = 1.0


@pytest.mark.parametrize(
    'shape, size, ties',
    [
        ((40, 48), 7, False),
        ((33, 29), 13, True),  # few grey levels: many equal values per window
        ((9, 64), 17, False),  # window wider than the short side: two reflections, scipy's path
        ((20, 20), 6, False),  # even window: scipy's path (its origin)
        ((300, 260), 5, True),  # more pixels than 16-bit ranks hold
    ],
)
@pytest.mark.parametrize('compiled', ['1', '0'])
def test_running_median_by_rank_is_scipys_to_the_bit(shape, size, ties, compiled, monkeypatch):
    # Both the compiled middle ranks (_median.c, where make bootstrap built it) and numpy's
    # partition (MLV_ROS_COMPILED=0, or not built).
    if compiled == '1' and filters._compiled() is None:
        pytest.skip('_median_c.so is not built (make bootstrap): numpy only')
    monkeypatch.setenv('MLV_ROS_COMPILED', compiled)
    rng = np.random.default_rng(size)
    img = rng.normal(size=shape)
    if ties:
        img = np.round(img * 2) / 2
    filters._cache.clear()
    assert np.array_equal(
        filters.running_median(img, size), ndi.median_filter(img, size=size, mode='reflect')
    )


def test_compiled_median_of_ranks_refuses_what_it_cannot_index():
    compiled = filters._compiled()
    if compiled is None:
        pytest.skip('_median_c.so is not built (make bootstrap)')
    pad = np.arange(36, dtype=np.int32).reshape(6, 6)
    assert compiled(pad, (4, 4), 1, 36).shape == (4, 4)
    with pytest.raises(ValueError, match='outside'):
        compiled(pad, (4, 4), 1, 35)  # a rank beyond the histogram
    with pytest.raises(ValueError, match='padded shape'):
        compiled(pad, (5, 4), 1, 36)  # the pass would read past the array
