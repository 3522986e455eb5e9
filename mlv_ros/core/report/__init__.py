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
Report of a run: figures in the spirit of the paper's Fig. 9–16, summary.json, index.html.

Pure functions of arrays and :class:`~mlv_ros.core.analysis.metrics.PhaseMetrics` lists
(matplotlib Agg, no pyplot state, no rclpy).
"""

from mlv_ros.core.report.build import build_report
from mlv_ros.core.report.figures import (
    draw_bullseye,
    draw_class_bullseye,
    plot_displacement_3d,
    plot_global_curves,
    plot_level_curves,
    plot_segment_findings,
    plot_strain_bullseyes,
)
from mlv_ros.core.report.summary import peak_segment_strain, RunData, summarize, write_summary_json

__all__ = [
    'RunData',
    'build_report',
    'draw_bullseye',
    'draw_class_bullseye',
    'peak_segment_strain',
    'plot_displacement_3d',
    'plot_global_curves',
    'plot_level_curves',
    'plot_segment_findings',
    'plot_strain_bullseyes',
    'summarize',
    'write_summary_json',
]
