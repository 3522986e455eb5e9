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

RSS is read every period from ``/proc/PID/statm`` (the kernel's counters: ~0.03 ms a process);
a rollup walks every page of the process (~4–7 ms a 400 MB process on the 2-core EPYC host at
load 10, where one every 0.1 s for the three processes of a graph run cost 3–6 s of system CPU a
study), so PSS and USS are rolled up every ``rollup_s`` and whenever the summed RSS exceeds the
largest sum rolled up so far by more than :data:`ROLLUP_MARGIN`: a PSS/USS peak between two
rollups that leaves the RSS below that is missed (by at most about the margin where PSS follows
RSS, as in a graph run, whose peaks are its arrays').

Linux only (``/proc``); elsewhere every figure is None. Sizes in MB (2²⁰ bytes).
"""

from __future__ import annotations

import os
from pathlib import Path
import threading
import time

_FIELDS = {'Rss:': 'rss', 'Pss:': 'pss', 'Private_Clean:': 'uss', 'Private_Dirty:': 'uss'}
#: A summed RSS this fraction above the largest rolled up so far triggers a rollup (a run's RSS
#: climbs in many small steps: a rollup at each new high was ~20 % of the samples).
ROLLUP_MARGIN = 0.01
_PAGE_MB = os.sysconf('SC_PAGE_SIZE') / 2**20 if hasattr(os, 'sysconf') else 4096 / 2**20


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


def resident(pid: int) -> float | None:
    """
    Return one process's RSS from ``/proc/PID/statm`` (the kernel's counters, no page walk), MB.

    Parameters
    ----------
    pid : int
        The process.

    Returns
    -------
    float or None
        RSS, MB; None if the process is gone or unreadable.

    """
    try:
        with open(f'/proc/{pid}/statm', 'rb') as fh:
            return int(fh.read().split()[1]) * _PAGE_MB
    except (OSError, IndexError, ValueError):
        return None


def descendants(root: int) -> list:
    """
    Return the processes below ``root`` (children, their children, ...).

    From each process's ``/proc/PID/task/TID/children`` (~0.01 ms a thread); where the kernel
    has none (no ``CONFIG_PROC_CHILDREN``), by a scan of every process's ``/proc/PID/stat``
    (~3.5–8 ms on a host with ~130 processes, once a ``rescan_s``).

    Parameters
    ----------
    root : int
        The tree's root process.

    Returns
    -------
    list of int
        Their pids, ``root`` not included.

    """
    if not Path(f'/proc/{root}/task/{root}/children').exists():
        return _descendants_by_scan(root)
    found, frontier = [], [root]
    while frontier:
        pid = frontier.pop()
        kids = []
        try:
            tasks = os.listdir(f'/proc/{pid}/task')
        except OSError:
            continue  # gone
        for tid in tasks:
            try:
                with open(f'/proc/{pid}/task/{tid}/children', 'rb') as fh:
                    kids += [int(c) for c in fh.read().split()]
            except OSError:
                continue  # the thread ended
        found += kids
        frontier += kids
    return found


def _descendants_by_scan(root: int) -> list:
    """Return :func:`descendants` from every process's parent in ``/proc/PID/stat``."""
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
        Seconds between looks for the tree's processes (:func:`descendants`); a process started
        in between is sampled from the next.
    rollup_s : float
        Longest time between two rollups of PSS and USS (also taken whenever the summed RSS is
        :data:`ROLLUP_MARGIN` above the largest sum rolled up so far, and by every
        :meth:`sample` called directly).

    Raises
    ------
    ValueError
        ``period_s``, ``rescan_s`` or ``rollup_s`` not positive.

    """

    def __init__(
        self,
        root: int | None = None,
        period_s: float = 0.1,
        rescan_s: float = 1.0,
        rollup_s: float = 1.0,
    ):
        if not period_s > 0:
            raise ValueError(f'period_s must be > 0, got {period_s}')
        if not rescan_s > 0:
            raise ValueError(f'rescan_s must be > 0, got {rescan_s}')
        if not rollup_s > 0:
            raise ValueError(f'rollup_s must be > 0, got {rollup_s}')
        self.root = os.getpid() if root is None else int(root)
        self.period_s, self.rescan_s = float(period_s), float(rescan_s)
        self.rollup_s = float(rollup_s)
        self._pids, self._scanned = [], -float('inf')
        self._rolled, self._rolled_rss = -float('inf'), -1.0  # last rollup: when, its RSS sum
        self._labels: dict = {}
        self.rollups = 0
        self.available = Path(f'/proc/{self.root}/smaps_rollup').exists()
        self.samples = 0
        self.peak = {'rss': 0.0, 'pss': 0.0, 'uss': 0.0}
        self.per_process: dict = {}  # label → its largest {rss, pss, uss} seen
        self._stop = threading.Event()
        self._thread = None

    def sample(self, rollup_all: bool = True) -> dict:
        """
        Take one sample now; fold it into the peaks.

        Parameters
        ----------
        rollup_all : bool
            Roll up PSS and USS now (default); else only when due (``rollup_s``, an RSS high).

        Returns
        -------
        dict
            ``{'rss', 'pss', 'uss'}`` summed over the tree at this instant, MB (``pss`` and
            ``uss`` None when not rolled up).

        """
        now = time.monotonic()
        if now - self._scanned >= self.rescan_s:
            self._pids, self._scanned = descendants(self.root), now
        pids = [self.root, *self._pids]
        rss = {pid: resident(pid) for pid in pids}
        rss_sum = sum(v for v in rss.values() if v is not None)
        due = now - self._rolled >= self.rollup_s
        if rollup_all or due or rss_sum > (1.0 + ROLLUP_MARGIN) * self._rolled_rss:
            return self._rollup(pids, now)
        for pid, mem in rss.items():
            if mem is not None:
                seen = self._seen(pid)
                seen['rss'] = max(seen['rss'], mem)
        self.peak['rss'] = max(self.peak['rss'], rss_sum)
        self.samples += 1
        return {'rss': rss_sum, 'pss': None, 'uss': None}

    def _seen(self, pid: int) -> dict:
        """Return the peaks kept for one process (created on its first sample)."""
        if pid not in self._labels:
            self._labels[pid] = 'root' if pid == self.root else f'{_label(pid)}[{pid}]'
        return self.per_process.setdefault(self._labels[pid], dict.fromkeys(self.peak, 0.0))

    def _rollup(self, pids: list, now: float) -> dict:
        """Sample RSS, PSS and USS of ``pids`` from their rollups; fold them into the peaks."""
        total = {'rss': 0.0, 'pss': 0.0, 'uss': 0.0}
        for pid in pids:
            mem = rollup(pid)
            if mem is None:
                continue
            seen = self._seen(pid)
            for k in total:
                total[k] += mem[k]
                seen[k] = max(seen[k], mem[k])
        for k in total:
            self.peak[k] = max(self.peak[k], total[k])
        self._rolled, self._rolled_rss = now, max(self._rolled_rss, total['rss'])
        self.samples += 1
        self.rollups += 1
        return total

    def _run(self):
        while not self._stop.wait(self.period_s):
            self.sample(rollup_all=False)

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
            ``per_process_peak_mb`` {label: {'rss', 'pss', 'uss'}}, ``samples``, ``rollups``
            (those with PSS and USS), ``period_s`` and ``rollup_s``.

        """
        r1 = {k: round(v, 1) for k, v in self.peak.items()} if self.available else None
        return {
            'peak_summed_mb': r1,
            'per_process_peak_mb': {
                k: {f: round(v, 1) for f, v in d.items()} for k, d in self.per_process.items()
            },
            'samples': self.samples,
            'rollups': self.rollups,
            'period_s': self.period_s,
            'rollup_s': self.rollup_s,
        }
