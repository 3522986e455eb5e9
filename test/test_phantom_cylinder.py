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

"""Cylinder-shell phantom: geometry and analytic deformations."""

from mlv_ros.core.sim.paper_cylinder import (
    control_subset,
    deform,
    DEFORMATIONS,
    H_CYL,
    R_INNER,
    R_OUTER,
    sample_cylinder_shell,
)
import numpy as np
import pytest


def test_shell_geometry_and_count():
    x = sample_cylinder_shell(5000, seed=0)
    rho = np.hypot(x[:, 0], x[:, 1])
    assert rho.min() >= R_INNER and rho.max() <= R_OUTER and np.abs(x[:, 2]).max() <= H_CYL / 2
    assert abs(len(x) - 5000) < 0.05 * 5000
    np.testing.assert_array_equal(x, sample_cylinder_shell(5000, seed=0))  # seeded


def test_deformations_analytic_properties():
    x = sample_cylinder_shell(2000, seed=1)

    def d(a, b):
        return (
            np.linalg.norm(a[:, None] - a[None], axis=2)[:50, :50]
            - np.linalg.norm(b[:, None] - b[None], axis=2)[:50, :50]
        )

    # rotation is rigid
    assert np.abs(d(deform(x, 'rotation'), x)).max() < 1e-12
    # twisting keeps radius and height, rotates by 15° at the top end
    y = deform(x, 'twisting')
    np.testing.assert_allclose(np.hypot(y[:, 0], y[:, 1]), np.hypot(x[:, 0], x[:, 1]))
    np.testing.assert_allclose(y[:, 2], x[:, 2])
    top = np.argmax(x[:, 2])
    ang = np.arctan2(y[top, 1], y[top, 0]) - np.arctan2(x[top, 1], x[top, 0])
    assert np.rad2deg(np.angle(np.exp(1j * ang))) == pytest.approx(15.0 * x[top, 2] / 15.0)
    # scaling
    np.testing.assert_allclose(deform(x, 'scaling'), x * [0.85, 0.85, 0.9])
    # bulge: 2 mm outward at the patch centre beyond the scaling, negligible on the far side
    b = deform(x, 'bulge') - deform(x, 'scaling')
    assert np.abs(b[:, 2]).max() == 0.0
    assert 1.5 < np.linalg.norm(b, axis=1).max() <= 2.0
    far = np.cos(np.arctan2(x[:, 1], x[:, 0])) < -0.5
    assert np.linalg.norm(b[far], axis=1).max() < 1e-3
    assert set(DEFORMATIONS) == {'scaling', 'rotation', 'twisting', 'combination', 'bulge'}


def test_control_subset_and_errors():
    idx = control_subset(1000, 0.1, seed=3)
    assert len(idx) == 100 and len(np.unique(idx)) == 100 and np.all(np.diff(idx) > 0)
    np.testing.assert_array_equal(idx, control_subset(1000, 0.1, seed=3))
    assert len(control_subset(1000, 0.0)) == 0
    with pytest.raises(ValueError, match='fraction'):
        control_subset(10, 1.5)
    with pytest.raises(ValueError, match='unknown deformation'):
        deform(np.zeros((3, 3)), 'shear')
    with pytest.raises(ValueError, match='at least 10'):
        sample_cylinder_shell(3)
