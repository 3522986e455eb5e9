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

/* The local stage's CG product A u as one pass over the pairs (see _fused.py, issue 17).
 * Built by scripts/bootstrap.sh into _fused_c.so beside this file; loaded with ctypes. */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* The phyxels' part with AVX2 vectors, chosen at run time where the CPU has AVX2 (the build
 * stays generic x86-64, -O2): each member's three components in the lanes of one vector, u and
 * the sums padded to four lanes a particle (one load / store a member). Every lane does the
 * scalar pass's multiplications and additions in the scalar pass's order, and "avx2" does not
 * enable FMA, so nothing is contracted: with out zero on entry (as _fused.py passes it), the
 * same bits as the scalar loop below (test_local_stage checks it). */
#if defined(__x86_64__) && defined(__GNUC__)
#define MLV_WIDE 1
typedef double v4 __attribute__((vector_size(32)));

__attribute__((target("avx2")))
static void phyxels_avx2(
    int64_t n, const int64_t *ptr, const int64_t *cols, const double *d, const double *c,
    const double *tangent, double alpha, double eps, const double *u4, double *out4,
    double *grad, const double *offset, double *out_offset)
{
    /* u4, out4: (n, 4), the fourth lane zero, so that a member is one vector load / store */
    for (int64_t i = 0; i < n; ++i) {
        v4 ga = {0, 0, 0, 0}, gb = {0, 0, 0, 0}, gc = {0, 0, 0, 0}, l = {0, 0, 0, 0};
        v4 ui;
        memcpy(&ui, u4 + 4 * i, sizeof ui);
        for (int64_t e = ptr[i]; e < ptr[i + 1]; ++e) {
            const int64_t j = cols[e];
            v4 uj, oj;
            memcpy(&uj, u4 + 4 * j, sizeof uj);
            const double d0 = d[3 * e], d1 = d[3 * e + 1], d2 = d[3 * e + 2];
            const v4 b0 = {d0, d0, d0, d0}, b1 = {d1, d1, d1, d1}, b2 = {d2, d2, d2, d2};
            ga += b0 * uj; gb += b1 * uj; gc += b2 * uj;
            const double w = alpha * c[e];
            const v4 wv = {w, w, w, w};
            const v4 f = wv * (uj - ui);
            l += f;
            memcpy(&oj, out4 + 4 * j, sizeof oj);
            oj += f;
            memcpy(out4 + 4 * j, &oj, sizeof oj);
        }
        v4 oi;
        memcpy(&oi, out4 + 4 * i, sizeof oi);
        oi -= l;
        memcpy(out4 + 4 * i, &oi, sizeof oi);
        const double g[9] = {ga[0], ga[1], ga[2], gb[0], gb[1], gb[2], gc[0], gc[1], gc[2]};
        memcpy(grad + 9 * i, g, sizeof g);
        const double *t = tangent + 81 * i;
        double s[9];
        for (int r = 0; r < 9; ++r) {
            const double *tr = t + 9 * r;
            s[r] = tr[0] * g[0] + tr[1] * g[1] + tr[2] * g[2] + tr[3] * g[3] + tr[4] * g[4]
                + tr[5] * g[5] + tr[6] * g[6] + tr[7] * g[7] + tr[8] * g[8];
        }
        const v4 s0 = {s[0], s[1], s[2], 0}, s1 = {s[3], s[4], s[5], 0};
        const v4 s2 = {s[6], s[7], s[8], 0};
        for (int64_t e = ptr[i]; e < ptr[i + 1]; ++e) {
            const int64_t j = cols[e];
            const double d0 = d[3 * e], d1 = d[3 * e + 1], d2 = d[3 * e + 2];
            const v4 b0 = {d0, d0, d0, d0}, b1 = {d1, d1, d1, d1}, b2 = {d2, d2, d2, d2};
            v4 oj;
            memcpy(&oj, out4 + 4 * j, sizeof oj);
            oj += b0 * s0 + b1 * s1 + b2 * s2;
            memcpy(out4 + 4 * j, &oj, sizeof oj);
        }
        if (out_offset) {
            const double *o = offset + 9 * i;
            const v4 o0 = {o[0], o[1], o[2], 0}, o1 = {o[3], o[4], o[5], 0};
            const v4 o2 = {o[6], o[7], o[8], 0};
            for (int64_t e = ptr[i]; e < ptr[i + 1]; ++e) {
                const int64_t j = cols[e];
                const double d0 = d[3 * e], d1 = d[3 * e + 1], d2 = d[3 * e + 2];
                const v4 b0 = {d0, d0, d0, d0}, b1 = {d1, d1, d1, d1}, b2 = {d2, d2, d2, d2};
                const v4 a = b0 * o0 + b1 * o1 + b2 * o2;
                out_offset[3 * j] += a[0]; out_offset[3 * j + 1] += a[1];
                out_offset[3 * j + 2] += a[2];
            }
        }
        const v4 ev = {eps, eps, eps, eps};
        memcpy(&oi, out4 + 4 * i, sizeof oi);
        oi += ev * ui;
        memcpy(out4 + 4 * i, &oi, sizeof oi);
    }
}
#endif

/* 1 where the phyxels' part may take the AVX2 loop (built for x86-64 and the CPU has AVX2). */
int64_t wide_available(void)
{
#ifdef MLV_WIDE
    return __builtin_cpu_supports("avx2") ? 1 : 0;
#else
    return 0;
#endif
}

