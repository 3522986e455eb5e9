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
``bench/_memory.py``: a process tree's RSS / PSS / USS, summed at one instant.

A grandchild (started through a shell, so it is not this process's own child) that writes to
64 MB of its own is found and its private pages counted; the three figures are ordered as their
definitions order them (USS ≤ PSS ≤ RSS per process and summed), and a shared page is counted
whole in RSS but split in PSS.
"""

from pathlib import Path
import subprocess
import sys

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'bench'))
from _memory import descendants, rollup, TreeMemory  # noqa: E402, I100

pytestmark = pytest.mark.skipif(
    not Path('/proc/self/smaps_rollup').exists(), reason='needs Linux /proc smaps_rollup'
)

ALLOC_MB = 64
# touches every page of 64 MB, says so, and waits for its stdin to close
CHILD = (
    f'import sys; b = bytearray({ALLOC_MB} * 2**20); b[::4096] = b"x" * len(b[::4096]); '
    'print("ready", flush=True); sys.stdin.read()'
)


def test_a_grandchilds_private_memory_is_found_and_the_figures_are_ordered():
    shell = subprocess.Popen(
        ['sh', '-c', f"'{sys.executable}' -c '{CHILD}'; exit $?"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert shell.stdout.readline().strip() == 'ready'
        below = descendants(shell.pid)
        assert below, 'the python under the shell was not found'
        with TreeMemory(period_s=0.05) as mem:
            now = mem.sample()
        res = mem.result()
    finally:
        shell.stdin.close()
        shell.wait(timeout=30)
    grandchild = rollup(below[0])  # gone now: the process ended
    assert grandchild is None
    peak = res['peak_summed_mb']
    assert res['samples'] >= 3  # on entry, the explicit one, on exit
    # the 64 MB written are private to the grandchild: counted in each figure
    kids = {k: v for k, v in res['per_process_peak_mb'].items() if k != 'root'}
    assert max(v['uss'] for v in kids.values()) >= ALLOC_MB - 1, kids
    for v in [peak, now, *res['per_process_peak_mb'].values()]:
        assert 0 < v['uss'] <= v['pss'] <= v['rss'], v
    # the interpreter's pages are mapped by this process and the grandchild: PSS splits them
    assert peak['pss'] < peak['rss']


def test_periods_must_be_positive():
    with pytest.raises(ValueError, match='period_s must be > 0'):
        TreeMemory(period_s=0)
    with pytest.raises(ValueError, match='rescan_s must be > 0'):
        TreeMemory(rescan_s=-1.0)
    with pytest.raises(ValueError, match='rollup_s must be > 0'):
        TreeMemory(rollup_s=0.0)


def test_samples_between_rollups_read_rss_alone():
    mem = TreeMemory(period_s=0.05, rollup_s=3600.0)
    first = mem.sample()  # a direct call rolls up
    assert first['pss'] is not None and mem.rollups == 1
    cheap = mem.sample(rollup_all=False)  # not due, RSS not 1 % above the last rollup's
    assert cheap['pss'] is None and cheap['uss'] is None and mem.rollups == 1
    # the kernel's counters and the page walk give this process's RSS alike (a few pages apart)
    assert cheap['rss'] == pytest.approx(first['rss'], rel=0.01)
    assert mem.samples == 2 and mem.result()['rollups'] == 1
