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
Meshless deformable model (paper §2).

Kernel/phyxels, MLS gradient, St Venant–Kirchhoff elasticity, global parametric deformation and the
fitting scheme. Pure numpy/scipy.

Typical use::

    frame = polar_frame(points, centre, long_axis, ref_direction)      # or cylindrical_frame
    model = MeshlessModel(points, frame)
    ctrl = model.attach(tag_positions_at_ed)                           # (M, 3) mm, or indices
    for phase in phases:                                               # warm start by default
        result = model.fit(ctrl, targets[phase], plane_normals=normals)
        x, state = result.positions, result.state
        strain = model.green_lagrange_strain()                         # (N, 3, 3), vs ED
"""

from mlv_ros.core.meshless.elastic import (  # noqa: F401
    green_lagrange,
    internal_forces,
    lame_parameters,
    strain_energy,
    svk_stress,
)
from mlv_ros.core.meshless.globals import (  # noqa: F401
    cylindrical_frame,
    global_shape,
    GlobalParameters,
    matrix_to_quat,
    model_jacobian,
    ModelCoordinates,
    ModelFrame,
    polar_frame,
    quat_from_axis_angle,
    quat_to_matrix,
    rotation_jacobian,
    shape_jacobian,
    thick_wall_frame,
)
from mlv_ros.core.meshless.kernel import build_phyxels, Phyxels, poly6  # noqa: F401
from mlv_ros.core.meshless.mls import MLSOperator  # noqa: F401
from mlv_ros.core.meshless.solver import (  # noqa: F401
    attach_control_points,
    ControlPoints,
    FitResult,
    MeshlessModel,
    plane_projectors,
)
