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
One compute thread in every graph process, whatever the environment says.

The same study must give the same motion, to the bit, however the graph is laid out (one process, a
child process, one process per node under ``ros2 launch``, several hosts).

OpenBLAS sums a matrix product's inner dimension in an order that depends on how many threads it
runs (measured: ``(a·w)ᵀ a`` of a 3000 × 143 design matrix differs by 2e-13 between 1 and 2
threads), so the registration's wall-surface fit moved the registered particles by 7e-14 mm with
the thread count, and the solver's CG stopping rule turned that into 0.016 mm at one phase of the
test_multihost study (its last local solve, at rtol 1e-3, took 91 CG iterations instead of 90;
the change, not its size, is what the stopping rule amplifies). The thread count of a process is
whatever its OpenBLAS read from ``OPENBLAS_NUM_THREADS`` when numpy was imported (the machine's
cores if unset), so a node started from its console script, one started by ``mlv-ros run`` (which
sets 1) and the nodes of a run inside a process that imported numpy earlier (a test, a notebook)
each had their own. The pools are therefore set at run time, with threadpoolctl, for every BLAS
and OpenMP library loaded; one thread is also what the graph's many small products run fastest
with (measured in :mod:`mlv_ros.cli`). OpenCV's pool is set to one thread alike.
"""

from __future__ import annotations

import contextlib
import sys

COMPUTE_THREADS = 1


@contextlib.contextmanager
def compute_threads():
    """
    Hold the BLAS/OpenMP and OpenCV thread pools at :data:`COMPUTE_THREADS` in the block.

    Every BLAS/OpenMP pool loaded in this process (numpy's, scipy's and OpenCV's OpenBLAS, any
    OpenMP runtime) and OpenCV's own pool are held at :data:`COMPUTE_THREADS` thread(s) while the
    block runs, then restored to what they were.

    scipy's OpenBLAS is loaded first (scipy.linalg), so that a node importing it later is held
    too; OpenCV is held only if imported before the block (import the node classes first).
    """
    import numpy  # noqa: F401  (its OpenBLAS)
    import scipy.linalg  # noqa: F401  (scipy's own OpenBLAS)
    from threadpoolctl import threadpool_limits

    cv2 = sys.modules.get('cv2')
    cv_before = cv2.getNumThreads() if cv2 is not None else None
    with threadpool_limits(limits=COMPUTE_THREADS):
        if cv2 is not None:
            cv2.setNumThreads(COMPUTE_THREADS)
        try:
            yield
        finally:
            if cv2 is not None:
                cv2.setNumThreads(cv_before)
