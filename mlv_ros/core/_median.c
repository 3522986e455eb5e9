/* Copyright 2026 The mlv_ros authors
 *
 * Licensed under the Apache License, Version 2.0 (the "License");
 * you may not use this file except in compliance with the License.
 * You may obtain a copy of the License at
 *
 *     http://www.apache.org/licenses/LICENSE-2.0
 *
 * Unless required by applicable law or agreed to in writing, software
 * distributed under the License is distributed on an "AS IS" BASIS,
 * WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
 * See the License for the specific language governing permissions and
 * limitations under the License.
 */

/* The running median of a rank image (see filters.py, issue 17): Huang's sliding histogram,
 * two-level (coarse bins of 2^shift ranks, then the ranks themselves). Built by
 * scripts/bootstrap.sh into _median_c.so beside this file; loaded with ctypes. Integer
 * arithmetic only: the median rank is exact, as np.partition's. */
#include <stdint.h>
#include <stdlib.h>

/* pad: (h + 2r) x (w + 2r) ranks, each in [0, n); out: h x w, the median rank of each
 * (2r + 1)^2 window. Returns 0, or -1 when the histograms cannot be allocated. */
int median_ranks(const int32_t *pad, int64_t h, int64_t w, int64_t r, int64_t n, int32_t *out)
{
    const int64_t pw = w + 2 * r, size = 2 * r + 1, mid = size * size / 2;
    int shift = 4;
    while ((INT64_C(1) << (2 * shift)) < n)
        ++shift;  /* ~sqrt(n) ranks a coarse bin: both scans stay short */
    const int64_t nb = ((n - 1) >> shift) + 1;
    int32_t *fine = calloc((size_t)n, sizeof *fine);
    int32_t *coarse = calloc((size_t)nb, sizeof *coarse);
    if (!fine || !coarse) {
        free(fine);
        free(coarse);
        return -1;
    }
    for (int64_t i = 0; i < h; ++i) {
        const int32_t *top = pad + i * pw;
        for (int64_t a = 0; a < size; ++a)
            for (int64_t b = 0; b < size; ++b) {
                const int32_t v = top[a * pw + b];
                ++fine[v];
                ++coarse[v >> shift];
            }
        int64_t cb = 0, below = 0;  /* below = coarse[0] + ... + coarse[cb - 1] */
        for (int64_t j = 0; j < w; ++j) {
            if (j > 0) {
                for (int64_t a = 0; a < size; ++a) {
                    const int32_t v = top[a * pw + j - 1], u = top[a * pw + j + 2 * r];
                    --fine[v];
                    --coarse[v >> shift];
                    below -= (v >> shift) < cb;
                    ++fine[u];
                    ++coarse[u >> shift];
                    below += (u >> shift) < cb;
                }
            }
            while (below > mid)
                below -= coarse[--cb];
            while (below + coarse[cb] <= mid)
                below += coarse[cb++];
            int64_t acc = below, v = cb << shift;
            while ((acc += fine[v]) <= mid)
                ++v;
            out[i * w + j] = (int32_t)v;
        }
        for (int64_t a = 0; a < size; ++a)  /* empty the histograms for the next row */
            for (int64_t b = w - 1; b < w + 2 * r; ++b) {
                const int32_t v = top[a * pw + b];
                --fine[v];
                --coarse[v >> shift];
            }
    }
    free(fine);
    free(coarse);
    return 0;
}
