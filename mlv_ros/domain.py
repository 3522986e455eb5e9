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
A private ROS_DOMAIN_ID for a run or a test process.

Two in-process graphs on one machine and one domain would hear each other's frames. A run (or a
test process) therefore claims a domain id by holding an exclusive ``flock`` on a per-id file;
the lock is released when the process exits, so concurrent runs never share a domain.
"""

from __future__ import annotations

import fcntl
from pathlib import Path
import tempfile

_HELD: list = []  # lock files kept open for the life of the process


def claim_domain_id(first: int = 101) -> int:
    """Lowest free id in ``first``..232, then 1..first-1 (Fast DDS accepts 0..232)."""
    lock_dir = Path(tempfile.gettempdir()) / 'mlv_ros_domains'
    lock_dir.mkdir(exist_ok=True)
    for domain in [*range(first, 233), *range(1, first)]:
        fh = open(lock_dir / f'{domain}.lock', 'w')
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.close()
            continue
        _HELD.append(fh)
        return domain
    raise RuntimeError('no free ROS domain id (1..232) on this machine')
