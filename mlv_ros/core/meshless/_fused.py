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
The local stage's CG product ``A u`` as one compiled pass (C, loaded with ctypes).

Issue 17: with scipy the product is three sparse passes — ``D u`` (CSC), the batched 9 × 9
tangent, ``[Dᵀ | α L]`` on the stacked stresses and displacements — that read the pair layout
three times (2.85 of an iteration's 3.3 ms at 3000 particles), plus the data springs' products.
Here (``_fused.c``) each phyxel ``i`` reads its members once to gather ``H_i = Σ_j u_j ⊗ d_ij``
and the fit error's Laplacian pairs ``s_i w_ij (u_i − u_j)``, applies its tangent and scatters
``d_ijᵀ S_i`` back; then each data spring gathers and scatters its particles: measured ~2× faster
than the scipy products on the default study's operator, equal to them to 1e-15 relative (the
sums' order differs, so not to the bit).

``make bootstrap`` builds ``_fused_c.so`` beside this file with the C compiler the message build
already needs (``cc -O2``: no fast-math, no CPU-specific code, so every build sums alike);
without it, or with ``MLV_ROS_COMPILED=0`` in the environment, :func:`kernel` returns None and
the scipy products are used. Where the CPU has AVX2 the phyxels' loop takes a vector copy of it
chosen at run time (a member's three components in one vector's lanes, ``u`` and the sums padded
to four lanes a particle; each lane sums as the scalar loop does, no FMA: the same bits;
:data:`WIDE` False keeps the scalar loop): the product 0.61× of the scalar pass on the default
study's operator (1.76 against 2.89 ms median at 3000 particles, 300 paired calls, load ~16).
"""

import ctypes
import os
from pathlib import Path

import numpy as np

LIBRARY = Path(__file__).with_name('_fused_c.so')

#: No constant stress (the kernel's last two arguments).
NO_OFFSET = (np.zeros((0, 9)), np.zeros((0, 3)))

#: No data springs, in the kernel's form.
NO_SPRINGS = (0.0, np.zeros(1, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0),
              np.zeros((0, 3, 3)))

#: Let the compiled product take its AVX2 loop where the CPU has one (the same bits).
WIDE = True

_loaded = None  # [the library's product or None], once tried


def springs(kappa: float, phi, metric) -> tuple:
    """
    Return data springs in the kernel's form.

    Parameters
    ----------
    kappa : float
        Their multiplier (P·mm).
    phi : scipy.sparse.csr_matrix, shape (M, N)
        Interpolation weights.
    metric : ndarray, shape (M, 3, 3)
        Their metrics (projectors times weights).

    """
    ptr, cols = checked_rows(phi.indptr, phi.indices, phi.shape[1])
    return (
        float(kappa),
        ptr,
        cols,
        np.ascontiguousarray(phi.data, dtype=np.float64),
        np.ascontiguousarray(metric, dtype=np.float64),
    )


def checked_rows(ptr, cols, n: int) -> tuple[np.ndarray, np.ndarray]:
    """
    Return CSR row pointers and columns as C-contiguous int64, checked to index ``n`` columns.

    Raises
    ------
    ValueError
        The pointers not non-decreasing from 0 to ``len(cols)``, or a column outside [0, n).

    """
    ptr = np.ascontiguousarray(ptr, dtype=np.int64)
    cols = np.ascontiguousarray(cols, dtype=np.int64)
    if ptr.size < 1 or ptr[0] != 0 or int(ptr[-1]) != cols.size or np.any(np.diff(ptr) < 0):
        raise ValueError('compiled product: the row pointers do not span the columns in order')
    if cols.size and (cols.min() < 0 or cols.max() >= n):
        raise ValueError(f'compiled product: a column index outside [0, {n})')
    return ptr, cols


def _pointer(a: np.ndarray, dtype, shape) -> int:
    """Return the data address of ``a``, checked C-contiguous with this dtype and shape."""
    if a.dtype != dtype or not a.flags.c_contiguous or a.shape != shape:
        raise ValueError(
            f'compiled product: expected a C-contiguous {np.dtype(dtype)} array of shape '
            f'{shape}, got {a.dtype} {a.shape}'
        )
    return a.ctypes.data


def _product(
    ptr, cols, d, c, tangent, alpha, eps, springs, u, out, grad, offset, out_offset, *, lib
):
    """
    Add ``Dᵀ T D u + alpha L u + eps u`` and the data springs' ``κ Φᵀ P Φ u`` to ``out`` (N, 3).

    Also writes ``D u`` to ``grad`` (N, 9). Every array is checked (dtype, layout, shape)
    before the C pass reads it.

    Parameters
    ----------
    ptr, cols, d : ndarray
        The MLS gradient by phyxel (:attr:`~mlv_ros.core.meshless.mls.MLSOperator.blocks`):
        phyxel ``i``'s entries ``ptr[i]:ptr[i+1]``, their members ``cols`` and ``d_ij`` (P+N, 3).
    c : ndarray, shape (P+N,)
        The fit-error pair weight ``s_i w_ij`` of each entry (0 for the particle itself).
    tangent : ndarray, shape (N, 9, 9)
        Per-particle tangent in the operator's layout (flat index ``3b + a`` holds
        ``H[a, b]``).
    alpha, eps : float
        Multipliers of the Laplacian and of ``u`` itself (the rigid-mode regulariser).
    springs : tuple
        ``(κ, ptr, cols, φ, P)`` (:func:`springs`; :data:`NO_SPRINGS` for none).
    u : ndarray, shape (N, 3)
        Displacements.
    out : ndarray, shape (N, 3)
        Accumulates the product (zero it first).
    grad : ndarray, shape (N, 9)
        ``D u`` in the operator's layout (row ``i``, ``3b + a``).
    offset, out_offset : ndarray, shapes (N, 9) and (N, 3), or :data:`NO_OFFSET`
        A constant stress in the same layout and where its ``Dᵀ offset`` is added (the
        incompressibility offsets of a right-hand side), in the same pass.
    lib : ctypes.CDLL
        The built library.

    """
    n = ptr.size - 1
    nnz = cols.size
    i8, f8 = np.int64, np.float64
    kappa, sptr, scols, phi, metric = springs
    m = sptr.size - 1
    if n < 0:
        raise ValueError('compiled product: no row pointer')
    with_offset = out_offset.shape[0] > 0
    # the index arrays' contents were checked once (checked_rows); here their ends and sizes
    if ptr[0] != 0 or int(ptr[-1]) != nnz or sptr[0] != 0 or int(sptr[-1]) != scols.size:
        raise ValueError('compiled product: a row pointer does not span its columns')
    lib.product(
        n,
        _pointer(ptr, i8, (n + 1,)),
        _pointer(cols, i8, (nnz,)),
        _pointer(d, f8, (nnz, 3)),
        _pointer(c, f8, (nnz,)),
        _pointer(tangent, f8, (n, 9, 9)),
        float(alpha),
        float(eps),
        float(kappa),
        m,
        _pointer(sptr, i8, (m + 1,)),
        _pointer(scols, i8, (scols.size,)),
        _pointer(phi, f8, (scols.size,)),
        _pointer(metric, f8, (m, 3, 3)),
        _pointer(u, f8, (n, 3)),
        _pointer(out, f8, (n, 3)),
        _pointer(grad, f8, (n, 9)),
        _pointer(offset, f8, (n, 9)) if with_offset else None,
        _pointer(out_offset, f8, (n, 3)) if with_offset else None,
        1 if WIDE else 0,
    )


def kernel():
    """
    Return the compiled product (:func:`_product` without ``lib``), or None.

    None when ``_fused_c.so`` was not built (``make bootstrap``) or does not load, or with
    ``MLV_ROS_COMPILED=0`` set: callers then take the scipy products.
    """
    global _loaded
    if os.environ.get('MLV_ROS_COMPILED', '').strip() == '0':
        return None
    if _loaded is None:
        _loaded = [None]
        try:
            lib = ctypes.CDLL(str(LIBRARY))
        except OSError:  # not built: the scipy products
            return None
        p, f, i = ctypes.c_void_p, ctypes.c_double, ctypes.c_int64
        try:
            lib.product.argtypes = [i, p, p, p, p, p, f, f, f, i, p, p, p, p, p, p, p, p, p, i]
            lib.product.restype = None
            lib.wide_available.argtypes, lib.wide_available.restype = [], i
        except AttributeError:  # a library built from an older _fused.c: the scipy products
            return None

        def product(*args):
            _product(*args, lib=lib)

        _loaded = [product]
    return _loaded[0]


def wide_available() -> bool:
    """Return whether the compiled product is built and takes its AVX2 loop on this CPU."""
    if kernel() is None:
        return False
    return bool(ctypes.CDLL(str(LIBRARY)).wide_available())
