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
Memory of a process tree, sampled: RSS, PSS and USS summed over the processes at each instant.

``ru_maxrss`` gives each process's own peak, and a sum of those peaks counts every shared page
(Python, numpy, scipy, OpenCV, the ROS libraries) once per process and adds peaks that never
happened together. :class:`TreeMemory` reads ``/proc/PID/smaps_rollup`` of a process and all its
descendants every ``period_s`` in a thread and keeps the largest sums over one instant of

- **RSS**: resident pages, a shared page counted in every process that maps it;
- **PSS**: each shared page divided among the processes that map it (system-wide), so the sum
  counts the tree's shared libraries about once;
- **USS**: pages private to a process (``Private_Clean + Private_Dirty``): what ending it frees.

Linux only (``/proc``); elsewhere every figure is None. Sizes in MB (2²⁰ bytes).
"""

from __future__ import annotations

import os
from pathlib import Path
import threading
import time

_FIELDS = {'Rss:': 'rss', 'Pss:': 'pss', 'Private_Clean:': 'uss', 'Private_Dirty:': 'uss'}


def rollup(pid: int) -> dict | None:
    """
    Return one process's resident memory from its ``smaps_rollup``, in MB.

    Parameters
    ----------
    pid : int
        The process.

    Returns
    -------
    dict or None
        ``{'rss', 'pss', 'uss'}``, MB; None if the process is gone or unreadable.

    """
    out = {'rss': 0.0, 'pss': 0.0, 'uss': 0.0}
    try:
        text = Path(f'/proc/{pid}/smaps_rollup').read_text()
    except OSError:
        return None
    for line in text.splitlines():
        parts = line.split()
        key = _FIELDS.get(parts[0]) if parts else None
        if key is not None:
            out[key] += int(parts[1]) / 1024.0  # kB
    return out


def descendants(root: int) -> list:
    """
    Return the processes below ``root`` (children, their children, ...), by a scan of ``/proc``.

    Parameters
    ----------
    root : int
        The tree's root process.

    Returns
    -------
    list of int
        Their pids, ``root`` not included.

    """
    parent = {}
    for entry in os.scandir('/proc'):
        if not entry.name.isdigit():
            continue
        try:
            stat = Path(f'/proc/{entry.name}/stat').read_text()
        except OSError:
            continue
        # the command name (field 2) is in parentheses and may hold spaces: split after it
        parent[int(entry.name)] = int(stat[stat.rindex(')') + 2:].split()[1])
    found, frontier = [], [root]
    while frontier:
        pid = frontier.pop()
        kids = [c for c, p in parent.items() if p == pid]
        found += kids
        frontier += kids
    return found


def _label(pid: int) -> str:
    """Return a process's name for the report: its ``-m`` module or script, else its command."""
    try:
        argv = Path(f'/proc/{pid}/cmdline').read_bytes().split(b'\0')
    except OSError:
        return str(pid)
    argv = [a.decode(errors='replace') for a in argv if a]
    if '-m' in argv[:-1]:
        return argv[argv.index('-m') + 1]
    scripts = [Path(a).name for a in argv[1:2] if a.endswith('.py')]
    return scripts[0] if scripts else Path(argv[0]).name if argv else str(pid)


class TreeMemory:
    """
    Sample a process tree's memory in a thread; the peaks of the sums over one instant.

    Use as a context manager around the work; :meth:`result` afterwards.

    Parameters
    ----------
    root : int, optional
        The tree's root; default this process.
    period_s : float
        Seconds between samples (a peak shorter than that may be missed; each process's own
        exact peak is ``ru_maxrss``).
    rescan_s : float
        Seconds between scans of ``/proc`` for the tree's processes (~3.5 ms of CPU a scan; a
        rollup ~0.3 ms a process); a process started in between is sampled from the next scan.

    Raises
    ------
    ValueError
        ``period_s`` or ``rescan_s`` not positive.

    """

    def __init__(self, root: int | None = None, period_s: float = 0.1, rescan_s: float = 1.0):
        if not period_s > 0:
            raise ValueError(f'period_s must be > 0, got {period_s}')
        if not rescan_s > 0:
            raise ValueError(f'rescan_s must be > 0, got {rescan_s}')
        self.root = os.getpid() if root is None else int(root)
        self.period_s, self.rescan_s = float(period_s), float(rescan_s)
        self._pids, self._scanned = [], -float('inf')
        self.available = Path(f'/proc/{self.root}/smaps_rollup').exists()
        self.samples = 0
        self.peak = {'rss': 0.0, 'pss': 0.0, 'uss': 0.0}
        self.per_process: dict = {}  # label → its largest {rss, pss, uss} seen
        self._stop = threading.Event()
        self._thread = None

    def sample(self) -> dict:
        """
        Take one sample now; fold it into the peaks.

        Returns
        -------
        dict
            ``{'rss', 'pss', 'uss'}`` summed over the tree at this instant, MB.

        """
        total = {'rss': 0.0, 'pss': 0.0, 'uss': 0.0}
        if time.monotonic() - self._scanned >= self.rescan_s:
            self._pids, self._scanned = descendants(self.root), time.monotonic()
        for pid in [self.root, *self._pids]:
            mem = rollup(pid)
            if mem is None:
                continue
            label = 'root' if pid == self.root else f'{_label(pid)}[{pid}]'
            seen = self.per_process.setdefault(label, dict.fromkeys(total, 0.0))
            for k in total:
                total[k] += mem[k]
                seen[k] = max(seen[k], mem[k])
        for k in total:
            self.peak[k] = max(self.peak[k], total[k])
        self.samples += 1
        return total

    def _run(self):
        while not self._stop.wait(self.period_s):
            self.sample()

    def __enter__(self) -> 'TreeMemory':
        if self.available:
            self.sample()
            self._thread = threading.Thread(target=self._run, name='tree-memory', daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self.sample()

    def result(self) -> dict:
        """
        Return the peaks: summed over the tree at one instant, and per process, MB.

        Returns
        -------
        dict
            ``peak_summed_mb`` ``{'rss', 'pss', 'uss'}`` (None where ``/proc`` is missing),
            ``per_process_peak_mb`` {label: {'rss', 'pss', 'uss'}}, ``samples`` and
            ``period_s``.

        """
        r1 = {k: round(v, 1) for k, v in self.peak.items()} if self.available else None
        return {
            'peak_summed_mb': r1,
            'per_process_peak_mb': {
                k: {f: round(v, 1) for f, v in d.items()} for k, d in self.per_process.items()
            },
            'samples': self.samples,
            'period_s': self.period_s,
        }
