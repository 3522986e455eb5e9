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
What ``launch/pipeline.launch.py`` makes of its arguments.

Kept free of launch and launch_ros (not on PyPI) so it can be tested without them.

Each launch gets its own run directory unless ``output_dir`` names one: ``runs/<YYYYmmdd-HHMMSS>``
under the directory ``ros2 launch`` was started from, created at once (``-2``, ``-3``... when
that second is taken), so a second launch from the same directory never finds the first one's
recording in its way.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
import time

from mlv_ros.qos import full_namespace, namespace_error

SOURCES = ('phantom', 'dicom', 'bag')
RUNS_DIR = 'runs'


@dataclass
class GraphSettings:
    """What the launch file starts the graph with."""

    namespace: str  # "" for the root (launch_ros's spelling), else "/study2"
    output_dir: Path  # the run directory; the recorder writes output_dir/run.mcap
    overrides: dict = field(
        default_factory=dict
    )  # node → {parameter: value}, over the params file


def fresh_run_dir(base: str | Path = RUNS_DIR, now: float | None = None) -> Path:
    """
    Create and return a new run directory ``base/<YYYYmmdd-HHMMSS>``.

    ``-2``, ``-3``... are appended when the name is taken.

    Parameters
    ----------
    base : str or Path
        Where runs go (created if missing).
    now : float, optional
        The time to name it for (default: now).

    Returns
    -------
    Path
        The directory, created empty by this call (so two launches never get the same one).

    """
    base = Path(base)
    base.mkdir(parents=True, exist_ok=True)
    stem = time.strftime('%Y%m%d-%H%M%S', time.localtime(time.time() if now is None else now))
    for n in range(1, 1000):
        candidate = base / (stem if n == 1 else f'{stem}-{n}')
        try:
            candidate.mkdir()
        except FileExistsError:
            continue
        return candidate
    raise FileExistsError(f'{base}: no free run directory for {stem}; give output_dir:=DIR')


def graph_settings(
    source: str = 'phantom',
    path: str = '',
    output_dir: str = '',
    namespace: str = '',
    cwd: str | Path | None = None,
) -> GraphSettings:
    """
    Return the graph's namespace, run directory and parameter overrides for the launch arguments.

    Parameters
    ----------
    source : str
        ``phantom``, ``dicom`` or ``bag`` (frame_source's ``source``).
    path : str
        The DICOM directory (``dicom``) or recording (``bag``); relative to ``cwd``.
    output_dir : str
        The run directory; empty: a fresh one under ``cwd/runs`` (:func:`fresh_run_dir`).
    namespace : str
        ROS namespace of every node (``study2`` or ``/study2``); empty: the root.
    cwd : str or Path, optional
        The directory relative paths are taken from (default: the current one).

    Returns
    -------
    GraphSettings

    Raises
    ------
    ValueError
        An argument that cannot work, in one line with the fix.

    """
    cwd = Path.cwd() if cwd is None else Path(cwd)
    if source not in SOURCES:
        raise ValueError(
            f'source:={source} is not one of {", ".join(SOURCES)}: e.g. source:=dicom '
            'path:=/data/study'
        )
    if source != 'phantom' and not path:
        what = 'DICOM directory' if source == 'dicom' else 'recording'
        raise ValueError(f'source:={source} needs path:= (the {what})')
    if namespace_error(namespace):
        raise ValueError(f'namespace:={namespace_error(namespace)}')
    ns = full_namespace(namespace)
    overrides = {'frame_source': {'source': source}}
    if path:
        overrides['frame_source']['path'] = str((cwd / Path(path).expanduser()).resolve())
    out = (
        (cwd / Path(output_dir).expanduser()).resolve()
        if output_dir
        else fresh_run_dir(cwd / RUNS_DIR)
    )
    if (out / 'run.mcap').exists():
        raise ValueError(
            f'output_dir:={out} already holds a run (run.mcap): give a new directory, or leave '
            'output_dir out for a fresh one under runs/'
        )
    overrides['recorder'] = {'output': str(out / 'run.mcap')}
    if ns != '/':  # /diagnostics is shared: name each status by the node's full name
        for node in (
            'frame_source',
            'tag_detector',
            'registration',
            'meshless_solver',
            'motion_analyzer',
            'recorder',
            'live_view',
        ):
            overrides.setdefault(node, {})['diagnostic_updater.use_fqn'] = True
    return GraphSettings(namespace='' if ns == '/' else ns, output_dir=out, overrides=overrides)
