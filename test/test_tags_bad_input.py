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

"""Bad images give an empty result with a reason, never an exception."""

from hypothesis import given, HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from mlv_ros.core.geometry import SliceGeometry
from mlv_ros.core.sim.tag_scene import TagScene
from mlv_ros.core.tags import detect_intersections, harp_track, SliceTracker
from mlv_ros.core.types import Frame
import numpy as np
import pytest

GEOM = SliceGeometry(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 1.3, 1.3, 6.0)


def _nan_image():
    img = TagScene(shape=(64, 64)).render(0.0)
    img[10, 20] = np.nan
    return img


BAD = {
    'no tags (smooth anatomy + noise)': (
        lambda: (
            100
            + 10 * np.hypot(*np.mgrid[-32:32, -32:32]) / 32
            + np.random.default_rng(0).standard_normal((64, 64))
        ),
        'no',
    ),
    'fully faded tags': (lambda: TagScene(shape=(64, 64), t1_fraction=1e-3).render(1.0), 'no'),
    'constant image': (lambda: np.full((64, 64), 7.0), 'constant'),
    'NaN pixels': (_nan_image, 'non-finite'),
    'tiny image': (lambda: np.ones((8, 8)), 'too small'),
    '1-D input': (lambda: np.arange(100.0), '2-D'),
    'non-numeric': (lambda: np.array([['a', 'b'], ['c', 'd']]), 'numeric'),
}


@pytest.mark.parametrize('name', list(BAD))
def test_detect_rejects_with_reason(name):
    make, word = BAD[name]
    det = detect_intersections(make())
    assert len(det) == 0
    assert word in det.reason, det.reason


@pytest.mark.parametrize('name', list(BAD))
def test_tracker_returns_empty_set_with_status(name):
    make, _ = BAD[name]
    tr = SliceTracker(GEOM)
    out = tr.update(Frame(make(), GEOM, 0, 0, 0, 3))
    assert len(out) == 0 and out.status
    # Later phases report that there is no ED reference rather than inventing points.
    good = TagScene(shape=(64, 64), ring=(10.5, 24.5)).render(0.1)
    out = tr.update(Frame(good, GEOM, 0, 0, 1, 3))
    assert len(out) == 0 and 'no ED reference' in out.status


def test_tracker_survives_bad_frame_mid_cine():
    scene = TagScene(shape=(96, 96), ring=(14.5, 30.5))
    tr = SliceTracker(GEOM)
    ed = tr.update(Frame(scene.render(0.0), GEOM, 0, 0, 0, 4), mask=scene.myocardium_mask(0.0))
    assert len(ed) > 20 and ed.status == ''
    out = tr.update(Frame(np.full((96, 96), np.nan), GEOM, 0, 0, 1, 4))
    assert len(out) == 0 and 'non-finite' in out.status
    # A garbage object instead of a Frame: reported, not raised.
    out = tr.update(None)
    assert len(out) == 0 and 'error' in out.status


def test_mask_problems_are_reasons():
    img = TagScene(shape=(64, 64)).render(0.0)
    assert 'shape' in detect_intersections(img, mask=np.ones((10, 10), bool)).reason
    assert 'empty' in detect_intersections(img, mask=np.zeros((64, 64), bool)).reason


def test_harp_with_bad_frames_reports_instead_of_raising():
    scene = TagScene(shape=(64, 64), ring=(10.5, 24.5))
    det = detect_intersections(scene.render(0.0), scene.myocardium_mask(0.0))
    res = harp_track([scene.render(0.0), np.full((64, 64), np.nan)], det.pixel_rc, det.params)
    assert res.valid[0].all() and not res.valid[1].any()
    res = harp_track([np.zeros((64, 64))], det.pixel_rc, det.params)
    assert 'constant' in res.reason


@settings(
    max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)
@given(
    arrays(
        np.float64,
        st.tuples(st.integers(1, 48), st.integers(1, 48)),
        elements=st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32), st.just(0.0)),
    )
)
def test_arbitrary_arrays_never_raise(img):
    det = detect_intersections(img)
    # Either points and no reason, or no points and a reason.
    assert (len(det) > 0) != bool(det.reason)
    out = SliceTracker(GEOM).update(Frame(img, GEOM, 0, 0, 0, 2))
    assert len(out) > 0 or out.status
