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

"""TPS-RPM: recovery of a known affine + smooth warp with outliers and missing points."""

from mlv_ros.core.tags import ThinPlateSpline, tps_rpm
import numpy as np


def _warp(p):
    a = np.array([[1.1, 0.15], [-0.1, 0.92]])
    return (
        p @ a.T
        + np.array([4.0, -3.0])
        + 2.5 * np.stack([np.sin(p[:, 1] / 25), np.cos(p[:, 0] / 30)], -1)
    )


def _problem(seed, k=80, missing=0.2, outliers=0.2, noise=0.2):
    rng = np.random.default_rng(seed)
    src = rng.uniform(-50, 50, (k, 2))
    dst = _warp(src)
    keep = np.sort(rng.permutation(k)[:int(round((1 - missing) * k))])
    tgt = np.vstack(
        [
            dst[keep] + rng.normal(0, noise, (len(keep), 2)),
            rng.uniform(-60, 60, (int(round(outliers * k)), 2)),
        ]
    )
    perm = rng.permutation(len(tgt))
    tgt = tgt[perm]
    truth = np.full(k, -1)
    truth[keep] = np.argsort(perm)[:len(keep)]
    return src, dst, tgt, truth


def test_tps_interpolates_and_reproduces_affine():
    rng = np.random.default_rng(1)
    p = rng.uniform(-10, 10, (30, 2))
    q = _warp(p)
    f = ThinPlateSpline.fit(p, q)
    assert np.allclose(f(p), q, atol=1e-8)
    a = np.array([[0.9, 0.2], [-0.3, 1.1]])
    g = ThinPlateSpline.fit(p, p @ a.T + 3.0, lam=5.0)  # affine maps bend nothing: λ is irrelevant
    x = rng.uniform(-15, 15, (10, 2))
    assert np.allclose(g(x), x @ a.T + 3.0, atol=1e-8)


def test_rpm_recovers_warp_with_outliers_and_missing_points():
    for seed in (0, 1, 2):
        src, dst, tgt, truth = _problem(seed)
        res = tps_rpm(src, tgt)
        inl = truth >= 0
        matched = res.match >= 0
        # Every source point with a true partner: found, and found correctly (≥ 95 %).
        assert np.mean(res.match[inl] == truth[inl]) >= 0.95
        # Wrong inlier pairings (a source point taking another point's partner): at most 2 %.
        wrong = matched & (res.match != truth)
        assert np.sum(np.isin(res.match[wrong], truth[inl])) <= 0.02 * np.sum(inl)
        # Points whose partner is missing rarely grab an outlier (only by chance proximity).
        assert np.sum(wrong) <= 0.35 * np.sum(~inl)
        # The warp follows the truth where data support it (noise σ = 0.2 on targets).
        err = np.linalg.norm(res.transform(src[inl]) - dst[inl], axis=1)
        assert np.median(err) < 0.35  # noise alone: median |n| = 0.235


def test_rpm_identity_and_empty():
    rng = np.random.default_rng(3)
    p = rng.uniform(0, 100, (40, 2))
    res = tps_rpm(p, p[::-1])
    assert np.all(res.match == np.arange(40)[::-1])
    res = tps_rpm(p, np.zeros((0, 2)))
    assert np.all(res.match == -1)
