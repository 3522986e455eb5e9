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
The ``mlv-ros`` subprocesses a graph benchmark runs per case: simulate a study, run the graph.

Shared by ``bench/robustness.py`` and ``bench/strain.py`` (a bench-local module: its leading
underscore keeps it out of ``mlv-ros bench``'s list). Each call runs this interpreter's
``mlv-ros``, so a benchmark measures the tree it was started from.
"""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile

BIN = Path(sys.executable).parent


def add_case_options(ap) -> None:
    """
    Add the options every graph benchmark takes: ``--out``, ``--keep`` and ``--timeout``.

    Parameters
    ----------
    ap : argparse.ArgumentParser
        The benchmark's parser.

    """
    ap.add_argument(
        '--out', default=None, help='keep studies and runs here (default: a temporary directory)'
    )
    ap.add_argument('--keep', action='store_true', help='keep the temporary directory')
    ap.add_argument('--timeout', type=float, default=900.0, help='per-run limit, seconds')


@contextmanager
def cases_folder(args, name: str):
    """
    Yield the folder the cases are written under: ``--out``, or a temporary one.

    Parameters
    ----------
    args : argparse.Namespace
        With ``out`` and ``keep`` (:func:`add_case_options`).
    name : str
        The benchmark's name, in the temporary folder's.

    Yields
    ------
    Path
        The folder; a temporary one is removed afterwards unless ``--keep``.

    """
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix=f'mlv-bench-{name}-'))
    try:
        yield root
    finally:
        if not args.out and not args.keep:
            shutil.rmtree(root, ignore_errors=True)


def mlv_ros(*args: str) -> subprocess.CompletedProcess:
    """
    Run ``mlv-ros ARGS...`` and wait for it.

    Parameters
    ----------
    *args : str
        The subcommand and its arguments.

    Returns
    -------
    subprocess.CompletedProcess
        Its exit code, with stdout and stderr as text.

    """
    return subprocess.run([str(BIN / 'mlv-ros'), *args], capture_output=True, text=True)


def simulate(seed: int, study: Path, *options: str) -> str | None:
    """
    Write the study ``mlv-ros simulate --random SEED`` draws.

    Parameters
    ----------
    seed : int
        The protocol seed.
    study : Path
        Output folder (``dicom/``, ``protocol.yaml``, ``groundtruth.json``, ...).
    *options : str
        Further ``mlv-ros simulate`` options (``--protocol FILE``, ``--phases N``).

    Returns
    -------
    str or None
        Why it failed (exit code and the end of its stderr), or None.

    """
    sim = mlv_ros(
        'simulate', '--random', str(seed), *options, '--out', str(study), '--no-progress'
    )
    if sim.returncode == 0:
        return None
    return f'simulate exited {sim.returncode}: {sim.stderr.strip()[-400:]}'


def run_dicom(study: Path, run_dir: Path, timeout: float) -> tuple[int, str | None]:
    """
    Run the whole graph on a simulated study's DICOM files (``mlv-ros run --dicom``).

    Parameters
    ----------
    study : Path
        The study folder (:func:`simulate`); its ``dicom/`` is read.
    run_dir : Path
        The run's ``--out`` folder (``run.mcap``, ``summary.json``, ...).
    timeout : float
        The run's ``--timeout``, seconds.

    Returns
    -------
    exit : int
        ``mlv-ros run``'s exit code.
    error : str or None
        Why there is no recording (the exit code and the end of its stderr), or None.

    """
    run = mlv_ros(
        'run',
        '--dicom',
        str(study / 'dicom'),
        '--out',
        str(run_dir),
        '--quiet',
        '--timeout',
        str(timeout),
    )
    if (run_dir / 'run.mcap').exists():
        return run.returncode, None
    return run.returncode, (
        f'run exited {run.returncode} without a recording: {run.stderr.strip()[-400:]}'
    )
