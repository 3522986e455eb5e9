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
Image filters shared by tag detection and segmentation.

:func:`running_median` is the image's running median over a square window (``scipy.ndimage``'s
``median_filter``, ``mode="reflect"``), kept for the images it was last asked for: the tag
detector and the registration each take it of every ED frame (tag-period estimation,
:func:`mlv_ros.core.registration.segment.tag_wavevectors` and
:func:`mlv_ros.core.tags.intersections.estimate_grid`), at ~0.2 s per 256² frame the largest
single cost of a whole study in one process (6.8 s of ~60 s profiled, 33 calls for 11 ED
frames). A result is returned for bit-identical input only (keyed by a digest of the pixels).
"""

from __future__ import annotations

from collections import OrderedDict
import hashlib
import threading

import numpy as np
from scipy import ndimage as ndi

CACHE_SIZE = 32  # images (a study's ED frames, each at one or two window sizes)
_cache: OrderedDict = OrderedDict()
_lock = threading.Lock()
stats = {'hits': 0, 'misses': 0}


def running_median(image: np.ndarray, size: int) -> np.ndarray:
    """
    ``ndi.median_filter(image, size=size, mode="reflect")`` of a 2-D float64 image, cached.

    The caller must not modify the returned array (it is shared; it is marked read-only).
    """
    img = np.ascontiguousarray(image, dtype=np.float64)
    h = hashlib.blake2b(img.view(np.uint8).ravel(), digest_size=16)
    key = (img.shape, int(size), h.digest())
    with _lock:
        out = _cache.get(key)
        if out is not None:
            _cache.move_to_end(key)
            stats['hits'] += 1
            return out
    out = ndi.median_filter(img, size=int(size), mode='reflect')
    out.flags.writeable = False
    with _lock:
        stats['misses'] += 1
        _cache[key] = out
        while len(_cache) > CACHE_SIZE:
            _cache.popitem(last=False)
    return out
