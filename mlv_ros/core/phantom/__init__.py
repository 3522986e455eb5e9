"""Numerical phantoms with analytic ground truth (pure numpy)."""

from mlv_ros.core.phantom.cylinder import (  # noqa: F401
    control_subset,
    deform,
    DEFORMATIONS,
    FIG4_DEFORMATIONS,
    H_CYL,
    R_INNER,
    R_OUTER,
    sample_cylinder_shell,
)
