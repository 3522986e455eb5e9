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
``mlv-ros run``: the whole graph, recorded to RUN_DIR/run.mcap.

The graph is run by :mod:`mlv_ros.runner` (the tag detector in a process of its own, the other
nodes in the run's process).

    mlv-ros run (--phantom PRESET | --dicom DIR [--study UID] | --bag FILE) --out RUN_DIR
                [--namespace NS]

Shows a progress bar over phases (on a terminal) and a short summary (:mod:`mlv_ros.console`:
what ran, how it ended, accuracy against the ground truth when the input is a phantom or a
simulated study, volumes, verdicts, where the results are); ``--verbose`` adds the nodes' INFO
lines, a line per event and the whole summary as JSON. Writes RUN_DIR/summary.json.

A run claims its ROS domain: a private one (an flock, :mod:`mlv_ros.domain`) unless the user
chose one (``--domain-id`` or ``ROS_DOMAIN_ID``); a chosen domain on which discovery finds a
node of another mlv_ros graph in the same namespace is refused (exit 2, one line naming it).
``--namespace NS`` puts every node, and so every graph topic, under ``/NS`` (``/NS/mlv/frames``;
the recording holds those names), so graphs in different namespaces share a domain. Every node
of the graph keeps to the study the input carries (``study_id``) and reports and ignores
messages of any other, so two graphs that do meet on one domain cannot mix.

The run watches its nodes: one that cannot start, gives up, raises, or leaves the graph with
nothing to do ends the run at once with that node's reason. SIGINT/SIGTERM stop the input, let
the phases in flight finish (at most ``--grace`` seconds; a second signal stops waiting), close
the recording with everything received and mark it incomplete. A ``--dicom`` run is not complete
either when part of the chosen study was left out (``left_out`` in the summary says what; every
series under the folder not used is in ``not_used``). Exit status: 0 complete, 1 not
complete (the reason on one line), 2 a mistake in the command or a graph that could not start
(nothing recorded), 130/143 interrupted by SIGINT/SIGTERM.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
import re
import signal
import sys

from mlv_ros.console import RunConsole, summary_lines
from mlv_ros.recording import find_groundtruth, groundtruth_accuracy, phantom_accuracy
from mlv_ros.runner import (
    exit_status,
    EXIT_UNTRACKED,
    EXIT_USAGE,
    outcome_line,
    params_error,
    run_graph,
    RunInterrupted,
    SIGNAL_EXIT,
    verdict_line,
    write_summary,
)
from mlv_ros.settings import REGISTRATION, setting

PARTICLES = setting(REGISTRATION, 'num_particles')  # --particles: the registration's range

MCAP_MAGIC = b'\x89MCAP0\r\n'
_UID = re.compile(r'[0-9]+(\.[0-9]+)*')


def add_arguments(parser):
    """
    Declare ``mlv-ros run``'s options, in the order --help lists them.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.

    """
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument(
        '--phantom',
        metavar='PRESET',
        help='simulate a preset (normal, hypertrophic, dilated, infarct, cylinder)',
    )
    src.add_argument('--dicom', metavar='DIR', help='read a DICOM directory')
    src.add_argument('--bag', metavar='FILE', help='replay the frames of a recorded MCAP')
    parser.add_argument(
        '--out', required=True, metavar='RUN_DIR', help='run directory (must not hold a run.mcap)'
    )
    parser.add_argument(
        '--study',
        metavar='UID',
        default=None,
        help='with --dicom: the StudyInstanceUID to analyse (default: the study with the most '
        'tagged cines)',
    )
    parser.add_argument(
        '--params', default=None, help='graph parameters YAML (default config/graph.yaml)'
    )
    _add_phantom_arguments(parser)
    _add_console_arguments(parser)
    _add_graph_arguments(parser)


def _add_phantom_arguments(parser):
    """Declare the options that shape the phantom and the model (``parser``: argparse)."""
    parser.add_argument(
        '--snr',
        type=float,
        default=None,
        help='phantom SNR, 0..1000, 0 = noise-free (default from the params file)',
    )
    parser.add_argument(
        '--size', type=int, default=None, help='phantom image size, pixels (32..1024)'
    )
    parser.add_argument(
        '--phases', type=int, default=None, help='phantom phases per cycle (2..200)'
    )
    parser.add_argument('--order', choices=('slice_major', 'phase_major'), default=None)
    parser.add_argument(
        '--particles',
        type=int,
        default=None,
        help=f'model particles ({PARTICLES.min_value}..{PARTICLES.max_value})',
    )
    parser.add_argument(
        '--masks',
        default=None,
        help='NIfTI label image of the ED myocardium (label 2) instead of automatic segmentation',
    )


def _add_console_arguments(parser):
    """Declare the options of time limits and of what the console shows (``parser``: argparse)."""
    parser.add_argument(
        '--timeout', type=float, default=600.0, help='give up after this many seconds'
    )
    parser.add_argument(
        '--grace',
        type=float,
        default=10.0,
        help='on SIGINT/SIGTERM, wait at most this many seconds for the phases in flight '
        '(default 10)',
    )
    parser.add_argument(
        '--no-progress',
        action='store_true',
        help='no progress bar (there is none when stderr is not a terminal)',
    )
    parser.add_argument('--quiet', action='store_true', help='the same as --no-progress')
    parser.add_argument(
        '--verbose',
        action='store_true',
        help="also the nodes' INFO lines, one line per event and the whole summary as JSON",
    )


def _add_graph_arguments(parser):
    """Declare the options of where the graph runs and who can watch it (``parser``: argparse)."""
    parser.add_argument(
        '--domain-id',
        type=int,
        default=None,
        help='ROS domain to run on, 0..232 (default: $ROS_DOMAIN_ID if set, else a free '
        'private one)',
    )
    parser.add_argument(
        '--namespace',
        metavar='NS',
        default=None,
        help='run every node and topic under this ROS namespace (e.g. study2: '
        '/study2/mlv/frames); '
        'graphs in different namespaces can share a domain',
    )
    parser.add_argument(
        '--live',
        action='store_true',
        help='serve the run live to Foxglove (ws://127.0.0.1:8765; layout '
        'config/foxglove_layout.json)',
    )
    parser.add_argument(
        '--live-port',
        type=int,
        default=None,
        metavar='N',
        help="the live view's port (implies --live; default 8765 from the params file, 0 = any "
        'free)',
    )


def _number_error(name: str, value, low, high, what: str = '') -> str | None:
    """Return the one-line complaint for an option outside ``low..high`` or not finite, or None."""
    if value is None or (math.isfinite(value) and low <= value <= high):
        return None
    return f'{name} must be from {low:g} to {high:g}{what}, got {value}'


def check_args(args) -> str | None:
    """Return the first mistake in ``mlv-ros run``'s arguments (one line with the fix), or None."""
    problems = [
        _number_error('--snr', args.snr, 0, 1000, ' (0 = noise-free)'),
        _number_error('--size', args.size, 32, 1024, ' pixels'),
        _number_error('--phases', args.phases, 2, 200),
        _number_error('--particles', args.particles, PARTICLES.min_value, PARTICLES.max_value),
        _number_error('--domain-id', args.domain_id, 0, 232),
        _number_error('--live-port', args.live_port, 0, 65535, ' (0 = any free port)'),
        None if args.namespace is None else _namespace_error(args.namespace),
        None
        if math.isfinite(args.timeout) and args.timeout > 0
        else f'--timeout must be a positive number of seconds, got {args.timeout}',
        None
        if math.isfinite(args.grace) and args.grace >= 0
        else f'--grace must be a number of seconds ≥ 0, got {args.grace}',
    ]
    out = Path(args.out)
    if (out / 'run.mcap').exists():
        problems.append(
            f'{out} already holds a run (run.mcap): choose a new --out directory (runs are '
            'never overwritten)'
        )
    elif out.exists() and not out.is_dir():
        problems.append(f'--out {out} is a file, not a directory: choose a new --out directory')
    if args.dicom and not Path(args.dicom).is_dir():
        problems.append(f'--dicom {args.dicom}: no such directory')
    if args.study is not None and not args.dicom:
        problems.append(
            '--study chooses a study of a --dicom folder: give --dicom DIR, or leave --study out'
        )
    elif args.study is not None and not _UID.fullmatch(args.study.strip()):
        problems.append(
            f'--study {args.study!r} is not a DICOM UID (digits and dots, e.g. '
            '1.2.840.113619.2.1): '
            "give the StudyInstanceUID the run's summary or 'DICOM study chosen' names"
        )
    if args.bag:
        problems.append(_bag_error(Path(args.bag)))
    if args.masks and not Path(args.masks).is_file():
        problems.append(f'--masks {args.masks}: no such file')
    if args.params:
        problems.append(params_error(Path(args.params)))
    return next((p for p in problems if p), None)


def _namespace_error(namespace: str) -> str | None:
    from mlv_ros.qos import namespace_error

    error = namespace_error(namespace)
    return f'--namespace {error}' if error else None


def _bag_error(path: Path) -> str | None:
    if path.is_dir():  # a rosbag2 directory: its .mcap
        if not any(path.glob('*.mcap')):
            return f'--bag {path}: no .mcap file in that directory'
        return None
    try:
        with open(path, 'rb') as fh:
            head = fh.read(len(MCAP_MAGIC))
    except OSError as exc:
        return f'--bag {path}: {exc.strerror or exc}'
    if head != MCAP_MAGIC:
        return (
            f'--bag {path} is not an MCAP recording; give the run.mcap of an earlier run '
            '(or a rosbag2 MCAP bag holding /mlv/frames)'
        )
    return None


def run(args) -> int:
    try:
        return _run(args)
    except KeyboardInterrupt:  # outside the graph (starting up, or computing the accuracy)
        print('mlv-ros run: interrupted (SIGINT)', file=sys.stderr)
        return SIGNAL_EXIT[signal.SIGINT]


def _source_and_overrides(args) -> tuple[dict, dict]:
    """Return the frame source's parameters and the other nodes' overrides the options give."""
    if args.phantom:
        source = {'source': 'phantom', 'preset': args.phantom}
        for key, val in (('snr', args.snr), ('size', args.size), ('num_phases', args.phases)):
            if val is not None:
                source[key] = float(val) if key == 'snr' else int(val)
    elif args.dicom:
        source = {'source': 'dicom', 'path': str(Path(args.dicom).resolve())}
        if args.study:
            source['study'] = args.study.strip()
    else:
        source = {'source': 'bag', 'path': str(Path(args.bag).resolve())}
    if args.order:
        source['order'] = args.order
    overrides = {'registration': {}}
    if args.particles is not None:
        overrides['registration']['num_particles'] = args.particles
    if args.masks:
        overrides['registration']['mask_path'] = str(Path(args.masks).resolve())
    return source, overrides


def _add_accuracy(args, summary: dict) -> None:
    """Add the accuracy against the truth (a phantom's, a simulated study's) to the summary."""
    truth = find_groundtruth(Path(args.dicom)) if args.dicom else None
    if not ((args.phantom or truth) and summary['phases_complete']):
        return
    acc = (
        phantom_accuracy(Path(summary['mcap']), args.phantom, summary['num_phases'])
        if args.phantom
        else groundtruth_accuracy(Path(summary['mcap']), truth)
    )
    summary['accuracy'] = {
        'es_phase': acc.get('es_phase'),
        'es': acc.get('es'),
        'inside_myocardium': acc.get('inside_myocardium'),
        'coverage': acc.get('coverage'),
        'per_phase': acc.get('per_phase'),
    }
    write_summary(Path(args.out), summary)


def _show(args, summary: dict) -> int:
    """Print the run's summary lines (stdout) and what to make of it (stderr); return the code."""
    if args.verbose:
        print(
            json.dumps(
                {k: v for k, v in summary.items() if k != 'accuracy'}
                | ({'accuracy_es': summary['accuracy']['es']} if 'accuracy' in summary else {}),
                indent=2,
            )
        )
    code, how = exit_status(summary)
    print(
        '\n'.join(
            summary_lines(
                summary, exit_status=code, exit_reason=how, accuracy=summary.get('accuracy')
            )
        ),
        flush=True,
    )
    line = outcome_line(summary)
    if line:
        print(f'mlv-ros run: {line}', file=sys.stderr)
    quality = verdict_line(summary)
    if quality:
        print(f'mlv-ros run: {quality}', file=sys.stderr)
    if code == EXIT_UNTRACKED:
        print(
            'mlv-ros run: the study could not be tracked: every phase after end-diastole failed '
            "(check the tags are visible in the images and the study's protocol)",
            file=sys.stderr,
        )
    elif (
        not summary['interrupted']
        and summary['phases_complete']
        and not summary['failed']
        and summary.get('twist_extrapolated')
    ):
        # How to read the twist of a run that ended normally (an interrupted or failed run says
        # only why, in one line).
        print(f'mlv-ros run: {summary["twist_extrapolated"]}', file=sys.stderr)
    return code


def _run(args) -> int:
    mistake = check_args(args)
    if mistake:
        print(f'mlv-ros run: {mistake}', file=sys.stderr)
        return EXIT_USAGE
    source, overrides = _source_and_overrides(args)
    console = RunConsole(verbose=args.verbose, progress=not (args.no_progress or args.quiet))
    restore = console.quiet_nodes()
    try:
        summary = run_graph(
            source,
            Path(args.out),
            args.params,
            overrides,
            args.timeout,
            progress=console.line,
            domain_id=args.domain_id,
            grace=args.grace,
            namespace=args.namespace,
            live=({} if args.live_port is None else {'port': args.live_port})
            if args.live or args.live_port is not None
            else None,
            on_phase=console.phase,
        )
    except RunInterrupted as exc:
        print(f'mlv-ros run: {exc}; nothing recorded', file=sys.stderr)
        return SIGNAL_EXIT[exc.signum]
    except (
        FileExistsError,
        FileNotFoundError,
        ValueError,
    ) as exc:  # RunStartError is a ValueError
        print(f'mlv-ros run: {exc}', file=sys.stderr)
        return EXIT_USAGE
    finally:
        console.close()
        restore()
    _add_accuracy(args, summary)
    return _show(args, summary)