void product(
    int64_t n, const int64_t *ptr, const int64_t *cols, const double *d, const double *c,
    const double *tangent, double alpha, double eps,
    double kappa, int64_t m, const int64_t *sptr, const int64_t *scols, const double *phi,
    const double *metric,
    const double *u, double *out, double *grad, const double *offset, double *out_offset,
    int64_t wide)
{
#ifdef MLV_WIDE
    double *pad = (wide && n > 0 && __builtin_cpu_supports("avx2"))
        ? malloc(8 * (size_t)n * sizeof(double)) : NULL;
    if (pad) {  /* u and the phyxels' sums padded to four lanes a particle */
        double *u4 = pad, *out4 = pad + 4 * n;
        for (int64_t i = 0; i < n; ++i) {
            u4[4 * i] = u[3 * i]; u4[4 * i + 1] = u[3 * i + 1]; u4[4 * i + 2] = u[3 * i + 2];
            u4[4 * i + 3] = 0.0;
        }
        memset(out4, 0, 4 * (size_t)n * sizeof(double));
        phyxels_avx2(n, ptr, cols, d, c, tangent, alpha, eps, u4, out4, grad, offset, out_offset);
        for (int64_t i = 0; i < n; ++i) {
            out[3 * i] += out4[4 * i]; out[3 * i + 1] += out4[4 * i + 1];
            out[3 * i + 2] += out4[4 * i + 2];
        }
        free(pad);
        n = 0;  /* the phyxels are done: only the data springs below */
    }
#else
    (void)wide;
#endif
    for (int64_t i = 0; i < n; ++i) {
        double g0 = 0, g1 = 0, g2 = 0, g3 = 0, g4 = 0, g5 = 0, g6 = 0, g7 = 0, g8 = 0;
        const double ui0 = u[3 * i], ui1 = u[3 * i + 1], ui2 = u[3 * i + 2];
        double l0 = 0, l1 = 0, l2 = 0;
        for (int64_t e = ptr[i]; e < ptr[i + 1]; ++e) {
            const int64_t j = cols[e];
            const double u0 = u[3 * j], u1 = u[3 * j + 1], u2 = u[3 * j + 2];
            const double d0 = d[3 * e], d1 = d[3 * e + 1], d2 = d[3 * e + 2];
            g0 += d0 * u0; g1 += d0 * u1; g2 += d0 * u2;
            g3 += d1 * u0; g4 += d1 * u1; g5 += d1 * u2;
            g6 += d2 * u0; g7 += d2 * u1; g8 += d2 * u2;
            const double w = alpha * c[e];
            const double f0 = w * (u0 - ui0), f1 = w * (u1 - ui1), f2 = w * (u2 - ui2);
            l0 += f0; l1 += f1; l2 += f2;
            out[3 * j] += f0; out[3 * j + 1] += f1; out[3 * j + 2] += f2;
        }
        out[3 * i] -= l0; out[3 * i + 1] -= l1; out[3 * i + 2] -= l2;
        double *gi = grad + 9 * i;
        gi[0] = g0; gi[1] = g1; gi[2] = g2; gi[3] = g3; gi[4] = g4;
        gi[5] = g5; gi[6] = g6; gi[7] = g7; gi[8] = g8;
        const double *t = tangent + 81 * i;
        double s[9];
        for (int r = 0; r < 9; ++r) {
            const double *tr = t + 9 * r;
            s[r] = tr[0] * g0 + tr[1] * g1 + tr[2] * g2 + tr[3] * g3 + tr[4] * g4
                + tr[5] * g5 + tr[6] * g6 + tr[7] * g7 + tr[8] * g8;
        }
        for (int64_t e = ptr[i]; e < ptr[i + 1]; ++e) {
            const int64_t j = cols[e];
            const double d0 = d[3 * e], d1 = d[3 * e + 1], d2 = d[3 * e + 2];
            out[3 * j] += d0 * s[0] + d1 * s[3] + d2 * s[6];
            out[3 * j + 1] += d0 * s[1] + d1 * s[4] + d2 * s[7];
            out[3 * j + 2] += d0 * s[2] + d1 * s[5] + d2 * s[8];
        }
        if (out_offset) {
            const double *o = offset + 9 * i;
            for (int64_t e = ptr[i]; e < ptr[i + 1]; ++e) {
                const int64_t j = cols[e];
                const double d0 = d[3 * e], d1 = d[3 * e + 1], d2 = d[3 * e + 2];
                out_offset[3 * j] += d0 * o[0] + d1 * o[3] + d2 * o[6];
                out_offset[3 * j + 1] += d0 * o[1] + d1 * o[4] + d2 * o[7];
                out_offset[3 * j + 2] += d0 * o[2] + d1 * o[5] + d2 * o[8];
            }
        }
        out[3 * i] += eps * ui0; out[3 * i + 1] += eps * ui1; out[3 * i + 2] += eps * ui2;
    }
    for (int64_t k = 0; k < m; ++k) {
        double v0 = 0, v1 = 0, v2 = 0;
        for (int64_t e = sptr[k]; e < sptr[k + 1]; ++e) {
            const int64_t j = scols[e];
            v0 += phi[e] * u[3 * j]; v1 += phi[e] * u[3 * j + 1]; v2 += phi[e] * u[3 * j + 2];
        }
        const double *p = metric + 9 * k;
        const double f0 = kappa * (p[0] * v0 + p[1] * v1 + p[2] * v2);
        const double f1 = kappa * (p[3] * v0 + p[4] * v1 + p[5] * v2);
        const double f2 = kappa * (p[6] * v0 + p[7] * v1 + p[8] * v2);
        for (int64_t e = sptr[k]; e < sptr[k + 1]; ++e) {
            const int64_t j = scols[e];
            out[3 * j] += phi[e] * f0; out[3 * j + 1] += phi[e] * f1; out[3 * j + 2] += phi[e] * f2;
        }
    }
}
