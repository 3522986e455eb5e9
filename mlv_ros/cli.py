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
``mlv-ros``: the command-line front end.

Each subcommand lives in ``mlv_ros.tools.<name>`` and exposes ``add_arguments(parser)`` and
``run(args) -> int``; modules are imported only when their subcommand runs, so a broken or slow
import in one never affects another.

Errors reach the user as one line on stderr, saying what to change, with a non-zero exit: the
argument parser's own (usage goes to ``--help``), each tool's known mistakes, and, as a last
resort, anything a tool let through (``MLV_ROS_TRACEBACK=1`` shows the traceback).
"""

from __future__ import annotations

import argparse
import errno
import importlib
import math
import os
import sys

# One compute thread per process for OpenBLAS/OpenMP and OpenCV (unless the user set them): the
# graph's work is many small numpy/scipy/OpenCV calls, and a second pool thread only spins on
# the core the first needs (pcg in core/meshless/local.py measured that for BLAS). Set before
# numpy, scipy or cv2 is imported, which happens only below (the tools import them). Measured
# on the 2-core machine under load (4-6), `bench pipeline` (default study, one process): 28.4,
# 30.9, 33.9, 29.0 s with the default pools, 26.9, 26.9 s with one thread; the tag detector in
# a process of its own was slowed 3x by the other's pool threads. (The graph's processes hold
# their pools at one thread at run time in any case, mlv_ros/threads.py, so that the motion is
# the same in any layout; this covers the other subcommands.)
for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'OPENCV_FOR_THREADS_NUM'):
    os.environ.setdefault(_var, '1')

SUBCOMMANDS = {
    'demo': ('mlv_ros.tools.demo', 'run the whole pipeline on the built-in normal phantom'),
    'run': ('mlv_ros.tools.run', 'run the graph on DICOM, a phantom preset or a bag'),
    'simulate': (
        'mlv_ros.tools.simulate',
        'write a simulated tagged-MRI study (DICOM + ground truth)',
    ),
    'report': ('mlv_ros.tools.report', 'build the motion report from a recorded run'),
    'export': (
        'mlv_ros.tools.export',
        'write a recorded run as a ParaView time series (.pvd/.vtu) and strain CSV',
    ),
    'recover': ('mlv_ros.tools.recover', 'rewrite a valid MCAP from a damaged one'),
    'bench': ('mlv_ros.tools.bench', 'run benchmarks (JSON to stdout)'),
}


class OneLineParser(argparse.ArgumentParser):
    """An argparse parser whose errors are one line (the usage block is ``--help``'s job)."""

    def error(self, message):
        self.exit(2, f'{self.prog}: {message} (see {self.prog} --help)\n')


def number(kind=float, min_value=None, max_value=None, *, above=None):
    """
    Return an argparse ``type`` for a finite int/float within bounds (``above``: strictly greater).

    ``nan``, ``inf`` and out-of-range values are refused with the allowed range, so they never
    reach code that would fail far from the option that caused it.
    """

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f'{text!r} is not {"an integer" if kind is int else "a number"}'
            ) from None
        if isinstance(value, float) and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f'{text!r} is not a finite number')
        if above is not None and not value > above:
            raise argparse.ArgumentTypeError(f'must be > {above:g}, got {text}')
        if min_value is not None and value < min_value:
            raise argparse.ArgumentTypeError(f'must be >= {min_value:g}, got {text}')
        if max_value is not None and value > max_value:
            raise argparse.ArgumentTypeError(f'must be <= {max_value:g}, got {text}')
        return value

    parse.__name__ = kind.__name__
    return parse


def one_line(text) -> str:
    """``text`` on a single line (exception messages may span several)."""
    return ' '.join(str(text).split())


def describe_os_error(exc: OSError) -> str:
    """Describe an OSError as what happened to which path, and what to do about it."""
    where = exc.filename if exc.filename is not None else ''
    what = exc.strerror or str(exc)
    fix = {
        errno.ENOENT: 'check the path',
        errno.EACCES: 'choose a place you may write to',
        errno.EPERM: 'choose a place you may write to',
        errno.EROFS: 'the disk is read-only: choose another place',
        errno.ENOSPC: 'the disk is full: free space or choose another place',
        errno.EISDIR: 'give a file, not a directory',
        errno.ENOTDIR: 'a part of the path is a file, not a directory',
        errno.EEXIST: 'choose a new name',
    }.get(exc.errno)
    text = f'{where}: {what}' if where else what
    return one_line(f'{text} ({fix})' if fix else text)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog='mlv-ros', description=__doc__.strip().splitlines()[0])
    sub = parser.add_subparsers(dest='command', metavar='COMMAND', required=True)
    for name, (module, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        try:
            importlib.import_module(module).add_arguments(p)
        except ModuleNotFoundError as exc:
            if exc.name != module:
                raise
            p.set_defaults(_missing=True)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    prog = f'mlv-ros {args.command}'
    if getattr(args, '_missing', False):
        print(f'{prog}: not available in this version', file=sys.stderr)
        return 2
    try:
        return int(importlib.import_module(args._module).run(args) or 0)
    except KeyboardInterrupt:
        print(f'{prog}: interrupted', file=sys.stderr)
        return 130
    except OSError as exc:  # a path the tool did not check: say which and what to do
        if os.environ.get('MLV_ROS_TRACEBACK'):
            raise
        print(f'{prog}: {describe_os_error(exc)}', file=sys.stderr)
        return 2
    except Exception as exc:  # a bug or a case no tool foresaw: one line, traceback on request
        if os.environ.get('MLV_ROS_TRACEBACK'):
            raise
        print(
            f'{prog}: unexpected {type(exc).__name__}: {one_line(exc)} '
            '(set MLV_ROS_TRACEBACK=1 to see where, and please report it)',
            file=sys.stderr,
        )
        return 1


if __name__ == '__main__':
    sys.exit(main())


def error_text(exc: BaseException) -> str:
    """
    Return an exception as one line of text.

    Expected errors by their message, anything else (a bug) with its type and where it was raised.
    """
    from rclpy.exceptions import InvalidParameterValueException, ParameterException

    if isinstance(exc, InvalidParameterValueException):  # rclpy's text ends in ": <name>"
        reason = str(exc).partition('Reason: ')[2].rpartition(': ')[0]
        return f'{reason or exc} (see --params)'
    if type(exc).__name__ == 'RCLInvalidROSArgsError':  # rcl refusing the parameters file
        reason = str(exc).partition('Error: ')[2].partition(', at /')[0]
        return f'the parameters file cannot be read by ROS: {reason or exc} (see --params)'
    if isinstance(exc, (ValueError, OSError, ParameterException)):
        return str(exc)
    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    file = os.path.basename(tb.tb_frame.f_code.co_filename) if tb else ''
    where = f' (at {file}:{tb.tb_lineno})' if tb else ''
    return f'{type(exc).__name__}: {exc}{where}'
