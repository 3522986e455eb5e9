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
Two solvers' CPU per phase on a run's recorded tag points, paired phase by phase in one process.

``python bench/solver_pair.py RUN.mcap --old TREE [--new TREE] [--rounds 3]``: each tree's
``mlv_ros`` (e.g. main's, ``git archive COMMIT mlv_ros | tar -x -C TREE``) is copied under a
package name of its own, both trackers are built from the run's registration, and every phase
is solved by one and then the other (the order swapped each round), so that the machine's load
falls on both alike: on 2 loaded cores a solver's median per phase moves by ±15 % from run to
run, the paired difference far less. Prints JSON: both medians over the phases after the first
(process time, one thread), the median paired difference and ratio with its quartiles, and
whether the two gave the same positions to the bit.
"""

import argparse
import importlib
import json
from pathlib import Path
import re
import shutil
import sys
import tempfile
import time

import numpy as np
from pipeline import recorded_solver_input, recorded_tracker


def load_tree(tree: Path, name: str, into: Path):
    """
    Import ``tree``'s ``mlv_ros`` as the package ``name`` (a copy under ``into``).

    Parameters
    ----------
    tree : Path
        A directory holding an ``mlv_ros`` package.
    name : str
        The package name of the copy (its absolute imports of ``mlv_ros`` renamed).
    into : Path
        Where the copy is written (on ``sys.path``).

    Returns
    -------
    tuple of module
        Its ``core.tracking``, ``conversions`` and ``threads``.

    """
    src = Path(tree) / 'mlv_ros'
    if not (src / '__init__.py').is_file():
        raise SystemExit(f'solver_pair: no mlv_ros package in {tree} (give a source tree)')
    dst = into / name
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns('__pycache__'))
    for f in dst.rglob('*.py'):
        f.write_text(re.sub(r'\bmlv_ros\b', name, f.read_text()))
    return tuple(
        importlib.import_module(f'{name}.{m}')
        for m in ('core.tracking', 'conversions', 'threads')
    )


def main(argv=None) -> int:
    """Run the paired replay and print its JSON line."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('run', type=Path, help='a recorded run.mcap')
    ap.add_argument('--old', type=Path, required=True, help='the baseline source tree')
    ap.add_argument(
        '--new', type=Path, default=Path(__file__).resolve().parents[1],
        help='the source tree to compare (default: this checkout)',
    )
    ap.add_argument('--rounds', type=int, default=3, help='replays of the whole run (>= 1)')
    args = ap.parse_args(argv)
    if args.rounds < 1:
        raise SystemExit('solver_pair: --rounds must be >= 1')
    work = Path(tempfile.mkdtemp(prefix='solver_pair_'))
    sys.path.insert(0, str(work))
    try:
        mods = {t: load_tree(getattr(args, t), f'mlv_ros_{t}', work) for t in ('old', 'new')}
        threads = mods['new'][2]
        cloud, state, sets = recorded_solver_input(args.run)
        if cloud is None or state is None or len(sets) < 3:
            raise SystemExit(f'solver_pair: {args.run} holds no registration or too few phases')

        def tracker(t):
            return recorded_tracker(cloud, state, sets.get(0), mods[t][0].MotionTracker)

        cpu: dict = {'old': [], 'new': []}
        same, num_phases = True, max(sets) + 1
        with threads.compute_threads():
            for r in range(args.rounds):
                trackers = {t: tracker(t) for t in ('old', 'new')}
                order = ('old', 'new') if r % 2 == 0 else ('new', 'old')
                for i, p in enumerate(sorted(sets)[1:]):
                    positions = {}
                    for t in order:
                        t0 = time.process_time()
                        positions[t] = trackers[t].solve(p, sets[p], num_phases).positions
                        if i > 0:  # the first phase also builds what later ones reuse
                            cpu[t].append(time.process_time() - t0)
                    same &= bool(np.array_equal(positions['old'], positions['new']))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    old, new = (np.array(cpu[t]) * 1e3 for t in ('old', 'new'))
    ratio = new / old
    print(json.dumps({
        'phases_timed': int(old.size),
        'rounds': args.rounds,
        'old_ms_median': round(float(np.median(old)), 1),
        'new_ms_median': round(float(np.median(new)), 1),
        'paired_difference_ms_median': round(float(np.median(old - new)), 2),
        'paired_ratio_median': round(float(np.median(ratio)), 4),
        'paired_ratio_quartiles': [round(float(q), 4) for q in np.percentile(ratio, [25, 75])],
        'positions_identical': same,
    }))
    return 0


if __name__ == '__main__':
    sys.exit(main())
