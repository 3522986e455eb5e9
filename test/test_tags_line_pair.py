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
A single-line pair's two series from two breath-holds: the shift between them, and a 60° pair.

The phantom renders the second series with the heart shifted (``line_pair_study``'s
``shift_mm``), the DICOM geometry unchanged, as a second breath-hold does. The shift estimate
must recover the shift's in-plane part on every plane, and the points of both families of a 60°
pair, the shift corrected, must lie on their ED tag lines: the error of a point along its line
normal is ``a(X) − a_line``, X the ED material point the truth puts under it and ``a`` its
coordinate along the normal in the series' own tag frame (the second's moved with the heart).
"""

from dataclasses import replace
from functools import lru_cache

from mlv_ros.core.sim import simulate_study
from mlv_ros.core.sim.imaging import plane_centre
from mlv_ros.core.sim.presets import load_preset
from mlv_ros.core.sim.study import line_pair_study
from mlv_ros.core.tags import estimate_pair_shift, LineSliceTracker
from mlv_ros.core.tags.line_pair import LARGE_SHIFT_MM
from mlv_ros.core.tags.lines import SECOND_FAMILY_IDS
from mlv_ros.core.types import PAIR_MISREGISTERED, TAGS_LINE_PAIR, VIEW_SA
import numpy as np
import pytest

PERIOD_MM = 7.0
ANGLE_DEG = 20.0


@lru_cache(maxsize=4)
def pair(turn_deg: float, shift=(0.0, 0.0), through: float = 0.0, phases: int = 10):
    pre = load_preset('normal')
    pre['imaging'].update(tag_lines='single', tag_angle_deg=ANGLE_DEG)
    first = simulate_study(pre, snr=20.0, quick=True, num_phases=phases, seed=3)
    second = line_pair_study(
        pre, first, turn_deg, shift_mm=shift, through_mm=through, quick=True, num_phases=phases
    )
    sa = first.geometries[(VIEW_SA, 0)]
    d = shift[0] * sa.row_direction + shift[1] * sa.column_direction
    return first, second, d + through * first.motion.frame.long_axis


def _in_plane_rc(g, d):
    """Return a 3-D shift's in-plane part on plane ``g`` as (row, col), mm."""
    return np.array([d @ g.column_direction, d @ g.row_direction])


def test_shift_between_the_two_series_is_recovered():
    """
    Check the estimate on a pair 3.0 mm apart in-plane: every plane within 0.6 mm, median 0.3.

    Measured on drawn studies (7101, 7102, 41; 41 slices): median error 0.15 mm, largest
    0.47 mm; the tags' directions differ between the series, so the anatomy's tag-free image
    differs slightly at a period's scale (the same family twice: ≤ 0.09 mm). Without tags
    there is no anatomy to match: unsure, with the reason.
    """
    first, second, d = pair(60.0, (1.8, -2.4))
    errors = []
    for key in first.keys:
        g = first.geometries[key]
        # the phantom: the second series' ED myocardium sits where the shift puts it
        rc = [np.argwhere(s.ed_masks[key]).mean(axis=0) for s in (first, second)]
        assert np.hypot(*((rc[1] - rc[0]) * g.row_spacing - _in_plane_rc(g, d))) < 0.3, key
        est = estimate_pair_shift(
            first.cine(*key)[0].image,
            second.cine(*key)[0].image,
            first.ed_masks[key],
            PERIOD_MM / g.row_spacing,
            g.row_spacing,
        )
        assert est.sure and not est.reason and est.score > 0.9, (key, est)
        assert not est.large and est.shift_mm < LARGE_SHIFT_MM
        errors.append(np.hypot(*(est.shift_rc * g.row_spacing - _in_plane_rc(g, d))))
    assert np.median(errors) < 0.3 and max(errors) < 0.6, np.round(errors, 2)
    rng = np.random.default_rng(0)
    noise = [rng.normal(size=(96, 96)) for _ in range(2)]
    mask = np.zeros((96, 96), bool)
    mask[30:60, 30:60] = True
    est = estimate_pair_shift(*noise, mask, 5.0, 1.5)
    assert not est.sure and est.reason and np.all(est.shift_rc == 0)


