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
