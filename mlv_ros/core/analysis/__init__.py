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
Motion analysis of the dense LV point cloud.

Cardiac frame, displacement decomposition, per-level twist / radius, cavity volume, Lagrangian
strain and AHA segments, and per-segment findings (peak strain with an uncertainty, wall-motion
class: :mod:`.findings`).

Pure numpy/scipy; nothing here imports rclpy. Inputs are arrays in DICOM patient coordinates
(mm); every function is Lagrangian: quantities are relative to end-diastole (ED, phase 0).

Sign conventions (see :mod:`mlv_ros.core.analysis.frame`): the long axis points apex → base,
circumferential angles and twist are positive counter-clockwise seen from the apex looking
toward the base, radial is positive outward, strains are Green–Lagrange ``E = ½(FᵀF − I)``.
"""

from mlv_ros.core.analysis.findings import CLASSES as FINDING_CLASSES
from mlv_ros.core.analysis.findings import Findings, segment_findings, SegmentFindings
from mlv_ros.core.analysis.frame import (
    cardiac_coordinates,
    CardiacCoordinates,
    estimate_frame,
    LVFrame,
)
from mlv_ros.core.analysis.metrics import LVAnalyzer, phase_metrics, PhaseMetrics
from mlv_ros.core.analysis.motion import (
    cavity_volume,
    decompose_displacement,
    endocardial_mask,
    la_radius,
    level_metrics,
    torsion,
)
from mlv_ros.core.analysis.strain import (
    AHA_SEGMENT_NAMES,
    aha_segments,
    cardiac_strain,
    deformation_gradient_mls,
    green_lagrange,
    mls_neighbourhood,
    segment_means,
)

__all__ = [
    'AHA_SEGMENT_NAMES',
    'CardiacCoordinates',
    'FINDING_CLASSES',
    'Findings',
    'LVAnalyzer',
    'LVFrame',
    'PhaseMetrics',
    'SegmentFindings',
    'aha_segments',
    'cardiac_coordinates',
    'cardiac_strain',
    'cavity_volume',
    'decompose_displacement',
    'deformation_gradient_mls',
    'endocardial_mask',
    'estimate_frame',
    'green_lagrange',
    'la_radius',
    'level_metrics',
    'mls_neighbourhood',
    'phase_metrics',
    'segment_findings',
    'segment_means',
    'torsion',
]
