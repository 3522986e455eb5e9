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
Benchmark: randomized acquisition protocols through the real DICOM path, against ground truth.

Each case draws a protocol (``mlv-ros simulate --random SEED``: shape, LV orientation, grid angle
and period, pixel size, matrix, slice thickness and spacing, SA/LA counts, LA rotations, phases,
cycle, T1, SNR, tagged surroundings or not, blood brightness, stack order and normal signs, bit
depth and rescale, series layout), writes the DICOM study and its ground truth, runs the whole
graph on the files (``mlv-ros run --dicom``) and compares the recorded motion with the analytic
truth.

Per case (JSON): the drawn protocol, exit codes, phases solved, ES median / p95 3D error (mm), the
largest twist error over levels at ES (deg; also over the levels the SA stack spans only: beyond it
twist is extrapolated, and the must-criterion takes all levels; and the extrapolated levels'
largest error over the rate part of the uncertainty the run states for them, ≤ 1 within even that),
particles inside the true myocardium, the fraction of the true myocardium the model covers, tag
points per slice (ED and fewest over the cycle), seconds, and whether the issue's must-criteria
hold (ES median ≤ 1.0 mm, p95 ≤ 2.5 mm, twist error ≤ 2°, every phase solved) with the model
covering ≥ 90 % of the true myocardium (errors are measured on the particles, so a model short of
the base would pass on what it has). The summary gives the worst and the median of each measure and
the number of cases passing.

    mlv-ros bench robustness [-- --cases 16 --seed 1000 --jobs 1 --out DIR --keep --abnormal
                              --rv on]

