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
LV phantoms with analytic ground-truth motion and tagged-MRI acquisition simulation.

Pure numpy/scipy (no rclpy). Units: mm, s, degrees in presets / radians internally; positions
in DICOM patient coordinates (LPS).

Public API
----------
load_preset(name_or_path) -> dict
    Read ``config/phantoms/<name>.yaml`` (``normal``, ``hypertrophic``, ``dilated``, ``infarct``,
    ``cylinder``) or any YAML path with the same layout; validated.
make_motion(preset, num_phases=None) -> LVMotion
    Ground truth. ``motion.position(X_ed (N,3), phase)``, ``motion.inverse(x (N,3), phase)``,
    ``motion.deformation_gradient(X_ed, phase) -> (N,3,3)``, ``motion.num_phases``,
    ``motion.times`` (s), ``motion.cycle_duration`` (s), ``motion.es_phase``,
    ``motion.frame`` (:class:`CardiacFrame`: ``apex``, ``base_centre``, ``long_axis``
    apex→base, ``septum`` in-plane reference, ``e2``, ``to_local``/``from_local``),
    ``motion.inside_myocardium(X_ed)``, ``motion.inside_blood(X_ed)``,
    ``motion.sample_myocardium(n, seed)``, ``motion.twist_deg(level, phase)`` (CCW seen from
    the apex positive), ``motion.level_curves(levels, phases)`` (twist / endo, mid, epi radius /
    thickness / height per level and phase), ``motion.base_descent_mm(phase)``.
simulate_study(preset="normal", snr=20.0, size=None, num_phases=None, seed=0, subplanes=None,
               pixel_spacing=None, quick=False, progress=None) -> Study
    ``study.frames`` (list of :class:`~mlv_ros.core.types.Frame`, float32 images),
    ``study.motion``, ``study.geometries[(view, idx)]``, ``study.ed_masks[(view, idx)]``
    (bool (rows, cols)), ``study.series_uids``, ``study.cine(view, idx)``.
    ``quick=True`` → 128², 10 phases, 3 sub-planes (a few seconds).
plan_slices, ImageSynthesizer, tag_pattern, slab_profile
    The image-formation pieces (see :mod:`mlv_ros.core.sim.imaging`).
draw_protocol(seed, fixed=None) -> dict, protocol_preset(protocol) -> dict
    Randomised acquisition protocols (:mod:`mlv_ros.core.sim.protocol`): draw every item
    (shape, orientation, grid, matrix, slices, timing, contrast, order, DICOM encoding) and
    turn a protocol into a preset for ``simulate_study``; ``dicom_options(protocol, study)``
    gives the matching ``write_study_dicom`` options.

Every other generator of a synthetic truth lives here too, imported by its module (not
re-exported here):

- :mod:`~mlv_ros.core.sim.paper_cylinder`: the paper's cylinder-shell phantom (§3.1, Fig. 4);
- :mod:`~mlv_ros.core.sim.tag_scene`: analytic tagged-image scenes with exact intersections;
- :mod:`~mlv_ros.core.sim.analytic_lv`: LV-like point clouds and analytic motions with exact
  deformation gradients;
- :mod:`~mlv_ros.core.sim.pattern`: the rotating tag-grid test pattern (graph smoke tests);
- :mod:`~mlv_ros.core.sim.evaluation`: a tracked run's accuracy against a phantom's truth.

Examples
--------
>>> from mlv_ros.core.sim import simulate_study
>>> study = simulate_study("normal", snr=20, quick=True)
>>> X = study.motion.sample_myocardium(1000, seed=0)
>>> x_es = study.motion.position(X, study.motion.es_phase)

"""

from mlv_ros.core.sim.imaging import (
    ImageSynthesizer,
    plan_slices,
    PlannedSlice,
    slab_profile,
    tag_pattern,
)
from mlv_ros.core.sim.motion import (
    AHA_LEVELS,
    aha_segment_window,
    CardiacFrame,
    LVMotion,
    make_motion,
)
from mlv_ros.core.sim.presets import available_presets, load_preset, PRESET_NAMES
from mlv_ros.core.sim.protocol import dicom_options, draw_protocol, protocol_preset
from mlv_ros.core.sim.study import QUICK, simulate_study, Study

__all__ = [
    'AHA_LEVELS',
    'CardiacFrame',
    'ImageSynthesizer',
    'LVMotion',
    'PRESET_NAMES',
    'PlannedSlice',
    'QUICK',
    'Study',
    'aha_segment_window',
    'available_presets',
    'dicom_options',
    'draw_protocol',
    'load_preset',
    'make_motion',
    'plan_slices',
    'protocol_preset',
    'simulate_study',
    'slab_profile',
    'tag_pattern',
]
