"""Numerical phantoms with analytic ground truth (pure numpy)."""

from mlv_ros.core.phantom.cylinder import (  # noqa: F401
    DEFORMATIONS, FIG4_DEFORMATIONS, H_CYL, R_INNER, R_OUTER, control_subset, deform,
    sample_cylinder_shell,
)
