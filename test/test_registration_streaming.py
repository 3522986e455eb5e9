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

"""Streaming ED masks (:class:`StreamingMasker`) on the simulator, fed frame by frame."""

import dataclasses

from mlv_ros.core.registration import segment as seg
from mlv_ros.core.registration.segment import dice
from mlv_ros.core.registration.streaming import blood_pool_candidates, StreamingMasker
from mlv_ros.core.sim import simulate_study
from mlv_ros.core.tags import SliceTracker
from mlv_ros.core.types import VIEW_LA, VIEW_SA
import numpy as np
import pytest

MIN_DICE = 0.85


@pytest.fixture(scope='module')
def studies():
    return {p: simulate_study(p, snr=20, quick=True) for p in ('normal', 'hypertrophic')}


def _stream(frames):
    """Feed frames one at a time as the node does; ED masks per (view, slice)."""
    m = StreamingMasker()
    out = {}
    for f in frames:
        m.observe_geometry(f)
        if f.phase_index == 0:
            out[(f.view, f.slice_index)] = m.ed_mask(f)
    return m, out


@pytest.mark.parametrize('preset', ['normal', 'hypertrophic'])
@pytest.mark.parametrize('order', ['slice', 'phase'])
def test_dice_every_slice(studies, preset, order):
    st = studies[preset]
    frames = st.frames if order == 'slice' else sorted(st.frames, key=lambda f: f.phase_index)
    assert frames[0].view == VIEW_SA and frames[0].slice_index == 0
    _, out = _stream(frames)
    assert set(out) == set(st.ed_masks)
    for k, (mask, why) in out.items():
        assert mask is not None, f'{k}: {why}'
        assert mask.dtype == bool and mask.shape == st.ed_masks[k].shape
        assert dice(mask, st.ed_masks[k]) >= MIN_DICE, k


def test_tracks_survive_to_phase_1(studies):
    st = studies['normal']
    _, out = _stream(st.frames)
    for k, (mask, _) in out.items():
        cine = [f for f in st.frames if (f.view, f.slice_index) == k]
        tr = SliceTracker(cine[0].geometry)
        p0 = tr.update(cine[0], mask=mask)
        p1 = tr.update(cine[1])
        assert len(p0) > 0 and len(p1) > 0, (k, p1.status)
        # Tracks stay on the myocardium (not the static background).
        rc = np.round(p0.pixel_rc).astype(int)
        assert st.ed_masks[k][rc[:, 0], rc[:, 1]].mean() > 0.8, k


def test_long_axis_apex_to_base(studies):
    st = studies['normal']
    m, _ = _stream([f for f in st.frames if f.view == VIEW_SA])
    p, d, known = m.long_axis()
    assert known
    truth = st.motion.frame.long_axis
    assert d @ truth > np.cos(np.radians(5.0))
    # The axis passes within a few mm of the true base centre's projection.
    bc = st.motion.frame.base_centre
    off = (bc - p) - ((bc - p) @ d) * d
    assert np.linalg.norm(off) < 3.0


def test_first_slice_off_centre_blood_pool(studies):
    """No axis yet and the heart off the FOV centre: the image-based blood pool finds it."""
    st = studies['normal']
    f = next(
        f for f in st.frames if f.view == VIEW_SA and f.slice_index == 2 and f.phase_index == 0
    )
    shift = (18, -22)
    g = dataclasses.replace(f, image=np.roll(f.image, shift, axis=(0, 1)))
    truth = np.roll(st.ed_masks[(VIEW_SA, 2)], shift, axis=(0, 1))
    cands = blood_pool_candidates(seg.tag_features(g.image), f.geometry.row_spacing)
    assert cands and np.linalg.norm(cands[0] - (np.argwhere(truth).mean(0))) < 3.0
    mask, why = StreamingMasker().ed_mask(g)
    assert mask is not None, why
    assert dice(mask, truth) >= MIN_DICE


def test_bad_input(studies):
    st = studies['normal']
    sa0 = next(f for f in st.frames if f.view == VIEW_SA and f.phase_index == 0)
    la0 = next(f for f in st.frames if f.view == VIEW_LA and f.phase_index == 0)
    m = StreamingMasker()
    mask, why = m.ed_mask(la0)
    assert mask is None and 'no SA slice' in why
    mask, why = m.ed_mask(dataclasses.replace(sa0, image=np.full((128, 128), 7.0, np.float32)))
    assert mask is None and 'constant' in why
    nan = sa0.image.copy()
    nan[5, 5] = np.nan
    mask, why = m.ed_mask(dataclasses.replace(sa0, image=nan))
    assert mask is None and 'non-finite' in why
    mask, why = m.ed_mask(dataclasses.replace(sa0, image=np.zeros((4, 4))))
    assert mask is None and '16x16' in why
    rng = np.random.default_rng(0)
    mask, why = m.ed_mask(
        dataclasses.replace(sa0, image=rng.normal(size=(128, 128)).astype(np.float32))
    )
    assert mask is None and why
    assert not m.sa_centres  # failures add nothing to the axis
    # Still usable afterwards.
    mask, why = m.ed_mask(sa0)
    assert mask is not None, why


def test_slice_off_the_axis(studies):
    """A slice whose cavity is far from the axis of the earlier slices is still found."""
    st = studies['normal']
    ed = {f.slice_index: f for f in st.frames if f.view == VIEW_SA and f.phase_index == 0}
    m = StreamingMasker()
    for i in range(4):
        assert m.ed_mask(ed[i])[0] is not None
    shift = (14, 12)
    g = dataclasses.replace(ed[4], image=np.roll(ed[4].image, shift, axis=(0, 1)))
    mask, why = m.ed_mask(g)
    assert mask is not None, why
    assert dice(mask, np.roll(st.ed_masks[(VIEW_SA, 4)], shift, axis=(0, 1))) >= MIN_DICE
    # The misplaced centre does not bend the axis for the slices after it.
    for i in range(5, 8):
        mask, why = m.ed_mask(ed[i])
        assert mask is not None and why == '', (i, why)
        assert dice(mask, st.ed_masks[(VIEW_SA, i)]) >= MIN_DICE
    la = next(f for f in st.frames if f.view == VIEW_LA and f.phase_index == 0)
    mask, why = m.ed_mask(la)
    assert mask is not None and dice(mask, st.ed_masks[(VIEW_LA, la.slice_index)]) >= MIN_DICE
