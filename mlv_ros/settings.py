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
Node parameters as tables of :class:`Setting` records: name, default, description, range.

A node declares its table (:meth:`mlv_ros.nodes.common.GraphNode.declare_settings`); ``mlv-ros
run`` checks its options against the same ranges, and :class:`~mlv_ros.core.tracking.MotionTracker`
its keyword arguments (:func:`check_keywords`), so a range is written once. Pure Python (no rclpy,
no numpy at import): the command line reads it before anything heavy is loaded.

The solver's model parameters are grouped as navigation2 groups its own (``twist.knots``,
``local.fit_error_weight``, ...; in a parameters file, nested maps: ``twist: {knots: 11}``). Each
keeps the core's keyword argument it is passed as (of
:class:`~mlv_ros.core.tracking.MotionTracker`), which is also the flat name it had before it was
grouped: a value given under that name is refused at start-up, naming the grouped one.
"""

from __future__ import annotations

import numbers
from typing import Callable, NamedTuple


class Setting(NamedTuple):
    """
    One node parameter: name, default, description and range (see ``GraphNode.param``).

    Attributes
    ----------
    name : str
        The parameter's name, grouped with dots (``twist.knots``).
    default : bool, int, float or str
        Its default; its type is the parameter's.
    description : str
        What it sets, with its unit.
    min_value, max_value : float or None
        Its declared range (numbers only; None: no range).
    check : callable or None
        ``check(value)`` returns why a value inside the range is still refused (None: accepted).
    keyword : str or None
        The node attribute and core keyword argument the value goes to (None: ``name``).

    """

    name: str
    default: object
    description: str
    min_value: float | None = None
    max_value: float | None = None
    check: Callable | None = None
    keyword: str | None = None

    @property
    def attribute(self) -> str:
        """Return where the value goes: the node attribute, the core keyword argument."""
        return self.keyword or self.name

    def error(self, value) -> str | None:
        """
        Return why ``value`` is refused (its type, range or ``check``), or None when it is taken.

        Parameters
        ----------
        value : object
            A value for this setting: an integer for an integer setting, a real number for a
            float one (NaN is outside every range).

        Returns
        -------
        str or None
            The reason, one line (e.g. ``must be from 1e-12 to 0.5``), or None.

        """
        number = isinstance(self.default, (int, float)) and not isinstance(self.default, bool)
        if number:
            integer = isinstance(self.default, int)
            if isinstance(value, bool) or not isinstance(
                value, numbers.Integral if integer else numbers.Real
            ):
                return f'must be {"an integer" if integer else "a number"}'
            if self.min_value is not None and not self.min_value <= value <= self.max_value:
                return f'must be from {self.min_value:g} to {self.max_value:g}'
        return None if self.check is None else self.check(value)


def _twist_knots_error(value) -> str | None:
    """Return the core's reason to refuse ``value`` as twist knots (None: accepted)."""
    from mlv_ros.core.tracking import twist_knots_error  # numpy: only when a node declares it

    return twist_knots_error(value)


