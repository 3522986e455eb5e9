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
``mlv-ros demo`` (the README's ``make demo``): the whole graph on the built-in phantom.

Simulate the built-in ``normal`` LV phantom (8 SA + 3 LA tagged cines, 256², 25 phases, SNR 20),
run the whole graph on it in one process, record the run, build the report and print the accuracy
against the phantom's analytic ground truth. About a minute and a half on 2 cores.

The console is ``mlv-ros run``'s (:mod:`mlv_ros.console`): a progress bar over phases on a
terminal, then a short summary; ``--verbose`` adds the event lines, the nodes' INFO lines and the
result as JSON.
"""

from __future__ import annotations

import json
from pathlib import Path
import signal
import sys
import time

from mlv_ros.cli import describe_os_error, one_line


def add_arguments(parser):
    parser.add_argument(
        '--out', default=None, help='run directory (default: runs/demo-<date-time>)'
    )
    parser.add_argument('--preset', default='normal', help='phantom preset (default: normal)')
    parser.add_argument(
        '--no-progress',
        action='store_true',
        help='no progress bar (there is none when stderr is not a terminal)',
    )
    parser.add_argument(
        '--verbose',
        action='store_true',
        help="also the nodes' INFO lines, one line per event and the result as JSON",
    )


def run(args) -> int:
    from mlv_ros.console import RunConsole, summary_lines
    from mlv_ros.recording import phantom_accuracy, write_report
    from mlv_ros.runner import run_graph, RunInterrupted, SIGNAL_EXIT, verdict_line

    def fail(msg) -> int:
        print(f'mlv-ros demo: {one_line(msg)}', file=sys.stderr)
        return 2

    out = Path(args.out or f'runs/demo-{time.strftime("%Y%m%d-%H%M%S")}')
    wrong = _check_before_start(args.preset, out)
    if wrong:
        return fail(wrong)
    print(
        f"[demo] simulating the '{args.preset}' phantom and running the graph -> {out}",
        file=sys.stderr,
    )
    console = RunConsole(verbose=args.verbose, progress=not args.no_progress)
    restore = console.quiet_nodes()
    try:
        summary = run_graph(
            {'source': 'phantom', 'preset': args.preset},
            out,
            progress=console.line,
            on_phase=console.phase,
        )
    except RunInterrupted as exc:
        print(f'mlv-ros demo: {exc}; nothing recorded', file=sys.stderr)
        return SIGNAL_EXIT[exc.signum]
    except (FileExistsError, FileNotFoundError, ValueError) as exc:
        return fail(exc)
    except OSError as exc:
        return fail(describe_os_error(exc))
    finally:
        console.close()
        restore()
    if summary.get('interrupted') or not summary['complete']:
        return _unfinished(args, summary)
    acc = phantom_accuracy(Path(summary['mcap']), args.preset, summary['num_phases'])
    index = write_report(Path(summary['mcap']))
    result = _result(out, summary, acc, index)
    (out / 'accuracy.json').write_text(json.dumps(acc, indent=2))
    if args.verbose:
        print(json.dumps(result, indent=2))
    print(
        '\n'.join(
            summary_lines(
                summary, exit_status=0, exit_reason='complete', accuracy=acc, report=str(index)
            )
        )
    )
    quality = verdict_line(summary)
    if quality:
        print(f'mlv-ros demo: {quality}', file=sys.stderr)
    return 0


def _check_before_start(preset: str, out: Path):
    """
    Check what can be checked in a moment, before the graph starts; create ``out``.

    Returns the complaint (an exception or a line), or None when the preset loads and ``out`` is
    writable and holds no run.
    """
    from mlv_ros.core.sim import load_preset

    try:
        load_preset(preset)
    except (FileNotFoundError, ValueError) as exc:
        return exc
    if (out / 'run.mcap').exists():
        return f'{out} already holds a run: choose a new --out (runs are never overwritten)'
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f'cannot write --out: {describe_os_error(exc)}'
    return None


def _unfinished(args, summary: dict) -> int:
    """
    Say why a demo run did not finish, and return its exit status.

    Parameters
    ----------
    args : argparse.Namespace
        The command line (``verbose``).
    summary : dict
        The run's summary (:func:`mlv_ros.runner.run_graph`), interrupted or not complete.

    Returns
    -------
    int
        The signal's exit status if interrupted, else 1.

    """
    from mlv_ros.console import summary_lines
    from mlv_ros.runner import exit_status, SIGNAL_EXIT

    if summary.get('interrupted'):
        print(
            f'mlv-ros demo: interrupted by {summary["interrupted"]}; the recording keeps the '
            'phases solved '
            f'({summary["phases_solved"]} of {summary["num_phases"]}) in {summary["mcap"]}',
            file=sys.stderr,
        )
        return SIGNAL_EXIT[signal.Signals[summary['interrupted']]]
    if args.verbose:
        print(json.dumps(summary, indent=2))
    _, how = exit_status(summary)
    print('\n'.join(summary_lines(summary, exit_status=1, exit_reason=how)))
    print(
        'mlv-ros demo: the run did not complete; see /diagnostics in the recording',
        file=sys.stderr,
    )
    return 1


def _result(out: Path, summary: dict, acc: dict, index: Path) -> dict:
    """
    Gather what the demo prints as JSON with --verbose: the run and its phantom accuracy.

    Parameters
    ----------
    out : Path
        The run directory.
    summary : dict
        The run's summary.
    acc : dict
        Its accuracy against the phantom's truth (:func:`mlv_ros.recording.phantom_accuracy`).
    index : Path
        The report's index.html.

    Returns
    -------
    dict

    """
    es = acc['es']
    return {
        'run_dir': str(out),
        'recording': summary['mcap'],
        'report': str(index),
        'seconds': summary['seconds'],
        'frames': summary['frames_published'],
        'phases': summary['num_phases'],
        'messages_recorded': summary['recorded_messages'],
        'accuracy_at_end_systole': {
            'phase': es['phase'],
            'median_3d_error_mm': round(es['median_mm'], 3),
            'p95_3d_error_mm': round(es['p95_mm'], 3),
            'max_twist_error_deg': round(es.get('twist_error_deg', float('nan')), 2),
            'max_radius_error_mm': round(es.get('radius_error_mm', float('nan')), 2),
        },
        'worst_phase_median_mm': round(max(r['median_mm'] for r in acc['per_phase']), 3),
        'phases_degraded': sorted(int(p) for p in summary.get('phases_degraded') or {}),
        'phases_failed': sorted(int(p) for p in summary.get('phases_failed') or {}),
        'particles_inside_true_myocardium': round(acc['inside_myocardium'], 4),
        'true_myocardium_covered': round(acc['coverage'], 4),
    }
