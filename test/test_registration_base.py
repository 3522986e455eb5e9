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

"""Where the ED model ends at the base when the LA views and the SA stack disagree."""

from mlv_ros.core.registration import register_ed
from mlv_ros.core.sim import simulate_study
from mlv_ros.core.types import VIEW_LA, VIEW_SA
import numpy as np
import pytest


@pytest.fixture(scope='module')
def study():
    st = simulate_study('normal', snr=20, quick=True, num_phases=2)
    return st, [f for f in st.frames if f.phase_index == 0]


def axial(st, X):
    f = st.motion.frame
    return (np.asarray(X) - f.apex) @ f.long_axis


def top_sa_level(st, ed):
    f = st.motion.frame
    levels = []
    for fr in ed:
        if fr.view == VIEW_SA:
            n = fr.geometry.normal
            levels.append(float((fr.geometry.image_position - f.apex) @ n / (f.long_axis @ n)))
    return max(levels)


def test_short_la_horseshoes_do_not_cut_off_segmented_sa_slices(study):
    """LA masks that stop halfway up (a horseshoe cut short) must not drop the SA slices above."""
    st, ed = study
    L = st.motion.frame.length
    masks = {}
    for k, m in st.ed_masks.items():
        if k[0] == VIEW_LA:
            g = st.geometries[k]
            rc = np.argwhere(m)
            keep = axial(st, g.pixel_to_patient(rc.astype(float))) < 0.5 * L
            m = np.zeros_like(m)
            m[tuple(rc[keep].T)] = True
        masks[k] = m
    top = top_sa_level(st, ed)
    assert top > 0.6 * L  # the premise: SA slices reach well above the truncated LA masks
    res = register_ed(ed, num_particles=1500, masks=masks)
    z = axial(st, res.particles)
    assert z.max() >= top - 2.0, (z.max(), top)
    assert any('LA views end' in w for w in res.warnings), res.warnings
    # and nothing changes when the views agree
    full = register_ed(ed, num_particles=1500, masks=st.ed_masks)
    assert not any('LA views end' in w for w in full.warnings)
    assert axial(st, full.particles).max() >= top - 2.0