# The solver's model (MotionTracker's keyword arguments). The model's own rule (one twist knot is
# no function of height) is the core's function, so one place says why a value is refused.
SOLVER_MODEL = (
    Setting(
        'local.data_weight',
        1.0e4,
        'tag-force stiffness relative to elasticity, for a tag point of local.tag_noise_mm',
        1e-3,
        1e9,
        keyword='data_weight',
    ),
    Setting(
        'local.tag_noise_mm',
        0.15,
        'tag-point localisation noise (mm, per in-plane axis) at which local.data_weight holds: '
        'a slice whose tracks jitter more in time (σ measured from their second differences) '
        'gets data_weight × (tag_noise_mm / σ)² (0 = off)',
        0.0,
        100.0,
        keyword='tag_noise_mm',
    ),
    Setting(
        'local.fit_error_weight',
        1.0e3,
        'MLS fit-error (zero-energy mode) stiffness relative to elasticity',
        0.0,
        1e9,
        keyword='hourglass_weight',
    ),
    Setting(
        'local.volume_weight',
        4.0e3,
        'near-incompressibility penalty, in units of the shear modulus (0 = off)',
        0.0,
        1e9,
        keyword='volume_weight',
    ),
    Setting(
        'local.longitudinal_weight',
        3.0e3,
        'stiffness against local stretch along the long axis, in units of the shear '
        'modulus (0 = off): only LA tags measure it',
        0.0,
        1e9,
        keyword='longitudinal_weight',
    ),
    Setting(
        'global.prior',
        1.0,
        'prior holding the global parameters at the previous phase, counted like this many '
        'control points (0 = off)',
        0.0,
        1e5,
        keyword='global_prior',
    ),
    Setting(
        'global.max_iterations',
        100,
        'global-stage iterations per phase',
        1,
        10000,
        keyword='max_iterations',
    ),
    Setting(
        'twist.knots',
        11,
        'knots of the twist function of height (0 = the single twist factor τ)',
        0,
        100,
        check=_twist_knots_error,
        keyword='twist_knots',
    ),
    Setting(
        'twist.smoothing',
        0.3,
        'curvature penalty of the twist function',
        1e-6,
        1e5,
        keyword='twist_smoothing',
    ),
    Setting(
        'slice_following.passes',
        1,
        're-attachment passes keeping tag points on their planes',
        0,
        10,
        keyword='slice_following',
    ),
    Setting(
        'slice_following.max_step_mm',
        5.0,
        "largest move of a tag point's material line along its plane normal per pass, mm",
        0.01,
        1000.0,
        keyword='follow_step_mm',
    ),
    # How closely the local stage's conjugate gradients solve (warm-started from the previous
    # phase; why these defaults: MotionTracker's docstring).
    Setting(
        'cg.rtol',
        2e-3,
        "relative residual at which the local stage's conjugate gradients stop",
        1e-12,
        0.5,
        keyword='cg_rtol',
    ),
    Setting(
        'cg.max_iterations',
        400,
        'most conjugate-gradient iterations per local solve',
        1,
        100000,
        keyword='cg_maxiter',
    ),
    Setting(
        'cg.rtol_following',
        5e-2,
        'CG tolerance of the slice-following passes before the last (the looser of it and '
        'cg.rtol): they only place the tag points for the next pass',
        1e-12,
        0.5,
        keyword='cg_rtol_following',
    ),
    # Which tag points are dropped as slipped or swapped tracks before the global fit.
    Setting(
        'outliers.floor_mm',
        3.0,
        'in-plane tag residual never counted an outlier, mm (kept below one tag period, a slip)',
        0.0,
        1000.0,
        keyword='outlier_mm',
    ),
    Setting(
        'outliers.sigmas',
        5.0,
        'a residual beyond the median by this many robust standard deviations (1.4826 MAD) is '
        'an outlier',
        0.5,
        1000.0,
        keyword='outlier_sigmas',
    ),
)

# When the solver solves and publishes (its stream, not the model): flat, as the other nodes'.
SOLVER_STREAM = (
    Setting(
        'incomplete_timeout_s',
        5.0,
        'solve an incomplete phase after this long without input',
        0.1,
        3600.0,
    ),
    Setting(
        'wait_for_subscribers',
        1,
        'matched subscribers of the motion and state topics to wait for before publishing',
        0,
        100,
    ),
    Setting('wait_timeout_s', 10.0, 'then publish to those present, with a warning', 0.0, 3600.0),
)

REGISTRATION = (
    Setting('num_particles', 3000, 'model particles', 100, 200000),
    Setting('seed', 0, 'particle sampling seed', 0, 2**31 - 1),
    Setting(
        'ed_timeout_s',
        5.0,
        'register with the ED slices present once frames stop arriving for this long',
        0.1,
        3600.0,
    ),
    Setting('min_sa_slices', 3, 'fewest SA slices to register from', 2, 100),
    Setting(
        'mask_path',
        '',
        'optional NIfTI label image of the ED myocardium (empty = automatic segmentation)',
    ),
    Setting('mask_label', 2, 'myocardium label in mask_path (ACDC: 2)', 0, 65535),
    Setting(
        'catch_up',
        True,
        'take frames with their history (TRANSIENT_LOCAL), so a restart gets the frames already '
        'sent; false for a publisher without history',
    ),
)

# Nodes that pair each motion cloud with its model state (motion_analyzer, live_view).
PAIRING = (
    Setting(
        'max_unpaired',
        200,
        'motion clouds / model states held while waiting for their pair',
        1,
        100000,
    ),
)


def setting(table, name: str) -> Setting:
    """
    Return the setting of ``table`` named ``name``.

    Parameters
    ----------
    table : tuple of Setting
        E.g. :data:`REGISTRATION`.
    name : str
        The parameter's name.

    Returns
    -------
    Setting
        The record.

    Raises
    ------
    KeyError
        No setting of that name.

    """
    for s in table:
        if s.name == name:
            return s
    raise KeyError(name)


def check_keywords(table, values: dict) -> None:
    """
    Check keyword arguments against the settings they come from: one range for node and core.

    Parameters
    ----------
    table : tuple of Setting
        E.g. :data:`SOLVER_MODEL`; each setting checks the value of its keyword
        (:attr:`Setting.attribute`) in ``values``.
    values : dict
        Keyword → value; keywords the table does not name are not looked at.

    Raises
    ------
    ValueError
        The first value a setting refuses (:meth:`Setting.error`), naming the keyword, the value,
        the reason and the node parameter, e.g. ``cg_rtol=0: must be from 1e-12 to 0.5 (node
        parameter cg.rtol)``.

    """
    for s in table:
        if s.attribute in values:
            why = s.error(values[s.attribute])
            if why:
                raise ValueError(
                    f'{s.attribute}={values[s.attribute]!r}: {why} (node parameter {s.name})'
                )
