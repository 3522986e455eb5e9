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
What the local stage does to the ES twist per level, one term or input changed at a time.

Re-tracks a recorded run as ``bench/retrack.py`` does (``--ideal``: every tracked point where
the truth puts it), solves every phase up to end-systole with the default
:class:`MotionTracker`, keeps the inputs of the ES phase's last local solve and solves that
local stage again from the same global configuration (CG to 1e-6) with one change at a time:
a data, fit-error, volume, axial or coupling weight; the volume term without its offset
``J_g − 1``; the SA or LA targets replaced by the truth of the material points they are
attached to; only the SA or only the LA springs. Prints one JSON line per case: the twist error
per level (degrees, solved − true, level 0 at the apex) of the global stage with the twist
function, of the default and of each variant, and the mean ``J − 1`` per level of the truth, the
global stage and the default solution.

    python bench/local_twist.py CASE_DIR [CASE_DIR ...] [--ideal] [--solver KEY=VALUE ...]

``--solver`` sets a :class:`MotionTracker` keyword, as ``bench/retrack.py``'s does (e.g.
``global_thickening=true``).

Measured on 3001 / 1001 / 1012 (``--ideal``): see :meth:`MotionTracker._twist_function`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys

from mlv_ros.core.analysis import LVAnalyzer, LVFrame
from mlv_ros.core.analysis.frame import lv_frame_axes
from mlv_ros.core.io.groundtruth import motion_from_groundtruth
from mlv_ros.core.tracking import MotionTracker
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import retrack  # noqa: E402, I100


def _levels_j(tr, x, level):
    """Return the mean ``J − 1`` of ``x`` (N, 3) per level index (0…9)."""
    F = np.eye(3) + tr.model.operator.gradient(x - tr.rest)
    j = np.linalg.det(F) - 1.0
    return [round(float(np.mean(j[level == k])), 4) for k in range(10)]


def replay(case: Path, ideal: bool, solver: dict | None = None) -> dict:
    """
    Return the ES twist error per level for the default local stage and each variant.

    Parameters
    ----------
    case : Path
        A robustness case (``run/run.mcap`` and ``study/``).
    ideal : bool
        Replace the tracked points by where the truth puts them.
    solver : dict, optional
        :class:`MotionTracker` keywords.

    """
    frames, cloud, state = retrack.recorded(case / 'run' / 'run.mcap')
    sets = retrack.track(frames)
    truth = motion_from_groundtruth(case / 'study')
    if ideal:
        sets, _ = retrack.ideal_targets(sets, truth)
    es, n = int(round(truth.es_phase)), max(sets) + 1
    captured = {}
    original = MotionTracker._local_solve

    def spy(self, *args, **kwargs):
        captured['call'] = (list(args), dict(kwargs))
        return original(self, *args, **kwargs)

    MotionTracker._local_solve = spy
    try:
        tr, positions, _ = retrack.solve(
            {p: sets[p] for p in sets if p <= es}, cloud, state, **(solver or {})
        )
    finally:
        MotionTracker._local_solve = original
    if es not in positions or 'call' not in captured:
        return {'case': case.name, 'error': 'ES not solved'}
    analyzer = LVAnalyzer(tr.rest, LVFrame(*lv_frame_axes(tr.rest, state.rotation)))
    true_x = truth.position(tr.rest, es)
    true = analyzer.phase(true_x, phase_index=es, num_phases=n).twist_deg

    def error(x):
        return np.round(analyzer.phase(x, phase_index=es, num_phases=n).twist_deg - true, 2)

    args, kwargs = captured['call']
    phi, targets, normals, x_global = args[0], args[1], args[2], args[3]
    apex, base, _ = lv_frame_axes(tr.rest, state.rotation)
    axis = (base - apex) / np.linalg.norm(base - apex)
    height = (tr.rest - apex) @ axis / np.linalg.norm(base - apex)
    level = np.clip((height * 10).astype(int), 0, 9)
    sa = np.abs(normals @ axis) > 0.7
    attached = truth.position(phi @ tr.rest, es)
    variants = {
        'default': ({}, {}),
        'data_x10': ({'data_weight': 10.0 * tr.data_weight}, {}),
        'data_div10': ({'data_weight': 0.1 * tr.data_weight}, {}),
        'fit_error_x10': ({'hourglass_weight': 10.0 * tr.hourglass_weight}, {}),
        'volume_off': ({'volume_weight': 0.0}, {}),
        'volume_no_offset': ({}, {'no_offset': True}),
        'axial_off': ({'longitudinal_weight': 0.0}, {}),
        'coupling_off': ({'longitudinal_coupling': 0.0}, {}),
        'sa_targets_attached_truth': ({}, {'targets': np.where(sa[:, None], attached, targets)}),
        'la_targets_attached_truth': ({}, {'targets': np.where(sa[:, None], targets, attached)}),
        'only_sa_springs': ({}, {'weights': sa.astype(np.float64)}),
        'only_la_springs': ({}, {'weights': (~sa).astype(np.float64)}),
    }
    out = {'case': case.name, 'ideal': ideal, 'twist_true_deg': np.round(true, 2).tolist()}
    out['global_and_twist_function'] = error(x_global).tolist()
    system = tr._local.system
    for name, (attrs, inputs) in variants.items():
        saved = {k: getattr(tr, k) for k in attrs}
        call = list(args)
        if 'targets' in inputs:
            call[1] = inputs['targets']
        if 'weights' in inputs:
            call[4] = (np.ones(len(targets)) if call[4] is None else call[4]) * inputs['weights']
        if inputs.get('no_offset'):
            tr._local.system = lambda **kw: system(**{**kw, 'volume': (*kw['volume'][:2], None)})
        for k, v in attrs.items():
            setattr(tr, k, v)
        tr._phase_coarse, tr.delta = None, None
        try:
            delta = original(tr, *call, **{**kwargs, 'rtol': 1e-6})
        finally:
            for k, v in saved.items():
                setattr(tr, k, v)
            tr._local.system = system
        out[name] = error(x_global + delta).tolist()
        if name == 'default':
            out['j_minus_1'] = {
                'truth': _levels_j(tr, true_x, level),
                'global': _levels_j(tr, x_global, level),
                'default': _levels_j(tr, x_global + delta, level),
            }
    return out


def main():
    """Print one JSON line per case."""
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('cases', nargs='+', type=Path)
    ap.add_argument('--ideal', action='store_true', help='truth-placed tag points')
    retrack.keyword_option(ap, '--solver', 'MotionTracker')
    args = ap.parse_args()
    solver = retrack.keywords(args.solver)
    for case in args.cases:
        print(json.dumps(replay(case, args.ideal, solver) | {'solver': solver}), flush=True)


if __name__ == '__main__':
    main()
