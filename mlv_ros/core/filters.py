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

It is computed as scipy's is, to the bit, but ~6× faster (:func:`_median_by_rank`: 20 ms
instead of 126 ms per 256² ED frame of the default study at a 13-px window): the pixels are
replaced by their ranks in the whole image (16-bit integers up to 65,536 pixels), each window's
middle rank is selected with ``np.partition`` over a sliding-window view, and the rank is mapped
back to its pixel value. The order of values is the order of ranks, so the middle rank is the
middle value's, ties included. The middle ranks come from a compiled pass where ``make bootstrap``
built it (``_median.c``: Huang's sliding histogram on the ranks, two-level; issue 17: 2.5 ms
instead of ~110 ms of ``np.partition`` per 256² frame at 13 px, so ~20 instead of ~130 ms per
ED frame, in the tag detector's process and again in the registration's); the same integers,
so the same medians to the bit, with or without it (``MLV_ROS_COMPILED=0`` takes numpy's).
"""

from __future__ import annotations

from collections import OrderedDict
import ctypes
import hashlib
import os
from pathlib import Path
import threading

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import ndimage as ndi

CACHE_SIZE = 32  # images (a study's ED frames, each at one or two window sizes)
_cache: OrderedDict = OrderedDict()
_lock = threading.Lock()
stats = {'hits': 0, 'misses': 0}
LIBRARY = Path(__file__).with_name('_median_c.so')
_loaded = None  # [the compiled median of ranks or None], once tried


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
    size = int(size)
    if img.ndim == 2 and size % 2 and size // 2 < min(img.shape) and np.isfinite(img).all():
        out = _median_by_rank(img, size)
    else:  # even windows (scipy's origin), windows wider than the image, NaN: scipy's own
        out = ndi.median_filter(img, size=size, mode='reflect')
    out.flags.writeable = False
    with _lock:
        stats['misses'] += 1
        _cache[key] = out
        while len(_cache) > CACHE_SIZE:
            _cache.popitem(last=False)
    return out


def _median_by_rank(img: np.ndarray, size: int, rows: int = 32) -> np.ndarray:
    """
    Return ``ndi.median_filter(img, size=size, mode="reflect")`` computed on pixel ranks.

    Parameters
    ----------
    img : ndarray of float64, shape (H, W)
        Finite pixels, any units; the result has the same.
    size : int
        Odd window width, px, with ``size // 2 < min(H, W)`` (one reflection at the border).
    rows : int
        Output rows per ``np.partition`` call (bounds the work array to
        ``rows · W · size²`` ranks).

    Returns
    -------
    ndarray of float64, shape (H, W)

    """
    flat = img.ravel()
    order = np.argsort(flat, kind='stable')
    half = size // 2
    compiled = _compiled() if flat.size < 1 << 31 else None
    if compiled is not None:
        rank = np.empty(flat.size, np.int32)
        rank[order] = np.arange(flat.size, dtype=np.int32)
        # numpy's 'symmetric' is scipy's 'reflect' (d c b a | a b c d).
        pad = np.pad(rank.reshape(img.shape), half, mode='symmetric')
        return flat[order][compiled(pad, img.shape, half, flat.size)]
    rank = np.empty(flat.size, np.uint16 if flat.size <= 1 << 16 else np.uint32)
    rank[order] = np.arange(flat.size)
    pad = np.pad(rank.reshape(img.shape), half, mode='symmetric')
    h, w = img.shape
    mid = size * size // 2
    out = np.empty(img.shape, rank.dtype)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        win = sliding_window_view(pad[r0:r1 + 2 * half], (size, size)).reshape(r1 - r0, w, -1)
        out[r0:r1] = np.partition(win, mid, axis=-1)[..., mid]
    return flat[order][out]


def _compiled():
    """
    Return the compiled median of ranks, ``f(pad, (h, w), half, n) -> (h, w) int32``, or None.

    None when ``_median_c.so`` was not built (``make bootstrap``) or does not load, or with
    ``MLV_ROS_COMPILED=0`` set: :func:`_median_by_rank` then partitions with numpy.
    """
    global _loaded
    if os.environ.get('MLV_ROS_COMPILED', '').strip() == '0':
        return None
    if _loaded is None:
        _loaded = [None]
        try:
            lib = ctypes.CDLL(str(LIBRARY))
        except OSError:  # not built: numpy's partition
            return None
        p, i = ctypes.c_void_p, ctypes.c_int64
        lib.median_ranks.argtypes = [p, i, i, i, i, p]
        lib.median_ranks.restype = ctypes.c_int

        def median_ranks(pad, shape, half, n):
            h, w = (int(v) for v in shape)
            pad = np.ascontiguousarray(pad, dtype=np.int32)
            # The pass reads pad[0 : h + 2·half, 0 : w + 2·half] and indexes its histogram by
            # the values: both checked here, not trusted.
            if pad.shape != (h + 2 * half, w + 2 * half) or half < 0:
                raise ValueError(f'median of ranks: padded shape {pad.shape} for {(h, w)}')
            if pad.size and (int(pad.min()) < 0 or int(pad.max()) >= n):
                raise ValueError(f'median of ranks: a rank outside [0, {n})')
            out = np.empty((h, w), np.int32)
            if lib.median_ranks(pad.ctypes.data, h, w, int(half), int(n), out.ctypes.data):
                raise MemoryError('median of ranks: its histograms could not be allocated')
            return out

        _loaded = [median_ranks]
    return _loaded[0]
