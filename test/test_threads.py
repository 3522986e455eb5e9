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
mlv_ros.threads: one BLAS/OpenMP/OpenCV thread in every graph process.

mlv_ros.threads: every graph process computes with one BLAS/OpenMP/OpenCV thread whatever its
libraries started with, because OpenBLAS's sums depend on its thread count and the same study
must give the same motion in any process layout (test_multihost checks that end to end).
"""

import os

import cv2
from mlv_ros.threads import COMPUTE_THREADS, compute_threads
import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits


def _product():
    """Return a weighted normal-equations product like the registration's wall-surface fit."""
    a = np.random.default_rng(0).standard_normal((3000, 143))
    w = np.linspace(0.5, 2.0, 3000)
    return (a * w[:, None]).T @ a


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason='one core: OpenBLAS runs one thread anyway')
def test_compute_threads_hold_every_pool_at_one_and_restore_them():
    with threadpool_limits(limits=1):
        one = _product()
    cv_before = cv2.getNumThreads()
    with threadpool_limits(limits=2):
        # On most OpenBLAS kernels this product's bits depend on the thread count, so ``held ==
        # one`` below shows the pools held; some (the Haswell kernel on an AMD EPYC host) give the
        # same bits at 1 and 2 threads, and there the thread counts asserted are what shows it.
        with compute_threads():
            assert {p['num_threads'] for p in threadpool_info()} == {COMPUTE_THREADS}
            assert cv2.getNumThreads() == COMPUTE_THREADS
            held = _product()
        assert {p['num_threads'] for p in threadpool_info() if p['user_api'] == 'blas'} == {2}
    assert cv2.getNumThreads() == cv_before
    np.testing.assert_array_equal(held, one)


def test_a_node_process_computes_with_one_thread():
    """
    Check that run_node holds the thread pools while the node lives.

    run_node (every node's console script, so every process under ``ros2 launch``) holds the
    pools while the node lives, whatever the process started with.
    """
    from mlv_ros.nodes.common import run_node

    seen = []

    def factory():
        seen.append({p['num_threads'] for p in threadpool_info()})
        raise ValueError('built far enough')  # run_node: a node that cannot start exits 2

    with threadpool_limits(limits=2):
        assert run_node(factory, args=[]) == 2
    assert seen == [{COMPUTE_THREADS}]