def _line_error(points, motion, phase, g, shape, angle_deg, offset):
    """Return each point's distance along its family's normal from the nearest tag line, mm."""
    a = np.radians(angle_deg)
    u = np.cos(a) * g.row_direction + np.sin(a) * g.column_direction
    coord = (motion.inverse(points, phase) - plane_centre(g, shape) + offset) @ u
    return coord, coord - np.round(coord / PERIOD_MM) * PERIOD_MM


@pytest.mark.parametrize('shift', [(0.0, 0.0), (1.8, -2.4)])
def test_a_60_degree_pair_gives_points_on_both_families(shift):
    """
    Check a 60° pair's points on every SA slice at ED to phase 3, aligned and 3 mm apart.

    Both families' points lie within 0.45 mm (median) of their own tag lines, along their
    normals, with the shift corrected (uncorrected the second's would be off by up to 3 mm
    along theirs); ED lines stay the same lines. Two families 60° apart measure motion along
    any in-plane direction, the worst with 1/sin 60° = 1.15 times a family's own error.
    """
    first, second, d = pair(60.0, shift)
    m = first.motion
    for key in [k for k in first.keys if k[0] == VIEW_SA][1:6]:
        g = first.geometries[key]
        tr = LineSliceTracker(g)
        lines = {}
        for fa, fb in list(zip(first.cine(*key), second.cine(*key)))[:4]:
            f = replace(fa, tag_lines=TAGS_LINE_PAIR, line_image=fb.image)
            pts = tr.update(f, first.ed_masks[key] if f.phase_index == 0 else None)
            if f.phase_index == 0:
                assert tr.pair_shift.sure and PAIR_MISREGISTERED not in pts.status
            two = pts.track_id >= SECOND_FAMILY_IDS
            assert two.sum() >= 10 and (~two).sum() >= 10, (key, f.phase_index)
            for sel, angle, off in ((~two, ANGLE_DEG, 0.0), (two, ANGLE_DEG + 60.0, d)):
                coord, err = _line_error(
                    pts.position[sel], m, f.phase_index, g, f.image.shape, angle, off
                )
                ids = pts.track_id[sel].tolist()
                if f.phase_index == 0:
                    lines.update(zip(ids, np.round(coord / PERIOD_MM)))
                assert np.all(np.round(coord / PERIOD_MM) == [lines[t] for t in ids])
                assert np.median(np.abs(err)) < 0.45, (key, f.phase_index, angle)


@pytest.mark.parametrize('roll_mm, sure', [(8.0, True), (20.0, False)])
def test_a_large_or_unsure_shift_degrades_the_slice(roll_mm, sure):
    """
    Check a second series moved 8 mm (corrected, beyond breath-holds) and 20 mm (not found).

    Both say so in the ED status (:data:`PAIR_MISREGISTERED`, which degrades the solver's
    phases); the 20 mm one lies beyond the search range (12 mm) and is not corrected.
    """
    first, second, _ = pair(90.0)
    key = (VIEW_SA, 3)
    g = first.geometries[key]
    px = int(round(roll_mm / g.row_spacing))
    moved = np.roll(second.cine(*key)[0].image, px, axis=1)  # the anatomy px columns on
    f = replace(first.cine(*key)[0], tag_lines=TAGS_LINE_PAIR, line_image=moved)
    tr = LineSliceTracker(g)
    pts = tr.update(f, first.ed_masks[key])
    est = tr.pair_shift
    assert est.sure == sure and PAIR_MISREGISTERED in pts.status, (est, pts.status)
    if sure:
        assert est.large and abs(est.shift_rc[1] - px) < 0.5 and abs(est.shift_rc[0]) < 0.5
        assert 'through-plane' in tr.pair_note
    else:
        assert np.all(est.shift_rc == 0) and 'not corrected' in tr.pair_note
