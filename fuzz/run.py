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
Run every fuzz target for a bounded time and print one JSON summary (``make fuzz``).

Each target runs in its own process (libFuzzer via atheris) for ``--seconds``, starting from
seeds written fresh by :mod:`seeds` plus whatever corpus earlier runs kept under ``--out``.
Crashing inputs are saved there as ``crash-*`` / ``timeout-*`` / ``oom-*``; the summary counts
them. Exit status 1 if any target found one.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import re
import subprocess
import sys
import time

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

TARGETS = ('fuzz_dicom', 'fuzz_messages')
_ARTIFACTS = ('crash-', 'timeout-', 'oom-', 'leak-', 'slow-unit-')


def _seed(target: str, seed_dir: Path) -> int:
    import seeds

    if target == 'fuzz_dicom':
        return len(seeds.dicom_seeds(seed_dir))
    return len(seeds.message_seeds(seed_dir))


def run_target(target: str, seconds: int, out: Path) -> dict:
    work = out / target
    corpus, seed_dir = work / 'corpus', work / 'seeds'
    corpus.mkdir(parents=True, exist_ok=True)
    n_seeds = _seed(target, seed_dir)
    before = {p.name for p in work.iterdir() if p.name.startswith(_ARTIFACTS)}
    cmd = [
        sys.executable,
        str(HERE / f'{target}.py'),
        f'-max_total_time={seconds}',
        '-timeout=30',
        '-rss_limit_mb=4096',
        '-max_len=65536',
        '-print_final_stats=1',
        f'-artifact_prefix={work}/',
        str(corpus),
        str(seed_dir),
    ]
    t0 = time.monotonic()
    proc = subprocess.run(cmd, capture_output=True, text=True, errors='replace')
    wall = time.monotonic() - t0
    log = proc.stdout + proc.stderr
    (work / 'last_run.log').write_text(log)
    runs = re.findall(r'stat::number_of_executed_units:\s*(\d+)', log) or re.findall(
        r'Done (\d+) runs', log
    )
    new = sorted(
        p.name for p in work.iterdir() if p.name.startswith(_ARTIFACTS) and p.name not in before
    )
    return {
        'target': target,
        'executions': int(runs[-1]) if runs else 0,
        'seconds': round(wall, 1),
        'seeds': n_seeds,
        'corpus_size': sum(1 for _ in corpus.iterdir()),
        'exit_code': proc.returncode,
        'crashes': len(new) or int(proc.returncode != 0),
        'artifacts': [str(work / n) for n in new],
        'log': str(work / 'last_run.log'),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    ap.add_argument('--seconds', type=int, default=60, help='fuzzing time per target (s)')
    ap.add_argument(
        '--out',
        type=Path,
        default=HERE.parent / 'build' / 'fuzz',
        help='working corpus, logs and crashing inputs',
    )
    ap.add_argument(
        '--targets',
        default=','.join(TARGETS),
        help='comma-separated subset of ' + ', '.join(TARGETS),
    )
    args = ap.parse_args(argv)
    if args.seconds < 1:
        ap.error('--seconds must be at least 1')
    targets = [t.strip() for t in args.targets.split(',') if t.strip()]
    unknown = sorted(set(targets) - set(TARGETS))
    if unknown:
        ap.error(f'unknown target(s) {unknown}; choose from {list(TARGETS)}')
    results = [run_target(t, args.seconds, args.out) for t in targets]
    summary = {
        'targets': results,
        'executions': sum(r['executions'] for r in results),
        'seconds': round(sum(r['seconds'] for r in results), 1),
        'crashes_found': sum(r['crashes'] for r in results),
    }
    print(json.dumps(summary, indent=2))
    return 1 if summary['crashes_found'] else 0


if __name__ == '__main__':
    raise SystemExit(main())