The drawn abnormal regions and right ventricle are left out unless ``--abnormal``: the cases
stay the normal hearts these seeds draw without them, comparable with kept results. ``--rv
drawn|on|off`` sets the right ventricle alone (e.g. ``--rv on``: every study with an RV beside the
LV, as real studies have). ``--tag-lines any`` draws single-line studies too (``mlv-ros simulate
--tag-lines any``: grid 50 %, a single-line pair 30 % with its angle and breath-hold shift drawn,
one family 20 %, every other item as the grid draw's); the default, grid, keeps the cases the
seeds always drew. A one-family study does not meet the must (motion along its lines is not
measured, every phase after ED says so; its ED model is as good as a grid's, but even with every
line point exact, ``bench/retrack.py --ideal``, 6503 / 6506 / 6522 are 2.2 / 0.8 / 3.6 mm off
at ES): the case carries ``tag_lines`` for the reader.

About 1–3 minutes per case on 2 cores (the drawn study's size and phase count set it).
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from concurrent.futures import ThreadPoolExecutor
import json
from pathlib import Path
import statistics
import sys
import time

from mlv_msgs.msg import TagPoints
from mlv_ros import bagio, qos
from mlv_ros.recording import groundtruth_accuracy
from rclpy.serialization import deserialize_message
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _graph_case import add_case_options, cases_folder, run_dicom, simulate  # noqa: E402, I100

MUST = {'median_mm': 1.0, 'p95_mm': 2.5, 'twist_error_deg': 2.0}
# Errors are measured on the model's particles: a model that misses the base scores well on what
# it has. Passing also needs the model to cover this much of the true myocardium.
MIN_COVERAGE = 0.9
GOAL_MEDIAN_MM = 0.5
# A phase more than this far off (median 3D error, mm) must not be delivered with verdict ok.
SILENT_MM = 2.0


def tag_points_per_slice(mcap: Path) -> dict:
    """``"SA 3" -> {"ed": n, "min": n}``: tag points at ED and the fewest at any phase."""
    counts = defaultdict(dict)
    for m in bagio.read_bag(mcap, topics=[qos.TAG_POINTS]):
        p = deserialize_message(m.data, TagPoints)
        counts[f'{"SA" if p.view == 0 else "LA"} {p.slice_index}'][p.phase_index] = len(p.track_id)
    return {k: {'ed': v.get(0, 0), 'min': min(v.values())} for k, v in sorted(counts.items())}


def run_case(
    seed: int,
    out: Path,
    timeout: float,
    abnormal: bool = False,
    rv: str | None = None,
    tag_lines: str = 'grid',
) -> dict:
    """
    Run one case.

    ``rv``: ``"on"`` / ``"off"`` forces the right ventricle, ``"drawn"`` keeps the draw (75 % of
    studies); None: drawn with ``abnormal``, off without (the seeds' normal hearts).
    ``tag_lines``: ``"grid"`` or ``"any"`` (``mlv-ros simulate --tag-lines``).
    """
    study, run_dir = out / 'study', out / 'run'
    case = {'seed': seed}
    t0 = time.monotonic()
    extra = []
    rv = rv or ('drawn' if abnormal else 'off')
    fixed = ('' if abnormal else 'abnormal_regions: []\n') + {
        'on': 'right_ventricle: true\n',
        'off': 'right_ventricle: false\n',
        'drawn': '',
    }[rv]
    # Without --abnormal: the studies these seeds drew before abnormal regions and the RV existed.
    if fixed:
        out.mkdir(parents=True, exist_ok=True)
        (out / 'fixed.yaml').write_text(fixed)
        extra = ['--protocol', str(out / 'fixed.yaml')]
    if tag_lines != 'grid':
        extra += ['--tag-lines', tag_lines]
    error = simulate(seed, study, *extra)
    case['simulate_seconds'] = round(time.monotonic() - t0, 1)
    if error:
        return case | {'error': error, 'pass': False}
    case['protocol'] = yaml.safe_load((study / 'protocol.yaml').read_text())
    case['tag_lines'] = case['protocol'].get('tag_lines', 'grid')
    t0 = time.monotonic()
    run_exit, error = run_dicom(study, run_dir, timeout)
    case['run_seconds'] = round(time.monotonic() - t0, 1)
    case['run_exit'] = run_exit
    if error:
        return case | {'error': error, 'pass': False}
    mcap = run_dir / 'run.mcap'
    summary = (
        json.loads((run_dir / 'summary.json').read_text())
        if (run_dir / 'summary.json').exists()
        else {}
    )
    case['phases_solved'] = summary.get('phases_solved')
    case['num_phases'] = summary.get('num_phases')
    case['tag_points'] = tag_points_per_slice(mcap)
    acc = groundtruth_accuracy(mcap, study)
    if 'error' in acc:
        return case | {'error': acc['error'], 'pass': False}
    es = acc['es'] or {}
    case['es'] = {
        k: round(es[k], 3)
        for k in (
            'median_mm',
            'p95_mm',
            'twist_error_deg',
            'twist_error_measured_deg',
            'twist_extrapolated_over_stated',
            'radius_error_mm',
        )
        if k in es
    }
    case['inside_myocardium'] = round(acc['inside_myocardium'], 3)
    case['coverage'] = round(acc['coverage'], 3)
    case['worst_phase_median_mm'] = round(max(r['median_mm'] for r in acc['per_phase']), 3)
    # Verdicts (mlv_ros.core.verdict): which phases the run flagged, and the wrong answers it did
    # not flag (median more than SILENT_MM off, delivered as ok) — the failure that must not be.
    flagged = {
        int(p) for key in ('phases_degraded', 'phases_failed') for p in summary.get(key) or {}
    }
    case['phases_degraded'] = sorted(int(p) for p in summary.get('phases_degraded') or {})
    case['phases_failed'] = sorted(int(p) for p in summary.get('phases_failed') or {})
    case['silent_wrong_phases'] = [
        r['phase']
        for r in acc['per_phase']
        if r['median_mm'] > SILENT_MM and r['phase'] not in flagged
    ]
    every_phase = case['phases_solved'] is not None and case['phases_solved'] == case['num_phases']
    case['pass'] = bool(
        every_phase
        and case['coverage'] >= MIN_COVERAGE
        and all(case['es'].get(k, float('inf')) <= v for k, v in MUST.items())
    )
    return case


def summarise(cases: list[dict]) -> dict:
    def col(key):
        return [c['es'][key] for c in cases if key in c.get('es', {})]

    out = {
        'cases': len(cases),
        'passing_must': sum(c['pass'] for c in cases),
        'every_phase_solved': sum(
            c.get('phases_solved') == c.get('num_phases') is not None for c in cases
        ),
        'errors': [f'seed {c["seed"]}: {c["error"]}' for c in cases if 'error' in c],
    }
    for key in (
        'median_mm',
        'p95_mm',
        'twist_error_deg',
        'twist_error_measured_deg',
        'radius_error_mm',
    ):
        v = col(key)
        if v:
            out[key] = {'worst': max(v), 'median': round(statistics.median(v), 3)}
    for key in ('inside_myocardium', 'coverage'):
        v = [c[key] for c in cases if key in c]
        if v:
            out[key] = {'worst': min(v), 'median': round(statistics.median(v), 3)}
    out['at_goal_median'] = sum(
        c.get('es', {}).get('median_mm', 9e9) <= GOAL_MEDIAN_MM for c in cases
    )
    out['failing_seeds'] = [c['seed'] for c in cases if not c['pass']]
    out['phases_flagged'] = sum(
        len(c.get('phases_degraded', [])) + len(c.get('phases_failed', [])) for c in cases
    )
    out['silent_wrong_phases'] = {
        c['seed']: c['silent_wrong_phases'] for c in cases if c.get('silent_wrong_phases')
    }
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--cases', type=int, default=16)
    ap.add_argument(
        '--seed', type=int, default=1000, help='first protocol seed (cases use seed, seed+1, …)'
    )
    add_case_options(ap)
    ap.add_argument(
        '--jobs',
        type=int,
        default=1,
        help='cases run at once (each run claims its own ROS domain)',
    )
    ap.add_argument(
        '--abnormal',
        action='store_true',
        help='keep the drawn regional abnormalities (default: none, the studies these seeds drew '
        'before; regional strain is `mlv-ros bench strain`)',
    )
    ap.add_argument(
        '--rv',
        choices=('drawn', 'on', 'off'),
        default=None,
        help='right ventricle: as drawn (75 %% of studies), always, never (default: drawn with '
        '--abnormal, else off)',
    )
    ap.add_argument(
        '--tag-lines',
        choices=('grid', 'any'),
        default='grid',
        help='grid (default: the grid studies the seeds always drew) or any (single-line pairs '
        'and one-family studies drawn too)',
    )
    args = ap.parse_args()
    if args.cases < 1:
        ap.error('--cases must be >= 1')

    def one(seed):
        case = run_case(
            seed, root / f'case-{seed}', args.timeout, args.abnormal, args.rv, args.tag_lines
        )
        print(
            json.dumps(
                {
                    k: case.get(k)
                    for k in (
                        'seed',
                        'tag_lines',
                        'pass',
                        'es',
                        'phases_solved',
                        'num_phases',
                        'run_seconds',
                        'error',
                    )
                    if k in case
                }
            ),
            file=sys.stderr,
            flush=True,
        )
        return case

    with cases_folder(args, 'robustness') as root:
        with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            cases = list(pool.map(one, range(args.seed, args.seed + args.cases)))
    print(
        json.dumps(
            {
                'summary': summarise(cases),
                'must': MUST | {'coverage': MIN_COVERAGE},
                'cases': cases,
                'out': str(root) if (args.out or args.keep) else None,
            },
            indent=1,
        )
    )
    return 0  # the verdict is in the JSON (summary.passing_must); other benches still run


if __name__ == '__main__':
    raise SystemExit(main())
