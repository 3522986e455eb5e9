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
Single-line tag studies in the core: line points tracked and solved, against the phantom's truth.

Simulates a phantom preset with ``imaging.tag_lines: single`` at ``--angle`` (``--mode pair``: a
second study of the same heart and noise level with the lines at ``--angle`` + 90°, as vendors
acquire two single-line series of one slice; ``--mode grid``: the grid at ``--angle``, for
comparison), tracks every slice with :class:`~mlv_ros.core.tags.LineTracker` (the grid with
:class:`~mlv_ros.core.tags.SliceTracker`) from the true ED myocardium and solves every phase
with :class:`~mlv_ros.core.tracking.MotionTracker` placed on the truth's LV frame (registration
is not part of it). Not the graph (``mlv-ros simulate --protocol`` with ``tag_lines: single`` or
``pair`` and ``mlv-ros run --dicom`` are: ``test/test_single_line_graph.py``).

    python bench/single_line.py [--preset normal] [--mode single|pair|grid] [--angle 105]
        [--snr 12] [--phases 20]

Prints one JSON document: ED points, the ES median / p95 3D error and its median radial,
circumferential and longitudinal parts (mm), the worst phase's median and p95, the phases
solved and the ES verdict.
"""

from __future__ import annotations

import argparse
import json

from mlv_ros.core.meshless import matrix_to_quat
from mlv_ros.core.sim import simulate_study
from mlv_ros.core.sim.presets import load_preset
from mlv_ros.core.tags import LineTracker, SliceTracker
from mlv_ros.core.tags.lines import merge_line_sets
from mlv_ros.core.tracking import MotionTracker
import numpy as np


def tracked(args):
    """Return ``(study, sets)``: phase → (view, slice) → TagPointSet of every family."""
    pre = load_preset(args.preset)
    families = [args.angle] + ([args.angle + 90.0] if args.mode == 'pair' else [])
    sets = {}
    for seed, angle in enumerate(families):
        lines = 'grid' if args.mode == 'grid' else 'single'
        pre['imaging'].update(tag_lines=lines, tag_angle_deg=angle)
        st = simulate_study(pre, snr=args.snr, quick=True, num_phases=args.phases, seed=seed)
        period_mm = float(pre['imaging']['tag_spacing_mm'])
        for key in st.keys:
            g = st.geometries[key]
            tr = (
                SliceTracker(g)
                if lines == 'grid'
                else LineTracker(g, spacing_px=period_mm / g.row_spacing, angle=np.radians(angle))
            )
            for f in st.cine(*key):
                pts = tr.update(f, st.ed_masks[key] if f.phase_index == 0 else None)
                have = sets.setdefault(f.phase_index, {})
                have[key] = merge_line_sets(have[key], pts) if key in have else pts
    return st, sets


def main(argv=None) -> dict:
    """Run one configuration and return its JSON document."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--preset', default='normal')
    ap.add_argument('--mode', choices=('single', 'pair', 'grid'), default='single')
    ap.add_argument('--angle', type=float, default=105.0)
    ap.add_argument('--snr', type=float, default=12.0)
    ap.add_argument('--phases', type=int, default=20)
    args = ap.parse_args(argv)
    st, sets = tracked(args)
    m, fr = st.motion, st.motion.frame
    X = m.sample_myocardium(2000, seed=1)
    R = np.stack([fr.septum, np.cross(fr.long_axis, fr.septum), fr.long_axis], axis=1)
    solver = MotionTracker(X, X.mean(0), matrix_to_quat(R))
    for pts in sets[0].values():
        solver.set_reference(pts)
    es, out, worst = int(round(m.es_phase)), vars(args), []
    out['ed_points'] = int(sum(len(p) for p in sets[0].values()))
    for p in range(1, m.num_phases):
        try:
            sol = solver.solve(p, sets[p], m.num_phases)
        except ValueError:
            continue
        d = sol.positions - m.position(X, p)
        e = np.linalg.norm(d, axis=1)
        worst.append((float(np.median(e)), float(np.percentile(e, 95))))
        if p == es:
            v = X - fr.apex
            rad = v - (v @ fr.long_axis)[:, None] * fr.long_axis
            rad /= np.linalg.norm(rad, axis=1, keepdims=True)
            parts = {
                'radial': rad,
                'circumferential': np.cross(fr.long_axis, rad),
                'longitudinal': np.broadcast_to(fr.long_axis, X.shape),
            }
            out['es'] = {
                'median_mm': round(float(np.median(e)), 3),
                'p95_mm': round(float(np.percentile(e, 95)), 3),
                **{
                    f'{k}_median_mm': round(float(np.median(np.abs(np.sum(d * u, 1)))), 3)
                    for k, u in parts.items()
                },
                'verdict': int(sol.state.verdict),
            }
    out['phases_solved'] = f'{len(worst)}/{m.num_phases - 1}'
    out['worst_phase_median_mm'] = round(max(w[0] for w in worst), 3) if worst else None
    out['worst_phase_p95_mm'] = round(max(w[1] for w in worst), 3) if worst else None
    return out


if __name__ == '__main__':
    print(json.dumps(main()))
